"""Training on two ranks gives the serial training's numbers.

``batch``: each rank trains on its half of every mini-batch and the gradients are
summed, so the parameters equal serial training with the same global batch (to
round-off).  ``domain``: every solve is distributed; the run equals the serial one.
"""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from _mpi import COMM, all_ranks, same_on_all_ranks

from prdp_petsc.errors import InputError, SolverError
from prdp_petsc.lab.training.harness import build_scene, run
from prdp_petsc.lab.training.parallel import Parallel
from prdp_petsc.lab.training.scene import load_scene, shuffled_batches

DEMOS = Path(__file__).resolve().parents[2] / "demos"


def _params(scene) -> np.ndarray:
    params = [p for g in scene.optimizer.param_groups for p in g["params"]]
    return torch.cat([p.detach().reshape(-1) for p in params]).numpy().copy()


def _train(scene, ranks: Parallel, epochs: int) -> list[float]:
    generator = torch.Generator().manual_seed(0)
    losses = []
    for epoch in range(epochs):
        for s in scene.solvers:
            s.max_it = 4
        losses += [ranks.step(scene, batch) for batch in scene.batches(epoch, generator)]
    return losses


def test_batch_parallel_parameters_equal_serial_training():
    module = load_scene(DEMOS / "heat1d.py")
    serial, split = (build_scene(module, "quick", seed=3) for _ in range(2))
    # batches of 7 (40 samples): 4 + 3 per rank and a last batch of 5, so a wrong
    # weighting of the ranks' shares would show
    serial.batches = split.batches = shuffled_batches(40, 7)
    losses_serial = _train(serial, Parallel(None), epochs=3)
    losses_split = _train(split, Parallel("batch"), epochs=3)
    expected, got = _params(serial), _params(split)
    assert not np.allclose(got, _params(build_scene(module, "quick", seed=3)))  # it trained
    rel = np.abs(got - expected).max() / np.abs(expected).max()
    assert all_ranks(rel <= 1e-12), rel
    assert all_ranks(np.allclose(losses_split, losses_serial, rtol=1e-12, atol=0))
    assert same_on_all_ranks(got)


def _epochs(result, key):
    return np.array([e[key] for e in result["epochs"]])


@pytest.mark.parametrize(
    "scene, mode",
    [
        ("heat1d.py", "batch"),
        ("heat.py", "domain"),
        ("poisson_inverse.py", "domain"),
        ("heat_nonlinear.py", "domain"),
        ("poisson_sip.py", "batch"),
    ],
)
def test_run_equals_serial_run(scene, mode, tmp_path):
    """``run(parallel=...)`` on two ranks reproduces the serial run: same K schedule,
    losses and validation errors; iteration totals count every rank's work."""
    kwargs = {"preset": "quick", "epochs": 4, "seed": 1, "progress": False}
    serial = run(DEMOS / scene, "prdp", **kwargs)
    out = Path(COMM.bcast(str(tmp_path), root=0))
    parallel = run(DEMOS / scene, "prdp", out=out, parallel=mode, **kwargs)
    assert all_ranks(parallel["stopped"] is None and serial["stopped"] is None)
    assert all_ranks(np.array_equal(_epochs(parallel, "k"), _epochs(serial, "k")))
    for key in ("train_loss", "val_metric"):
        got, expected = _epochs(parallel, key), _epochs(serial, key)
        assert all_ranks(np.allclose(got, expected, rtol=1e-9, atol=0)), (key, got, expected)
    # the same solves ran (split across ranks for batch, collectively for domain)
    total = parallel["totals"]["fwd_iterations"] + parallel["totals"]["adj_iterations"]
    assert all_ranks(
        total == serial["totals"]["fwd_iterations"] + serial["totals"]["adj_iterations"]
    )
    assert parallel["parallel"] == {"mode": mode, "ranks": COMM.Get_size()}
    assert all_ranks((out / "results.json").is_file())  # rank 0 wrote it
    assert same_on_all_ranks(_epochs(parallel, "val_metric"))


