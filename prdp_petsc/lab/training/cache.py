"""Scene data kept on disk between runs (``$PRDP_PETSC_CACHE``).

Some scenes build their data with minutes of direct solves (``demos/ns2d.py``: the
reference trajectories on the 2N grid).  `disk_cached` keeps such an array in
``$PRDP_PETSC_CACHE`` (default ``~/.cache/prdp_petsc``; ``PRDP_PETSC_CACHE=""`` turns
it off) under a name made of the scene's key and a hash of the source files that
compute it, so that the runs of a comparison build it once and a changed scheme never
reads old data.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

__all__ = ["cache_folder", "disk_cached"]


def cache_folder() -> Path | None:
    """``$PRDP_PETSC_CACHE`` (default ``~/.cache/prdp_petsc``); None where it is ``""``."""
    folder = os.environ.get("PRDP_PETSC_CACHE", str(Path.home() / ".cache" / "prdp_petsc"))
    return Path(folder) if folder else None


def disk_cached(
    prefix: str, key: str, compute: Callable[[], np.ndarray], *, sources: Iterable = ()
) -> np.ndarray:
    """``compute()``, or the array an earlier call with the same arguments stored.

    Parameters
    ----------
    prefix, key : str
        The file is ``{prefix}_{hash}_{key}.npy`` in `cache_folder`: `key` names every
        argument the array depends on (``"n48_count5_..."``).
    compute : callable ``() -> numpy.ndarray``
        Builds the array where no stored one exists (and always where the cache is off).
    sources : iterable of path-like
        The files whose code computes the array; the first 12 hex digits of the SHA-1
        of their bytes are the file name's ``{hash}``.

    The file is written under a temporary name and renamed: a concurrent run reads a
    whole file or none.
    """
    folder = cache_folder()
    if folder is None:
        return compute()
    digest = hashlib.sha1()
    for source in sources:
        digest.update(Path(source).read_bytes())
    cached = folder / f"{prefix}_{digest.hexdigest()[:12]}_{key}.npy"
    if cached.exists():
        return np.load(cached)
    array = compute()
    cached.parent.mkdir(parents=True, exist_ok=True)
    partial = cached.with_suffix(f".{os.getpid()}.tmp.npy")
    np.save(partial, array)
    partial.replace(cached)
    return array
