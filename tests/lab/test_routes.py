"""Routes with sub-options and by name: what ``compare --routes`` sets in PETSc."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from petsc4py import PETSc

from prdp_petsc.lab.training.compare import compare
from prdp_petsc.lab.training.routes import (
    parse_route,
    parse_routes,
    route_options,
    route_settings,
    route_string,
)
from prdp_petsc.lab.training.scene import load_scene

DEMOS = Path(__file__).resolve().parents[2] / "demos"

SPLIT = "gmres/fieldsplit:pc_fieldsplit_detect_saddle_point:pc_fieldsplit_type=schur"


def test_sub_options_follow_the_pair_in_order_and_a_bare_one_is_a_flag():
    assert route_settings(SPLIT) == {
        "ksp_type": "gmres",
        "pc_type": "fieldsplit",
        "pc_fieldsplit_detect_saddle_point": None,
        "pc_fieldsplit_type": "schur",
    }
    assert parse_route(SPLIT) == ("gmres", "fieldsplit")
    assert route_settings("cg/icc") == {"ksp_type": "cg", "pc_type": "icc"}


@pytest.mark.parametrize(
    "bad, match",
    [
        ("cg/icc:", "not 'option'"),
        ("cg/icc:pc_factor_levels=", "not 'option'"),
        ("cg/icc:=2", "not 'option'"),
        ("cg/icc:-pc_factor_levels=2", "not 'option'"),
        ("cg/icc:a=b=c", "not 'option'"),
        ("cg/icc:pc_type=sor", "sets 'pc_type' twice"),
        ("cg/icc:x=1:x=2", "sets 'x' twice"),
        ("cg/icc:x=1 2", "ksp_type/pc_type"),
        ("cg:x=1", "ksp_type/pc_type"),
    ],
)
def test_malformed_sub_options_are_refused(bad, match):
    with pytest.raises(ValueError, match=match):
        route_settings(bad)


def test_a_scene_names_its_routes_and_an_unknown_name_lists_them():
    named = {"split": SPLIT}
    assert parse_routes("split, cg/icc", named) == ("split", "cg/icc")
    assert route_settings("split", named) == route_settings(SPLIT)
    with pytest.raises(ValueError, match=r"no route named 'schur' \(the scene names: split\)"):
        parse_routes("schur", named)
    with pytest.raises(ValueError, match="no route named 'split' .*names: none"):
        parse_routes("split")
    with pytest.raises(ValueError, match="must name a"):
        route_settings("a", {"a": "b", "b": "cg/icc"})  # a name of a name


def test_route_string_inverts_route_settings_on_ns2ds_schur_pc():
    ns2d = load_scene(DEMOS / "ns2d.py")
    settings = route_settings("schur", ns2d.ROUTES)
    assert settings == {k: (None if v is None else str(v)) for k, v in ns2d.SCHUR.items()}
    assert route_string(settings) == ns2d.ROUTES["schur"]
    with pytest.raises(ValueError, match="needs ksp_type and pc_type"):
        route_string({"ksp_type": "cg"})
    with pytest.raises(ValueError, match="ksp_type/pc_type"):
        route_string({"ksp_type": "cg", "pc_type": "icc", "ksp_view": "ascii:out.txt x"})


def test_route_options_set_every_sub_option_per_prefix_and_restore(petsc_option):
    petsc_option("r1_pc_fieldsplit_type", "additive")  # the user's command line
    opts = PETSc.Options()
    with route_options(["r1_", "r2_"], "split", {"split": SPLIT}):
        for prefix in ("r1_", "r2_"):
            assert opts.getString(prefix + "pc_fieldsplit_type") == "schur"
            assert opts.getBool(prefix + "pc_fieldsplit_detect_saddle_point")
            assert opts.getString(prefix + "ksp_type") == "gmres"
    assert opts.getString("r1_pc_fieldsplit_type") == "additive"
    for name in ("r1_pc_fieldsplit_detect_saddle_point", "r2_pc_fieldsplit_type", "r2_ksp_type"):
        assert not opts.hasName(name)


def test_compare_runs_a_named_route_with_its_sub_options(tmp_path):
    """ns2d's ``schur`` on the quick grid: the runs are named by it, the solver the
    run recorded is the fieldsplit PC, and its K_full is its own."""
    s = compare(DEMOS / "ns2d.py", preset="quick", epochs=1, out=tmp_path, progress=False,
                plots=False, routes="schur")  # fmt: skip
    kr = s["routes"]["schur"]["k_full"]
    assert {"prdp@schur", f"fixed:{kr}@schur"} <= set(s["runs"])
    assert kr < s["k_full"]  # the Schur complement PC needs fewer iterations than GMRES(8)
    recorded = json.loads((tmp_path / "prdp_on_schur" / "results.json").read_text())
    assert recorded["solvers"][0]["forward"]["pc_type"] == "fieldsplit"
    assert not PETSc.Options().hasName("ns2d_pc_fieldsplit_type")  # restored afterwards


def test_the_cli_checks_route_names_against_the_scene(tmp_path):
    cmd = [sys.executable, "-m", "prdp_petsc.lab.cli", "compare", str(DEMOS / "ns2d.py"),
           "--preset", "quick", "--routes", "cg/icc,shur", "--out", str(tmp_path)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--routes: no route named 'shur' (the scene names: schur)" in done.stderr


def test_work_precision_takes_only_plain_pairs(tmp_path):
    cmd = [sys.executable, "-m", "prdp_petsc.lab.cli", "work-precision", "poisson", "--preset",
           "quick", "--out", str(tmp_path), "--routes", "cg/icc:pc_factor_levels=1"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "plain ksp/pc pairs" in done.stderr


def test_routes_auto_runs_the_route_a_pilot_picks(tmp_path, monkeypatch):
    """``routes="auto"``: one timed full-fidelity epoch per candidate, then the
    comparison runs the fastest candidate's route only; a resume keeps the pick."""
    import prdp_petsc.lab.training.compare as compare_module

    real = compare_module.pilot_routes
    calls = []

    def pilot(*args, **kwargs):
        calls.append(args[1])
        result = real(*args, **kwargs)
        # the pick, whatever the timings: the route, so that the test sees it run
        result["picked"] = "cg/icc"
        return result

    monkeypatch.setattr(compare_module, "pilot_routes", pilot)
    heat2d = DEMOS / "heat.py"
    s = compare(heat2d, preset="quick routes=cg/icc,cg/gamg", epochs=2, out=tmp_path,
                progress=False, plots=False, routes="auto")  # fmt: skip
    assert calls == [("cg/icc", "cg/gamg")]
    candidates = s["pilot"]["candidates"]
    assert set(candidates) == {"scene solver", "cg/icc", "cg/gamg"}
    assert candidates["scene solver"]["k_full"] == s["k_full"]
    assert all(c["epoch_seconds"] > 0 for c in candidates.values())
    assert candidates["cg/icc"]["k_full"] == s["routes"]["cg/icc"]["k_full"]
    assert any(n.endswith("@cg/icc") for n in s["runs"])
    assert not any(n.endswith("@cg/gamg") for n in s["runs"])
    from prdp_petsc.lab.training.summary import format_table

    assert "pilot (1 timed full-fidelity epoch each, after an untimed one)" in format_table(s)
    # an interrupted comparison has no summary yet: the pick is in pilot.json from the start
    assert json.loads((tmp_path / "pilot.json").read_text()) == s["pilot"]
    (tmp_path / "summary.json").unlink()
    s2 = compare(heat2d, preset="quick routes=cg/icc,cg/gamg", epochs=2, out=tmp_path,
                 progress=False, plots=False, routes=("auto",), resume=True)  # fmt: skip
    assert len(calls) == 1 and s2["pilot"] == s["pilot"]  # the resumed comparison's pick
    assert set(s2["reused"]) == set(s["runs"])  # and its runs, none trained again


