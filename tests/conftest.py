"""Fixtures shared by the test files."""

import os

import pytest
from petsc4py import PETSc

# scenes that cache data on disk (ns2d's reference trajectories) do it in no folder
# of the user's: tests compute what they use
os.environ["PRDP_PETSC_CACHE"] = ""


@pytest.fixture
def petsc_option():
    """Set options in the PETSc database (as from the command line); removed afterwards."""
    opts = PETSc.Options()
    names = []

    def put(name, value):
        opts.setValue(name, value)
        names.append(name)

    yield put
    for name in names:
        opts.delValue(name)
