"""Navier–Stokes neural-hybrid corrector with the solver in the loop (PRDP on GMRES(8)).

PDE: incompressible Navier–Stokes, u_t + (u·∇)u − ν Δu + ∇p = 0, ∇·u = 0, on the
periodic unit square, ν = 1e-4.  Discretisation (`prdp_petsc.lab.components.mac`): MAC
staggered grid with N × N cells, finite differences, implicit Euler with Δt = 0.1
and one Picard linearisation about the previous velocity, first-order upwind
advection: one monolithic (u, v, p) system of 3N² unknowns per step (6 912 on the
48² paper grid), singular with the constant pressures as null space.

Solver in the loop: PETSc GMRES(8) without preconditioner (``ksp_gmres_restart 8``,
``pc_type none``), the constant-pressure null space attached, in fixed mode
(rtol = atol = 0).  K counts GMRES iterations and PRDP moves it in steps of 8
(``k_init = k_step = 8``): one PRDP step is one restart cycle, as in the reference
(its "K" is ``max_it = 8K``).  The operator depends on the velocity through the
Picard wind, A(θ) = A₀ + Gθ with θ = [a⁺; a⁻], so `prdp_petsc.solve` gives gradients
with respect to the right-hand side *and* to the velocity that built the operator.
The adjoint (transpose) solve runs the same K iterations as the forward solve;
``adjoint_rtol`` gives it its own tolerance relative to its own right-hand side.  Any
PETSc solver is one option away (``-ns2d_pc_type fieldsplit ...``); ``SCHUR`` is the
fieldsplit Schur-complement route that ``compare --routes schur`` runs.

Learning problem (solver-in-the-loop correction, as the reference): a `ConvResNet` C
(below; 3 → 3 channels u, v, p; circular padding; ``hidden`` channels, ``blocks``
blocks; float32 inside) corrects the coarse step after every step,
s_{t+1} = P_K(s_t) + C(P_K(s_t)); the loss is the MSE of the states of an
``unroll``-step rollout through solver and network against the reference, summed.
Training windows start every ``window_stride`` steps of ``n_train`` reference
trajectories of ``train_steps`` steps.  Reference data: the same
scheme on a 2N × 2N grid (direct sparse solve) restricted to N × N by face averages
(which keep the discrete divergence zero), built once per process and kept on disk
(`reference_data`).  Initial velocities: random smooth divergence-free fields from a
stream function (spectrum ∝ exp(−0.12|k|²), velocity std 1), zero pressure.  Adam
with cosine decay ``lr`` → ``lr_final`` per epoch.

Validation (what PRDP watches): the ``val_steps``-step rollout nMSE of the x-velocity
on held-out flows, ‖û − u‖²/‖u‖², with the solver at full fidelity (the training
solver to ``rtol_full``, or with ``val_solver: "schur"`` the Schur route to the same
tolerance); ``val_metric: "rollout_mean"`` validates on the mean velocity error of that
rollout instead.  The harness also records the per-step velocity error of a
``rollout_steps``-step rollout with the corrector (``rollout``) and without it
(``uncorrected_rollout``).

Settings beyond the sizes:

* ``solver_grad: False`` detaches the solver from the graph (the reference's effective
  gradient); ``noise: σ`` trains one step at a time from noisy inputs (Gaussian, σ
  times the velocity std) instead of unrolling.
* ``unroll: m``, ``checkpoint``, ``unroll_curriculum: E`` (`prdp_petsc.lab.training.unroll`):
  m-step rollouts of the hybrid, the network's activations recomputed in the backward
  pass, m doubled from 1 every E epochs.
* ``correction: "indirect"`` feeds the network's output into the implicit step as a
  momentum forcing, s ↦ P_K(s; f = C(s)) with C: 3 → 2 channels (the Indirect Neural
  Corrector).
* ``train_solver: "schur"`` trains with the Schur route (K counts its iterations).
* ``warm_start_epochs: True`` starts every training solve from that window's solution
  of the last epoch (`prdp_petsc.autograd.warm_starts.WarmStarts`); ``pc_lag: N`` sets the training
  solver's PC up only at every N-th operator (`prdp_petsc.KSPSolver`'s ``pc_lag``).
* ``routes``: the KSP/PC routes ``compare`` also runs (names in ``ROUTES``).

Presets: ``quick`` (12², tests), ``paper`` (48², the reference network and batch, 25
training windows and 24 epochs instead of the reference's 200 samples and 100
epochs), ``large`` (64², a small network, validated on the Schur route: the solve
dominates the training step), ``long`` (32², 32-step unrolls on 50-step trajectories,
Schur training and validation on the mean error of a 50-step rollout) and its
baselines ``long_nograd`` and ``long_noise``; ``long_quick`` (tests).  Variants:
``{quick,paper}_detached`` and ``{quick,paper}_noise``; ``paper_k64`` and
``large_k64`` start PRDP at 8 restart cycles, ``large_k192`` starts and refines by
192 iterations (24 on the Schur route).  Why the presets are set as they are: the
scenes guide (ns2d); what they measure: the ns2d results pages.

Run ``prdp-petsc compare demos/ns2d.py --preset paper --out results/ns2d``;
``prdp-petsc scene demos/ns2d.py adjoint --preset paper --k 8 64 256`` prints the cost
and effect of the capped adjoint, ``... energy RUN_FOLDER`` a trained run's rollout
error, energy and correlation (`prdp_petsc.lab.reports.ns2d`).
"""

