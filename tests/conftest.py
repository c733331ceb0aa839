"""Fixtures shared by the test files."""

import pytest
from petsc4py import PETSc


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
