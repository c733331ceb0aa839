"""What one differentiable linear solve returns when asked: x with its outcome.

``sol = pp.solve(A, b, solver, return_solution=True)`` gives a `LinearSolution`: the
solution tensor ``sol.value`` (differentiable as the plain return value is) and the
outcome of this call, which the caller can keep: ``sol.forward`` (every sample's
iterations, reason and residual norm) and, once a backward has run through
``sol.value``, ``sol.adjoint``.  The solver's ``last_forward`` / ``last_adjoint`` hold
the same for the latest call only, and its ``stats`` the running totals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..core.results import CallInfo

__all__ = ["AdjointSlot", "LinearSolution"]


class AdjointSlot:
    """Where a backward leaves the `CallInfo` of its transpose solve.

    The autograd graph holds this, not the `LinearSolution` (which holds the graph
    through its ``value``): no reference cycle keeps the graph alive after use.
    """

    __slots__ = ("info",)

    def __init__(self) -> None:
        self.info: CallInfo | None = None


@dataclass(eq=False)
class LinearSolution:
    """The solution of one `prdp_petsc.solve` call and its outcome.

    Attributes
    ----------
    value : torch.Tensor
        x, shape of b; differentiable.
    forward : CallInfo
        The forward solve of every sample (batch order): iterations, PETSc reason,
        residual norm (None where PETSc computed none).
    adjoint : CallInfo or None
        The transpose solve of every sample, filled in by the backward through
        `value` (None before it, and in ``mode="unrolled"``, which runs no adjoint
        solve; the latest one after a second backward with ``retain_graph``).

    For b of shape (n,) `iterations`, `reason` and `residual_norm` are one
    sample's values; for (B, n) an array (a list for `reason`) over the batch.
    """

    value: torch.Tensor
    forward: CallInfo
    slot: AdjointSlot = field(default_factory=AdjointSlot, repr=False)

    @property
    def adjoint(self) -> CallInfo | None:
        """The transpose solve of every sample, once a backward ran through `value`."""
        return self.slot.info

    @property
    def iterations(self) -> int | np.ndarray:
        """Forward iterations (``(B,)`` for a batch)."""
        return self.forward[0].iterations if self.value.ndim == 1 else self.forward.iterations

    @property
    def reason(self) -> str | list[str]:
        """PETSc's ``KSPConvergedReason`` name of the forward solve (a list for a batch)."""
        return self.forward[0].reason if self.value.ndim == 1 else self.forward.reasons

    @property
    def residual_norm(self) -> float | None | np.ndarray:
        """PETSc's last residual norm of the forward solve: None (NaN in a batch's
        ``(B,)`` array) where PETSc computed none."""
        if self.value.ndim == 1:
            return self.forward[0].residual_norm
        return self.forward.residual_norms

    @property
    def converged(self) -> bool:
        """Whether every sample's forward solve met a tolerance (the cap is not one)."""
        return self.forward.converged
