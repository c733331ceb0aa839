"""KSPSolver: capped iterations, PC reuse, options, adjoint settings, stats, transposes.

The forward and transpose solves are checked against scipy's direct solver and
against each other (dot-product test); the torch-unrolled iteration against PETSc's
own, iterate for iterate.
"""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch
from _core import (
    CONVERGED,
    fd_poisson,
    interior_operator,
    randn,
    random_theta,
    unit_square,
)
from petsc4py import PETSc

import prdp_petsc as pp
from prdp_petsc.core.results import SolveInfo, SolverStats


def nonsymmetric():
    """Advection–diffusion ``A_II`` on the unit square as a scipy CSR matrix."""
    A = interior_operator(unit_square(3), advect=True).A_II
    return A.matrix(random_theta(A.n_params, seed=1).numpy())


def rng_vec(n, seed):
    return np.random.default_rng(seed).standard_normal(n)


@pytest.fixture(scope="module")
def pc_setups():
    """Number of ``PCSetUp`` calls so far (PETSc logging is switched on once)."""
    PETSc.Log.begin()
    event = PETSc.Log.Event("PCSetUp")
    return lambda: event.getPerfInfo()["count"]


# -- capped iterations ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "options",
    [
        {"ksp_type": "richardson", "pc_type": "jacobi"},
        {"ksp_type": "cg", "pc_type": "jacobi"},
        {"ksp_type": "gmres", "pc_type": "none"},  # K = 40 crosses the restart at 30
    ],
    ids=lambda o: o["ksp_type"],
)
@pytest.mark.parametrize("K", [1, 3, 7, 40])
def test_fixed_mode_runs_exactly_K_iterations(options, K):
    solver = pp.KSPSolver(options, max_it=K)
    solver.set_operator(fd_poisson(10))
    sol = solver.solve(rng_vec(100, 0))
    assert sol.iterations == K
    assert sol.reason == "DIVERGED_MAX_IT" and not sol.converged
    assert solver.solve_transpose(rng_vec(100, 1)).iterations == K
    assert solver.stats.forward_iterations == K and solver.stats.adjoint_iterations == K


def test_max_it_is_a_runtime_knob_and_pc_is_reused(pc_setups):
    D = interior_operator(unit_square(3))
    A = D.A_II
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, max_it=3)
    theta = random_theta(A.n_params)
    b = randn(A.shape[0], seed=2, requires_grad=True)
    c0 = pc_setups()
    pp.solve(A, b, solver, theta=theta)
    assert pc_setups() == c0 + 1
    pp.solve(A, b, solver, theta=theta)  # same θ: nothing to set up
    assert pc_setups() == c0 + 1
    for K in (5, 2, 9):
        solver.max_it = K
        sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
        assert sol.iterations == K
    assert pc_setups() == c0 + 1  # a new cap is not a new operator
    sol.value.sum().backward()  # the adjoint shares the forward PC
    assert sol.adjoint[0].iterations == 9 and pc_setups() == c0 + 1
    pp.solve(A, b, solver, theta=2.0 * theta)  # new values: one new setup
    assert pc_setups() == c0 + 2
    pp.solve(A, randn(5, A.shape[0], seed=3), solver, theta=3.0 * theta)  # batch: one setup
    assert pc_setups() == c0 + 3
    assert solver.stats.operator_updates == 3


def test_adjoint_with_own_pc_sets_up_its_own(pc_setups):
    D = interior_operator(unit_square(3))
    A = D.A_II
    adjoint = pp.AdjointSettings(options={"pc_type": "jacobi"})
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, max_it=4, adjoint=adjoint)
    theta = random_theta(A.n_params)
    c0 = pc_setups()
    for _ in range(2):
        b = randn(A.shape[0], seed=4, requires_grad=True)
        pp.solve(A, b, solver, theta=theta).sum().backward()
    assert pc_setups() == c0 + 2  # one forward, one adjoint, then both reused
    assert solver.ksp.getPC().getType() == "icc"
    assert solver.adjoint_ksp.getPC().getType() == "jacobi"
    assert solver.adjoint_ksp.getPC().handle != solver.ksp.getPC().handle


