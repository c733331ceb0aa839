"""A batch of operators: θ of shape (B, p) gives every sample its own A(θ_i), in one call.

gradcheck in float64 with converged solves (implicit) or a fixed K (unrolled, the
exact derivative of the truncated map), Dirichlet lifting with per-sample θ and g,
and equality with a Python loop of single solves.
"""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch
from _core import CONVERGED, interior_operator, randn, random_theta, unit_square
from petsc4py import PETSc
from torch.autograd import gradcheck

import prdp_petsc as pp
from prdp_petsc.autograd.bridge import matvec
from prdp_petsc.core.results import SolverStats

CG_JACOBI = {"ksp_type": "cg", "pc_type": "jacobi"}
BATCH = 3


@pytest.fixture(scope="module")
def dirichlet():
    return interior_operator(unit_square(2), "P1")


def thetas(p, seed=0, requires_grad=False):
    """BATCH different positive coefficient vectors, shape (BATCH, p)."""
    t = torch.stack([random_theta(p, seed=seed + i) for i in range(BATCH)])
    return t.requires_grad_(requires_grad)


def converged():
    return pp.KSPSolver(CG_JACOBI, **CONVERGED)


def test_parametric_batch_helpers_match_single_operators(dirichlet):
    A = dirichlet.A_IB  # rectangular: A_i v_i and A_iᵀ w_i differ in shape
    theta = thetas(A.n_params, seed=1).numpy()
    v, w = randn(BATCH, A.shape[1], seed=2).numpy(), randn(BATCH, A.shape[0], seed=3).numpy()
    values = A.values(theta)
    assert values.shape == (BATCH, A.nnz)
    for i in range(BATCH):
        M = A.matrix(theta[i])
        np.testing.assert_allclose(values[i], A.values(theta[i]), rtol=1e-15)
        np.testing.assert_allclose(A.matvecs(values, v)[i], M @ v[i], rtol=1e-13)
        np.testing.assert_allclose(A.matvecs(values, w, transpose=True)[i], M.T @ w[i], rtol=1e-13)
        np.testing.assert_allclose(
            A.vjp_matvec(w, v, per_sample=True)[i], A.vjp_matvec(w[i], v[i]), rtol=1e-13
        )
    with pytest.raises(ValueError, match="one theta"):
        A.matrix(theta)


def test_gradcheck_batch_of_operators(dirichlet):
    A = dirichlet.A_II
    solver = converged()
    b = randn(BATCH, A.shape[0], seed=4, requires_grad=True)
    theta = thetas(A.n_params, seed=5, requires_grad=True)
    assert gradcheck(lambda b, t: pp.solve(A, b, solver, theta=t), (b, theta))


def test_gradcheck_batch_of_operators_unrolled(dirichlet):
    A = dirichlet.A_II
    solver = pp.KSPSolver(CG_JACOBI, max_it=4)
    b = randn(BATCH, A.shape[0], seed=6, requires_grad=True)
    theta = thetas(A.n_params, seed=7, requires_grad=True)
    assert gradcheck(lambda b, t: pp.solve(A, b, solver, theta=t, mode="unrolled"), (b, theta))


def test_gradcheck_dirichlet_batch_of_operators(dirichlet):
    """Per-sample θ and g, shared f: u_i solves A_II(θ_i) u = f_I − A_IB(θ_i) g_i."""
    D = dirichlet
    solver = converged()
    f = randn(D.n, seed=8, requires_grad=True)
    g = randn(BATCH, len(D.boundary), seed=9, requires_grad=True)
    theta = thetas(D.A_II.n_params, seed=10, requires_grad=True)
    assert gradcheck(lambda f, g, t: D.solve(f, g, solver, theta=t), (f, g, theta))


