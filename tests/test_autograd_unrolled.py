"""Unrolled mode fails, stops and reports like implicit mode (PETSc's own KSPSolve).

The torch iteration repeats PETSc's convergence test and breakdown checks, so the
same problem gives the same `SolverError` reason, the same outcome (iterations,
reason and residual norm of every sample) and the same iterate in both modes; adjoint
statistics count a backward only when it runs.
"""

import re
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from _core import fd_poisson, interior_operator, randn, random_theta, unit_square
from torch.autograd import gradgradcheck

import prdp_petsc as pp

#: damped Jacobi with spectral radius > 1 on the 2D Laplacian: diverges
DIVERGENT = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 3.0}
MODES = ("implicit", "unrolled")
CG = {"ksp_type": "cg", "pc_type": "jacobi"}


def run_both(M, b, options, **solver_kw):
    """Each mode's outcome and x or SolverError: the `LinearSolution` of a call that
    returned, or what a failed call's error reports (`reported`)."""
    out = {}
    for mode in MODES:
        solver = pp.KSPSolver(options, **solver_kw)
        try:
            sol = pp.solve(M, b, solver, mode=mode, return_solution=True)
        except pp.SolverError as err:
            out[mode] = (reported(err), err)
        else:
            out[mode] = (sol, sol.value)
    return out


def reported(err: pp.SolverError) -> SimpleNamespace:
    """The failing sample's reason, iterations and residual norm (None: not computed),
    as the error names them: "... after 12 iterations (cg/jacobi, residual 1.234e+05)"."""
    message = str(err)
    iterations = re.search(r"after (\d+) iterations", message)
    norm = re.search(r"residual (not computed|[^),]+)\)", message)
    assert iterations and norm, message
    residual = None if norm[1] == "not computed" else float(norm[1])
    return SimpleNamespace(reason=err.reason, iterations=int(iterations[1]), residual_norm=residual)


def indefinite_pc():
    M = fd_poisson(6).tolil()
    M[0, 0] = -M[0, 0]
    return sp.csr_matrix(M)


@pytest.mark.parametrize(
    ("matrix", "options", "solver_kw", "seed", "reason"),
    [
        (fd_poisson(8), DIVERGENT, {"max_it": 200}, 1, "DIVERGED_DTOL"),
        (fd_poisson(8), DIVERGENT, {"max_it": 200, "divtol": 10.0}, 1, "DIVERGED_DTOL"),
        # divtol·‖r₀‖ overflows: the residual norm reaches Inf first
        (fd_poisson(8), DIVERGENT, {"max_it": 2000, "divtol": 1e308}, 1, "DIVERGED_NANORINF"),
        # Jacobi with one negative diagonal entry: zᵀr changes sign
        (indefinite_pc(), CG, {"max_it": 100, "rtol": 1e-10}, 0, "DIVERGED_INDEFINITE_PC"),
        # eigenvalues of both signs: pᵀAp changes sign
        ((fd_poisson(6) - 180.0 * sp.eye(36)).tocsr(), {"ksp_type": "cg", "pc_type": "none"},
         {"max_it": 100, "rtol": 1e-10}, 1, "DIVERGED_INDEFINITE_MAT"),
    ],
    ids=["dtol", "divtol", "inf", "indefinite-pc", "indefinite-mat"],
)  # fmt: skip
def test_divergence_raises_the_same_error_in_both_modes(matrix, options, solver_kw, seed, reason):
    b = 1e3 * randn(matrix.shape[0], seed=seed)
    out = run_both(matrix, b, options, **solver_kw)
    for mode in MODES:
        last, err = out[mode]
        assert isinstance(err, pp.SolverError), (mode, last)
        assert err.reason == reason and reason in str(err), mode
        assert last.reason == reason
    implicit, unrolled = out["implicit"][0], out["unrolled"][0]
    assert unrolled.iterations == implicit.iterations < solver_kw["max_it"]
    # the messages give four significant digits
    assert unrolled.residual_norm == pytest.approx(implicit.residual_norm, rel=1e-3)


def test_custom_divtol_stops_earlier():
    b = randn(64, seed=1)
    default = run_both(fd_poisson(8), b, DIVERGENT, max_it=200)["unrolled"][0]
    tight = run_both(fd_poisson(8), b, DIVERGENT, max_it=200, divtol=10.0)["unrolled"][0]
    assert 0 < tight.iterations < default.iterations


def test_divergence_in_a_batch_reports_the_first_failing_column():
    """Column 1 diverges, columns 0 and 2 (zero right-hand sides) converge at once."""
    b = torch.zeros(3, 64, dtype=torch.float64)
    b[1] = randn(64, seed=2)
    solver = pp.KSPSolver(DIVERGENT, max_it=200)
    with pytest.raises(pp.SolverError, match="sample 1 of the batch") as err:
        pp.solve(fd_poisson(8), b, solver, mode="unrolled")
    assert err.value.reason == "DIVERGED_DTOL" and reported(err.value).iterations > 0


