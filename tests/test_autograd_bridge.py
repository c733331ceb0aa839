"""The torch bridge refuses what it cannot do instead of answering wrongly.

* A second derivative through a PETSc solve (or a numpy matvec) would silently
  miss the solve's second-order term: the backward functions are
  once-differentiable, so a double backward raises.
* ``theta=`` with a scipy matrix is refused by `Dirichlet.solve` as by `solve`.
"""

import numpy as np
import pytest
import torch
from _core import CONVERGED, fd_poisson, interior_operator, randn, random_theta, unit_square

import prdp_petsc as pp
from prdp_petsc.autograd.bridge import matvec
from prdp_petsc.core.results import SolverStats


def converged():
    return pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, **CONVERGED)


def second_grad(y, t):
    """grad of ``Σy² + Σt³`` w.r.t. t with create_graph, then its gradient again.

    The t³ term keeps the first gradient attached to the graph, so only the
    missing second-order term of the solve can make the second call go wrong.
    """
    (g,) = torch.autograd.grad((y**2).sum() + (t**3).sum(), t, create_graph=True)
    return torch.autograd.grad(g.sum(), t)


@pytest.mark.parametrize("wrt", ["b", "theta"])
def test_double_backward_through_a_solve_raises(wrt):
    A = interior_operator(unit_square(2)).A_II
    b = randn(A.shape[0], seed=1, requires_grad=wrt == "b")
    theta = random_theta(A.n_params, seed=2, requires_grad=wrt == "theta")
    x = pp.solve(A, b, converged(), theta=theta)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        second_grad(x, b if wrt == "b" else theta)


def test_double_backward_of_a_loss_linear_in_x_raises_for_theta():
    """L = ⟨w, x(θ)⟩: the upstream gradient w is constant, yet ∂²L/∂θ² ≠ 0 through x."""
    A = interior_operator(unit_square(2)).A_II
    theta = random_theta(A.n_params, seed=3, requires_grad=True)
    x = pp.solve(A, randn(A.shape[0], seed=4), converged(), theta=theta)
    (g,) = torch.autograd.grad(x @ randn(A.shape[0], seed=5), theta, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        torch.autograd.grad(g.sum(), theta)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        g.sum().backward()


def test_double_backward_through_matvec_raises():
    A = interior_operator(unit_square(2)).A_IB
    theta = random_theta(A.n_params, seed=6, requires_grad=True)
    y = matvec(A, randn(A.shape[1], seed=7), theta=theta)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        second_grad(y, theta)


def test_double_backward_through_constant_dirichlet_lifting_raises():
    D = pp.Dirichlet(fd_poisson(4), [0, 1, 2, 3])
    g = randn(4, seed=8, requires_grad=True)
    rhs = D.rhs(randn(16, seed=9), g)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        second_grad(rhs, g)


def test_dirichlet_theta_with_a_scipy_matrix_is_refused():
    D = pp.Dirichlet(fd_poisson(3), [0, 8])
    solver = converged()
    with pytest.raises(ValueError, match="theta= is only meaningful for a ParametricMatrix"):
        D.solve(randn(9), randn(2), solver, theta=random_theta(4))
    assert solver.stats == SolverStats()


def test_dirichlet_parametric_matrix_without_theta_is_refused():
    D = interior_operator(unit_square(2))
    solver = converged()
    with pytest.raises(ValueError, match="pass its parameters as theta="):
        D.solve(randn(D.n), randn(len(D.boundary)), solver)
    assert solver.stats == SolverStats()


# -- the per-call result: return_solution=True -------------------------------------------
def test_return_solution_keeps_this_calls_outcome_beside_x():
    """The result keeps its own call's outcome after the same solver ran another call."""
    A = fd_poisson(6)
    b = randn(36, seed=3, requires_grad=True)
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=4) as solver:
        sol = pp.solve(A, b, solver, return_solution=True)
        assert isinstance(sol, pp.LinearSolution)
        assert (sol.iterations, sol.reason, sol.converged) == (4, "DIVERGED_MAX_IT", False)
        assert sol.residual_norm == sol.info[0].residual_norm > 0
        assert sol.info.kind == "forward" and len(sol.info) == 1
        assert sol.adjoint is None  # no backward yet
        solver.max_it, solver.rtol = 50, 1e-12
        other = pp.solve(A, b.detach() * 2, solver, return_solution=True)  # another call
        assert other.converged and other.info is not sol.info
        assert (sol.iterations, sol.reason) == (4, "DIVERGED_MAX_IT")
        sol.value.square().sum().backward()  # the adjoint runs at the solver's cap now
        assert sol.adjoint.kind == "adjoint" and sol.adjoint.converged
        assert other.adjoint is None  # its own backward has not run
        solver.max_it, solver.rtol = 4, 0.0
        torch.testing.assert_close(sol.value, pp.solve(A, b.detach(), solver))


