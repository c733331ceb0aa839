"""The shipped demos are importable scenes that train for real (quick presets)."""

from pathlib import Path

import pytest

from prdp_petsc.training.harness import run
from prdp_petsc.training.scene import load_scene

DEMOS = Path(__file__).resolve().parent.parent / "demos"


@pytest.mark.parametrize("name", ["heat1d", "poisson_inverse"])
def test_demo_is_a_documented_scene(name):
    module = load_scene(DEMOS / f"{name}.py")
    assert {"quick", "paper"} <= set(module.PRESETS)
    assert "PDE" in module.__doc__ and "Solver in the loop" in module.__doc__


def test_poisson_inverse_recovers_theta_with_prdp():
    result = run(DEMOS / "poisson_inverse.py", "prdp", preset="quick", progress=False)
    ks = [e["k"] for e in result["epochs"]]
    errors = [e["val_metric"] for e in result["epochs"]]
    assert ks[0] == 25 and ks[-1] > 25  # the controller refined
    assert all(b - a in (0, 10) for a, b in zip(ks, ks[1:]))  # by k_step = 10
    assert errors[0] == pytest.approx(0.9 * 1.5, rel=0.2)  # starts near |5 - 2| / 2
    assert errors[-1] < 0.1 * errors[0]


def test_poisson_inverse_fixed_coarse_k_is_biased():
    coarse = run(DEMOS / "poisson_inverse.py", "fixed:25", preset="quick", progress=False)
    fine = run(DEMOS / "poisson_inverse.py", "fixed:300", preset="quick", progress=False)
    assert coarse["totals"]["final_val_error"] > 0.5  # K = 25 cannot recover θ
    assert fine["totals"]["final_val_error"] < 0.1 * coarse["totals"]["final_val_error"]