RICHARDSON = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.6}


@pytest.mark.parametrize(
    "options",
    [
        CG,
        {**CG, "ksp_norm_type": "unpreconditioned"},
        {**CG, "ksp_norm_type": "natural"},
        {**CG, "ksp_norm_type": "none"},
        {"ksp_type": "cg", "pc_type": "none"},
        RICHARDSON,
        {**RICHARDSON, "ksp_norm_type": "unpreconditioned"},
        {**RICHARDSON, "ksp_norm_type": "none"},
        {"ksp_type": "richardson", "pc_type": "none", "ksp_richardson_scale": 0.005},
    ],
    ids=lambda o: "-".join(str(v) for v in o.values()),
)
@pytest.mark.parametrize(("max_it", "rtol"), [(7, 0.0), (500, 1e-6)], ids=["fixed", "rtol"])
def test_the_outcome_matches_implicit(options, max_it, rtol):
    """Iterations, reason and residual norm (of the KSP's norm type) of every column."""
    if rtol and options.get("ksp_norm_type") == "none":
        pytest.skip("no norm, no rtol test: 500 iterations would run far past convergence")
    b = randn(2, 36, seed=3)
    out = run_both(fd_poisson(6), b, options, max_it=max_it, rtol=rtol)
    implicit, unrolled = out["implicit"][0], out["unrolled"][0]
    assert unrolled.iterations.tolist() == implicit.iterations.tolist()
    assert unrolled.reason == implicit.reason
    if options.get("ksp_norm_type") == "none":  # no norm computed: None, never 0.0
        for sol in (unrolled, implicit):
            assert [s.residual_norm for s in sol.info] == [None, None]
    else:
        np.testing.assert_allclose(
            unrolled.residual_norm, implicit.residual_norm, rtol=1e-9, atol=1e-12
        )
    if rtol == 0.0 and options.get("ksp_norm_type") != "none":
        assert implicit.iterations.tolist() == [max_it] * 2
        assert implicit.reason == ["DIVERGED_MAX_IT"] * 2
    x_implicit, x_unrolled = out["implicit"][1], out["unrolled"][1]
    torch.testing.assert_close(x_unrolled, x_implicit, rtol=1e-10, atol=1e-12)


def test_tiny_right_hand_side_is_scaled_as_in_implicit_mode():
    """b ~ 1e-169: CG's zᵀr would underflow to 0 and stop at x = 0 without scaling."""
    b = randn(36, seed=4)
    tiny = b * 2.0**-560
    solver = pp.KSPSolver(CG, max_it=10)
    reference = pp.solve(fd_poisson(6), b, solver, mode="unrolled", return_solution=True)
    sol = pp.solve(fd_poisson(6), tiny, solver, mode="unrolled", return_solution=True)
    x_tiny = sol.value
    assert torch.equal(x_tiny, reference.value * 2.0**-560)
    assert sol.iterations == reference.iterations == 10
    assert sol.residual_norm == pytest.approx(reference.residual_norm * 2.0**-560)
    x_implicit = pp.solve(fd_poisson(6), tiny, pp.KSPSolver(CG, max_it=10))
    torch.testing.assert_close(x_tiny, x_implicit, rtol=1e-10, atol=0.0)


def test_adjoint_work_is_counted_only_when_backward_runs():
    solver = pp.KSPSolver(CG, max_it=5)
    b = randn(2, 36, seed=5, requires_grad=True)
    x = pp.solve(fd_poisson(6), b, solver, mode="unrolled")
    stats = solver.stats
    assert (stats.forward_solves, stats.forward_iterations) == (2, 10)
    assert (stats.adjoint_solves, stats.adjoint_iterations) == (0, 0)
    x.sum().backward()
    assert (stats.adjoint_solves, stats.adjoint_iterations) == (2, 10)
    assert b.grad is not None and torch.isfinite(b.grad).all()


def test_no_adjoint_work_without_backward_even_when_grad_is_enabled():
    solver = pp.KSPSolver(CG, max_it=4, rtol=1e-3)
    theta_free = randn(36, seed=6, requires_grad=True)
    # the graph is built, never used
    sol = pp.solve(fd_poisson(6), theta_free, solver, mode="unrolled", return_solution=True)
    assert solver.stats.adjoint_solves == 0 and solver.stats.adjoint_iterations == 0
    assert solver.stats.forward_iterations == sol.iterations > 0


def test_unrolled_second_derivatives_are_exact():
    """The unrolled graph is twice differentiable in b and θ (its SpMV backward too)."""
    A = interior_operator(unit_square(2), "P1").A_II
    solver = pp.KSPSolver(CG, max_it=3)
    b = randn(A.shape[0], seed=7, requires_grad=True)
    theta = random_theta(A.n_params, seed=8, requires_grad=True)
    assert gradgradcheck(lambda b, t: pp.solve(A, b, solver, theta=t, mode="unrolled"), (b, theta))
