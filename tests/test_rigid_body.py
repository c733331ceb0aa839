"""Rigid-body modes and the block size of scikit-fem vector bases (`prdp_petsc.fem.vector`).

`rigid_body_modes` must span the kernel of free elasticity (2D: 3, 3D: 6) on the
dofs the operator keeps; `block_size` must say d exactly when scikit-fem numbers
the kept dofs node by node.
"""

import numpy as np
import pytest
import skfem
from _vector import clamped, elasticity

import prdp_petsc as pp
from prdp_petsc.errors import InputError
from prdp_petsc.fem.vector import block_size


# -- the modes and the numbering -----------------------------------------------------------
@pytest.mark.parametrize(
    ("dim", "element", "count"),
    [
        (2, skfem.ElementTriP1, 3),
        (2, skfem.ElementTriP2, 3),
        (2, skfem.ElementQuad1, 3),
        (3, skfem.ElementHex1, 6),
        (3, skfem.ElementTetP1, 6),
    ],
)
def test_rigid_body_modes_span_the_kernel_of_free_elasticity(dim, element, count):
    mesh = {
        (2, skfem.ElementQuad1): skfem.MeshQuad().refined(2),
        (3, skfem.ElementHex1): skfem.MeshHex().refined(1),
        (3, skfem.ElementTetP1): skfem.MeshTet().refined(1),
    }.get((dim, element), skfem.MeshTri().refined(2))
    basis = skfem.Basis(mesh, skfem.ElementVector(element()))
    M = pp.elasticity_operator(basis).matrix(np.ones(mesh.nelements)).toarray()
    modes = pp.rigid_body_modes(basis)
    assert modes.shape == (count, basis.N)
    scale = np.abs(M).sum(axis=1).max()
    assert np.abs(M @ modes.T).max() <= 1e-12 * scale
    # the kernel is exactly this big: the next singular value is far from zero
    singular_values = np.linalg.svd(M, compute_uv=False)
    assert singular_values[-count - 1] > 1e-6 * singular_values[0]
    assert np.linalg.matrix_rank(modes) == count
    np.testing.assert_allclose(np.linalg.norm(modes, axis=1), 1.0)


def test_modes_on_the_kept_dofs_are_the_rows_of_the_full_ones():
    basis, A = elasticity(n=3)
    bc = clamped(basis, A)
    full, kept = pp.rigid_body_modes(basis), pp.rigid_body_modes(basis, bc.interior)
    assert kept.shape == (3, len(bc.interior))
    for f, k in zip(full, kept, strict=True):  # the same vector up to its scale
        np.testing.assert_allclose(k * np.linalg.norm(f[bc.interior]), f[bc.interior], atol=1e-14)


def test_scikit_fem_numbers_vector_dofs_node_by_node():
    """What `block_size` relies on: components of a node are consecutive (ElementVector)."""
    for element, dim in ((skfem.ElementTriP2, 2), (skfem.ElementHex1, 3)):
        mesh = skfem.MeshHex().refined(1) if dim == 3 else skfem.MeshTri().refined(1)
        basis = skfem.Basis(mesh, skfem.ElementVector(element()))
        for c, idx in enumerate(basis.split_indices()):
            np.testing.assert_array_equal(idx, np.arange(c, basis.N, dim))
        assert block_size(basis) == dim


def test_block_size_is_d_for_whole_nodes_and_1_for_a_roller():
    basis, A = elasticity(n=3)
    assert block_size(basis, clamped(basis, A).interior) == 2
    left = np.isclose(basis.doflocs[0], 0.0)
    roller = np.flatnonzero(left & np.isin(np.arange(basis.N), basis.split_indices()[0]))
    keep = np.setdiff1d(np.arange(basis.N), roller)  # u_x fixed, u_y free on x = 0
    assert block_size(basis, keep) == 1


def test_rigid_body_modes_refuse_what_they_cannot_describe():
    scalar = skfem.Basis(skfem.MeshTri(), skfem.ElementTriP1())
    with pytest.raises(InputError, match="vector basis"):
        pp.rigid_body_modes(scalar)
    three = skfem.Basis(skfem.MeshTri(), skfem.ElementVector(skfem.ElementTriP1(), 3))
    with pytest.raises(InputError, match="one component per space dimension"):
        pp.rigid_body_modes(three)
    basis, _ = elasticity(n=2)
    with pytest.raises(InputError, match="lie in"):
        pp.rigid_body_modes(basis, np.array([basis.N]))
