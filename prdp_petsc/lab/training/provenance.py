"""Provenance: what made a result file (versions, command line, commit, machine).

Every ``results.json`` and ``summary.json`` the training harness writes carries a
``provenance`` object from `provenance`, so a number can be traced to the code and
the libraries that produced it.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

__all__ = ["DISTRIBUTIONS", "git_commit", "provenance"]

#: Distributions whose versions a result records (names as pip knows them).
DISTRIBUTIONS = ("prdp-petsc", "petsc4py", "torch", "numpy", "scipy", "scikit-fem")


def provenance(threads: int, ranks: int) -> dict:
    """What produced a result file, as plain JSON types.

    Parameters
    ----------
    threads : int
        torch threads the run used (`prdp_petsc.lab.training.harness.torch_threads`).
    ranks : int
        MPI ranks the run used (1 for a serial run).

    Returns
    -------
    dict
        ``versions`` (``prdp-petsc``, ``petsc`` from ``PETSc.Sys.getVersion()``,
        ``petsc4py``, ``torch``, ``numpy``, ``scipy``, ``scikit-fem``, ``python``;
        None for one that is not installed), ``command`` (``sys.argv``), ``git``
        (`git_commit`: ``commit`` and ``dirty``, or None outside a git checkout),
        ``timestamp`` (ISO 8601, local time with its UTC offset), ``host``
        (``cpus``: ``os.cpu_count()``, ``platform``), ``torch_threads`` and
        ``mpi_ranks``.
    """
    versions = {name: _version(name) for name in DISTRIBUTIONS}
    versions["petsc"] = _petsc_version()
    versions["python"] = platform.python_version()
    return {
        "versions": versions,
        "command": list(sys.argv),
        "git": git_commit(),
        "timestamp": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "host": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "torch_threads": threads,
        "mpi_ranks": ranks,
    }


def git_commit(path: str | Path | None = None) -> dict | None:
    """``{"commit": HEAD, "dirty": bool}`` of the git checkout that holds `path`.

    `path` (a folder) defaults to this package's.  None when the folder holds no file
    tracked by a git checkout (an installed wheel, a virtual environment inside a
    checkout) or git is missing or fails: provenance never stops a run.  ``dirty`` is True when
    tracked files differ from HEAD (untracked files do not count).
    """
    folder = Path(__file__).resolve().parent.parent if path is None else Path(path)
    try:
        # its files must be tracked: a virtual environment inside a checkout is not
        _git(folder, "ls-files", "--error-unmatch", ".")
        commit = _git(folder, "rev-parse", "HEAD")
        dirty = bool(_git(folder, "status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": commit, "dirty": dirty}


def _git(folder: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "-C", str(folder), *args],
        capture_output=True,
        text=True,
        timeout=10,
        check=True,
    )
    return done.stdout.strip()


def _version(distribution: str) -> str | None:
    try:
        return version(distribution)
    except PackageNotFoundError:
        return None


def _petsc_version() -> str | None:
    try:
        from petsc4py import PETSc
    except ImportError:  # pragma: no cover - a dependency
        return None
    return ".".join(str(part) for part in PETSc.Sys.getVersion())
