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
  rounding level; otherwise the (deterministic) iteration is run again up to the
  first iteration far beyond rounding level (or the one of the smallest recorded
  residual) and that iterate is accepted if it is at rounding level.  A breakdown
  above rounding level stays an error, as does an unrecoverable loss of accuracy.
* **KSP types without a correct transpose.**  `NO_TRANSPOSE_KSP` lists the types
  whose ``KSPSolveTranspose`` runs without error but does not apply the transposed
  iteration (found by comparing with a forward solve on an explicit Aᵀ); the
  adjoint refuses them rather than return a wrong gradient.
"""

from __future__ import annotations

import logging

import numpy as np
from petsc4py import PETSc

from .results import SolverError

__all__ = [
    "FAR_BEYOND",
    "LATE_BREAKDOWNS",
    "LATE_REASONS",
    "NO_TRANSPOSE_KSP",
    "check_transpose_ksp",
    "ROUNDING_LEVEL",
    "SAFE_RANGE",
    "backward_error",
    "rescue",
    "rhs_exponent",
    "rhs_exponents",
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


def rhs_exponent(row: np.ndarray) -> int:
    """Power of two e such that ``row · 2⁻ᵉ`` has its largest entry in [0.5, 1).

    Returns 0 (no scaling) for a zero row or one whose largest entry lies in
    `SAFE_RANGE`.
    """
    return int(rhs_exponents(np.asarray(row, dtype=np.float64).reshape(1, -1))[0])


def backward_error(mat: PETSc.Mat, b: PETSc.Vec, x: PETSc.Vec, *, transpose: bool) -> float:
    """``‖b − A x‖ / (‖A‖ ‖x‖ + ‖b‖)`` (Aᵀ with `transpose`), null-space part removed.

    ‖A‖ is ``max(‖A‖₁, ‖A‖_∞)`` ≥ ‖A‖₂.  NaN when x is not finite.
    """
    r = b.duplicate()
    (mat.multTranspose if transpose else mat.mult)(x, r)
    r.aypx(-1.0, b)  # r = b − A x
    ns = mat.getNullSpace() if transpose else mat.getTransposeNullSpace()
    if ns is not None and bool(ns):
        ns.remove(r)  # the incompatible part of b is projected away by KSPSolve
    norm_a = max(mat.norm(PETSc.NormType.INFINITY), mat.norm(PETSc.NormType.NORM_1))
    denom = norm_a * x.norm() + b.norm()
    return float(r.norm() / denom) if denom > 0 else 0.0


def went_far(ksp: PETSc.KSP) -> bool:
    """True when the recorded residual fell below `FAR_BEYOND` times the initial one.

    Only then can an iterate have been corrupted by running past rounding level;
    the check costs nothing otherwise (the history is recorded anyway).
    """
    h = ksp.getConvergenceHistory()
    if h.size < 2 or not h[0] > 0:
        return False
    low = h[1:].min()
    if np.isnan(low):  # rare: a NaN residual; look at the finite ones
        tail = h[1:][np.isfinite(h[1:])]
        low = tail.min() if tail.size else np.inf
    return bool(low <= FAR_BEYOND * h[0])


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
    `ROUNDING_LEVEL` and ``ksp`` the state of the run that produced it.  The
    recovery re-runs the (deterministic) iteration from zero up to the first
    iteration far beyond rounding level, or else the one of the smallest residual.
    """
    iterations = ksp.getIterationNumber()
    if backward_error(mat, b, x, transpose=transpose) <= ROUNDING_LEVEL:
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
    if backward_error(mat, b, x, transpose=transpose) <= ROUNDING_LEVEL:
        logger.info(
            "the iterate after %d iterations is not at rounding level; the one of "
            "iteration %d is and is returned",
            iterations,
            target,
        )
        return iterations
    return None
