"""`gradient_check` and `find_k_full` take what a training loop has: the check a PRDP
controller certifies with, and K_full of the operator `solve` gets."""

import warnings

import numpy as np
import pytest
import torch
from _core import interior_operator, unit_square

import prdp_petsc as pp
from prdp_petsc.errors import InputError


@pytest.fixture
def problem():
    basis = unit_square(3)
    A = interior_operator(basis, "P0").A_II
    b = torch.ones(A.shape[0], dtype=torch.float64)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=3)
    yield A, b, solver
    solver.destroy()


def test_find_k_full_takes_what_solve_takes(problem):
    A, b, solver = problem
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    k_full = pp.find_k_full(A, b, solver, theta=theta)  # a ParametricMatrix and tensors
    assert k_full == pp.find_k_full(A.matrix(np.ones(A.n_params)), b.numpy(), solver)
    assert 5 < k_full < 100 and solver.max_it == 3  # the probe ran on a clone
    solver.max_it = k_full
    solver.rtol = 1e-8
    sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
    assert sol.converged and sol.iterations == k_full
    thetas = torch.stack([theta.detach(), 4 * theta.detach()])  # a batch of operators
    assert pp.find_k_full(A, b.expand(2, -1), solver, theta=thetas) == k_full  # scaled: same count
    with pytest.raises(InputError, match="theta="):
        pp.find_k_full(A, b, solver)
    with pytest.raises(InputError, match="find_k_full\\(A, b, solver"):
        pp.find_k_full(solver, A, b)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a probe that stops short raises, without a warning first
        with pytest.raises(pp.SolverError, match="K_full is undefined"):
            pp.find_k_full(A, b, solver, theta=theta, max_it=3)


def test_gradient_check_is_the_gradient_through_the_capped_solve(problem):
    A, b, solver = problem
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    target = torch.linspace(0, 1, A.shape[0], dtype=torch.float64)

    def loss():
        return (pp.solve(A, b, solver, theta=torch.exp(theta)) - target).square().sum()

    check = pp.gradient_check(loss, [theta], solver)
    with torch.no_grad():  # works where an update loop usually sits
        g2, g40 = check(2), check(40)
    assert solver.max_it == 3 and theta.grad is None  # cap restored, nothing accumulated
    solver.max_it = 40
    (expected,) = torch.autograd.grad(loss(), [theta])
    np.testing.assert_allclose(g40, expected.numpy(), rtol=1e-12)
    assert np.linalg.norm(g2 - g40) > 1e-3 * np.linalg.norm(g40)  # the cap matters
    unused = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    g = pp.gradient_check(loss, [theta, unused], [solver])(40)
    assert g.shape == (A.n_params + 3,) and np.all(g[-3:] == 0)


def test_a_random_loss_draws_the_same_numbers_at_every_cap_and_leaves_the_stream(problem):
    # noisy inputs (or dropout): the two evaluations of a check must differ only by the
    # cap, and the check must not move the random stream training draws from
    A, b, solver = problem
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)

    def loss():
        noisy = b * (1 + 0.1 * torch.randn(b.shape, dtype=b.dtype))
        return pp.solve(A, noisy, solver, theta=torch.exp(theta)).square().sum()

    check = pp.gradient_check(loss, [theta], solver)
    torch.manual_seed(0)
    state = torch.get_rng_state()
    first, coarse = check(40), check(2)
    np.testing.assert_array_equal(check(40), first)  # the same draws again
    assert torch.equal(torch.get_rng_state(), state)  # and the stream untouched
    assert np.linalg.norm(coarse - first) > 1e-3 * np.linalg.norm(first)  # the cap still matters


def test_gradient_check_refuses_what_cannot_be_a_check(problem):
    A, b, solver = problem
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    with pytest.raises(InputError, match="requires gradients"):
        pp.gradient_check(lambda: theta.sum(), [theta.detach()], solver)
    with pytest.raises(InputError, match="KSPSolver"):
        pp.gradient_check(lambda: theta.sum(), [theta], [])
    detached = pp.gradient_check(
        lambda: pp.solve(A, b, solver, theta=theta.detach()).sum(), [theta], solver
    )
    with pytest.raises(InputError, match="does not depend"):
        detached(3)
    assert solver.max_it == 3


