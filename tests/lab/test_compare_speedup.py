"""Time to full-fidelity accuracy, the speedup over the best full-fidelity route, the
routes a scene declares and the ``rtol`` schedule (PRDP moving PETSc's rtol)."""

import json
import math
from pathlib import Path

import pytest

import prdp_petsc.lab.training.compare as compare_module
import prdp_petsc.lab.training.seeds as seeds_module
from prdp_petsc.errors import SolverError
from prdp_petsc.lab.cli.training import make_parser
from prdp_petsc.lab.training.accuracy import time_to_accuracy
from prdp_petsc.lab.training.compare import compare, scene_routes
from prdp_petsc.lab.training.harness import load_trained, release, run
from prdp_petsc.lab.training.routes import parse_routes
from prdp_petsc.lab.training.scene import load_scene
from prdp_petsc.lab.training.schedules import (
    RTOL_FACTOR,
    RTOL_INIT,
    RTOL_MAX_IT_FACTOR,
    rtol_from_level,
    rtol_levels,
)
from prdp_petsc.lab.training.seeds import _aggregate, compare_seeds, format_seeds
from prdp_petsc.lab.training.summary import format_table, speedup_vs_best_full, summarize
from prdp_petsc.prdp import PRDP

DEMOS = Path(__file__).resolve().parents[2] / "demos"
HEAT1D, HEAT2D = DEMOS / "heat1d.py", DEMOS / "heat.py"

#: Student's t quantile t_{0.975} with one degree of freedom (two seeds)
T_1 = 12.706204736174707


def log(errors, walls, stopped=None, k=1):
    """A run's log as `run` returns it: validation errors and wall times per epoch."""
    epochs = [
        {"epoch": i, "k": k, "val_metric": e, "wall_time": w, "solver_time": w / 2,
         "fwd_iterations": k, "adj_iterations": k, "train_loss": 0.0}
        for i, (e, w) in enumerate(zip(errors, walls))
    ]  # fmt: skip
    totals = {"epochs": len(epochs)}
    if epochs:
        totals.update(
            final_val_error=errors[-1], best_val_error=min(errors), wall_time=sum(walls),
            solver_time=sum(walls) / 2, fwd_iterations=k * len(epochs),
            adj_iterations=k * len(epochs), k_final=k,
        )  # fmt: skip
    return {"epochs": epochs, "totals": totals, "stopped": stopped}


def runs_on_two_routes():
    """Full fidelity is fixed:10 (scene) and fixed:3@cg/icc; the target is 1.05 x 0.1."""
    return {
        "fixed:10": log([0.5, 0.2, 0.1], [2, 2, 2]),  # reaches 0.105 at epoch 3: 6 s
        "fixed:3@cg/icc": log([0.3, 0.104, 0.1], [1, 1, 1]),  # epoch 2: 2 s, best full
        "prdp": log([0.5, 0.2, 0.103], [0.5, 0.5, 0.5]),  # epoch 3: 1.5 s
        "prdp@cg/icc": log([0.2, 0.1, 0.1], [0.4, 0.4, 0.4]),  # epoch 2: 0.8 s, best reduced
        "rtol@cg/icc": log([0.1, 0.1, 0.2], [0.1, 0.1, 0.1]),  # drifts back above: never
        "fixed:1": log([0.1, 0.1], [0.05, 0.05], {"epoch": 2, "reason": "DIVERGED_DTOL"}),
        "twin:10": log([0.1, 0.1, 0.1], [0.01, 0.01, 0.01]),  # 0.01 s, but no candidate
    }


def test_time_to_accuracy_on_hand_computed_logs():
    assert time_to_accuracy(log([0.5, 0.2, 0.1], [2, 2, 2]), 0.105) == 6
    assert time_to_accuracy(log([0.2, 0.1, 0.1], [0.5, 0.25, 1]), 0.105) == 0.75
    assert time_to_accuracy(log([0.1, 0.1, 0.2], [1, 1, 1]), 0.105) is None  # drifts back
    stopped = log([0.1, 0.1], [1, 1], {"epoch": 2, "reason": "DIVERGED_DTOL"})
    assert time_to_accuracy(stopped, 0.105) is None  # did not train to the end
    assert time_to_accuracy(log([0.1], [1]), math.nan) is None


