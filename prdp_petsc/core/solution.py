"""What every linear solve returns: the solution with the outcome of the call that made it.

One type for every layer: `KSPSolver.solve` and `KSPSolver.solve_transpose` return a
`LinearSolution` whose `value` is an ndarray; ``prdp_petsc.solve(...,
return_solution=True)`` and ``Dirichlet.solve(..., return_solution=True)`` one whose
`value` is a differentiable torch tensor, and whose `adjoint` a backward through it
fills.  The outcome of a call is read here, from what the call returned, never from the
solver afterwards; the solver keeps only the running totals (``solver.stats``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .results import CallInfo

if TYPE_CHECKING:  # the core imports no torch; a tensor value comes from prdp_petsc.solve
    import numpy as np
    import torch

__all__ = ["AdjointSlot", "LinearSolution"]


class AdjointSlot:
    """Where a backward through a `LinearSolution`'s value leaves the `CallInfo` of its
    transpose solve (`prdp_petsc.autograd`).

    The autograd graph holds this, not the `LinearSolution` (which holds the graph
    through its ``value``): no reference cycle keeps the graph alive after use.
    """

    __slots__ = ("info",)

    def __init__(self) -> None:
        self.info: CallInfo | None = None


@dataclass(eq=False)
class LinearSolution:
    """The solution of one linear solve call and its outcome.

    Attributes
    ----------
    value : numpy.ndarray or torch.Tensor
        The solution, shape of the right-hand side: x of ``A x = b`` (λ of
        ``Aᵀ λ = g`` from `KSPSolver.solve_transpose`).  An ndarray from a
        `KSPSolver`, a differentiable tensor from `prdp_petsc.solve`; on a solver's
        device path the ``out`` it was given (an array, or a sequence of rows: a
        batch).
    info : CallInfo
        The solve that made `value`, every sample in batch order: iterations, PETSc
        reason, residual norm (None where PETSc computed none), PC age.  Its
        ``kind`` says which side ran (``"forward"``, or ``"adjoint"`` for
        `KSPSolver.solve_transpose`); ``info[i]`` is sample i's `SolveInfo`.
    adjoint : CallInfo or None
        The transpose solve of every sample that a backward through a tensor
        `value` ran (None before it, for an ndarray `value`, and in
        ``mode="unrolled"``, which runs no adjoint solve; the latest one after a
        second backward with ``retain_graph``).

    For a right-hand side of shape (n,) `iterations`, `reason` and `residual_norm`
    are one sample's values; for (B, n) an array (a list for `reason`) over the
    batch.  The solver's ``stats`` count the work of every call (running totals).
    """

    value: np.ndarray | torch.Tensor
    info: CallInfo
    slot: AdjointSlot = field(default_factory=AdjointSlot, repr=False)

    @property
    def adjoint(self) -> CallInfo | None:
        """The transpose solve of every sample, once a backward ran through `value`."""
        return self.slot.info

    @property
    def _single(self) -> bool:
        """One right-hand side of shape (n,), not a batch (a sequence of rows is one)."""
        return getattr(self.value, "ndim", 2) == 1

    @property
    def iterations(self) -> int | np.ndarray:
        """Iterations of the solve (``(B,)`` for a batch)."""
        return self.info[0].iterations if self._single else self.info.iterations

    @property
    def reason(self) -> str | list[str]:
        """PETSc's ``KSPConvergedReason`` name of the solve (a list for a batch)."""
        return self.info[0].reason if self._single else self.info.reasons

    @property
    def residual_norm(self) -> float | None | np.ndarray:
        """PETSc's last residual norm of the solve: None (NaN in a batch's ``(B,)``
        array) where PETSc computed none."""
        if self._single:
            return self.info[0].residual_norm
        return self.info.residual_norms

    @property
    def converged(self) -> bool:
        """Whether every sample's solve met a tolerance (the cap is not one)."""
        return self.info.converged
