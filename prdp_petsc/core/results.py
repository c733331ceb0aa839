"""What a capped solve returns besides the solution: outcome, counters, errors."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from petsc4py import PETSc

from ..errors import SolverError

__all__ = ["CallInfo", "Side", "SolveInfo", "SolverError", "SolverStats", "reason_name"]

_REASONS = {
    getattr(PETSc.KSP.ConvergedReason, name): name
    for name in dir(PETSc.KSP.ConvergedReason)
    if name.isupper() and isinstance(getattr(PETSc.KSP.ConvergedReason, name), int)
}


class Side(StrEnum):
    """The two solves of a `KSPSolver`: forward ``A x = b`` and adjoint ``Aᵀ λ = g``.

    The values are the words a record uses (`CallInfo.kind`, `SolverStats.record`):
    ``Side.FORWARD.value == "forward"``.
    """

    FORWARD = "forward"
    ADJOINT = "adjoint"


def reason_name(reason: int) -> str:
    """Name of a PETSc ``KSPConvergedReason`` value, e.g. ``"DIVERGED_MAX_IT"``."""
    return _REASONS.get(int(reason), f"UNKNOWN({int(reason)})")


@dataclass(frozen=True)
class SolveInfo:
    """Outcome of one KSP solve: iteration count, reason name and residual norm.

    Attributes
    ----------
    iterations : int
        PETSc's iteration count of the returned iterate.
    reason : str
        PETSc's ``KSPConvergedReason`` name.
    residual_norm : float or None
        The last residual norm PETSc computed (in the KSP's norm type), or None
        when PETSc computed none: ``-ksp_norm_type none``, ``preonly``, or
        Richardson with a PC that runs its own sweeps (SOR), whose tolerances
        PETSc then ignores.  Never 0.0 for "not computed".
    rate : float or None
        Geometric mean residual reduction per iteration, ``(‖r_K‖/‖r_0‖)^(1/K)``
        from the KSP's residual history (in its norm type); None where PETSc
        computed no norm or ran no iteration.
    pc_age : int
        Operator value changes since the preconditioner this solve used was set
        up (0: a fresh PC; > 0 only with ``KSPSolver(pc_lag=N)``, N > 1).
    k_equivalent : float or None
        On a reused PC (``pc_age > 0``): the iterations the stale PC needs to
        reduce the residual as far as the fresh PC does in this solve's K,
        ``K · log(rate_fresh) / log(rate)`` with ``rate_fresh`` measured on the
        solves right after the last set-up (``inf`` when the stale PC reduces
        nothing); ≥ K when the stale PC is worse.  None on a fresh PC, or where a
        rate is unknown.
    """

    iterations: int
    reason: str
    residual_norm: float | None
    rate: float | None = None
    pc_age: int = 0
    k_equivalent: float | None = None

    @property
    def residual_computed(self) -> bool:
        """Whether PETSc computed a residual norm (see `residual_norm`)."""
        return self.residual_norm is not None

    @property
    def converged(self) -> bool:
        """True when PETSc reports that a tolerance was met (``CONVERGED_RTOL``, ...).

        Hitting the cap is not convergence, and neither is ``CONVERGED_ITS``: PETSc
        reports it when it ran the requested iterations without a norm to test
        (``preonly``, ``-ksp_norm_type none``, Richardson+SOR).  Richardson with
        multigrid tests the tolerance inside the PC: converged, with no residual
        norm at the KSP (`residual_norm` None).
        """
        return self.reason.startswith("CONVERGED") and self.reason != "CONVERGED_ITS"


@dataclass(frozen=True)
class CallInfo:
    """The outcome of every sample of one solver call (a batch), in batch order.

    A call's `prdp_petsc.core.solution.LinearSolution` carries it as ``info`` (and a
    backward's transpose solve as ``adjoint``).  Index it (``info[i]``) for one
    sample's `SolveInfo`.

    Attributes
    ----------
    kind : {"forward", "adjoint"}
        The `Side` of the call, as its value (a plain string in a JSON record).
    samples : tuple of SolveInfo
    """

    kind: str
    samples: tuple

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i) -> SolveInfo:
        return self.samples[i]

    def __iter__(self):
        return iter(self.samples)

    @property
    def iterations(self) -> np.ndarray:
        """Iterations per sample, ``(B,)`` int."""
        return np.array([s.iterations for s in self.samples], dtype=np.int64)

    @property
    def reasons(self) -> list[str]:
        """PETSc reason name per sample."""
        return [s.reason for s in self.samples]

    @property
    def residual_norms(self) -> np.ndarray:
        """Residual norm per sample, ``(B,)``; NaN where PETSc computed none
        (`residual_computed` says which)."""
        return np.array(
            [np.nan if s.residual_norm is None else s.residual_norm for s in self.samples]
        )

    @property
    def residual_computed(self) -> np.ndarray:
        """Whether PETSc computed each sample's residual norm, ``(B,)`` bool."""
        return np.array([s.residual_computed for s in self.samples], dtype=bool)

    @property
    def pc_ages(self) -> np.ndarray:
        """`SolveInfo.pc_age` per sample, ``(B,)`` int."""
        return np.array([s.pc_age for s in self.samples], dtype=np.int64)

    @property
    def k_equivalents(self) -> np.ndarray:
        """`SolveInfo.k_equivalent` per sample, ``(B,)``; NaN where None (fresh PC or
        no rate)."""
        return np.array(
            [np.nan if s.k_equivalent is None else s.k_equivalent for s in self.samples]
        )

    @property
    def converged(self) -> bool:
        """True when every sample converged (`SolveInfo.converged`)."""
        return bool(self.samples) and all(s.converged for s in self.samples)

    @staticmethod
    def concat(calls) -> CallInfo:
        """One record of several calls of the same kind (a batch of operators)."""
        calls = list(calls)
        kind = calls[0].kind if calls else Side.FORWARD.value
        return CallInfo(kind, tuple(s for c in calls for s in c.samples))


@dataclass
class SolverStats:
    """Counters of forward and adjoint work since the last `KSPSolver.reset_stats`.

    ``pc_setups`` counts the preconditioner set-ups the solves caused (a PC shared
    by the forward and adjoint KSPs once), ``pc_quality_rebuilds`` those of them
    that ``KSPSolver(pc_lag=N)``'s quality guard forced before the lag ran out.
    """

    forward_solves: int = 0
    forward_iterations: int = 0
    forward_time: float = 0.0
    adjoint_solves: int = 0
    adjoint_iterations: int = 0
    adjoint_time: float = 0.0
    operator_updates: int = 0
    pc_setups: int = 0
    pc_quality_rebuilds: int = 0

    def record(self, kind: str, solves: int, iterations: int, seconds: float) -> None:
        """Add one call's work to the ``forward`` or ``adjoint`` counters."""
        if kind == Side.FORWARD:
            self.forward_solves += solves
            self.forward_iterations += iterations
            self.forward_time += seconds
        else:
            self.adjoint_solves += solves
            self.adjoint_iterations += iterations
            self.adjoint_time += seconds

    def as_dict(self) -> dict:
        return dict(self.__dict__)