class _Regression:
    """Least squares of a linear model, 12 samples: per-sample losses (x_i·w - y_i)²
    reduced over the batch by `reduce` ("mean", "sum", or "normalised": the sum over
    Σ y_i² of the batch); `noise` adds torch's random numbers to the residuals."""

    def __init__(self, reduce: str = "mean", noise: float = 0.0):
        g = torch.Generator().manual_seed(0)
        self.x = torch.randn(12, 3, generator=g, dtype=torch.float64)
        self.y = torch.randn(12, generator=g, dtype=torch.float64)
        self.weight = torch.nn.Parameter(torch.full((3,), 0.5, dtype=torch.float64))
        self.optimizer = torch.optim.SGD([self.weight], lr=0.1)
        self.reduce, self.noise, self.calls = reduce, noise, 0

    def loss(self, idx):
        self.calls += 1
        residual = self.x[idx] @ self.weight - self.y[idx]
        if self.noise:
            residual = residual + self.noise * torch.randn(len(idx), dtype=torch.float64)
        per_sample = residual**2
        if self.reduce == "sum":
            return per_sample.sum()
        if self.reduce == "normalised":
            return per_sample.sum() / (self.y[idx] ** 2).sum()
        return per_sample.mean()


def _step_error(ranks, scene, batch):
    """The error `ranks.step` raised (None if none), so every rank reaches the asserts."""
    try:
        ranks.step(scene, batch)
    except Exception as error:
        return error
    return None


@pytest.mark.parametrize("reduce", ["sum", "normalised"])
def test_batch_mode_refuses_a_loss_that_is_not_a_mean(reduce):
    scene = _Regression(reduce)
    start = scene.weight.detach().clone()
    error = _step_error(Parallel("batch"), scene, torch.arange(7))
    assert all_ranks(isinstance(error, InputError)), error
    assert all_ranks("mean of per-sample losses" in str(error))
    assert all_ranks("--parallel domain" in str(error))
    assert all_ranks(torch.equal(scene.weight.detach(), start))  # refused before the step


def test_batch_mode_checks_a_mean_loss_once_and_trains_as_serial():
    serial, split = _Regression(), _Regression()
    ranks, alone = Parallel("batch"), Parallel(None)
    rng = torch.random.get_rng_state()
    batches = [torch.tensor([3, 0, 7, 11, 5, 1, 9]), torch.tensor([2, 4, 10, 6, 8])]
    got = [ranks.step(split, b) for b in batches]
    expected = [alone.step(serial, b) for b in batches]
    assert all_ranks(np.allclose(got, expected, rtol=1e-14, atol=0)), (got, expected)
    assert all_ranks(torch.allclose(split.weight, serial.weight, rtol=1e-14, atol=0))
    # the first step's whole-batch forward, then one share per step
    assert all_ranks(split.calls == 3 and serial.calls == 2), split.calls
    assert all_ranks(torch.equal(torch.random.get_rng_state(), rng))


def test_batch_mode_refuses_a_loss_that_draws_random_numbers():
    scene = _Regression(noise=1e-3)
    torch.manual_seed(5)
    rng = torch.random.get_rng_state()
    error = _step_error(Parallel("batch"), scene, torch.arange(8))
    assert all_ranks(isinstance(error, InputError)), error
    assert all_ranks("random number generator" in str(error))
    assert all_ranks("--parallel domain" in str(error))
    # the check put torch's generator back, and the share's forward never ran
    assert all_ranks(scene.calls == 1)
    assert all_ranks(torch.equal(torch.random.get_rng_state(), rng))


def test_run_stops_every_rank_for_a_sum_loss():
    """heat1d with the sum of its per-sample losses: serial training runs it, batch
    mode stops on every rank at the first step with the reason and what to do."""
    heat1d = load_scene(DEMOS / "heat1d.py")

    def build(config, seed):
        scene = heat1d.build(config, seed)
        mean = scene.loss
        scene.loss = lambda idx: mean(idx) * len(idx)
        return scene

    module = SimpleNamespace(__name__="heat1d_sum", PRESETS=heat1d.PRESETS, build=build)
    kwargs = {"preset": "quick", "epochs": 2, "seed": 1, "progress": False, "module": module}
    result = run(DEMOS / "heat1d.py", "fixed:4", parallel="batch", **kwargs)
    stopped = result["stopped"] or {}
    assert all_ranks(stopped.get("reason") == "INVALID_INPUT" and stopped.get("epoch") == 0)
    assert all_ranks("mean of per-sample losses" in stopped.get("message", ""))
    assert all_ranks(result["epochs"] == [])


