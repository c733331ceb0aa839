"""KSPSolver defects found by trying it as a new user: symmetry, lifecycle, options.

Each test here failed on the code before the fix it names.
"""

import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
from _core import BETA, fd_poisson, randn, unit_square
from petsc4py import PETSc
from skfem import BilinearForm
from skfem.helpers import dot, grad

import prdp_petsc as pp
from prdp_petsc.core.solver import UnusedOptionWarning

CG_JACOBI = {"ksp_type": "cg", "pc_type": "jacobi"}


def penalized_advection_diffusion(epsilon=None, beta: float = 1.0) -> sp.csr_matrix:
    """``−Δu + β·∇u`` with Dirichlet rows penalised by ``1/ε`` (skfem.penalize's default
    ε when None)."""
    basis = unit_square(3)

    @BilinearForm
    def form(u, v, w):
        return dot(grad(u), grad(v)) + beta * (BETA[0] * u.grad[0] + BETA[1] * u.grad[1]) * v

    A = form.assemble(basis)
    kw = {} if epsilon is None else {"epsilon": epsilon}
    A, _ = skfem.penalize(A, np.zeros(A.shape[0]), D=basis.get_dofs(), **kw)
    return A.tocsr()


# -- B1: symmetry judged entry against mirror ------------------------------------------


@pytest.mark.parametrize(("epsilon", "beta"), [(1e-20, 1.0), (None, 1e-5)])
def test_large_penalty_does_not_hide_an_asymmetry(epsilon, beta):
    """A 1/ε diagonal used to set the scale of the symmetry test: wrong ∂L/∂b."""
    A = penalized_advection_diffusion(epsilon, beta)
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "jacobi"}, max_it=2000, rtol=1e-13)
    b = randn(A.shape[0], seed=1, requires_grad=True)
    w = randn(A.shape[0], seed=2)
    pp.solve(A, b, solver).backward(w)
    assert not solver.is_symmetric
    exact = spla.spsolve(A.T.tocsc(), w.numpy())
    assert np.linalg.norm(b.grad.numpy() - exact) <= 1e-8 * np.linalg.norm(exact)


def test_parametric_symmetry_is_tested_entry_against_mirror():
    basis = unit_square(2)
    K = pp.diffusion_operator(basis, "P0")
    assert K.is_symmetric
    n = K.shape[0]
    big = sp.diags(np.r_[1e20, np.ones(n - 1)]).tocsr()
    skew = sp.csr_matrix(([1.0, -1.0], ([1, 2], [2, 1])), shape=(n, n))
    assert (K + big).is_symmetric
    assert not (K + big + skew).is_symmetric  # the 1e20 entry used to hide ±1


def test_declared_structure_wins_over_the_test():
    A = penalized_advection_diffusion(1e-20)
    solver = pp.KSPSolver(CG_JACOBI, max_it=3, structure=pp.Structure(symmetric=False))
    solver.set_operator(fd_poisson(4))
    assert not solver.is_symmetric  # declared: no test, KSPSolveTranspose for the adjoint
    solver = pp.KSPSolver(CG_JACOBI, max_it=3)
    solver.set_operator(A, known_symmetric=True)
    assert solver.is_symmetric
    K = pp.diffusion_operator(unit_square(1), "P0")
    declared = pp.ParametricMatrix(K.indptr, K.indices, K.shape, K.a0, K.G, symmetric=False)
    assert K.is_symmetric and not declared.is_symmetric


# -- B3: lifecycle ---------------------------------------------------------------------


def test_bad_option_value_fails_at_construction_naming_it():
    with pytest.raises(ValueError, match="-pc_type no_such_pc: not a PETSc PC type"):
        pp.KSPSolver({"ksp_type": "cg", "pc_type": "no_such_pc"}, max_it=3)
    with pytest.raises(ValueError, match="-tst_ksp_type nope: not a PETSc KSP type"):
        pp.KSPSolver("-ksp_type nope", prefix="tst_", max_it=3)
    solver = pp.KSPSolver(CG_JACOBI, max_it=3)  # the database is clean afterwards
    solver.set_operator(fd_poisson(3))
    assert solver.solve(np.ones(9)).value.shape == (9,)
    assert not PETSc.Options().hasName("pc_type")


def test_destroy_and_context_manager():
    with pp.KSPSolver(CG_JACOBI, max_it=3) as solver:
        solver.set_operator(fd_poisson(3))
        x = solver.solve(np.ones(9)).value
        mat = solver.mat
    assert np.all(np.isfinite(x))
    assert mat.handle == 0  # the Mat made by the solver was freed
    with pytest.raises(RuntimeError, match="destroyed"):
        solver.solve(np.ones(9))


def test_work_vectors_are_reused_between_solves():
    solver = pp.KSPSolver(CG_JACOBI, max_it=3)
    solver.set_operator(fd_poisson(3))
    solver.solve(np.ones(9))
    handles = (solver._x.handle, solver._b.handle)
    solver.solve(np.ones((4, 9)))
    solver.solve_transpose(np.ones(9))
    assert (solver._x.handle, solver._b.handle) == handles