def test_summary_times_every_run_and_divides_best_full_by_best_reduced():
    summary = summarize("s", {"": 10, "cg/icc": 3}, runs_on_two_routes())
    times = {name: r["time_to_full_accuracy"] for name, r in summary["runs"].items()}
    assert times == pytest.approx(
        {
            "fixed:10": 6.0,
            "fixed:3@cg/icc": 2.0,
            "prdp": 1.5,
            "prdp@cg/icc": 0.8,
            "rtol@cg/icc": None,
            "fixed:1": None,
            "twin:10": 0.01,
        }  # fmt: skip
    )
    assert summary["speedup_vs_best_full"] == pytest.approx(2.5)  # 2 s / 0.8 s
    # the headline's savings: PRDP 3 x 0.5 s against fixed:10's 3 x 2 s, as many iterations
    assert summary["savings"]["wall_time"] == pytest.approx(1 - 1.5 / 6)
    assert summary["savings"]["iterations"] == pytest.approx(0.0)
    assert summary["val_error_ratio"] == pytest.approx(1.03) and summary["equal_accuracy"]
    best = summary["fastest"]  # the twin (0.01 s) is no candidate
    assert best["winner"] == "prdp@cg/icc" and best["winner_seconds"] == pytest.approx(0.8)
    detail = summary["speedup"]
    assert detail["full"] == "fixed:3@cg/icc" and detail["reduced"] == "prdp@cg/icc"
    assert detail["full_seconds"] == pytest.approx(2.0)
    assert detail["reduced_seconds"] == pytest.approx(0.8)
    assert detail["target_val_error"] == pytest.approx(0.105)
    assert detail["reference"] == "fixed:10" and "unavailable" not in detail
    table = format_table(summary)
    assert "speedup vs best full fidelity: 2.50x (fixed:3@cg/icc" in table
    assert "in 2.00 s; prdp@cg/icc in 0.80 s)" in table
    header, *rows = table.splitlines()[1:8]
    assert header.split()[-2:] == ["s", "stopped"] and "reach s" in header
    reach = {row.split()[0]: row.split()[-2] for row in rows if row.split()[-1] == "no"}
    assert reach["prdp@cg/icc"] == "0.80" and reach["rtol@cg/icc"] == "—"


def test_the_twin_is_no_candidate_and_a_coarse_k_is_a_reduced_run():
    # the twin is fastest of all, fixed:3 on the scene's solver is not its K_full
    logs = {
        "fixed:10": log([0.2, 0.1], [1, 1]),  # 2 s
        "twin:10": log([0.1, 0.1], [0.1, 0.1]),
        "fixed:3": log([0.104, 0.1], [0.5, 0.5]),  # coarse K: reduced, 0.5 s
    }
    out = speedup_vs_best_full(logs, 10)
    assert out["speedup_vs_best_full"] == pytest.approx(4.0)
    assert out["speedup"]["full"] == "fixed:10" and out["speedup"]["reduced"] == "fixed:3"


def test_no_speedup_without_a_reduced_run_that_reaches_full_accuracy():
    logs = {
        "fixed:10": log([0.2, 0.1], [1, 1]),
        "prdp": log([0.3, 0.2], [0.1, 0.1]),
        "fixed:1": log([0.1, 0.2], [0.1, 0.1]),
    }
    summary = summarize("s", 10, logs)
    assert summary["speedup_vs_best_full"] is None
    why = summary["speedup"]["unavailable"]
    assert why.startswith("no reduced run (prdp, fixed:1) reached full-fidelity accuracy")
    assert summary["speedup"]["full"] == "fixed:10" and summary["speedup"]["reduced"] is None
    assert f"speedup vs best full fidelity: none, {why}" in format_table(summary)
    # without full fidelity, or with a full-fidelity run that stopped, there is no target
    assert (
        "did not run" in speedup_vs_best_full({"prdp": logs["prdp"]}, 10)["speedup"]["unavailable"]
    )
    stop = {"epoch": 1, "reason": "DIVERGED_DTOL"}
    broken = {**logs, "fixed:10": log([0.2], [1], stop)}
    out = speedup_vs_best_full(broken, 10)
    assert out["speedup_vs_best_full"] is None
    assert "stopped at epoch 1 (DIVERGED_DTOL)" in out["speedup"]["unavailable"]


