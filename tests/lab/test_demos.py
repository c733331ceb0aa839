"""Every scene in demos/ trains for real on its quick preset (scikit-fem's test_examples.py).

A scene is any ``demos/*.py`` that defines ``PRESETS`` and ``build`` at top level; it is
found by reading the file (nothing is imported at collection), so a new scene is tested
the moment its file lands, and fails `test_every_scene_has_its_checks` until `CHECKS`
holds a check of it and `PINNED` its number.

Two kinds of check, on each preset's full PRDP training (`CASES`):

* properties that hold on every seed for a reason each check states (K moves only by
  the controller's rule and never past K_full, closed-form eigenvalues and K_full,
  energy decay, a divergence-free step, a stiffness bound), run on each seed of `SEEDS`;
* one number per case, the final validation metric on seed `SEED` (`PINNED`): a quick
  run is deterministic (one torch thread, seeded data, PETSc on one process: the same
  bits twice in a process, in a fresh one and with one or two BLAS threads), so its
  tolerance `RTOL` covers floating-point and BLAS differences only.
"""

import ast
import math
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
import torch

import prdp_petsc as pp
from prdp_petsc.fem.fd import laplacian
from prdp_petsc.lab.components import mac
from prdp_petsc.lab.reports import topopt as topopt_reports
from prdp_petsc.lab.training.harness import build_scene, find_k_full, run
from prdp_petsc.lab.training.scene import load_scene

DEMOS = Path(__file__).resolve().parents[2] / "demos"
SEEDS = (0, 1)
#: The seed of the pinned numbers, and their relative tolerance.
SEED, RTOL = 0, 1e-6


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
#: What the physical checks train: every scene's quick preset, and the presets of a
#: scene's other settings (heat.py's cube); a check is keyed ``stem`` or ``stem:preset``.
CASES = [(p, "quick") for p in SCENES] + [(DEMOS / "heat.py", "quick3d")]


def case_name(path: Path, preset: str) -> str:
    return path.stem if preset == "quick" else f"{path.stem}:{preset}"


def train(path: Path, seed: int, out: Path, preset: str = "quick") -> types.SimpleNamespace:
    """PRDP on `preset`; also the untrained metric, K_full and the trained scene.

    The scene's ``build`` is wrapped so that the metric of the freshly built model
    (before any step) and K_full of its probe are taken on the very scene that trains.
    """
    module = load_scene(path)
    trained = types.SimpleNamespace(module=module, seed=seed)

    def build(config, seed):
        scene = module.build(config, seed)
        trained.config, trained.scene = config, scene
        trained.k_max_set = scene.prdp.get("k_max")  # the scene's own cap, if any
        trained.untrained, trained.k_full = scene.validate(), find_k_full(scene)
        return scene

    wrapper = types.SimpleNamespace(PRESETS=module.PRESETS, build=build)
    trained.result = run(path, "prdp", preset=preset, seed=seed, out=out, progress=False,
                         module=wrapper)  # fmt: skip
    trained.errors = [e["val_metric"] for e in trained.result["epochs"]]
    trained.losses = [e["train_loss"] for e in trained.result["epochs"]]
    return trained


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """``trained(path, seed, preset)``: one PRDP run per scene, preset and seed, shared by
    the tests."""
    runs = {}

    def get(path: Path, seed: int, preset: str = "quick"):
        if (path, seed, preset) not in runs:
            out = tmp_path_factory.mktemp(f"{path.stem}_{preset}_{seed}")
            runs[path, seed, preset] = train(path, seed, out, preset)
        return runs[path, seed, preset]

    return get


def test_scenes_are_discovered():
    assert {"heat1d", "poisson_inverse"} <= {p.stem for p in SCENES}
    assert not is_scene(Path(__file__))


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_scene_loads_and_has_the_presets_the_tests_use(path):
    """Loading checks the presets (`check_presets`); these tests train ``quick``."""
    module = load_scene(path)
    assert {"quick", "paper"} <= set(module.PRESETS)


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_scene_trains_with_prdp_on_quick_preset(path, trained):
    t = trained(path, SEED)
    result, epochs = t.result, t.result["epochs"]
    assert result["stopped"] is None
    assert [e["epoch"] for e in epochs] == list(range(t.scene.epochs))
    assert all(math.isfinite(e) for e in t.errors + t.losses)
    # the solvers really ran, K iterations per forward solve in fixed mode
    assert all(e["k"] >= 1 and e["fwd_iterations"] >= e["k"] for e in epochs)
    assert result["totals"]["epochs"] == len(epochs)


