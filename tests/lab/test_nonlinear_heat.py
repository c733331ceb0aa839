"""Differentiable Newton and Picard solves (prdp_petsc.autograd.nonlinear) and the
nonlinear heat step they are built for (`NonlinearHeat` in demos/heat_nonlinear.py).

The gradient checks of docs/maths.md §6 on a nonlinear residual: gradcheck and a
Taylor rate >= 1.9 with converged inner and outer solves, the converged solution
against scipy's fsolve, Newton against Picard, and the failures that must raise.
"""

from pathlib import Path

import numpy as np
import pytest
import scipy.optimize
import scipy.sparse as sp
import skfem
import torch
from _core import observed_rate, randn, taylor_rate, unit_square
from skfem import BilinearForm, LinearForm
from skfem.helpers import dot, grad

import prdp_petsc as pp
from prdp_petsc.autograd.nonlinear import NonlinearProblem, newton_solve
from prdp_petsc.lab.training.scene import load_scene

SCENE = Path(__file__).resolve().parents[2] / "demos" / "heat_nonlinear.py"
NonlinearHeat = load_scene(SCENE).NonlinearHeat

GMRES = {"ksp_type": "gmres", "pc_type": "jacobi"}
TIGHT = {"rtol": 1e-13, "atol": 1e-14}  # outer loop to rounding level


def converged(options=GMRES, **kwargs):
    return pp.KSPSolver(options, max_it=1000, rtol=1e-14, atol=1e-50, **kwargs)


def heat_inputs(refine=2, dt=0.05, seed=0):
    """A heat step with Dirichlet data and a source: (problem, u0, (u_prev, f, g, α))."""
    basis = unit_square(refine)
    heat = NonlinearHeat(basis, dt)
    rng = np.random.default_rng(seed)
    x, y = basis.doflocs
    u_prev = torch.from_numpy(2 * np.sin(np.pi * x) * np.sin(np.pi * y) + 0.1 * x)
    f = torch.from_numpy(rng.random(basis.N))
    g = torch.from_numpy(0.1 * x[heat.boundary])
    alpha = torch.tensor(2.0, dtype=torch.float64)
    return heat, u_prev[heat.interior].clone(), (u_prev, f, g, alpha)


def test_jacobian_is_the_derivative_of_the_residual():
    """|R(u + εv) − R(u) − ε J v| falls like ε², so the κ'(u) term is right."""
    heat, u0, params = heat_inputs(refine=3)
    p = [t.numpy() for t in params]
    u, v = u0.numpy() + 0.3, randn(heat.n, seed=1).numpy()
    r0, J = heat.residual(u, *p), heat.jacobian(u, *p)
    eps = 1e-2 * 0.5 ** np.arange(5)
    rem = [np.linalg.norm(heat.residual(u + e * v, *p) - r0 - e * (J @ v)) for e in eps]
    assert observed_rate(eps, rem) >= 1.9
    assert abs(J - J.T).max() > 1e-3  # the Newton Jacobian is not symmetric
    P = heat.picard(u, *p)
    assert abs(P - P.T).max() == 0  # the Picard operator is


def test_converged_solution_matches_scipy_fsolve():
    heat, u0, params = heat_inputs(refine=3)
    solution = newton_solve(heat, u0, *params, solver=converged(), **TIGHT)
    assert solution.converged and solution.iterations <= 8
    p = [t.numpy() for t in params]
    reference = scipy.optimize.fsolve(
        heat.residual,
        u0.numpy(),
        args=tuple(p),
        fprime=lambda u, *q: heat.jacobian(u, *q).toarray(),
        xtol=1e-13,
    )
    np.testing.assert_allclose(solution.value.numpy(), reference, rtol=0, atol=1e-10)
    assert np.linalg.norm(heat.residual(solution.value.numpy(), *p)) < 1e-12


def test_newton_and_picard_reach_the_same_solution_and_gradient():
    """Picard: CG on the symmetric Picard operator, GMRES adjoint with the Jacobian."""
    heat, u0, params = heat_inputs(refine=3)
    u_prev = params[0].clone().requires_grad_(True)
    results = {}
    for method in ("newton", "picard"):
        forward = converged(
            {"ksp_type": "cg", "pc_type": "jacobi"} if method == "picard" else GMRES
        )
        adjoint = converged()
        sol = newton_solve(
            heat,
            u0,
            u_prev,
            *params[1:],
            solver=forward,
            adjoint_solver=adjoint,
            method=method,
            max_newton=100,
            **TIGHT,
        )
        (grad,) = torch.autograd.grad((sol.value**2).sum(), u_prev)
        results[method] = (sol, grad)
    newton, picard = results["newton"][0], results["picard"][0]
    assert newton.converged and picard.converged
    assert newton.iterations < picard.iterations  # quadratic against linear convergence
    np.testing.assert_allclose(newton.value.detach(), picard.value.detach(), atol=1e-11)
    np.testing.assert_allclose(results["newton"][1], results["picard"][1], rtol=1e-8, atol=1e-12)


