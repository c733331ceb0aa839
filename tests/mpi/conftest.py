"""Tests that need several MPI ranks: ``make test`` runs this folder under ``mpiexec -n 2``.

Run by hand with ``mpiexec -n 2 python -m pytest -q -p no:cacheprovider tests/mpi``
(as root, Open MPI also needs ``OMPI_ALLOW_RUN_AS_ROOT=1
OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1``).  On one process they are skipped; without
mpi4py (``pip install .[mpi]``) they are not collected.
"""

import pytest

try:
    from mpi4py import MPI
except ImportError:  # pragma: no cover - the Makefile installs mpi4py
    MPI = None
    collect_ignore_glob = ["test_*.py"]


def pytest_report_header(config):
    ranks = MPI.COMM_WORLD.Get_size() if MPI else "mpi4py not installed: MPI tests not collected"
    return f"MPI ranks: {ranks}"


def pytest_collection_modifyitems(config, items):
    if MPI is None or MPI.COMM_WORLD.Get_size() >= 2:
        return
    skip = pytest.mark.skip(reason="needs several MPI ranks: mpiexec -n 2 (make test runs it)")
    for item in items:
        if item.path.parent.name == "mpi":
            item.add_marker(skip)
