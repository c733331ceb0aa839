"""Preconditioner lag (``KSPSolver(pc_lag=N)``): fewer set-ups, the same converged answer,
stale PCs reported (pc_age, k_equivalent) and set up again when they get worse.

The operator is one implicit-Euler heat step ``A(θ) = M + Δt K(θ)`` (P1, κ per
element, Δt κ/h² ≈ 1), so that scaling θ changes the balance of mass and stiffness
and hence what a preconditioner built for another θ is worth (a pure ``K(θ)`` scaled
by 100 is preconditioned exactly as well by the old PC: Krylov methods are scale
invariant).  θ drifts as ``θ₀ exp(0.03 t f)`` with a random field f, as an optimizer
moves a coefficient field.  PETSc's own ``PCSetUp`` event count is the ground truth
for the set-ups.
"""

import logging
import math

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from _core import fd_poisson, unit_square
from petsc4py import PETSc

import prdp_petsc as pp

ILU = {"ksp_type": "gmres", "pc_type": "ilu"}
GAMG = {"ksp_type": "cg", "pc_type": "gamg"}
GAMG_GMRES = {"ksp_type": "gmres", "pc_type": "gamg"}
CONVERGED = {"max_it": 1000, "rtol": 1e-10, "atol": 1e-50}


@pytest.fixture(scope="module")
def pc_setups():
    """Number of ``PCSetUp`` calls so far (PETSc logging is switched on once)."""
    PETSc.Log.begin()
    event = PETSc.Log.Event("PCSetUp")
    return lambda: event.getPerfInfo()["count"]


@pytest.fixture(scope="module")
def heat():
    """``(A, θ(t), b)``: the heat-step operator, the drifting θ and a right-hand side."""
    basis = unit_square(4)
    A = pp.Dirichlet(
        pp.diffusion_operator(basis) * 4e-3 + pp.mass_matrix(basis), basis.get_dofs()
    ).A_II
    rng = np.random.default_rng(0)
    theta0 = 1.0 + rng.random(A.n_params)
    field = rng.standard_normal(A.n_params)
    b = rng.standard_normal(A.shape[0])
    return A, lambda t: theta0 * np.exp(0.03 * t * field), b


def drift(solver, heat, steps, *, jump_at=None, solutions=None):
    """Solve A(θ(t)) x = b for t < steps (θ × 100 from `jump_at` on); the records
    (the solutions appended to `solutions`)."""
    A, theta, b = heat
    out = []
    for t in range(steps):
        th = theta(t) * (100.0 if jump_at is not None and t >= jump_at else 1.0)
        solver.set_operator(A.matrix(th))
        sol = solver.solve(b)
        out.append(sol.info[0])
        if solutions is not None:
            solutions.append(sol.value)
    return out


@pytest.mark.parametrize("options", [ILU, GAMG], ids=["ilu", "gamg"])
def test_default_sets_up_at_every_change_and_reports_fresh_pcs(options, heat, pc_setups):
    solver = pp.KSPSolver(options, max_it=4)
    assert solver.pc_lag == 1 and solver.pc_lag_tol == 1.2
    c0 = pc_setups()
    infos = drift(solver, heat, 6)
    assert pc_setups() - c0 == solver.stats.pc_setups == 6
    assert [i.pc_age for i in infos] == [0] * 6
    assert all(i.k_equivalent is None and 0 < i.rate < 1 for i in infos)
    assert solver.stats.pc_quality_rebuilds == 0


@pytest.mark.parametrize("options", [ILU, GAMG], ids=["ilu", "gamg"])
def test_lag_sets_the_pc_up_every_nth_change(options, heat, pc_setups):
    A, theta, b = heat
    solver = pp.KSPSolver(options, max_it=4, pc_lag=5)
    c0 = pc_setups()
    ages = []
    for t in range(11):
        th = torch.from_numpy(theta(t)).requires_grad_(True)
        sol = pp.solve(A, torch.from_numpy(b), solver, theta=th, return_solution=True)
        sol.value.sum().backward()
        # the adjoint shares the forward PC: the same age, no set-up of its own
        assert sol.adjoint.pc_ages.tolist() == sol.info.pc_ages.tolist()
        ages.append(int(sol.info[0].pc_age))
    assert ages == [0, 1, 2, 3, 4, 0, 1, 2, 3, 4, 0]
    assert pc_setups() - c0 == solver.stats.pc_setups == 3  # t = 0, 5, 10 (of 11)
    assert solver.stats.operator_updates == 11