@pytest.mark.parametrize("seed", SEEDS, ids=lambda s: f"seed{s}")
@pytest.mark.parametrize(("path", "preset"), CASES, ids=lambda c: getattr(c, "stem", c))
def test_prdp_moves_k_only_up_by_its_rule_and_never_past_k_full(path, preset, seed, trained):
    """K starts at the scene's K₀; between epochs it stays or refines to
    min(max(K + k_step, ⌈growth K⌉), k_max) (`PRDP.update`), so it never decreases; the
    cap is K_full of the scene's probe (past it a solve buys nothing) unless the scene
    sets a lower one.  Properties of the controller, so on every seed."""
    t = trained(path, seed, preset)
    prdp = t.result["prdp"]
    ks = [e["k"] for e in t.result["epochs"]]
    assert ks[0] == prdp["k_init"] == t.scene.prdp["k_init"]
    for k, following in zip(ks, ks[1:]):
        refined = math.ceil(prdp.get("growth", 1.0) * k)
        assert following in (k, min(max(k + prdp["k_step"], refined), prdp["k_max"]))
    assert prdp["k_max"] == (t.k_max_set or t.k_full) <= t.k_full
    assert max(ks) <= prdp["k_max"]


# -- the physics of each scene, on every seed ------------------------------------------------


def check_heat1d(t):
    # Damped Jacobi (ω = 0.8) on the BTCS matrix I + r(2I − S), r = νΔt/h²: the
    # diagonal is the constant 1 + 2r, so the iteration matrix is symmetric with
    # spectral radius ρ₁ = 1 − ω(1 + 4r sin²(πh/2))/(1 + 2r) (the smoothest mode; the
    # roughest contracts by |1 − ω(1 + 4r)/(1 + 2r)| = 0.33 < ρ₁ = 0.72).  So from zero
    # ‖r_K‖ ≤ ρ₁^K ‖b‖ whatever b is, and K_full ≤ ⌈ln 10⁻⁶ / ln ρ₁⌉ = 43.
    n = t.config["n"]
    h, r, omega = 1 / (n + 1), t.module.NU_DT * (n + 1) ** 2, t.module.JACOBI_SCALE
    rho = 1 - omega * (1 + 4 * r * math.sin(math.pi * h / 2) ** 2) / (1 + 2 * r)
    bound = math.ceil(math.log(t.scene.rtol_full) / math.log(rho))
    assert bound == 43 and t.k_full <= bound


def _modal_emulator(t):
    """Learned numbers of the ModalNet heat emulator (heat.py on the L-shape and the cube)."""
    # The untrained network is the projection onto the kept modes, which does not
    # decay; the exact step is one multiplier per mode, within the network's reach, so
    # training beats the projection.
    assert t.errors[-1] < t.untrained
    # The learned multiplier of the slowest mode moves from its start at 1 towards the
    # exact implicit-Euler decay 1 / (1 + Δt λ₁), the minimiser of the converged loss.
    mesh = pp.load_mesh(t.config["mesh"], refine=t.config["refine"])
    dt = t.config["dt"]
    A, B, _, _ = t.module.heat_step_system(mesh, dt)
    lam, _ = t.module.laplacian_modes((A - B) / dt, B, 3)
    (weights,) = t.scene.optimizer.param_groups[0]["params"]
    assert weights.shape == (t.config["modes"],)
    exact = 1 / (1 + dt * lam[0])
    assert abs(float(weights.detach()[0]) - exact) < 1 - exact
    return lam


def check_heat(t):
    lam = _modal_emulator(t)
    # Conforming P1 eigenvalues are upper bounds of the exact ones and converge to
    # them: the L-shape (0, 1)² minus [½, 1]² has λ₁ = 4 × 9.6397238 (Trefethen and
    # Betcke's value for the three-unit-square L, scaled by 2²) and λ₃ = 8π²
    # (sin 2πx sin 2πy vanishes on the whole boundary).  Measured 38.741 and 79.206.
    l1, l3 = 4 * 9.6397238, 8 * math.pi**2
    assert l1 <= lam[0] <= 1.01 * l1
    assert l3 <= lam[2] <= 1.01 * l3


def check_heat3d(t):
    lam = _modal_emulator(t)
    # unit cube: λ₁ = 3π², and P1 gives an upper bound (h ≈ 0.13: 4 % above)
    assert 3 * math.pi**2 <= lam[0] <= 1.06 * 3 * math.pi**2


