"""Curl-curl on Nédélec elements: the discrete gradient spans its kernel, and declaring it
as a sparse null space is cheap.

``(curl u, curl v)`` on lowest-order Nédélec elements (``ElementTriN1``,
``ElementTetN0``) maps every gradient of a P1 function to zero.  Undeclared, that
kernel makes CG fail (`tests/test_singular.py`); declared as ``Structure(nullspace=
discrete_gradient(basis, dofs))``, a solve returns the solution orthogonal to every
gradient, the minimum-norm least-squares solution.  Declared sparse, the null space
is the projection ``x − G (GᵀG)⁻¹ Gᵀ x`` (`prdp_petsc.core.nullspace.SparseSpan`):
no dense vector is built and nothing is orthonormalised, where a dense array of k
vectors costs a QR of n × k and k dot products per iteration.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
from _curl_curl import curl_curl, interior
from skfem import BilinearForm
from skfem.helpers import dot, grad

import prdp_petsc as pp
from prdp_petsc.core import nullspace
from prdp_petsc.core.nullspace import SparseSpan
from prdp_petsc.errors import InputError

CASES = {
    "tri": (lambda: skfem.MeshTri().refined(3), skfem.ElementTriN1, skfem.ElementTriP1),
    "tet": (lambda: skfem.MeshTet().refined(2), skfem.ElementTetN0, skfem.ElementTetP1),
}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("boundary", [False, True])
def test_the_discrete_gradient_spans_the_kernel(case, boundary):
    """A G = 0, G has full column rank, and one column per interior vertex with the
    boundary eliminated (per vertex but one without)."""
    make_mesh, element, _ = CASES[case]
    mesh = make_mesh()
    basis, A, b = curl_curl(mesh, element)
    dofs = None
    if boundary:
        A, b, dofs = interior(basis, A, b)
    G = pp.discrete_gradient(basis, dofs)
    assert sp.issparse(G) and G.shape[0] == A.shape[0]
    assert abs(A @ G).max() <= 1e-12 * abs(A).max()
    expected = len(mesh.interior_nodes()) if boundary else mesh.p.shape[1] - 1
    assert G.shape[1] == expected
    assert np.linalg.matrix_rank(G.toarray()) == expected
    assert set(np.unique(G.data)) == {-1.0, 1.0}  # two entries ±1 per edge row, or fewer


@pytest.mark.parametrize("case", CASES)
def test_g_phi_is_the_gradient(case):
    """G φ are the Nédélec dofs of ∇φ: equal to the L² projection of ∇φ onto the
    Nédélec space (exact: ∇P1 lies in it), so the sign of every edge is the element's."""
    make_mesh, element, scalar = CASES[case]
    mesh = make_mesh()
    basis = skfem.Basis(mesh, element())

    @BilinearForm
    def mass(u, v, w):
        return dot(u, v)

    @BilinearForm
    def mixed(u, v, w):
        return dot(grad(u), v)

    B = mixed.assemble(basis.with_element(scalar()), basis)
    projected = spla.spsolve(mass.assemble(basis).tocsc(), B.tocsc()).toarray()
    G = pp.discrete_gradient(basis).toarray()
    last = mesh.p.shape[1] - 1  # the vertex left out (no boundary: the last one)
    assert np.abs(G - np.delete(projected, last, axis=1)).max() <= 1e-12


def test_holes_get_a_column_per_boundary_part():
    """An annulus with u × n = 0 on both circles: the function that is 1 on the inner
    circle and 0 on the outer has a gradient in the kernel; it is a column of G."""
    mesh = skfem.MeshTri.init_circle(3)
    inner = np.linalg.norm(mesh.p, axis=0) < 0.45
    mesh = mesh.remove_elements(np.flatnonzero(np.all(inner[mesh.t], axis=0)))
    basis, A, b = curl_curl(mesh, skfem.ElementTriN1)
    A, b, dofs = interior(basis, A, b)
    G = pp.discrete_gradient(basis, dofs)
    assert abs(A @ G).max() <= 1e-12 * abs(A).max()
    assert G.shape[1] == len(mesh.interior_nodes()) + 1
    assert np.linalg.matrix_rank(G.toarray()) == G.shape[1]


def test_other_elements_are_refused():
    mesh = skfem.MeshTri().refined(1)
    with pytest.raises(InputError, match="lowest-order Nédélec"):
        pp.discrete_gradient(skfem.Basis(mesh, skfem.ElementTriP1()))
    with pytest.raises(InputError, match="lowest-order Nédélec"):
        pp.discrete_gradient(skfem.Basis(skfem.MeshQuad().refined(1), skfem.ElementQuadN1()))
    basis = skfem.Basis(mesh, skfem.ElementTriN1())
    with pytest.raises(InputError, match="dofs"):
        pp.discrete_gradient(basis, np.array([0, 0, 1]))


