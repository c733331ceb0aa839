"""Heat 1D emulator trained through a capped damped-Jacobi solve (the paper's heat 1D).

PDE: u_t = u_xx on (0, 1), u(0) = u(1) = 0, one implicit step with ν·Δt = 1e-3, as the paper
does: one backward-Euler (BTCS) step is ``(I − 0.001 L/dx²) u¹ = u⁰`` with L the
second-difference matrix on 30 interior points (dx = 1/31).

Solver in the loop: Richardson + PCJACOBI (damped Jacobi, scale 0.8) in fixed
mode, K = ``max_it`` iterations from zero; implicit (adjoint) gradients.

Learning problem (mixed chain): an MLP 30→30 (width 64, depth 3) maps u⁰ to
û¹; the loss compares the *capped* solver step P_K(û¹) with the exact u².  With
small K, P_K is far from the exact step and the network learns a biased û¹;
the validation metric shows it: the mean relative L2 error of a 10-step
autoregressive rollout of the MLP against the exact trajectory, on 5 held-out
initial conditions (the harness also records a 30-step rollout curve).  PRDP
raises K only as far as that metric needs; its EMA restarts at each refinement
(``restart_window``), since the rollout at K = 1-2 blows up and would otherwise
hide the plateaus that follow.  Initial conditions are truncated Fourier sine series.

Multi-step training (``unroll`` = m, default 1): the chain s ← P_K(N(s)) runs m times
from u⁰ under autograd, its k-th state is compared with the exact u²ᵏ, and the loss
is the sum of the m terms (`prdp_petsc.lab.training.unroll.windows` cuts the training
windows u⁰, u², …, u²ᵐ from the exact trajectories).  m = 1 is the one-step loss
above, to the bit.

Presets: ``quick`` (tests), ``paper`` (the reference's settings) and ``paper_k10``
(``paper`` with PRDP from K₀ = 10; the scenes guide says why; results pages
heat1d_seeds, heat1d_m2_seeds, heat1d_k10_seeds).

Run ``python demos/heat1d.py compare --preset paper --out results/heat1d``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import torch

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.fem.fd import grid_points, laplacian
from prdp_petsc.lab.components.networks import mlp
from prdp_petsc.lab.training.rollout import rollout_errors
from prdp_petsc.lab.training.scene import shuffled_batches
from prdp_petsc.lab.training.unroll import windows
from prdp_petsc.prdp import PAPER

PRESETS = {
    "quick": {
        "n": 30,
        "n_train": 40,
        "n_val": 5,
        "modes": 5,
        "epochs": 12,
        "batch": 20,
        "lr": 3e-3,
        "gamma": 0.95,
        "unroll": 1,
        "k_init": 1,
    },
}
PRESETS["paper"] = {
    **PRESETS["quick"],
    "n_train": 200,
    "epochs": 200,
    "lr": 2e-3,
    "gamma": 0.985,
}
# PRDP from K = 10: past the Ks whose learned map amplifies over the rollout (above)
PRESETS["paper_k10"] = {**PRESETS["paper"], "k_init": 10}

NU_DT = 1e-3  # the paper's 0.001 in (I - 0.001 L/dx^2)
VAL_STEPS = 10  # validation: mean error of a 10-step rollout
ROLLOUT_STEPS = 30  # the recorded rollout curve
JACOBI_SCALE = 0.8


def initial_conditions(count: int, n: int, modes: int, rng: np.random.Generator) -> np.ndarray:
    """Truncated sine series sum_k a_k sin(k pi x), a_k ~ U(-1, 1)/k, on the interior grid."""
    x = grid_points(n)[0]
    k = np.arange(1, modes + 1)
    amplitudes = rng.uniform(-1, 1, size=(count, modes)) / k
    return amplitudes @ np.sin(np.pi * np.outer(k, x))


def network(n: int) -> torch.nn.Sequential:
    """The scene's network: an MLP on the n nodal values, three GELU layers of 64."""
    return mlp(n, n, width=64, depth=3)


def build(config: dict, seed: int) -> lab.Scene:
    n, m = config["n"], config["unroll"]
    if m < 1:
        raise ValueError(f"unroll must be >= 1, got {m}")
    A = (sp.identity(n, format="csr") - NU_DT * laplacian(n)).tocsr()
    rng = np.random.default_rng(seed)
    dense = A.toarray()
    step = lambda u: scipy.linalg.solve(dense, u.T, assume_a="pos").T  # noqa: E731
    u0 = initial_conditions(config["n_train"] + config["n_val"], n, config["modes"], rng)
    traj = [u0]
    for _ in range(max(ROLLOUT_STEPS, 2 * m)):
        traj.append(step(traj[-1]))
    traj = torch.from_numpy(np.stack(traj))  # (steps + 1, samples, n)
    n_train = config["n_train"]
    # one window per training trajectory: u⁰, u², …, u²ᵐ (each chain step spans two)
    targets = windows(traj[: 2 * m + 1 : 2, :n_train], m + 1)  # (m + 1, n_train, n)
    val_traj = traj[: ROLLOUT_STEPS + 1, n_train:].contiguous()  # (steps + 1, n_val, n)

    solver = pp.KSPSolver(
        {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": JACOBI_SCALE},
        prefix="heat_",
        max_it=1,
    )
    net = network(n)
    optimizer = torch.optim.Adam(net.parameters(), lr=config["lr"])

    def loss(idx):
        """Σₖ ‖(P_K ∘ N)ᵏ(u⁰) − u²ᵏ‖², k = 1 … m, averaged over the batch."""
        state, total = targets[0, idx], 0
        for target in targets[1:, idx]:
            state = pp.solve(A, net(state), solver)
            total = total + ((state - target) ** 2).sum(-1).mean()
        return total

    def validate():
        return float(rollout_errors(net, val_traj[0], val_traj[1 : VAL_STEPS + 1]).mean())

    def rollout():
        return rollout_errors(net, val_traj[0], val_traj[1:])

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=shuffled_batches(config["n_train"], config["batch"]),
        loss=loss,
        validate=validate,
        rollout=rollout,
        probe=lambda: (A, val_traj[1].numpy(), None),
        rtol_full=1e-6,
        epochs=config["epochs"],
        # the paper's controller with a longer EMA and restart_window: at the smallest K
        # the rollout blows up, and with the reference's EMA that spike would mask the
        # plateaus that follow
        prdp={**PAPER, "k_init": config["k_init"], "ema_window": 8, "restart_window": True},
        scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=config["gamma"]),
        info={"n": n, "nu_dt": NU_DT, "jacobi_scale": JACOBI_SCALE, **config},
    )


# -- Things to try --------------------------------------------------------------------------
# * PRDP from K = 10, past the Ks whose learned map amplifies: ``--preset paper_k10``.
# * Two chained solver steps per sample: ``--set unroll=2``.
# * A constant K against PRDP: ``run --schedule fixed:10 --out DIR``.
# * Another solver in the loop: ``-heat_ksp_type cg -heat_pc_type jacobi``; watch it with
#   ``-heat_ksp_monitor``.


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
