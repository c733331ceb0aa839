"""Long unrolls (`prdp_petsc.lab.training.unroll`): gradients, memory, windows, curriculum.

An m-step rollout of (implicit solve ↔ network) differentiated with the network
checkpointed equals the same rollout differentiated with plain autograd; the
indirect correction's gradient through the solve's right-hand side matches finite
differences; checkpointing keeps what autograd saves from growing with the
network's activations.
"""

import numpy as np
import pytest
import torch
from _core import CONVERGED, interior_operator, random_theta, unit_square

import prdp_petsc as pp
from prdp_petsc.lab.training.unroll import (
    Hybrid,
    SavedTensorMeter,
    horizon,
    unrolled_loss,
    windows,
)

CG = {"ksp_type": "cg", "pc_type": "jacobi"}


@pytest.fixture(scope="module")
def problem():
    """``A(θ)`` (P1 stiffness with κ per element, interior rows) and target windows."""
    A = interior_operator(unit_square(3)).A_II
    n = A.shape[0]
    theta = random_theta(A.n_params)
    rng = np.random.default_rng(0)
    targets = torch.from_numpy(rng.standard_normal((9, 3, n)) * 0.3)
    return A, theta, targets


def _hybrid(problem, correction, checkpoint, solver):
    A, theta, _ = problem
    n = A.shape[0]
    torch.manual_seed(3)
    net = torch.nn.Sequential(
        torch.nn.Linear(n, 16), torch.nn.Tanh(), torch.nn.Linear(16, n)
    ).double()

    def physics(state, forcing, keys):
        b = state if forcing is None else state + forcing
        return pp.solve(A, b, solver, theta=theta)

    return Hybrid(physics, net, correction=correction, checkpoint=checkpoint), net


@pytest.mark.parametrize("correction", ["direct", "indirect"])
@pytest.mark.parametrize("solver_grad", [True, False])
def test_checkpointed_unroll_has_the_plain_unrolls_gradient(problem, correction, solver_grad):
    solver = pp.KSPSolver(CG, **CONVERGED)
    grads = []
    for checkpoint in (False, True):
        step, net = _hybrid(problem, correction, checkpoint, solver)
        loss = unrolled_loss(step, problem[2], steps=6, solver_grad=solver_grad)
        grads.append(torch.autograd.grad(loss, list(net.parameters())))
    for plain, checked in zip(*grads, strict=True):
        assert torch.allclose(plain, checked, rtol=1e-12, atol=1e-14)
    # the physics gradient matters: detaching the solver's input changes it
    assert all(g.abs().max() > 0 for g in grads[0])


def test_capped_solves_inside_the_unroll_use_the_solvers_k(problem):
    solver = pp.KSPSolver(CG, max_it=3)
    step, _ = _hybrid(problem, "direct", True, solver)
    solver.reset_stats()
    unrolled_loss(step, problem[2], steps=5).backward()
    assert solver.stats.forward_iterations == 5 * 3 * 3  # 5 steps × 3 samples × K = 3
    # the first solve sees only data (no gradient needed): 4 adjoint solves per sample
    assert solver.stats.adjoint_iterations == 4 * 3 * 3


@pytest.mark.parametrize("correction", ["direct", "indirect"])
def test_unrolled_gradient_matches_finite_differences(problem, correction):
    solver = pp.KSPSolver(CG, **CONVERGED)
    step, net = _hybrid(problem, correction, True, solver)
    weight = net[2].weight
    direction = torch.from_numpy(np.random.default_rng(5).standard_normal(weight.shape))

    def loss():
        return unrolled_loss(step, problem[2], steps=4)

    (g,) = torch.autograd.grad(loss(), [weight])
    eps = 1e-6
    with torch.no_grad():
        weight += eps * direction
        up = float(loss())
        weight -= 2 * eps * direction
        down = float(loss())
        weight += eps * direction
    fd = (up - down) / (2 * eps)
    assert abs(float((g * direction).sum()) - fd) <= 1e-7 * abs(fd)