def test_dirichlet_batch_matches_direct_solves(dirichlet):
    D = dirichlet
    theta = thetas(D.A_II.n_params, seed=11)
    f = randn(BATCH, D.n, seed=12)
    g = randn(len(D.boundary), seed=13)  # shared boundary values
    u = D.solve(f, g, converged(), theta=theta)
    assert u.shape == (BATCH, D.n)
    for i in range(BATCH):
        th = theta[i].numpy()
        rhs = f[i].numpy()[D.interior] - D.A_IB.matrix(th) @ g.numpy()
        u_i = spla.spsolve(D.A_II.matrix(th).tocsc(), rhs)
        np.testing.assert_allclose(u[i, D.interior].numpy(), u_i, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(u[i, D.boundary].numpy(), g.numpy())


@pytest.mark.parametrize("mode", ["implicit", "unrolled"])
def test_batch_equals_loop_of_single_solves(dirichlet, mode):
    A = dirichlet.A_II
    n = A.shape[0]
    b, w = randn(BATCH, n, seed=14), randn(BATCH, n, seed=15)
    theta = thetas(A.n_params, seed=16, requires_grad=True)
    solver = converged() if mode == "implicit" else pp.KSPSolver(CG_JACOBI, max_it=6)
    batch = pp.solve(A, b, solver, theta=theta, mode=mode, return_solution=True)
    x = batch.value
    (grad,) = torch.autograd.grad((x * w).sum(), theta)
    assert grad.shape == theta.shape
    for i in range(BATCH):
        t_i = theta[i].detach().clone().requires_grad_(True)
        alone = pp.solve(A, b[i], solver, theta=t_i, mode=mode, return_solution=True)
        (g_i,) = torch.autograd.grad(alone.value @ w[i], t_i)
        torch.testing.assert_close(x[i], alone.value, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(grad[i], g_i, rtol=1e-12, atol=1e-14)
        sample = batch.info[i]  # every sample's outcome is the one it has alone
        assert (alone.iterations, alone.reason) == (sample.iterations, sample.reason)
        assert alone.residual_norm == pytest.approx(sample.residual_norm, rel=1e-9)


def test_matvec_batch_of_operators(dirichlet):
    A = dirichlet.A_IB
    v = randn(BATCH, A.shape[1], seed=17, requires_grad=True)
    theta = thetas(A.n_params, seed=18, requires_grad=True)
    assert gradcheck(lambda v, t: matvec(A, v, theta=t), (v, theta))
    y = matvec(A, v, theta=theta)
    for i in range(BATCH):
        torch.testing.assert_close(y[i], matvec(A, v[i], theta=theta[i]), rtol=1e-14, atol=0)


def test_one_pc_setup_per_sample_and_the_last_is_reused_in_backward(dirichlet):
    PETSc.Log.begin()
    event = PETSc.Log.Event("PCSetUp")
    A = dirichlet.A_II
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, **CONVERGED)
    b = randn(BATCH, A.shape[0], seed=19)
    theta = thetas(A.n_params, seed=20, requires_grad=True)
    c0 = event.getPerfInfo()["count"]
    x = pp.solve(A, b, solver, theta=theta)
    c1 = event.getPerfInfo()["count"]
    x.sum().backward()
    c2 = event.getPerfInfo()["count"]
    assert (c1 - c0, c2 - c1) == (BATCH, BATCH - 1)
    assert solver.stats.forward_solves == solver.stats.adjoint_solves == BATCH


@pytest.mark.parametrize(("b_shape", "theta_batch"), [((9,), 1), ((2, 9), 3), ((9,), 3)])
def test_batch_of_operators_needs_a_matching_batch_of_right_hand_sides(b_shape, theta_batch):
    A = interior_operator(unit_square(2)).A_II
    solver = pp.KSPSolver(CG_JACOBI, max_it=5)
    theta = random_theta(A.n_params).expand(theta_batch, -1)
    with pytest.raises(ValueError, match=r"theta must have shape .*\.expand\("):
        pp.solve(A, torch.ones(b_shape, dtype=torch.float64), solver, theta=theta)
    assert solver.stats == SolverStats()


def test_dirichlet_batch_sizes_must_agree():
    D = interior_operator(unit_square(2))
    solver = pp.KSPSolver(CG_JACOBI, max_it=5)
    theta = random_theta(D.A_II.n_params).expand(3, -1)
    with pytest.raises(ValueError, match="f has batch size 2 but theta has 3"):
        D.solve(randn(2, D.n), randn(len(D.boundary)), solver, theta=theta)
    assert solver.stats == SolverStats()
