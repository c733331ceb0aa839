"""Gradients through capped PETSc solves: gradcheck, Taylor tests, unrolled vs implicit.

All in float64.  With converged solves the implicit (adjoint) gradient is the true
derivative and must pass `torch.autograd.gradcheck` and a second-order Taylor test;
with a small fixed K it is not the derivative of the truncated solver, which the
Taylor rate (≈ 1 instead of 2) shows, while the unrolled gradient is (rate 2).
"""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import skfem
import torch
from _core import (
    CONVERGED,
    interior_operator,
    randn,
    random_theta,
    taylor_rate,
    unit_square,
)
from torch.autograd import gradcheck

import prdp_petsc as pp

CG_JACOBI = {"ksp_type": "cg", "pc_type": "jacobi"}
GMRES_ILU = {"ksp_type": "gmres", "pc_type": "ilu"}


def converged_cg():
    return pp.KSPSolver(CG_JACOBI, **CONVERGED)


# -- gradcheck ---------------------------------------------------------------------------


@pytest.mark.parametrize("coefficient", ["P0", "P1"])
def test_gradcheck_b_and_theta(coefficient):
    D = interior_operator(unit_square(3), coefficient)
    A = D.A_II
    solver = converged_cg()
    b = randn(A.shape[0], seed=1, requires_grad=True)
    theta = random_theta(A.n_params, requires_grad=True)
    assert gradcheck(lambda b, t: pp.solve(A, b, solver, theta=t), (b, theta))
    assert solver.stats.adjoint_solves > 0  # the adjoint KSP produced these gradients


@pytest.mark.parametrize("coefficient", ["P0", "P1"])
def test_gradcheck_on_shipped_mesh(coefficient):
    """The sliver mesh (a few hundred vertices, thin triangles): P0 and P1 coefficients."""
    basis = skfem.Basis(pp.load_mesh("sliver"), skfem.ElementTriP1())
    D = interior_operator(basis, coefficient)
    A = D.A_II
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, **CONVERGED)
    b = randn(A.shape[0], seed=2, requires_grad=True)
    theta = random_theta(A.n_params, seed=3, requires_grad=True)
    assert gradcheck(lambda b, t: pp.solve(A, b, solver, theta=t), (b, theta), fast_mode=True)


@pytest.mark.parametrize("coefficient", ["P0", "P1"])
def test_gradcheck_dirichlet_values(coefficient):
    """u_B = g is differentiable: gradients in f, g and θ through the lifting f_I − A_IB(θ) g."""
    basis = unit_square(2)
    D = interior_operator(basis, coefficient)
    solver = converged_cg()
    f = randn(basis.N, seed=4, requires_grad=True)
    g = randn(len(D.boundary), seed=5, requires_grad=True)
    theta = random_theta(D.A_II.n_params, seed=6, requires_grad=True)
    assert gradcheck(lambda f, g, t: D.solve(f, g, solver, theta=t), (f, g, theta))


def test_gradcheck_dirichlet_values_constant_matrix():
    basis = unit_square(2)
    theta = random_theta(basis.mesh.nelements).numpy()
    D = pp.Dirichlet(pp.diffusion_operator(basis).matrix(theta), basis.get_dofs())
    solver = converged_cg()
    f = randn(2, basis.N, seed=7, requires_grad=True)  # a batch of right-hand sides
    g = randn(len(D.boundary), seed=8, requires_grad=True)
    assert gradcheck(lambda f, g: D.solve(f, g, solver), (f, g))


def test_dirichlet_gradient_in_g_is_lifting_adjoint():
    """∂L/∂g = w_B − A_IBᵀ λ with Aᵀ_II λ = w_I, for L = ⟨w, u⟩."""
    basis = unit_square(3)
    D = interior_operator(basis)
    theta = random_theta(D.A_II.n_params)
    g = randn(len(D.boundary), seed=9, requires_grad=True)
    f = randn(basis.N, seed=10)
    w = randn(basis.N, seed=11)
    (D.solve(f, g, converged_cg(), theta=theta) @ w).backward()
    th = theta.numpy()
    lam = spla.spsolve(D.A_II.matrix(th).T.tocsc(), w.numpy()[D.interior])
    expected = w.numpy()[D.boundary] - D.A_IB.matrix(th).T @ lam
    np.testing.assert_allclose(g.grad.numpy(), expected, rtol=1e-9, atol=1e-12)


def test_gradcheck_batch():
    """b of shape (B, n) shares one operator; ∂L/∂θ sums the per-sample contributions."""
    D = interior_operator(unit_square(3), "P1")
    A = D.A_II
    solver = converged_cg()
    b = randn(3, A.shape[0], seed=12, requires_grad=True)
    theta = random_theta(A.n_params, seed=13, requires_grad=True)
    assert gradcheck(lambda b, t: pp.solve(A, b, solver, theta=t), (b, theta))