# -- options ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "options",
    [{"ksp_type": "bcgs", "pc_type": "sor"}, "-ksp_type bcgs -pc_type sor"],
    ids=["dict", "string"],
)
def test_options_set_ksp_and_pc_type_under_prefix(options):
    solver = pp.KSPSolver(options, prefix="opt_", max_it=5)
    solver.set_operator(fd_poisson(4))
    assert solver.ksp.getOptionsPrefix() == "opt_"
    assert solver.adjoint_ksp.getOptionsPrefix() == "opt_adj_"
    assert solver.ksp.getType() == "bcgs" and solver.ksp.getPC().getType() == "sor"
    assert solver.adjoint_ksp.getType() == "bcgs"  # the adjoint defaults to the forward
    assert solver.adjoint_ksp.getPC().handle == solver.ksp.getPC().handle  # shared PC
    assert not PETSc.Options().hasName("opt_ksp_type")  # nothing left in the database
    rtol, atol, _, max_it = solver.ksp.getTolerances()
    assert (rtol, atol, max_it) == (0.0, 0.0, 5)


def test_command_line_options_override_the_dict(petsc_option):
    petsc_option("tst_ksp_type", "gmres")
    petsc_option("tst_adj_pc_type", "jacobi")
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, prefix="tst_", max_it=5)
    solver.set_operator(fd_poisson(4))
    assert solver.ksp.getType() == "gmres"  # -tst_ksp_type gmres wins over the dict
    assert solver.ksp.getPC().getType() == "icc"
    assert solver.adjoint_ksp.getType() == "gmres"  # inherits the forward, as configured
    assert solver.adjoint_ksp.getPC().getType() == "jacobi"
    assert PETSc.Options().getString("tst_ksp_type") == "gmres"  # left as the user set it


def test_adjoint_settings_apply_to_the_adjoint_only():
    adjoint = pp.AdjointSettings(options={"ksp_type": "gmres"}, max_it=3, rtol=1e-8)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=10, adjoint=adjoint)
    solver.set_operator(fd_poisson(6))
    assert solver.ksp.getType() == "cg" and solver.adjoint_ksp.getType() == "gmres"
    assert solver.adjoint_ksp.getPC().handle == solver.ksp.getPC().handle  # no pc_*: shared
    assert solver.ksp.getTolerances()[::3] == (0.0, 10)
    assert solver.adjoint_ksp.getTolerances()[::3] == (1e-8, 3)
    solver.max_it = 20  # the adjoint keeps its own cap
    assert solver.adjoint_ksp.getTolerances()[3] == 3
    solver.adjoint_max_it = None  # ... until it follows the forward one again
    assert solver.adjoint_ksp.getTolerances()[3] == 20 == solver.adjoint_max_it
    solver.solve(rng_vec(36, 5))
    solver.solve_transpose(rng_vec(36, 6))
    assert solver.stats.forward_iterations == 20


def test_adjoint_follows_forward_max_it_by_default():
    solver = pp.KSPSolver({"ksp_type": "cg"}, max_it=4)
    solver.set_operator(fd_poisson(6))
    solver.max_it = 6
    assert solver.solve_transpose(rng_vec(36, 7)).iterations == 6 == solver.adjoint_max_it


def test_tolerance_options_must_be_keywords():
    with pytest.raises(ValueError, match="keyword"):
        pp.KSPSolver({"ksp_max_it": 5}, max_it=5)


# -- stats ------------------------------------------------------------------------------------


def test_stats_the_result_and_reset():
    D = interior_operator(unit_square(3))
    A = D.A_II
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=4)
    theta = random_theta(A.n_params, requires_grad=True)
    b = randn(3, A.shape[0], seed=8)
    sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
    sol.value.sum().backward()
    s = solver.stats
    assert (s.forward_solves, s.forward_iterations) == (3, 12)
    assert (s.adjoint_solves, s.adjoint_iterations) == (3, 12)
    assert s.operator_updates == 1 and s.forward_time > 0 and s.adjoint_time > 0
    last = sol.info[-1]
    assert isinstance(last, SolveInfo)
    assert last.iterations == 4 and last.reason == "DIVERGED_MAX_IT" and last.residual_norm > 0
    assert set(s.as_dict()) >= {"forward_solves", "adjoint_iterations", "operator_updates"}
    solver.reset_stats()
    assert solver.stats == SolverStats()
    solver.max_it = 500
    solver.rtol = 1e-10
    sol = pp.solve(A, b[0], solver, theta=theta.detach(), return_solution=True)
    assert sol.converged and sol.reason == "CONVERGED_RTOL"
    assert solver.stats.forward_iterations == sol.iterations < 500
    assert solver.stats.adjoint_solves == 0


