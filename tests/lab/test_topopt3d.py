"""The 3D SIMP cantilever of demos/topopt3d.py against a published benchmark.

pasteurlabs/mosaic (commit a535cb306546d2c7276790368270f43b742059ef) stores reference
compliances of the same problem: vector Q1 hexahedra on [0, 2] × [0, 1] × [0, 1],
clamped at x = 0, a traction (0, 0, −1) on the face x = 2, E = 70 + (70000 − 70) ρ³,
ν = 0.3, C = fᵀu, on N × 2 × 4 meshes.  Each stored value is the trimmed mean of
several FEM codes' float32 compliances (FEniCS, Firedrake, deal.II, JAX-FEM agree),
so float32 equality is the precision it is stored at.  The scene's `Cantilever`
(``pp.elasticity_operator`` + ``pp.Dirichlet`` + a CG + GAMG ``pp.KSPSolver`` with
the rigid-body modes at rtol 1e-12) reproduces all ten, and a sparse direct solve
of the same operator agrees.

The design sensitivity through the bridge (``torch.autograd`` through
``pp.solve``) is checked against the analytic SIMP sensitivity
−p ρ^(p−1) (E_0 − E_min) u_eᵀ k_0 u_e, computed by scikit-fem alone, and against
central finite differences.
"""

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import skfem
import torch
from skfem.helpers import ddot, sym_grad, trace

import prdp_petsc as pp
from prdp_petsc.lab.training.scene import load_scene

SCENE = load_scene(Path(__file__).resolve().parents[2] / "demos" / "topopt3d.py")

# Mosaic's material (mosaic/benchmarks/problems/structural_mesh/config.py: _E_MAX,
# _NU, _XMIN; penalisation 3 in every solver).
E_0, E_MIN, NU, PENAL = 70_000.0, 70.0, 0.3, 3.0

# pasteurlabs/mosaic @ a535cb306546d2c7276790368270f43b742059ef,
# mosaic/benchmarks/problems/structural_mesh/references/forward_baseline.npz:
# uniform ρ = 0.5 on N × 2 × 4 meshes (reference_i, float32, as their uint32 bits).
BASELINE = {4: 997208975, 6: 998160718, 8: 998392689, 12: 998540196, 16: 998595104}
# ... references/forward_agreement.npz: uniform ρ = rho_0 (a float32) on 8 × 2 × 4.
AGREEMENT = {0.2: 1029959679, 0.4: 1006404160, 0.5: 998392689, 0.7: 985586209, 0.9: 976478000}


def _float32(bits: int) -> np.float32:
    return np.array([bits], dtype=np.uint32).view(np.float32)[0]


def mosaic_cantilever(n: int) -> "SCENE.Cantilever":
    """Mosaic's mesh n × 2 × 4 with the load on the whole face x = 2 (traction 1)."""
    return SCENE.Cantilever((n, 2, 4), z_c=0.5, half_width=0.5)


def stiffness(rho) -> np.ndarray:
    return E_MIN + (E_0 - E_MIN) * np.asarray(rho, dtype=np.float64) ** PENAL


CASES = [(n, 0.5, bits) for n, bits in BASELINE.items()]
CASES += [(8, rho, bits) for rho, bits in AGREEMENT.items()]


@pytest.mark.parametrize(("n", "rho", "bits"), CASES, ids=lambda v: str(v))
def test_mosaic_compliances_are_reproduced_in_float32(n, rho, bits):
    """float32(C) equals Mosaic's stored float32, with CG + GAMG and with a direct solve.

    Mosaic builds ρ as a float32 array, so ρ goes through float32 first (with the
    float64 0.2, 0.4 or 0.9 the compliance is one float32 ulp off).
    """
    problem = mosaic_cantilever(n)
    rho32 = float(np.float32(rho))
    theta = np.full(problem.A.n_params, stiffness(rho32))
    with problem.solver(1000, rtol=1e-12, prefix="t_mosaic_") as solver:
        c = problem.compliance(theta, solver)  # one solve, converged or it raises
        assert solver.stats.forward_solves == 1 and solver.stats.forward_iterations <= 40
    direct = spla.spsolve(problem.bc.A_II.matrix(theta).tocsc(), problem.b)
    c_direct = float(problem.b @ direct)
    reference = _float32(bits)
    assert np.float32(c) == reference, (c, float(reference))
    assert np.float32(c_direct) == reference
    assert c == pytest.approx(c_direct, rel=1e-10)


