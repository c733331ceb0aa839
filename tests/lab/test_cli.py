"""The command line starts PETSc with its PETSc options (run in fresh interpreters)."""

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HEAT1D = ROOT / "demos" / "heat1d.py"


def python(*args, cwd=ROOT, timeout=300):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


def test_importing_the_cli_does_not_start_petsc():
    # petsc4py.init(argv) must run before the first `from petsc4py import PETSc`
    code = (
        "import sys, prdp_petsc, prdp_petsc.lab.cli\n"
        "prdp_petsc.lab.cli.split_petsc_options(['run', 'x.py', '-log_view'])\n"
        "print(sorted(m for m in ('petsc4py.PETSc', 'torch') if m in sys.modules))\n"
        "print(prdp_petsc.__version__ != '', 'solve' in dir(prdp_petsc))"
    )
    done = python("-c", code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:2] == ["[]", "True True"]


def test_log_view_through_the_cli(tmp_path):
    done = python(
        "-m", "prdp_petsc.lab.cli", "run", str(HEAT1D), "--preset", "quick", "--epochs", "1",
        "--schedule", "fixed:3", "--out", str(tmp_path), "--no-progress", "-log_view",
        "-heat_pc_type", "none",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "PETSc Performance Summary" in done.stdout
    assert "KSPSolve" in done.stdout  # the event table of the training's solves
    result = json.loads((tmp_path / "results.json").read_text())
    assert result["solvers"][0]["forward"] == {"ksp_type": "richardson", "pc_type": "none"}
    assert result["totals"]["epochs"] == 1


POISSON = ROOT / "demos" / "poisson_inverse.py"  # its solver's prefix is poisson_
STRICT = "error::prdp_petsc.errors.UnusedOptionWarning"


def poisson_run(out, *petsc, command=(sys.executable, "-m", "prdp_petsc.lab.cli"), env=None):
    """One epoch of poisson_inverse through the command line, with PETSc options."""
    args = ["run", str(POISSON), "--preset", "quick", "--epochs", "1", "--schedule", "fixed:3",
            "--no-progress", "--out", str(out), *petsc]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    return subprocess.run(
        [*command, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )


def test_warning_filter_makes_a_misspelt_option_an_error(tmp_path):
    strict = (sys.executable, "-W", STRICT, "-m", "prdp_petsc.lab.cli")
    done = poisson_run(tmp_path / "typo", "-poisson_ksp_tpye", "cg", command=strict)
    assert done.returncode == 1, done.stderr[-2000:]
    assert "prdp-petsc: error: UnusedOptionWarning" in done.stderr
    assert "-poisson_ksp_tpye" in done.stderr
    # spelt right, the same command runs, and PETSc read the option
    done = poisson_run(tmp_path / "right", "-poisson_ksp_type", "cg", command=strict)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "UnusedOptionWarning" not in done.stderr
    result = json.loads((tmp_path / "right" / "results.json").read_text())
    assert result["solvers"][0]["forward"]["ksp_type"] == "cg"
    assert result["totals"]["epochs"] == 1
    # without the filter the typo is a warning only
    done = poisson_run(tmp_path / "warned", "-poisson_ksp_tpye", "cg")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "UnusedOptionWarning" in done.stderr and "-poisson_ksp_tpye" in done.stderr


def test_pythonwarnings_with_the_console_script(tmp_path):
    script = Path(sys.executable).with_name("prdp-petsc")
    if not script.is_file():
        pytest.skip("the prdp-petsc console script is not installed next to this Python")
    env = {"PYTHONWARNINGS": STRICT}
    done = poisson_run(tmp_path / "typo", "-poisson_ksp_tpye", "cg", command=(script,), env=env)
    assert done.returncode == 1, done.stderr[-2000:]
    assert "UnusedOptionWarning" in done.stderr and "-poisson_ksp_tpye" in done.stderr
    done = poisson_run(tmp_path / "right", "-poisson_ksp_type", "cg", command=(script,), env=env)
    assert done.returncode == 0, done.stderr[-2000:]


def test_apply_warning_options_reads_them_as_python_does(capsys):
    from prdp_petsc.errors import UnusedOptionWarning
    from prdp_petsc.lab.cli import apply_warning_options

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        apply_warning_options(
            [
                "e::prdp_petsc.errors.UnusedOptionWarning",  # an abbreviated action
                "ignore:PETSc never:prdp_petsc.errors.UnusedOptionWarning",  # later: first
                "error::UserWarning",  # not ours: Python applied it already
                "error::prdp_petsc.errors.SolverError",
                "error::prdp_petsc.no_such_module.Warning",
            ]
        )
        with pytest.raises(UnusedOptionWarning, match="-x_ksp_tpye"):
            warnings.warn("options -x_ksp_tpye unread", UnusedOptionWarning)
        warnings.warn("PETSc never read -x_ksp_tpye", UnusedOptionWarning)  # ignored
        warnings.warn("not ours", UserWarning)  # still ignored: "error::UserWarning" skipped
    err = capsys.readouterr().err
    assert "prdp_petsc.errors.SolverError is not a warning category" in err
    assert "No module named 'prdp_petsc.no_such_module'" in err


# -- a scene's own commands (COMMANDS): prdp-petsc scene and python SCENE_FILE NAME ----------
NS2D = ROOT / "demos" / "ns2d.py"
REPORT_HEAD = "case fwd its adj its fwd s adj s adj/fwd |g-g_conv| |g-g_det| cos".split()


def exit_status(call, *args):
    """The exit status of a usage error (argparse raises SystemExit) or of a return."""
    try:
        return call(*args)
    except SystemExit as stop:
        return stop.code


def check_adjoint_report(text: str, ks: tuple[int, ...]) -> None:
    """ns2d's adjoint table on quick (batch 8, 2-step unroll): fixed-K iteration counts,
    the converged gradient against itself, no adjoint solve when detached."""
    lines = text.splitlines()
    assert lines[0] == "preset quick, batch 8"
    assert lines[1].split() == REPORT_HEAD
    rows = {line.split()[0]: line.split()[1:] for line in lines[2 : 4 + len(ks)]}
    assert list(rows) == [*(f"K={k}" for k in ks), "converged", "detached"]
    for name, row in rows.items():
        assert len(row) == 8 and all(math.isfinite(float(x)) for x in row), (name, row)
    for k in ks:  # rtol = atol = 0: K iterations per solve, 2 solves and 1 adjoint per sample
        assert (int(rows[f"K={k}"][0]), int(rows[f"K={k}"][1])) == (2 * 8 * k, 8 * k)
    converged, detached = rows["converged"], rows["detached"]
    assert int(converged[1]) > 8 * 8  # to rtol 1e-8: more than one restart cycle each
    assert float(converged[5]) == 0.0 and converged[7] == "1.000"
    assert int(detached[0]) == int(converged[0]) and int(detached[1]) == 0
    assert float(detached[6]) == 0.0


def test_scene_lists_a_scenes_commands(capsys):
    from prdp_petsc.lab import cli

    assert cli.main(["scene", str(NS2D)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("commands of ns2d.py (prdp-petsc scene ")
    assert out[1].split()[:2] == ["adjoint", "Print"]
    assert cli.main(["scene", str(ROOT / "demos" / "poisson_field.py")]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[0] == "plot"
    assert cli.main(["scene", str(HEAT1D)]) == 0
    assert "heat1d.py defines no commands" in capsys.readouterr().out
    # python demos/ns2d.py -h: run and compare's help, then the scene's commands
    assert cli.scene_main(str(NS2D), ["-h"]) == 0
    out = capsys.readouterr().out
    assert "{run,compare}" in out and "\n  adjoint  Print the adjoint figures" in out


def test_scene_dispatches_ns2d_adjoint_with_petsc_options():
    # PETSc options are split off for petsc4py.init: -log_view reaches PetscInitialize
    done = python(
        "-m", "prdp_petsc.lab.cli", "scene", str(NS2D), "adjoint", "--k", "8", "-log_view"
    )
    assert done.returncode == 0, done.stderr[-2000:]
    check_adjoint_report(done.stdout, (8,))
    assert "PETSc Performance Summary" in done.stdout


def test_scene_main_dispatches_ns2d_adjoint(capsys):
    """``python demos/ns2d.py adjoint ...``: the demo's __main__ is ``scene_main``."""
    from prdp_petsc.lab import cli

    assert cli.scene_main(str(NS2D), ["adjoint", "--preset", "quick", "--k", "8", "16"]) == 0
    check_adjoint_report(capsys.readouterr().out, (8, 16))


@pytest.mark.parametrize(
    "args, message",
    [
        (["--k", "0"], "adjoint: error: argument --k: expected an integer >= 1, got '0'"),
        (["--k", "8", "x"], "adjoint: error: argument --k: expected an integer >= 1, got 'x'"),
        (["--preset", "nope"], "adjoint: error: --preset: preset must be one of ["),
        (["--preset", "quick n=1.5"], "adjoint: error: --preset: setting n: expected an integer"),
        (["quick", "8"], "adjoint: error: unrecognized arguments: quick 8"),  # the old form
    ],
)
def test_a_usage_error_of_a_scene_command_exits_2(capsys, args, message):
    from prdp_petsc.lab import cli

    assert exit_status(cli.main, ["scene", str(NS2D), "adjoint", *args]) == 2
    err = capsys.readouterr().err
    assert f"prdp-petsc scene {NS2D} {message}" in err, err  # prog names the command
    assert exit_status(cli.scene_main, str(NS2D), ["adjoint", *args]) == 2
    assert f"ns2d.py {message}" in capsys.readouterr().err


def test_an_unknown_scene_command_exits_2_with_the_available_names(capsys):
    from prdp_petsc.lab import cli

    assert exit_status(cli.main, ["scene", str(NS2D), "adjiont"]) == 2
    err = capsys.readouterr().err
    assert "error: unknown command 'adjiont'; ns2d.py's commands: adjoint, energy\n" in err
    assert exit_status(cli.scene_main, str(NS2D), ["adjiont"]) == 2  # run, compare there too
    assert "unknown command 'adjiont'; ns2d.py's commands: run, compare, adjoint, energy\n" in (
        capsys.readouterr().err
    )
    assert exit_status(cli.main, ["scene", str(HEAT1D), "adjoint"]) == 2
    assert "heat1d.py's commands: none (it defines no COMMANDS)" in capsys.readouterr().err
    assert exit_status(cli.main, ["scene"]) == 2  # no SCENE_FILE
    assert "error: give a SCENE_FILE" in capsys.readouterr().err


SCENE_WITH_A_FAILING_COMMAND = '''
PRESETS = {"quick": {}, "paper": {}}


def build(config, seed):
    raise NotImplementedError


def fail(parser):
    """Fail."""
    return lambda args: float("nan") < {}


COMMANDS = {"fail": fail}
'''


def test_an_error_in_a_scene_command_prints_one_line_unless_debug(tmp_path, capsys):
    from prdp_petsc.lab import cli

    scene = tmp_path / "failing.py"
    scene.write_text(SCENE_WITH_A_FAILING_COMMAND)
    assert cli.main(["scene", str(scene), "fail"]) == 1
    err = capsys.readouterr().err
    assert err == (
        "prdp-petsc: error: TypeError: '<' not supported between instances of 'float' and "
        "'dict' (--debug shows the traceback)\n"
    )
    with pytest.raises(TypeError, match="'<' not supported"):
        cli.main(["scene", str(scene), "fail", "--debug"])
    scene = tmp_path / "shadowing.py"
    scene.write_text(SCENE_WITH_A_FAILING_COMMAND.replace('{"fail"', '{"run"'))
    assert cli.main(["scene", str(scene)]) == 1  # the harness's names are refused
    assert "COMMANDS: 'run' is the harness's" in capsys.readouterr().err


def test_petsc_options_after_a_bare_double_dash_belong_to_the_inner_command():
    from prdp_petsc.lab.cli import split_petsc_options

    argv = ["record", "x", "--", "compare", "s.py", "-fwd_pc_type", "gamg", "--out", "o"]
    assert split_petsc_options(argv) == (argv, [])
    assert split_petsc_options(["run", "s.py", "-ksp_monitor", "--out", "o"]) == (
        ["run", "s.py", "--out", "o"],
        ["-ksp_monitor"],
    )


def test_the_lab_check_names_every_package_of_the_lab_extra(monkeypatch):
    """Without one of them a command stops before it starts, not after a comparison
    trained (pandas and tabulate print its tables)."""
    import importlib.util
    import re
    import tomllib

    from prdp_petsc.lab.cli import dispatch

    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    extra = pyproject["project"]["optional-dependencies"]["lab"]
    names = [re.match(r"[A-Za-z0-9_-]+", requirement)[0] for requirement in extra]
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    assert dispatch.missing_lab_packages() == names


def test_without_the_lab_extra_the_command_says_how_to_install_it(monkeypatch, capsys):
    from prdp_petsc.lab import cli
    from prdp_petsc.lab.cli import dispatch

    monkeypatch.setattr(dispatch, "missing_lab_packages", lambda: ["tqdm"])
    assert cli.main(["run", "demos/heat1d.py"]) == 2
    err = capsys.readouterr().err
    assert "needs tqdm" in err and "pip install 'prdp-petsc[lab]'" in err


# One spelling per concept (prdp_petsc.lab.cli.arguments): the report tools declare their
# shared options through the same helpers, so they parse them alike.


def report_parser(tool):
    import importlib

    return importlib.import_module(f"prdp_petsc.lab.reports.{tool}")._parser()


@pytest.mark.parametrize(
    "tool, argv",
    [
        ("ablation", ["demos/heat.py", "--seeds", "0,2-3", "--preset", "paper"]),
        ("unseen", ["--seeds", "0,2-3", "--preset", "quick"]),
        ("bench", ["bridge", "--preset", "quick"]),
        ("bench_elasticity", ["--preset", "quick"]),
        ("bench_mpi", ["demos/heat.py", "--preset", "quick"]),
        ("horizon", ["demos/ns2d.py", "--preset", "long"]),
        ("rollouts", ["--run", "a=r0"]),
    ],
)  # fmt: skip
def test_the_report_tools_read_shared_options_alike(tool, argv):
    args = report_parser(tool).parse_args([*argv, "--out", "o", "--debug"])
    assert args.out == Path("o") and args.debug is True
    if "--seeds" in argv:
        assert args.seeds == [0, 2, 3]
    if "--preset" in argv:
        assert args.preset == argv[argv.index("--preset") + 1]


@pytest.mark.parametrize(
    "tool, argv",
    [
        ("bench", ["bridge", "--out", "o", "--quick"]),
        ("bench", ["bridge", "--out", "o", "--ksp-type", "gmres"]),
        ("bench_mpi", ["--out", "o", "--scene", "demos/heat.py"]),
        ("unseen", ["--out", "o", "--seeds", "0", "1"]),
    ],
)  # fmt: skip
def test_a_second_spelling_is_a_usage_error(capsys, tool, argv):
    assert exit_status(report_parser(tool).parse_args, argv) == 2
    assert "error: " in capsys.readouterr().err


def test_bench_reads_one_route(capsys):
    parse = report_parser("bench").parse_args
    assert parse(["bridge", "--out", "o", "--routes", "gmres/ilu"]).routes == ("gmres", "ilu")
    assert parse(["bridge", "--out", "o"]).routes == ("cg", "jacobi")
    assert exit_status(parse, ["bridge", "--out", "o", "--routes", "cg/icc,cg/sor"]) == 2
    assert "expected one KSP/PC pair" in capsys.readouterr().err


def test_usage_lists_every_command_and_refuses_an_unknown_one(capsys):
    from prdp_petsc.lab import cli
    from prdp_petsc.lab.cli.dispatch import COMMANDS

    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(f"\n  {name} " in out for name in COMMANDS)
    assert exit_status(cli.main, ["frobnicate"]) == 2
    assert "unknown command 'frobnicate'; the commands: run, compare, scene, bench" in (
        capsys.readouterr().err
    )


def test_topopt_results_reads_ks_and_load_cases():
    import argparse

    from prdp_petsc.lab.reports.topopt import commands

    parser = argparse.ArgumentParser()
    commands(None)["results"](parser)
    args = parser.parse_args(["--k", "2", "4", "--seeds", "0-1", "--out", "o"])
    assert (args.k, args.seeds, args.out, args.preset) == ([2, 4], [0, 1], Path("o"), "quick")
    assert parser.parse_args(["--out", "o"]).seeds == [0, 1, 2]
    assert exit_status(parser.parse_args, ["--ks", "2,4", "--out", "o"]) == 2
