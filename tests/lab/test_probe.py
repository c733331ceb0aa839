"""The harness's probe: K_full of a scene's first solver, from its ``probe()``."""

from types import SimpleNamespace

import numpy as np
import pytest
from _core import fd_poisson, randn, raw_ksp
from petsc4py import PETSc

import prdp_petsc as pp
from prdp_petsc.lab.training.harness import find_k_full

JACOBI = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.7}
CG = {"ksp_type": "cg", "pc_type": "jacobi"}


@pytest.mark.parametrize("options", [JACOBI, CG], ids=["richardson-jacobi", "cg-jacobi"])
def test_k_full_from_a_guess_is_petscs_count_to_rtol_times_norm_b(options):
    """K_full with a guess in the probe = PETSc's own iterations from x0 to ‖r‖ ≤ rtol ‖b‖."""

    A = fd_poisson(10).tocsr()
    b = randn(100, seed=14).numpy()
    x0 = np.linalg.solve(A.toarray(), b) + 1e-5 * randn(100, seed=15).numpy()  # a good guess
    rtol = 1e-6

    def scene(*probe):
        return SimpleNamespace(
            solvers=[pp.KSPSolver(options, max_it=1)], probe=lambda: probe, rtol_full=rtol
        )

    cold, warm = find_k_full(scene(A, b, None)), find_k_full(scene(A, b, x0))
    mat = PETSc.Mat().createAIJ(A.shape, csr=(A.indptr, A.indices, A.data), comm=PETSc.COMM_SELF)
    counts = []
    for guess in (np.zeros(100), x0):
        ksp = raw_ksp(mat, options)
        ksp.setTolerances(rtol=rtol, atol=0.0, max_it=10_000)
        ksp.setInitialGuessNonzero(True)
        x, rhs = mat.createVecs()
        rhs.setArray(b)
        x.setArray(guess)
        ksp.solve(rhs, x)
        assert ksp.getConvergedReason() > 0
        counts.append(ksp.getIterationNumber())
        for obj in (ksp, x, rhs):
            obj.destroy()
    mat.destroy()
    assert (cold, warm) == tuple(counts)
    assert warm < cold


def test_k_full_refuses_a_probe_without_its_guess():
    """``probe() -> (A, b)`` is refused: the shape is ``(A, b, x0)``, x0 None from zero."""

    A = fd_poisson(3).tocsr()
    scene = SimpleNamespace(
        solvers=[pp.KSPSolver(CG, max_it=1)], probe=lambda: (A, np.ones(9)), rtol_full=1e-6
    )
    with pytest.raises(TypeError, match=r"\(A, b, x0\), with x0=None .* got a 2-tuple"):
        find_k_full(scene)
