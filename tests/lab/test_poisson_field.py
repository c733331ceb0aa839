"""demos/poisson_field.py: κ-field recovery on the L-shaped mesh through capped CG."""

from pathlib import Path

import numpy as np
import pytest
import torch

from prdp_petsc.lab.training.harness import build_scene, find_k_full, run
from prdp_petsc.lab.training.scene import load_scene

SCENE = Path(__file__).resolve().parents[2] / "demos" / "poisson_field.py"
MODULE = load_scene(SCENE)


@pytest.fixture(scope="module")
def quick():
    return build_scene(load_scene(SCENE), "quick", 0)


def test_initial_error_and_sizes(quick):
    # κ = 1 everywhere against 1 + 9 bump + 3 bump: area-weighted relative L2 error
    assert quick.validate() == pytest.approx(0.75, abs=0.02)
    assert quick.info["elements"] == 2808 and quick.info["unknowns"] == 1325
    assert quick.info["kappa_contrast"] == pytest.approx(10, rel=0.01)
    assert 60 <= find_k_full(quick) <= 120  # CG + Jacobi on A_II(κ_true), rtol 1e-6


def test_smoothness_regulariser_is_a_graph_laplacian():
    module = load_scene(SCENE)
    from prdp_petsc import load_mesh

    L = module.element_adjacency_laplacian(load_mesh("lshape"))
    assert abs(L - L.T).max() == 0
    assert np.allclose(L @ np.ones(L.shape[0]), 0)  # constants are not penalised
    assert set(np.unique(L.diagonal())) <= {1.0, 2.0, 3.0}  # ≤ 3 neighbours per triangle


def test_prdp_recovers_kappa_and_refines():
    result = run(SCENE, "prdp", preset="quick", progress=False)
    ks = [e["k"] for e in result["epochs"]]
    errors = [e["val_metric"] for e in result["epochs"]]
    assert ks[0] == 20 and ks[-1] >= 50  # the controller refined ...
    assert all(b - a in (0, 10) for a, b in zip(ks, ks[1:]))  # ... by k_step = 10
    assert errors[-1] < 0.5 * 0.75  # less than half the initial κ error
    assert errors[-1] < 0.3


def test_full_fidelity_recovers_kappa_and_coarse_k_fails():
    full = run(SCENE, "fixed:90", preset="quick", progress=False)
    coarse = run(SCENE, "fixed:20", preset="quick", progress=False)
    assert full["totals"]["final_val_error"] < 0.3
    # the truncated solve misleads the gradient: the recovered κ is far off
    assert coarse["totals"]["final_val_error"] > 3 * full["totals"]["final_val_error"]


def test_unrolled_and_implicit_modes_give_the_same_forward_loss():
    """CG + Jacobi in torch (mode="unrolled") runs PETSc's iteration: same loss at equal K."""
    losses = {}
    for mode in ("implicit", "unrolled"):
        torch.manual_seed(0)
        scene = MODULE.build({**MODULE.PRESETS["quick"], "mode": mode, "steps": 1}, 0)
        for solver in scene.solvers:
            solver.max_it = 30
        losses[mode] = float(scene.loss(None).detach())
    assert losses["unrolled"] == pytest.approx(losses["implicit"], rel=1e-10)


def test_plot_fields_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    theta = np.zeros(2808)  # κ = 1 on the quick mesh
    from prdp_petsc.lab.reports.poisson_field import plot_fields

    plot_fields(MODULE, theta, tmp_path / "fields.png")
    assert (tmp_path / "fields.png").stat().st_size > 10_000