from __future__ import annotations

import functools
import math
import sys

import numpy as np
import torch

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.autograd.warm_starts import WarmStarts
from prdp_petsc.lab.components import mac
from prdp_petsc.lab.reports import ns2d as ns2d_reports
from prdp_petsc.lab.training import unroll
from prdp_petsc.lab.training.cache import disk_cached
from prdp_petsc.lab.training.routes import parse_routes, route_string
from prdp_petsc.lab.training.scene import shuffled_batches
from prdp_petsc.lab.training.unroll import CORRECTIONS, Hybrid, unrolled_loss
from prdp_petsc.prdp import PAPER

_BASE = {
    "dt": 0.1,
    "nu": 1e-4,
    "unroll": 2,
    "unroll_curriculum": 0,
    "correction": "direct",
    "checkpoint": False,
    "solver_grad": True,
    "noise": 0.0,
    "adjoint_rtol": None,
    "train_solver": "gmres",
    "val_solver": "same",
    "val_metric": "u_nmse",
    "train_steps": 5,
    "window_stride": 1,
    "val_steps": 5,
    "rollout_steps": 20,
    "lr": 1e-3,
    "lr_final": 1e-4,
    "rtol_full": 1e-5,
    "k_init": 8,
    "k_step": 8,
    "warm_start_epochs": False,
    "pc_lag": 1,
    # the KSP/PC pairs `compare` also runs (``--routes`` overrides them): none here;
    # ``paper`` and ``large`` run ``schur`` (`ROUTES`; the scenes guide says why)
    "routes": "",
}

PRESETS = {
    "quick": {
        **_BASE,
        "n": 12,
        "n_train": 6,
        "n_val": 3,
        "batch": 8,
        "hidden": 16,
        "blocks": 1,
        "epochs": 8,
        "compare_ks": [8, 16],
    },
    "paper": {
        **_BASE,
        "n": 48,
        "n_train": 5,
        "train_steps": 6,
        "n_val": 5,
        "batch": 25,
        "hidden": 64,
        "blocks": 3,
        "epochs": 24,
        "compare_ks": [8, 64, 128],
        "routes": "schur",
    },
    "large": {
        **_BASE,
        "n": 64,
        "n_train": 4,
        "train_steps": 3,
        "n_val": 2,
        "val_solver": "schur",
        "batch": 8,
        "hidden": 8,
        "blocks": 1,
        "epochs": 16,
        "compare_ks": [8, 256],
        "routes": "schur",
    },
}
# PRDP from 8 restart cycles, refining by 8 (the reference starts at 1 and steps by 1)
PRESETS["paper_k64"] = {**PRESETS["paper"], "k_init": 64}
PRESETS["large_k64"] = {**PRESETS["large"], "k_init": 64, "k_step": 64}
# time to accuracy with the Schur route: PRDP's step scaled to that route is 24 iterations
PRESETS["large_k192"] = {**PRESETS["large"], "k_init": 192, "k_step": 192}
# long horizons (solver in the loop over m steps, 50-step held-out rollouts): a 32² grid,
# trained and validated with the Schur-complement PC (K counts GMRES(30) iterations)
PRESETS["long"] = {
    **_BASE,
    "n": 32,
    "n_train": 12,
    "train_steps": 50,
    "window_stride": 8,
    "n_val": 2,
    "unroll": 32,
    "checkpoint": True,
    "train_solver": "schur",
    "val_solver": "schur",
    "val_steps": 50,
    "val_metric": "rollout_mean",
    "rollout_steps": 50,
    "batch": 8,
    "hidden": 24,
    "blocks": 2,
    "epochs": 20,
    # PRDP from K = 8 in steps of 4 (the scenes guide says why not from K = 2)
    "k_init": 8,
    "k_step": 4,
    "compare_ks": [],
}
# the baselines on the same trajectories, network and epochs: no solver gradients, and
# one step at a time from noisy inputs (every start of every trajectory)
PRESETS["long_nograd"] = {**PRESETS["long"], "solver_grad": False}
PRESETS["long_noise"] = {**PRESETS["long"], "unroll": 1, "window_stride": 1, "noise": 0.05}
PRESETS["long_quick"] = {
    **PRESETS["long"],
    "n": 12,
    "n_train": 3,
    "train_steps": 6,
    "window_stride": 1,
    "unroll": 4,
    "hidden": 8,
    "blocks": 1,
    "epochs": 4,
    "compare_ks": [2],
}
PRESETS["quick_detached"] = {**PRESETS["quick"], "solver_grad": False}
PRESETS["quick_noise"] = {**PRESETS["quick"], "unroll": 1, "noise": 0.05}
PRESETS["paper_detached"] = {**PRESETS["paper"], "solver_grad": False}
PRESETS["paper_noise"] = {**PRESETS["paper"], "unroll": 1, "noise": 0.05}

