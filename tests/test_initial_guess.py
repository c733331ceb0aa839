"""``solve(..., x0=)``: a capped solve that starts from an initial guess.

* The K iterations are PETSc's own from x0 (``KSPSetInitialGuessNonzero``), for a
  stationary method and for CG.
* For a capped Richardson/Jacobi iteration with the adjoint capped alike, the
  implicit gradient with respect to b and x0 is the exact derivative of the K
  steps (finite differences agree); converged, the gradient ignores x0.
* θ of a ParametricMatrix, the unrolled mode and the shape check.
"""

import numpy as np
import pytest
import torch
from _core import (
    CONVERGED,
    fd_poisson,
    interior_operator,
    randn,
    random_theta,
    raw_ksp,
    unit_square,
)
from petsc4py import PETSc

import prdp_petsc as pp

JACOBI = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.7}
CG = {"ksp_type": "cg", "pc_type": "jacobi"}


def petsc_from_x0(A, b, x0, options, k):
    """K iterations of a raw petsc4py KSP from the nonzero initial guess x0."""
    mat = PETSc.Mat().createAIJ(A.shape, csr=(A.indptr, A.indices, A.data), comm=PETSc.COMM_SELF)
    ksp = raw_ksp(mat, options)
    ksp.setTolerances(rtol=0.0, atol=0.0, max_it=k)
    ksp.setConvergenceTest(lambda ksp, its, rnorm: its >= k and 1 or 0)  # exactly K
    ksp.setInitialGuessNonzero(True)
    x, rhs = mat.createVecs()
    rhs.setArray(b)
    x.setArray(x0)
    ksp.solve(rhs, x)
    assert ksp.getIterationNumber() == k
    out = x.getArray().copy()
    for obj in (ksp, mat, x, rhs):
        obj.destroy()
    return out


@pytest.mark.parametrize("options", [JACOBI, CG], ids=["richardson-jacobi", "cg-jacobi"])
def test_iterates_are_petscs_from_the_initial_guess(options):
    A = fd_poisson(7)
    b, x0 = randn(49, seed=1), randn(49, seed=2)
    k = 7
    x = pp.solve(A, b, pp.KSPSolver(options, max_it=k), x0=x0)
    ref = petsc_from_x0(A.tocsr(), b.numpy(), x0.numpy(), options, k)
    np.testing.assert_allclose(x.numpy(), ref, rtol=1e-12, atol=1e-12)
    cold = pp.solve(A, b, pp.KSPSolver(options, max_it=k))
    assert not np.allclose(x.numpy(), cold.numpy())  # the guess did change the K iterates


def test_capped_jacobi_gradient_is_exact_in_b_and_x0():
    """x_K = x0 + S_K (b − A x0): ∂/∂b = S_K, ∂/∂x0 = I − S_K A, adjoint Jacobi gives both."""
    A = fd_poisson(4)
    solver = pp.KSPSolver(JACOBI, max_it=5)
    b = randn(16, seed=3, requires_grad=True)
    x0 = randn(16, seed=4, requires_grad=True)
    assert torch.autograd.gradcheck(lambda b, x0: pp.solve(A, b, solver, x0=x0), (b, x0))


def test_converged_solve_ignores_the_guess():
    A = fd_poisson(4)
    solver = pp.KSPSolver(CG, **CONVERGED)
    b = randn(16, seed=5)
    x0 = randn(16, seed=6, requires_grad=True)
    x = pp.solve(A, b, solver, x0=x0)
    np.testing.assert_allclose(x.detach().numpy(), pp.solve(A, b, solver).numpy(), atol=1e-11)
    (g,) = torch.autograd.grad(x.square().sum(), x0)
    assert g.abs().max() < 1e-9


def test_theta_and_x0_gradcheck_converged():
    A = interior_operator(unit_square(1)).A_II
    solver = pp.KSPSolver(CG, **CONVERGED)
    theta = random_theta(A.n_params, seed=7, requires_grad=True)
    b = randn(A.shape[0], seed=8, requires_grad=True)
    x0 = randn(A.shape[0], seed=9, requires_grad=True)
    fn = lambda t, b, x0: pp.solve(A, b, solver, theta=t, x0=x0)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (theta, b, x0))


def test_batch_of_operators_and_unrolled_mode():
    A = interior_operator(unit_square(1)).A_II
    n = A.shape[0]
    theta = torch.stack([random_theta(A.n_params, seed=s) for s in (10, 11)])
    b, x0 = randn(2, n, seed=12), randn(2, n, seed=13)
    solver = pp.KSPSolver(JACOBI, max_it=6)
    x = pp.solve(A, b, solver, theta=theta, x0=x0)
    u = pp.solve(A, b, solver, theta=theta, x0=x0, mode="unrolled")
    np.testing.assert_allclose(x.numpy(), u.numpy(), rtol=1e-10, atol=1e-12)
    for i in range(2):  # sample i from its own guess
        xi = pp.solve(A, b[i], solver, theta=theta[i], x0=x0[i])
        np.testing.assert_allclose(x[i].numpy(), xi.numpy(), rtol=1e-12, atol=1e-13)


def test_guess_of_another_shape_is_refused():
    A = fd_poisson(3)
    with pytest.raises(ValueError, match="x0 must have the shape of b"):
        pp.solve(A, randn(9, seed=1), pp.KSPSolver(CG, max_it=3), x0=randn(2, 9, seed=2))
