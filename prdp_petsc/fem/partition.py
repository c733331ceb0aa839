"""A mesh split over MPI ranks: owned elements and vertices, a ghost layer, contiguous numbering.

`PartitionedMesh.distribute` takes a scikit-fem mesh on one rank (the root), splits
its elements into one part per rank (`partition_elements`: METIS on the element
graph, or recursive coordinate bisection), and sends every rank its piece:

* **Elements.**  Rank r owns the elements of part r.  Its local mesh holds them
  and, as a ghost layer, every other element that touches a vertex it owns, so
  that scikit-fem assembles the *complete* rows of its own vertices on this
  rank alone.
* **Vertices.**  A vertex is owned by the lowest rank among the parts of the
  elements around it.
* **Numbering.**  Vertices and elements are renumbered so that each rank owns a
  contiguous block, in rank order (PETSc's convention), keeping the original
  order within a rank.  A local mesh lists its owned vertices (elements) first,
  in global order, then its ghosts, in global order: the layout of
  `prdp_petsc.core.ghosts.GhostedSpace`, whose exchanges fill ghost values from
  their owners.

Only the root ever holds the whole mesh: it reads or builds it, partitions it
and sends the pieces (``mpi4py`` point-to-point messages); the other ranks
receive their piece and never see the rest.  The root's peak memory is the
whole mesh plus the partitioner's graph (at start-up; assembly, which comes after,
costs every rank more); every other rank holds its piece only.  A mesh too large
for one node would need a parallel reader and partitioner (ParMETIS, PETSc's
DMPlex), which this module does not provide.

Vertex degrees of freedom only: P1 (or Q1) unknowns, whose dofs are the mesh
vertices, and coefficients per element (P0) or per vertex (P1).  Named
boundaries of the original mesh are not carried over; `boundary_vertices` finds
the mesh boundary on every rank alone (see there).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from ..core.ghosts import GhostedSpace
from ..core.parallel import as_petsc_comm
from ..errors import InputError

if TYPE_CHECKING:
    import skfem
    from petsc4py import PETSc

__all__ = ["METHODS", "PartitionedMesh", "element_graph", "partition_elements"]

logger = logging.getLogger(__name__)

#: The element partitioners `partition_elements` knows.
METHODS = ("metis", "rcb")


def element_graph(mesh: skfem.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """CSR adjacency ``(indptr, indices)`` of the elements: two elements are neighbours
    when they share a facet (an edge of a triangle, a face of a tetrahedron, ...).

    Built by sorting every element's facets by their vertices (``mesh.t`` and the
    element's facet list ``mesh.refdom.facets``), without scikit-fem's facet
    numbering, so it costs a few sorts of ``nelements × facets per element`` keys.
    """
    import scipy.sparse as sp

    t = mesh.t
    facets = np.asarray(mesh.refdom.facets)  # (facets per element, vertices per facet)
    local = np.sort(t[facets], axis=1)  # (facets per element, vertices per facet, nelements)
    keys = local.transpose(1, 0, 2).reshape(facets.shape[1], -1)
    owner = np.tile(np.arange(mesh.nelements), facets.shape[0])
    order = np.lexsort(keys[::-1])
    keys = keys[:, order]
    same = np.flatnonzero(np.all(keys[:, 1:] == keys[:, :-1], axis=0))
    a, b = owner[order[same]], owner[order[same + 1]]
    n = mesh.nelements
    graph = sp.csr_matrix(
        (np.ones(2 * len(a), dtype=np.int8), (np.r_[a, b], np.r_[b, a])), shape=(n, n)
    )
    return graph.indptr, graph.indices


def partition_elements(mesh: skfem.Mesh, parts: int, *, method: str = "metis") -> np.ndarray:
    """The part (0 ... parts − 1) of every element of `mesh`.

    Parameters
    ----------
    mesh : skfem.Mesh
    parts : int
        Number of parts (ranks), >= 1.
    method : {"metis", "rcb"}
        ``"metis"``: METIS (``pymetis.part_graph``, the ``mpi`` extra) on
        `element_graph`, minimising the facets cut between parts with balanced
        part sizes.  ``"rcb"``: recursive coordinate bisection of the element
        centroids (no dependency; cuts are planes, so parts of an unstructured or
        curved domain can be less compact).

    Returns
    -------
    ndarray of int64, shape (nelements,)
        Every part is non-empty when ``parts <= nelements``.

    Notes
    -----
    Deterministic: the same mesh gives the same parts (METIS is run with its
    default seed).
    """
    if parts < 1:
        raise InputError(f"parts must be >= 1, got {parts}")
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if parts > mesh.nelements:
        raise InputError(f"cannot split {mesh.nelements} elements into {parts} parts")
    if parts == 1:
        return np.zeros(mesh.nelements, dtype=np.int64)
    if method == "rcb":
        return _bisect(mesh.p[:, mesh.t].mean(axis=1), parts)
    import pymetis

    indptr, indices = element_graph(mesh)
    _, membership = pymetis.part_graph(parts, adjacency=pymetis.CSRAdjacency(indptr, indices))
    part = np.asarray(membership, dtype=np.int64)
    if len(np.unique(part)) != parts:  # METIS may leave a part empty on tiny meshes
        logger.warning("METIS left a part empty; using coordinate bisection instead")
        return _bisect(mesh.p[:, mesh.t].mean(axis=1), parts)
    return part


def _bisect(points: np.ndarray, parts: int) -> np.ndarray:
    """Recursive coordinate bisection of `points` (dim, n) into `parts` parts of
    sizes proportional to the number of parts on each side."""
    out = np.empty(points.shape[1], dtype=np.int64)

    def split(index: np.ndarray, first: int, count: int) -> None:
        if count == 1:
            out[index] = first
            return
        left = count // 2
        coords = points[:, index]
        axis = int(np.argmax(coords.max(axis=1) - coords.min(axis=1)))
        order = index[np.argsort(coords[axis], kind="stable")]
        cut = len(index) * left // count
        split(order[:cut], first, left)
        split(order[cut:], first + left, count - left)

    split(np.arange(points.shape[1]), 0, parts)
    return out


class PartitionedMesh:
    """This rank's piece of a mesh split over the ranks (see the module notes).

    Made by `distribute` (collective); not constructed directly.

    Attributes
    ----------
    mesh : skfem.Mesh
        The local mesh: owned elements then ghost elements, its vertices owned
        ones first.  Assemble on it with any scikit-fem basis whose dofs are
        the vertices (``skfem.Basis(part.mesh, skfem.ElementTetP1())``).
    comm : PETSc.Comm
    vertices, elements : GhostedSpace
        The global vertex and element numbering: this rank's owned block and its
        ghosts, in the local mesh's order (``vertices.global_ids[i]`` is the global
        number of local vertex i).
    owned_vertices, owned_elements : int
        How many of the local vertices (elements) this rank owns: the first ones.
    original_vertices, original_elements : ndarray
        Index in the mesh given to `distribute` of every local vertex (element).
    vertex_data, element_data : dict of ndarray
        The arrays given to `distribute` as `vertex_data` (`element_data`), their
        last axis cut to the local vertices (elements), in the local order.
    """

    def __init__(self, mesh, comm, vertices: GhostedSpace, elements: GhostedSpace, piece: dict):
        self.mesh = mesh
        self.comm = comm
        self.vertices = vertices
        self.elements = elements
        self.owned_vertices = vertices.owned
        self.owned_elements = elements.owned
        self.original_vertices = piece["vertex_ids"]
        self.original_elements = piece["element_ids"]
        self.vertex_data = piece["vertex_data"]
        self.element_data = piece["element_data"]

    @classmethod
    def distribute(
        cls,
        mesh: skfem.Mesh | None,
        comm: PETSc.Comm | None = None,
        *,
        method: str = "metis",
        root: int = 0,
        vertex_data: dict | None = None,
        element_data: dict | None = None,
    ) -> PartitionedMesh:
        """Split `mesh` (given on rank `root`) into one piece per rank of `comm`.

        Parameters
        ----------
        mesh : skfem.Mesh or None
            The whole mesh on rank `root`; ignored (pass None) on the others.
            Any scikit-fem mesh type: the local pieces are of the same type.
        comm : PETSc.Comm or mpi4py communicator, optional
            Default: `prdp_petsc.core.parallel.default_comm` (``COMM_WORLD`` under
            ``--parallel domain``).
        method : {"metis", "rcb"}
            Element partitioner (`partition_elements`).
        root : int
            The rank that holds `mesh`.
        vertex_data, element_data : dict of ndarray, optional
            Arrays defined on the whole mesh (on `root`), last axis one entry per
            vertex (element) of `mesh`, e.g. observations or material labels: every
            rank receives the entries of its local vertices (elements), in
            ``part.vertex_data`` (``part.element_data``).  Data made this way does
            not depend on the number of ranks.

        Returns
        -------
        PartitionedMesh
            This rank's piece (collective: every rank calls it).
        """
        comm = as_petsc_comm(comm)
        size = comm.getSize()
        data = (vertex_data or {}, element_data or {})
        if size == 1:
            pieces = _pieces(mesh, np.zeros(mesh.nelements, dtype=np.int64), 1, data)
            return cls._from_piece(next(pieces), comm)
        world = comm.tompi4py()
        if comm.getRank() == root:
            if mesh is None:
                raise InputError("PartitionedMesh.distribute: the root rank needs the mesh")
            mine = None
            part = partition_elements(mesh, size, method=method)
            for rank, piece in enumerate(_pieces(mesh, part, size, data)):
                if rank == root:
                    mine = piece
                else:
                    world.send(piece, dest=rank, tag=71)
        else:
            mine = world.recv(source=root, tag=71)
        return cls._from_piece(mine, comm)

    @classmethod
    def _from_piece(cls, piece: dict, comm) -> PartitionedMesh:
        mesh = piece["type"](piece["p"], piece["t"])
        vertices = GhostedSpace(piece["owned_vertices"], piece["ghost_vertices"], comm)
        elements = GhostedSpace(piece["owned_elements"], piece["ghost_elements"], comm)
        return cls(mesh, comm, vertices, elements, piece)

    def boundary_vertices(self) -> np.ndarray:
        """Global numbers of the owned vertices on the boundary of the whole mesh.

        Exact without communication: every element around an owned vertex is in
        the local mesh, so a facet through an owned vertex lies on the local
        mesh's boundary exactly when it lies on the whole mesh's.
        """
        local = self.mesh.boundary_nodes()
        local = local[local < self.owned_vertices]
        return np.sort(self.vertices.global_ids[local]).astype(np.int64)

    def owned(self, local_values: np.ndarray, where: str = "vertices") -> np.ndarray:
        """The owned entries (the first ones) of per-vertex or per-element local values."""
        count = self.owned_vertices if where == "vertices" else self.owned_elements
        return np.asarray(local_values)[..., :count]

    def destroy(self) -> None:
        """Free the PETSc Vecs of the two ghosted spaces (collective)."""
        self.vertices.destroy()
        self.elements.destroy()


def _pieces(mesh, part: np.ndarray, size: int, data: tuple = ({}, {})):
    """Yield every rank's piece, in rank order (on the root only); `data` holds the
    per-vertex and per-element arrays to cut along."""
    t = mesh.t
    nv, ne = mesh.nvertices, mesh.nelements
    owner = np.full(nv, size, dtype=np.int64)  # a vertex: the lowest part around it
    np.minimum.at(owner, t.ravel(), np.tile(part, t.shape[0]))
    new_vertex = np.empty(nv, dtype=np.int64)
    new_vertex[np.lexsort((np.arange(nv), owner))] = np.arange(nv)
    new_element = np.empty(ne, dtype=np.int64)
    new_element[np.lexsort((np.arange(ne), part))] = np.arange(ne)
    for rank in range(size):
        owned_e = part == rank
        touching = np.any(owner[t] == rank, axis=0)
        ghost_e = np.flatnonzero(touching & ~owned_e)
        ghost_e = ghost_e[np.argsort(new_element[ghost_e])]
        elements = np.concatenate([np.flatnonzero(owned_e), ghost_e])
        used = np.unique(t[:, elements])
        mine = used[owner[used] == rank]
        ghost_v = used[owner[used] != rank]
        ghost_v = ghost_v[np.argsort(new_vertex[ghost_v])]
        vertices = np.concatenate([mine, ghost_v])  # owned: increasing = global order
        local_of = np.empty(nv, dtype=np.int64)
        local_of[vertices] = np.arange(len(vertices))
        yield {
            "type": type(mesh),
            "p": np.ascontiguousarray(mesh.p[:, vertices]),
            "t": np.ascontiguousarray(local_of[t[:, elements]]),
            "owned_vertices": len(mine),
            "ghost_vertices": new_vertex[ghost_v],
            "owned_elements": int(owned_e.sum()),
            "ghost_elements": new_element[ghost_e],
            "vertex_ids": vertices,
            "element_ids": elements,
            "vertex_data": {k: np.asarray(v)[..., vertices] for k, v in data[0].items()},
            "element_data": {k: np.asarray(v)[..., elements] for k, v in data[1].items()},
        }
