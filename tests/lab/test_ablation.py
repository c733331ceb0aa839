"""The solver-only bound and ``prdp-petsc ablation``: which lever buys what."""

import json
import math
from pathlib import Path

import pytest

from prdp_petsc.lab.reports.ablation import KIND, ablation, format_ablation, lever_effect, main
from prdp_petsc.lab.reports.kinds import DataSet
from prdp_petsc.lab.training.seeds import format_seeds
from prdp_petsc.lab.training.summary import format_table, solver_bound, speedup_vs_best_full

HEAT1D = Path(__file__).resolve().parents[2] / "demos" / "heat1d.py"


def _log(walls, solver, vals):
    return {
        "epochs": [
            {"wall_time": w, "solver_time": s, "val_metric": v}
            for w, s, v in zip(walls, solver, vals, strict=True)
        ]
    }


def test_solver_bound_is_wall_over_the_time_outside_the_solver():
    assert solver_bound(_log([2, 2], [1.5, 1.5], [1, 1])) == pytest.approx(4.0)
    assert solver_bound(_log([1], [1], [1])) is None  # all in the solver: no bound
    assert solver_bound({"epochs": []}) is None
    assert solver_bound({"epochs": [{"wall_time": 1.0}]}) is None  # no solver time recorded
    logs = {
        "fixed:10": _log([2, 2], [1.0, 1.0], [0.5, 0.1]),  # 4 s, half in the solver
        "fixed:3@cg/icc": _log([1, 1], [0.75, 0.75], [0.2, 0.1]),  # best full, 3/4 solver
        "prdp": _log([0.5, 0.5], [0.1, 0.1], [0.3, 0.1]),
    }
    detail = speedup_vs_best_full(logs, {"": 10, "cg/icc": 3})["speedup"]
    assert detail["full"] == "fixed:3@cg/icc" and detail["solver_bound"] == pytest.approx(4.0)


def test_ablation_runs_each_lever_and_divides_the_baselines_times(tmp_path):
    report = ablation(HEAT1D, {"k2": "k_init=2"}, preset="quick", seeds=[0, 1], out=tmp_path,
                      epochs=3, twin=False, progress=False, plots=False)  # fmt: skip
    assert list(report["configs"]) == ["baseline", "k2"]
    assert report["configs"]["k2"]["preset"] == "quick k_init=2"
    for name in ("baseline", "k2"):  # each configuration is a compare --seeds of its own
        seeds = json.loads((tmp_path / name / "seeds.json").read_text())
        assert seeds["seeds"] == [0, 1] and len(seeds["per_seed"]) == 2
        summary = json.loads((tmp_path / name / "seed_1" / "summary.json").read_text())
        assert "twin:" not in " ".join(summary["runs"])  # twin=False reached compare
    k2 = json.loads((tmp_path / "k2" / "seed_0" / "prdp" / "results.json").read_text())
    assert k2["epochs"][0]["k"] == 2  # the lever's setting reached the run
    base, lever = (report["configs"][n]["result"]["per_seed"] for n in ("baseline", "k2"))
    want = [
        b["reduced_seconds"] / r["reduced_seconds"]
        for b, r in zip(base, lever, strict=True)
        if b.get("reduced_seconds") and r.get("reduced_seconds")
    ]
    got = report["effects"]["k2"]["reduced_vs_baseline"]
    assert want and got["n"] == len(want)  # reduced runs reach full accuracy on heat1d quick
    geo = math.exp(sum(map(math.log, want)) / len(want))
    assert got["geometric_mean"] == pytest.approx(geo, rel=1e-12)
    assert json.loads((tmp_path / "ablation.json").read_text())["effects"] == report["effects"]
    text = format_ablation(report)
    assert "k2" in text and "k_init=2" in text and "baseline time / lever time" in text
    ds = DataSet("abl", KIND, {}, {"ablation.json": report}, [])
    rows = KIND.headline(ds)
    assert len(rows) == 1 and "lever `k2` (k_init=2)" in rows[0][0]
    assert "as fast as the baseline's: fastest reduced run" in rows[0][1]
    assert "Which lever buys what" in KIND.title(ds)


def test_lever_effect_skips_seeds_where_either_side_never_reached():
    base = {"per_seed": [{"seed": 0, "reduced_seconds": 4.0, "full_seconds": 8.0},
                         {"seed": 1}]}  # fmt: skip
    lever = {"per_seed": [{"seed": 0, "reduced_seconds": 2.0, "full_seconds": 8.0},
                          {"seed": 1, "reduced_seconds": 1.0, "full_seconds": 1.0}]}  # fmt: skip
    effect = lever_effect(base, lever)
    assert effect["reduced_vs_baseline"]["geometric_mean"] == pytest.approx(2.0)
    assert effect["reduced_vs_baseline"]["n"] == 1
    assert effect["full_vs_baseline"]["geometric_mean"] == pytest.approx(1.0)


def test_the_seeds_table_and_compare_table_print_the_bound(tmp_path):
    report = ablation(HEAT1D, {}, preset="quick", seeds=[0], out=tmp_path, epochs=2,
                      twin=False, progress=False, plots=False)  # fmt: skip
    result = report["configs"]["baseline"]["result"]
    summary = json.loads((tmp_path / "baseline" / "seed_0" / "summary.json").read_text())
    assert summary["speedup"]["solver_bound"] > 1
    assert "solver-only bound" in format_table(summary)
    assert result["per_seed"][0]["solver_bound"] == summary["speedup"]["solver_bound"]
    assert "solver-only bound" in format_seeds(result)
    reach = {n: r["time_to_full_accuracy"] for n, r in summary["runs"].items()}
    assert result["per_seed"][0]["reach_seconds"] == reach
    assert "prdp vs full" in result["levers"]
    assert "time to full-fidelity accuracy, B / A" in format_seeds(result)
    assert "read from an earlier comparison" not in format_seeds(result)
    again = ablation(HEAT1D, {}, preset="quick", seeds=[0], out=tmp_path, epochs=2, twin=False,
                     progress=False, plots=False, resume=True)  # fmt: skip
    again = again["configs"]["baseline"]["result"]
    row = again["per_seed"][0]
    assert len(row["reused"]) == row["runs"] == len(summary["runs"])  # nothing trained again
    assert f"{row['runs']} of {row['runs']} runs were read" in format_seeds(again)


@pytest.mark.parametrize(
    "lever", [["warm"], ["warm", "warm_start_epochs"], ["baseline", "k_init=2"]]
)
def test_a_malformed_lever_is_a_usage_error(lever, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main([str(HEAT1D), "--lever", *lever, "--out", str(tmp_path)])
    assert stop.value.code == 2
