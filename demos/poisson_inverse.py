"""Poisson inverse problem with one parameter, solved through a capped Jacobi solver.

PDE: u'' = −θ sin(2πx) on (0, 1), u(0) = u(1) = 0, second-order finite differences
on 30 interior points.  The reference solution uses θ_ref = 2; gradient descent
starts from θ₀ = 5 and minimises the mean squared misfit of u(θ) against it.

Solver in the loop: plain Jacobi (Richardson + PCJACOBI, scale 1) in fixed mode,
implicit gradients.  There is no network: the scene builds only the physics, θ
and an SGD optimizer (learning rate 275, as in the reference).  With small K the
truncated solve biases the recovered θ; the validation metric is the relative
parameter error |θ − θ_ref| / θ_ref.  Reference PRDP settings (tum-pbs/PRDP; the
algorithm is in docs/maths.md §7): no EMA, window 2, τ_step 0.92, K₀ 25, ΔK 10,
K ≤ 600.  Only progressive-refinement savings are possible here: the parameter
error needs the converged solve.

Run ``python demos/poisson_inverse.py compare --preset paper --out results/poisson``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
import torch

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.fem.fd import grid_points, laplacian
from prdp_petsc.prdp import PAPER

PRESETS = {
    "quick": {"n": 30, "steps": 60, "lr": 275.0},
    "paper": {"n": 30, "steps": 180, "lr": 275.0},
}

THETA_REF = 2.0
THETA_INIT = 5.0


def build(config: dict, seed: int) -> lab.Scene:
    n = config["n"]
    A = (-laplacian(n)).tocsr()  # SPD: −u'' = θ sin(2πx)
    shape = np.sin(2 * np.pi * grid_points(n)[0])
    u_ref = torch.from_numpy(spla.spsolve(A.tocsc(), THETA_REF * shape))
    source = torch.from_numpy(shape)
    theta = torch.tensor([THETA_INIT], dtype=torch.float64, requires_grad=True)
    solver = pp.KSPSolver(
        {"ksp_type": "richardson", "pc_type": "jacobi"}, prefix="poisson_", max_it=25
    )
    optimizer = torch.optim.SGD([theta], lr=config["lr"])

    def loss(_):
        u = pp.solve(A, theta * source, solver)
        return (u - u_ref).square().mean()

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=lambda epoch, generator: [None],  # one gradient step per "epoch"
        loss=loss,
        validate=lambda: abs(theta.item() - THETA_REF) / THETA_REF,
        probe=lambda: (A, THETA_REF * shape, None),
        rtol_full=1e-6,
        epochs=config["steps"],
        prdp={  # the paper's Poisson runs
            **PAPER,
            "k_init": 25,
            "k_step": 10,
            "k_max": 600,
            "tau_step": 0.92,
            "window": 2,
            "use_ema": False,
        },
        compare_ks=[25, 100, 300],
        info={"n": n, "theta_ref": THETA_REF, "theta_init": THETA_INIT, **config},
    )


# -- Things to try --------------------------------------------------------------------------
# * A constant K, and the biased θ it converges to: ``run --schedule fixed:100 --out DIR``.
# * CG instead of damped Jacobi: ``-poisson_ksp_type cg``.


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