# -- correctness against scipy, dot-product tests ---------------------------------------------


@pytest.mark.parametrize(
    ("matrix", "options"),
    [
        ("symmetric", {"ksp_type": "cg", "pc_type": "icc"}),
        ("symmetric", {"ksp_type": "cg", "pc_type": "gamg"}),
        ("nonsymmetric", {"ksp_type": "gmres", "pc_type": "ilu"}),
        ("nonsymmetric", {"ksp_type": "bcgs", "pc_type": "jacobi"}),
    ],
)
def test_converged_solves_match_spsolve(matrix, options):
    M = fd_poisson(12) if matrix == "symmetric" else nonsymmetric()
    n = M.shape[0]
    solver = pp.KSPSolver(options, **CONVERGED)
    solver.set_operator(M)
    B = np.stack([rng_vec(n, 9), rng_vec(n, 10)])
    x = solver.solve(B)
    assert x.converged
    y = solver.solve_transpose(B)
    assert y.converged
    x, y = x.value, y.value
    for k in range(2):
        exact = spla.spsolve(M.tocsc(), B[k])
        exact_t = spla.spsolve(M.T.tocsc(), B[k])
        np.testing.assert_allclose(x[k], exact, rtol=0, atol=1e-9 * np.abs(exact).max())
        np.testing.assert_allclose(y[k], exact_t, rtol=0, atol=1e-9 * np.abs(exact_t).max())


@pytest.mark.parametrize("K", [1, 4, 15])
def test_dot_product_stationary_transpose_is_exact_adjoint(K):
    """Richardson+Jacobi with K steps is a linear map; K transposed steps are its adjoint."""
    M = nonsymmetric()
    n = M.shape[0]
    options = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.7}
    solver = pp.KSPSolver(options, max_it=K)
    solver.set_operator(M)
    u, v = rng_vec(n, 11), rng_vec(n, 12)
    lhs = solver.solve(u).value @ v
    rhs = u @ solver.solve_transpose(v).value
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)


@pytest.mark.parametrize(
    ("matrix", "options"),
    [
        ("symmetric", {"ksp_type": "cg", "pc_type": "icc"}),
        ("nonsymmetric", {"ksp_type": "gmres", "pc_type": "ilu"}),
    ],
)
def test_dot_product_converged(matrix, options):
    M = fd_poisson(12) if matrix == "symmetric" else nonsymmetric()
    n = M.shape[0]
    solver = pp.KSPSolver(options, **CONVERGED)
    solver.set_operator(M)
    u, v = rng_vec(n, 13), rng_vec(n, 14)
    x, y = solver.solve(u).value, solver.solve_transpose(v).value
    assert abs(x @ v - u @ y) <= 1e-10 * abs(x @ v)
    assert abs((M @ x) @ y - x @ (M.T @ y)) <= 1e-12 * np.linalg.norm(M @ x) * np.linalg.norm(y)
    np.testing.assert_allclose(M @ x, u, atol=1e-10 * np.abs(u).max())


def test_dot_product_fails_for_truncated_krylov():
    """Control: a truncated CG is not linear in b, so its 'transpose' is no adjoint."""
    M = fd_poisson(12)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=3)
    solver.set_operator(M)
    u, v = rng_vec(144, 15), rng_vec(144, 16)
    lhs, rhs = solver.solve(u).value @ v, u @ solver.solve_transpose(v).value
    assert abs(lhs - rhs) > 1e-3 * abs(lhs)


def test_operator_values_changed_in_place_are_used():
    """Regression: set_operator compared values by identity, so in-place edits were ignored."""
    M = fd_poisson(6)
    solver = pp.KSPSolver({"ksp_type": "preonly", "pc_type": "lu"}, max_it=1)
    b = rng_vec(36, 17)
    solver.set_operator(M)
    x1 = solver.solve(b).value
    M.data *= 2.0
    solver.set_operator(M)
    np.testing.assert_allclose(solver.solve(b).value, x1 / 2.0, rtol=1e-12)


