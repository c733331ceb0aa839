"""Every scene in demos/ trains for real on its quick preset (scikit-fem's test_examples.py).

A scene is any ``demos/*.py`` that defines ``PRESETS`` and ``build`` at top level; it is
found by reading the file (nothing is imported at collection), so a new scene is tested
the moment its file lands.
"""

import ast
import math
from pathlib import Path

import pytest

from prdp_petsc.training.harness import run
from prdp_petsc.training.scene import load_scene

DEMOS = Path(__file__).resolve().parent.parent / "demos"
QUICK_EPOCHS = 3


def is_scene(path: Path) -> bool:
    """True if the file defines ``PRESETS`` and ``def build`` at module level."""
    names = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.FunctionDef):
            names.add(node.name)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(t.id for t in targets if isinstance(t, ast.Name))
    return {"PRESETS", "build"} <= names


SCENES = sorted(p for p in DEMOS.glob("*.py") if is_scene(p))


def test_scenes_are_discovered():
    assert {"heat1d", "poisson_inverse"} <= {p.stem for p in SCENES}
    assert not is_scene(Path(__file__))


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_scene_is_documented(path):
    module = load_scene(path)
    assert {"quick", "paper"} <= set(module.PRESETS)
    assert "PDE" in module.__doc__ and "Solver in the loop" in module.__doc__


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_scene_trains_with_prdp_on_quick_preset(path, tmp_path):
    result = run(path, "prdp", preset="quick", epochs=QUICK_EPOCHS, out=tmp_path, progress=False)
    assert result["stopped"] is None
    epochs = result["epochs"]
    assert [e["epoch"] for e in epochs] == list(range(QUICK_EPOCHS))
    assert all(math.isfinite(e["val_metric"]) and e["val_metric"] >= 0 for e in epochs)
    assert all(math.isfinite(e["train_loss"]) for e in epochs)
    # the solvers really ran, K iterations per forward solve in fixed mode
    assert all(e["k"] >= 1 and e["fwd_iterations"] >= e["k"] for e in epochs)
    assert result["totals"]["epochs"] == QUICK_EPOCHS
    assert (tmp_path / "results.json").is_file()


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