# -- B4: options -----------------------------------------------------------------------


def test_misspelt_option_in_the_dict_is_reported():
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_typ": "gamg"}, max_it=3)
    solver.set_operator(fd_poisson(4))
    with pytest.warns(UnusedOptionWarning, match=r"never read .*-pc_typ"):
        solver.solve(np.ones(16))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.solve(np.ones(16))  # reported once; the solve itself is fine


def test_misspelt_option_on_the_command_line_is_reported(petsc_option):
    petsc_option("h2d_ksp_tpye", "gmres")
    solver = pp.KSPSolver(CG_JACOBI, prefix="h2d_", max_it=3)
    solver.set_operator(fd_poisson(4))
    with pytest.warns(UnusedOptionWarning, match="-h2d_ksp_tpye"):
        solver.solve(np.ones(16))


def test_options_read_only_at_pc_setup_or_solve_are_not_reported():
    solver = pp.KSPSolver(
        "-ksp_type cg -pc_type gamg -mg_levels_ksp_type richardson -ksp_converged_reason",
        prefix="rd_",
        max_it=3,
    )
    solver.set_operator(fd_poisson(8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.solve(np.ones(64))
        solver.solve_transpose(np.ones(64))


def test_adjoint_option_misspelt_is_reported_at_the_first_adjoint_solve():
    solver = pp.KSPSolver(CG_JACOBI, max_it=3, adjoint={"options": {"ksp_tyep": "gmres"}})
    solver.set_operator(fd_poisson(4))
    solver.solve(np.ones(16))
    with pytest.warns(UnusedOptionWarning, match="-adj_ksp_tyep"):
        solver.solve_transpose(np.ones(16))


@pytest.mark.parametrize("name", ["rtol", "atol"])
def test_tolerances_are_properties(name):
    solver = pp.KSPSolver(CG_JACOBI, max_it=500)
    solver.set_operator(fd_poisson(8))
    setattr(solver, name, 1e-3)
    rtol, atol, _, _ = solver.ksp.getTolerances()
    assert {"rtol": rtol, "atol": atol}[name] == 1e-3  # applied now, not at the next max_it
    assert solver.solve(np.ones(64)).converged
    with pytest.raises(ValueError, match=name):
        setattr(solver, name, -1.0)


@pytest.mark.parametrize("key", ["ksp_rtol", "ksp_max_it", "adj_ksp_max_it"])
def test_command_line_tolerances_are_refused(petsc_option, key):
    petsc_option("cl_" + key, "7")
    with pytest.raises(ValueError, match="PRDP schedule owns max_it"):
        pp.KSPSolver(CG_JACOBI, prefix="cl_", max_it=3)


def test_empty_prefix_does_not_copy_unrelated_options_to_the_adjoint(petsc_option):
    petsc_option("log_view_memory", None)
    petsc_option("ksp_type", "gmres")
    solver = pp.KSPSolver({"pc_type": "jacobi"}, max_it=3)
    names = [name for name, _ in solver.config.option_items()]
    assert "adj_ksp_type" in names  # KSP options are inherited by the adjoint
    assert "adj_log_view_memory" not in names
    assert solver.adjoint_ksp.getType() == "gmres"


def test_batch_solutions_with_reused_work_vectors_match_spsolve():
    A = fd_poisson(5)
    b = np.random.default_rng(0).standard_normal((3, 25))
    solver = pp.KSPSolver(CG_JACOBI, max_it=200, rtol=1e-12)
    solver.set_operator(A)
    x = solver.solve(b).value
    assert np.allclose(x, spla.spsolve(A.tocsc(), b.T).T, atol=1e-10)


# -- fast paths must not go stale (review findings) ------------------------------------


def test_options_reach_a_pc_set_up_again_for_a_new_pattern():
    """GAMG reads its level options when it gets a new Mat: they must be pushed then too."""
    solver = pp.KSPSolver(
        "-ksp_type cg -pc_type gamg -mg_levels_ksp_type richardson -mg_levels_pc_type sor",
        prefix="np_",
        max_it=3,
    )
    solver.set_operator(fd_poisson(12))
    solver.solve(np.ones(144))
    solver.solve(np.ones(144))  # a steady solve pushes nothing
    solver.set_operator(fd_poisson(14))  # a new pattern: a new Mat, GAMG set up again
    solver.solve(np.ones(196))
    smoother = solver.ksp.getPC().getMGSmoother(1)
    assert (smoother.getType(), smoother.getPC().getType()) == ("richardson", "sor")


def test_changed_symmetry_declaration_is_applied_for_unchanged_values():
    A = fd_poisson(4)
    solver = pp.KSPSolver(CG_JACOBI, max_it=3)
    solver.set_operator(A, known_symmetric=True)
    version = solver.operator_version
    solver.set_operator(A, known_symmetric=False)
    assert not solver.is_symmetric and solver.operator_version > version
    solver.set_operator(A)  # back to testing the values
    assert solver.is_symmetric


def test_read_only_view_of_a_changed_buffer_is_not_taken_as_unchanged():
    A = fd_poisson(4).tocsr()
    base = A.data.copy()
    view = base[:]
    view.flags.writeable = False
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "none"}, max_it=200, rtol=1e-12)
    csr = (A.indptr, A.indices, view, A.shape)
    solver.set_operator(csr)
    x1 = solver.solve(np.ones(16)).value
    base *= 2.0  # the caller changes the values behind the read-only view
    solver.set_operator(csr)
    x2 = solver.solve(np.ones(16)).value
    assert np.allclose(x2, x1 / 2, rtol=1e-8)