def test_batch_theta_gradient_is_sum_over_samples():
    D = interior_operator(unit_square(3))
    A = D.A_II
    solver = converged_cg()
    b = randn(4, A.shape[0], seed=14)
    w = randn(4, A.shape[0], seed=15)
    theta = random_theta(A.n_params, requires_grad=True)
    (g_batch,) = torch.autograd.grad((pp.solve(A, b, solver, theta=theta) * w).sum(), theta)
    g_each = sum(
        torch.autograd.grad(pp.solve(A, b[i], solver, theta=theta) @ w[i], theta)[0]
        for i in range(4)
    )
    torch.testing.assert_close(g_batch, g_each, rtol=1e-12, atol=1e-14)


def test_gradcheck_nonsymmetric():
    """Advection–diffusion: the adjoint uses Aᵀ, so gradcheck passes only if it is a transpose."""
    D = interior_operator(unit_square(3), advect=True)
    A = D.A_II
    theta = random_theta(A.n_params, seed=16, requires_grad=True)
    M = A.matrix(theta.detach().numpy())
    assert abs(M - M.T).max() > 1.0  # really non-symmetric
    solver = pp.KSPSolver(GMRES_ILU, **CONVERGED)
    b = randn(A.shape[0], seed=17, requires_grad=True)
    assert gradcheck(lambda b, t: pp.solve(A, b, solver, theta=t), (b, theta))


def test_nonsymmetric_adjoint_is_true_transpose():
    """∂⟨w, A⁻¹b⟩/∂b = A⁻ᵀ w, which differs clearly from A⁻¹ w."""
    D = interior_operator(unit_square(3), advect=True)
    A = D.A_II
    theta = random_theta(A.n_params, seed=18)
    M = A.matrix(theta.numpy()).tocsc()
    b = randn(A.shape[0], seed=19, requires_grad=True)
    w = randn(A.shape[0], seed=20)
    (pp.solve(A, b, pp.KSPSolver(GMRES_ILU, **CONVERGED), theta=theta) @ w).backward()
    transpose = spla.spsolve(M.T.tocsc(), w.numpy())
    wrong = spla.spsolve(M, w.numpy())
    np.testing.assert_allclose(b.grad.numpy(), transpose, rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(wrong - transpose) > 0.1 * np.linalg.norm(transpose)


# -- Taylor tests -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def taylor_problem():
    D = interior_operator(unit_square(3))
    A = D.A_II
    n, p = A.shape[0], A.n_params
    b, d = randn(n, seed=21), randn(n, seed=22)
    theta, h = random_theta(p, seed=23), randn(p, seed=24)

    def loss(solver, mode="implicit"):
        return lambda t: 0.5 * ((pp.solve(A, b, solver, theta=t, mode=mode) - d) ** 2).sum()

    return loss, theta, h


def test_taylor_converged(taylor_problem):
    loss, theta, h = taylor_problem
    assert taylor_rate(loss(converged_cg()), theta, h) >= 1.9


def test_taylor_dirichlet_values():
    basis = unit_square(3)
    D = interior_operator(basis, "P1")
    theta = random_theta(D.A_II.n_params, seed=25)
    f, w = randn(basis.N, seed=26), randn(basis.N, seed=27)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, **CONVERGED)

    def J(g):
        u = D.solve(f, g, solver, theta=theta)
        return (u * w).sum() + 0.5 * (u**2).sum()

    g0 = randn(len(D.boundary), seed=28)
    assert taylor_rate(J, g0, randn(len(D.boundary), seed=29)) >= 1.9


TAYLOR_RATES: dict = {}


def test_taylor_rate_degrades_with_small_K(taylor_problem, record_property):
    """Implicit gradients of a truncated CG are inconsistent: rate ≈ 1 at small fixed K.

    The unrolled gradient is the exact derivative of the K-step map, so it keeps rate 2
    at every K; the implicit one recovers rate 2 once K reaches convergence.
    """
    loss, theta, h = taylor_problem
    for K in (1, 2, 4, 8, 16, 32):
        solver = pp.KSPSolver(CG_JACOBI, max_it=K)
        TAYLOR_RATES[K] = {
            "implicit": taylor_rate(loss(solver), theta, h),
            "unrolled": taylor_rate(loss(solver, "unrolled"), theta, h),
        }
    solver = converged_cg()
    TAYLOR_RATES["converged"] = {"implicit": taylor_rate(loss(solver), theta, h)}
    stats = solver.stats  # the converged solves' iterations, on average
    TAYLOR_RATES["converged"]["K"] = round(stats.forward_iterations / stats.forward_solves)
    record_property("taylor_rates", TAYLOR_RATES)
    print("Taylor rates (CG+Jacobi, fixed K):", TAYLOR_RATES)

    for K in (1, 2, 4):
        assert 0.8 < TAYLOR_RATES[K]["implicit"] < 1.2, (K, TAYLOR_RATES[K])
    assert TAYLOR_RATES[8]["implicit"] < 1.5  # still inconsistent
    for K in (1, 2, 4, 8, 16, 32):
        assert TAYLOR_RATES[K]["unrolled"] >= 1.9, (K, TAYLOR_RATES[K])
    assert TAYLOR_RATES["converged"]["implicit"] >= 1.9
    assert TAYLOR_RATES[32]["implicit"] >= 1.9  # 49 unknowns: K = 32 has converged