def check_heat_nonlinear(t):
    # MeshNet starts as the identity, which does not decay; training beats it.
    assert t.errors[-1] < t.untrained
    # The exact steps of the scene: testing R(u¹) = 0 with u¹ gives
    # ‖u¹‖²_M + Δt (κ(u¹)∇u¹, ∇u¹) = (u⁰, u¹)_M, and κ = 1 + αu² ≥ 1 with the discrete
    # Poincaré inequality (∇u, ∇u) ≥ λ₁‖u‖²_M (λ₁ ≥ the L-shape's 4 × 9.6397238)
    # bound the energy ratio per step by (1 + Δt λ₁)⁻² = 0.862.  Faster than the
    # linear step (α = 0) from the same state, which a direct solve with M + Δt K
    # reproduces.
    from skfem.models.poisson import laplace

    config, module = t.config, t.module
    mesh = pp.load_mesh(config["mesh"], refine=config["refine"])
    basis = skfem.Basis(mesh, skfem.ElementTriP1())
    heat = module.NonlinearHeat(basis, config["dt"])
    inner = np.ix_(heat.interior, heat.interior)
    M, K = heat.M[inner].tocsr(), laplace.assemble(basis)[inner].tocsr()
    u0 = module.initial_conditions(heat, 2, np.random.default_rng(t.seed))
    nonlinear = module.trajectories(heat, u0, 10, config["alpha"])
    linear = module.trajectories(heat, u0, 10, 0.0)

    def energy(traj):  # (steps + 1, samples)
        return np.stack([((M @ u.T).T * u).sum(-1) for u in traj])

    bound = (1 + config["dt"] * 4 * 9.6397238) ** -2
    assert np.all(energy(nonlinear)[1:] <= bound * energy(nonlinear)[:-1])
    assert np.all(energy(nonlinear)[-1] < energy(linear)[-1])
    lu = spla.splu((M + config["dt"] * K).tocsc())
    u = u0
    for _ in range(10):
        u = lu.solve(M @ u.T).T
    assert np.abs(u - linear[-1]).max() <= 1e-10 * np.abs(u).max()


def check_ns2d(t):
    # The corrector starts as the zero map (the plain coarse solver, a network output
    # it can always return); training finds a better one at some epoch, and lowers
    # the loss it minimises.
    assert min(t.errors) < t.untrained
    assert t.losses[-1] < t.losses[0]
    # MAC conserves mass: the converged step from the probe's state is discretely
    # divergence-free, with zero-mean pressure (the null space removed).
    n = t.config["n"]
    A, b, x0 = t.scene.probe()
    assert x0 is None  # GMRES from zero
    with pp.KSPSolver(t.module.GMRES, prefix="t_demo_ns_", max_it=50_000, rtol=1e-12,
                      structure=pp.Structure(nullspace=mac.nullspace(n))) as solver:  # fmt: skip
        solver.set_operator(A)
        sol = solver.solve(b)
        assert sol.converged
    x = sol.value
    u, v, p = x.reshape(3, -1)
    assert np.abs(mac.divergence(x, n)).max() < 1e-9 * n * np.abs(np.r_[u, v]).max()
    assert abs(p.mean()) < 1e-12 * np.abs(p).max()


def check_poisson_field(t):
    # κ = 1 against κ_true = 1 + 9 g(0.1) + 3 g(0.08), g(σ) a Gaussian of width σ
    # well inside the L (area ¾): ∫g² = πσ², ∫g = 2πσ², the cross term e^-6 small, so
    # the initial error is √(2.726 / 4.847) = 0.750 (measured 0.7503); the 1 % covers
    # the quadrature of the Gaussians on the mesh.
    g1, g2 = (9.0, 0.1), (3.0, 0.08)
    sq = sum(a**2 * math.pi * s**2 for a, s in (g1, g2))
    lin = sum(a * 2 * math.pi * s**2 for a, s in (g1, g2))
    assert t.untrained == pytest.approx(math.sqrt(sq / (0.75 + 2 * lin + sq)), rel=0.01)
    assert t.errors[-1] < t.untrained  # the fit moves κ towards the truth


