"""Stability suite at small sizes: hard problems, extreme inputs and failure modes.

The rows come from `prdp_petsc.lab.reports.stability` (the same code that writes the README
table); each test asserts residuals, iteration counts, Taylor rates, finiteness or
the error type and PETSc reason.  Thresholds are sized to hold at the full sizes of
the README table too (``prdp-petsc stability``), not only at these quick sizes.
"""

import json

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl
import torch

import prdp_petsc as pp
from prdp_petsc.core import safeguards
from prdp_petsc.lab.reports import problems, stability
from prdp_petsc.lab.reports.problems import poisson_problem


@pytest.fixture(scope="module")
def rows():
    out = {}
    for name, case in stability.CASES.items():
        out[name] = case(quick=True)
    return out


def _ok(row):
    assert row["outcome"] == "ok", row.get("message")
    assert not row["nan_or_inf"]
    return row


# -- hard but well-posed problems: converge, rate 2 ------------------------------------------
def test_stiff_heat_steps_converge_with_taylor_rate_two(rows):
    heat = rows["stiff_heat"]
    assert len(heat) == 12  # Δt κ/h² = 1e-2 … 1e8, two PCs
    for row in heat:
        _ok(row)
        assert row["taylor_rate"] >= 1.9, row
        assert row["residual"] <= 1e-4  # 1.3e-5 at Δt κ/h² = 1e8, full size
    mild = [r for r in heat if r["setting"] in ("Δt κ/h² = 1e-02", "Δt κ/h² = 1e+00")]
    assert all(r["residual"] <= 1e-11 for r in mild)
    gamg = [r["iterations"] for r in heat if r["solver"] == "cg/gamg"]
    assert max(gamg) <= 20  # multigrid does not degrade with stiffness
    # ICC does: M + Δt K goes from the well-conditioned mass matrix to the stiffness
    # matrix (condition ~ h⁻²) as Δt κ/h² grows; 9 → 155 iterations (9 → 309 full size)
    icc = [r["iterations"] for r in heat if r["solver"] == "cg/icc"]
    assert icc == sorted(icc) and icc[-1] > 5 * icc[0]


def test_contrast_up_to_1e8(rows):
    contrast = rows["contrast"]
    assert {r["setting"] for r in contrast} >= {"inclusions 1e+08", "checkerboard 1e+08"}
    for row in contrast:
        _ok(row)
        # at 1e8 float64 rounding in J itself (2e-6 relative) bends the rate: 1.88 full size
        assert row["taylor_rate"] >= (1.85 if "1e+08" in row["setting"] else 1.9), row
        assert row["residual"] <= 1e-4  # 2.4e-5 for cg/jacobi at 1e8, full size
    for pattern in ("inclusions", "checkerboard"):
        gamg = [
            r["iterations"]
            for r in contrast
            if r["solver"] == "cg/gamg" and r["setting"].startswith(pattern)
        ]
        assert max(gamg) <= 1.7 * min(gamg)  # nearly flat in the contrast (18 → 28 full)
    # at every contrast the point preconditioner needs several times GAMG's count
    # (7.6-16x at these sizes: 129-264 against 15-17; 15-20x full size)
    for setting in {r["setting"] for r in contrast}:
        its = {r["solver"]: r["iterations"] for r in contrast if r["setting"] == setting}
        assert its["cg/jacobi"] > 4 * its["cg/gamg"], setting


def test_anisotropy_up_to_1e4(rows):
    for row in rows["anisotropy"]:
        _ok(row)
        assert row["taylor_rate"] >= 1.9
        assert row["residual"] <= 1e-9
    # anisotropy degrades both preconditioners: counts grow with the ratio
    # (GAMG 12, 47, 85; ICC 51, 86, 114 for ratios 1, 1e2, 1e4; full size 13, 61, 146
    # and 107, 206, 307)
    for solver in ("cg/gamg", "cg/icc"):
        its = [r["iterations"] for r in rows["anisotropy"] if r["solver"] == solver]
        assert len(its) == 3 and its[0] < its[1] < its[2], solver


def test_sliver_mesh(rows):
    for row in rows["sliver"]:
        _ok(row)
        assert "min angle 1.8" in row["setting"]
        assert row["taylor_rate"] >= 1.9
        assert row["residual"] <= 1e-9


