"""Communicators and row layouts: how numpy vectors map onto distributed PETSc Vecs.

A `KSPSolver` lives on a communicator: ``PETSC_COMM_SELF`` by default, or the one
given as ``comm=``, or the one set for a block of code with `use_comm` (what
``prdp-petsc run --parallel domain`` does, so that scenes build distributed
solvers without changing a line).

Two layouts of the vectors a solver takes and returns exist:

``replicated``
    The operator is a scipy CSR matrix (or a `ParametricMatrix`) that every rank
    holds in full: each rank assembled it (redundantly) and keeps only its rows
    in the distributed PETSc Mat (MPIAIJ, PETSc's default row split).  Right-hand
    sides and solutions are full-length arrays, equal on every rank: the rows a
    rank owns are copied into the Vec before ``KSPSolve``, and the solution is
    gathered to every rank after it (``VecScatterCreateToAll``).  So the torch
    tensors, losses and gradients on the ranks are the same as in a serial run.
``owned``
    The operator is the caller's own distributed PETSc Mat, or an
    `~prdp_petsc.core.operator.OwnedCSR` of this rank's rows (what
    `~prdp_petsc.fem.distributed.DistributedParametricMatrix` assembles from a
    partitioned mesh): vectors hold the rank's own rows only (PETSc's
    convention), nothing is gathered.  This is the layout for problems too large
    to replicate.

The layout follows from the operator the solver is given; on one process both
are the same.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np
from petsc4py import PETSc

if TYPE_CHECKING:  # mpi4py is optional (the `mpi` extra)
    from mpi4py import MPI

__all__ = ["RowLayout", "default_comm", "ownership_range", "use_comm"]

_default: list = []  # stack of communicators set by `use_comm`


def default_comm() -> PETSc.Comm:
    """The communicator new solvers get: the innermost `use_comm`, else ``COMM_SELF``."""
    return _default[-1] if _default else PETSc.COMM_SELF


@contextmanager
def use_comm(comm: PETSc.Comm | MPI.Comm) -> Iterator[PETSc.Comm]:
    """Solvers created in the block (without ``comm=``) live on `comm`.

    `comm` is a ``PETSc.Comm`` or an mpi4py communicator.  Collective: every rank
    of `comm` must run the same solves in the same order.
    """
    comm = as_petsc_comm(comm)
    _default.append(comm)
    try:
        yield comm
    finally:
        _default.pop()


def as_petsc_comm(comm: PETSc.Comm | MPI.Comm | None) -> PETSc.Comm:
    """`comm` as a ``PETSc.Comm`` (None: `default_comm`); accepts mpi4py communicators."""
    if comm is None:
        return default_comm()
    if isinstance(comm, PETSc.Comm):
        return comm
    return PETSc.Comm(comm)  # an mpi4py communicator


def ownership_range(n: int, comm: PETSc.Comm, block_size: int = 1) -> tuple[int, int]:
    """Rows ``[start, end)`` of an n-row object owned by this rank (PETSc's default split).

    The split is by blocks of `block_size` rows (n must be a multiple of it): the
    first ``(n / block_size) % size`` ranks get one block more, as
    ``PetscSplitOwnershipBlock`` does.
    """
    size, rank = comm.getSize(), comm.getRank()
    base, extra = divmod(n // block_size, size)
    start = rank * base + min(rank, extra)
    return start * block_size, (start + base + (rank < extra)) * block_size


class RowLayout:
    """Copies between numpy vectors and the rows of a PETSc Vec (see the module notes).

    Parameters
    ----------
    vec : PETSc.Vec
        A Vec with the operator's row layout.
    replicated : bool
        True: numpy vectors are full length and solutions are gathered to every
        rank; False: numpy vectors hold this rank's rows only.

    Attributes
    ----------
    size : int
        Length of the numpy vectors this layout takes (global or local).
    start, end : int
        This rank's rows.
    """

    def __init__(self, vec: PETSc.Vec, *, replicated: bool):
        self.start, self.end = vec.getOwnershipRange()
        self._comm = vec.getComm()
        self.distributed = vec.getComm().getSize() > 1
        self.replicated = replicated and self.distributed
        self.size = vec.getSize() if replicated else vec.getLocalSize()
        self._scatter = self._full = None
        if self.replicated:
            self._scatter, self._full = PETSc.Scatter.toAll(vec)

    def local(self, row: np.ndarray) -> np.ndarray:
        """This rank's part of the numpy vector `row`."""
        return row[self.start : self.end] if self.replicated else row

    def gather(self, vec: PETSc.Vec) -> np.ndarray:
        """`vec` as a numpy array in this layout (read-only; copy before keeping it)."""
        if not self.replicated:
            return vec.getArray(readonly=True)
        self._scatter.scatter(vec, self._full, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        return self._full.getArray(readonly=True)

    def agree_max(self, values: np.ndarray) -> np.ndarray:
        """Element-wise maximum of integer `values` over the ranks (collective).

        In the owned layout each rank sees only its rows of a right-hand side, so
        decisions about the whole vector (its scaling, NaN) are taken together.
        """
        values = np.array(values, dtype=np.int64)
        if not self.distributed:
            return values
        from mpi4py import MPI  # needed only by the owned layout on several ranks

        self._comm.tompi4py().Allreduce(MPI.IN_PLACE, values, op=MPI.MAX)
        return values

    def destroy(self) -> None:
        for obj in (self._scatter, self._full):
            if obj is not None:
                obj.destroy()
        self._scatter = self._full = None
