"""`WarmStarts`: each sample's last solution as its next initial guess.

A converged solve from the stored guess gives what a solve from zero gives (value
and both gradients); a capped one gets closer to the converged solution; the
guesses are constants, so no graph links one epoch's backward to the last.
"""

import numpy as np
import pytest
import torch
from _core import CONVERGED, interior_operator, randn, random_theta, unit_square

import prdp_petsc as pp
from prdp_petsc.autograd.warm_starts import WarmStarts
from prdp_petsc.errors import NonFiniteError

CG = {"ksp_type": "cg", "pc_type": "jacobi"}


@pytest.fixture(scope="module")
def problem():
    """``(A, θ(epoch), b)``: Poisson with κ per element drifting slowly, 4 samples."""
    A = interior_operator(unit_square(3)).A_II
    theta0 = random_theta(A.n_params).numpy()
    field = np.random.default_rng(1).standard_normal(A.n_params)
    b = randn(4, A.shape[0], seed=2).detach()
    return A, lambda epoch: torch.from_numpy(theta0 * np.exp(0.02 * epoch * field)), b


def test_guesses_are_detached_copies_of_what_was_stored():
    starts = WarmStarts()
    assert starts.guess(torch.tensor([3, 1])) is None and starts.misses == 2
    x = torch.arange(6.0, dtype=torch.float64).reshape(2, 3).requires_grad_(True)
    y = x * 2
    starts.store(torch.tensor([3, 1]), y)
    guess = starts.guess([1, 3])
    assert torch.equal(guess, torch.stack([y[1], y[0]]).detach())
    assert not guess.requires_grad and guess.grad_fn is None
    with torch.no_grad():
        y += 100  # the caller's tensor changes; the stored copy does not
    assert torch.equal(starts.guess(np.array([1, 3])), guess)
    assert starts.hits == 4 and len(starts) == 2 and 3 in starts and 0 not in starts


def test_missing_keys_start_from_zero_or_from_the_fill():
    starts = WarmStarts()
    starts.store(5, torch.ones(3, dtype=torch.float64))  # one key: a vector
    assert torch.equal(starts.guess(5), torch.ones(3, dtype=torch.float64))
    assert torch.equal(starts.guess([7, 5]), torch.tensor([[0.0] * 3, [1.0] * 3]).double())
    fill = torch.full((2, 3), 2.0, dtype=torch.float64, requires_grad=True)
    guess = starts.guess([7, 5], fill=fill)
    assert guess.tolist() == [[2.0] * 3, [1.0] * 3] and not guess.requires_grad
    assert torch.equal(starts.guess(9, fill=fill[0]), fill[0].detach())
    starts.store([(0, 4), (1, 4)], torch.zeros(2, 3, dtype=torch.float64))  # tuple keys
    assert (1, 4) in starts and starts.guess((0, 4)).shape == (3,)


def test_bad_input_is_refused():
    starts = WarmStarts()
    with pytest.raises(ValueError, match="one row per key"):
        starts.store([1, 2, 3], torch.zeros(2, 4))
    with pytest.raises(NonFiniteError, match=r"keys \[2\]"):
        starts.store([1, 2], torch.tensor([[0.0, 1.0], [float("nan"), 0.0]]))
    assert len(starts) == 0  # nothing of a refused batch is kept
    with pytest.raises(ValueError, match="1-D"):
        starts.guess(torch.zeros(2, 2, dtype=torch.int64))
    starts.store([1], torch.zeros(1, 4))
    with pytest.raises(ValueError, match="differ in shape"):
        starts.guess([1, 2], fill=torch.zeros(2, 5))


def test_state_dict_round_trip():
    starts = WarmStarts()
    starts.store([(0, 1), (1, 1), 4], torch.randn(3, 5, dtype=torch.float64))
    other = WarmStarts()
    other.load_state_dict(starts.state_dict())
    for key in [(0, 1), (1, 1), 4]:
        assert torch.equal(other.guess(key), starts.guess(key))