def test_petsc_mat_operator():
    M = nonsymmetric()
    mat = PETSc.Mat().createAIJ(size=M.shape, csr=(M.indptr, M.indices, M.data))
    mat.assemble()
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "ilu"}, **CONVERGED)
    solver.set_operator(mat)
    b = rng_vec(M.shape[0], 18)
    np.testing.assert_allclose(solver.solve(b).value, spla.spsolve(M.tocsc(), b), rtol=1e-9)
    assert solver.mat.handle == mat.handle


# -- the unrolled iteration is PETSc's --------------------------------------------------------


@pytest.mark.parametrize(
    "options",
    [
        {"ksp_type": "cg", "pc_type": "jacobi"},
        {"ksp_type": "cg", "pc_type": "none"},
        {"ksp_type": "cg", "pc_type": "jacobi", "ksp_norm_type": "unpreconditioned"},
        {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.8},
        {"ksp_type": "richardson", "pc_type": "none", "ksp_richardson_scale": 0.004},
    ],
    ids=["cg-jacobi", "cg-none", "cg-unprec-norm", "richardson-jacobi", "richardson-none"],
)
@pytest.mark.parametrize(("K", "rtol"), [(1, 0.0), (5, 0.0), (30, 0.0), (1000, 1e-5)])
def test_unrolled_forward_equals_petsc(options, K, rtol):
    """Same iterates, same iteration count, same stopping reason (also when rtol stops it)."""
    M = fd_poisson(6)
    b = randn(3, 36, seed=19)
    solver = pp.KSPSolver(options, max_it=K, rtol=rtol)
    petsc = pp.solve(M, b, solver, return_solution=True)
    petsc_its = solver.stats.forward_iterations
    torch_ = pp.solve(M, b, solver, mode="unrolled", return_solution=True)
    assert torch_.iterations.tolist() == petsc.iterations.tolist()
    assert torch_.reason == petsc.reason
    assert solver.stats.forward_iterations == 2 * petsc_its
    np.testing.assert_allclose(torch_.residual_norm, petsc.residual_norm, rtol=1e-6, atol=1e-12)
    x_torch, x_petsc = torch_.value.detach().numpy(), petsc.value.numpy()
    np.testing.assert_allclose(x_torch, x_petsc, rtol=0, atol=1e-10 * np.abs(x_petsc).max())
    if rtol:
        assert petsc.reason == ["CONVERGED_RTOL"] * 3 and petsc.iterations.max() < K


def test_unrolled_stops_when_converged_and_keeps_gradients_finite():
    """Regression: the unrolled CG ran all K steps past convergence and gave NaN gradients."""
    D = interior_operator(unit_square(2))
    A = D.A_II
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=200, rtol=1e-13)
    theta = random_theta(A.n_params, requires_grad=True)
    b = randn(A.shape[0], seed=20, requires_grad=True)
    sol = pp.solve(A, b, solver, theta=theta, mode="unrolled", return_solution=True)
    assert sol.converged and sol.iterations < 20
    sol.value.pow(2).sum().backward()
    assert torch.isfinite(theta.grad).all() and torch.isfinite(b.grad).all()


def test_unrolled_advection_matrix_iterates():
    """Richardson on a non-symmetric matrix: the torch loop matches PETSc as well."""
    M = nonsymmetric()
    options = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.7}
    solver = pp.KSPSolver(options, max_it=12)
    b = randn(M.shape[0], seed=21)
    x1 = pp.solve(M, b, solver)
    x2 = pp.solve(M, b, solver, mode="unrolled")
    torch.testing.assert_close(x1, x2, rtol=1e-12, atol=1e-14)


# -- symmetric operators: the adjoint as a forward solve -------------------------------


def _grad_b(A, solver, seed=7):
    b = randn(A.shape[0], seed=seed, requires_grad=True)
    w = randn(A.shape[0], seed=seed + 1)
    (pp.solve(A, b, solver) * w).sum().backward()
    return b.grad


