"""No silent wrong answer at the library's boundaries.

Each test here reproduces a path that once returned a plausible wrong number without
an error: a symmetric-only method on a non-symmetric operator, an operator edited in
place between forward and backward, NaN turned into zero, a residual PETSc never
computed reported as 0.0 with "converged", one sample's outcome standing for a batch.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from _core import reaction_problem

import prdp_petsc as pp
from prdp_petsc.errors import InputError, NonFiniteError, StructureError


def advection_diffusion(n=60, peclet=40.0):
    """1D −u'' + c u' (central differences): the non-symmetric regime PRDP runs in."""
    h = 1.0 / (n + 1)
    main = 2.0 * np.ones(n) / h**2
    off = -np.ones(n - 1) / h**2
    adv = peclet * np.ones(n - 1) / (2 * h)
    return sp.diags([off - adv, main, off + adv], [-1, 0, 1]).tocsr()


def spd(n=60):
    return advection_diffusion(n, peclet=0.0)


RHS = np.random.default_rng(0).standard_normal(60)


# -- 1. symmetric-only methods on a non-symmetric operator ----------------------------
@pytest.mark.parametrize(
    "options, culprit",
    [
        ("-ksp_type cg -pc_type jacobi", "ksp_type cg"),
        ("-ksp_type minres -pc_type none", "ksp_type minres"),
        ("-ksp_type cg -pc_type icc", "ksp_type cg"),
        ("-ksp_type gmres -pc_type icc", "pc_type icc"),
        ("-ksp_type gmres -pc_type bjacobi -sub_pc_type icc", "sub_pc_type icc"),
        ("-ksp_type gmres -pc_type bjacobi -sub_ksp_type cg -sub_pc_type jacobi", "sub_ksp_type"),
    ],
)
def test_symmetric_only_method_on_nonsymmetric_operator_is_refused(options, culprit):
    with pp.KSPSolver(options, prefix="sym_", max_it=40) as solver:
        solver.set_operator(advection_diffusion())
        with pytest.raises(StructureError, match=culprit) as info:
            solver.solve(RHS)
        assert "gmres" in str(info.value) or "ilu" in str(info.value)  # names an alternative
        assert solver.stats.forward_solves == 0  # nothing was solved


def test_the_refused_method_really_was_wrong_and_the_alternative_is_right():
    A = advection_diffusion()
    exact = spla.spsolve(A.tocsc(), RHS)
    with pp.KSPSolver("-ksp_type cg -pc_type jacobi", max_it=40, check_structure=False) as cg:
        cg.set_operator(A)  # the expert's opt-out: it runs, and is far off
        off = np.linalg.norm(cg.solve(RHS).value - exact) / np.linalg.norm(exact)
    assert off > 0.5
    with pp.KSPSolver("-ksp_type gmres -pc_type ilu", max_it=200, rtol=1e-12) as gmres:
        gmres.set_operator(A)
        np.testing.assert_allclose(gmres.solve(RHS).value, exact, rtol=1e-8)


def test_symmetric_operators_and_declarations_are_not_refused():
    with pp.KSPSolver("-ksp_type cg -pc_type icc", max_it=200, rtol=1e-12) as solver:
        solver.set_operator(spd())
        x = solver.solve(RHS).value
        np.testing.assert_allclose(x, spla.spsolve(spd().tocsc(), RHS), rtol=1e-8)
    # the caller's word wins over the test (e.g. an operator symmetric in exact arithmetic)
    with pp.KSPSolver("-ksp_type cg", max_it=5, structure=pp.Structure(symmetric=True)) as solver:
        solver.set_operator(advection_diffusion())
        assert solver.solve(RHS).iterations == 5


def test_rounding_level_asymmetry_is_symmetric():
    # entries that cancel down to 1e-9 of the diagonal keep rounding errors of its size
    A = spd().tolil()
    A[0, 1], A[1, 0] = 1e-7, 1e-7 + 3e-16 * 3600
    with pp.KSPSolver("-ksp_type cg -pc_type jacobi", max_it=5) as solver:
        solver.set_operator(A.tocsr())
        assert solver.is_symmetric is True
        solver.solve(RHS)


def test_unrolled_cg_on_nonsymmetric_operator_is_refused():
    b = torch.tensor(RHS)
    with pp.KSPSolver("-ksp_type cg -pc_type jacobi", max_it=10) as solver:
        with pytest.raises(StructureError, match="unrolled"):
            pp.solve(advection_diffusion(), b, solver, mode="unrolled")


# -- 2. the operator contract: the backward uses what the forward used ---------------
@pytest.mark.parametrize("other_solve_in_between", [False, True])
def test_operator_edited_in_place_does_not_change_the_pending_gradient(other_solve_in_between):
    M = advection_diffusion()
    M0 = M.copy()
    g = np.random.default_rng(1).standard_normal(60)
    with pp.KSPSolver("-ksp_type gmres -pc_type ilu", max_it=300, rtol=1e-13) as solver:
        b = torch.tensor(RHS, requires_grad=True)
        x = pp.solve(M, b, solver)
        M.data *= 3  # the caller edits its matrix before the backward
        if other_solve_in_between:
            pp.solve(M, torch.tensor(RHS), solver)
        x.backward(torch.tensor(g))
    expected = spla.spsolve(M0.T.tocsc(), g)
    np.testing.assert_allclose(b.grad.numpy(), expected, rtol=1e-9)