def check_poisson3d(t):
    # κ = 1 against κ_true = 1 + Σ a_i g_i, g_i 3D Gaussians (σ 0.12 and 0.1) well inside
    # the cube: ∫g_i g_j = (2π σ_i²σ_j² / (σ_i² + σ_j²))^{3/2} exp(−d_ij² / 2(σ_i² + σ_j²))
    # and ∫g_i = (2πσ_i²)^{3/2} give the initial error 0.58785 (measured 0.58797 with
    # centroid values on the quick mesh).
    bumps = [(9.0, 0.12, np.array([0.35, 0.4, 0.5])), (3.0, 0.1, np.array([0.7, 0.65, 0.4]))]

    def cross(a, b):
        (ai, si, ci), (aj, sj, cj) = a, b
        s2 = si**2 + sj**2
        scale = (2 * math.pi * si**2 * sj**2 / s2) ** 1.5
        return ai * aj * scale * math.exp(-float(np.sum((ci - cj) ** 2)) / (2 * s2))

    sq = sum(cross(a, b) for a in bumps for b in bumps)
    lin = sum(a * (2 * math.pi * s**2) ** 1.5 for a, s, _ in bumps)
    assert t.untrained == pytest.approx(math.sqrt(sq / (1 + 2 * lin + sq)), rel=0.01)
    assert t.errors[-1] < t.untrained
    # every rank's share: the one process owns every unknown
    assert t.scene.info["owned_unknowns"] == [(t.config["n"] - 2) ** 3]


def _poisson_inverse_rho(n: int) -> float:
    """Jacobi contraction of the mode sin(2πx) of −u'' (h = 1/(n + 1)): cos(2πh)."""
    return math.cos(2 * math.pi / (n + 1))


def check_poisson_inverse(t):
    # The right-hand side θ sin(2πx) is an eigenvector of −Δ_h with a constant
    # diagonal, so every Jacobi iteration multiplies its residual by exactly
    # ρ = cos(2πh): K_full = ⌈ln 10⁻⁶ / ln ρ⌉ = 668 (measured 668).
    rho = _poisson_inverse_rho(t.config["n"])
    assert t.k_full == math.ceil(math.log(t.scene.rtol_full) / math.log(rho)) == 668
    # θ starts at 0.5: |θ − 2|/2 = 1.5 exactly.  At K₀ = 25 the capped misfit's
    # minimiser is 2 / (1 − ρ²⁵), 1.48 off (`test_poisson_inverse_fixed_k_...`), so
    # only refining can bring θ near 2: the controller must refine.
    assert t.untrained == 1.5
    assert t.result["epochs"][-1]["k"] > t.scene.prdp["k_init"]
    assert t.errors[-1] < t.errors[0]


def check_poisson_sip(t):
    # The network starts at zero: x error exactly 1; training moves it below.
    assert t.untrained == 1.0 and t.errors[-1] < 1.0
    # P = A⁻¹M smooths: the error left in x sits in the rough modes P damps most,
    # while the smooth truth passes, so the solution misfit is the smaller one.
    final = t.scene.info["final"]
    assert final["x_error"] == t.errors[-1]
    assert final["y_error"] < final["x_error"]


def check_topopt3d(t):
    # The final design holds the volume fraction (OC's bisection, 0.3 to float32).  No
    # design of ρ ≤ 1 is stiffer than the solid block (compliance falls as the
    # stiffness rises), and the optimiser, which starts from the uniform design of the
    # same volume, ends stiffer than it.  The uniform design's compliance is the
    # solid's over E(0.3) exactly (a uniform E scales the operator).
    config, problem = t.config, t.scene.problem
    assert float(t.scene.designs[-1].mean()) == pytest.approx(config["volfrac"], abs=1e-6)
    assert t.errors[-1] < config["move"]  # a design change within the move limit
    final = topopt_reports.scored(t.module, t.scene, config)[-1]
    with problem.solver(1000, rtol=1e-10, prefix="t_demo_to_") as solver:
        solid = problem.compliance(np.ones(problem.A.n_params), solver)
        e_uniform = float(t.module.simp(torch.tensor(config["volfrac"]), config["penal"],
                                        config["e_min"]))  # fmt: skip
        uniform = problem.compliance(np.full(problem.A.n_params, e_uniform), solver)
    assert uniform == pytest.approx(solid / e_uniform, rel=1e-8)
    assert solid < final < uniform
    # The box is symmetric in z ↦ 1 − z, so the load band at 1 − z_c (seed 0's at z = 0
    # is seed 2's at z = 1) gives the mirrored displacement and the same compliance.
    n = config["n"]
    mirror = t.module.Cantilever((2 * n, n, n), z_c=1 - t.module.load_case(t.seed))
    with mirror.solver(1000, rtol=1e-10, prefix="t_demo_to_") as solver:
        mirrored = mirror.compliance(np.ones(mirror.A.n_params), solver)
    assert mirrored == pytest.approx(solid, rel=1e-8)


