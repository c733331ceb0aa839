"""Numerical safeguards around one PETSc KSP solve, used by `KSPSolver`.

* **Extreme right-hand sides.**  Krylov methods square residual norms (CG's
  ``rᵀz``, BiCGStab's ``ρ``): a right-hand side of size 1e-150 underflows to a false
  breakdown, 1e-300 even to a silent ``x = 0``; 1e150 overflows.  Every capped
  K-step Krylov or stationary map is homogeneous, ``x_K(s b) = s x_K(b)``, so a
  right-hand side whose largest entry lies outside `SAFE_RANGE` is multiplied by a
  power of two (exact in floating point) and the solution scaled back.
* **Breakdowns at rounding level.**  Run far beyond convergence with
  ``rtol = atol = 0``, CG reports ``DIVERGED_INDEFINITE_PC``, GMRES
  ``DIVERGED_BREAKDOWN``, BiCGStab breaks down or even diverges (DTOL) once the
  residual has reached rounding level; CG+ICC may even end at the cap with an
  iterate that drifted far from the solution (relative error 2e-4 seen after
  20000 iterations), its recursive residual having underflowed.  `rescue`
  recognises these cases: the iterate is accepted when its backward error is at
  rounding level and its true residual is below the initial one; otherwise the
  (deterministic) iteration is run again up to the first iteration far beyond
  rounding level (or the one of the smallest recorded residual) and that iterate
  is accepted if it passes the same test.  A breakdown
  above rounding level stays an error, as does an unrecoverable loss of accuracy.
* **Iterates that did not solve the system.**  A Krylov method's stopping test
  reads its own residual norm, often the preconditioned one; on a singular
  operator whose null space nobody declared (elasticity without Dirichlet
  conditions) GAMG's coarse solve blows the iterate up along the kernel, the
  preconditioned norm falls by 1e-14 in one iteration, and PETSc reports
  ``CONVERGED_RTOL`` for an x of size 1e14 whose true residual is 50 times the
  right-hand side.  Its backward error ``‖b − A x‖ / (‖A‖ ‖x‖ + ‖b‖)`` is tiny
  precisely because ‖x‖ exploded, so it cannot tell.  `judge` looks at the true
  residual ``‖b − A x‖`` against the initial one ``‖b‖`` (a solve starts from
  zero) and at whether x is a null vector of A (`Residual.null_vector`).  What
  is checked when (`prdp_petsc.core.step.SolveStep` applies it):

  - a *converged* solve: always, one ``MatMult``.  Met a tolerance
    (``CONVERGED_RTOL``/``ATOL``): it must have reduced the true residual
    (``‖b − A x‖ ≤ ‖b‖``; the tolerance was tested in the KSP's norm, which may
    be far from the true one), and an x that is a null vector to
    `NULL_TOLERANCE` must have reduced it below `STALLED` ``‖b‖``.  Stopped
    for another reason (``CONVERGED_STEP_LENGTH``, ``HAPPY_BREAKDOWN``, ...: no
    residual was tested): it must have reduced the true residual below
    ``√rtol ‖b‖`` (at most `STALLED` ``‖b‖``): MINRES stops with ``STEP_LENGTH``
    at the least-squares floor of an incompatible singular system, even at x = 0;
  - a *capped* solve (``DIVERGED_MAX_IT``, or ``CONVERGED_ITS``: K iterations
    without a norm to test): two vector norms, and a ``MatMult``
    only when ``‖A‖ ‖x‖ > ‖b‖ / NULL_TOLERANCE`` (an x only an operator of
    condition number ≥ 1e8 explains).  A capped iterate may legitimately have a
    larger residual than zero, so it is refused only when it is a null vector to
    rounding level (`ROUNDING_LEVEL`) and did not reduce the residual;
  - an iterate accepted after a late breakdown (`rescue`) must also have
    reduced the true residual;
  - a failed solve is diagnosed (no cost on the hot path): an x that is a null
    vector to rounding level with a residual above `STALLED` ``‖b‖`` is reported
    as `prdp_petsc.errors.SingularOperatorError`, which says to declare the null
    space; otherwise PETSc's reason stands, and its message says how to declare
    a null space if x is a null vector to `NEAR_NULL` (`looks_singular`: a hint,
    not a verdict);
  - a solve with a tolerance that ended without meeting it (``DIVERGED_MAX_IT``
    with ``rtol > 0`` or ``atol > 0``) gets its true residual (one ``MatMult``)
    for the warning or error `prdp_petsc.KSPSolver` gives it (``not_converged``),
    with the same hint.  A capped or failed solve is relabelled
    only at rounding level because an ill-conditioned operator has null vectors to
    `NULL_TOLERANCE` too (a SIMP stiffness with contrast 1e-9 : 1 breaks GAMG's
    default smoothers with an x that is one to 6e-9; that is ``DIVERGED_INDEFINITE_PC``,
    not a missing null space), while a singular one blows x up to 1e-12..1e-17.
* **KSP types without a correct transpose.**  `NO_TRANSPOSE_KSP` lists the types
  whose ``KSPSolveTranspose`` runs without error but does not apply the transposed
  iteration (found by comparing with a forward solve on an explicit Aᵀ); the
  adjoint refuses them rather than return a wrong gradient.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc

from .nullspace import NULL_TOLERANCE
from .results import SolverError

__all__ = [
    "FAR_BEYOND",
    "LATE_BREAKDOWNS",
    "DECLARE_NULLSPACE",
    "LATE_REASONS",
    "NEAR_NULL",
    "NO_TRANSPOSE_KSP",
    "NULL_TOLERANCE",
    "ROUNDING_LEVEL",
    "SAFE_RANGE",
    "STALLED",
    "Residual",
    "backward_error",
    "exponent_of",
    "check_transpose_ksp",
    "judge",
    "looks_singular",
    "operator_norm",
    "rescue",
    "rhs_exponent",
    "rhs_exponents",
    "true_residual",
    "went_far",
]

logger = logging.getLogger(__name__)

#: backward error ``‖b − A x‖ / (‖A‖ ‖x‖ + ‖b‖)`` that counts as converged to rounding
ROUNDING_LEVEL = 1e4 * np.finfo(np.float64).eps
#: recorded residual reduction that lies certainly beyond rounding level (see `went_far`)
FAR_BEYOND = 1e-20
#: right-hand sides whose largest entry lies outside this range are rescaled
SAFE_RANGE = (2.0**-100, 2.0**100)
#: PETSc reasons that are spurious when the residual had already reached rounding level
LATE_BREAKDOWNS = frozenset(
    {
        "DIVERGED_BREAKDOWN",
        "DIVERGED_BREAKDOWN_BICG",
        "DIVERGED_INDEFINITE_PC",
        "DIVERGED_INDEFINITE_MAT",
        "DIVERGED_DTOL",
        "DIVERGED_NANORINF",
    }
)
#: the same as PETSc ``KSPConvergedReason`` values
LATE_REASONS = frozenset(getattr(PETSc.KSP.ConvergedReason, name) for name in LATE_BREAKDOWNS)
#: KSP types whose transpose solve silently runs another iteration (PETSc 3.26)
NO_TRANSPOSE_KSP = frozenset({"cgls"})
#: a true residual above this fraction of the initial one has not moved towards a
#: solution: for an x that is a null vector of A, the sign of a singular operator
#: (a stalled solve stays near 1, a converged one falls by orders of magnitude even
#: at high contrast; tests/test_singular.py checks both sides)
STALLED = 0.1
#: an iterate of a failed or unconverged solve with ``‖A x‖ ≤ NEAR_NULL ‖A‖ ‖x‖`` looks
#: like a null vector of A (`looks_singular`): its message says how to declare a null
#: space.  A hint, not a verdict: an ill-conditioned operator has such near-null
#: vectors too (`judge` claims singularity only at `ROUNDING_LEVEL`), an indefinite one
#: does not (tests/test_singular.py checks curl-curl's iterates against Helmholtz's)
NEAR_NULL = 1e-4
#: how to declare a null space: the end of every message on a singular-looking operator
DECLARE_NULLSPACE = (
    "declare the whole null space, KSPSolver(structure=pp.Structure(nullspace=...)): "
    "rigid_body_modes(basis) for elasticity without Dirichlet conditions, "
    "discrete_gradient(basis, dofs) (sparse) for curl-curl on Nédélec elements, "
    "'constant' for a pure Neumann problem; or add boundary conditions"
)


def check_transpose_ksp(ksp) -> None:
    """Raise `SolverError` if the adjoint's KSP type has no correct transpose solve."""
    if ksp.getType() in NO_TRANSPOSE_KSP:
        raise SolverError(
            f"adjoint ksp_type {ksp.getType()!r} has no correct transpose solve in PETSc (it "
            "would return a wrong gradient); choose another adjoint ksp_type, e.g. "
            "AdjointSettings(options={'ksp_type': 'gmres'})",
            reason="NO_TRANSPOSE",
        )