def test_parametric_matrix_returns_a_writeable_matrix_despite_the_values_cache():
    P = pp.diffusion_operator(unit_square(1), "P0")
    theta = np.ones(P.n_params)
    M = P.matrix(theta)
    M.data *= 2.0  # the user's own copy
    assert np.allclose(P.matrix(theta).data * 2.0, M.data)
    assert P.values(theta) is P.values(theta.copy())  # equal θ: the cached array


def test_backward_after_another_operator_was_set_uses_its_own_operator():
    """The backward skips set_operator only while the solver still holds its operator."""
    A1, A2 = fd_poisson(4), 2.0 * fd_poisson(4) + sp.identity(16)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=500, rtol=1e-13)
    b1 = randn(16, seed=1, requires_grad=True)
    x1 = pp.solve(A1, b1, solver)
    pp.solve(A2, randn(16, seed=2), solver)  # the solver now holds A2
    w = randn(16, seed=3)
    x1.backward(w)
    exact = spla.spsolve(A1.T.tocsc(), w.numpy())
    assert np.allclose(b1.grad.numpy(), exact, rtol=1e-9, atol=1e-11)


def test_setup_on_another_communicator_keeps_the_operator():
    solver = pp.KSPSolver(CG_JACOBI, max_it=300, rtol=1e-12)
    solver.set_operator(fd_poisson(3))
    version = solver.operator_version
    solver._destroy_ksps()  # what a rebuild on a larger communicator does first
    solver._build(PETSc.COMM_SELF)
    solver.rebuild_on(PETSc.COMM_SELF)  # same size: nothing to do
    assert solver.operator_version == version


def test_operator_layouts_report_what_changed_and_keep_counting_across_kinds():
    """One layout class per operator kind (`layout_for`), one `Change` per update; a new
    kind continues the version count, so a backward's remembered version never matches."""
    from prdp_petsc.core.operator import CallerMat, Change, ReplicatedCSR, layout_for

    A = fd_poisson(3)
    op = layout_for(A)
    assert type(op) is ReplicatedCSR and op.mat is None
    assert op.update(A) is Change.NEW and op.symmetric
    assert op.update(A.copy()) is Change.NONE
    assert op.update(A, known_symmetric=False) is Change.SYMMETRY and not op.symmetric
    assert op.update(2.0 * A) is Change.VALUES and op.symmetric  # tested again
    assert layout_for(op.mat, op) is op and op.update(op.mat) is Change.NONE  # its own Mat
    version = op.version
    mat = PETSc.Mat().createAIJ(size=A.shape, csr=(A.indptr, A.indices, A.data))
    held = layout_for(mat, op)
    assert type(held) is CallerMat and held.version == version and op.mat is None
    assert held.update(mat) is Change.NEW and held.version == version + 1
    assert held.csr() is None and held.arrays() == [] and held.symmetric is None  # not known
    assert layout_for(mat, held) is held and held.update(mat) is Change.NONE
    with pytest.raises(TypeError, match="OwnedCSR"):
        layout_for(np.eye(3), held)
    back = layout_for(A, held)
    assert type(back) is ReplicatedCSR and back.update(A) is Change.NEW
    assert back.version == version + 2 and held.mat is None
    back.destroy()
    mat.destroy()


def test_each_result_names_its_side_and_the_solver_keeps_none():
    """Forward and adjoint are one object each (`Side`); a call's record names its side
    by the plain word a JSON file holds, and lives in the result only: the sides keep
    their KSP, not the outcome of their last call."""
    from prdp_petsc.core.results import Side

    solver = pp.KSPSolver(CG_JACOBI, max_it=3)
    solver.set_operator(fd_poisson(3))
    forward = solver.solve(np.ones(9)).info
    adjoint = solver.solve_transpose(np.ones(9)).info
    assert (forward.kind, adjoint.kind) == (Side.FORWARD.value, Side.ADJOINT.value)
    assert type(forward.kind) is str and forward.iterations == adjoint.iterations == 3
    for side in (solver._fwd, solver._adj):
        assert not hasattr(side, "last")
    solver.destroy()