def test_gradcheck_all_inputs():
    heat, u0, params = heat_inputs(refine=2)
    inputs = tuple(t.clone().requires_grad_(True) for t in params)
    solver = converged()

    def step(*p):
        return newton_solve(heat, u0, *p, solver=solver, **TIGHT).value

    assert torch.autograd.gradcheck(step, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


def test_taylor_rate_converged():
    heat, u0, (u_prev, f, g, alpha) = heat_inputs(refine=3)
    w = randn(heat.n, seed=3)
    solver = converged()
    sizes = [u_prev.numel(), f.numel(), g.numel(), 1]
    m = torch.cat([u_prev, f, g, alpha.reshape(1)])
    h = randn(len(m), seed=4)

    def J(m):
        a, b, c, d = torch.split(m, sizes)
        u = newton_solve(heat, u0, a, b, c, d[0], solver=solver, **TIGHT).value
        return (u * w).sum() + 0.5 * (u**2).sum()

    assert taylor_rate(J, m, h) >= 1.9


def test_truncated_loop_returns_the_iterate_and_counts_the_work():
    heat, u0, params = heat_inputs(refine=3)
    solver = pp.KSPSolver(GMRES, max_it=3)  # fixed mode: 3 KSP iterations per step
    solution = newton_solve(heat, u0, *params, solver=solver, max_newton=4)
    assert solution.reason == "DIVERGED_MAX_IT" and not solution.converged
    assert solution.iterations == 4 and solution.inner_iterations == 12
    assert solver.stats.forward_iterations == 12 and len(solution.residual_norms) == 5
    assert solution.residual_norms[-1] < solution.residual_norms[0]
    with pytest.raises(pp.SolverError, match="max_newton=4") as err:
        newton_solve(heat, u0, *params, solver=solver, max_newton=4, require_convergence=True)
    assert err.value.reason == "NEWTON_DIVERGED_MAX_IT"


def cube_root_problem(n=5):
    """R(u) = u^(1/3) componentwise: the Newton step is u ↦ −2u, the residual grows."""
    return NonlinearProblem(
        n=n,
        residual=np.cbrt,
        jacobian=lambda u: sp.diags(np.abs(u) ** (-2 / 3) / 3).tocsr(),
        jacobian_symmetric=True,
    )


def test_diverging_newton_raises():
    problem = cube_root_problem()
    solver = converged({"ksp_type": "cg", "pc_type": "jacobi"})
    u0 = torch.linspace(0.5, 1.0, 5, dtype=torch.float64)
    with pytest.raises(pp.SolverError, match="divtol=10") as err:
        newton_solve(problem, u0, solver=solver, divtol=10.0)
    assert err.value.reason == "NEWTON_DIVERGED_DTOL"
    # |R| grows by 2^(1/3) per step: divtol 10 is passed after ceil(3 log2 10) = 10 steps
    assert solver.stats.forward_solves == 10


def test_nan_residual_raises():
    problem = NonlinearProblem(n=3, residual=np.log, jacobian=lambda u: sp.diags(1 / u).tocsr())
    u0 = torch.tensor([-1.0, 1.0, 2.0], dtype=torch.float64)
    with pytest.raises(pp.SolverError) as err, np.errstate(invalid="ignore"):
        newton_solve(problem, u0, solver=converged())
    assert err.value.reason == "NEWTON_DIVERGED_FNORM_NAN"


def test_only_needed_gradients_are_computed():
    heat, u0, params = heat_inputs(refine=2)
    calls = []

    class Spy:
        n, jacobian_symmetric, picard_symmetric = heat.n, False, True
        residual, jacobian = heat.residual, heat.jacobian

        def vjp(self, u, lam, *p, needs):
            calls.append(needs)
            return heat.vjp(u, lam, *p, needs=needs)

    solver = converged()
    newton_solve(Spy(), u0, *params, solver=solver, **TIGHT)
    assert solver.stats.adjoint_solves == 0 and not calls  # nothing requires grad
    f = params[1].clone().requires_grad_(True)
    sol = newton_solve(Spy(), u0, params[0], f, *params[2:], solver=solver, **TIGHT)
    sol.value.sum().backward()
    assert calls == [(False, True, False, False)] and solver.stats.adjoint_solves == 1


def test_double_backward_raises():
    heat, u0, params = heat_inputs(refine=2)
    alpha = params[3].clone().requires_grad_(True)
    u = newton_solve(heat, u0, *params[:3], alpha, solver=converged(), **TIGHT).value
    (grad,) = torch.autograd.grad((u**2).sum() + alpha**3, alpha, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        torch.autograd.grad(grad, alpha)


def test_symmetric_only_krylov_on_the_newton_jacobian_is_refused():
    heat, u0, params = heat_inputs(refine=2)
    cg = converged({"ksp_type": "cg", "pc_type": "jacobi"})
    with pytest.raises(ValueError, match="needs a symmetric operator"):
        newton_solve(heat, u0, *params, solver=cg)
    u_prev = params[0].clone().requires_grad_(True)
    with pytest.raises(ValueError, match="Jacobian is not symmetric"):  # CG adjoint on J
        newton_solve(heat, u0, u_prev, *params[1:], solver=cg, method="picard")
    declared = converged(structure=pp.Structure(symmetric=True))
    with pytest.raises(ValueError, match=r"Structure\(symmetric=True\)"):
        newton_solve(heat, u0, u_prev, *params[1:], solver=declared)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"method": "secant"}, "method"),
        ({"max_newton": 0}, "max_newton"),
        ({"rtol": -1.0}, "rtol"),
        ({"divtol": 0.5}, "divtol"),
    ],
)
def test_bad_settings_are_refused(kwargs, match):
    heat, u0, params = heat_inputs(refine=2)
    with pytest.raises(ValueError, match=match):
        newton_solve(heat, u0, *params, solver=converged(), **kwargs)


