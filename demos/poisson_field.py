"""Recover a diffusion-coefficient field on an unstructured mesh through a capped CG solve.

PDE: −∇·(κ∇u) = 1 on the L-shaped domain (the shipped gmsh mesh ``lshape``), u = 0 on
the boundary.  Discretisation: P1 finite elements (scikit-fem) for u, κ = exp(θ)
piecewise constant (P0, one θ per element, so κ stays positive);
``A(κ) = pp.diffusion_operator(basis, "P0")`` with the Dirichlet nodes eliminated
(`prdp_petsc.Dirichlet`).  The true κ is smooth with a contrast of 10: a background
of 1 with one Gaussian inclusion rising to 10 and a milder one (κ ≈ 4).
Observations: the true u at every node plus 1 % Gaussian noise (fixed seed).

Inverse problem: Adam on θ (no network) minimises
``½‖u(θ) − u_obs‖² / ‖u_obs‖² + ½ β θᵀ L θ``, where L is the graph Laplacian of the
mesh's element adjacency (elements sharing an edge, from ``mesh.f2t``), a small
smoothness regulariser.  One "batch" per epoch, several Adam steps in it.  Validation
metric: the element-area weighted relative L2 error of the recovered κ against the
true κ.

Solver in the loop: CG + Jacobi (``-pf_ksp_type``/``-pf_pc_type``) in fixed mode,
K = ``max_it`` iterations from zero, implicit (adjoint) gradients.  A truncated solve
underestimates u, so the fitted κ is biased low away from the boundary; PRDP raises K
only as far as the κ error needs.  Any PETSc solver is one option away
(``-pf_pc_type gamg``); ``compare --routes cg/gamg`` also runs PRDP and full fidelity
with it.  K_full is measured on the true operator ``A_II(κ_true)``.

Presets: ``quick`` (refine 0: 1 485 nodes, 2 808 elements; tests) and ``paper``
(refine 1: 5 777 nodes, 11 232 elements).

Run ``python demos/poisson_field.py compare --preset paper --routes cg/gamg --out results/pf``;
``python demos/poisson_field.py plot --preset paper --out fields.png`` (or ``prdp-petsc
scene demos/poisson_field.py plot ...``) draws true against recovered κ.
``config["mode"]`` picks implicit (PETSc adjoint) or unrolled (the CG iteration in
torch) gradients (the bridge benchmark compares their cost).
"""

from __future__ import annotations

import sys

import numpy as np
import scipy.sparse as sp
import skfem
import torch

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.lab.components.emulators import torch_sparse
from prdp_petsc.lab.reports import poisson_field as field_reports
from prdp_petsc.prdp import PAPER

PRESETS = {
    "quick": {
        "refine": 0,
        "epochs": 30,
        "steps": 10,
        "lr": 0.1,
        "beta": 1e-5,
        "noise": 0.01,
        "k_init": 20,
        "k_step": 10,
        "mode": "implicit",
    },
}
PRESETS["paper"] = {
    **PRESETS["quick"],
    "refine": 1,
    "epochs": 40,
    "k_init": 40,
    "k_step": 20,
}

PREFIX = "pf_"


def true_kappa(points: np.ndarray) -> np.ndarray:
    """κ_true at `points` (2, m): 1 + 9 bump(0.3, 0.3) + 3 bump(0.25, 0.75)."""
    x, y = points
    big = np.exp(-((x - 0.3) ** 2 + (y - 0.3) ** 2) / (2 * 0.1**2))
    small = np.exp(-((x - 0.25) ** 2 + (y - 0.75) ** 2) / (2 * 0.08**2))
    return 1.0 + 9.0 * big + 3.0 * small


def element_adjacency_laplacian(mesh) -> sp.csr_matrix:
    """Graph Laplacian ``L = DᵀD`` of the elements, D the (interior facet × element)
    incidence with +1/−1 for the two elements sharing each facet."""
    pairs = mesh.f2t[:, mesh.f2t[1] >= 0]
    m = pairs.shape[1]
    rows = np.repeat(np.arange(m), 2)
    D = sp.csr_matrix(
        (np.tile([1.0, -1.0], m), (rows, pairs.T.ravel())), shape=(m, mesh.t.shape[1])
    )
    return (D.T @ D).tocsr()