def test_the_pilot_times_after_a_warm_up_epoch_and_skips_a_candidate_that_stops(monkeypatch):
    """With the training runs replaced by logs of known epoch times: the pick is the
    least time of the epochs after the first; a run that stopped is no candidate."""
    import prdp_petsc.lab.training.compare as compare_module
    from prdp_petsc.lab.training.compare import pilot_routes

    first_epoch = {"": 0.1, "icc": 50.0, "sor": 0.01, "gamg": 9.0}  # untimed: ignored
    later = {"": 3.0, "icc": 1.0, "sor": 0.5, "gamg": 2.0}

    def fake_run(scene_file, schedule, settings, **kwargs):
        epochs = settings.epochs
        opts = PETSc.Options()  # the route's PC, as route_options set it (none: the scene's)
        pc = opts.getString("heat_pc_type") if opts.hasName("heat_pc_type") else ""
        walls = [first_epoch[pc]] + [later[pc]] * (epochs - 1)
        stopped = {"epoch": 1, "reason": "DIVERGED_DTOL", "message": "KSP diverged"}
        if pc == "sor":  # the fastest, but it diverged after one epoch
            return {"epochs": [{"wall_time": walls[0]}], "stopped": stopped}
        return {"epochs": [{"wall_time": w} for w in walls], "stopped": None}

    heat1d = DEMOS / "heat1d.py"
    module = load_scene(heat1d)
    monkeypatch.setattr(compare_module, "run", fake_run)
    monkeypatch.setattr(compare_module, "find_k_full", lambda scene: 7)
    prefixes = ["heat_"]  # heat1d's solver prefix
    p = pilot_routes(heat1d, ("cg/icc", "richardson/sor", "cg/gamg"), module=module,
                     preset="quick", seed=0, prefixes=prefixes, k_full=30, epochs=2)  # fmt: skip
    c = p["candidates"]
    assert c["scene solver"] == {"k_full": 30, "epoch_seconds": 3.0}
    assert c["cg/icc"]["epoch_seconds"] == 1.0 and c["cg/gamg"]["epoch_seconds"] == 2.0
    assert c["richardson/sor"] == {"skipped": "its pilot run stopped: KSP diverged"}
    assert p["picked"] == "cg/icc" and p["epochs"] == 2
    assert pilot_routes(heat1d, (), module=module, preset="quick", seed=0, prefixes=prefixes,
                        k_full=30) == {"epochs": 0, "candidates": {}, "picked": None}  # fmt: skip