def _row(seed, speedup, reason="no reduced run (prdp) reached full-fidelity accuracy"):
    row = {"seed": seed, "k_full": 9, "savings_unavailable": "no savings: prdp stopped",
           "stopped": [], "speedup_vs_best_full": speedup}  # fmt: skip
    if speedup is None:
        row["speedup_unavailable"] = reason
    return row


def test_seeds_aggregate_the_speedup_and_report_the_failures():
    result = _aggregate("s", [0, 1, 2], [_row(0, 2.0), _row(1, 8.0), _row(2, None)])
    speedup = result["speedup"]
    # geometric mean of 2 and 8 is 4; the log-sd is ln 2 · √2, so the 95 % interval
    # is 4 · 2^(±t) with t = t_{0.975, 1}
    assert speedup["geometric_mean"] == pytest.approx(4.0)
    assert speedup["interval"] == pytest.approx([4 * 2**-T_1, 4 * 2**T_1])
    assert speedup["n"] == 2 and speedup["seeds"] == 3 and speedup["goal_met"] == 2
    assert speedup["failures"] == [
        {"seed": 2, "reason": "no reduced run (prdp) reached full-fidelity accuracy"}
    ]
    table = format_seeds(result)
    assert "speedup vs best full fidelity: geometric mean 4.000" in table
    assert "speedup >= 2 on 2 of 3 seeds (1 without a speedup)" in table
    assert "seed 2: no speedup, no reduced run (prdp) reached" in table
    # on no seed at all: still reported, not dropped
    alone = _aggregate("s", [0], [_row(0, None)])
    none = alone["speedup"]
    assert none["n"] == 0 and none["geometric_mean"] is None and none["goal_met"] == 0
    assert "on no seed did a reduced run reach it" in format_seeds(alone)


def test_compare_seeds_records_each_seeds_speedup(tmp_path, monkeypatch):
    speedups = {0: (3.0, "fixed:5@cg/icc", "prdp@cg/icc"), 1: (None, None, None)}

    def fake(scene, *, seed, out, twin, **kwargs):
        value, full, reduced = speedups[seed]
        detail = {"full": full, "reduced": reduced}
        if value is None:
            detail["unavailable"] = "no reduced run (prdp) reached full-fidelity accuracy"
        return {"k_full": 9, "runs": {}, "savings_unavailable": "no savings: none ran",
                "speedup_vs_best_full": value, "speedup": detail}  # fmt: skip

    monkeypatch.setattr(seeds_module, "compare", fake)
    monkeypatch.setattr(seeds_module, "format_table", lambda summary: "")
    result = compare_seeds(HEAT1D, [0, 1], out=tmp_path, plots=False)
    first, second = result["per_seed"]
    assert first["speedup_vs_best_full"] == 3.0 and first["speedup_reduced"] == "prdp@cg/icc"
    assert first["speedup_full"] == "fixed:5@cg/icc"
    assert second["speedup_vs_best_full"] is None and "reached" in second["speedup_unavailable"]
    assert result["speedup"]["n"] == 1 and result["speedup"]["failures"][0]["seed"] == 1
    assert json.loads((tmp_path / "seeds.json").read_text())["speedup"]["goal_met"] == 1


