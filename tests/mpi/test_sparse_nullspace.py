"""A sparse null space on several ranks: the discrete gradient of curl-curl.

On one process `Structure(nullspace=G)` (scipy sparse, columns spanning the kernel)
is a projection with a factored ``GᵀG``; on more ranks its columns become
distributed vectors (the replicated layout slices them like the rows).  The
solution must equal the serial one, orthogonal to every gradient.
"""

import sys
from pathlib import Path

import numpy as np
import skfem
from _mpi import all_ranks
from petsc4py import PETSc

import prdp_petsc as pp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared problems
from _curl_curl import curl_curl, interior  # noqa: E402


def test_the_discrete_gradient_as_a_null_space_on_two_ranks():
    basis, A, b = curl_curl(skfem.MeshTet().refined(2), skfem.ElementTetN0)
    A, b, kept = interior(basis, A, b)
    G = pp.discrete_gradient(basis, kept)
    structure = pp.Structure(nullspace=G)
    out = []
    for comm in (PETSc.COMM_SELF, PETSc.COMM_WORLD):
        with pp.KSPSolver(
            {"ksp_type": "cg", "pc_type": "jacobi"},
            max_it=1000,
            rtol=1e-12,
            comm=comm,
            structure=structure,
        ) as solver:
            solver.set_operator(A)
            sol = solver.solve(b)
            out.append(sol.value)
            vectors = len(solver.mat.getNullSpace().getVecs())
            assert all_ranks(sol.converged)
            assert all_ranks(vectors == (0 if comm.getSize() == 1 else G.shape[1]))
    assert all_ranks(np.abs(out[1] - out[0]).max() <= 1e-8 * np.abs(out[0]).max())
    assert all_ranks(np.abs(G.T @ out[1]).max() <= 1e-10 * np.abs(out[1]).max())