def rhs_exponents(batch: np.ndarray) -> np.ndarray:
    """`rhs_exponent` of every row of a ``(B, n)`` batch, vectorised."""
    if batch.shape[1] == 0:
        return np.zeros(len(batch), dtype=int)
    biggest = np.maximum(batch.max(axis=1), -batch.min(axis=1))  # no |batch| temporary
    safe = (biggest == 0.0) | ((SAFE_RANGE[0] <= biggest) & (biggest <= SAFE_RANGE[1]))
    return np.where(safe, 0, np.frexp(biggest)[1])


def exponent_of(biggest: float) -> int:
    """`rhs_exponent` of a right-hand side whose largest entry is `biggest` (``‖b‖_∞``,
    finite): 0 for 0 or a size in `SAFE_RANGE`."""
    if biggest == 0.0 or SAFE_RANGE[0] <= biggest <= SAFE_RANGE[1]:
        return 0
    return int(np.frexp(biggest)[1])


def rhs_exponent(row: np.ndarray) -> int:
    """Power of two e such that ``row · 2⁻ᵉ`` has its largest entry in [0.5, 1).

    Returns 0 (no scaling) for a zero row or one whose largest entry lies in
    `SAFE_RANGE`.
    """
    return int(rhs_exponents(np.asarray(row, dtype=np.float64).reshape(1, -1))[0])