class _Failing:
    """A scene whose loss fails on rank 1 only: every rank must stop, none may hang."""

    def __init__(self):
        self.weight = torch.nn.Parameter(torch.ones(2, dtype=torch.float64))
        self.optimizer = torch.optim.SGD([self.weight], lr=0.1)

    def loss(self, idx):
        if COMM.Get_rank() == 1:
            raise SolverError("forward solve diverged: DIVERGED_DTOL", reason="DIVERGED_DTOL")
        return (self.weight**2).sum() * len(idx)


def test_a_failed_solve_on_one_rank_stops_every_rank():
    with pytest.raises(SolverError) as caught:
        Parallel("batch").step(_Failing(), torch.arange(4))
    assert caught.value.reason == "DIVERGED_DTOL"
    assert all_ranks("DIVERGED_DTOL" in str(caught.value))


def test_batch_mode_refuses_batches_that_are_not_sample_indices():
    with pytest.raises(TypeError, match="--parallel domain"):
        Parallel("batch").step(_Failing(), None)


class _ValidationFails:
    """A batch scene whose validation (rank 0 only) fails: every rank must stop."""

    def __init__(self):
        self.weight = torch.nn.Parameter(torch.ones(2, dtype=torch.float64))
        self.optimizer = torch.optim.SGD([self.weight], lr=0.1)

    def validate(self):
        raise SolverError(
            "validation solve diverged: DIVERGED_NANORINF", reason="DIVERGED_NANORINF"
        )

    def rollout(self):
        raise RuntimeError("no rollout")


def test_a_failed_validation_on_rank_0_stops_every_rank():
    ranks = Parallel("batch")
    with pytest.raises(SolverError, match="DIVERGED_NANORINF"):
        ranks.validate(_ValidationFails())
    with pytest.raises(RuntimeError, match="no rollout"):
        ranks.rollout(_ValidationFails().rollout)


def test_synchronize_starts_every_rank_from_rank_0():
    scene = _Failing()
    with torch.no_grad():
        scene.weight.fill_(float(COMM.Get_rank()))
    Parallel("batch").synchronize(scene)
    assert all_ranks(torch.equal(scene.weight.detach(), torch.zeros(2, dtype=torch.float64)))


def test_ns2d_schur_validation_runs_distributed():
    """``val_solver: "schur"`` (the large presets) validates under ``--parallel domain``."""
    module = load_scene(DEMOS / "ns2d.py")
    module.PRESETS["quick_schur"] = {**module.PRESETS["quick"], "val_solver": "schur"}
    serial = build_scene(module, "quick_schur", 0).validate()
    ranks = Parallel("domain")
    with ranks.solvers():
        scene = build_scene(module, "quick_schur", 0)
    got = ranks.validate(scene)
    # both solve to rtol_full = 1e-5 with another PC (ILU per rank): equal to that order
    assert all_ranks(np.isclose(got, serial, rtol=1e-4, atol=0)), (got, serial)


def test_compare_seeds_with_twin_runs_distributed(tmp_path):
    """``compare_seeds`` under ``--parallel batch``: every rank runs every seed and
    twin, rank 0 alone writes ``seeds.json``, all ranks agree on the statistics."""
    from prdp_petsc.lab.training.seeds import compare_seeds

    out = Path(COMM.bcast(str(tmp_path), root=0))
    result = compare_seeds(DEMOS / "heat1d.py", [0, 1], preset="quick", epochs=2, out=out,
                           progress=False, plots=False, parallel="batch")  # fmt: skip
    assert all_ranks(result["compared"] == 2 and (out / "seeds.json").is_file())
    assert all_ranks(all(r["twin_ratio"] is not None for r in result["per_seed"]))
    assert same_on_all_ranks([r["prdp_ratio"] for r in result["per_seed"]])
