"""Partitioning and renumbering of a mesh for the owned layout, on one process.

`partition_elements` and the pieces `PartitionedMesh.distribute` sends are checked
without MPI: every vertex and element is owned once, in contiguous blocks, and the
rows each piece assembles alone are exactly the whole mesh's rows (the ghost layer
is complete).  The owned-layout bridge on one process equals the serial one.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import skfem
import torch
from petsc4py import PETSc

import prdp_petsc as pp
from prdp_petsc.fem.distributed import DistributedParametricMatrix
from prdp_petsc.fem.partition import (
    PartitionedMesh,
    _pieces,
    element_graph,
    partition_elements,
)


def _tets():
    return pp.load_mesh("box3d")


def test_element_graph_joins_elements_that_share_a_facet():
    mesh = skfem.MeshTri().refined(3)
    indptr, indices = element_graph(mesh)
    graph = sp.csr_matrix((np.ones(len(indices)), indices, indptr)).toarray()
    expected = np.zeros_like(graph)
    pairs = mesh.f2t[:, mesh.f2t[1] >= 0]  # interior facets: their two elements
    expected[pairs[0], pairs[1]] = expected[pairs[1], pairs[0]] = 1
    assert np.array_equal(graph, expected)


@pytest.mark.parametrize("method", ["metis", "rcb"])
@pytest.mark.parametrize("parts", [2, 3, 5])
def test_partition_elements_is_balanced_and_deterministic(method, parts):
    mesh = _tets()
    part = partition_elements(mesh, parts, method=method)
    sizes = np.bincount(part, minlength=parts)
    assert len(sizes) == parts and sizes.sum() == mesh.nelements
    # rcb: sizes differ by at most one per level; METIS: its default 3 % imbalance
    assert sizes.max() <= 1.031 * mesh.nelements / parts + 1
    assert np.array_equal(part, partition_elements(mesh, parts, method=method))


def test_metis_cuts_fewer_facets_than_a_random_split():
    mesh = _tets()
    indptr, indices = element_graph(mesh)
    rows = np.repeat(np.arange(mesh.nelements), np.diff(indptr))

    def cut(part):
        return int(np.sum(part[rows] != part[indices])) // 2

    random = np.random.default_rng(0).integers(0, 2, mesh.nelements)
    assert cut(partition_elements(mesh, 2)) < 0.1 * cut(random)


def test_partition_elements_refuses_bad_settings():
    mesh = skfem.MeshTri()
    with pytest.raises(pp.InputError, match="method"):
        partition_elements(mesh, 2, method="scotch")
    with pytest.raises(pp.InputError, match="cannot split"):
        partition_elements(mesh, 3)


@pytest.mark.parametrize("size", [2, 3])
def test_pieces_own_every_vertex_once_and_assemble_complete_rows(size):
    """Each piece's owned rows, assembled on its local mesh alone, equal the whole
    mesh's rows under the new numbering (so the ghost layer holds every element
    around an owned vertex)."""
    mesh = _tets()
    part = partition_elements(mesh, size)
    pieces = list(_pieces(mesh, part, size))
    theta = 1.0 + np.random.default_rng(1).random(mesh.nelements)
    whole = pp.diffusion_operator(skfem.Basis(mesh, skfem.ElementTetP1())).matrix(theta)

    vertex_blocks = [p["vertex_ids"][: p["owned_vertices"]] for p in pieces]
    element_blocks = [p["element_ids"][: p["owned_elements"]] for p in pieces]
    order = np.concatenate(vertex_blocks)  # new number -> original vertex
    assert np.array_equal(np.sort(order), np.arange(mesh.nvertices))
    assert np.array_equal(np.sort(np.concatenate(element_blocks)), np.arange(mesh.nelements))
    assert all(np.all(part[e] == r) for r, e in enumerate(element_blocks))
    new = np.empty(mesh.nvertices, dtype=np.int64)
    new[order] = np.arange(mesh.nvertices)
    starts = np.cumsum([0] + [p["owned_vertices"] for p in pieces])
    for rank, piece in enumerate(pieces):
        # ghosts: global numbers owned elsewhere, sorted; owned: this rank's block
        ghosts = piece["ghost_vertices"]
        assert np.all(np.diff(ghosts) > 0)
        assert not np.any((ghosts >= starts[rank]) & (ghosts < starts[rank + 1]))
        local = piece["type"](piece["p"], piece["t"])
        A = pp.diffusion_operator(skfem.Basis(local, skfem.ElementTetP1()))
        rows = A.matrix(theta[piece["element_ids"]])[: piece["owned_vertices"]].tocoo()
        global_cols = new[piece["vertex_ids"][rows.col]]
        got = sp.csr_matrix(
            (rows.data, (rows.row, global_cols)), shape=(piece["owned_vertices"], mesh.nvertices)
        )
        expected = whole[piece["vertex_ids"][: piece["owned_vertices"]]][:, order]
        assert abs(got - expected).max() <= 1e-13 * abs(whole).max()


def test_owned_layout_on_one_process_equals_the_serial_bridge():
    """On ``COMM_SELF`` the owned layout is one piece: solve, ∂L/∂f, ∂L/∂θ, ∂L/∂g of the
    serial `ParametricMatrix` path, in the partition's numbering."""
    mesh = _tets()
    piece = PartitionedMesh.distribute(mesh, PETSc.COMM_SELF)
    assert piece.owned_vertices == mesh.nvertices == piece.vertices.local_size
    local = skfem.Basis(piece.mesh, skfem.ElementTetP1())
    A = DistributedParametricMatrix.from_local(pp.diffusion_operator(local), piece)
    bc = pp.Dirichlet(A, piece.boundary_vertices())
    serial = pp.Dirichlet(pp.diffusion_operator(local), local.get_dofs())
    assert np.array_equal(serial.boundary, bc.boundary)
    rng = np.random.default_rng(2)
    inputs = (1.0 + rng.random(mesh.nelements), rng.standard_normal(mesh.nvertices),
              rng.standard_normal(len(bc.boundary)))  # fmt: skip
    weights = torch.from_numpy(rng.standard_normal(mesh.nvertices))
    results = []
    for dirichlet, prefix in ((serial, "part_ser_"), (bc, "part_own_")):
        theta, f, g = (torch.tensor(a, requires_grad=True) for a in inputs)
        with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, prefix=prefix, max_it=12) as s:
            u = dirichlet.solve(f, g, s, theta=theta)
            (u * weights).sum().backward()
        results.append([u.detach().numpy(), f.grad.numpy(), theta.grad.numpy(), g.grad.numpy()])
    for got, expected in zip(results[1], results[0], strict=True):
        assert np.abs(got - expected).max() <= 1e-12 * np.abs(expected).max()
    piece.destroy()


def test_the_owned_layout_refuses_vector_fields_clearly():
    """An elasticity operator (3 unknowns per vertex) on a partitioned mesh: refused,
    saying what the owned layout holds and what to use instead."""
    mesh = _tets()
    piece = PartitionedMesh.distribute(mesh, PETSc.COMM_SELF)
    vector = skfem.Basis(piece.mesh, skfem.ElementVector(skfem.ElementTetP1()))
    with pytest.raises(pp.InputError, match="3 unknowns per vertex.*replicated layout"):
        DistributedParametricMatrix.from_local(pp.elasticity_operator(vector), piece)