@pytest.mark.parametrize(
    "options, symmetric_pc",
    [
        ({"ksp_type": "cg", "pc_type": "jacobi"}, None),
        ({"ksp_type": "cg", "pc_type": "icc"}, None),
        ({"ksp_type": "gmres", "pc_type": "none"}, None),
        ({"ksp_type": "cg", "pc_type": "gamg"}, True),
    ],
)
def test_symmetric_adjoint_as_forward_solve_matches_transpose_solve(options, symmetric_pc):
    """Capped (K = 4) gradients agree with KSPSolveTranspose; symmetry is detected."""
    A = fd_poisson(8)
    fast = pp.KSPSolver(options, max_it=4, adjoint=pp.AdjointSettings(symmetric_pc=symmetric_pc))
    slow = pp.KSPSolver(options, max_it=4, adjoint=pp.AdjointSettings(symmetric_pc=False))
    g_fast, g_slow = _grad_b(A, fast), _grad_b(A, slow)
    assert fast.is_symmetric and fast._adjoint_is_forward() and not slow._adjoint_is_forward()
    assert torch.allclose(g_fast, g_slow, rtol=1e-10, atol=1e-13)
    assert fast.stats.adjoint_iterations == slow.stats.adjoint_iterations == 4


def test_nonsymmetric_operator_keeps_the_transpose_solve():
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "jacobi"}, max_it=50, rtol=1e-12)
    A = nonsymmetric()
    g = _grad_b(A, solver)
    assert not solver.is_symmetric and not solver._adjoint_is_forward()
    w = randn(A.shape[0], seed=8).numpy()
    assert np.allclose(g.numpy(), spla.spsolve(A.T.tocsc(), w), rtol=1e-8, atol=1e-10)


def test_symmetry_is_rechecked_when_values_change():
    A = fd_poisson(4)
    solver = pp.KSPSolver({"ksp_type": "gmres"}, max_it=3)
    solver.set_operator(A)
    assert solver.is_symmetric
    B = A.copy()
    B.data[1] += 0.25  # same pattern, values no longer symmetric
    solver.set_operator(B)
    assert not solver.is_symmetric
    known, flag = solver.mat.isSymmetricKnown()
    assert known and not flag


def test_sor_adjoint_works_for_symmetric_operators():
    """PETSc applies SOR's transpose once the matrix is marked symmetric."""
    A = fd_poisson(5)
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "sor"}, max_it=200, rtol=1e-12)
    g = _grad_b(A, solver)
    w = randn(A.shape[0], seed=8).numpy()
    assert np.allclose(g.numpy(), spla.spsolve(A.tocsc(), w), rtol=1e-8, atol=1e-10)


def test_options_read_at_pc_setup_reach_the_pc():
    """GAMG reads its level-smoother options at PCSetUp, after KSPSetFromOptions."""
    solver = pp.KSPSolver(
        "-ksp_type cg -pc_type gamg -mg_levels_ksp_type richardson -mg_levels_pc_type sor",
        prefix="lvl_",
        max_it=5,
    )
    pp.solve(fd_poisson(20), randn(400, seed=1), solver)
    smoother = solver.ksp.getPC().getMGSmoother(1)
    assert (smoother.getType(), smoother.getPC().getType()) == ("richardson", "sor")
    assert not PETSc.Options().hasName("lvl_mg_levels_pc_type")  # nothing leaks


def test_rounding_level_asymmetry_counts_as_symmetric():
    A = fd_poisson(4).tocsr()
    B = A.copy()
    B.data[1] *= 1 + 1e-16 * 4  # a last-bit difference, as assembly order produces
    solver = pp.KSPSolver({"ksp_type": "cg"}, max_it=3)
    solver.set_operator(B)
    assert solver.is_symmetric


def test_command_line_forward_options_reach_the_inheriting_adjoint():
    opts = PETSc.Options()
    opts.setValue("inh_ksp_type", "cg")
    opts.setValue("inh_adj_pc_type", "none")
    try:
        solver = pp.KSPSolver(
            {"ksp_type": "richardson", "pc_type": "jacobi"}, prefix="inh_", max_it=3
        )
        solver.rebuild_on()
        assert solver.ksp.getType() == solver.adjoint_ksp.getType() == "cg"
        assert solver.ksp.getPC().getType() == "jacobi"
        assert solver.adjoint_ksp.getPC().getType() == "none"  # its own option wins
    finally:
        opts.delValue("inh_ksp_type")
        opts.delValue("inh_adj_pc_type")


