"""Helpers of the MPI tests: every test runs the same collective calls on every rank
in the same order and checks agreement with `all_ranks`, so a failure on one rank
fails all of them instead of leaving one waiting in a collective call."""

from mpi4py import MPI

COMM = MPI.COMM_WORLD


def all_ranks(ok) -> bool:
    """True when `ok` holds on every rank (collective)."""
    return bool(COMM.allreduce(bool(ok), op=MPI.LAND))


def max_over_ranks(value: float) -> float:
    return float(COMM.allreduce(float(value), op=MPI.MAX))


def same_on_all_ranks(array) -> bool:
    """True when `array` is bitwise equal on every rank (collective)."""
    import numpy as np

    first = COMM.bcast(np.asarray(array), root=0)
    return all_ranks(np.array_equal(first, np.asarray(array)))