def test_an_adjoint_with_its_own_pc_lags_on_its_own(heat, pc_setups):
    A, theta, b = heat
    adjoint = pp.AdjointSettings(options={"pc_type": "jacobi"})
    solver = pp.KSPSolver(ILU, max_it=4, pc_lag=3, adjoint=adjoint)
    c0 = pc_setups()
    for t in range(7):
        th = torch.from_numpy(theta(t)).requires_grad_(True)
        sol = pp.solve(A, torch.from_numpy(b), solver, theta=th, return_solution=True)
        sol.value.sum().backward()
        assert sol.info[0].pc_age == sol.adjoint[0].pc_age == t % 3
    assert pc_setups() - c0 == solver.stats.pc_setups == 2 * 3  # t = 0, 3, 6; two PCs


@pytest.mark.parametrize("options", [ILU, GAMG], ids=["ilu", "gamg"])
def test_reuse_changes_the_pc_not_the_converged_answer(options, heat):
    """Converged solves (rtol 1e-10): x, ∂L/∂b and ∂L/∂θ agree with and without reuse."""
    A, theta, b = heat
    w = torch.from_numpy(np.random.default_rng(5).standard_normal(A.shape[0]))
    runs = {}
    for lag in (1, 5):
        solver = pp.KSPSolver(options, pc_lag=lag, **CONVERGED)
        rows = []
        for t in range(7):
            th = torch.from_numpy(theta(t)).requires_grad_(True)
            bt = torch.from_numpy(b).requires_grad_(True)
            sol = pp.solve(A, bt, solver, theta=th, return_solution=True)
            (sol.value * w).sum().backward()
            assert sol.converged and sol.adjoint.converged
            rows.append((sol.value.detach(), bt.grad, th.grad, sol.info[0]))
        runs[lag] = rows
    for (x1, gb1, gt1, i1), (x5, gb5, gt5, i5) in zip(runs[1], runs[5], strict=True):
        for fresh, stale in ((x1, x5), (gb1, gb5), (gt1, gt5)):
            assert float((stale - fresh).norm() / fresh.norm()) < 1e-8
        assert i1.pc_age == 0
    assert [r[3].pc_age for r in runs[5]] == [0, 1, 2, 3, 4, 0, 1]
    # the stale PC really was another one: its iterates differ from the fresh PC's
    assert any(r5[3].rate != r1[3].rate for r1, r5 in zip(runs[1][1:5], runs[5][1:5]))


def test_capped_solves_on_a_stale_pc_report_k_equivalent(heat):
    """k_equivalent = K log(rate_fresh)/log(rate), ≥ K once the PC has grown worse."""
    K = 5
    solver = pp.KSPSolver(ILU, max_it=K, pc_lag=5, pc_lag_tol=10.0)
    infos = drift(solver, heat, 5)
    fresh = infos[0]
    assert fresh.pc_age == 0 and fresh.k_equivalent is None and fresh.iterations == K
    for age, info in enumerate(infos[1:], start=1):
        assert info.pc_age == age and info.iterations == K
        expected = K * math.log(fresh.rate) / math.log(info.rate)
        assert info.k_equivalent == pytest.approx(expected, rel=1e-12)
        assert (info.k_equivalent >= K) == (info.rate >= fresh.rate)
    # four drift steps on make the old ILU measurably worse
    assert infos[-1].rate > fresh.rate and infos[-1].k_equivalent > K * 1.005
    # a batch on a stale PC: every sample carries the age and its own k_equivalent
    A, theta, b = heat
    solver.set_operator(A.matrix(theta(5)))  # age 5 = lag: a fresh PC
    assert solver.solve(np.stack([b, -2 * b])).info.pc_ages.tolist() == [0, 0]
    solver.set_operator(A.matrix(theta(6)))
    stale = solver.solve(np.stack([b, b[::-1].copy()])).info
    assert stale.pc_ages.tolist() == [1, 1]
    assert np.all(stale.k_equivalents > 0)


