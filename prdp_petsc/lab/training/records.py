"""Result files: a run's ``results.json`` by name, and JSON that any value fits into,
written atomically (a run stopped mid-write keeps the previous complete file).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["RESULTS", "to_json", "write_json"]

#: File name of a run's results in its output folder.
RESULTS = "results.json"


def to_json(value):
    """``value`` as plain JSON types: paths become strings, numpy/torch scalars and
    arrays numbers and lists, other keys and objects their ``str``."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, dict):
        return {_json_key(k): to_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_json(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if hasattr(value, "tolist"):  # numpy scalars and arrays, torch tensors
        return to_json(value.tolist())
    return str(value)


def _json_key(key):
    plain = key is None or isinstance(key, bool | int | float | str)
    return key if plain else str(to_json(key))


def write_json(path: Path, data: dict) -> None:
    """Write ``to_json(data)`` to ``path`` atomically (through a temporary file)."""
    path = Path(path)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(to_json(data), indent=1))
    tmp.replace(path)
