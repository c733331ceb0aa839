"""`newton_solve` on a problem built from numpy callables (no scene physics).

The nonlinear heat step of the heat_nonlinear scene is tested in
``tests/lab/test_nonlinear_heat.py``; these tests need only the library.
"""

import numpy as np
import pytest
import scipy.optimize as so
import torch
from _core import reaction_problem

import prdp_petsc as pp
from prdp_petsc.errors import NonFiniteError

CG = {"ksp_type": "cg", "pc_type": "jacobi"}


def inputs(n=6, seed=0):
    problem = reaction_problem(n)
    f = torch.from_numpy(np.random.default_rng(seed).random(problem.n) * 10)
    c = torch.tensor(5.0, dtype=torch.float64)
    return problem, f, c


def converged():
    return pp.KSPSolver(CG, max_it=500, rtol=1e-14, atol=1e-50)


def test_converged_newton_solves_the_residual_as_scipy_does():
    problem, f, c = inputs()
    with converged() as solver:
        sol = pp.newton_solve(problem, None, f, c, solver=solver, rtol=1e-13)
    assert sol.reason.startswith("CONVERGED") and sol.iterations < 10
    assert sol.converged and sol.residual_norm == sol.residual_norms[-1] <= 1e-10
    ref = so.root(lambda u: problem.residual(u, f.numpy(), 5.0), np.zeros(problem.n), tol=1e-14)
    assert np.linalg.norm(sol.value.numpy() - ref.x) <= 1e-10 * np.linalg.norm(ref.x)


def test_implicit_gradient_passes_gradcheck():
    problem, f, c = inputs(n=4)
    f.requires_grad_(True)
    c.requires_grad_(True)
    with converged() as solver:

        def u_star(f, c):
            return pp.newton_solve(problem, None, f, c, solver=solver, rtol=1e-13).value

        assert torch.autograd.gradcheck(u_star, (f, c), eps=1e-6, atol=1e-7)


def test_a_capped_inner_solve_counts_its_iterations():
    problem, f, c = inputs()
    with pp.KSPSolver(CG, max_it=3) as solver:
        sol = pp.newton_solve(problem, None, f, c, solver=solver, max_newton=4, rtol=0.0)
    assert sol.iterations == 4 and sol.inner_iterations == 4 * 3


def test_non_finite_inputs_raise():
    problem, f, c = inputs()
    with converged() as solver:
        with pytest.raises(NonFiniteError):
            pp.newton_solve(
                problem,
                torch.full((problem.n,), torch.nan, dtype=torch.float64),
                f,
                c,
                solver=solver,
            )
        with pytest.raises(NonFiniteError):
            pp.newton_solve(problem, None, f * torch.inf, c, solver=solver)


def test_double_backward_raises():
    problem, f, c = inputs(n=4)
    f.requires_grad_(True)
    with converged() as solver:
        u = pp.newton_solve(problem, None, f, c, solver=solver, rtol=1e-13).value
        (g,) = torch.autograd.grad(u.square().sum(), f, create_graph=True)
        with pytest.raises(RuntimeError, match="differentiate twice"):
            g.sum().backward()