CHECKS = {
    "heat1d": check_heat1d,
    "heat": check_heat,
    "heat:quick3d": check_heat3d,
    "heat_nonlinear": check_heat_nonlinear,
    "ns2d": check_ns2d,
    "poisson_field": check_poisson_field,
    "poisson3d": check_poisson3d,
    "poisson_inverse": check_poisson_inverse,
    "poisson_sip": check_poisson_sip,
    "topopt3d": check_topopt3d,
}

#: The final validation metric of each case's PRDP run on seed `SEED` (each scene's
#: docstring says what its metric is).  A change to a scene that moves one on purpose
#: updates it here; any other change must leave it within `RTOL`.
PINNED = {
    "heat1d": 7.423716378379538,  # 10-step rollout error: quick's K ≤ 3 blows up
    "heat": 0.1036036471000559,  # rollout error (0.22 of the untrained 0.472)
    "heat:quick3d": 0.14703062243163992,  # rollout error (untrained 9.46)
    "heat_nonlinear": 0.5083000282635964,  # rollout error (identity: 1.159)
    "ns2d": 0.03621309813871238,  # 5-step nMSE (coarse solver alone: 0.0611)
    "poisson_field": 0.27144774661741344,  # κ error (start 0.750)
    "poisson3d": 0.40319058213086056,  # κ error (start 0.588)
    "poisson_inverse": 0.02426312196204572,  # |θ − 2|/2 (start 1.5)
    "poisson_sip": 0.478120084963546,  # relative x error (start 1)
    "topopt3d": 0.0844279018879841,  # the last design change max |x_t − x_{t−1}|
}


def test_every_scene_has_its_checks():
    cases = {case_name(*case) for case in CASES}
    for table in (CHECKS, PINNED):
        missing = cases - set(table)
        assert not missing, f"add {sorted(missing)} to CHECKS and PINNED"
        assert set(table) <= cases  # no check of a scene or preset that is gone


@pytest.mark.parametrize("seed", SEEDS, ids=lambda s: f"seed{s}")
@pytest.mark.parametrize(("path", "preset"), CASES, ids=lambda c: getattr(c, "stem", c))
def test_quick_training_meets_the_scenes_physics(path, preset, seed, trained):
    t = trained(path, seed, preset)
    assert t.result["stopped"] is None
    CHECKS[case_name(path, preset)](t)


@pytest.mark.parametrize(("path", "preset"), CASES, ids=lambda c: getattr(c, "stem", c))
def test_quick_training_gives_its_pinned_number(path, preset, trained):
    name = case_name(path, preset)
    final = trained(path, SEED, preset).errors[-1]
    assert final == pytest.approx(PINNED[name], rel=RTOL), f"{name}: update PINNED if meant"


@pytest.mark.parametrize("stem", ["poisson_field", "poisson3d", "poisson_inverse"])
def test_a_scene_without_randomness_trains_the_same_on_every_seed(stem, trained):
    """Fixed noise seed and θ₀ (no network, no data drawn): the seed changes nothing."""
    first, second = (trained(DEMOS / f"{stem}.py", seed) for seed in SEEDS)
    assert first.errors == second.errors and first.losses == second.losses


@pytest.mark.parametrize("k", [25, 100, 300])
def test_poisson_inverse_fixed_k_converges_to_the_biased_theta(k):
    """K Jacobi iterations from zero leave (1 − ρ^K) of the solution of the eigenmode,
    so the capped misfit is minimal at θ* = θ_ref / (1 − ρ^K): |θ* − 2|/2 = 1.4769,
    0.14470, 0.0020239 for K = 25, 100, 300; the 1 % covers what 60 SGD steps leave
    of the way to it (0.4 % at K = 300)."""
    module = load_scene(DEMOS / "poisson_inverse.py")
    result = run(DEMOS / "poisson_inverse.py", f"fixed:{k}", progress=False, module=module)
    rho = _poisson_inverse_rho(module.PRESETS["quick"]["n"])
    theta_star = module.THETA_REF / (1 - rho**k)
    expected = abs(theta_star - module.THETA_REF) / module.THETA_REF
    assert result["totals"]["final_val_error"] == pytest.approx(expected, rel=0.01)


