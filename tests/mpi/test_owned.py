"""The owned layout: each rank assembles, solves and differentiates its own rows only.

The tetrahedral ``box3d`` mesh is split with METIS (`PartitionedMesh.distribute`),
every rank assembles its piece with scikit-fem, and ``Dirichlet.solve`` runs on
this rank's rows and θ.  The serial run of the same problem on the whole mesh (the
original numbering, ``COMM_SELF``) gives the reference: u, ∂L/∂f, ∂L/∂θ and ∂L/∂g
(the Dirichlet data) must agree to 1e-10 (relative, over all ranks), for capped
and converged solves.  ``make test`` runs this file on 2 and on 3 ranks.
"""

import numpy as np
import pytest
import skfem
import torch
from _mpi import COMM, all_ranks, max_over_ranks
from petsc4py import PETSc
from skfem import BilinearForm

import prdp_petsc as pp
from prdp_petsc.autograd.owned import sum_over_ranks
from prdp_petsc.core.ghosts import GhostedSpace
from prdp_petsc.fem.distributed import DistributedParametricMatrix
from prdp_petsc.fem.partition import PartitionedMesh

CONVERGED = {"max_it": 2000, "rtol": 1e-13, "atol": 1e-50}


@BilinearForm
def _advection(u, v, w):
    return (20.0 * u.grad[0] + 10.0 * u.grad[1] - 5.0 * u.grad[2]) * v


def _g(points):
    """Dirichlet data: a smooth function of the coordinates."""
    return np.sin(3 * points[0]) + points[1] * points[2]


def _operator(basis, advect: bool):
    A = pp.diffusion_operator(basis, "P0")
    return A + _advection.assemble(basis).tocsr() if advect else A


@pytest.fixture(scope="module")
def mesh():
    return pp.load_mesh("box3d")


@pytest.fixture(scope="module")
def part(mesh):
    part = PartitionedMesh.distribute(mesh if COMM.Get_rank() == 0 else None, PETSc.COMM_WORLD)
    yield part
    part.destroy()


def _run(bc, theta, f, g, weights, solver, reduce, x0=None):
    """u and ∂L/∂(f, θ, g) of ``L = Σ weights ⊙ u`` through ``bc.solve``."""
    theta, f, g = (torch.tensor(a, requires_grad=True) for a in (theta, f, g))
    if x0 is None:
        u = bc.solve(f, g, solver, theta=theta)
    else:  # the interior solve from a guess, then lifted
        rhs = bc.rhs(f, g, theta)
        u_i = pp.solve(bc.A_II, rhs, solver, theta=theta, x0=torch.tensor(x0))
        u = bc.expand(u_i, g)
    reduce((u * torch.tensor(weights)).sum()).backward()
    return u.detach().numpy(), f.grad.numpy(), theta.grad.numpy(), g.grad.numpy()


def _sum(t):
    return sum_over_ranks(t, COMM)


def _relative_errors(got, expected) -> list[float]:
    """max |got − expected| over the ranks / max |expected| over the ranks, per pair."""
    return [
        max_over_ranks(np.abs(a - b).max(initial=0.0)) / max_over_ranks(np.abs(b).max(initial=0.0))
        for a, b in zip(got, expected, strict=True)
    ]