def test_routes_are_declared_by_the_scenes_presets():
    assert parse_routes(" cg/icc, cg/gamg,cg/icc") == ("cg/icc", "cg/gamg")
    assert parse_routes("") == ()
    with pytest.raises(ValueError, match="ksp_type/pc_type"):
        parse_routes("cg")
    heat2d = load_scene(HEAT2D)
    assert scene_routes(heat2d, "quick") == ("cg/icc",)
    assert scene_routes(heat2d, "paper") == ("cg/icc", "cg/gamg")
    assert scene_routes(heat2d, "quick routes=cg/gamg") == ("cg/gamg",)
    assert scene_routes(load_scene(DEMOS / "heat_nonlinear.py"), "paper") == (
        "gmres/ilu",
        "gmres/gamg",
    )
    assert scene_routes(load_scene(HEAT1D), "quick") == ()  # no key: no routes
    ns2d = load_scene(DEMOS / "ns2d.py")  # no plain ksp/pc pair fits: the named Schur PC
    assert scene_routes(ns2d, "quick") == () and scene_routes(ns2d, "long") == ()
    assert scene_routes(ns2d, "paper") == scene_routes(ns2d, "large_k64") == ("schur",)


def test_cli_routes_default_to_the_scene_and_empty_means_none():
    parser = make_parser()
    args = parser.parse_args(["compare", "scene.py", "--out", "o"])
    assert args.routes is None and args.schedules == ("prdp",)
    args = parser.parse_args(["compare", "scene.py", "--out", "o", "--routes", ""])
    assert args.routes == ()
    args = parser.parse_args(["compare", "scene.py", "--out", "o", "--schedules", "prdp,rtol"])
    assert args.schedules == ("prdp", "rtol")
    with pytest.raises(ValueError, match="schedules must be some of prdp, auto, rtol"):
        compare(HEAT1D, schedules=("prdp", "adaptive"), progress=False)


def test_a_route_whose_probe_fails_is_skipped(tmp_path, monkeypatch):
    real, calls = compare_module.find_k_full, []

    def find_k_full(scene):  # the scene's own probe converges, the route's does not
        calls.append(scene)
        if len(calls) > 1:
            raise SolverError("forward KSPSolve failed inside PETSc (gmres/ilu)", "DIVERGED")
        return real(scene)

    monkeypatch.setattr(compare_module, "find_k_full", find_k_full)
    s = compare(HEAT1D, epochs=1, out=tmp_path, progress=False, plots=False,
                routes=("gmres/ilu",))  # fmt: skip
    assert s["routes"]["gmres/ilu"] == {
        "skipped": "forward KSPSolve failed inside PETSc (gmres/ilu)"
    }
    assert not any("@" in name for name in s["runs"])
    assert "gmres/ilu: skipped" in format_table(s)


def test_rtol_levels_reach_the_scenes_tolerance():
    assert (RTOL_INIT, RTOL_FACTOR, RTOL_MAX_IT_FACTOR) == (0.1, 0.1, 10)
    assert rtol_levels(1e-6) == 5  # 1e-1 ... 1e-6
    assert rtol_levels(1e-5) == 4
    assert rtol_levels(0.5) == 0  # looser than the first level: the scene's own


def test_rtol_schedule_follows_rtol_from_level_and_iterations_grow_as_it_tightens():
    result = run(HEAT2D, "rtol", preset="quick", epochs=8, progress=False)
    plan, epochs = result["rtol"], result["epochs"]
    k_full = plan["k_full"]
    assert plan["levels"] == 5 and plan["max_it"] == 10 * k_full == 850
    assert result["prdp"]["k_init"] == 1 and result["prdp"]["k_max"] == 6
    # the levels are those of a PRDP controller fed the same validation errors ...
    controller = PRDP(**result["prdp"])
    levels = []
    for e in epochs:
        levels.append(controller.level)
        controller.update(e["val_metric"])
    assert [e["rtol_level"] for e in epochs] == levels
    assert levels[0] == 0 and levels[-1] >= 2  # it refined at least twice in 8 epochs
    assert all(b - a in (0, 1) for a, b in zip(levels, levels[1:]))
    # ... and rtol is rtol_from_level of that level, down to the scene's rtol_full
    for e in epochs:
        assert e["rtol"] == rtol_from_level(e["rtol_level"], 0.1, 0.1, 1e-6)
        assert e["k"] == 850 and e["fwd_solves"] == e["adj_solves"] == 32
    # PETSc's rtol test stops early: at rtol 0.1 a solve takes a fraction of K_full
    per_solve = {}
    for e in epochs:
        per_solve.setdefault(e["rtol_level"], []).append(e["fwd_iterations"] / e["fwd_solves"])
    mean = [sum(v) / len(v) for _, v in sorted(per_solve.items())]
    assert all(a < b for a, b in zip(mean, mean[1:]))  # a tighter rtol costs more
    assert mean[-1] < k_full


