"""Vector-valued scikit-fem bases: rigid-body modes and the block size of their dofs.

Linear elasticity on ``Basis(mesh, ElementVector(ElementTriP1()))`` (or
``ElementTetP1``, ``ElementQuad1``, ``ElementHex1``, P2/Q2, ...) has the rigid-body
motions as kernel when no Dirichlet condition holds the body: 3 in 2D (two
translations, one rotation), 6 in 3D.  Clamped, they are no longer null vectors,
but A still maps them to little, and algebraic multigrid converges at a rate
independent of the mesh only if its coarse spaces reproduce them: give them to
`prdp_petsc.KSPSolver` as ``Structure(near_nullspace=...)`` (``MatSetNearNullSpace``),
or as ``Structure(nullspace=...)`` for the floating body itself.

`rigid_body_modes` computes them from the dof locations (``basis.doflocs``) and
the component of each dof (``basis.split_indices()``), so it needs no assumption
about the numbering; `block_size` says whether the numbering is the one a PETSc
block size describes.  scikit-fem's ``ElementVector`` numbers the d components of
each dof location consecutively (node by node: ``u_x, u_y, u_z`` of vertex 0,
then of vertex 1, ..., then edge, facet and interior dofs the same way), so the
block size of its operator is d, and stays d after a Dirichlet elimination that
keeps either all or none of each node's components (a clamped boundary, not a
roller that fixes one component).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    import skfem

__all__ = ["block_size", "rigid_body_modes"]


def _components(basis: skfem.CellBasis) -> tuple[np.ndarray, int]:
    """The component of every dof of a vector basis, and the dimension d."""
    import skfem

    if not isinstance(basis.elem, skfem.ElementVector):
        raise InputError(
            f"a vector basis is needed, e.g. Basis(mesh, ElementVector(ElementTriP1())); "
            f"got {type(basis.elem).__name__}"
        )
    dim = basis.mesh.dim()
    parts = basis.split_indices()
    if len(parts) != dim:
        raise InputError(
            f"the basis has {len(parts)} components on a {dim}-dimensional mesh; rigid-body "
            "modes need one component per space dimension"
        )
    if any(name != "u" for name in basis.elem.elem.dofnames):
        raise InputError(
            f"rigid-body modes need point values at each dof ({type(basis.elem.elem).__name__} "
            f"has dofs {basis.elem.elem.dofnames}): a Lagrange element such as ElementTriP1"
        )
    component = np.empty(basis.N, dtype=np.int64)
    for c, idx in enumerate(parts):
        component[idx] = c
    return component, dim


def _kept(basis: skfem.CellBasis, dofs) -> np.ndarray:
    if dofs is None:
        return np.arange(basis.N)
    kept = np.asarray(dofs)
    if kept.ndim != 1 or not np.issubdtype(kept.dtype, np.integer):
        raise InputError("dofs must be a 1-d array of dof indices, e.g. Dirichlet(...).interior")
    if kept.size and (kept.min() < 0 or kept.max() >= basis.N):
        raise InputError(f"dofs must lie in [0, {basis.N}), the dofs of the basis")
    return kept


def rigid_body_modes(basis: skfem.CellBasis, dofs: np.ndarray | None = None) -> np.ndarray:
    """The rigid-body motions of a vector basis: 3 in 2D, 6 in 3D, on the kept dofs.

    Parameters
    ----------
    basis : skfem.CellBasis
        A basis of ``ElementVector`` of a Lagrange element with one component per
        space dimension (``ElementVector(ElementTriP1())``, ``ElementHex1``, P2, ...).
    dofs : array of int, optional
        The dofs the operator keeps, in its order: ``Dirichlet(A, fixed).interior``
        for an operator after elimination; all dofs by default.

    Returns
    -------
    ndarray, shape (3, len(dofs)) in 2D or (6, len(dofs)) in 3D
        Translations along each axis, then rotations about the centroid of the dof
        locations (2D: ``(-y, x)``; 3D: about x ``(0, -z, y)``, y ``(z, 0, -x)``, z
        ``(-y, x, 0)``), each scaled to unit length.  Pass them to
        ``Structure(near_nullspace=...)`` with ``block_size=basis.mesh.dim()``
        (`block_size` checks that), or as ``nullspace=`` for a body no
        Dirichlet condition holds (`KSPSolver` orthonormalises either).

    Notes
    -----
    The modes are computed from ``basis.doflocs`` and the component of each dof
    (``basis.split_indices()``), whatever the numbering; PETSc's
    ``MatNullSpaceCreateRigidBody`` needs coordinates in a block-interleaved
    vector instead.
    """
    component, dim = _components(basis)
    kept = _kept(basis, dofs)
    x = basis.doflocs - basis.doflocs.mean(axis=1, keepdims=True)
    rotations = [(0, 1)] if dim == 2 else [(1, 2), (2, 0), (0, 1)]  # about z; x, y, z
    modes = np.zeros((dim + len(rotations), basis.N))
    for c in range(dim):
        modes[c] = component == c
    for k, (i, j) in enumerate(rotations):  # rotation in the (i, j) plane: u_i = -x_j, u_j = x_i
        mode = modes[dim + k]
        mode[component == i] = -x[j, component == i]
        mode[component == j] = x[i, component == j]
    modes = modes[:, kept]
    return modes / np.linalg.norm(modes, axis=1, keepdims=True)


def block_size(basis: skfem.CellBasis, dofs: np.ndarray | None = None) -> int:
    """The block size of the kept dofs of a vector basis: d if node-by-node, else 1.

    d (the mesh dimension) when every run of d consecutive kept dofs holds the
    components 0, ..., d−1 at one location (scikit-fem's ``ElementVector``
    numbering, minus whole nodes), else 1: a Dirichlet condition on one component
    of a node (a roller) breaks the blocks, and a wrong block size would make GAMG
    aggregate dofs of different nodes as one.
    """
    component, dim = _components(basis)
    kept = _kept(basis, dofs)
    if kept.size % dim:
        return 1
    blocks = kept.reshape(-1, dim)
    same_place = np.all(basis.doflocs[:, blocks] == basis.doflocs[:, blocks[:, :1]])
    in_order = np.all(component[blocks] == np.arange(dim))
    return dim if same_place and in_order else 1