def test_a_prdp_loop_with_the_shipped_check_counts_every_solve(problem):
    """An optimisation loop (one gradient per epoch): the savings `PRDP.savings` reports
    equal the solver's own count of every forward and adjoint iteration, the checks'
    and the metric's included."""
    A, b, solver = problem
    theta = torch.zeros(A.n_params, dtype=torch.float64, requires_grad=True)
    with torch.no_grad():
        target = pp.solve(
            A, b, solver.clone(max_it=200, rtol=1e-12), theta=torch.exp(0.3 + 0 * theta)
        )

    def loss():
        return (pp.solve(A, b, solver, theta=torch.exp(theta)) - target).square().sum()

    k_full = pp.find_k_full(A, b, solver, theta=torch.ones(A.n_params))
    prdp = pp.PRDP.for_problem(k_full, check=pp.gradient_check(loss, [theta], solver))
    opt = torch.optim.Adam([theta], lr=0.05)
    solver.reset_stats()
    epochs = 30
    for _ in range(epochs):
        solver.max_it = prdp.k
        opt.zero_grad()
        loss().backward()
        opt.step()
        with torch.no_grad():
            prdp.update(float(loss()))  # the metric's forward solve is not a training cost
    stats = solver.stats
    spent = stats.forward_iterations + stats.adjoint_iterations
    # an epoch at K_full: one forward and one adjoint solve, and the metric's forward solve
    per_epoch_full = 3 * k_full
    measured = 1 - spent / (epochs * per_epoch_full)
    assert prdp.checks  # checks ran and are in `spent`
    s = prdp.savings()  # the checks as they measured themselves
    assert s["total"] == pytest.approx(measured, abs=1e-12)
    checks_spent = sum(c.cost for c in prdp.checks)
    assert s["check_share"] == pytest.approx(checks_spent / spent, abs=1e-12)
    # told a check costs as an epoch at its cap, and not counting the metric's solve
    metric_solves = sum(st.k for st in prdp.history)  # forward only, one per update
    counted = 1 - (spent - metric_solves) / (epochs * 2 * k_full)
    assert prdp.savings(check_weight=1.0)["total"] == pytest.approx(counted, abs=1e-12)
    checks, total = prdp.check.spent()  # what the controller's budget reads
    assert total == spent and checks == sum(2 * (c.k + c.against) for c in prdp.checks)
    assert all(c.cost == 2 * (c.k + c.against) for c in prdp.checks)


def test_the_check_counts_on_across_a_stats_reset(problem):
    A, b, solver = problem
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    check = pp.gradient_check(lambda: pp.solve(A, b, solver, theta=theta).sum(), [theta], solver)
    pp.solve(A, b, solver, theta=theta.detach())  # 3 forward iterations of "training"
    check(5)  # 5 forward + 5 adjoint
    assert check.spent() == (10, 13)
    solver.reset_stats()
    pp.solve(A, b, solver, theta=theta.detach())
    assert check.spent() == (10, 16)
    solver.reset_stats()  # reset every epoch, as a training loop may do: each epoch counts
    for _ in range(2):
        check.spent()
        solver.reset_stats()
        pp.solve(A, b, solver, theta=theta.detach())
        pp.solve(A, b, solver, theta=theta.detach())  # 6 >= the 3 seen before the reset
    assert check.spent() == (10, 28)


def test_find_k_full_measures_the_capped_solves_error(problem):
    import math
    import pickle

    import scipy.sparse.linalg as spla

    A, b, solver = problem
    M = A.matrix(np.ones(A.n_params))
    k_full = pp.find_k_full(M, b.numpy(), solver)
    caps = sorted(k_full.errors)
    assert caps == sorted({math.ceil(k_full / 8), math.ceil(k_full / 4), math.ceil(k_full / 2)})
    x = spla.spsolve(M.tocsc(), b.numpy())
    for k in caps:  # the error of the solve capped at k, against a direct solve
        capped = solver.clone(max_it=k, rtol=0.0, atol=0.0)
        capped.set_operator(M)
        x_k = capped.solve(b.numpy()).value
        capped.destroy()
        expected = np.linalg.norm(x_k - x) / np.linalg.norm(x)
        assert k_full.errors[k] == pytest.approx(expected, rel=1e-6)
    assert k_full.errors[caps[0]] > k_full.errors[caps[-1]]  # CG: the error falls with k
    import copy

    assert copy.deepcopy({"k": k_full})["k"].errors == k_full.errors
    clone = pickle.loads(pickle.dumps(k_full))
    assert clone == k_full and clone.errors == k_full.errors
    assert type(k_full + 1) is int  # arithmetic gives plain ints