def operator_norm(mat: PETSc.Mat) -> float:
    """``max(‖A‖₁, ‖A‖_∞)`` ≥ ‖A‖₂: one pass over the entries (collective)."""
    return max(mat.norm(PETSc.NormType.INFINITY), mat.norm(PETSc.NormType.NORM_1))


@dataclass(frozen=True)
class Residual:
    """How well an iterate x solves ``A x = b`` (``Aᵀ x = b`` for a transpose solve).

    Attributes
    ----------
    norm : float
        ``‖b − A x‖``, its part in the transpose null space removed (KSPSolve
        projects b onto the range of A).
    initial : float
        ``‖b‖``, projected alike: the residual of the initial guess x = 0.
    product : float
        ``‖A x‖``.
    scale : float
        ``‖A‖ ‖x‖`` (`operator_norm`); NaN when x is not finite.
    rhs : float
        ``‖b‖`` unprojected (for the backward error).
    """

    norm: float
    initial: float
    product: float
    scale: float
    rhs: float

    @property
    def reduced(self) -> bool:
        """Whether x is no worse than the initial guess: ``‖b − A x‖ ≤ ‖b‖``."""
        return bool(self.norm <= self.initial)

    @property
    def relative(self) -> float:
        """``‖b − A x‖ / ‖b‖`` (0 for b = 0 = r)."""
        if self.initial > 0:
            return self.norm / self.initial
        return np.inf if self.norm > 0 else 0.0

    @property
    def backward(self) -> float:
        """Backward error ``‖b − A x‖ / (‖A‖ ‖x‖ + ‖b‖)``."""
        denom = self.scale + self.rhs
        return float(self.norm / denom) if denom > 0 else 0.0

    def null_vector(self, tolerance: float) -> bool:
        """Whether x is a null vector of A to `tolerance`: ``‖A x‖ ≤ tolerance ‖A‖ ‖x‖``."""
        return bool(self.scale > 0 and self.product <= tolerance * self.scale)

    def describe(self) -> str:
        return (
            f"‖b − A x‖/‖b‖ = {self.relative:.3g}, ‖A x‖/(‖A‖ ‖x‖) = "
            f"{self.product / self.scale if self.scale > 0 else 0.0:.3g}"
        )