def test_gradcheck_fails_for_truncated_implicit_passes_for_unrolled():
    D = interior_operator(unit_square(3))
    A = D.A_II
    solver = pp.KSPSolver(CG_JACOBI, max_it=3)
    theta = random_theta(A.n_params, seed=30, requires_grad=True)
    b = randn(A.shape[0], seed=31)

    def run(mode):
        return gradcheck(
            lambda t: pp.solve(A, b, solver, theta=t, mode=mode),
            (theta,),
            raise_exception=False,
            fast_mode=True,
        )

    assert run("unrolled")
    assert not run("implicit")


# -- unrolled vs implicit ---------------------------------------------------------------


@pytest.mark.parametrize("K", [1, 2, 5, 20])
def test_unrolled_equals_implicit_for_damped_jacobi(K):
    """Richardson+Jacobi from zero with A fixed: K transposed sweeps are the exact adjoint.

    The operator is non-symmetric, so this also checks that the adjoint sweeps use Aᵀ.
    """
    A = interior_operator(unit_square(3), advect=True).A_II
    M = A.matrix(random_theta(A.n_params, seed=42).numpy())  # a constant scipy matrix
    solver = pp.KSPSolver(
        {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.6}, max_it=K
    )
    w = randn(M.shape[0], seed=32)
    grads = {}
    for mode in ("implicit", "unrolled"):
        b = randn(M.shape[0], seed=33, requires_grad=True)
        (pp.solve(M, b, solver, mode=mode) @ w).backward()
        grads[mode] = b.grad
    scale = grads["implicit"].abs().max()
    assert (grads["implicit"] - grads["unrolled"]).abs().max() <= 1e-12 * scale


def test_unrolled_differs_from_implicit_for_cg_until_converged():
    D = interior_operator(unit_square(3))
    A = D.A_II
    theta = random_theta(A.n_params, seed=34)
    b0, w = randn(A.shape[0], seed=35), randn(A.shape[0], seed=36)

    def grads(solver):
        out = {}
        for mode in ("implicit", "unrolled"):
            b = b0.clone().requires_grad_(True)
            x = pp.solve(A, b, solver, theta=theta, mode=mode)
            (0.5 * (x @ x) + x @ w).backward()  # nonlinear loss in x
            out[mode] = b.grad
        return out

    def rel_diff(g):
        return float((g["implicit"] - g["unrolled"]).norm() / g["implicit"].norm())

    small = rel_diff(grads(pp.KSPSolver(CG_JACOBI, max_it=2)))
    conv = rel_diff(grads(converged_cg()))
    assert small > 0.05
    assert conv < 1e-9


def test_unrolled_theta_gradient_converged_matches_implicit():
    D = interior_operator(unit_square(3), "P1")
    A = D.A_II
    b = randn(2, A.shape[0], seed=37)
    grads = []
    for mode in ("implicit", "unrolled"):
        theta = random_theta(A.n_params, seed=38, requires_grad=True)
        pp.solve(A, b, converged_cg(), theta=theta, mode=mode).pow(2).sum().backward()
        grads.append(theta.grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-8, atol=1e-12)


# -- autograd bookkeeping ------------------------------------------------------------------


def test_output_device_dtype_and_no_adjoint_without_grad():
    D = interior_operator(unit_square(3))
    A = D.A_II
    solver = converged_cg()
    theta = random_theta(A.n_params)
    b = randn(A.shape[0], seed=39)
    x = pp.solve(A, b, solver, theta=theta)
    assert x.device == b.device and x.dtype == torch.float64 and x.shape == b.shape
    assert not x.requires_grad
    assert solver.stats.adjoint_solves == 0


def test_only_requested_gradients_are_computed():
    D = interior_operator(unit_square(3))
    A = D.A_II
    solver = converged_cg()
    theta = random_theta(A.n_params)  # no gradient wanted
    b = randn(A.shape[0], seed=40, requires_grad=True)
    x = pp.solve(A, b, solver, theta=theta)
    x.sum().backward()
    assert theta.grad is None and b.grad is not None
    assert solver.stats.adjoint_solves == 1


def test_in_place_change_of_solution_is_caught():
    """∂L/∂θ needs x: editing the output in place must raise, not give a wrong gradient."""
    D = interior_operator(unit_square(3))
    A = D.A_II
    theta = random_theta(A.n_params, requires_grad=True)
    x = pp.solve(A, randn(A.shape[0], seed=41), converged_cg(), theta=theta)
    x.add_(1.0)
    with pytest.raises(RuntimeError, match="inplace"):
        x.sum().backward()