def test_nonlinear_heat_refuses_a_bad_time_step_and_a_basis_not_p1():
    basis = skfem.Basis(skfem.MeshTri(), skfem.ElementTriP1())
    with pytest.raises(ValueError, match="dt"):
        NonlinearHeat(basis, dt=0.0)
    with pytest.raises(ValueError, match="P1"):
        NonlinearHeat(skfem.Basis(skfem.MeshTri(), skfem.ElementTriP2()), dt=0.1)


# The forms of the step as scikit-fem writes them, with the iterate as the field w.u and
# the basis' own quadrature (exact for these P1 forms): the reference of the demo's
# element-by-element assembly.
@LinearForm
def flux_form(v, w):
    return (1.0 + w.alpha * w.u**2) * dot(grad(w.u), grad(v))


@LinearForm
def d_alpha_form(v, w):
    return w.u**2 * dot(grad(w.u), grad(v))


@BilinearForm
def picard_form(u, v, w):
    return u * v + w.dt * (1.0 + w.alpha * w.u**2) * dot(grad(u), grad(v))


@BilinearForm
def jacobian_form(u, v, w):
    kappa, d_kappa = 1.0 + w.alpha * w.u**2, 2.0 * w.alpha * w.u
    return u * v + w.dt * (kappa * dot(grad(u), grad(v)) + d_kappa * u * dot(grad(w.u), grad(v)))


@pytest.mark.parametrize(
    "element, mesh",
    [
        (skfem.ElementTriP1(), skfem.MeshTri.init_sqsymmetric().refined(2)),
        (skfem.ElementTetP1(), skfem.MeshTet().refined(2)),
        (skfem.ElementLineP1(), skfem.MeshLine().refined(4)),
    ],
    ids=["triangles", "tetrahedra", "lines"],
)
def test_p1_assembly_matches_the_scikit_fem_forms(element, mesh):
    """The residual, both operators and the g and α products of the element assembly."""
    basis, dt = skfem.Basis(mesh, element), 0.05
    heat = NonlinearHeat(basis, dt)
    I, B = heat.interior, heat.boundary
    rng = np.random.default_rng(3)
    u_i, lam = rng.standard_normal(heat.n), rng.standard_normal(heat.n)
    u_prev, f, g = rng.standard_normal(basis.N), rng.random(basis.N), rng.random(len(B))
    p = (u_prev, f, g, 1.7)
    u = heat.expand(u_i, g)
    w = {"u": basis.interpolate(u), "alpha": 1.7, "dt": dt}
    residual = heat.M[I] @ (u - u_prev - dt * f) + dt * flux_form.assemble(basis, **w)[I]
    np.testing.assert_allclose(heat.residual(u_i, *p), residual, atol=1e-12)
    J = jacobian_form.assemble(basis, **w).tocsr()
    P = picard_form.assemble(basis, **w).tocsr()
    for mine, full in ((heat.jacobian(u_i, *p), J), (heat.picard(u_i, *p), P)):
        reference = full[I][:, I]
        assert mine.shape == reference.shape == (heat.n, heat.n)
        assert abs(mine - reference).max() < 1e-12 * abs(reference).max()
    _, _, d_g, d_alpha = heat.vjp(u_i, lam, *p, needs=(False, False, True, True))
    np.testing.assert_allclose(d_g, J[I][:, B].T @ lam, rtol=1e-11, atol=1e-12)
    reference = dt * (d_alpha_form.assemble(basis, **w)[I] @ lam)
    np.testing.assert_allclose(d_alpha, reference, rtol=1e-11, atol=1e-12)
