"""The command line starts PETSc with its PETSc options (run in fresh interpreters)."""

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
HEAT1D = ROOT / "demos" / "heat1d.py"


def python(*args, cwd=ROOT, timeout=300):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


def test_importing_the_cli_does_not_start_petsc():
    # petsc4py.init(argv) must run before the first `from petsc4py import PETSc`
    code = (
        "import sys, prdp_petsc, prdp_petsc.cli\n"
        "prdp_petsc.cli.split_petsc_options(['run', 'x.py', '-log_view'])\n"
        "print(sorted(m for m in ('petsc4py.PETSc', 'torch') if m in sys.modules))\n"
        "print(prdp_petsc.__version__ != '', 'solve' in dir(prdp_petsc))"
    )
    done = python("-c", code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:2] == ["[]", "True True"]


def test_log_view_through_the_cli(tmp_path):
    done = python(
        "-m", "prdp_petsc.cli", "run", str(HEAT1D), "--preset", "quick", "--epochs", "1",
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


def poisson_run(out, *petsc, command=(sys.executable, "-m", "prdp_petsc.cli"), env=None):
    """One epoch of poisson_inverse through the command line, with PETSc options."""
    args = ["run", str(POISSON), "--preset", "quick", "--epochs", "1", "--schedule", "fixed:3",
            "--no-progress", "--out", str(out), *petsc]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    return subprocess.run(
        [*command, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )


def test_warning_filter_makes_a_misspelt_option_an_error(tmp_path):
    strict = (sys.executable, "-W", STRICT, "-m", "prdp_petsc.cli")
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
    from prdp_petsc.cli import apply_warning_options
    from prdp_petsc.errors import UnusedOptionWarning

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