# -- pure Neumann: null space -----------------------------------------------------------------
def test_neumann_compatible_rhs_solution_and_gradient(rows):
    neumann = [r for r in rows["neumann"] if r["setting"] == "compatible rhs"]
    assert len(neumann) == 3
    for row in neumann:
        _ok(row)
        x = row["_x"]
        assert abs(x.mean()) <= 1e-12 * np.abs(x).max()  # minimum-norm solution: ⊥ 1
        assert row["residual"] <= 1e-9  # 1.2e-10 for cg/gamg, full size
        assert row["taylor_rate"] >= 1.9
    # every KSP/PC returns the same solution
    ref = neumann[0]["_x"]
    for row in neumann[1:]:
        assert np.linalg.norm(row["_x"] - ref) <= 1e-9 * np.linalg.norm(ref)


def test_neumann_incompatible_rhs_is_projected(rows):
    (row,) = [r for r in rows["neumann"] if r["setting"] == "incompatible rhs"]
    _ok(row)
    assert row["projection_error"] <= 1e-10  # = solution of the projected rhs
    assert row["residual"] <= 1e-9  # residual of the projected problem (1.2e-10 full)


def _neumann_matrix():
    from skfem import Basis, ElementTriP1

    mesh = pp.load_mesh("lshape")
    A = pp.diffusion_operator(Basis(mesh, ElementTriP1()))
    return A, np.ones(A.n_params)


def test_neumann_against_bordered_direct_solve_and_b_gradient():
    A, theta = _neumann_matrix()
    M = A.matrix(theta)
    n = M.shape[0]
    rng = np.random.default_rng(3)
    b = rng.standard_normal(n)
    b -= b.mean()
    one = np.ones((n, 1))
    bordered = sp.bmat([[M, one], [one.T, None]]).tocsc()
    x_ref = spl.spsolve(bordered, np.append(b, 0.0))[:n]
    solver = pp.KSPSolver(
        "-ksp_type cg -pc_type gamg",
        max_it=200,
        rtol=1e-12,
        structure=pp.Structure(nullspace="constant"),
    )
    b_t = torch.from_numpy(b).requires_grad_(True)
    x = pp.solve(M, b_t, solver)
    assert np.linalg.norm(x.detach().numpy() - x_ref) <= 1e-9 * np.linalg.norm(x_ref)
    w = torch.from_numpy(rng.standard_normal(n))
    (w * x).sum().backward()
    lam = b_t.grad.numpy()
    assert abs(lam.mean()) <= 1e-12 * np.abs(lam).max()  # λ = A⁺ᵀ w ⊥ 1
    w_c = w.numpy() - w.numpy().mean()
    assert np.linalg.norm(M @ lam - w_c) <= 1e-9 * np.linalg.norm(w_c)


def test_wrong_nullspace_is_rejected():
    A, theta = _neumann_matrix()
    M = A.matrix(theta) + sp.identity(A.shape[0])  # not singular: 1 is no null vector
    solver = pp.KSPSolver("-ksp_type cg", max_it=5, structure=pp.Structure(nullspace="constant"))
    with pytest.raises(ValueError, match="not a null space"):
        solver.set_operator(M)
    with pytest.raises(ValueError, match="linearly independent"):
        pp.KSPSolver(
            max_it=5,
            structure=pp.Structure(nullspace=np.zeros((1, 4))),
        )
    with pytest.raises(ValueError, match="'constant'"):
        pp.KSPSolver(max_it=5, structure=pp.Structure(nullspace="constants"))


# -- K = 1 and K far beyond convergence --------------------------------------------------------
def test_k_equals_one(rows):
    cg, rich = rows["iterations"][:2]
    for row in (cg, rich):
        _ok(row)
        assert row["iterations"] == 1 and row["reason"] == "DIVERGED_MAX_IT"
    # the capped implicit gradient is not the derivative of the 1-step map: rate 1
    assert 0.8 <= cg["taylor_rate"] <= 1.2


def test_k_equals_one_cg_is_one_exact_step():
    A, b, theta = stability._lshape_poisson(True)
    M = A.matrix(theta)
    solver = pp.KSPSolver("-ksp_type cg -pc_type none", max_it=1)
    solver.set_operator(M)
    x = solver.solve(b).value
    alpha = (b @ b) / (b @ (M @ b))
    np.testing.assert_allclose(x, alpha * b, rtol=1e-13)


def test_k_far_beyond_convergence_does_not_raise(rows):
    far = [r for r in rows["iterations"] if r["case"] == "K far beyond"]
    assert len(far) == 5
    for row in far:
        _ok(row)
        assert row["residual"] <= 1e-12
        assert row["taylor_rate"] >= 1.9
    # GMRES and BiCGStab do break down at rounding level: accepted, reason kept
    assert {r["reason"] for r in far} >= {"DIVERGED_BREAKDOWN"}


