"""K_full: the iterations a solver needs to converge on a representative system.

PRDP's start, step and cap come from this one number (`prdp_petsc.PRDP.for_problem`),
and full fidelity means "capped at K_full".  The probe runs on a clone of the
caller's solver, so its options (and the command line's, under its prefix) apply.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .results import SolverError
from .solver import KSPSolver

__all__ = ["find_k_full"]


def find_k_full(
    A,
    b,
    solver: KSPSolver,
    *,
    theta=None,
    rtol: float = 1e-8,
    x0=None,
    max_it: int = 100_000,
) -> int:
    """Iterations `solver`'s KSP/PC needs to reach `rtol` on ``A x = b``.

    Takes what `prdp_petsc.solve` takes, in the same order.

    Parameters
    ----------
    A : ParametricMatrix, scipy.sparse matrix, PETSc.Mat or CSR tuple
        A representative operator; a `~prdp_petsc.fem.parametric.ParametricMatrix`
        is evaluated at `theta`.
    b : ndarray or torch.Tensor, shape (n,) or (B, n)
        Representative right-hand side(s); the largest count over them is returned.
    solver : KSPSolver
        Its options, prefix and declared structure are used (on a clone).
    theta : ndarray or torch.Tensor, shape (p,) or (B, p), optional
        Parameters of a ParametricMatrix `A` (required for one, refused otherwise);
        (B, p) probes one operator per row of `b`.
    rtol : float
        What "converged" means for this problem.
    x0 : ndarray or torch.Tensor, shape of `b`, optional
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
    InputError
        If `solver` is not a `KSPSolver`, or `theta` does not fit `A`.
    """
    if not isinstance(solver, KSPSolver):
        raise InputError(
            f"solver must be a KSPSolver, got {type(solver).__name__}: the arguments are "
            "find_k_full(A, b, solver, theta=...), as for prdp_petsc.solve"
        )
    b = np.atleast_2d(_array(b))
    x0 = None if x0 is None else np.atleast_2d(_array(x0))
    operator_of = _operators(A, theta, len(b))
    iterations, M = [], None
    # a probe that stops short raises its own error below: no NotConvergedWarning first
    with solver.clone(max_it=max_it, rtol=rtol, atol=0.0, not_converged="ignore") as probe:
        for i, row in enumerate(b):
            if (row_operator := operator_of(i)) is not M:  # one operator: set once
                M = row_operator
                probe.set_operator(M)
            if x0 is not None:
                probe.ksp.setConvergenceHistory(max_it + 1, reset=True)
            count = _solve(probe, row)
            if x0 is not None:  # ‖b‖ in the KSP's norm, then the history from x0
                target = rtol * probe.ksp.getConvergenceHistory()[0]
                probe.rtol = rtol * 1e-3
                _solve(probe, row - M @ x0[i])
                history = probe.ksp.getConvergenceHistory()
                probe.rtol = rtol
                reached = np.flatnonzero(history <= target)
                count = int(reached[0]) if len(reached) else count
            iterations.append(count)
    return max(iterations)


def _array(value) -> np.ndarray:
    """A numpy or torch array (any device, with or without gradients) as float64 numpy."""
    if hasattr(value, "detach"):  # a torch tensor, without importing torch
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


def _operators(A, theta, rows: int):
    """``i -> the operator of row i``: ``A.matrix(θ)`` of a parametric `A` (row i's own,
    made when asked, for a (B, p) θ whose rows match those of b), else `A` itself."""
    parametric = callable(getattr(A, "matrix", None)) and hasattr(A, "n_params")
    if not parametric:
        if theta is not None:
            raise InputError("theta= is only meaningful for a ParametricMatrix A")
        return lambda i: A
    if theta is None:
        raise InputError("A is a ParametricMatrix: pass its parameters as theta=")
    theta = _array(theta)
    if theta.ndim == 1:
        M = A.matrix(theta)
        return lambda i: M
    if theta.ndim != 2 or len(theta) != rows:
        raise InputError(
            f"theta of shape {theta.shape} needs b of shape ({len(theta)}, n), one row per "
            f"operator; b has {rows} rows"
        )
    return lambda i: A.matrix(theta[i])


def _solve(probe: KSPSolver, row: np.ndarray) -> int:
    sol = probe.solve(row)
    if not sol.converged:
        raise SolverError(
            f"the solver did not reach rtol={probe.rtol} in {probe.max_it} iterations "
            f"({sol.reason}); K_full is undefined",
            reason=sol.reason,
        )
    return sol.iterations
