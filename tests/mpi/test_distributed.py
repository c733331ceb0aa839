"""Domain-parallel solves: one PETSc solve across the ranks equals the serial solve.

The distributed solver (``comm=COMM_WORLD``: MPIAIJ, rows split across the ranks,
replicated tensors) and a serial solver (``COMM_SELF``) run the same problem in
the same process; solution, ∂L/∂b and ∂L/∂θ must agree to 1e-10 (relative), and
every rank must hold the same tensors.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import skfem
import torch
from _mpi import COMM, all_ranks, same_on_all_ranks
from petsc4py import PETSc
from skfem import BilinearForm

import prdp_petsc as pp
from prdp_petsc.core.parallel import ownership_range, use_comm

CONVERGED = {"max_it": 2000, "rtol": 1e-13, "atol": 1e-50}


def _basis(refine=4):
    return skfem.Basis(skfem.MeshTri().refined(refine), skfem.ElementTriP1())


def _problem(advect: bool):
    """Interior operator ``A_II(θ)`` of −∇·(θ∇u) [+ β·∇u], θ per element."""
    basis = _basis()
    A = pp.diffusion_operator(basis, "P0")
    if advect:

        @BilinearForm
        def form(u, v, w):
            return (20.0 * u.grad[0] + 10.0 * u.grad[1]) * v

        A = A + form.assemble(basis).tocsr()
    return pp.Dirichlet(A, basis.get_dofs()).A_II


def _rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def _gradients(A, solver, theta, b, weights):
    theta = theta.detach().clone().requires_grad_()
    b = b.detach().clone().requires_grad_()
    x = pp.solve(A, b, solver, theta=theta)
    (x * weights).sum().backward()
    return x.detach().numpy(), b.grad.numpy(), theta.grad.numpy()


def test_capped_solve_from_a_guess_equals_serial():
    """``solve(..., x0=)`` distributed: iterates from the guess and ∂L/∂x0 as in serial."""
    A = _problem(False)
    rng = np.random.default_rng(2)
    theta = torch.from_numpy(1.0 + rng.random(A.n_params))
    b, x0, weights = (torch.from_numpy(rng.standard_normal((2, A.shape[0]))) for _ in range(3))
    options = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.7}
    results = []
    for comm, prefix in ((PETSc.COMM_SELF, "ser0_"), (PETSc.COMM_WORLD, "dist0_")):
        guess = x0.clone().requires_grad_()
        with pp.KSPSolver(options, prefix=prefix, comm=comm, max_it=9) as solver:
            x = pp.solve(A, b, solver, theta=theta, x0=guess)
            (x * weights).sum().backward()
        results.append((x.detach().numpy(), guess.grad.numpy()))
    errors = [_rel(g, e) for g, e in zip(results[1], results[0], strict=True)]
    assert all_ranks(max(errors) <= 1e-10), errors
    assert all(same_on_all_ranks(g) for g in results[1])


@pytest.mark.parametrize(
    "advect, options, settings",
    [
        (False, {"ksp_type": "cg", "pc_type": "jacobi"}, CONVERGED),
        (False, {"ksp_type": "cg", "pc_type": "jacobi"}, {"max_it": 12}),
        (True, {"ksp_type": "gmres", "pc_type": "jacobi"}, CONVERGED),
        (True, {"ksp_type": "gmres", "pc_type": "none"}, {"max_it": 10}),
        (False, {"ksp_type": "cg", "pc_type": "gamg"}, CONVERGED),
    ],
    ids=["cg-converged", "cg-K12", "gmres-nonsym", "gmres-K10-nonsym", "cg-gamg"],
)
def test_solution_and_gradients_equal_serial(advect, options, settings):
    A = _problem(advect)
    rng = np.random.default_rng(1)
    theta = torch.from_numpy(1.0 + rng.random(A.n_params))
    b = torch.from_numpy(rng.standard_normal((3, A.shape[0])))
    weights = torch.from_numpy(rng.standard_normal((3, A.shape[0])))
    with pp.KSPSolver(options, prefix="ser_", **settings) as serial:
        expected = _gradients(A, serial, theta, b, weights)
    with pp.KSPSolver(options, prefix="dist_", comm=PETSc.COMM_WORLD, **settings) as dist:
        got = _gradients(A, dist, theta, b, weights)
        assert dist.mat.getType() == "mpiaij"
        assert dist.mat.getOwnershipRange() == ownership_range(A.shape[0], PETSc.COMM_WORLD)
    errors = [_rel(g, e) for g, e in zip(got, expected, strict=True)]
    assert all_ranks(max(errors) <= 1e-10), errors
    assert all(same_on_all_ranks(g) for g in got)


def test_batch_of_operators_and_new_values():
    """θ of shape (B, p): one operator per sample, each set into the MPIAIJ Mat in turn."""
    A = _problem(advect=False)
    rng = np.random.default_rng(2)
    theta = torch.from_numpy(1.0 + rng.random((3, A.n_params)))
    b = torch.from_numpy(rng.standard_normal((3, A.shape[0])))
    weights = torch.from_numpy(rng.standard_normal((3, A.shape[0])))
    options = {"ksp_type": "cg", "pc_type": "jacobi"}
    with pp.KSPSolver(options, **CONVERGED) as serial:
        expected = _gradients(A, serial, theta, b, weights)
    with pp.KSPSolver(options, comm=PETSc.COMM_WORLD, **CONVERGED) as dist:
        got = _gradients(A, dist, theta, b, weights)
    assert all_ranks(max(_rel(g, e) for g, e in zip(got, expected, strict=True)) <= 1e-10)


@pytest.mark.parametrize("nullspace", ["constant", "vector"])
def test_singular_operator_with_null_space(nullspace):
    """Pure Neumann Laplacian: the null space (full-length vector) is split like the rows."""
    basis = _basis(3)
    K = pp.diffusion_operator(basis, "P0").matrix(np.ones(basis.mesh.nelements))
    n = K.shape[0]
    K = sp.csr_matrix(K)
    spec = "constant" if nullspace == "constant" else np.ones(n)
    b = np.random.default_rng(3).standard_normal(n)
    out = []
    for comm in (PETSc.COMM_SELF, PETSc.COMM_WORLD):
        with pp.KSPSolver(
            {"ksp_type": "cg"}, structure=pp.Structure(nullspace=spec), comm=comm, **CONVERGED
        ) as s:
            s.set_operator(K)
            out.append(s.solve(b).value)
    assert all_ranks(_rel(out[1], out[0]) <= 1e-10)
    assert all_ranks(abs(out[1].sum()) <= 1e-8 * np.abs(out[1]).max())  # minimum norm


def test_use_comm_makes_distributed_solvers_and_clone_keeps_it():
    with use_comm(COMM):  # an mpi4py communicator is accepted
        solver = pp.KSPSolver({"ksp_type": "cg"}, max_it=5)
    with solver, solver.clone(max_it=7) as other:
        ranks = [solver.describe()["ranks"], other.describe()["ranks"]]
    assert all_ranks(ranks == [COMM.Get_size()] * 2)
    with pp.KSPSolver(max_it=5) as serial:
        assert serial.describe()["ranks"] == 1


def _owned_mat(full):
    """A caller's MPIAIJ Mat holding this rank's rows of `full`, and those rows."""
    n = full.shape[0]
    start, end = ownership_range(n, PETSc.COMM_WORLD)
    local = full[start:end]
    mat = PETSc.Mat().createAIJ(
        size=((end - start, n), (end - start, n)),
        csr=(local.indptr.astype(PETSc.IntType), local.indices.astype(PETSc.IntType), local.data),
        comm=PETSc.COMM_WORLD,
    )
    mat.assemble()
    return mat, (start, end)


def test_owned_layout_with_a_callers_distributed_mat():
    """A caller's MPIAIJ Mat: vectors hold the rank's own rows, nothing is gathered."""
    n = 40
    full = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n)).tocsr()
    mat, (start, end) = _owned_mat(full)
    b = np.random.default_rng(4).standard_normal(n)
    with pp.KSPSolver({"ksp_type": "cg"}, **CONVERGED) as solver:
        solver.set_operator(mat)
        x_local = solver.solve(b[start:end]).value
        with pytest.raises(ValueError, match="local rows"):
            solver.solve(b if end - start != n else b[:-1])
    mat.destroy()
    x = np.concatenate(COMM.allgather(x_local))
    expected = np.linalg.solve(full.toarray(), b)
    assert all_ranks(_rel(x, expected) <= 1e-10)


@pytest.mark.parametrize("layout", ["replicated", "owned"])
def test_bench_mpi_solve_worker_records_the_split(layout):
    """``bench mpi``'s 3D solve on the unrefined box: rows split, K iterations, memory."""
    from types import SimpleNamespace

    from prdp_petsc.lab.reports.bench_mpi import _solve_worker

    args = SimpleNamespace(refine=0, cube=0, k=15, repeats=1, layout=layout)
    record = _solve_worker(args)
    rows = COMM.allgather(record["rows_per_rank"])
    assert all_ranks(record["layout"] == layout and record["unknowns"] == 1195)
    assert all_ranks(sum(rows) == record["unknowns"] and record["iterations"] == 15)
    assert all_ranks(0 < record["petsc_mat_mb_per_rank"] < record["peak_rss_mb_per_rank"])
    if layout == "owned":  # each rank holds its own piece: less than the whole
        owned = COMM.allgather(record["owned_arrays_mb_per_rank"])
        assert all_ranks(all(0 < m for m in owned))