def test_user_mat_edited_in_place_is_not_taken_as_symmetric():
    M = PETSc.Mat().createAIJ(size=(3, 3), nnz=3, comm=PETSc.COMM_SELF)
    for i in range(3):
        for j in range(3):
            M.setValue(i, j, 4.0 if i == j else 1.0)
    M.assemble()
    M.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "none"}, max_it=10, rtol=1e-14)
    solver.set_operator(M)
    M.setValue(0, 1, 2.0)  # no longer symmetric; PETSc drops the flag
    M.assemble()
    M.setOption(PETSc.Mat.Option.SYMMETRIC, False)
    solver.set_operator(M)
    g = np.array([1.0, 2.0, 3.0])
    dense = np.full((3, 3), 1.0) + 3.0 * np.eye(3)
    dense[0, 1] = 2.0
    lam = solver.solve_transpose(g).value
    assert np.allclose(lam, np.linalg.solve(dense.T, g), atol=1e-12)


def test_clone_copies_every_setting():
    solver = pp.KSPSolver(
        "-ksp_type cg",
        prefix="cl_",
        max_it=7,
        rtol=1e-3,
        divtol=1e3,
        structure=pp.Structure(nullspace="constant"),
        adjoint=pp.AdjointSettings(max_it=2),
    )
    copy = solver.clone(max_it=50)
    assert (copy.prefix, copy.max_it, copy.rtol, copy.divtol, copy.structure.nullspace) == (
        "cl_",
        50,
        1e-3,
        1e3,
        "constant",
    )
    assert copy.options == solver.options and copy.adjoint_max_it == 2
    copy.adjoint_max_it = 9
    assert solver.adjoint_max_it == 2  # settings objects are not shared


@pytest.mark.parametrize(
    "name, value",
    [
        ("symmetric", True),
        ("nullspace", "constant"),
        ("transpose_nullspace", "constant"),
        ("near_nullspace", "constant"),
        ("block_size", 2),
        ("fields", {"u": np.arange(2)}),
    ],
)
def test_structure_is_declared_once_and_the_old_keywords_are_refused(name, value):
    """`structure=pp.Structure(...)` is the one spelling: the keywords of 0.1's shims
    (``nullspace=`` and the other five) are refused by the solver and by `clone`."""
    with pytest.raises(TypeError, match=f"unexpected keyword argument '{name}'"):
        pp.KSPSolver(max_it=5, **{name: value})
    with pp.KSPSolver(max_it=5, structure=pp.Structure(nullspace="constant")) as s:
        declared = s.structure
        assert declared.nullspace == declared.transpose_nullspace == "constant"
        assert declared.block_size == 1
        copy = s.clone(max_it=3)
        assert copy.structure is s.structure
        copy.destroy()
        with pytest.raises(TypeError, match=f"unexpected keyword argument '{name}'"):
            s.clone(**{name: value})


def test_structure_must_be_a_structure_and_the_shims_are_gone():
    with pytest.raises(TypeError, match="pp.Structure"):
        pp.KSPSolver(max_it=5, structure={"nullspace": "constant"})
    with pp.KSPSolver(max_it=5) as s:
        assert not hasattr(s, "setup") and not hasattr(s, "set_tolerances")
        assert not hasattr(s, "symmetric")  # the outcome is is_symmetric
        # the declaration is read from `structure` only: no mirrors on the solver
        for name in (
            "declared_symmetric",
            "nullspace",
            "transpose_nullspace",
            "near_nullspace",
            "block_size",
            "fields",
        ):
            assert not hasattr(s, name), name


def test_clone_with_another_structure_takes_it_whole():
    v = np.ones(8) / np.sqrt(8.0)
    with pp.KSPSolver(max_it=5, structure=pp.Structure(nullspace="constant")) as s:
        copy = s.clone(structure=pp.Structure(nullspace=v[None, :]))
        declared = copy.structure
        assert declared.transpose_nullspace is declared.nullspace
        assert declared.nullspace.shape == (1, 8)
        copy.destroy()


def test_structure_refuses_impossible_declarations():
    with pytest.raises(pp.InputError, match="symmetric must be"):
        pp.Structure(symmetric=1)
    with pytest.raises(pp.InputError, match="transpose_nullspace without nullspace"):
        pp.Structure(transpose_nullspace="constant")
