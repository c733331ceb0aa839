"""The ``auto`` schedule: `PRDP.for_problem` inside the harness, with a gradient check,
and ``prdp-petsc defaults`` (the default construction beside a scene's tuned settings)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from prdp_petsc import PRDP
from prdp_petsc.lab.cli import main
from prdp_petsc.lab.reports.defaults import format_defaults
from prdp_petsc.lab.training.harness import build_scene, find_k_full, run
from prdp_petsc.lab.training.scene import load_scene
from prdp_petsc.lab.training.schedules import gradient_check, parse_schedule

HEAT1D = Path(__file__).parents[2] / "demos" / "heat1d.py"


def test_auto_is_a_schedule():
    assert parse_schedule("auto").kind == "auto"
    with pytest.raises(ValueError, match="'auto'"):
        parse_schedule("automatic")


def test_auto_run_starts_at_an_eighth_of_k_full_and_ends_certified(tmp_path):
    result = run(HEAT1D, "auto", preset="quick", seed=1, progress=False, out=tmp_path)
    k_full = result["prdp"]["k_full"]
    ks = [e["k"] for e in result["epochs"]]
    assert ks[0] == -(-k_full // 8) and ks == sorted(ks) and ks[-1] <= k_full
    levels = {-(-k_full // 2**j) for j in range(4)}  # K_full/8, /4, /2 and K_full
    assert set(ks) <= levels
    cert = result["certificate"]
    assert cert["k"] == ks[-1] and cert["k_full"] == k_full
    assert cert["certified"] == (cert["gap"] <= cert["tol"])
    assert json.loads((tmp_path / "results.json").read_text())["certificate"] == cert


def test_gradient_check_is_the_training_gradient_and_leaves_no_trace():
    module = load_scene(HEAT1D)
    scene = build_scene(module, "quick", 0)
    k_full = find_k_full(scene)
    check = gradient_check(scene)
    before = [s.max_it for s in scene.solvers]
    g_full, g_one = check(k_full), check(1)
    assert [s.max_it for s in scene.solvers] == before
    params = [p for g in scene.optimizer.param_groups for p in g["params"]]
    assert g_full.shape == (sum(p.numel() for p in params),)
    assert all(p.grad is None for p in params)
    assert np.allclose(check(k_full), g_full)  # the same fixed batch every time
    assert np.linalg.norm(g_one - g_full) > 0.05 * np.linalg.norm(g_full)


def test_defaults_report(tmp_path, capsys):
    rc = main(["defaults", str(HEAT1D), "--preset", "quick", "--seeds", "0", "--out",
               str(tmp_path)])  # fmt: skip
    assert rc == 0
    result = json.loads((tmp_path / "defaults.json").read_text())
    row = result["per_seed"][0]
    for name in ("tuned", "default"):
        r = row[name]
        assert r["ratio"] == pytest.approx(r["final_val_error"] / row["full"]["final_val_error"])
        assert r["saved"] == pytest.approx(1 - r["iterations"] / row["full"]["iterations"])
        assert result[name]["compared"] == 1
        equal = r["ratio"] <= 1.05  # one seed: saved at equal accuracy is its own saving, or none
        assert r["equal_accuracy"] == equal and result[name]["equal_accuracy"] == int(equal)
        assert result[name]["saved_at_equal_accuracy"] == (r["saved"] if equal else None)
    assert row["default"]["certified"] in (True, False)
    assert row["tuned"]["certified"] is None  # the tuned controller runs no checks
    assert "default: error ratio" in capsys.readouterr().out
    assert "tuned: error ratio" in format_defaults(result)
    # the default run starts where PRDP.for_problem puts it from the scene's own probe
    from prdp_petsc.lab.training.probe import probe

    start = PRDP.for_problem(probe(build_scene(load_scene(HEAT1D), "quick", 0))).k_init
    run = json.loads((tmp_path / "seed_0" / "default" / "results.json").read_text())
    assert run["epochs"][0]["k"] == start == row["start"]
    assert str(start) in row["probe_errors"]  # what chose the start is on record
    # every check of the run is on record, the end's certificate last, and printed
    checks = run["checks"]
    assert checks and checks == row["default"]["checks"]
    if run["certificate"]["k"] < row["k_full"]:  # at K_full the end compares nothing
        assert checks[-1] == run["certificate"]
    assert [c["k"] for c in checks] == sorted(c["k"] for c in checks)
    line = next(x for x in format_defaults(result).splitlines() if x.startswith("seed 0 default"))
    assert f"started at K={start}" in line and line.count("gap") == len(checks)


def test_a_check_never_trains_a_scene_whose_loss_steps_its_optimiser():
    # poisson_field's loss takes `steps - 1` Adam steps before returning the last loss
    scene = build_scene(load_scene(HEAT1D.parent / "poisson_field.py"), "quick", 0)
    theta = scene.optimizer.param_groups[0]["params"][0]
    before = theta.detach().clone()
    check = gradient_check(scene)
    first = check(20)
    assert torch.equal(theta.detach(), before)
    assert not scene.optimizer.state  # Adam has taken no step
    assert np.array_equal(check(20), first)  # the same weights, the same batch


def test_a_scenes_check_loss_is_what_the_check_differentiates():
    # poisson3d's epoch is `steps` Adam steps (as many solves); its check is one solve
    scene = build_scene(load_scene(HEAT1D.parent / "poisson3d.py"), "quick", 0)
    check = gradient_check(scene)
    g = check(4)
    spent, _ = check.spent()
    assert 0 < spent <= 2 * 4  # one forward and one adjoint solve at K = 4
    theta = scene.optimizer.param_groups[0]["params"][0]
    for s in scene.solvers:
        s.max_it = 4
    (expected,) = torch.autograd.grad(scene.check_loss(), [theta])
    assert np.allclose(g, expected.numpy())
    assert not scene.optimizer.state  # the check took no Adam step


def test_defaults_baselines_name_the_best_constant_cap_at_equal_accuracy(tmp_path):
    from prdp_petsc.lab.reports.defaults import defaults
    from prdp_petsc.lab.training.accuracy import constant_caps

    result = defaults(HEAT1D, "quick", [0], baselines=True)
    row = result["per_seed"][0]
    caps = constant_caps(row["k_full"])
    assert result["baselines"] == list(caps) == ["K_full/8", "K_full/4", "K_full/2"]
    for label in caps:  # a constant cap's run saves what its cap says, to the iteration
        r, full = row[label], row["full"]
        assert r["k_final"] == caps[label]
        assert r["saved"] == pytest.approx(1 - r["iterations"] / full["iterations"])
        s = result[label]
        assert s["equal_over_seeds"] == (
            s["ratio"]["geometric_mean"] <= 1.05 and r["ratio"] <= 1.10
        )
    fits = [b for b in caps if result[b]["equal_over_seeds"]]
    assert result["best_constant"] == max(fits, key=lambda b: result[b]["saved"], default=None)
    assert "best constant cap at equal accuracy" in format_defaults(result) or not fits
    # beside each cap, the probe's error of the solve capped there (the default's start)
    printed = format_defaults(result)
    for label, cap in caps.items():
        line = next(x for x in printed.splitlines() if x.strip().startswith(label))
        assert line.rstrip().endswith(f"{100 * row['probe_errors'][str(cap)]:.1f} %")


def test_check_lines_mark_a_certified_k_that_was_refined_all_the_same():
    from prdp_petsc.lab.reports.defaults import check_lines

    def check(epoch, k, reference, gap, certified):
        return {"epoch": epoch, "k": k, "reference": reference, "k_full": 40, "gap": gap,
                "descent": 1.0, "certified": certified}  # fmt: skip

    near = [check(2, 5, 10, 0.3, False), check(5, 10, 20, 0.04, True), check(8, 20, 40, 0.01, True)]
    row = {"seed": 0, "k_full": 40, "start": 5, "probe_errors": {"5": 0.12},
           "default": {"k_final": 20, "checks": near}}  # fmt: skip
    (line,) = check_lines({"per_seed": [row]})
    assert line.startswith("seed 0 default: started at K=5 (the probe's solve there: 12.0 % off)")
    parts = line.split("; ")[1:]
    assert "✗" in parts[0] and "refined" in parts[1] and "refined" not in parts[2]
    row["default"]["k_final"] = 40  # the last certified K refined too
    assert check_lines({"per_seed": [row]})[0].endswith("refined)")
    assert check_lines({"per_seed": [{"seed": 1, "default": {}}]}) == []  # nothing on record


def test_defaults_resume_reads_finished_runs_and_trains_the_missing_ones(tmp_path):
    import shutil

    from prdp_petsc.lab.reports.defaults import defaults, notes

    first = defaults(HEAT1D, "quick", [0], out=tmp_path)
    assert "reused" not in first
    shutil.rmtree(tmp_path / "seed_0" / "default")
    again = defaults(HEAT1D, "quick", [0], out=tmp_path, resume=True)
    assert again["reused"] == ["seed 0 full", "seed 0 tuned"]
    before, after = first["per_seed"][0], again["per_seed"][0]
    assert after["full"] == before["full"] and after["tuned"] == before["tuned"]  # read back
    assert after["default"]["iterations"] == before["default"]["iterations"]  # trained again
    assert any("--resume" in line for line in notes(again))
