"""Training harness: run / compare on the heat1d scene (quick preset), CLI, divergence."""

import json
from pathlib import Path

import numpy as np
import pytest
from petsc4py import PETSc

from prdp_petsc.cli import main
from prdp_petsc.training.compare import compare
from prdp_petsc.training.harness import parse_schedule, run

HEAT1D = Path(__file__).resolve().parent.parent / "demos" / "heat1d.py"


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    return out, compare(HEAT1D, preset="quick", out=out, progress=False)


def test_compare_summary_is_complete(summary):
    out, s = summary
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["k_full"] == s["k_full"] > 1
    assert set(on_disk) >= {"scene", "k_full", "runs", "savings", "val_error_ratio", "plots"}
    full = f"fixed:{s['k_full']}"
    assert "prdp" in s["runs"] and full in s["runs"] and "fixed:1" in s["runs"]
    for r in s["runs"].values():
        assert set(r) >= {
            "final_val_error",
            "wall_time",
            "fwd_iterations",
            "adj_iterations",
            "k_final",
        }
        assert np.isfinite(r["final_val_error"]) and r["wall_time"] > 0
    assert s["runs"][full]["k_final"] == s["k_full"]
    for name in on_disk["plots"]:
        assert (out / name).stat().st_size > 1000


def test_savings_match_logged_iterations(summary):
    out, s = summary
    prdp = json.loads((out / "prdp" / "results.json").read_text())
    full = json.loads((out / f"fixed_{s['k_full']}" / "results.json").read_text())
    inner = sum(e["fwd_iterations"] + e["adj_iterations"] for e in prdp["epochs"])
    inner_full = sum(e["fwd_iterations"] + e["adj_iterations"] for e in full["epochs"])
    assert s["savings"]["iterations"] == pytest.approx(1 - inner / inner_full, rel=1e-12)
    # fixed mode: every forward and adjoint solve runs exactly K iterations
    epoch = full["epochs"][0]
    assert epoch["fwd_iterations"] == epoch["adj_iterations"]
    assert epoch["fwd_iterations"] % s["k_full"] == 0
    n_solves = epoch["fwd_iterations"] // s["k_full"]
    for e in prdp["epochs"]:
        assert e["fwd_iterations"] == e["k"] * n_solves
    ic = 1 - prdp["epochs"][-1]["k"] / s["k_full"]
    assert s["savings"]["ic"] == pytest.approx(ic, rel=1e-12)
    assert s["savings"]["pr"] == pytest.approx(s["savings"]["iterations"] - ic, rel=1e-12)
    assert s["val_error_ratio"] == pytest.approx(
        s["runs"]["prdp"]["final_val_error"] / s["runs"][f"fixed:{s['k_full']}"]["final_val_error"]
    )


def test_run_is_deterministic(tmp_path):
    a = run(HEAT1D, "fixed:3", epochs=3, seed=1, out=tmp_path / "a", progress=False)
    b = run(HEAT1D, "fixed:3", epochs=3, seed=1, out=tmp_path / "b", progress=False)
    c = run(HEAT1D, "fixed:3", epochs=3, seed=2, progress=False)
    va = [e["val_metric"] for e in a["epochs"]]
    assert va == [e["val_metric"] for e in b["epochs"]]
    assert va != [e["val_metric"] for e in c["epochs"]]
    assert json.loads((tmp_path / "a" / "results.json").read_text())["totals"]["epochs"] == 3


def test_parse_schedule():
    assert parse_schedule("prdp") is None
    assert parse_schedule("fixed:7") == 7
    for bad in ("fixed:0", "fixed:x", "adaptive"):
        with pytest.raises(ValueError):
            parse_schedule(bad)


def test_cli_run_passes_petsc_options(tmp_path):
    opts = PETSc.Options()
    try:
        rc = main(
            [
                "run",
                str(HEAT1D),
                "--schedule",
                "fixed:4",
                "--epochs",
                "2",
                "--out",
                str(tmp_path),
                "--no-progress",
                "-heat_ksp_type",
                "cg",
            ]
        )
    finally:
        opts.delValue("heat_ksp_type")
    assert rc == 0
    result = json.loads((tmp_path / "results.json").read_text())
    # the adjoint inherits the command-line forward options
    assert result["ksp"] == {
        "ksp_type": "cg",
        "pc_type": "jacobi",
        "adjoint_ksp_type": "cg",
        "adjoint_pc_type": "jacobi",
    }
    assert [e["k"] for e in result["epochs"]] == [4, 4]


DIVERGING_SCENE = """
import numpy as np, scipy.sparse as sp, torch
import prdp_petsc as pp

PRESETS = {"quick": {}}

def build(config, seed):
    A = (sp.identity(10) - 1e-2 * pp.laplacian(10)).tocsr()
    solver = pp.KSPSolver({"ksp_type": "richardson", "pc_type": "jacobi",
                           "ksp_richardson_scale": 3.0}, prefix="div_", max_it=1)
    theta = torch.ones(10, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([theta], lr=0.1)
    metric = iter(range(1, 100))  # gets worse every epoch: PRDP refines every epoch
    return pp.Scene(
        solvers=[solver], optimizer=opt, batches=lambda e, g: [None],
        loss=lambda _: pp.solve(A, theta, solver).square().sum(),
        validate=lambda: float(next(metric)), probe=lambda: (A, np.ones(10)), epochs=20,
        prdp={"window": 1, "ema_window": 1, "k_step": 4},
    )
"""


def test_diverged_solve_stops_cleanly(tmp_path):
    scene = tmp_path / "diverging.py"
    scene.write_text(DIVERGING_SCENE)
    # K grows by 4 per epoch; Richardson with scale 3 amplifies the error ~2x per
    # iteration, so PETSc's DTOL (1e5) stops it after ~17 iterations
    result = run(scene, "prdp", out=tmp_path / "out", progress=False)
    stopped = result["stopped"]
    assert stopped is not None and stopped["reason"] == "DIVERGED_DTOL"
    on_disk = json.loads((tmp_path / "out" / "results.json").read_text())
    assert on_disk["stopped"]["epoch"] == stopped["epoch"] == len(on_disk["epochs"]) > 0
