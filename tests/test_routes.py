"""Routes with sub-options and by name: what ``compare --routes`` sets in PETSc."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from petsc4py import PETSc

from prdp_petsc.training.compare import compare
from prdp_petsc.training.routes import (
    parse_route,
    parse_routes,
    route_options,
    route_settings,
    route_string,
)
from prdp_petsc.training.scene import load_scene

DEMOS = Path(__file__).resolve().parent.parent / "demos"

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
    cmd = [sys.executable, "-m", "prdp_petsc.cli", "compare", str(DEMOS / "ns2d.py"),
           "--preset", "quick", "--routes", "cg/icc,shur", "--out", str(tmp_path)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--routes: no route named 'shur' (the scene names: schur)" in done.stderr


def test_work_precision_takes_only_plain_pairs(tmp_path):
    cmd = [sys.executable, "-m", "prdp_petsc.cli", "work-precision", "poisson", "--quick",
           "--out", str(tmp_path), "--routes", "cg/icc:pc_factor_levels=1"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "plain ksp/pc pairs" in done.stderr
