"""Recover a 3D diffusion coefficient per tetrahedron, each rank holding only its own part.

PDE: −∇·(κ∇u) = 1 on the unit cube, u = 0 on its boundary.  Discretisation: P1 finite
elements (scikit-fem) on a tetrahedral grid (``skfem.MeshTet.init_tensor``, ``n`` points
per axis, six tetrahedra per cell), κ = exp(θ) piecewise constant (P0, one θ per
tetrahedron).  The true κ is 1 plus two Gaussian inclusions (peaks 10 and 4).
Observations: the true u at every vertex plus 1 % Gaussian noise (fixed seed, drawn on
the whole mesh, so they do not depend on the number of ranks).  The 3D counterpart of
``demos/poisson_field.py``.

Owned layout (`prdp_petsc.fem.partition`, `prdp_petsc.fem.distributed`): rank 0 builds
the mesh and splits it with METIS; every rank assembles its piece alone, and θ, u, the
observations and every tensor of the loss hold that rank's own tetrahedra and vertices.
Under ``prdp-petsc run ... --parallel domain`` the ranks share one PETSc solve; on one
process it is the whole problem.  The misfit and the metric are sums over the ranks,
one ``MPI_Allreduce`` each (`prdp_petsc.autograd.owned.sum_over_ranks`).  θ is declared
``Scene.owned_parameters``: each rank starts from and keeps its own part.  Resuming such
a run on several ranks is refused: the checkpoint holds rank 0's part only.

Inverse problem: Adam on θ (no network) minimises ``½‖u(θ) − u_obs‖² / ‖u_obs‖² +
½ β Σ_T |T| θ_T²`` (a small pull towards κ = 1, local to every tetrahedron).  ``steps``
Adam steps per epoch.  Validation metric: the volume-weighted relative L2 error of κ
against the true κ.

Solver in the loop: CG + GAMG (``-p3_ksp_type``/``-p3_pc_type``; ``pc`` in the presets
picks the PC) in fixed mode, K = ``max_it`` iterations from zero, implicit (adjoint)
gradients, the GAMG hierarchy set up again for every new θ.  K_full is measured on
the true operator.

Presets: ``quick`` (n = 11: 729 unknowns, 6 000 tetrahedra; tests), ``paper`` (n = 41:
59 319 unknowns, 384 000 tetrahedra) and ``large`` (n = 102: 1 000 000 unknowns,
6 181 806 tetrahedra; two ranks: ``mpiexec -n 2 prdp-petsc run demos/poisson3d.py
--preset large --schedule prdp --parallel domain --out results/poisson3d-large``).
"""

from __future__ import annotations

import numpy as np
import skfem
import torch

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.autograd.owned import sum_over_ranks
from prdp_petsc.core.parallel import default_comm
from prdp_petsc.fem.distributed import DistributedParametricMatrix
from prdp_petsc.fem.partition import PartitionedMesh
from prdp_petsc.prdp import PAPER

_BASE = {
    "steps": 5,
    "lr": 0.1,
    "beta": 1e-4,
    "noise": 0.01,
    "pc": "gamg",
    "k_init": 2,
    "k_step": 2,
}
PRESETS = {
    "quick": {**_BASE, "n": 11, "epochs": 12},
    "paper": {**_BASE, "n": 41, "epochs": 30},
    "large": {**_BASE, "n": 102, "epochs": 8, "steps": 3},
}

PREFIX = "p3_"


def true_kappa(points: np.ndarray) -> np.ndarray:
    """κ_true at `points` (3, m): 1 + 9 bump(0.35, 0.4, 0.5; 0.12) + 3 bump(0.7, 0.65, 0.4; 0.1)."""

    def bump(centre, width):
        return np.exp(
            -sum((p - c) ** 2 for p, c in zip(points, centre, strict=True)) / (2 * width**2)
        )

    return 1.0 + 9.0 * bump((0.35, 0.4, 0.5), 0.12) + 3.0 * bump((0.7, 0.65, 0.4), 0.1)


@skfem.LinearForm
def _unit_load(v, w):
    return v


def _volumes(mesh: skfem.MeshTet) -> np.ndarray:
    p = mesh.p[:, mesh.t]  # (3, 4, elements)
    edges = p[:, 1:] - p[:, :1]
    return np.abs(np.einsum("ie,je,ke,ijk->e", edges[:, 0], edges[:, 1], edges[:, 2],
                            _LEVI_CIVITA)) / 6.0  # fmt: skip


_LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_i, _j, _k], _LEVI_CIVITA[_i, _k, _j] = 1.0, -1.0