def test_converged_solve_from_the_guess_has_the_same_value_and_gradients(problem):
    """x, ∂L/∂b, ∂L/∂θ from the cached guess equal those from zero (1e-8), and this
    epoch's backward leaves the last epoch's tensors alone."""
    A, theta, b = problem
    solver = pp.KSPSolver(CG, **CONVERGED)
    starts = WarmStarts()
    idx = torch.tensor([2, 0, 3])
    w = randn(3, A.shape[0], seed=7).detach()
    th0 = theta(0).requires_grad_(True)
    x0 = pp.solve(A, b[idx], solver, theta=th0)
    starts.store(idx, x0)
    (x0 * w).sum().backward()
    grad0 = th0.grad.clone()
    results = {}
    for start in ("zero", "cached"):
        th = theta(1).requires_grad_(True)
        bt = b[idx].clone().requires_grad_(True)
        guess = starts.guess(idx) if start == "cached" else None
        x = pp.solve(A, bt, solver, theta=th, x0=guess)
        (x * w).sum().backward()
        results[start] = (x.detach(), bt.grad, th.grad)
    for zero, cached in zip(results["zero"], results["cached"], strict=True):
        assert float((cached - zero).norm() / zero.norm()) < 1e-8
    assert torch.equal(th0.grad, grad0)  # no gradient flowed into the last epoch
    # iterations: rtol is relative to the initial residual ‖b − A x0‖, so only an
    # absolute tolerance turns the better guess into fewer iterations
    tolerances = {
        "rtol": {"rtol": 1e-10},
        "atol": {"rtol": 0.0, "atol": 1e-10 * float(b.norm(dim=1).min())},
    }
    its = {}
    for name, tol in tolerances.items():
        solver = pp.KSPSolver(CG, max_it=1000, **tol)
        for start in ("zero", "cached"):
            guess = starts.guess(idx) if start == "cached" else None
            sol = pp.solve(A, b[idx], solver, theta=theta(1), x0=guess, return_solution=True)
            its[name, start] = sol.info.iterations
    assert np.all(np.abs(its["rtol", "cached"] - its["rtol", "zero"]) <= 1)  # the same count
    assert np.all(its["atol", "cached"] <= its["atol", "zero"] - 3)  # fewer


@pytest.mark.parametrize("options", [CG, {"ksp_type": "richardson", "pc_type": "jacobi"}])
def test_capped_solves_from_the_guess_approach_the_converged_solution(problem, options):
    """K = 3 per epoch while θ drifts: from the cached guess the error keeps falling,
    from zero it stays where 3 iterations leave it."""
    A, theta, b = problem
    K = 3
    capped = pp.KSPSolver(options, max_it=K)
    exact = pp.KSPSolver(CG, **CONVERGED)
    starts = WarmStarts()
    rng = np.random.default_rng(3)
    errors = {"zero": [], "cached": []}
    for epoch in range(8):
        th = theta(epoch)
        x_star = pp.solve(A, b, exact, theta=th)
        for batch in np.array_split(rng.permutation(len(b)), 2):  # two batches per epoch
            idx = torch.from_numpy(batch)
            x = pp.solve(A, b[idx], capped, theta=th, x0=starts.guess(idx))
            starts.store(idx, x)
        cached = starts.guess(torch.arange(len(b)))
        zero = pp.solve(A, b, capped, theta=th)
        for name, value in (("zero", zero), ("cached", cached)):
            errors[name].append(float((value - x_star).norm() / x_star.norm()))
    ratio = np.array(errors["cached"]) / np.array(errors["zero"])
    assert ratio[0] == pytest.approx(1.0, abs=1e-12)  # first epoch: nothing stored yet
    assert np.all(np.diff(ratio) < 0) and ratio[-1] < 0.1


# -- the scenes that start their solves from zero (or from the network output) each epoch --
