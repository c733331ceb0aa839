"""Declared structure on several ranks: block size, near-null space, fields, singular.

The replicated layout splits the rows by whole blocks and slices full-length
(near-)null-space vectors like the rows; a caller's distributed Mat (the owned
layout) takes vectors of this rank's entries and field indices in PETSc's global
numbering.  Every solve must equal the serial one; a singular operator raises on
every rank (collectively, nobody left waiting).
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from _mpi import COMM, all_ranks
from petsc4py import PETSc

import prdp_petsc as pp
from prdp_petsc.core.operator import OwnedCSR
from prdp_petsc.core.parallel import ownership_range
from prdp_petsc.errors import SingularOperatorError

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared problems
from _vector import SCHUR, body_load, clamped, elasticity, stokes  # noqa: E402

CONVERGED = {"max_it": 500, "rtol": 1e-11}
GAMG = {"ksp_type": "cg", "pc_type": "gamg"}


def _rel(a, b) -> float:
    return float(np.abs(np.asarray(a) - b).max() / np.abs(b).max())


@pytest.fixture(scope="module")
def cube():
    """3D elasticity on 3³ hexahedra, one face clamped: (basis, bc, M, f)."""
    basis, A = elasticity(n=3, dim=3)
    bc = clamped(basis, A)
    return basis, bc, bc.A_II.matrix(np.ones(A.n_params)), body_load(basis)[bc.interior]


def test_replicated_layout_splits_whole_blocks_and_keeps_the_modes(cube):
    basis, bc, M, f = cube
    structure = pp.Structure(near_nullspace=pp.rigid_body_modes(basis, bc.interior), block_size=3)
    out = []
    for comm in (PETSc.COMM_SELF, PETSc.COMM_WORLD):
        with pp.KSPSolver(GAMG, comm=comm, structure=structure, **CONVERGED) as solver:
            solver.set_operator(M)
            sol = solver.solve(f)
            out.append(sol.value)
            start, end = solver.mat.getOwnershipRange()
            assert all_ranks(start % 3 == 0 and end % 3 == 0 and solver.mat.getBlockSize() == 3)
            assert all_ranks(len(solver.mat.getNearNullSpace().getVecs()) == 6)
            assert all_ranks(sol.converged and sol.iterations <= 20)
    assert all_ranks(_rel(out[1], out[0]) <= 1e-8)
    assert all_ranks(ownership_range(M.shape[0], PETSc.COMM_WORLD, 3) == (start, end))


def test_owned_layout_with_a_callers_mat(cube):
    """A caller's MPIAIJ Mat of this rank's block rows: the modes as this rank's entries,
    the block size set on the caller's Mat."""
    basis, bc, M, f = cube
    n = M.shape[0]
    start, end = ownership_range(n, PETSc.COMM_WORLD, 3)
    local = sp.csr_matrix(M)[start:end]
    mat = PETSc.Mat().createAIJ(
        size=((end - start, n), (end - start, n)),
        csr=(local.indptr.astype(PETSc.IntType), local.indices.astype(PETSc.IntType), local.data),
        comm=PETSc.COMM_WORLD,
    )
    mat.assemble()
    modes = pp.rigid_body_modes(basis, bc.interior)[:, start:end]
    with pp.KSPSolver(
        GAMG, structure=pp.Structure(near_nullspace=modes, block_size=3), **CONVERGED
    ) as solver:
        solver.set_operator(mat)
        sol = solver.solve(f[start:end])
        x = np.concatenate(COMM.allgather(sol.value))
        assert all_ranks(mat.getBlockSize() == 3 and sol.iterations <= 20)
    mat.destroy()
    assert all_ranks(_rel(x, np.linalg.solve(M.toarray(), f)) <= 1e-8)


def test_owned_rows_that_split_a_block_are_refused():
    """OwnedCSR rows of 3 and 5 on two ranks cannot carry block_size=2."""
    n = 8
    full = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n)).tocsr()
    rank, size = COMM.Get_rank(), COMM.Get_size()
    bounds = [0, 3] + [3 + (n - 3) * (r + 1) // (size - 1) for r in range(size - 1)]
    start, end = bounds[rank], bounds[rank + 1]
    local = full[start:end]
    owned = OwnedCSR(
        local.indptr, local.indices, local.data, (n, n), (end - start, end - start),
        PETSc.COMM_WORLD,
    )  # fmt: skip
    with pp.KSPSolver(max_it=5, structure=pp.Structure(block_size=2)) as solver:
        with pytest.raises(pp.InputError, match="whole blocks"):
            solver.set_operator(owned)


def test_stokes_fields_on_two_ranks_equal_serial():
    _, A, bc, fields, _ = stokes(n=3)
    M = bc.A_II.matrix(np.ones(A.n_params))
    b = np.random.default_rng(3).standard_normal(M.shape[0])
    out = []
    for comm in (PETSc.COMM_SELF, PETSc.COMM_WORLD):
        with pp.KSPSolver(
            SCHUR, comm=comm, structure=pp.Structure(fields=fields), **CONVERGED
        ) as solver:
            solver.set_operator(M)
            out.append(solver.solve(b).value)
            splits = solver.ksp.getPC().getFieldSplitSubKSP()
            assert all_ranks(
                [k.getOptionsPrefix() for k in splits] == ["fieldsplit_u_", "fieldsplit_p_"]
            )
    assert all_ranks(_rel(out[1], out[0]) <= 1e-8)


def test_singular_operator_raises_on_every_rank():
    basis, A = elasticity(n=3)
    K = A.matrix(np.ones(A.n_params))
    with pp.KSPSolver(GAMG, comm=PETSc.COMM_WORLD, max_it=200, rtol=1e-8) as solver:
        solver.set_operator(K)
        with pytest.raises(SingularOperatorError):
            solver.solve(body_load(basis))
    modes = pp.rigid_body_modes(basis)
    with pp.KSPSolver(
        GAMG, comm=PETSc.COMM_WORLD, structure=pp.Structure(nullspace=modes), **CONVERGED
    ) as solver:
        solver.set_operator(K)
        x = solver.solve(body_load(basis)).value
    expected = np.linalg.pinv(K.toarray()) @ body_load(basis)
    assert all_ranks(_rel(x, expected) <= 1e-8)