def test_pattern_edited_in_place_between_forward_and_backward_is_not_used():
    """The backward's re-set operator is the solver's kept copy, not the caller's arrays."""
    M = advection_diffusion()
    M0 = M.copy()
    g = np.random.default_rng(2).standard_normal(60)
    with pp.KSPSolver("-ksp_type gmres -pc_type ilu", max_it=300, rtol=1e-13) as solver:
        b = torch.tensor(RHS, requires_grad=True)
        x = pp.solve(M, b, solver)
        M.data *= 2
        M.indices[:] = M.indices[::-1].copy()  # nonsense, and never read again
        pp.solve(spd() * 3, torch.tensor(RHS), solver)  # another operator in between
        x.backward(torch.tensor(g))
    np.testing.assert_allclose(b.grad.numpy(), spla.spsolve(M0.T.tocsc(), g), rtol=1e-9)


def test_the_solver_keeps_the_operator_without_a_copy_per_call():
    """A scipy matrix: values copied when they change, not per call; the library's own
    read-only values (a ParametricMatrix at θ): never copied."""
    import tracemalloc

    M = spd(4000)
    rhs = torch.tensor(np.random.default_rng(3).standard_normal(4000), requires_grad=True)
    with pp.KSPSolver("-ksp_type cg -pc_type jacobi", max_it=5) as solver:
        pp.solve(M, rhs, solver).sum().backward()
        kept = solver.operator_csr()
        assert kept[2] is not M.data and not kept[2].flags.writeable
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        pp.solve(M, rhs, solver).sum().backward()
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
        assert solver.operator_csr()[2] is kept[2]  # unchanged values: the same array
        assert peak < 6 * 4000 * 8  # a few vectors (M.data alone is 3 vectors)
        M.data *= 2
        pp.solve(M, rhs, solver)
        assert solver.operator_csr()[2] is not kept[2] and np.all(kept[2] == M.data / 2)

    P = pp.ParametricMatrix(
        M.indptr, M.indices, M.shape, np.zeros(M.nnz), sp.csr_matrix(M.data[:, None])
    )
    theta = torch.ones(1, dtype=torch.float64)
    with pp.KSPSolver("-ksp_type cg -pc_type jacobi", max_it=5) as solver:
        pp.solve(P, rhs, solver, theta=theta)
        assert solver.operator_csr()[2] is P.values(theta.numpy())


def test_parametric_matrix_is_immutable():
    A = pp.ParametricMatrix(
        spd().indptr, spd().indices, spd().shape, spd().data.copy(), sp.csr_matrix((spd().nnz, 1))
    )
    for array in (A.a0, A.G.data, A.indices, A.indptr):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 7
    source = np.ones(spd().nnz)
    B = pp.ParametricMatrix(spd().indptr, spd().indices, spd().shape, source, A.G)
    source[:] = 5.0  # the caller's array is not the matrix's
    assert np.all(B.a0 == 1.0)


# -- 3. NaN and Inf never become numbers ---------------------------------------------
def test_nan_right_hand_side_raises_in_the_raw_solver():
    bad = RHS.copy()
    bad[3] = np.nan
    with pp.KSPSolver("-ksp_type gmres", max_it=10) as solver:
        solver.set_operator(advection_diffusion())
        with pytest.raises(NonFiniteError, match="NaN or Inf"):
            solver.solve(bad)
        with pytest.raises(NonFiniteError):
            solver.solve_transpose(np.where(np.arange(60) == 0, np.inf, RHS))
        with pytest.raises(NonFiniteError, match="rows \\[1\\]"):
            solver.solve(np.stack([RHS, bad]))


@pytest.mark.parametrize("mode", ["implicit", "unrolled"])
def test_nan_cotangent_raises_instead_of_a_zero_gradient(mode):
    options = "-ksp_type richardson -pc_type jacobi"
    with pp.KSPSolver(options, max_it=10) as solver:
        b = torch.tensor(RHS, requires_grad=True)
        x = pp.solve(spd(), b, solver, mode=mode)
        g = torch.zeros(60, dtype=torch.float64)
        g[7] = torch.nan
        with pytest.raises(NonFiniteError, match="NaN or Inf"):
            x.backward(g)


