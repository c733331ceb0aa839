"""Provenance: what made a result file (versions, command line, commit, machine).

Every ``results.json`` and ``summary.json`` carries `provenance`; the benchmarks record
`machine_info`; ``prdp-petsc pages record`` records `machine`, `versions` and
`git_commit`.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import platform
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

__all__ = [
    "write_result",
    "DISTRIBUTIONS",
    "cpu",
    "git_commit",
    "load_average",
    "machine",
    "machine_info",
    "provenance",
    "versions",
]

#: Distributions whose versions a result records (names as pip knows them).
DISTRIBUTIONS = ("prdp-petsc", "petsc4py", "torch", "numpy", "scipy", "scikit-fem")


def provenance(threads: int, ranks: int) -> dict:
    """What produced a result file run on `threads` torch threads and `ranks` MPI ranks:
    ``versions``, ``command`` (``sys.argv``), ``git`` (`git_commit`), ``timestamp``
    (local ISO 8601), ``host``, ``torch_threads`` and ``mpi_ranks``."""
    return {
        "versions": versions(),
        "command": list(sys.argv),
        "git": git_commit(),
        "timestamp": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "host": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "torch_threads": threads,
        "mpi_ranks": ranks,
    }


def versions(*more: str) -> dict:
    """The installed version of each of `DISTRIBUTIONS` and `more` (None: not
    installed), ``petsc`` and ``python``."""
    found = {name: _version(name) for name in (*DISTRIBUTIONS, *more)}
    from petsc4py import PETSc  # a dependency of the library

    found["petsc"] = ".".join(str(part) for part in PETSc.Sys.getVersion())
    found["python"] = platform.python_version()
    return found


def machine() -> dict:
    """``platform``, ``cpu`` (`cpu`), ``cpu_count`` and ``load_average`` (`load_average`)."""
    return {
        "platform": platform.platform(),
        "cpu": cpu(),
        "cpu_count": os.cpu_count(),
        "load_average": load_average(),
    }


def machine_info() -> dict:
    """What a benchmark records about where it ran: `machine`, ``torch_threads`` and
    ``versions``."""
    import torch

    return {**machine(), "torch_threads": torch.get_num_threads(), "versions": versions()}


def cpu() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``; else ``platform.processor()``)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def load_average() -> list[float] | None:
    """The load averages over 1, 5 and 15 minutes (None where the system has none)."""
    return [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None


def git_commit(path: str | Path | None = None) -> dict | None:
    """``{"commit": HEAD, "dirty": bool, "modified": [tracked files that differ]}`` of
    the git checkout that holds the folder `path` (default: this package's); None where
    no git checkout tracks it (an installed wheel) or git fails: provenance never stops
    a run."""
    folder = Path(__file__).resolve().parent if path is None else Path(path)
    try:
        # its files must be tracked: a virtual environment inside a checkout is not
        _git(folder, "ls-files", "--error-unmatch", ".")
        commit = _git(folder, "rev-parse", "HEAD").strip()
        status = _git(folder, "status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    modified = sorted(line[3:] for line in status.splitlines() if line.strip())
    return {"commit": commit, "dirty": bool(modified), "modified": modified}


def _git(folder: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "-C", str(folder), *args],
        capture_output=True,
        text=True,
        timeout=10,
        check=True,
    )
    return done.stdout.rstrip("\n")  # keep the leading blank of `status --porcelain`


def _version(distribution: str) -> str | None:
    try:
        return version(distribution)
    except PackageNotFoundError:
        return None


def write_result(folder: str | Path, name: str, result: dict) -> Path:
    """Write a benchmark's `result` as ``folder/name`` (indented JSON) and log where."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(json.dumps(result, indent=2) + "\n")
    logging.getLogger(__name__).info("wrote %s", path)
    return path
