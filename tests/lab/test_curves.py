"""TensorBoard curves of a run (`prdp_petsc.lab.training.curves`), read back as
TensorBoard reads them: heat1d on its quick preset, through ``prdp-petsc run``."""

import json
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.backend.event_processing.event_multiplexer import EventMultiplexer
from tensorboard.plugins.hparams import plugin_data_pb2

from prdp_petsc.lab.cli import main
from prdp_petsc.lab.training.compare import compare
from prdp_petsc.lab.training.harness import run

HEAT1D = Path(__file__).resolve().parents[2] / "demos" / "heat1d.py"


def _curves(folder) -> dict[str, tuple[list[int], list[float]]]:
    """Every scalar of the event files in `folder`: tag -> (steps, values)."""
    events = EventAccumulator(str(folder))
    events.Reload()
    return {
        tag: ([e.step for e in events.Scalars(tag)], [e.value for e in events.Scalars(tag)])
        for tag in events.Tags()["scalars"]
    }


def _float32(values) -> list[float]:
    """`values` as TensorBoard stores a scalar (float32)."""
    return [float(np.float32(v)) for v in values]


@pytest.fixture(scope="module")
def prdp_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    code = main(["run", str(HEAT1D), "--preset", "quick", "--out", str(out), "--no-progress"])
    assert code == 0
    return out, json.loads((out / "results.json").read_text())


def test_curves_equal_results(prdp_run):
    out, result = prdp_run
    curves = _curves(out)
    epochs = result["epochs"]
    assert len(epochs) == result["totals"]["epochs"] == result["requested_epochs"]
    for tag in ("loss/train", "metric/validation", "solver/K", "solver/inner_iterations"):
        steps, _ = curves[tag]
        assert steps == [e["epoch"] for e in epochs] == list(range(len(epochs)))
    assert curves["loss/train"][1] == _float32(e["train_loss"] for e in epochs)
    assert curves["metric/validation"][1] == _float32(e["val_metric"] for e in epochs)
    assert curves["solver/K"][1] == [e["k"] for e in epochs]
    inner = np.cumsum([e["fwd_iterations"] + e["adj_iterations"] for e in epochs])
    assert curves["solver/inner_iterations"][1] == inner.tolist()
    assert curves["time/wall"][1][-1] == pytest.approx(result["totals"]["wall_time"], rel=1e-6)


def test_k_never_decreases(prdp_run):
    out, result = prdp_run
    k = _curves(out)["solver/K"][1]
    assert all(b >= a for a, b in zip(k, k[1:], strict=False))
    # PRDP refined on this run: the property is not that of a constant
    assert k[-1] > k[0] == result["prdp"]["k_init"]


def test_hparams_name_the_run(prdp_run):
    out, result = prdp_run
    events = EventAccumulator(str(out))
    events.Reload()
    content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hparams = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
    assert hparams["scene"].string_value == "heat1d"
    assert hparams["preset"].string_value == "quick"
    assert hparams["schedule"].string_value == "prdp"
    assert hparams["route"].string_value == "richardson/jacobi"  # the scene's solver
    assert hparams["seed"].number_value == result["seed"] == 0


def test_resumed_run_continues_its_curves(prdp_run, tmp_path):
    _, whole = prdp_run
    run(HEAT1D, "prdp", epochs=5, out=tmp_path, progress=False)
    resumed = run(resume=tmp_path, epochs=whole["requested_epochs"], progress=False)
    curves = _curves(tmp_path)
    epochs = resumed["epochs"]
    assert curves["solver/K"][0] == list(range(len(epochs)))  # every epoch once
    assert curves["solver/K"][1] == [e["k"] for e in whole["epochs"]]
    inner = np.cumsum([e["fwd_iterations"] + e["adj_iterations"] for e in epochs])
    assert curves["solver/inner_iterations"][1] == inner.tolist()  # counted from epoch 0


def test_compare_writes_one_tensorboard_run_per_schedule(tmp_path):
    summary = compare(HEAT1D, preset="quick", epochs=3, out=tmp_path, progress=False, routes=())
    runs = EventMultiplexer().AddRunsFromDirectory(str(tmp_path))
    runs.Reload()
    folders = {name.replace(":", "_") for name in summary["runs"]}
    assert set(runs.Runs()) == folders
    for name in folders:
        assert runs.Scalars(name, "solver/K")[-1].step == 2
        result = json.loads((tmp_path / name / "results.json").read_text())
        assert [e.value for e in runs.Scalars(name, "loss/train")] == _float32(
            e["train_loss"] for e in result["epochs"]
        )


def test_checks_are_counted_once_in_their_epoch(tmp_path):
    result = run(HEAT1D, "auto", out=tmp_path, progress=False)
    curves = _curves(tmp_path)
    steps, checks = curves["prdp/check_iterations"]
    checks = dict(zip(steps, checks, strict=True))
    inner = np.diff([0, *curves["solver/inner_iterations"][1]])
    k = curves["solver/K"][1]
    per_k = inner[0] / k[0]  # epoch 0 makes no check: training alone, per unit of K
    assert 0 not in checks and len(curves["prdp/check_gap"][0]) >= 1
    for epoch in range(len(k)):  # what an epoch ran beyond training is its checks' cost
        made = checks.get(epoch, 0) - checks.get(epoch - 1, 0)
        assert inner[epoch] - made == per_k * k[epoch]
    assert result["certificate"]["cost"] > 0  # the certificate at the end, last epoch's
    assert made == result["certificate"]["cost"]