@pytest.mark.parametrize(
    "advect, options, settings",
    [
        (False, {"ksp_type": "cg", "pc_type": "jacobi"}, {"max_it": 15}),
        (False, {"ksp_type": "cg", "pc_type": "gamg"}, CONVERGED),
        (True, {"ksp_type": "gmres", "pc_type": "bjacobi"}, CONVERGED),
        (True, {"ksp_type": "gmres", "pc_type": "none"}, {"max_it": 10}),
    ],
    ids=["cg-jacobi-K15", "cg-gamg-converged", "gmres-bjacobi-converged", "gmres-K10"],
)
def test_owned_solve_and_gradients_equal_serial(mesh, part, advect, options, settings):
    basis = skfem.Basis(mesh, skfem.ElementTetP1())
    serial_bc = pp.Dirichlet(_operator(basis, advect), basis.get_dofs())
    local = skfem.Basis(part.mesh, skfem.ElementTetP1())
    A = DistributedParametricMatrix.from_local(_operator(local, advect), part)
    assert A.is_symmetric is not advect
    bc = pp.Dirichlet(A, part.boundary_vertices())

    rng = np.random.default_rng(5)
    theta = 1.0 + rng.random(mesh.nelements)
    f = rng.standard_normal((2, mesh.nvertices))  # a batch of two sharing θ
    weights = rng.standard_normal((2, mesh.nvertices))
    with pp.KSPSolver(options, prefix="own_ser_", **settings) as solver:
        expected = _run(serial_bc, theta, f, _g(mesh.p[:, serial_bc.boundary]), weights, solver,
                        lambda t: t)  # fmt: skip

    vertices = part.original_vertices[: part.owned_vertices]
    elements = part.original_elements[: part.owned_elements]
    g = _g(part.mesh.p[:, bc.boundary])  # owned rows are the local mesh's first vertices
    with pp.KSPSolver(options, prefix="own_dist_", comm=PETSc.COMM_WORLD, **settings) as solver:
        got = _run(bc, theta[elements], f[:, vertices], g, weights[:, vertices], solver,
                   _sum)  # fmt: skip
        mat = solver.mat
        assert mat.getType() == "mpiaij" and mat.getLocalSize()[0] == len(bc.interior)
        assert mat.getSize()[0] == len(serial_bc.interior)
    boundary = np.searchsorted(serial_bc.boundary, part.original_vertices[bc.boundary])
    mine = [expected[0][:, vertices], expected[1][:, vertices], expected[2][elements],
            expected[3][boundary]]  # fmt: skip
    errors = _relative_errors(got, mine)
    assert all_ranks(max(errors) <= 1e-10), errors
    assert all_ranks(np.abs(got[2]).max() > 0 and np.abs(got[3]).max() > 0)  # not vacuous


def test_owned_solve_from_a_guess_equals_serial(mesh, part):
    """``solve(..., x0=)`` in the owned layout: a capped Richardson + Jacobi from a guess."""
    basis = skfem.Basis(mesh, skfem.ElementTetP1())
    serial_bc = pp.Dirichlet(_operator(basis, False), basis.get_dofs())
    local = skfem.Basis(part.mesh, skfem.ElementTetP1())
    bc = pp.Dirichlet(DistributedParametricMatrix.from_local(_operator(local, False), part),
                      part.boundary_vertices())  # fmt: skip
    rng = np.random.default_rng(6)
    theta = 1.0 + rng.random(mesh.nelements)
    f, weights, guess = (rng.standard_normal(mesh.nvertices) for _ in range(3))
    options = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.7}
    with pp.KSPSolver(options, prefix="own_x0s_", max_it=9) as solver:
        expected = _run(serial_bc, theta, f, _g(mesh.p[:, serial_bc.boundary]), weights, solver,
                        lambda t: t, x0=guess[serial_bc.interior])  # fmt: skip
    vertices = part.original_vertices[: part.owned_vertices]
    elements = part.original_elements[: part.owned_elements]
    with pp.KSPSolver(options, prefix="own_x0d_", comm=PETSc.COMM_WORLD, max_it=9) as solver:
        got = _run(bc, theta[elements], f[vertices], _g(part.mesh.p[:, bc.boundary]),
                   weights[vertices], solver, _sum,
                   x0=guess[vertices[bc.interior]])  # fmt: skip
    boundary = np.searchsorted(serial_bc.boundary, part.original_vertices[bc.boundary])
    mine = [expected[0][vertices], expected[1][vertices], expected[2][elements],
            expected[3][boundary]]  # fmt: skip
    assert all_ranks(max(_relative_errors(got, mine)) <= 1e-10)


def test_partition_covers_the_mesh_once(mesh, part):
    """Owned vertices and elements: every one on exactly one rank, in contiguous blocks."""
    vertices = np.concatenate(COMM.allgather(part.original_vertices[: part.owned_vertices]))
    elements = np.concatenate(COMM.allgather(part.original_elements[: part.owned_elements]))
    assert all_ranks(np.array_equal(np.sort(vertices), np.arange(mesh.nvertices)))
    assert all_ranks(np.array_equal(np.sort(elements), np.arange(mesh.nelements)))
    starts = COMM.allgather((part.vertices.start, part.vertices.end))
    assert all_ranks(all(a[1] == b[0] for a, b in zip(starts, starts[1:])))
    boundary = np.concatenate(COMM.allgather(part.boundary_vertices()))
    serial = skfem.Basis(mesh, skfem.ElementTetP1()).get_dofs()
    owner_ids = np.concatenate(COMM.allgather(part.vertices.global_ids[: part.owned_vertices]))
    original = np.empty(mesh.nvertices, dtype=np.int64)
    original[owner_ids] = vertices
    assert all_ranks(np.array_equal(np.sort(original[boundary]), np.sort(serial)))