def test_sequential_only_pc_names_its_parallel_form():
    n = 60
    A = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n)).tocsr()
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, comm=COMM, **CONVERGED) as s:
        s.set_operator(A)
        with pytest.raises(pp.SolverError, match="sub_pc_type icc"):
            s.solve(np.ones(n))
    options = {"ksp_type": "cg", "pc_type": "bjacobi", "sub_pc_type": "icc"}
    with pp.KSPSolver(options, comm=COMM, **CONVERGED) as s:
        s.set_operator(A)
        x = s.solve(np.ones(n)).value
    assert all_ranks(_rel(A @ x, np.ones(n)) <= 1e-10)


@pytest.mark.parametrize("atol", [0.0, 1e-3])
def test_owned_layout_scales_the_right_hand_side_together(atol):
    """An entry beyond 2^100 on one rank's rows: every rank scales b by the same power
    of two (a per-rank choice solved another problem, or hung on diverging tests)."""
    n = 40
    full = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n)).tocsr()
    mat, (start, end) = _owned_mat(full)
    b = np.random.default_rng(5).standard_normal(n)
    b[0] = 1e40
    with pp.KSPSolver({"ksp_type": "cg"}, max_it=500, rtol=1e-12, atol=atol) as solver:
        solver.set_operator(mat)
        x = np.concatenate(COMM.allgather(solver.solve(b[start:end]).value))
    mat.destroy()
    assert all_ranks(_rel(x, np.linalg.solve(full.toarray(), b)) <= 1e-9)
