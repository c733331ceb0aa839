"""Recover a two-region conductivity through a capped CG solve (the docs' example scene).

PDE: −∇·(κ∇u) = 1 on the shipped L-shaped mesh, u = 0 on the boundary, P1 elements
(scikit-fem).  κ is κ_in inside the disc |x − c| < r and κ_out outside; the data is
u for κ = (3, 1), solved to convergence.

Solver in the loop: CG + Jacobi, capped at K = ``max_it`` iterations (fixed mode,
``rtol = atol = 0``), implicit gradients through the adjoint solve.  Learned: log κ
(two numbers, started from a random guess), by Adam on the relative squared misfit
of u(κ).  Validation metric (what PRDP watches): the relative error of κ.

Run ``prdp-petsc compare docs/examples/my_scene.py --out results/my_scene``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
import torch
from skfem import Basis, ElementTriP1

import prdp_petsc as pp
from prdp_petsc import lab

PRESETS = {
    "quick": {"refine": 0, "epochs": 30, "steps": 10, "lr": 0.05, "gamma": 0.95},
    "paper": {"refine": 1, "epochs": 60, "steps": 5, "lr": 0.05, "gamma": 0.95},
}
KAPPA_TRUE = (3.0, 1.0)  # (inside the disc, outside)
CENTRE, RADIUS = (0.25, 0.25), 0.2  # a disc in the L-shape's lower left square


def build(config: dict, seed: int) -> lab.Scene:
    mesh = pp.load_mesh("lshape", refine=config["refine"])
    basis = Basis(mesh, ElementTriP1())
    A = pp.diffusion_operator(basis, coefficient="P0")  # A(κ) = a0 + G κ, κ per element
    bc = pp.Dirichlet(A, basis.get_dofs())  # u = 0 on the boundary: A_II(κ) u_I = f_I
    load = pp.mass_matrix(basis) @ np.ones(basis.N)  # f = 1

    centroids = mesh.p[:, mesh.t].mean(axis=1)
    inside = np.linalg.norm(centroids - np.array(CENTRE)[:, None], axis=0) < RADIUS
    regions = torch.from_numpy(np.stack([inside, ~inside], axis=1).astype(np.float64))
    kappa_true = regions @ torch.tensor(KAPPA_TRUE, dtype=torch.float64)  # per element

    A_true = bc.A_II.matrix(kappa_true.numpy())  # scipy CSR of the interior system
    f = torch.from_numpy(load)
    g = torch.zeros(len(bc.boundary), dtype=torch.float64)
    u_data = torch.zeros(basis.N, dtype=torch.float64)
    u_data[bc.interior] = torch.from_numpy(spla.spsolve(A_true.tocsc(), load[bc.interior]))

    rng = np.random.default_rng(seed)  # the initial guess depends on the seed
    log_kappa = torch.tensor(rng.normal(0.0, 0.3, 2), requires_grad=True)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, prefix="mine_", max_it=1)
    optimizer = torch.optim.Adam([log_kappa], lr=config["lr"])

    def loss(_batch):
        u = bc.solve(f, g, solver, theta=regions @ log_kappa.exp())
        return (u - u_data).square().mean() / u_data.square().mean()

    def validate() -> float:
        kappa = log_kappa.detach().exp().numpy()
        return float(np.linalg.norm(kappa - KAPPA_TRUE) / np.linalg.norm(KAPPA_TRUE))

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=lambda epoch, generator: [None] * config["steps"],  # Adam steps per epoch
        loss=loss,
        validate=validate,
        probe=lambda: (A_true, load[bc.interior], None),  # K_full: CG to rtol_full
        rtol_full=1e-8,
        epochs=config["epochs"],
        # as demos/poisson_inverse.py: no EMA, a plateau over two epochs refines K by 10
        prdp={"k_init": 10, "k_step": 10, "use_ema": False, "window": 2, "tau_step": 0.92},
        scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=config["gamma"]),
        info={"unknowns": len(bc.interior), "kappa_true": KAPPA_TRUE, **config},
    )


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