def test_uniform_compliance_scales_with_one_over_e():
    """C ∝ 1/E(ρ) for a uniform design (a fixed load, ν fixed): the stored values
    obey it to their float32 rounding, C(0.2)/C(0.5) = E(0.5)/E(0.2) ≈ 14.0."""
    ratio = float(_float32(AGREEMENT[0.2])) / float(_float32(AGREEMENT[0.5]))
    expected = stiffness(np.float32(0.5)) / stiffness(np.float32(0.2))
    assert ratio == pytest.approx(expected, rel=3e-7)


@skfem.Functional
def _unit_energy(w):
    """u_eᵀ k_0 u_e per element (E = 1), by scikit-fem alone."""
    lam, mu = NU / ((1 + NU) * (1 - 2 * NU)), 1 / (2 * (1 + NU))
    eu = sym_grad(w["u"])
    return lam * trace(eu) ** 2 + 2 * mu * ddot(eu, eu)


@pytest.fixture(scope="module")
def random_design():
    """Mosaic's random density (ics._random: 0.5 + 0.3 N(0, 1), clipped to
    [0.05, 0.95], seed 0) on 8 × 2 × 4, mapped to scikit-fem's element order."""
    problem = mosaic_cantilever(8)
    ijk = np.floor(problem.centroids.T / np.array([2 / 8, 1 / 2, 1 / 4])).astype(int)
    mosaic_index = ijk[:, 0] + 8 * (ijk[:, 1] + 2 * ijk[:, 2])
    rng = np.random.default_rng(0)
    rho = np.clip(0.5 + 0.3 * rng.standard_normal(64).astype(np.float32), 0.05, 0.95)
    return problem, rho.astype(np.float64)[mosaic_index]


def _compliance(problem, rho: torch.Tensor, solver) -> torch.Tensor:
    b = torch.from_numpy(problem.b)
    theta = E_MIN + (E_0 - E_MIN) * rho**PENAL
    return b @ pp.solve(problem.bc.A_II, b, solver, theta=theta)


def test_sensitivity_matches_the_analytic_simp_formula_and_differences(random_design):
    """dC/dρ from torch autograd through the converged solve (implicit adjoint):
    equal to −p ρ^(p−1) (E_0 − E_min) u_eᵀ k_0 u_e to 1e-9, and to central finite
    differences along a random direction to 1e-7 (ε = 1e-5)."""
    problem, rho_np = random_design
    rho = torch.tensor(rho_np, requires_grad=True)
    with problem.solver(1000, rtol=1e-13, prefix="t_sens_") as solver:
        c = _compliance(problem, rho, solver)
        (grad,) = torch.autograd.grad(c, rho)
        u = np.zeros(problem.basis.N)
        u[problem.bc.interior] = spla.spsolve(
            problem.bc.A_II.matrix(stiffness(rho_np)).tocsc(), problem.b
        )
        energy = _unit_energy.elemental(problem.basis, u=problem.basis.interpolate(u))
        analytic = -PENAL * rho_np ** (PENAL - 1) * (E_0 - E_MIN) * energy
        assert np.all(analytic < 0)  # more material, less compliance
        np.testing.assert_allclose(grad.numpy(), analytic, rtol=1e-9, atol=0)

        direction = np.random.default_rng(1).standard_normal(rho_np.size)
        eps = 1e-5
        with torch.no_grad():
            up = _compliance(problem, torch.tensor(rho_np + eps * direction), solver)
            down = _compliance(problem, torch.tensor(rho_np - eps * direction), solver)
        fd = float(up - down) / (2 * eps)
        assert fd == pytest.approx(float(grad.numpy() @ direction), rel=1e-7)


def test_capped_sensitivity_is_the_energy_of_the_capped_state(random_design):
    """With K capped, the bridge's gradient is −p ρ^(p−1)(E_0 − E_min) u_Kᵀ k_0 u_K:
    CG's adjoint for the same right-hand side from zero is u_K itself, so the capped
    gradient is the analytic formula at the capped displacement, not at the exact one."""
    problem, rho_np = random_design
    rho = torch.tensor(rho_np, requires_grad=True)
    with problem.solver(2, prefix="t_capped_") as solver:
        c = _compliance(problem, rho, solver)
        (grad,) = torch.autograd.grad(c, rho)
        u_k = np.zeros(problem.basis.N)
        solver.set_operator(problem.bc.A_II.matrix(stiffness(rho_np)))
        u_k[problem.bc.interior] = solver.solve(problem.b).value
    energy = _unit_energy.elemental(problem.basis, u=problem.basis.interpolate(u_k))
    analytic = -PENAL * rho_np ** (PENAL - 1) * (E_0 - E_MIN) * energy
    np.testing.assert_allclose(grad.numpy(), analytic, rtol=1e-8)
    exact = spla.spsolve(problem.bc.A_II.matrix(stiffness(rho_np)).tocsc(), problem.b)
    assert float(c.detach()) < float(problem.b @ exact)  # the capped compliance reads low