def test_a_route_with_sub_options_gets_a_short_folder_of_its_own():
    from prdp_petsc.lab.training.compare import _folder_name

    ns2d = load_scene(DEMOS / "ns2d.py")
    long = ns2d.ROUTES["schur"]
    name = _folder_name(f"rtol@{long}")
    assert name.startswith("rtol_on_gmres-fieldsplit_") and len(name) < 60
    assert _folder_name("prdp@gmres/ilu:a=b") != _folder_name("prdp@gmres/ilu:a:b")
    assert _folder_name("fixed:8@cg/icc") == "fixed_8_on_cg-icc"  # plain pairs as before
    assert _folder_name("twin:626") == "twin_626"


def test_auto_is_no_route_among_others():
    with pytest.raises(ValueError, match="'auto' lets a pilot pick one of the scene's routes"):
        parse_routes("auto,cg/icc")


@pytest.mark.parametrize("bad", ["auto", "cg/icc", "scene solver", "a:b", "2nd"])
def test_a_scene_cannot_name_a_route_like_a_pair_or_the_pilot(bad):
    with pytest.raises(ValueError, match="ROUTES names a route"):
        parse_routes("cg/icc", {bad: "gmres/ilu"})


def test_the_pilot_picks_the_least_epoch_time_and_skips_what_does_not_fit(monkeypatch):
    """heat1d with CG + ICC as a route that fits and a route whose K_full probe fails
    (as ILU on a zero diagonal block does): the latter is skipped with the reason."""
    import prdp_petsc.lab.training.compare as compare_module
    from prdp_petsc.errors import SolverError
    from prdp_petsc.lab.training.compare import SCENE_SOLVER, pilot_routes
    from prdp_petsc.lab.training.harness import build_scene, find_k_full, release

    heat1d = DEMOS / "heat1d.py"
    module = load_scene(heat1d)
    scene = build_scene(module, "quick", 0)
    prefixes, k = [s.prefix for s in scene.solvers], find_k_full(scene)
    release(scene)

    def probe(scene):
        if scene.solvers[0].describe()["forward"].get("pc_type") == "sor":
            raise SolverError("forward KSPSolve failed inside PETSc (gmres/sor)", "DIVERGED")
        return find_k_full(scene)

    monkeypatch.setattr(compare_module, "find_k_full", probe)
    p = pilot_routes(heat1d, ("cg/icc", "gmres/sor"), module=module, preset="quick", seed=0,
                     prefixes=prefixes, k_full=k)  # fmt: skip
    timed = {n: c["epoch_seconds"] for n, c in p["candidates"].items() if "epoch_seconds" in c}
    assert set(timed) == {SCENE_SOLVER, "cg/icc"} and p["picked"] == min(timed, key=timed.get)
    assert p["candidates"]["gmres/sor"] == {
        "skipped": "forward KSPSolve failed inside PETSc (gmres/sor)"
    }
    assert p["candidates"]["cg/icc"]["k_full"] < k  # ICC needs fewer iterations than Jacobi