def true_residual(
    mat: PETSc.Mat, b: PETSc.Vec, x: PETSc.Vec, *, transpose: bool, norm: float | None = None
) -> Residual:
    """The `Residual` of `x` (one ``MatMult``; `norm` is `operator_norm`, if known)."""
    product = b.duplicate()
    (mat.multTranspose if transpose else mat.mult)(x, product)
    r = b.copy()
    r.axpy(-1.0, product)  # r = b − A x
    ns = mat.getNullSpace() if transpose else mat.getTransposeNullSpace()
    rhs = b.norm()
    initial = rhs
    if ns is not None and bool(ns):
        ns.remove(r)  # the incompatible part of b is projected away by KSPSolve
        projected = b.copy()
        ns.remove(projected)
        initial = projected.norm()
        projected.destroy()
    scale = (operator_norm(mat) if norm is None else norm) * x.norm()
    out = Residual(float(r.norm()), float(initial), float(product.norm()), float(scale), rhs)
    for vec in (r, product):
        vec.destroy()
    return out


def judge(residual: Residual, outcome: str, rtol: float = 0.0) -> str | None:
    """None if the iterate stands, else ``"singular"`` or ``"not solved"``.

    `outcome` is ``"converged"`` (a tolerance was met: ``CONVERGED_RTOL``,
    ``CONVERGED_ATOL``, their ``_NORMAL_EQUATIONS`` forms, ``CONVERGED_USER``),
    ``"stopped"`` (another ``CONVERGED_*`` claim that tests no residual: ``STEP_LENGTH``,
    ``HAPPY_BREAKDOWN``, ``NEG_CURVE``), ``"capped"`` (``DIVERGED_MAX_IT``,
    ``CONVERGED_ITS``) or ``"failed"`` (a solve that raises anyway: only the
    diagnosis matters).  `rtol` is the solve's relative tolerance, which a stop
    must meet loosely (``√rtol``, at most `STALLED`).  See the module notes.
    """
    stalled = residual.norm > STALLED * residual.initial
    if outcome in ("capped", "failed"):  # PETSc's outcome stands unless x is a null
        # vector to rounding level (singular to working precision); ill-conditioned is
        # not singular: a stiffness contrast of 1e-9 has null vectors to 6e-9
        if residual.null_vector(ROUNDING_LEVEL):
            grew = not residual.reduced if outcome == "capped" else stalled
            return "singular" if grew else None
        return None
    if residual.null_vector(NULL_TOLERANCE) and stalled:
        return "singular"
    if outcome == "converged" and not residual.reduced:
        return "not solved"
    if outcome == "stopped":
        limit = min(STALLED, float(np.sqrt(rtol))) if rtol > 0 else STALLED
        if residual.norm > limit * residual.initial:
            return "not solved"
    return None


def looks_singular(residual: Residual) -> bool:
    """Whether the iterate of `residual` is a null vector of A to `NEAR_NULL`."""
    return residual.null_vector(NEAR_NULL)