def test_return_solution_of_a_batch_reports_every_sample():
    A = fd_poisson(6)
    b = randn(3, 36, seed=4)
    b[1] = 0.0  # a zero right-hand side converges at once
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=5, rtol=1e-8) as solver:
        sol = pp.solve(A, b, solver, return_solution=True)
    assert sol.iterations.tolist()[1] == 0 and sol.iterations.tolist()[0] == 5
    assert len(sol.reason) == 3 and sol.residual_norm.shape == (3,)
    assert not sol.converged


@pytest.mark.parametrize("mode", ["implicit", "unrolled"])
def test_return_solution_with_a_guess_and_parameters(mode):
    basis = unit_square(2)
    A = interior_operator(basis).A_II
    theta = random_theta(A.n_params, requires_grad=True)
    b = randn(A.shape[0], seed=5)
    x0 = randn(A.shape[0], seed=6)
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=3) as solver:
        sol = pp.solve(A, b, solver, theta=theta, x0=x0, mode=mode, return_solution=True)
        sol.value.sum().backward()
    assert sol.iterations == 3 and theta.grad is not None
    assert (sol.adjoint is None) == (mode == "unrolled")


def test_return_solution_holds_no_reference_cycle():
    """The graph holds the adjoint's slot, not the result (which holds the graph): the
    result, its graph and the operator it keeps go as soon as the caller drops them."""
    import gc
    import weakref

    A = fd_poisson(6)
    b = randn(36, seed=3, requires_grad=True)
    gc.disable()
    try:
        with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=4) as solver:
            sol = pp.solve(A, b, solver, return_solution=True)
            gone = weakref.ref(sol)
            sol.value.sum().backward(retain_graph=True)
            assert sol.adjoint.kind == "adjoint" and len(sol.adjoint) == 1
            del sol
            assert gone() is None
    finally:
        gc.enable()


def test_dirichlet_solve_returns_its_solution_too():
    basis = unit_square(2)
    A = pp.diffusion_operator(basis)
    bc = pp.Dirichlet(A, basis.get_dofs())
    theta = random_theta(A.n_params, requires_grad=True)
    f = torch.ones(basis.N, dtype=torch.float64)
    g = torch.zeros(len(bc.boundary), dtype=torch.float64)
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=3) as solver:
        sol = bc.solve(f, g, solver, theta=theta, return_solution=True)
        plain = bc.solve(f, g, solver, theta=theta.detach())
        sol.value.square().sum().backward()
    assert sol.value.shape == (basis.N,) and torch.equal(sol.value.detach(), plain)
    assert sol.iterations == 3 and sol.adjoint.iterations.tolist() == [3]


def test_every_solve_returns_the_one_result_type():
    """`KSPSolver.solve` / `solve_transpose` (numpy) and `pp.solve` (torch) return one
    type, read the same way; the solver keeps no per-call outcome, only `stats`."""
    A = fd_poisson(5)
    b = randn(3, 25, seed=7)
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=6) as solver:
        solver.set_operator(A)
        forward = solver.solve(b.numpy())
        adjoint = solver.solve_transpose(b[0].numpy())
        bridged = pp.solve(A, b, solver, return_solution=True)
        for name in ("last", "last_forward", "last_adjoint"):
            assert not hasattr(solver, name), name
        assert solver.stats.forward_iterations == 2 * 3 * 6
    assert type(forward) is type(adjoint) is type(bridged) is pp.LinearSolution
    assert isinstance(forward.value, np.ndarray) and isinstance(bridged.value, torch.Tensor)
    np.testing.assert_array_equal(forward.value, bridged.value.numpy())
    assert forward.iterations.tolist() == bridged.iterations.tolist() == [6, 6, 6]
    assert forward.reason == bridged.reason == ["DIVERGED_MAX_IT"] * 3
    assert forward.info.kind == "forward" and adjoint.info.kind == "adjoint"
    assert (adjoint.iterations, adjoint.reason) == (6, "DIVERGED_MAX_IT")
    assert adjoint.residual_norm > 0 and not adjoint.converged and adjoint.adjoint is None
    np.testing.assert_allclose(adjoint.value, forward.value[0], rtol=1e-12)  # A = Aᵀ