@pytest.fixture(scope="module", params=list(CASES))
def incompatible(request):
    """Curl-curl without the boundary, ε = 0, an incompatible load, and its gradients."""
    make_mesh, element, _ = CASES[request.param]
    basis, A, b = curl_curl(make_mesh(), element)
    A, b, dofs = interior(basis, A, b)
    return A, b, pp.discrete_gradient(basis, dofs)


@pytest.mark.parametrize("options", [{"ksp_type": "cg", "pc_type": "icc"}, {"ksp_type": "cg"}])
def test_declared_gradients_give_the_least_squares_solution(incompatible, options):
    """With G declared sparse, CG converges to A⁺b, orthogonal to every gradient (without
    it, CG fails: tests/test_singular.py)."""
    A, b, G = incompatible
    structure = pp.Structure(nullspace=G)
    with pp.KSPSolver(options, max_it=1000, rtol=1e-12, structure=structure) as solver:
        solver.set_operator(A)
        sol = solver.solve(b)
        assert sol.converged
    x = sol.value
    assert np.linalg.norm(G.T @ x) <= 1e-10 * spla.norm(G) * np.linalg.norm(x)
    expected = np.linalg.pinv(A.toarray()) @ b
    assert np.linalg.norm(x - expected) <= 1e-8 * np.linalg.norm(expected)
    # the residual of the compatible part fell: b minus its part along the gradients
    compatible = b - G @ spla.spsolve((G.T @ G).tocsc(), G.T @ b)
    assert np.linalg.norm(compatible - A @ x) <= 1e-8 * np.linalg.norm(compatible)


def test_a_sparse_null_space_builds_no_dense_vector(incompatible, monkeypatch):
    """The cost driver: a dense null space is orthonormalised (a QR of n × k) and removed
    with k dot products per iteration.  A sparse one builds no vector and no QR: PETSc's
    null space has no vectors, only the projection; and the check after new values is
    one sparse product A G, not k products."""
    A, b, G = incompatible
    built = []
    monkeypatch.setattr(
        nullspace,
        "_orthonormal_columns",
        lambda rows, name: built.append(rows.shape) or np.linalg.qr(rows.T)[0],
    )
    products = []
    defects = SparseSpan.defects
    monkeypatch.setattr(
        SparseSpan, "defects", lambda self, *a, **k: products.append(1) or defects(self, *a, **k)
    )
    with pp.KSPSolver(
        {"ksp_type": "cg"}, max_it=500, rtol=1e-10, structure=pp.Structure(nullspace=G)
    ) as solver:
        solver.set_operator(A)
        ns = solver.mat.getNullSpace()
        assert ns.getVecs() == [] and not ns.hasConstant()
        assert isinstance(ns.getFunction()[0], SparseSpan)
        assert solver.mat.getTransposeNullSpace().handle == ns.handle  # one object
        solver.solve(b)
        solver.set_operator((2.0 * A).tocsr())  # new values: checked again, one product
        solver.solve(b)
    assert built == []
    assert len(products) == 2  # once per set of values (A symmetric: Aᵀ G is A G)
    # the same space as dense rows: one QR, once, however many Mats the solver gets
    rows = G.T.toarray()
    with pp.KSPSolver(
        {"ksp_type": "cg"}, max_it=500, rtol=1e-10, structure=pp.Structure(nullspace=rows)
    ) as solver:
        solver.set_operator(A)
        assert len(solver.mat.getNullSpace().getVecs()) == G.shape[1]
        solver.set_operator(sp.csr_matrix(A + 0 * sp.eye(A.shape[0])))  # a new pattern
        solver.solve(b)
    assert built == [rows.shape]


def test_a_wrong_sparse_null_space_is_refused(incompatible):
    A, b, G = incompatible
    shifted = (A + 1e-3 * sp.eye(A.shape[0])).tocsr()  # ε > 0: no kernel
    with pp.KSPSolver({"ksp_type": "cg"}, max_it=10, structure=pp.Structure(nullspace=G)) as s:
        with pytest.raises(InputError, match="not a null space"):
            s.set_operator(shifted)
    dependent = sp.hstack([G, G[:, :1] + G[:, 1:2]]).tocsr()
    with pp.KSPSolver(
        {"ksp_type": "cg"}, max_it=10, structure=pp.Structure(nullspace=dependent)
    ) as s:
        with pytest.raises(InputError, match="linearly independent"):
            s.set_operator(A)
    with pytest.raises(InputError, match="NaN"):
        pp.Structure(nullspace=sp.csr_matrix(np.full((3, 1), np.nan)))
    with pytest.raises(InputError, match="non-zero"):
        pp.Structure(nullspace=sp.csr_matrix((3, 2)))