GMRES = {"ksp_type": "gmres", "ksp_gmres_restart": 8, "pc_type": "none"}
# the Schur route (``val_solver``/``train_solver: "schur"``, ``--routes schur``): GMRES with
# the velocity–pressure Schur complement PC, ILU(0) on both blocks (per rank under MPI)
SCHUR = {
    "ksp_type": "gmres",
    "ksp_gmres_restart": 30,
    "pc_type": "fieldsplit",
    "pc_fieldsplit_detect_saddle_point": None,
    "pc_fieldsplit_type": "schur",
    "pc_fieldsplit_schur_precondition": "selfp",
    "pc_fieldsplit_schur_fact_type": "lower",
    "fieldsplit_0_ksp_type": "preonly",
    "fieldsplit_0_pc_type": "bjacobi",  # ILU(0) per rank: PETSc's ILU is serial only
    "fieldsplit_1_ksp_type": "preonly",
    "fieldsplit_1_pc_type": "bjacobi",
}
# the routes `compare` can run by name (``--routes schur``): the Schur-complement PC
ROUTES = {"schur": route_string(SCHUR)}
# the settings that name one of a few choices
CHOICES = {
    "train_solver": ("gmres", "schur"),
    "val_solver": ("same", "schur"),
    "correction": CORRECTIONS,
    "val_metric": ("u_nmse", "rollout_mean"),
}


@functools.lru_cache(maxsize=4)
def reference_data(n: int, count: int, steps: int, dt: float, nu: float, seed: int):
    """Reference trajectories (steps + 1, count, 3n²): the 2n² simulation restricted.

    Cached in memory per process and on disk (`prdp_petsc.lab.training.cache.disk_cached`,
    keyed by the arguments and the source of `prdp_petsc.lab.components.mac`).
    """

    def compute():
        rng = np.random.default_rng(seed)
        fine = mac.simulate(mac.random_states(2 * n, count, rng), 2 * n, dt, nu, steps)
        return mac.restrict(fine, 2 * n)

    key = f"n{n}_count{count}_steps{steps}_dt{dt!r}_nu{nu!r}_seed{seed}"
    return torch.from_numpy(disk_cached("ns2d", key, compute, sources=[mac.__file__]))


