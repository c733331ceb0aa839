"""Scene data kept on disk between runs (``$PRDP_PETSC_CACHE``, default
``~/.cache/prdp_petsc``; ``PRDP_PETSC_CACHE=""`` turns it off), such as ns2d's reference
trajectories: the runs of a comparison build them once, and a changed scheme (its
source files hashed into the name) never reads old data."""

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
    """``compute()``, or the array an earlier call with the same arguments stored as
    ``{prefix}_{hash}_{key}.npy``: `key` names every argument the array depends on, the
    hash is that of the `sources` (the files whose code computes it).  Written under a
    temporary name and renamed, so that a concurrent run reads a whole file or none.
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