def test_small_compare_with_a_route_and_both_schedules(tmp_path):
    s = compare(HEAT2D, preset="quick", epochs=6, out=tmp_path, progress=False, plots=False,
                routes=["cg/icc"], schedules=("prdp", "rtol"))  # fmt: skip
    k, kr = s["k_full"], s["routes"]["cg/icc"]["k_full"]
    assert s["schedules"] == ["prdp", "rtol"]
    names = {"prdp", "rtol", f"fixed:{k}", "prdp@cg/icc", "rtol@cg/icc", f"fixed:{kr}@cg/icc"}
    assert names <= set(s["runs"])
    full = [f"fixed:{k}", f"fixed:{kr}@cg/icc"]
    reduced = [name for name in s["runs"] if name not in full]
    times = {name: r["time_to_full_accuracy"] for name, r in s["runs"].items()}
    # full fidelity reaches its own final error at the latest in its last epoch
    assert 0 < times[f"fixed:{k}"] <= s["runs"][f"fixed:{k}"]["wall_time"]
    best_full = min(times[n] for n in full if times[n] is not None)
    reached = [times[n] for n in reduced if times[n] is not None]
    detail = s["speedup"]
    assert detail["full_seconds"] == best_full and times[detail["full"]] == best_full
    if reached:
        assert detail["reduced_seconds"] == min(reached)
        assert s["speedup_vs_best_full"] == pytest.approx(
            times[detail["full"]] / times[detail["reduced"]], rel=1e-12
        )
        assert min(best_full, min(reached)) == s["fastest"]["winner_seconds"]
    else:
        assert s["speedup_vs_best_full"] is None and "no reduced run" in detail["unavailable"]
    # the rtol runs: PETSc's rtol test under the cap, fewer iterations than K_full
    for name, cap_of in (("rtol", k), ("rtol@cg/icc", kr)):
        r = s["runs"][name]["rtol"]
        assert r["max_it"] == 10 * cap_of and r["init"] == 0.1
        assert r["fwd_per_solve_first"] < cap_of
    # PRDP refines: K never decreases, nor passes its solver's K_full
    for name, folder, cap in (("prdp", "prdp", k), ("prdp@cg/icc", "prdp_on_cg-icc", kr)):
        epochs = json.loads((tmp_path / folder / "results.json").read_text())["epochs"]
        ks = [e["k"] for e in epochs]
        assert all(a <= b for a, b in zip(ks, ks[1:]))
        assert ks[-1] == s["runs"][name]["k_final"] <= cap
    recorded = json.loads((tmp_path / "rtol_on_cg-icc" / "results.json").read_text())
    assert recorded["solvers"][0]["forward"] == {"ksp_type": "cg", "pc_type": "icc"}
    assert [e["rtol"] for e in recorded["epochs"]][0] == 0.1
    table = format_table(s)
    assert "reach s" in table and "speedup vs best full fidelity" in table
    assert "rtol@cg/icc: PETSc's rtol test under max_it" in table
    # a trained rtol run reloads with its last tolerance
    scene = load_trained(tmp_path / "rtol")
    try:
        last = json.loads((tmp_path / "rtol" / "results.json").read_text())["epochs"][-1]
        assert scene.solvers[0].rtol == last["rtol"] and scene.solvers[0].max_it == 10 * k
    finally:
        release(scene)


