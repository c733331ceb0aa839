"""K_full: the iterations a solver needs to converge on a representative system.

PRDP's start, step and cap come from this probe (`prdp_petsc.PRDP.for_problem`), and
full fidelity means "capped at K_full".  The probe runs on a clone of the caller's
solver, so its options (and the command line's, under its prefix) apply.  Besides the
count it measures how far the solve capped at a fraction of K_full lands from the
converged one (`KFull.errors`): where a capped solve is far off, training at that cap
can do damage that no later refinement undoes, so PRDP does not start there.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from .results import SolverError
from .solver import KSPSolver

__all__ = ["PROBED_FRACTIONS", "KFull", "find_k_full"]

#: the caps, as fractions of K_full (rounded up), at which the probe measures the error of
#: the capped solve (`KFull.errors`): PRDP's levels below K_full
PROBED_FRACTIONS = (1 / 8, 1 / 4, 1 / 2)


class KFull(int):
    """K_full, as `find_k_full` measured it: an ``int`` that also carries `errors`.

    Attributes
    ----------
    errors : dict of int to float
        ``{k: ‖x_k − x‖ / ‖x‖}`` at the caps ``ceil(f K_full)`` of `PROBED_FRACTIONS`:
        the relative error of the solve capped at k (fixed mode, from the problem's
        start) against the converged x, the largest over the probed right-hand sides.
        Arithmetic on a `KFull` gives a plain ``int`` (``int(k_full)`` for storage where
        only plain types may go, such as a ``torch.load(weights_only=True)`` checkpoint).
    """

    errors: dict[int, float]

    def __new__(cls, value: int, errors: dict[int, float] | None = None) -> KFull:
        self = super().__new__(cls, value)
        self.errors = dict(errors or {})
        return self

    def __reduce__(self):
        return (KFull, (int(self), self.errors))


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
    KFull
        K_full (an ``int``), with the relative error of the solve capped at K_full/8,
        /4 and /2 (`KFull.errors`, one more capped solve at each; `PRDP.for_problem`
        starts where that error is small).

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
    iterations, M, solved = [], None, []
    # a probe that stops short raises its own error below: no NotConvergedWarning first
    with solver.clone(max_it=max_it, rtol=rtol, atol=0.0, not_converged="ignore") as probe:
        for i, row in enumerate(b):
            if (row_operator := operator_of(i)) is not M:  # one operator: set once
                M = row_operator
                probe.set_operator(M)
            if x0 is not None:
                probe.ksp.setConvergenceHistory(max_it + 1, reset=True)
            count, x = _solve(probe, row)
            start = None
            if x0 is not None:  # ‖b‖ in the KSP's norm, then the history from x0
                target = rtol * probe.ksp.getConvergenceHistory()[0]
                probe.rtol = rtol * 1e-3
                start = row - M @ x0[i]
                _, dx = _solve(probe, start)
                x = x0[i] + dx
                history = probe.ksp.getConvergenceHistory()
                probe.rtol = rtol
                reached = np.flatnonzero(history <= target)
                count = int(reached[0]) if len(reached) else count
            iterations.append(count)
            solved.append((M, row if start is None else start, x))
        k_full = max(iterations)
        errors = _capped_errors(probe, solved, k_full, x0)
    return KFull(k_full, errors)


def _capped_errors(probe: KSPSolver, solved: list, k_full: int, x0) -> dict[int, float]:
    """``{k: largest ‖x_k − x‖ / ‖x‖}`` over the probed rows, k = ceil(f K_full) for f in
    `PROBED_FRACTIONS` (below K_full), x_k the solve capped at k in fixed mode; empty
    where every converged x is zero (nothing to measure an error against)."""
    caps = sorted({max(1, math.ceil(k_full * f)) for f in PROBED_FRACTIONS} - {k_full})
    errors: dict[int, float] = {}
    probe.rtol, probe.atol = 0.0, 0.0
    M = None
    for i, (operator, rhs, x) in enumerate(solved):
        if operator is not M:
            M = operator
            probe.set_operator(M)
        scale = float(np.linalg.norm(x))
        if scale == 0:
            continue
        converged = x if x0 is None else x - x0[i]  # what the solve from the start reaches
        for k in caps:
            probe.max_it = k
            x_k = probe.solve(rhs).value
            error = float(np.linalg.norm(x_k - converged)) / scale
            errors[k] = max(errors.get(k, 0.0), error)
    return errors


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


def _solve(probe: KSPSolver, row: np.ndarray) -> tuple[int, np.ndarray]:
    sol = probe.solve(row)
    if not sol.converged:
        raise SolverError(
            f"the solver did not reach rtol={probe.rtol} in {probe.max_it} iterations "
            f"({sol.reason}); K_full is undefined",
            reason=sol.reason,
        )
    return sol.iterations, sol.value
