"""K_full: the iterations a solver needs to converge on a representative system.

PRDP's start, step and cap come from this one number (`prdp_petsc.PRDP.for_problem`),
and full fidelity means "capped at K_full".  The probe runs on a clone of the
caller's solver, so its options (and the command line's, under its prefix) apply.
"""

from __future__ import annotations

import numpy as np

from .results import SolverError
from .solver import KSPSolver

__all__ = ["find_k_full"]


def find_k_full(
    solver: KSPSolver,
    A,
    b: np.ndarray,
    *,
    rtol: float = 1e-8,
    x0: np.ndarray | None = None,
    max_it: int = 100_000,
) -> int:
    """Iterations `solver`'s KSP/PC needs to reach `rtol` on ``A x = b``.

    Parameters
    ----------
    solver : KSPSolver
        Its options, prefix and declared structure are used (on a clone).
    A : scipy.sparse matrix, PETSc.Mat or CSR tuple
        A representative operator (e.g. ``P.matrix(theta)`` of a `ParametricMatrix`).
    b : ndarray, shape (n,) or (B, n)
        Representative right-hand side(s); the largest count over them is returned.
    rtol : float
        What "converged" means for this problem.
    x0 : ndarray, shape of `b`, optional
        The guess the problem's solves start from: the count is then that of a
        solve from x0 stopped by PETSc's default test ``‖r_k‖ ≤ rtol ‖b‖`` (in the
        KSP's norm, not relative to the smaller initial residual), so a good guess
        also shortens full fidelity.
    max_it : int
        Give up (`SolverError`) beyond this many iterations.

    Returns
    -------
    int
        K_full.

    Raises
    ------
    SolverError
        If the solver does not reach `rtol` within `max_it` iterations.
    """
    b = np.atleast_2d(np.asarray(b, dtype=np.float64))
    x0 = None if x0 is None else np.atleast_2d(np.asarray(x0, dtype=np.float64))
    iterations = []
    with solver.clone(max_it=max_it, rtol=rtol, atol=0.0) as probe:
        probe.set_operator(A)
        for i, row in enumerate(b):
            if x0 is not None:
                probe.ksp.setConvergenceHistory(max_it + 1, reset=True)
            count = _solve(probe, row)
            if x0 is not None:  # ‖b‖ in the KSP's norm, then the history from x0
                target = rtol * probe.ksp.getConvergenceHistory()[0]
                probe.rtol = rtol * 1e-3
                _solve(probe, row - A @ x0[i])
                history = probe.ksp.getConvergenceHistory()
                probe.rtol = rtol
                reached = np.flatnonzero(history <= target)
                count = int(reached[0]) if len(reached) else count
            iterations.append(count)
    return max(iterations)


def _solve(probe: KSPSolver, row: np.ndarray) -> int:
    probe.solve(row)
    if not probe.last.converged:
        raise SolverError(
            f"the solver did not reach rtol={probe.rtol} in {probe.max_it} iterations "
            f"({probe.last.reason}); K_full is undefined",
            reason=probe.last.reason,
        )
    return probe.last.iterations