def test_an_rtol_run_resumes_exactly(tmp_path):
    straight = run(HEAT2D, "rtol", preset="quick", epochs=7, out=tmp_path / "a", progress=False)
    run(HEAT2D, "rtol", preset="quick", epochs=4, out=tmp_path / "b", progress=False)
    resumed = run(resume=tmp_path / "b", epochs=7, progress=False)

    def seen(result):
        return [(e["val_metric"], e["rtol"], e["fwd_iterations"], e["adj_iterations"])
                for e in result["epochs"]]  # fmt: skip

    assert seen(resumed) == seen(straight)  # level, rtol and iterations continue as one run
    assert resumed["rtol"] == straight["rtol"]


def test_the_summary_keeps_each_runs_rollouts():
    logs = runs_on_two_routes()
    logs["prdp"]["rollout"] = [0.1, 0.2, 0.4]
    logs["prdp"]["uncorrected_rollout"] = [0.2, 0.3, 0.5]
    runs = summarize("s", {"": 10, "cg/icc": 3}, logs)["runs"]
    assert runs["prdp"]["rollout"] == [0.1, 0.2, 0.4]
    assert runs["prdp"]["uncorrected_rollout"] == [0.2, 0.3, 0.5]
    assert "rollout" not in runs["fixed:10"] and "uncorrected_rollout" not in runs["fixed:10"]


def test_lever_ratios_divide_each_reference_time_by_the_levers_seed_by_seed():
    from prdp_petsc.lab.training.seeds import lever_ratios

    rows = [
        {"seed": 0, "k_full": 10, "reach_seconds": {
            "fixed:10": 8.0, "prdp": 4.0, "rtol": None, "fixed:2": 6.0, "fixed:5": 5.0,
            "fixed:3@cg/icc": 2.0, "prdp@cg/icc": 1.0, "rtol@cg/icc": 4.0, "twin:10": 0.5}},
        {"seed": 1, "k_full": 11, "reach_seconds": {
            "fixed:11": 9.0, "prdp": 1.0, "rtol": 3.0, "fixed:2": None, "fixed:5": None,
            "fixed:4@cg/icc": 3.0, "prdp@cg/icc": None, "rtol@cg/icc": 1.0, "twin:11": 0.5}},
    ]  # fmt: skip
    levers = lever_ratios(rows)
    assert set(levers) == {"prdp vs full", "rtol vs full", "best coarse K vs full",
                           "full@cg/icc vs full", "prdp@cg/icc vs full@cg/icc",
                           "rtol@cg/icc vs full@cg/icc"}  # fmt: skip
    assert levers["prdp vs full"]["geometric_mean"] == pytest.approx(math.sqrt(2.0 * 9.0))
    assert levers["rtol vs full"]["n"] == 1 and levers["rtol vs full"]["seeds"] == 2
    assert levers["best coarse K vs full"]["geometric_mean"] == pytest.approx(8.0 / 5.0)
    assert levers["full@cg/icc vs full"]["geometric_mean"] == pytest.approx(math.sqrt(4.0 * 3.0))
    assert levers["prdp@cg/icc vs full@cg/icc"]["geometric_mean"] == pytest.approx(2.0)
    assert levers["rtol@cg/icc vs full@cg/icc"]["geometric_mean"] == pytest.approx(
        math.sqrt(0.5 * 3.0)
    )
    assert lever_ratios([{"seed": 0, "k_full": 3}]) == {}  # rows of an older comparison


def test_rtol_from_level():
    assert rtol_from_level(0) == pytest.approx(0.1)
    assert rtol_from_level(3) == pytest.approx(1e-4)
    assert rtol_from_level(2, factor=0.5) == pytest.approx(0.025)
    assert rtol_from_level(100) == 1e-10
    with pytest.raises(ValueError, match="factor"):
        rtol_from_level(1, factor=1.5)