def test_checkpointing_keeps_the_networks_activations_out_of_the_graph(problem):
    """What autograd saves for an 8-step unroll: with checkpoints, the step inputs
    and the solves' states; without, every activation of every network call too."""
    solver = pp.KSPSolver(CG, max_it=5)
    A, theta, targets = problem
    n = A.shape[0]
    wide = torch.nn.Sequential(
        torch.nn.Linear(n, 2048), torch.nn.Tanh(), torch.nn.Linear(2048, n)
    ).double()

    def physics(state, forcing, keys):
        return pp.solve(A, state, solver, theta=theta)

    saved = {}
    for checkpoint in (False, True):
        for m in (2, 8):
            step = Hybrid(physics, wide, checkpoint=checkpoint)
            meter = SavedTensorMeter()
            with meter():
                unrolled_loss(step, targets, steps=m).backward()
            saved[checkpoint, m] = meter.peak
    # an activation is 3 × 2048 doubles: 8 steps without checkpoints keep one per
    # step more than 2 steps do; with checkpoints 6 more steps add less than one
    activation = 3 * 2048 * 8
    assert saved[False, 8] - saved[False, 2] >= 6 * activation
    assert saved[True, 8] - saved[True, 2] < activation
    assert saved[True, 8] < saved[False, 8] / 2


def test_windows_are_every_consecutive_span_of_each_trajectory():
    traj = torch.arange(5 * 2 * 1, dtype=torch.float64).reshape(5, 2, 1)  # T + 1 = 5
    w = windows(traj, 3)
    assert w.shape == (3, 2 * 3, 1)
    # start t = 0 of trajectories 0 and 1, then t = 1, then t = 2
    assert w[:, :, 0].T.tolist() == [
        [0, 2, 4], [1, 3, 5], [2, 4, 6], [3, 5, 7], [4, 6, 8], [5, 7, 9]
    ]  # fmt: skip
    assert windows(traj, 2, stride=3)[:, :, 0].T.tolist() == [[0, 2], [1, 3], [6, 8], [7, 9]]
    with pytest.raises(ValueError, match="length"):
        windows(traj, 6)


def test_horizon_doubles_up_to_the_unroll():
    assert [horizon(e, 8, every=2) for e in range(9)] == [1, 1, 2, 2, 4, 4, 8, 8, 8]
    assert horizon(0, 8, start=2, every=3) == 2 and horizon(100, 8) == 8
    with pytest.raises(ValueError):
        horizon(0, 8, every=-1)


def test_bad_settings_are_refused(problem):
    with pytest.raises(ValueError, match="correction"):
        Hybrid(lambda s, f, k: s, torch.nn.Identity(), correction="sideways")
    step = Hybrid(lambda s, f, k: s, torch.nn.Identity())
    with pytest.raises(ValueError, match="steps"):
        unrolled_loss(step, problem[2], steps=9)


def test_horizon_report_rows_measure_what_checkpointing_saves():
    from pathlib import Path

    from prdp_petsc.lab.reports.horizon import format_horizon_report, horizon_row

    scene = str(Path(__file__).resolve().parents[2] / "demos" / "ns2d.py")
    rows = [horizon_row(scene, "long_quick", 4, checkpoint=c, k=3, epochs=1) for c in (True, False)]
    config = {"n_train": 3, "train_steps": 6}  # long_quick: 3 windows per trajectory at m = 4
    assert rows[0]["windows"] == rows[1]["windows"] == config["n_train"] * 3
    assert 0 < rows[0]["saved_tensors_mb"] < rows[1]["saved_tensors_mb"] / 2
    assert all(r["peak_rss_mb"] >= r["rss_at_start_mb"] > 0 for r in rows)
    text = format_horizon_report({"scene": "ns2d.py", "preset": "long_quick", "k": 3, "rows": rows})
    title, header, *lines = text.splitlines()
    assert header.split()[:3] == ["m", "ckpt", "windows"] and len(lines) == 2
    assert [line.split()[:3] for line in lines] == [["4", "yes", "9"], ["4", "no", "9"]]