def test_ghost_exchange_is_the_transpose_of_its_reverse(part):
    """Dot-product test: ⟨update(a), c⟩ = ⟨a, accumulate(c)⟩, summed over the ranks."""
    space: GhostedSpace = part.elements
    rng = np.random.default_rng(7 + COMM.Get_rank())
    a, c = rng.standard_normal(space.owned), rng.standard_normal(space.local_size)
    left = COMM.allreduce(float(space.update(a) @ c))
    right = COMM.allreduce(float(a @ space.accumulate(c)))
    assert all_ranks(abs(left - right) <= 1e-12 * abs(left))
    # ghosts hold their owners' values: global ids as values come back as themselves
    ids = space.update(np.arange(space.start, space.end, dtype=np.float64))
    assert all_ranks(np.array_equal(ids, space.global_ids))


def test_a_bad_theta_on_one_rank_raises_on_every_rank(part):
    local = skfem.Basis(part.mesh, skfem.ElementTetP1())
    A = DistributedParametricMatrix.from_local(pp.diffusion_operator(local, "P0"), part)
    theta = torch.ones(A.n_params, dtype=torch.float64)
    b = torch.ones(A.local_shape[0], dtype=torch.float64)
    if COMM.Get_rank() == COMM.Get_size() - 1:
        theta[0] = -1.0
    with pp.KSPSolver({"ksp_type": "cg"}, comm=PETSc.COMM_WORLD, max_it=3) as solver:
        with pytest.raises(pp.InputError, match="must be > 0"):
            pp.solve(A, b, solver, theta=theta)
        short = b[:-1] if COMM.Get_rank() == 0 else b
        with pytest.raises(pp.InputError, match="each rank's own rows"):
            pp.solve(A, short, solver, theta=torch.ones(A.n_params, dtype=torch.float64))


def test_sum_over_ranks_passes_the_gradient_to_every_part():
    part = torch.tensor([float(COMM.Get_rank() + 1)], dtype=torch.float64, requires_grad=True)
    total = sum_over_ranks(part.square().sum(), COMM)
    total.backward()
    total = total.detach()
    size = COMM.Get_size()
    assert all_ranks(float(total) == sum((r + 1) ** 2 for r in range(size)))
    assert all_ranks(float(part.grad[0]) == 2.0 * (COMM.Get_rank() + 1))


def test_owned_scene_trains_on_the_ranks_as_in_one_process(tmp_path):
    """``demos/poisson3d.py`` under ``--parallel domain``: the owned layout's run equals
    the one-process run (CG + Jacobi, whose iterates do not depend on the partition)."""
    from pathlib import Path

    from prdp_petsc.lab.training.harness import run

    scene = Path(__file__).resolve().parents[2] / "demos" / "poisson3d.py"
    kwargs = {"preset": "quick pc=jacobi k_init=20 k_step=10", "epochs": 4, "progress": False}
    serial = run(scene, "prdp", **kwargs)
    out = Path(COMM.bcast(str(tmp_path), root=0))
    parallel = run(scene, "prdp", out=out, parallel="domain", **kwargs)
    owned = parallel["info"]["owned_unknowns"]
    assert all_ranks(len(owned) == COMM.Get_size() and sum(owned) == 9**3 and min(owned) > 0)
    assert all_ranks(parallel["stopped"] is None and serial["stopped"] is None)
    for key in ("k", "train_loss", "val_metric"):
        got = np.array([e[key] for e in parallel["epochs"]])
        expected = np.array([e[key] for e in serial["epochs"]])
        assert all_ranks(np.allclose(got, expected, rtol=1e-9, atol=0)), (key, got, expected)
    assert all_ranks(parallel["epochs"][-1]["val_metric"] < parallel["epochs"][0]["val_metric"])


