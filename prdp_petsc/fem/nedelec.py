"""Nédélec (edge) elements: the discrete gradient, which spans the kernel of curl-curl.

The lowest-order Nédélec elements of scikit-fem on simplices (``ElementTriN1`` in 2D,
``ElementTetN0`` in 3D) have one dof per mesh edge, the tangential integral
``∫_e u·t ds``.  The gradient of a piecewise linear function φ lies in that space,
and its dofs are differences of vertex values: ``(∇φ)_e = ±(φ(b) − φ(a))`` for the
edge from vertex a to vertex b.  The matrix G of these differences is the *discrete
gradient*; as ``curl ∇φ = 0``, ``A G = 0`` for the curl-curl operator
``(curl u, curl v)`` (the ``ε = 0`` case of ``(curl u, curl v) + ε (u, v)``).  Its
columns span the kernel of A on a domain without holes (a domain with holes or
tunnels has harmonic fields besides, which are not gradients).

Without that kernel declared, Krylov methods on curl-curl blow up along it or fail
(``DIVERGED_DTOL``, ``DIVERGED_INDEFINITE_MAT``); declared, a solve returns the
solution orthogonal to every gradient::

    G = discrete_gradient(basis, D.interior)
    solver = KSPSolver(options, max_it=..., structure=Structure(nullspace=G))

`prdp_petsc.KSPSolver` takes G as it is, sparse, and projects with it at the cost of
one sparse solve with ``GᵀG`` (see `prdp_petsc.core.nullspace`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ..errors import InputError

if TYPE_CHECKING:
    import skfem

__all__ = ["discrete_gradient"]


def _edges(basis: skfem.CellBasis) -> tuple[np.ndarray, ...]:
    """``(dof, low, high, sign)`` of every mesh edge of a lowest-order Nédélec basis: its
    dof, its vertices (lower index first), and the sign s of its basis function's
    tangential integral from low to high (±1), so that ``(∇φ)_e = s (φ(high) − φ(low))``.
    """
    import skfem

    elem, mesh = basis.elem, basis.mesh
    dim = mesh.dim()
    counts = (elem.nodal_dofs, elem.facet_dofs, getattr(elem, "edge_dofs", 0), elem.interior_dofs)
    wanted = (0, 1, 0, 0) if dim == 2 else (0, 0, 1, 0)
    simplex = elem.refdom in (skfem.refdom.RefTri, skfem.refdom.RefTet)
    if not isinstance(elem, skfem.element.ElementHcurl) or tuple(counts) != wanted or not simplex:
        raise InputError(
            "the discrete gradient needs a lowest-order Nédélec basis on simplices (one dof "
            f"per edge: ElementTriN1, ElementTetN0); got {type(elem).__name__}"
        )
    if dim == 2:
        edges, local_edges, elem_edges = mesh.facets, elem.refdom.facets, mesh.t2f
        dof = basis.dofs.facet_dofs[0]
    else:
        edges, local_edges, elem_edges = mesh.edges, elem.refdom.edges, mesh.t2e
        dof = basis.dofs.edge_dofs[0]
    # the tangential integral of each reference basis function along its edge: ±1,
    # the sign the element's orientation (lower global vertex first) carries to the mesh
    corners = elem.refdom.p
    sign = np.zeros(edges.shape[1])
    for i, (a, b) in enumerate(local_edges):
        phi, _ = elem.lbasis((corners[:, a] + corners[:, b])[:, None] / 2, i)
        value = float(phi[:, 0] @ (corners[:, b] - corners[:, a]))
        if not np.isclose(abs(value), 1.0, rtol=0, atol=1e-12):
            raise InputError(
                f"{type(elem).__name__}: its basis function {i} has tangential integral "
                f"{value:g} along its edge, not ±1; not a lowest-order Nédélec element"
            )
        seen = sign[elem_edges[i]]
        if np.any((seen != 0) & (seen != value)):
            raise InputError(
                f"{type(elem).__name__}: neighbouring elements orient an edge differently"
            )
        sign[elem_edges[i]] = value
    return dof, edges.min(axis=0), edges.max(axis=0), sign


def _kept(n: int, dofs) -> np.ndarray:
    if dofs is None:
        return np.arange(n)
    kept = np.asarray(dofs)
    if kept.ndim != 1 or not np.issubdtype(kept.dtype, np.integer):
        raise InputError("dofs must be a 1-d array of dof indices, e.g. Dirichlet(...).interior")
    if kept.size and (kept.min() < 0 or kept.max() >= n):
        raise InputError(f"dofs must lie in [0, {n}), the dofs of the basis")
    if np.unique(kept).size != kept.size:
        raise InputError("dofs must not repeat a dof")
    return kept


def discrete_gradient(basis: skfem.CellBasis, dofs: np.ndarray | None = None) -> sp.csr_matrix:
    """The gradients of the vertex functions on a lowest-order Nédélec basis, sparse.

    Parameters
    ----------
    basis : skfem.CellBasis
        A basis of ``ElementTriN1`` or ``ElementTetN0`` (one dof per edge).  (scikit-fem's
        ``ElementQuadN1`` is refused: the gradients of ``ElementQuad1`` functions do not
        lie in the space it assembles, ``A ∇φ ≠ 0``.)
    dofs : array of int, optional
        The dofs the operator keeps, in its order: ``Dirichlet(A, fixed).interior``
        for an operator after elimination (``u × n = 0`` on the boundary); all dofs
        by default.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (len(dofs), m)
        G with ``G[e, high] = s``, ``G[e, low] = −s`` (s = ±1, the orientation of the
        basis function of edge e), so that ``G φ`` are the Nédélec dofs of ``∇φ`` for
        the piecewise linear φ with vertex values φ: ``A @ G = 0`` for curl-curl.  Its
        columns are linearly independent, as a null space needs: one per vertex whose
        gradient vanishes on the removed dofs (the vertices no removed edge touches);
        one per connected set of the other vertices (joined by removed edges), the
        gradient of the function that is 1 on that set; and in every connected part
        of the mesh one column fewer, since a constant has no gradient (the largest
        set's, else the last vertex's).  Pass it as ``Structure(nullspace=G)``.

    Notes
    -----
    The sign of every edge comes from the element's own basis functions (their
    tangential integral along the reference edges, carried to the mesh by
    scikit-fem's orientation, lower vertex index first), so no convention is
    assumed.  On a domain with holes (2D) or tunnels (3D), curl-curl has harmonic
    fields in its kernel besides the gradients; declare them too.
    """
    from scipy.sparse.csgraph import connected_components

    dof, low, high, sign = _edges(basis)
    n_vertices = basis.mesh.p.shape[1]
    kept = _kept(basis.N, dofs)
    full = sp.csr_matrix(
        (np.concatenate([-sign, sign]), (np.tile(dof, 2), np.concatenate([low, high]))),
        shape=(basis.N, n_vertices),
    )
    removed = np.ones(basis.N, dtype=bool)
    removed[kept] = False
    cut = removed[dof]  # the edges whose dof the operator dropped
    graph = sp.coo_matrix((np.ones(cut.sum()), (low[cut], high[cut])), (n_vertices,) * 2)
    _, group = connected_components(graph, directed=False)
    touched = np.zeros(n_vertices, dtype=bool)
    touched[low[cut]] = touched[high[cut]] = True
    # column label: a free vertex its own, a touched vertex its set's (joined by cut edges)
    label = np.where(touched, n_vertices + group, np.arange(n_vertices))
    mesh_graph = sp.coo_matrix((np.ones(low.size), (low, high)), (n_vertices,) * 2)
    _, part = connected_components(mesh_graph, directed=False)
    dropped = [_dropped(label[part == p], n_vertices) for p in np.unique(part)]
    columns = np.setdiff1d(np.unique(label), dropped)
    index = np.full(2 * n_vertices, -1)
    index[columns] = np.arange(columns.size)
    keep = index[label] >= 0
    combine = sp.csr_matrix(
        (np.ones(keep.sum()), (np.flatnonzero(keep), index[label[keep]])),
        shape=(n_vertices, columns.size),
    )
    G = (full[kept] @ combine).tocsr()
    G.eliminate_zeros()  # an edge inside a set: its two ends cancel
    return G


def _dropped(labels: np.ndarray, n_vertices: int) -> int:
    """The column left out of one connected part of the mesh (`labels`: the column label
    of each of its vertices): its largest set of touched vertices, else its last vertex."""
    values, sizes = np.unique(labels, return_counts=True)
    sets = values >= n_vertices
    if sets.any():
        return int(values[sets][np.argmax(sizes[sets])])
    return int(values.max())