class ConvResNet(torch.nn.Module):
    """Residual CNN on periodic 2D grids: 1×1 lift, residual blocks, 1×1 projection.

    Each block is ``h ← h + conv(σ(conv(σ(h))))`` with 3×3 convolutions and circular
    padding (the grid is periodic), σ = GELU.

    Parameters
    ----------
    in_channels, out_channels : int
    hidden : int
        Channels inside the blocks.
    blocks : int
        Residual blocks (two 3×3 convolutions each).
    dtype : torch.dtype
        Parameter dtype (float32 by default: the convolutions dominate the cost and
        a corrector needs no float64); `forward` casts its input to it and its
        output back.
    zero_init : bool
        Zero the projection, so the network starts as the zero map (a corrector
        that starts by changing nothing).

    Notes
    -----
    Input and output have shape (B, C, H, W).  With ``hidden=64, blocks=3`` and 3
    channels in and out it has 222 019 parameters.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        hidden: int = 64,
        blocks: int = 3,
        *,
        dtype: torch.dtype = torch.float32,
        zero_init: bool = True,
    ):
        super().__init__()

        def conv(cin, cout, k):
            return torch.nn.Conv2d(cin, cout, k, padding=k // 2, padding_mode="circular")

        self.lift = conv(in_channels, hidden, 1)
        self.blocks = torch.nn.ModuleList(
            [torch.nn.ModuleList([conv(hidden, hidden, 3), conv(hidden, hidden, 3)])
             for _ in range(blocks)]
        )  # fmt: skip
        self.project = conv(hidden, out_channels, 1)
        if zero_init:
            with torch.no_grad():
                self.project.weight.zero_()
                self.project.bias.zero_()
        self.to(dtype)
        self.dtype = dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        act = torch.nn.functional.gelu
        h = self.lift(x.to(self.dtype))
        for first, second in self.blocks:
            h = h + second(act(first(act(h))))
        return self.project(h).to(x.dtype)


class Corrector:
    """The solver step P_K and the network C of the hybrid, direct or indirect.

    ``correction: "direct"`` steps s ↦ P_K(s) + C(P_K(s)) (C: 3 → 3 channels);
    ``"indirect"`` steps s ↦ P_K(s; f = C(s)) (C: 3 → 2 channels), the forcing
    f/Δt added to the momentum rows of the implicit step's right-hand side (the
    continuity rows stay zero, so the singular system stays consistent).  With
    `warm_starts` (a `WarmStarts`), a solve given ``keys`` (one per state) starts
    from the solutions stored under them and stores its own.
    """

    def __init__(self, config: dict, net: torch.nn.Module, warm_starts: WarmStarts | None = None):
        self.n, self.dt = config["n"], config["dt"]
        self.A = mac.ns_operator(self.n, self.dt, config["nu"])
        W = mac.wind_matrix(self.n).tocoo()
        index = torch.from_numpy(np.vstack([W.row, W.col]).astype(np.int64))
        self.W = torch.sparse_coo_tensor(
            index, torch.from_numpy(W.data), W.shape, check_invariants=True
        ).coalesce()
        self.scale = torch.from_numpy(mac.rhs_scale(self.n, self.dt))
        self.net = net
        self.correction, self.checkpoint = config["correction"], config["checkpoint"]
        self.warm_starts = warm_starts

    def theta(self, state: torch.Tensor) -> torch.Tensor:
        """Picard parameters θ = [a⁺; a⁻], a = W s, of states (B, 3n²) (differentiable)."""
        a = torch.sparse.mm(self.W, state.T).T
        # a⁺ + a⁻ = a with derivatives summing to 1 also at a = 0 (one upwind side);
        # clamp(min=0) and clamp(max=0) both pass 1 there, counting both sides
        positive = torch.relu(a)
        return torch.cat([positive, a - positive], dim=1)

    def solve(
        self, state: torch.Tensor, solver: pp.KSPSolver, keys=None, forcing=None
    ) -> torch.Tensor:
        """The capped solve P_K(s; f): operator and right-hand side from s, plus the
        forcing f (B, 2n²) on the momentum rows (from the warm starts of `keys`, if any)."""
        starts = self.warm_starts if keys is not None else None
        x0 = None if starts is None else starts.guess(keys)
        b = state * self.scale
        if forcing is not None:
            b = b + torch.cat([forcing / self.dt, torch.zeros_like(state[:, 2 * self.n**2 :])], 1)
        x = pp.solve(self.A, b, solver, theta=self.theta(state), x0=x0)
        if starts is not None:
            starts.store(keys, x)
        return x

    def network(self, state: torch.Tensor) -> torch.Tensor:
        """C on states (B, 3n²): a state correction (direct) or a forcing (indirect)."""
        n = self.n
        return self.net(state.reshape(-1, 3, n, n)).reshape(len(state), -1)

    def step(self, solver: pp.KSPSolver) -> Hybrid:
        """The corrected step with `solver` (`prdp_petsc.lab.training.unroll.Hybrid`)."""

        def physics(state, forcing, keys):
            return self.solve(state, solver, keys, forcing)

        return Hybrid(physics, self.network, correction=self.correction, checkpoint=self.checkpoint)

    def __call__(self, state: torch.Tensor, solver: pp.KSPSolver, keys=None) -> torch.Tensor:
        return self.step(solver)(state, keys)


def hybrid_loss(
    hybrid: Corrector, solver, windows, *, steps=None, solver_grad: bool = True, samples=None
):
    """Summed MSE of an m-step corrected rollout from ``windows[0]`` (B, 3n²)
    against ``windows[1:]`` (`unrolled_loss`); ``solver_grad=False`` detaches each
    solve's input.  `samples` (the windows' indices) key the warm starts of step t
    as ``(t, index)``."""
    keys = None if samples is None else (lambda t: [(t, i) for i in samples])
    return unrolled_loss(
        hybrid.step(solver), windows, steps=steps, solver_grad=solver_grad, keys=keys
    )


def setup(config: dict, seed: int) -> dict:
    """Data, solvers and corrector of a preset: ``train`` windows (3, B, 3n²), ``val``
    trajectories (T + 1, B, 3n²), ``solver`` (capped), ``full`` (to ``rtol_full``),
    ``hybrid`` (`Corrector`)."""
    n, dt, nu = config["n"], config["dt"], config["nu"]
    # training windows (s_t, …, s_t+m) from every start t of the reference trajectories
    traj = reference_data(n, config["n_train"], config["train_steps"], dt, nu, 1000 + seed)
    train = unroll.windows(traj, config["unroll"] + 1, config["window_stride"])
    steps = max(config["val_steps"], config["rollout_steps"])
    val = reference_data(n, config["n_val"], steps, dt, nu, 2000 + seed)
    adjoint = None
    if config["adjoint_rtol"] is not None:
        adjoint = pp.AdjointSettings(rtol=config["adjoint_rtol"], max_it=100_000)
    chosen = {
        "train_solver": config["train_solver"],
        "val_solver": config["val_solver"],
        "correction": config["correction"],
        "val_metric": config["val_metric"],
    }
    for key, value in chosen.items():
        if value not in CHOICES[key]:
            raise ValueError(f"{key} must be one of {CHOICES[key]}, got {value!r}")
    options = SCHUR if config["train_solver"] == "schur" else GMRES
    solver = pp.KSPSolver(
        options,
        prefix="ns2d_",
        max_it=config["k_init"],
        adjoint=adjoint,
        structure=pp.Structure(nullspace=mac.nullspace(n)),
        pc_lag=config["pc_lag"],
    )
    val_solver = config["val_solver"]
    if val_solver == "schur":  # the converged step, reached sooner
        full = pp.KSPSolver(
            SCHUR,
            prefix="ns2d_val_",
            max_it=100_000,
            rtol=config["rtol_full"],
            structure=pp.Structure(nullspace=mac.nullspace(n)),
        )
    else:  # the training solver run to rtol_full (with a fresh PC at every solve)
        full = solver.clone(max_it=100_000, rtol=config["rtol_full"], pc_lag=1)
    out = 3 if config["correction"] == "direct" else 2  # indirect: a momentum forcing
    net = ConvResNet(3, out, hidden=config["hidden"], blocks=config["blocks"])
    hybrid = Corrector(config, net, WarmStarts() if config["warm_start_epochs"] else None)
    return {"train": train, "val": val, "solver": solver, "full": full, "hybrid": hybrid}


def build(config: dict, seed: int) -> lab.Scene:
    parse_routes(config["routes"], ROUTES)  # `compare` runs them; a malformed one fails here
    n = config["n"]
    parts = setup(config, seed)
    train, val, solver, full, hybrid = (
        parts[k] for k in ("train", "val", "solver", "full", "hybrid")
    )
    net = hybrid.net
    n_train, n_val = train.shape[1], val.shape[1]
    optimizer = torch.optim.Adam(net.parameters(), lr=config["lr"])
    epochs, ratio = config["epochs"], config["lr_final"] / config["lr"]

    def lr_factor(epoch: int) -> float:  # cosine decay lr → lr_final, then constant
        return ratio + (1 - ratio) * 0.5 * (1 + math.cos(math.pi * min(epoch / epochs, 1.0)))

    velocity_std = float(train[0].reshape(n_train, 3, -1)[:, :2].std())

    epoch_now = [0]  # the epoch being trained, for the horizon curriculum
    batches = shuffled_batches(n_train, config["batch"])

    def epoch_batches(epoch: int, generator: torch.Generator):
        epoch_now[0] = epoch
        return batches(epoch, generator)

    def loss(idx):
        if config["noise"] > 0:  # one step at a time from noisy inputs
            losses = []
            for t in range(len(train) - 1):
                s = train[t, idx].clone()
                noise = torch.randn(s.shape, dtype=s.dtype) * config["noise"] * velocity_std
                s.view(len(idx), 3, -1)[:, :2] += noise.view(len(idx), 3, -1)[:, :2]
                keys = [(t, i) for i in idx.tolist()]
                losses.append(((hybrid(s, solver, keys) - train[t + 1, idx]) ** 2).mean())
            return sum(losses)
        steps = unroll.horizon(epoch_now[0], config["unroll"], every=config["unroll_curriculum"])
        return hybrid_loss(
            hybrid,
            solver,
            train[:, idx],
            steps=steps,
            solver_grad=config["solver_grad"],
            samples=idx.tolist(),
        )

    # the gradient check's batch: every fifth training window (an epoch may be one batch,
    # and a check differentiates its batch twice: at K and at 2K, 3/5 of an epoch at K)
    check_windows = torch.arange(0, n_train, 5)

    def rollout_states(steps: int, step) -> torch.Tensor:
        with torch.no_grad():
            states, s = [], val[0]
            for _ in range(steps):
                s = step(s)
                states.append(s)
        return torch.stack(states)

    def velocity_errors(states: torch.Tensor) -> np.ndarray:
        """Per-step ‖(û, v̂) − (u, v)‖/‖(u, v)‖ of validation states (T, n_val, 3n²)."""
        steps = len(states)
        pred = states.reshape(steps, n_val, 3, -1)[:, :, :2].flatten(2)
        ref = val[1 : steps + 1].reshape(steps, n_val, 3, -1)[:, :, :2].flatten(2)
        return ((pred - ref).norm(dim=-1) / ref.norm(dim=-1)).mean(-1).numpy()

    corrected = lambda s: hybrid(s, full)  # noqa: E731

    def validate() -> float:
        if config["val_metric"] == "rollout_mean":
            return float(velocity_errors(rollout_states(config["val_steps"], corrected)).mean())
        pred = rollout_states(config["val_steps"], corrected)[-1].reshape(n_val, 3, -1)[:, 0]
        ref = val[config["val_steps"]].reshape(n_val, 3, -1)[:, 0]
        return float((((pred - ref) ** 2).sum(-1) / (ref**2).sum(-1)).mean())

    def rollout() -> np.ndarray:
        return velocity_errors(rollout_states(config["rollout_steps"], corrected))

    def uncorrected_rollout() -> np.ndarray:
        return velocity_errors(
            rollout_states(config["rollout_steps"], lambda s: hybrid.solve(s, full))
        )

    def probe():
        s = val[1, 0].numpy()
        theta = mac.picard_parameters(s, mac.wind_matrix(n))
        return hybrid.A.matrix(theta), s * hybrid.scale.numpy(), None

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=epoch_batches,
        loss=loss,
        check_loss=lambda: loss(check_windows),
        validate=validate,
        rollout=rollout,
        uncorrected_rollout=uncorrected_rollout,
        probe=probe,
        rtol_full=config["rtol_full"],
        epochs=epochs,
        prdp={
            **PAPER,
            "k_init": config["k_init"],
            "k_step": config["k_step"],
            "tau_step": 0.95,
            "ema_window": 4,
            "window": 2,
        },
        scheduler=torch.optim.lr_scheduler.LambdaLR(optimizer, lr_factor),
        compare_ks=config["compare_ks"],
        info={
            "unknowns": 3 * n * n,
            "nnz": hybrid.A.nnz,
            "network_parameters": sum(p.numel() for p in net.parameters()),
            **config,
        },
    )


# the scene's report commands: ``prdp-petsc scene demos/ns2d.py adjoint|energy ...``
COMMANDS = ns2d_reports.commands(sys.modules[__name__])


# -- Things to try --------------------------------------------------------------------------
# * The reference's effective gradient, the solver detached: ``--preset quick_detached``.
# * Correct through the implicit step's forcing: ``--set correction=indirect``.
# * Train on the Schur route: ``--set train_solver=schur``; or ``compare --routes schur``.
# * What the capped adjoint costs and changes:
#   ``prdp-petsc scene demos/ns2d.py adjoint --preset quick --k 8 64``.


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
