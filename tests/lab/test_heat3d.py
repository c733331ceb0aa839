"""demos/heat.py on the cube: the implicit-Euler P1 step on the tetrahedral box, ModalNet,
quick3d-preset numbers."""

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch

import prdp_petsc as pp
from prdp_petsc.lab.components.emulators import gaussian_bumps
from prdp_petsc.lab.training.harness import build_scene, find_k_full, run
from prdp_petsc.lab.training.rollout import rollout_errors
from prdp_petsc.lab.training.scene import load_scene

DEMOS = Path(__file__).resolve().parents[2] / "demos"
HEAT = load_scene(DEMOS / "heat.py")
DT = HEAT.PRESETS["quick3d"]["dt"]


@pytest.fixture(scope="module")
def system():
    mesh = pp.load_mesh("box3d", refine=0)
    A, B, interior, basis = HEAT.heat_step_system(mesh, DT)
    return mesh, A, B, interior


def test_mesh_sizes_and_operator(system):
    mesh, A, B, interior = system
    assert mesh.dim() == 3 and mesh.t.shape[0] == 4  # tetrahedra
    assert A.shape == (465, 465) == B.shape
    assert abs(A - A.T).max() < 1e-14  # symmetric
    assert np.all(A.diagonal() > 0)
    ones = np.ones(A.shape[0])
    assert ones @ (A - B) @ ones > 0  # Δt K_II is positive definite (Dirichlet)


def test_jacobi_at_k_full_matches_a_direct_solve(system):
    _, A, B, interior = system
    rng = np.random.default_rng(0)
    mesh = pp.load_mesh("box3d", refine=0)
    u0 = gaussian_bumps(mesh.p[:, interior], 2, rng) * HEAT.bubble(A, B, DT)
    exact = spla.spsolve(A.tocsc(), B @ u0[0])
    scene = build_scene(HEAT, "quick3d", 0)
    k_full = find_k_full(scene)
    solver = scene.solvers[0]
    solver.max_it = k_full
    solver.set_operator(A)
    x = solver.solve(B @ u0[0]).value
    assert np.linalg.norm(x - exact) / np.linalg.norm(exact) < 1e-5
    solver.max_it = 5  # a capped solve is far from the step
    solver.set_operator(A)
    capped = solver.solve(B @ u0[0]).value
    assert np.linalg.norm(capped - exact) > 0.1 * np.linalg.norm(exact)


def test_energy_decays_at_the_rate_of_the_first_mode(system):
    _, A, B, _ = system
    lam, phi = HEAT.laplacian_modes((A - B) / DT, B, 4)
    assert lam[0] == pytest.approx(3 * np.pi**2, rel=0.06)  # unit cube: 3π² (P1, h ≈ 0.13)
    assert lam[1] == pytest.approx(6 * np.pi**2, rel=0.15)  # threefold (2,1,1)
    assert np.allclose(phi.T @ B @ phi, np.eye(4), atol=1e-10)  # M-orthonormal
    lu = spla.splu(A.tocsc())
    u = np.random.default_rng(1).standard_normal(A.shape[0])
    energy = [u @ B @ u]
    for _ in range(30):
        u = lu.solve(B @ u)
        energy.append(u @ B @ u)
    assert np.all(np.diff(energy) < 0)  # implicit Euler: ‖u‖_M decreases every step
    # late steps decay like the first mode: factor 1 / (1 + Δt λ₁) per step in ‖u‖_M
    assert np.sqrt(energy[-1] / energy[-2]) == pytest.approx(1 / (1 + DT * lam[0]), rel=1e-3)
    # the exact step is diagonal in the modes
    assert np.allclose(lu.solve(B @ phi[:, 0]), phi[:, 0] / (1 + DT * lam[0]))


def test_modal_net_starts_as_projection_and_represents_the_step(system):
    mesh, A, B, interior = system
    rng = np.random.default_rng(2)
    u0 = gaussian_bumps(mesh.p[:, interior], 6, rng) * HEAT.bubble(A, B, DT)
    net = HEAT.ModalNet((A - B) / DT, B, 16)
    phi = net.phi.numpy()
    u = torch.from_numpy(u0)
    expected = (phi @ (phi.T @ B @ u0.T)).T
    assert np.allclose(net(u).detach().numpy(), expected)
    assert torch.allclose(net(u[0]), net(u)[0])
    with pytest.raises(ValueError, match="ModalNet expects"):
        net(u[:, :-1])
    lu = spla.splu(A.tocsc())
    traj = [u0]
    for _ in range(10):
        traj.append(lu.solve(B @ traj[-1].T).T)
    traj = torch.from_numpy(np.stack(traj))
    with torch.no_grad():  # the exact step of the kept modes: a good emulator
        net.weight.copy_(1 / (1 + DT * net.eigenvalues))
    errors = rollout_errors(net, traj[0], traj[1:])
    # error of the dropped modes: largest at the first step, gone once they have decayed
    assert errors.mean() < 0.06 and errors[-1] < 1e-3
    identity = rollout_errors(lambda v: v, traj[0], traj[1:])
    assert identity.mean() > 20 * errors.mean()


def test_quick_preset_learns_the_step():
    """K_full and a PRDP run on the quick preset: numbers, not only 'it ran'."""
    scene = build_scene(HEAT, "quick3d", 0)
    assert scene.info["n"] == 465
    assert 40 <= find_k_full(scene) <= 100
    initial = scene.validate()  # the network starts as the projection (no decay)
    result = run(DEMOS / "heat.py", "prdp", preset="quick3d", progress=False)
    errors = [e["val_metric"] for e in result["epochs"]]
    assert result["stopped"] is None and len(errors) == HEAT.PRESETS["quick3d"]["epochs"]
    assert errors[-1] < 0.2 * initial
    assert len(result["rollout"]) == HEAT.PRESETS["quick3d"]["rollout_steps"]
    assert np.all(np.isfinite(result["rollout"]))