@skfem.LinearForm
def _unit_load(v, w):
    return v


def build(config: dict, seed: int) -> lab.Scene:
    mesh = pp.load_mesh("lshape", refine=config["refine"])
    basis = skfem.Basis(mesh, skfem.ElementTriP1())
    A = pp.diffusion_operator(basis, "P0")
    bc = pp.Dirichlet(A, basis.get_dofs())
    f_np = _unit_load.assemble(basis)
    f = torch.from_numpy(f_np)
    g = torch.zeros(len(bc.boundary), dtype=torch.float64)

    centroids = mesh.p[:, mesh.t].mean(axis=1)
    kappa_true = true_kappa(centroids)
    e1 = mesh.p[:, mesh.t[1]] - mesh.p[:, mesh.t[0]]
    e2 = mesh.p[:, mesh.t[2]] - mesh.p[:, mesh.t[0]]
    area = 0.5 * np.abs(e1[0] * e2[1] - e1[1] * e2[0])
    kappa_norm = np.sqrt(np.sum(area * kappa_true**2))

    # observations: converged solve at the true κ, plus 1 % noise (fixed seed)
    u_true = np.zeros(basis.N)
    u_true[bc.interior] = sp.linalg.spsolve(bc.A_II.matrix(kappa_true).tocsc(), f_np[bc.interior])
    rng = np.random.default_rng(1234)
    noise = config["noise"] * np.sqrt(np.mean(u_true**2)) * rng.standard_normal(basis.N)
    u_obs = torch.from_numpy(u_true + noise)
    obs_scale = float(u_obs.square().sum())

    L = torch_sparse(element_adjacency_laplacian(mesh))
    theta = torch.zeros(A.n_params, dtype=torch.float64, requires_grad=True)
    solver = pp.KSPSolver(
        {"ksp_type": "cg", "pc_type": "jacobi"}, prefix=PREFIX, max_it=config["k_init"]
    )
    optimizer = torch.optim.Adam([theta], lr=config["lr"])
    beta = config["beta"]
    mode = config["mode"]

    def loss(_):
        """``steps`` Adam steps; the last one's loss is returned for the harness to step."""
        for step in range(config["steps"]):
            optimizer.zero_grad()
            u = bc.solve(f, g, solver, theta=torch.exp(theta), mode=mode)
            misfit = 0.5 * (u - u_obs).square().sum() / obs_scale
            value = misfit + 0.5 * beta * theta @ (L @ theta)
            if step < config["steps"] - 1:
                value.backward()
                optimizer.step()
        return value

    def validate():
        kappa = np.exp(theta.detach().numpy())
        return float(np.sqrt(np.sum(area * (kappa - kappa_true) ** 2)) / kappa_norm)

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=lambda epoch, generator: [None],
        loss=loss,
        validate=validate,
        probe=lambda: (bc.A_II.matrix(kappa_true), f_np[bc.interior], None),
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
            "nodes": int(basis.N),
            "unknowns": int(len(bc.interior)),
            "elements": int(A.n_params),
            "nnz": int(bc.A_II.nnz),
            "kappa_contrast": float(kappa_true.max() / kappa_true.min()),
            **config,
        },
    )


# ``prdp-petsc scene demos/poisson_field.py plot ...``: true against recovered κ
COMMANDS = field_reports.commands(sys.modules[__name__])


# -- Things to try --------------------------------------------------------------------------
# * Unrolled gradients (the CG iteration in torch) instead of the adjoint:
#   ``--set mode=unrolled``.
# * GAMG in the loop: ``-pf_pc_type gamg``, or ``compare --routes cg/gamg``.
# * True against recovered κ: ``python demos/poisson_field.py plot --out fields.png``.


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