def test_bicgstab_divergence_after_convergence_returns_the_best_iterate():
    """High contrast + BiCGStab run far beyond convergence diverges (DTOL) late.

    The library re-runs to the iteration of the smallest residual.
    """
    from prdp_petsc.fem.meshes import load_mesh

    mesh = load_mesh("lshape")
    A, b, _ = poisson_problem(mesh)
    cx, cy = stability.centroids(mesh)
    theta = np.where((cx < 0.3) & (cy < 0.3), 1e8, 1.0)
    M = A.matrix(theta)
    x_ref = spl.spsolve(M.tocsc(), b)
    for options in ("-ksp_type cg -pc_type icc", "-ksp_type bcgs -pc_type jacobi"):
        solver = pp.KSPSolver(options, max_it=5000)
        solver.set_operator(M)
        sol = solver.solve(b)
        assert np.linalg.norm(sol.value - x_ref) <= 1e-8 * np.linalg.norm(x_ref), options
        assert sol.iterations < 5000


def test_cg_drifting_far_beyond_convergence_is_caught():
    """CG+ICC run 20000 iterations past convergence ended (on PETSc 3.26) at the cap with
    a relative error of 2e-4 and no divergence reason; the library re-runs to the first
    iteration far beyond rounding level and returns that iterate."""
    A, b, theta = stability._lshape_poisson(False)
    h = theta * np.random.default_rng(0).uniform(-1.0, 1.0, theta.size)
    M = A.matrix(theta - 1e-8 * h)
    solver = pp.KSPSolver("-ksp_type cg -pc_type icc", max_it=20_000)
    solver.set_operator(M)
    x = solver.solve(b).value
    x_ref = spl.spsolve(M.tocsc(), b)
    assert np.linalg.norm(x - x_ref) <= 1e-12 * np.linalg.norm(x_ref)


def test_rerun_target_prefers_first_iteration_far_beyond():
    h = np.array([1.0, 1e-3, 1e-10, 1e-21, 1e-30, 1e-5, 1e3])
    assert safeguards._rerun_target(h, 6) == 3
    assert safeguards._rerun_target(np.array([1.0, 1e-3, 1e-8, 1e2]), 3) == 2
    assert safeguards._rerun_target(np.array([1.0, 2.0, 4.0]), 2) is None


def test_real_breakdowns_raise(rows):
    skew, indefinite = [r for r in rows["no_transpose"] if r["case"] == "breakdown"]
    assert skew["outcome"] == "SolverError: DIVERGED_BREAKDOWN"
    assert indefinite["outcome"] == "SolverError: DIVERGED_INDEFINITE_MAT"


# -- extreme right-hand sides -----------------------------------------------------------------
def test_rhs_magnitudes(rows):
    mag = rows["magnitude"]
    assert {r["setting"] for r in mag} == {"‖b‖ ~ 1e-150", "‖b‖ ~ 1e+150", "‖b‖ ~ 1e-300"}
    for row in mag:
        _ok(row)
        assert row["residual"] <= 1e-10
        assert row["taylor_rate"] >= 1.9
    # a relative tolerance makes the count independent of ‖b‖: the rescaling by a power
    # of two is exact, and CG and GMRES need the same count at every magnitude; the
    # mantissa of ‖b‖ still moves BiCGStab a little (91-93 here, 196-201 full size)
    its = {
        s: [r["iterations"] for r in mag if r["solver"] == s] for s in {r["solver"] for r in mag}
    }
    assert len(set(its["cg/jacobi"])) == len(set(its["gmres/ilu"])) == 1
    assert max(its["bcgs/jacobi"]) <= 1.05 * min(its["bcgs/jacobi"])


def test_power_of_two_scaling_is_exact():
    A, b, theta = stability._lshape_poisson(True)
    M = A.matrix(theta)
    for options in ("-ksp_type bcgs -pc_type jacobi", "-ksp_type cg -pc_type none"):
        solver = pp.KSPSolver(options, max_it=40)
        solver.set_operator(M)
        x = solver.solve(b).value
        for e in (-500, 500):
            sol = solver.solve(np.ldexp(b, e))
            np.testing.assert_array_equal(np.ldexp(sol.value, -e), x)
            assert sol.iterations == 40


def test_rhs_exponents_batch_matches_rows():
    batch = np.array([[1e-3, 2.0], [0.0, 0.0], [3e-150, -1e-160], [-7e200, 1.0]])
    assert list(safeguards.rhs_exponents(batch)) == [safeguards.rhs_exponent(r) for r in batch]