def backward_error(mat: PETSc.Mat, b: PETSc.Vec, x: PETSc.Vec, *, transpose: bool) -> float:
    """``‖b − A x‖ / (‖A‖ ‖x‖ + ‖b‖)`` (Aᵀ with `transpose`), null-space part removed.

    ‖A‖ is ``max(‖A‖₁, ‖A‖_∞)`` ≥ ‖A‖₂.  NaN when x is not finite.
    """
    return true_residual(mat, b, x, transpose=transpose).backward


def went_far(ksp: PETSc.KSP, history: list | np.ndarray | None = None) -> bool:
    """True when the recorded residual fell below `FAR_BEYOND` times the initial one.

    Only then can an iterate have been corrupted by running past rounding level;
    the check costs nothing otherwise (the history is recorded anyway; pass it as
    `history`, best as a list, if already fetched).
    """
    h = ksp.getConvergenceHistory() if history is None else history
    if isinstance(h, np.ndarray):
        h = h.tolist()
    if len(h) < 2 or not h[0] > 0:
        return False
    # min starts from h[0] > 0 and a comparison with NaN is False: NaN residuals are
    # skipped; h[0] itself is far above FAR_BEYOND * h[0]
    return min(h) <= FAR_BEYOND * h[0]


def _rerun_target(history: np.ndarray, iterations: int) -> int | None:
    """Iteration to stop at: the first far beyond rounding level, else the best one."""
    h = np.where(np.isfinite(history), history, np.nan)[: iterations + 1]
    if h.size < 2 or np.all(np.isnan(h)):
        return None
    far = np.flatnonzero(h[1:] <= FAR_BEYOND * h[0]) + 1 if h[0] > 0 else np.array([], int)
    best = int(far[0]) if far.size else int(np.nanargmin(h))
    return best if 1 <= best < iterations else None


def rescue(
    ksp: PETSc.KSP, mat: PETSc.Mat, b: PETSc.Vec, x: PETSc.Vec, *, transpose: bool
) -> int | None:
    """Decide whether a solve that ran past convergence returned a trustworthy iterate.

    Called after a solve that ended with one of `LATE_BREAKDOWNS`, or whose
    residual history went `FAR_BEYOND` convergence.  Returns None when the iterate
    is not at rounding level and cannot be recovered (the caller raises), otherwise
    the number of iterations of a discarded run (0 when the returned iterate was
    accepted as it is); `x` then holds an iterate with backward error ≤
    `ROUNDING_LEVEL` and a true residual below the initial one (`_at_rounding`),
    and ``ksp`` the state of the run that produced it.  The
    recovery re-runs the (deterministic) iteration from zero up to the first
    iteration far beyond rounding level, or else the one of the smallest residual.
    """
    iterations = ksp.getIterationNumber()
    if _at_rounding(mat, b, x, transpose):
        logger.info(
            "%s after %d iterations at rounding level: iterate accepted",
            ksp.getConvergedReason(),
            iterations,
        )
        return 0
    target = _rerun_target(np.asarray(ksp.getConvergenceHistory()), iterations)
    if target is None:
        return None
    rtol, atol, divtol, max_it = ksp.getTolerances()
    try:
        ksp.setTolerances(max_it=target)
        x.set(0.0)
        (ksp.solveTranspose if transpose else ksp.solve)(b, x)
    finally:
        ksp.setTolerances(rtol=rtol, atol=atol, divtol=divtol, max_it=max_it)
    if _at_rounding(mat, b, x, transpose):
        logger.info(
            "the iterate after %d iterations is not at rounding level; the one of "
            "iteration %d is and is returned",
            iterations,
            target,
        )
        return iterations
    return None


def _at_rounding(mat: PETSc.Mat, b: PETSc.Vec, x: PETSc.Vec, transpose: bool) -> bool:
    """Backward error at rounding level, and the true residual below the initial one.

    The second condition refuses an iterate that exploded along a null vector of a
    singular operator: its backward error is tiny because ‖x‖ is huge.
    """
    residual = true_residual(mat, b, x, transpose=transpose)
    return residual.backward <= ROUNDING_LEVEL and residual.reduced