# -- heat1d's unroll setting (multi-step training) ------------------------------------------


def _heat1d_scene_and_net(preset: str, seed: int = 0):
    """heat1d's scene, and a copy of its MLP (the loss closes over the scene's own)."""
    module = load_scene(DEMOS / "heat1d.py")
    scene = build_scene(module, preset, seed)
    net = module.network(module.PRESETS["quick"]["n"])
    for mine, theirs in zip(net.parameters(), scene.optimizer.param_groups[0]["params"]):
        mine.data.copy_(theirs.detach())
    return module, scene, net


def _heat1d_data(module, seed: int, steps: int):
    """The exact states u⁰ … u^steps of heat1d quick's training trajectories, computed
    as the scene does (the same dense SPD solve, so the same bits)."""
    config = module.PRESETS["quick"]
    n = config["n"]
    rng = np.random.default_rng(seed)
    u0 = module.initial_conditions(config["n_train"] + config["n_val"], n, config["modes"], rng)
    A = (sp.identity(n, format="csr") - module.NU_DT * laplacian(n)).tocsr()
    traj = [u0]
    for _ in range(steps):
        traj.append(scipy.linalg.solve(A.toarray(), traj[-1].T, assume_a="pos").T)
    return A, torch.from_numpy(np.stack(traj)[:, : config["n_train"]])


def test_heat1d_unroll_1_is_the_one_step_loss_to_the_bit():
    """unroll = 1 (every preset's default) is the loss ‖P_K(N(u⁰)) − u²‖² the scene had."""
    module, scene, net = _heat1d_scene_and_net("quick")
    (solver,) = scene.solvers
    solver.max_it = 5
    A, traj = _heat1d_data(module, 0, 2)
    idx = torch.tensor([3, 0, 17, 8])
    u2_hat = pp.solve(A, net(traj[0][idx]), solver)
    old = ((u2_hat - traj[2][idx]) ** 2).sum(-1).mean()
    assert old.item() > 1e-3
    assert torch.equal(scene.loss(idx), old)


def test_heat1d_unroll_2_sums_two_chained_steps():
    """unroll = 2: (P_K ∘ N)¹ and (P_K ∘ N)² of u⁰ against u² and u⁴, summed; the same
    number as the library's `unrolled_loss` (a mean over the n values, so times n)."""
    from prdp_petsc.lab.training.unroll import unrolled_loss

    module, scene, net = _heat1d_scene_and_net("quick unroll=2")
    (solver,) = scene.solvers
    solver.max_it = 5
    A, traj = _heat1d_data(module, 0, 4)
    idx = torch.tensor([3, 0, 17, 8])
    targets = traj[::2][:, idx]  # u⁰, u², u⁴
    step = lambda state, keys: pp.solve(A, net(state), solver)  # noqa: E731
    expected = module.PRESETS["quick"]["n"] * unrolled_loss(step, targets)
    one_step = module.PRESETS["quick"]["n"] * unrolled_loss(step, targets, steps=1)
    loss = scene.loss(idx)
    assert loss.item() == pytest.approx(expected.item(), rel=1e-12)
    assert loss.item() > 1.5 * one_step.item()  # the second step adds its own misfit


#: heat1d quick unroll=2's last training loss on seed `SEED` (11.67 in its first epoch)
UNROLL_2_LOSS = 3.7849813074337253


def test_heat1d_trains_with_unroll_2_on_quick(tmp_path):
    """PRDP on quick with two chained solves per sample: twice unroll = 1's inner
    iterations at each K; the final training loss on seed 0 is pinned (`RTOL`)."""
    path = DEMOS / "heat1d.py"
    config = load_scene(path).PRESETS["quick"]
    result = run(path, "prdp", preset="quick unroll=2", seed=SEED, progress=False, out=tmp_path)
    epochs = result["epochs"]
    for e in epochs:
        assert e["fwd_iterations"] == e["adj_iterations"] == 2 * e["k"] * config["n_train"]
    losses = [e["train_loss"] for e in epochs]
    assert losses[-1] == pytest.approx(UNROLL_2_LOSS, rel=RTOL)
    assert result["config"]["unroll"] == 2


def test_heat1d_paper_k10_starts_prdp_at_k_10():
    module = load_scene(DEMOS / "heat1d.py")
    assert build_scene(module, "paper_k10", 0).prdp["k_init"] == 10
    assert build_scene(module, "quick", 0).prdp["k_init"] == 1