def test_nan_inputs_raise_in_dirichlet_and_newton():
    import skfem

    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    A = pp.diffusion_operator(basis)
    d = pp.Dirichlet(A, basis.get_dofs())
    theta = torch.ones(A.n_params, dtype=torch.float64)
    f = torch.ones(basis.N, dtype=torch.float64)
    g = torch.zeros(len(d.boundary), dtype=torch.float64)
    with pp.KSPSolver("-ksp_type cg", max_it=10) as solver:
        with pytest.raises(NonFiniteError):
            d.solve(f * torch.nan, g, solver, theta=theta)
        with pytest.raises(NonFiniteError):
            d.solve(f, g + torch.inf, solver, theta=theta)
        with pytest.raises(NonFiniteError):
            d.solve(f, g, solver, theta=theta * torch.nan)
    problem = reaction_problem(4)
    f = torch.ones(problem.n, dtype=torch.float64)
    u0 = torch.zeros(problem.n, dtype=torch.float64)
    with pp.KSPSolver("-ksp_type gmres", max_it=50, rtol=1e-10) as solver:
        with pytest.raises(NonFiniteError):
            pp.newton_solve(problem, u0 * torch.nan, f, 1.0, solver=solver)
        with pytest.raises(NonFiniteError):
            pp.newton_solve(problem, u0, f * torch.inf, 1.0, solver=solver)


# -- 5. per-call results, and no residual PETSc did not compute --------------------
def test_residual_not_computed_is_not_zero_and_not_converged():
    with pp.KSPSolver("-ksp_type richardson -pc_type sor", max_it=3) as solver:
        solver.set_operator(spd())
        sol = solver.solve(RHS)
    x, info = sol.value, sol.info[0]
    assert (sol.reason, sol.residual_norm, sol.converged) == (info.reason, None, False)
    assert info.reason == "CONVERGED_ITS" and info.iterations == 3
    assert info.residual_norm is None and not info.residual_computed
    assert not info.converged
    true_residual = np.linalg.norm(RHS - spd() @ x) / np.linalg.norm(RHS)
    assert true_residual > 1e-3  # the "CONVERGED" PETSc reports is far from converged


def test_a_batch_reports_every_sample():
    rhs = np.stack([RHS, np.zeros(60), np.sin(np.linspace(0, np.pi, 60))])
    with pp.KSPSolver("-ksp_type cg -pc_type none", max_it=500, rtol=1e-10) as solver:
        solver.set_operator(spd())
        batch = solver.solve(rhs).info
        alone = [solver.solve(row).iterations for row in rhs]
        adjoint = solver.solve_transpose(rhs[:2]).info
    assert len(batch) == 3 and batch.kind == "forward"
    assert batch.iterations.tolist() == alone
    assert len(set(alone)) == 3  # three different outcomes, not the last one thrice
    assert batch[1].iterations == 0 and batch[1].converged  # b = 0: x = 0 at once
    assert batch.converged and batch.residual_computed.all()
    assert len(adjoint) == 2 and adjoint.kind == "adjoint"


def test_a_batch_of_operators_reports_every_sample_in_batch_order():
    import skfem

    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    A = pp.diffusion_operator(basis, reaction=1.0)
    theta = torch.stack([torch.ones(A.n_params), 1e4 * torch.ones(A.n_params)]).double()
    b = torch.ones(2, A.shape[0], dtype=torch.float64, requires_grad=True)
    with pp.KSPSolver("-ksp_type cg -pc_type none", max_it=500, rtol=1e-10) as solver:
        sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
        sol.value.sum().backward()
        forward, adjoint = sol.info, sol.adjoint
    assert len(forward) == len(adjoint) == 2
    # κ = 1e4 makes the operator stiffer against the unit reaction: more iterations
    assert forward.iterations[1] > forward.iterations[0]
    assert adjoint.iterations.tolist() == forward.iterations.tolist()  # symmetric, same rhs


def test_input_errors_are_value_errors_with_their_own_class():
    assert issubclass(NonFiniteError, InputError) and issubclass(InputError, ValueError)
    with pp.KSPSolver("-ksp_type gmres", max_it=10) as solver:
        solver.set_operator(spd())
        with pytest.raises(InputError, match="right-hand side has 3 entries"):
            solver.solve(np.ones(3))


def test_a_read_only_array_with_a_writeable_view_is_still_copied():
    """A caller's read-only values are not taken at their word: a view made before the
    flag was cleared can still edit them.  The backward uses the forward's values, and
    the next forward sees the edit."""
    rng = np.random.default_rng(5)
    A = (
        sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(20, 20))
        + sp.random(20, 20, density=0.1, random_state=1)
    ).tocsr()
    A.sort_indices()
    A0 = A.copy()
    values = A.data.copy()
    view = values[:]
    values.flags.writeable = False
    A.data = values
    g = rng.standard_normal(20)
    with pp.KSPSolver({"ksp_type": "gmres", "pc_type": "jacobi"}, max_it=200, rtol=1e-13) as s:
        b = torch.ones(20, dtype=torch.float64, requires_grad=True)
        x = pp.solve(A, b, s)
        view *= 3  # edits A's values through the writeable view
        pp.solve(A0 * 2, torch.ones(20, dtype=torch.float64), s)  # another operator
        x.backward(torch.from_numpy(g))
        expected = spla.spsolve(A0.T.tocsc(), g)
        assert np.abs(b.grad.numpy() - expected).max() <= 1e-10 * np.abs(expected).max()
        x3 = pp.solve(A, torch.ones(20, dtype=torch.float64), s).numpy()
        assert np.abs(A @ x3 - 1.0).max() <= 1e-10  # the edited values, not the kept ones