@pytest.mark.parametrize("options", [ILU, GAMG_GMRES], ids=["ilu", "gamg"])
def test_quality_guard_sets_the_pc_up_after_a_jump(options, heat, pc_setups, caplog):
    """θ × 100 at t = 3: that solve is reported worse, the next one gets a fresh PC
    (whose rates are the new reference: t = 5 is not flagged)."""
    K = 5
    solver = pp.KSPSolver(options, max_it=K, pc_lag=10)
    c0 = pc_setups()
    with caplog.at_level(logging.INFO, logger="prdp_petsc.core.lag"):
        infos = drift(solver, heat, 6, jump_at=3)
    assert [i.pc_age for i in infos] == [0, 1, 2, 3, 0, 1]
    jump = infos[3]
    assert jump.k_equivalent > solver.pc_lag_tol * K  # worse, and said so in the record
    assert all(i.k_equivalent < solver.pc_lag_tol * K for i in infos[1:3] + infos[5:])
    assert solver.stats.pc_quality_rebuilds == 1
    assert pc_setups() - c0 == solver.stats.pc_setups == 2
    assert "set up again before the next solve" in caplog.text
    assert infos[4].rate < jump.rate  # the fresh PC is better on the jumped operator
    # ... much better for GAMG (0.14 against 0.77 per iteration), hardly for ILU (0.529
    # against 0.534): there the jump made the operator harder, and the log says so
    harder = "the operator got harder" in caplog.text
    assert harder == (options is ILU)
    assert (infos[4].rate < 0.5 * jump.rate) == (options is GAMG_GMRES)
    # without the guard (a tolerance nothing reaches) the stale PC stays
    lax = pp.KSPSolver(options, max_it=K, pc_lag=10, pc_lag_tol=1e6)
    assert [i.pc_age for i in drift(lax, heat, 6, jump_at=3)] == [0, 1, 2, 3, 4, 5]
    assert lax.stats.pc_setups == 1 and lax.stats.pc_quality_rebuilds == 0


def test_a_solve_that_fails_on_a_stale_pc_runs_again_on_a_fresh_one(heat, caplog):
    """CG on a GAMG built for θ, applied to 100 θ: indefinite (its Chebyshev smoother's
    eigenvalue bounds are stale), CG breaks down; the call reruns on a new GAMG and
    returns what a solver without lag returns."""
    K = 5
    # a GAMG set up again keeps its interpolation by default: off, to compare bitwise
    options = {**GAMG, "pc_gamg_reuse_interpolation": False}
    solver = pp.KSPSolver(options, max_it=K, pc_lag=10)
    xs = []
    with caplog.at_level(logging.WARNING, logger="prdp_petsc.core.solver"):
        infos = drift(solver, heat, 5, jump_at=3, solutions=xs)
    assert [i.pc_age for i in infos] == [0, 1, 2, 0, 1]
    assert "DIVERGED_INDEFINITE_PC" in caplog.text
    assert solver.stats.pc_setups == 2 and solver.stats.pc_quality_rebuilds == 1
    assert 5 * K < solver.stats.forward_iterations < 6 * K  # and the failed attempt's
    A, theta, b = heat
    fresh = pp.KSPSolver(options, max_it=K)
    fresh.set_operator(A.matrix(100 * theta(3)))
    np.testing.assert_allclose(xs[3], fresh.solve(b).value, rtol=1e-12, atol=1e-14)


def test_a_new_pattern_gets_a_new_pc_within_the_lag(pc_setups):
    solver = pp.KSPSolver(ILU, max_it=3, pc_lag=10)
    c0 = pc_setups()
    A = fd_poisson(6)
    solver.set_operator(A)
    solver.solve(np.ones(36))
    solver.set_operator(A * 1.5)
    assert solver.solve(np.ones(36)).info[0].pc_age == 1
    B = fd_poisson(7)  # another size
    solver.set_operator(B)
    solver.solve(np.ones(49))
    C = sp.csr_matrix(B + sp.eye(49, k=3))  # same size, another pattern
    solver.set_operator(C)
    assert solver.solve(np.ones(49)).info[0].pc_age == 0
    assert pc_setups() - c0 == solver.stats.pc_setups == 3


def test_lag_settings_are_validated_copied_and_described():
    for bad in (0, -1, 1.5, True, "5"):
        with pytest.raises(ValueError, match="pc_lag must be an integer >= 1"):
            pp.KSPSolver(ILU, max_it=3, pc_lag=bad)
    for bad in (0.9, math.nan, math.inf, "1.2"):
        with pytest.raises(ValueError, match="pc_lag_tol must be a finite number >= 1"):
            pp.KSPSolver(ILU, max_it=3, pc_lag_tol=bad)
    solver = pp.KSPSolver(ILU, max_it=3, pc_lag=4, pc_lag_tol=1.5)
    other = solver.clone(max_it=7)
    assert (other.pc_lag, other.pc_lag_tol) == (4, 1.5)
    assert solver.describe()["pc_lag"] == 4 and solver.describe()["pc_lag_tol"] == 1.5