def build(config: dict, seed: int) -> lab.Scene:
    comm = default_comm()  # COMM_WORLD under --parallel domain, else COMM_SELF
    root = comm.getRank() == 0
    n = config["n"]
    mesh = noise = None
    if root:  # only rank 0 ever holds the whole mesh
        axis = np.linspace(0.0, 1.0, n)
        mesh = skfem.MeshTet.init_tensor(axis, axis, axis)
        noise = np.random.default_rng(1234).standard_normal(mesh.nvertices)
    part = PartitionedMesh.distribute(mesh, comm, vertex_data={"noise": noise} if root else None)
    del mesh
    basis = skfem.Basis(part.mesh, skfem.ElementTetP1())
    A = DistributedParametricMatrix.from_local(
        pp.diffusion_operator(basis, "P0"), part, symmetric=True
    )
    bc = pp.Dirichlet(A, part.boundary_vertices())
    owned = part.owned_elements
    f = torch.from_numpy(_unit_load.assemble(basis)[: part.owned_vertices])
    g = torch.zeros(len(bc.boundary), dtype=torch.float64)

    centroids = part.mesh.p[:, part.mesh.t[:, :owned]].mean(axis=1)
    kappa_true = true_kappa(centroids)
    volume = _volumes(part.mesh)[:owned]

    def total(*values) -> np.ndarray:  # sums over the ranks, one collective
        return sum_over_ranks(torch.tensor(values, dtype=torch.float64), comm).numpy()

    kappa_norm = float(np.sqrt(total(np.sum(volume * kappa_true**2))[0]))
    options = {"ksp_type": "cg", "pc_type": config["pc"]}

    # observations: converged solve at the true κ, plus noise drawn on the whole mesh
    kappa = torch.from_numpy(kappa_true)
    with pp.KSPSolver(options, prefix="p3_true_", max_it=10_000, rtol=1e-10) as exact:
        u_true = bc.solve(f, g, exact, theta=kappa).numpy()
    rms = float(np.sqrt(total(np.sum(u_true**2))[0] / A.shape[0]))
    u_obs = torch.from_numpy(
        u_true + config["noise"] * rms * part.vertex_data["noise"][: part.owned_vertices]
    )
    obs_scale = float(total(float(u_obs.square().sum()))[0])

    # θ of this rank's own tetrahedra (`Scene.owned_parameters`: each rank its own part)
    theta = torch.zeros(owned, dtype=torch.float64, requires_grad=True)
    weights = torch.from_numpy(volume / float(total(volume.sum())[0]))
    solver = pp.KSPSolver(options, prefix=PREFIX, max_it=config["k_init"])
    optimizer = torch.optim.Adam([theta], lr=config["lr"])
    beta = config["beta"]

    def objective():
        """The misfit plus the pull towards κ = 1, summed over the ranks: one solve."""
        u = bc.solve(f, g, solver, theta=torch.exp(theta))
        local = 0.5 * (u - u_obs).square().sum() / obs_scale
        local = local + 0.5 * beta * (weights * theta.square()).sum()
        return sum_over_ranks(local, comm)

    def loss(_):
        """``steps`` Adam steps; the last one's loss is returned for the harness to step."""
        for step in range(config["steps"]):
            optimizer.zero_grad()
            value = objective()
            if step < config["steps"] - 1:
                value.backward()
                optimizer.step()
        return value

    def validate():
        kappa = np.exp(theta.detach().numpy())
        return float(np.sqrt(total(np.sum(volume * (kappa - kappa_true) ** 2))[0]) / kappa_norm)

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=lambda epoch, generator: [None],
        loss=loss,
        check_loss=objective,  # the gradient at θ, without the epoch's Adam steps
        validate=validate,
        probe=lambda: (bc.A_II.owned_csr(kappa_true), bc.rhs(f, g, kappa).numpy(), None),
        owned_parameters=[theta],
        rtol_full=1e-6,
        epochs=config["epochs"],
        prdp={
            **PAPER,
            "k_init": config["k_init"],
            "k_step": config["k_step"],
            "tau_step": 0.95,
            "window": 2,
            "use_ema": False,
        },
        info={
            "vertices": int(A.shape[0]),
            "unknowns": int(bc.A_II.shape[0]),
            "elements": int(A.params.size),
            "ranks": comm.getSize(),
            "owned_unknowns": _gather(comm, len(bc.interior)),
            **config,
        },
    )


def _gather(comm, value: int) -> list[int]:
    """`value` of every rank, in rank order."""
    return comm.tompi4py().allgather(value) if comm.getSize() > 1 else [value]


# -- Things to try --------------------------------------------------------------------------
# * Another preconditioner: ``--set pc=jacobi``; watch the solves with ``-p3_ksp_monitor``.
# * Two ranks, each assembling its own tetrahedra:
#   ``mpiexec -n 2 prdp-petsc run demos/poisson3d.py --parallel domain --out DIR``.

if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