def test_rhs_exponent():
    assert safeguards.rhs_exponent(np.array([1e-3, 2.0])) == 0
    assert safeguards.rhs_exponent(np.zeros(3)) == 0
    e = safeguards.rhs_exponent(np.array([3e-150, -1e-160]))
    assert 0.5 <= 3e-150 * 2.0**-e < 1.0
    e = safeguards.rhs_exponent(np.array([-7e200]))
    assert 0.5 <= 7e200 * 2.0**-e < 1.0


# -- transposes: clear errors, never a silent wrong gradient -----------------------------------
def test_pc_without_transpose_is_a_clear_error(rows):
    sor, explicit, cgls = rows["no_transpose"][:3]
    assert sor["outcome"] == "SolverError: NO_TRANSPOSE"
    assert "ksp_use_explicittranspose" in sor["message"]
    assert cgls["outcome"] == "SolverError: NO_TRANSPOSE"
    _ok(explicit)
    assert explicit["taylor_rate"] >= 1.9


def test_explicit_transpose_gradient_matches_direct_and_keeps_forward_pc():
    p = problems.advection(refine=0)
    M = p.matrix()
    solver = pp.KSPSolver(
        "-ksp_type gmres -pc_type sor",
        max_it=500,
        rtol=1e-12,
        adjoint=pp.AdjointSettings(options={"ksp_use_explicittranspose": True}),
    )
    solver.set_operator(M)
    assert solver.adjoint_ksp.getPC().handle != solver.ksp.getPC().handle
    x0 = solver.solve(p.b).value
    lam = solver.solve_transpose(p.loss_grad(x0)).value
    x1 = solver.solve(p.b).value  # the forward PC must still be SOR of A, not of Aᵀ
    np.testing.assert_array_equal(x0, x1)
    _, lam_ref, g_ref = problems.direct_gradient(p)
    assert np.linalg.norm(lam - lam_ref) <= 1e-9 * np.linalg.norm(lam_ref)
    g = p.A.theta_gradient(lam, x0)
    assert np.linalg.norm(g - g_ref) <= 1e-9 * np.linalg.norm(g_ref)


def test_cgls_adjoint_is_refused_before_solving():
    p = problems.advection(refine=0)
    solver = pp.KSPSolver("-ksp_type gmres", max_it=5, adjoint={"options": {"ksp_type": "cgls"}})
    solver.set_operator(p.matrix())
    with pytest.raises(pp.SolverError) as err:
        solver.solve_transpose(p.b)
    assert err.value.reason == "NO_TRANSPOSE"
    assert solver.stats.adjoint_solves == 0


# -- the command ---------------------------------------------------------------------------------
def test_stability_main_writes_table(tmp_path):
    assert (
        stability.main(["--out", str(tmp_path), "--preset", "quick", "--cases", "magnitude"]) == 0
    )
    data = json.loads((tmp_path / "stability.json").read_text())
    assert len(data["rows"]) == 9
    assert all(r["outcome"] == "ok" and r["taylor_rate"] >= 1.9 for r in data["rows"])
    table = (tmp_path / "stability.md").read_text()
    assert table.count("\n") == 2 + 9 and "1e-150" in table


def test_taylor_rate_detects_a_wrong_gradient():
    def J(t):
        return float(np.sum(np.sin(t)))

    t = np.linspace(0.1, 1.0, 5)
    h = np.ones(5)
    right, info = stability.taylor_rate(J, t, np.cos(t), h)
    wrong, _ = stability.taylor_rate(J, t, 1.2 * np.cos(t), h)
    assert right >= 1.9 and 0.8 <= wrong <= 1.2
    assert len(info["eps"]) == 5 and info["noise"] < 1e-14


def test_high_contrast_is_not_taken_for_singular():
    """Contrast 1e10: the solution is a null vector of A to 5e-13 (legitimately), but its
    residual is at rounding level; converged and capped solves both come back."""
    from prdp_petsc.fem.meshes import load_mesh
    from prdp_petsc.lab.reports import stability

    mesh = load_mesh("lshape")
    A, b, _ = poisson_problem(mesh)
    cx, cy = stability.centroids(mesh)
    M = A.matrix(np.where((cx < 0.3) & (cy < 0.3), 1e10, 1.0))
    expected = spl.spsolve(M.tocsc(), b)
    for max_it, rtol in ((5000, 1e-12), (30, 0.0)):
        with pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, max_it=max_it, rtol=rtol) as s:
            s.set_operator(M)
            x = s.solve(b).value
        if rtol:
            assert np.linalg.norm(x - expected) <= 1e-6 * np.linalg.norm(expected)
