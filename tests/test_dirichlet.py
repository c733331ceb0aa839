"""`Dirichlet` reads the boundary values in the caller's order and refuses repeats.

It used to sort and de-duplicate the indices (``np.unique``) and read ``g`` in that
sorted order: values given wall by wall in the caller's order were silently permuted.
"""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch
from _core import CONVERGED, unit_square

import prdp_petsc as pp
from prdp_petsc.errors import InputError


def walls(basis):
    """The boundary dofs wall by wall (right wall first: not increasing), and their x."""
    x, y = basis.doflocs
    right = np.flatnonzero(np.isclose(x, 1.0))
    left = np.flatnonzero(np.isclose(x, 0.0))
    rest = np.flatnonzero(
        ~np.isclose(x, 0.0) & ~np.isclose(x, 1.0) & (np.isclose(y, 0.0) | np.isclose(y, 1.0))
    )
    return np.concatenate([right, left, rest]), x


@pytest.mark.parametrize("parametric", [True, False])
def test_boundary_values_are_read_in_the_callers_order(parametric):
    basis = unit_square(3)
    dofs, x = walls(basis)
    assert np.any(np.diff(dofs) < 0)  # the case np.unique used to reorder
    A = pp.diffusion_operator(basis, "P0")
    theta = np.ones(A.n_params)
    op = A if parametric else A.matrix(theta)
    bc = pp.Dirichlet(op, dofs)
    assert np.array_equal(bc.boundary, dofs)
    g = torch.from_numpy(x[dofs].copy())  # u = x on the boundary: harmonic, so u = x inside
    f = torch.zeros(basis.N, dtype=torch.float64)
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, **CONVERGED) as solver:
        kw = {"theta": torch.from_numpy(theta)} if parametric else {}
        u = bc.solve(f, g, solver, **kw).numpy()
    np.testing.assert_allclose(u, x, atol=1e-10)
    assert np.array_equal(u[dofs], g.numpy())


def test_the_gradient_in_g_follows_the_callers_order():
    basis = unit_square(2)
    dofs, _ = walls(basis)
    A = pp.diffusion_operator(basis, "P0").matrix(np.ones(basis.mesh.t.shape[1]))
    bc = pp.Dirichlet(A, dofs)
    interior = np.setdiff1d(np.arange(basis.N), dofs)
    g = torch.linspace(0.0, 1.0, len(dofs), dtype=torch.float64, requires_grad=True)
    w = torch.from_numpy(np.random.default_rng(0).normal(size=basis.N))
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, **CONVERGED) as solver:
        (bc.solve(torch.zeros(basis.N, dtype=torch.float64), g, solver) @ w).backward()
    # d(w·u)/dg = w_B − A_IBᵀ A_II⁻ᵀ w_I with B in the caller's order
    A = A.tocsr()
    lam = spla.spsolve(A[interior][:, interior].T.tocsc(), w.numpy()[interior])
    expected = w.numpy()[dofs] - A[interior][:, dofs].T @ lam
    np.testing.assert_allclose(g.grad.numpy(), expected, atol=1e-10)


def test_repeated_or_out_of_range_boundary_indices_are_refused():
    basis = unit_square(2)
    A = pp.diffusion_operator(basis, "P0")
    dofs = basis.get_dofs().all()
    with pytest.raises(InputError, match=r"repeats indices \[" + str(dofs[0])):
        pp.Dirichlet(A, np.concatenate([dofs, dofs[:1]]))
    with pytest.raises(InputError, match="must lie in"):
        pp.Dirichlet(A, [basis.N])
    with pytest.raises(InputError, match="integer"):
        pp.Dirichlet(A, dofs.astype(float))


def test_scikit_fem_dofs_are_taken_as_they_are():
    basis = unit_square(2)
    A = pp.diffusion_operator(basis, "P0")
    dofs = basis.get_dofs()
    bc = pp.Dirichlet(A, dofs)
    assert np.array_equal(bc.boundary, dofs.all())
