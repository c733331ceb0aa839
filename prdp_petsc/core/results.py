"""What a capped solve returns besides the solution: outcome, counters, errors."""

from __future__ import annotations

from dataclasses import dataclass

from petsc4py import PETSc

from ..errors import SolverError

__all__ = ["SolveInfo", "SolverError", "SolverStats", "reason_name"]

_REASONS = {
    getattr(PETSc.KSP.ConvergedReason, name): name
    for name in dir(PETSc.KSP.ConvergedReason)
    if name.isupper() and isinstance(getattr(PETSc.KSP.ConvergedReason, name), int)
}


def reason_name(reason: int) -> str:
    """Name of a PETSc ``KSPConvergedReason`` value, e.g. ``"DIVERGED_MAX_IT"``."""
    return _REASONS.get(int(reason), f"UNKNOWN({int(reason)})")


@dataclass(frozen=True)
class SolveInfo:
    """Outcome of one KSP solve: iteration count, reason name and residual norm."""

    iterations: int
    reason: str
    residual_norm: float

    @property
    def converged(self) -> bool:
        """True when PETSc reports convergence (not when the cap was hit)."""
        return self.reason.startswith("CONVERGED")


@dataclass
class SolverStats:
    """Counters of forward and adjoint work since the last `KSPSolver.reset_stats`."""

    forward_solves: int = 0
    forward_iterations: int = 0
    forward_time: float = 0.0
    adjoint_solves: int = 0
    adjoint_iterations: int = 0
    adjoint_time: float = 0.0
    operator_updates: int = 0

    def record(self, kind: str, solves: int, iterations: int, seconds: float) -> None:
        """Add one call's work to the ``forward`` or ``adjoint`` counters."""
        setattr(self, f"{kind}_solves", getattr(self, f"{kind}_solves") + solves)
        setattr(self, f"{kind}_iterations", getattr(self, f"{kind}_iterations") + iterations)
        setattr(self, f"{kind}_time", getattr(self, f"{kind}_time") + seconds)

    def as_dict(self) -> dict:
        return dict(self.__dict__)
