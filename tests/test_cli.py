"""The command line starts PETSc with its PETSc options (run in fresh interpreters)."""

import json
import os
import subprocess
import sys
from pathlib import Path

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