class _OwnedAndShared:
    """A scene with an owned θ (this rank's part, its own length) and a shared weight w:
    ``L = Σ_ranks Σ_i (w·θ_i − r)²``, summed with `sum_over_ranks`."""

    def __init__(self):
        rank = COMM.Get_rank()
        self.theta = torch.arange(rank + 2, dtype=torch.float64).requires_grad_(True)
        self.w = torch.tensor([1.5 + rank], dtype=torch.float64, requires_grad=True)
        # a shared weight only rank 0's part of the loss uses: no gradient on the others
        self.v = torch.tensor([2.0], dtype=torch.float64, requires_grad=True)
        self.owned_parameters = [self.theta]
        self.optimizer = torch.optim.SGD([self.theta, self.w, self.v], lr=0.0)

    def loss(self, _):
        local = (self.w * self.theta - COMM.Get_rank()).square().sum()
        if COMM.Get_rank() == 0:
            local = local + self.v.square().sum()
        return sum_over_ranks(local, COMM)


def test_the_harness_keeps_owned_parameters_and_sums_the_shared_gradients():
    from prdp_petsc.lab.training.parallel import Parallel

    scene = _OwnedAndShared()
    ranks = Parallel("domain")
    ranks.synchronize(scene)  # w from rank 0; θ (of another length on every rank) kept
    assert all_ranks(float(scene.w.detach()) == 1.5)
    assert all_ranks(torch.equal(scene.theta.detach(), torch.arange(COMM.Get_rank() + 2.0)))
    ranks.step(scene, None)
    # ∂L/∂w = Σ_ranks Σ_i 2 (w θ_i − r) θ_i, on every rank; ∂L/∂θ stays each rank's own
    expected = sum(sum(2 * (1.5 * t - r) * t for t in range(r + 2)) for r in range(COMM.Get_size()))
    assert all_ranks(float(scene.w.grad[0]) == pytest.approx(expected, rel=1e-14))
    assert all_ranks(scene.v.grad is not None and float(scene.v.grad[0]) == 4.0)
    rank = COMM.Get_rank()
    own = 2 * (1.5 * torch.arange(rank + 2.0) - rank) * 1.5
    assert all_ranks(torch.allclose(scene.theta.grad, own.double(), rtol=1e-14))


def test_an_owned_layout_run_is_not_resumed_on_several_ranks(tmp_path):
    from pathlib import Path

    from prdp_petsc.errors import InputError
    from prdp_petsc.lab.training.harness import run

    scene = Path(__file__).resolve().parents[2] / "demos" / "poisson3d.py"
    out = Path(COMM.bcast(str(tmp_path), root=0))
    run(scene, "fixed:5", preset="quick", epochs=1, out=out, parallel="domain", progress=False)
    with pytest.raises(InputError, match="cannot be resumed on several ranks"):
        run(resume=out, epochs=2, parallel="domain", progress=False)


def test_owned_solve_returns_its_solution_with_the_adjoint_outcome(part):
    """``return_solution=True`` in the owned layout: the outcome of both solves, collective."""
    local = skfem.Basis(part.mesh, skfem.ElementTetP1())
    A = DistributedParametricMatrix.from_local(_operator(local, False), part)
    bc = pp.Dirichlet(A, part.boundary_vertices())
    rng = np.random.default_rng(7 + COMM.rank)
    theta = torch.from_numpy(1.0 + rng.random(bc.A_II.n_params)).requires_grad_(True)
    b = torch.from_numpy(rng.standard_normal(bc.A_II.local_shape[0]))
    options = {"ksp_type": "cg", "pc_type": "jacobi"}
    with pp.KSPSolver(options, prefix="own_sol_", comm=PETSc.COMM_WORLD, max_it=7) as solver:
        sol = pp.solve(bc.A_II, b, solver, theta=theta, return_solution=True)
        plain = pp.solve(bc.A_II, b, solver, theta=theta.detach())
        _sum(sol.value.square().sum()).backward()
    assert all_ranks(sol.iterations == 7 and sol.reason == "DIVERGED_MAX_IT")
    assert all_ranks(sol.adjoint is not None and sol.adjoint.iterations.tolist() == [7])
    assert all_ranks(torch.equal(sol.value.detach(), plain))
