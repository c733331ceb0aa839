"""Ghosted index spaces: a rank's own block of a distributed vector plus copies of others'.

An index space of global size N (the vertices of a mesh, its elements, the
unknowns of a system) is split over the ranks of a communicator: rank r *owns*
the contiguous block ``[start, end)`` and keeps *ghost* copies of some indices
other ranks own (those its assembly reads).  A rank's local vectors list the
owned entries first, in global order, then the ghosts, in the order given.

`GhostedSpace` moves values between the owned block and the local vector with
PETSc's ghosted Vec (``VecCreateGhost``):

``update``
    owned values → local vector, the ghosts filled from their owners
    (``VecGhostUpdate`` with ``INSERT_VALUES``, ``SCATTER_FORWARD``);
``accumulate``
    local vector → owned values, each ghost entry *added* to its owner's
    (``ADD_VALUES``, ``SCATTER_REVERSE``): the transpose of `update`, which is
    what a gradient needs.

Both are collective.  Nothing here is ever of global length.
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from ..errors import InputError

__all__ = ["GhostedSpace", "exclusive_offset"]


def exclusive_offset(count: int, comm: PETSc.Comm) -> tuple[int, int]:
    """``(sum of count over the lower ranks, sum over all ranks)`` (collective)."""
    if comm.getSize() == 1:
        return 0, int(count)
    counts = comm.tompi4py().allgather(int(count))
    return int(sum(counts[: comm.getRank()])), int(sum(counts))


class GhostedSpace:
    """One rank's view of a distributed index space: an owned block plus ghosts.

    Parameters
    ----------
    owned : int
        Number of indices this rank owns; the ranks' blocks follow each other in
        rank order (rank 0 owns ``[0, owned_0)``, ...).
    ghosts : array of int
        Global indices owned by other ranks that this rank keeps copies of.
    comm : PETSc.Comm
        Communicator of the space (collective construction).

    Attributes
    ----------
    start, end : int
        This rank's owned block ``[start, end)``.
    size : int
        Global size N.
    owned : int
    ghosts : ndarray of PETSc ints
    local_size : int
        ``owned + len(ghosts)``: the length of local vectors.
    global_ids : ndarray
        Global index of each local entry (``start ... end - 1``, then the ghosts).

    Notes
    -----
    One PETSc ghosted Vec (``VecCreateGhost``) is kept for the exchanges; free it
    with `destroy` (distributed PETSc objects are otherwise only freed at a
    collective clean-up).  A batch ``(B, n)`` is exchanged one row at a time.
    """

    def __init__(self, owned: int, ghosts, comm: PETSc.Comm) -> None:
        if owned < 0:
            raise InputError(f"owned must be >= 0, got {owned}")
        self.comm = comm
        self.owned = int(owned)
        self.ghosts = np.asarray(ghosts, dtype=PETSc.IntType).ravel()
        self.start, self.size = exclusive_offset(self.owned, comm)
        self.end = self.start + self.owned
        mine = (self.ghosts >= self.start) & (self.ghosts < self.end)
        if np.any(mine) or np.any(self.ghosts < 0) or np.any(self.ghosts >= self.size):
            raise InputError(
                f"ghosts must be global indices in [0, {self.size}) owned by other ranks "
                f"(this rank owns [{self.start}, {self.end}))"
            )
        self.local_size = self.owned + len(self.ghosts)
        self.global_ids = np.concatenate(
            [np.arange(self.start, self.end, dtype=PETSc.IntType), self.ghosts]
        )
        self.vec = PETSc.Vec().createGhost(self.ghosts, size=(self.owned, self.size), comm=comm)

    def update(self, owned: np.ndarray) -> np.ndarray:
        """Local vector(s) of `owned` values ``(owned,)`` or ``(B, owned)``: ghosts filled
        from their owners (collective)."""
        owned = np.asarray(owned, dtype=np.float64)
        self._check(owned, self.owned, "owned")
        rows = owned.reshape(-1, self.owned)
        out = np.empty((len(rows), self.local_size))
        for row, target in zip(rows, out, strict=True):
            self.vec.setArray(row)
            self.vec.ghostUpdate(PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.FORWARD)
            with self.vec.localForm() as local:
                target[:] = local.getArray(readonly=True)
        return out.reshape(*owned.shape[:-1], self.local_size)

    def accumulate(self, local: np.ndarray) -> np.ndarray:
        """Owned values of local vector(s) ``(local_size,)`` or ``(B, local_size)``: each
        ghost entry added to its owner's entry (collective; the transpose of `update`)."""
        local = np.asarray(local, dtype=np.float64)
        self._check(local, self.local_size, "local")
        rows = local.reshape(-1, self.local_size)
        out = np.empty((len(rows), self.owned))
        for row, target in zip(rows, out, strict=True):
            with self.vec.localForm() as form:
                form.setArray(row)
            self.vec.ghostUpdate(PETSc.InsertMode.ADD_VALUES, PETSc.ScatterMode.REVERSE)
            target[:] = self.vec.getArray(readonly=True)
        return out.reshape(*local.shape[:-1], self.owned)

    def _check(self, values: np.ndarray, n: int, name: str) -> None:
        if values.ndim not in (1, 2) or values.shape[-1] != n:
            raise InputError(f"{name} values must have shape ({n},) or (batch, {n})")

    def destroy(self) -> None:
        """Free the PETSc Vec (collective)."""
        if self.vec is not None:
            self.vec.destroy()
            self.vec = None

    def __repr__(self) -> str:
        return (
            f"GhostedSpace(owned=[{self.start}, {self.end}) of {self.size}, "
            f"ghosts={len(self.ghosts)})"
        )