def test_density_filter_preserves_a_uniform_design_and_is_local():
    H = SCENE.density_filter(SCENE.Cantilever((8, 4, 4)).centroids, 1.5 / 4)
    np.testing.assert_allclose(H @ np.ones(H.shape[0]), 1.0, rtol=1e-14)
    assert H.min() >= 0
    assert H.getnnz(axis=1).max() <= 27  # neighbours within 1.5 element widths: a 3³ block


def test_optimality_criteria_keeps_the_volume_and_the_move_limit():
    x = torch.full((50,), 0.4, dtype=torch.float64, requires_grad=True)
    x.grad = -torch.linspace(0.1, 5.0, 50, dtype=torch.float64)  # dC/dx < 0
    volume_grad = torch.full((50,), 1 / 50, dtype=torch.float64)
    oc = SCENE.OptimalityCriteria([x], volume=lambda d: float(d.mean()),
                                  volume_grad=volume_grad, volfrac=0.4, move=0.1)  # fmt: skip
    oc.step()
    assert float(x.detach().mean()) == pytest.approx(0.4, abs=1e-7)
    assert float((x.detach() - 0.4).abs().max()) <= 0.1 + 1e-15
    assert x[-1] > x[0]  # material goes where it lowers the compliance most
    with pytest.raises(ValueError, match="volfrac"):
        SCENE.OptimalityCriteria([x], volume=float, volume_grad=volume_grad, volfrac=1.5)


def test_load_cases_0_and_2_are_mirror_images():
    """The band at z = 0 and at z = 1 mirror each other in z ↦ 1 − z: the solid
    block's compliance is the same for both (to solver accuracy); the middle band
    (case 1) is a different load."""
    cases = [SCENE.Cantilever((8, 4, 4), z_c=SCENE.load_case(seed)) for seed in range(3)]
    solid = []
    with cases[0].solver(1000, rtol=1e-12, prefix="t_mirror_") as solver:
        for problem in cases:
            solid.append(problem.compliance(np.ones(problem.A.n_params), solver))
    assert solid[0] == pytest.approx(solid[2], rel=1e-10)
    assert abs(solid[1] - solid[0]) > 1e-3 * solid[0]


def test_results_command_scores_every_route_on_quick():
    """`results` on quick, one load case: the converged route is the reference
    (ratio 1, nothing saved), a constant K = 2 costs exactly 2 forward + 2 adjoint
    iterations per design iteration, and the page's table has a line per route."""
    from prdp_petsc.lab.reports.topopt import format_results, results, target_met

    data = results(SCENE, "quick", [0], [2])
    (case,) = data["cases"]
    routes = case["routes"]
    assert routes["converged"]["ratio"] == 1.0 and routes["converged"]["saved"] == 0.0
    epochs = SCENE.PRESETS["quick"]["epochs"]
    assert routes["K=2"]["iterations"] == 2 * 2 * epochs
    assert all(abs(r["volume"] - 0.3) < 1e-6 for r in routes.values() if "volume" in r)
    table = format_results(data)
    assert all(label in table for label in routes)
    assert target_met(data) == [
        routes["PRDP (auto)"]["ratio"] <= 1.01 and routes["PRDP (auto)"]["saved"] >= 0.5
    ]


def test_the_results_page_says_when_a_route_beats_the_converged_design():
    from prdp_petsc.lab.reports.topopt import spread, target_met

    def case(seed, prdp_ratio):
        routes = {
            "converged": {"ratio": 1.0, "saved": 0.0},
            "PRDP (auto)": {"ratio": prdp_ratio, "saved": 0.7},
        }
        return {"seed": seed, "load_height": 0.5, "routes": routes}

    data = {"cases": [case(0, 1.005), case(1, 0.95)]}
    assert target_met(data) == [True, True]
    assert "PRDP (auto) on case 1 (0.950)" in spread(data)
    assert spread({"cases": [case(0, 1.005)]}) is None
