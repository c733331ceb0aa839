"""Run-to-run noise: the torch seed, compare's twin, compare over seeds."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from prdp_petsc.lab.cli import main
from prdp_petsc.lab.parsing import parse_seeds
from prdp_petsc.lab.training.compare import TWIN_SEED_OFFSET, compare
from prdp_petsc.lab.training.harness import build_scene, run
from prdp_petsc.lab.training.scene import load_scene, preset_config
from prdp_petsc.lab.training.seeds import (
    _aggregate,
    compare_seeds,
    equal_accuracy_savings,
    format_ratio,
    format_seeds,
    optional_ratio_statistics,
    ratio_statistics,
)

HEAT1D = Path(__file__).resolve().parents[2] / "demos" / "heat1d.py"


def test_parse_seeds():
    assert parse_seeds("3") == [3]
    assert parse_seeds("0-2,7") == [0, 1, 2, 7]
    assert parse_seeds("1,1,0-1") == [1, 0]
    for bad in ("", "a", "3-1", "1-x", ","):
        with pytest.raises(ValueError, match="seeds"):
            parse_seeds(bad)


def test_ratio_statistics_on_a_log_scale():
    # 2 and 1/2 are equally far from 1: the geometric mean is 1
    s = ratio_statistics([2.0, 0.5])
    assert s["geometric_mean"] == pytest.approx(1.0)
    lo, hi = s["interval"]
    assert lo == pytest.approx(1 / hi)  # symmetric on the log scale
    # t(0.975, 1) = 12.706; sd of log(2), -log(2) is sqrt(2) log 2; / sqrt(2)
    assert math.log(hi) == pytest.approx(12.7062 * math.log(2), rel=1e-4)
    same = ratio_statistics([1.1, 1.1, 1.1])
    assert same["geometric_mean"] == pytest.approx(1.1)
    assert same["interval"] == pytest.approx([1.1, 1.1])
    assert ratio_statistics([1.2])["interval"] is None
    assert ratio_statistics([1.0, math.inf])["geometric_mean"] == math.inf


def test_optional_ratio_statistics_without_a_ratio():
    assert optional_ratio_statistics([]) == {"geometric_mean": None, "interval": None, "n": 0}
    assert optional_ratio_statistics([4.0, 1.0]) == ratio_statistics([4.0, 1.0])


def test_format_ratio_writes_the_mean_its_interval_and_a_note():
    stats = {"geometric_mean": 2.0, "interval": [1.5, 2.75], "n": 3}
    assert format_ratio(stats) == "2.000 (95 % interval 1.500–2.750)"
    assert format_ratio(stats, ".2f", "×", "n = 3") == "2.00× (95 % interval 1.50–2.75, n = 3)"
    assert format_ratio(stats, ci_spec=".1f") == "2.000 (95 % interval 1.5–2.8)"
    one = {"geometric_mean": 1.25, "interval": None, "n": 1}
    assert format_ratio(one, ".2f", "×") == "1.25×"
    assert format_ratio(one, extra="n = 1") == "1.250 (n = 1)"
    none = optional_ratio_statistics([])
    assert format_ratio(none, extra="n = 0") == "— (n = 0)"
    assert format_ratio(None) == "—"


def test_equal_accuracy_savings_count_the_seeds_at_equal_accuracy_only():
    rows = [
        {"equal_accuracy": True, "iterations_saved": 0.2, "wall_time_saved": 0.1, "saved": 0.3},
        {"equal_accuracy": False, "iterations_saved": 0.9, "wall_time_saved": 0.9, "saved": 0.9},
        {"equal_accuracy": True, "iterations_saved": 0.6, "wall_time_saved": -0.1, "saved": 0.5},
    ]
    out = equal_accuracy_savings(rows)
    assert out["seeds"] == 2  # the second seed ended behind: nothing saved at equal accuracy
    assert out["iterations_saved"] == pytest.approx({"mean": 0.4, "min": 0.2, "max": 0.6})
    assert out["wall_time_saved"] == pytest.approx({"mean": 0.0, "min": -0.1, "max": 0.1})
    assert equal_accuracy_savings(rows, keys=("saved",)) == {
        "seeds": 2, "saved": pytest.approx({"mean": 0.4, "min": 0.3, "max": 0.5})
    }  # fmt: skip
    assert equal_accuracy_savings([rows[1]]) is None


def test_torch_seed_changes_the_network_not_the_data(tmp_path):
    kwargs = dict(epochs=3, seed=1, progress=False)
    module = load_scene(HEAT1D)
    base = run(HEAT1D, "fixed:5", **kwargs)
    same = run(HEAT1D, "fixed:5", torch_seed=1, **kwargs)
    other = run(HEAT1D, "fixed:5", torch_seed=7, out=tmp_path, **kwargs)
    val = [e["val_metric"] for e in base["epochs"]]
    assert val == [e["val_metric"] for e in same["epochs"]]
    assert val != [e["val_metric"] for e in other["epochs"]]
    assert json.loads((tmp_path / "results.json").read_text())["torch_seed"] == 7
    assert base["torch_seed"] == 1
    a, b = build_scene(module, "quick", 1), build_scene(module, "quick", 1, torch_seed=7)
    assert np.array_equal(a.probe()[1], b.probe()[1])  # the same data
    first = [p.detach().clone() for p in a.optimizer.param_groups[0]["params"]]
    assert not all(torch.equal(p, q) for p, q in zip(first, b.optimizer.param_groups[0]["params"]))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("seeds")
    return out, compare_seeds(HEAT1D, [0, 1], preset="quick", out=out, progress=False, plots=False)


def test_compare_twin_is_full_fidelity_in_another_order(study):
    out, result = study
    summary = json.loads((out / "seed_1" / "summary.json").read_text())
    k = summary["k_full"]
    twin = json.loads((out / "seed_1" / f"twin_{k}" / "results.json").read_text())
    full = json.loads((out / "seed_1" / f"fixed_{k}" / "results.json").read_text())
    assert twin["schedule"] == full["schedule"] == f"fixed:{k}"
    assert twin["seed"] == full["seed"] == 1
    assert twin["torch_seed"] == 1 + TWIN_SEED_OFFSET and full["torch_seed"] == 1
    assert summary["noise_ratio"] == pytest.approx(
        twin["totals"]["final_val_error"] / full["totals"]["final_val_error"]
    )
    assert summary["noise_ratio"] != 1.0  # other initial weights do change training
    assert f"twin:{k}" in summary["runs"]


def test_compare_seeds_aggregates_what_each_seed_measured(study):
    """Each row holds what that seed's runs wrote (read back from their files); the
    statistics over the rows are checked on literal numbers in
    `test_aggregate_on_hand_computed_rows`."""
    out, result = study
    assert json.loads((out / "seeds.json").read_text())["per_seed"] == result["per_seed"]
    rows = result["per_seed"]
    assert [r["seed"] for r in rows] == [0, 1]
    for r in rows:
        folder = out / f"seed_{r['seed']}"
        summary = json.loads((folder / "summary.json").read_text())
        k = summary["k_full"]

        def last(name):
            log = json.loads((folder / name / "results.json").read_text())
            return log["epochs"][-1]["val_metric"]

        assert r["k_full"] == k
        assert r["prdp_val_error"] == last("prdp")
        assert r["full_val_error"] == last(f"fixed_{k}")
        assert r["twin_val_error"] == last(f"twin_{k}")
        assert r["prdp_ratio"] == summary["val_error_ratio"]
        assert r["twin_ratio"] == summary["noise_ratio"]
        assert r["iterations_saved"] == summary["savings"]["iterations"]
        assert r["wall_time_saved"] == summary["savings"]["wall_time"]
    assert result["compared"] == result["prdp_ratio"]["n"] == 2
    table = format_seeds(result)
    assert "PRDP / full: geometric mean" in table and "twin / full" in table
    assert f"met on {result['equal_accuracy']} of 2 seeds" in table


def test_aggregate_on_hand_computed_rows():
    rows = [_row(0, 2.0, twin=1.0, saved=0.2), _row(1, 0.5, twin=1.0, saved=0.5),
            _row(2, 1.0, twin=4.0, saved=0.8)]  # fmt: skip
    result = _aggregate("s", [0, 1, 2], rows)
    # (2 × 0.5 × 1)^(1/3) = 1; (1 × 1 × 4)^(1/3) = 4^(1/3)
    assert result["prdp_ratio"]["geometric_mean"] == pytest.approx(1.0)
    assert result["twin_ratio"]["geometric_mean"] == pytest.approx(4 ** (1 / 3))
    # savings count only the seeds at equal accuracy (ratios 0.5 and 1.0 <= 1.05): the
    # seed whose PRDP ended 2x full fidelity's error saved nothing
    assert result["savings"]["seeds"] == 2
    saved = result["savings"]["iterations_saved"]
    assert saved == pytest.approx({"mean": 0.65, "min": 0.5, "max": 0.8})
    assert result["equal_accuracy"] == 2 and result["compared"] == 3
    assert "savings over the 2 of 3 seeds at equal accuracy" in format_seeds(result)
    behind = _aggregate("s", [0], [_row(0, 2.0, twin=1.0, saved=0.9)])
    assert behind["savings"] is None
    assert "savings: none at equal accuracy" in format_seeds(behind)


def test_cli_compare_seeds(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = main(
        ["compare", str(HEAT1D), "--seeds", "0-1", "--epochs", "2", "--out", str(out),
         "--no-progress"]
    )  # fmt: skip
    assert rc == 0
    text = capsys.readouterr().out
    assert "seed 0\n" in text and "seed 1\n" in text and "PRDP / full" in text
    assert (out / "seeds.json").is_file() and (out / "seed_1" / "summary.json").is_file()
    assert json.loads((out / "seeds.json").read_text())["plot"] == "seeds.png"
    assert (out / "seeds.png").stat().st_size > 1000
    with pytest.raises(SystemExit):  # one seed or several, not both
        main(["compare", str(HEAT1D), "--seed", "1", "--seeds", "0-1", "--out", str(out)])


def test_single_compare_without_twin_has_no_noise_ratio(tmp_path):
    s = compare(HEAT1D, preset="quick", epochs=1, out=tmp_path, progress=False, plots=False)
    assert "noise_ratio" not in s and not any(n.startswith("twin") for n in s["runs"])


def test_preset_with_changed_settings(caplog):
    module = load_scene(HEAT1D)
    config = preset_config(module, "quick epochs=2 lr=5e-3 name=abc")
    assert config["epochs"] == 2 and config["lr"] == 5e-3
    assert {k: v for k, v in config.items() if k not in ("epochs", "lr", "name")} == {
        k: v for k, v in module.PRESETS["quick"].items() if k not in ("epochs", "lr")
    }
    assert config["name"] == "abc" and "'name' is in no preset" in caplog.text
    assert preset_config(module, "quick") == module.PRESETS["quick"]
    with pytest.raises(ValueError, match="preset must be one of"):
        preset_config(module, "nope epochs=2")
    for bad in ("quick epochs", "quick =2", "quick epochs="):
        with pytest.raises(ValueError, match="key=value"):
            preset_config(module, bad)


def test_cli_set_changes_the_run(tmp_path, capsys):
    rc = main(["run", str(HEAT1D), "--schedule", "fixed:3", "--set", "epochs=2", "--set",
               "lr=1e-3", "--out", str(tmp_path), "--no-progress"])  # fmt: skip
    assert rc == 0
    result = json.loads((tmp_path / "results.json").read_text())
    assert result["preset"] == "quick epochs=2 lr=1e-3" and len(result["epochs"]) == 2
    with pytest.raises(SystemExit):
        main(["run", str(HEAT1D), "--set", "epochs", "--out", str(tmp_path)])
    assert "KEY=VALUE" in capsys.readouterr().err


def test_settings_take_the_presets_types():
    module = load_scene(Path(__file__).resolve().parents[2] / "demos" / "ns2d.py")
    config = preset_config(module, "quick solver_grad=false lr=1 adjoint_rtol=1e-6 val_solver=x")
    assert config["solver_grad"] is False
    assert config["lr"] == 1.0 and isinstance(config["lr"], float)
    assert config["adjoint_rtol"] == 1e-6 and config["val_solver"] == "x"
    assert preset_config(module, "quick solver_grad=True")["solver_grad"] is True
    for bad, why in (("epochs=2.0", "integer"), ("solver_grad=yes", "true or false"),
                     ("lr=abc", "cannot read"), ("lr=True", "number")):  # fmt: skip
        with pytest.raises(ValueError, match=why):
            preset_config(module, f"quick {bad}")
    with pytest.raises(ValueError, match="preset must be one of"):
        preset_config(module, "")


def _row(seed, prdp, twin=1.0, stopped=(), saved=0.5):
    if prdp is None:
        return {"seed": seed, "k_full": 9, "savings_unavailable": "no savings: prdp stopped",
                "stopped": list(stopped)}  # fmt: skip
    return {"seed": seed, "k_full": 9, "prdp_val_error": prdp, "full_val_error": 1.0,
            "twin_val_error": twin, "prdp_k_final": 3, "stopped": list(stopped),
            "prdp_ratio": prdp, "twin_ratio": twin, "iterations_saved": saved,
            "wall_time_saved": 0.4, "equal_accuracy": prdp <= 1.05}  # fmt: skip


def test_a_seed_without_comparison_counts_against_the_test():
    rows = [_row(0, 1.0), _row(1, 1.02), _row(2, None, stopped=["prdp"])]
    result = _aggregate("s", [0, 1, 2], rows)
    assert result["compared"] == 2 and result["prdp_ratio"]["n"] == 2
    table = format_seeds(result)
    assert "met on 2 of 3 seeds (1 without a comparison" in table
    assert "no savings: prdp stopped" in table


@pytest.mark.parametrize(
    "ratios, verdict",
    [
        ((1.0, 1.01, 1.02), "within 5 %"),
        ((1.3, 1.32, 1.31), "behind"),
        ((0.99, 1.12, 1.05), "cannot decide"),
    ],  # fmt: skip
)
def test_the_interval_is_read_against_the_5_percent_test(ratios, verdict):
    rows = [_row(i, r) for i, r in enumerate(ratios)]
    table = format_seeds(_aggregate("s", list(range(len(rows))), rows))
    assert verdict in table and "n = 3)" in table


def test_ratio_statistics_edge_cases():
    with pytest.raises(ValueError):
        ratio_statistics([])
    assert ratio_statistics([0.0, 1.0])["geometric_mean"] == 0.0
    assert ratio_statistics([1.0, math.nan])["geometric_mean"] == math.inf


def test_an_interrupted_twin_keeps_the_summary(tmp_path, monkeypatch):
    import prdp_petsc.lab.training.compare as compare_module

    real = compare_module.run

    def run(scene_file, schedule, settings, **kwargs):
        if settings.torch_seed is not None:
            raise KeyboardInterrupt
        return real(scene_file, schedule, settings, **kwargs)

    monkeypatch.setattr(compare_module, "run", run)
    with pytest.raises(KeyboardInterrupt):
        compare(HEAT1D, epochs=1, out=tmp_path, progress=False, plots=False, twin=True)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert "prdp" in summary["runs"] and "savings" in summary
    assert not any(name.startswith("twin") for name in summary["runs"])


def test_compare_seeds_runs_each_seed_once(tmp_path, monkeypatch):
    import prdp_petsc.lab.training.seeds as seeds_module

    calls = []

    def fake(scene, *, seed, out, twin, **kwargs):
        calls.append(seed)
        return {"k_full": 9, "runs": {}, "savings_unavailable": "no savings: none ran"}

    monkeypatch.setattr(seeds_module, "compare", fake)
    monkeypatch.setattr(seeds_module, "format_table", lambda summary: "")
    result = compare_seeds(HEAT1D, [0, 0, 1], out=tmp_path)
    assert calls == [0, 1] and result["seeds"] == [0, 1]


def test_the_twin_is_not_a_route_to_the_target(tmp_path):
    s = compare(HEAT1D, epochs=2, out=tmp_path, progress=False, twin=True, routes=("cg/jacobi",))
    twin = f"twin:{s['k_full']}"
    assert twin in s["runs"] and "noise_ratio" in s
    assert twin not in s["fastest"]["seconds_to_target"]
    assert "prdp@cg/jacobi" in s["fastest"]["seconds_to_target"]
    assert (tmp_path / f"twin_{s['k_full']}" / "results.json").is_file()


def test_set_changes_prdp_settings_in_every_scene(caplog):
    # heat1d writes its PRDP settings into the scene, not from its config
    module = load_scene(HEAT1D)
    scene = build_scene(module, "quick k_step=3 tau_stop=0.95 k_max=None", 0)
    assert scene.prdp["k_step"] == 3 and scene.prdp["tau_stop"] == 0.95
    assert scene.prdp["k_max"] is None and "no preset" not in caplog.text
    assert build_scene(module, "quick", 0).prdp["k_step"] == 1
    with pytest.raises(ValueError, match="integer"):
        build_scene(module, "quick k_step=2.5", 0)
    result = run(HEAT1D, "prdp", preset="quick k_init=2", epochs=1, progress=False)
    assert result["prdp"]["k_init"] == 2 and result["epochs"][0]["k"] == 2
