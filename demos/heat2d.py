"""Heat 2D emulator on an unstructured mesh, trained through a capped PETSc solve.

PDE: u_t = ∇·(κ∇u) on the L-shaped domain (the shipped gmsh mesh ``lshape``),
u = 0 on the boundary, κ = 1.  Discretisation: P1 finite elements (scikit-fem),
implicit Euler, one step ``(M + Δt K) uⁿ⁺¹ = M uⁿ`` on the interior nodes
(Dirichlet nodes eliminated).  Initial conditions: sums of random Gaussian bumps
times the bubble (−Δd = 1), so they vanish smoothly on the boundary.

Solver in the loop: damped Jacobi (``richardson`` + ``jacobi``, scale 0.8, the
paper's solver) in fixed mode, K = ``max_it`` iterations; implicit (adjoint)
gradients.  The solve starts from its input ûⁿ⁺¹ (``solve(..., x0=)``, PETSc's
nonzero initial guess), as a time stepper would: the step changes smooth fields
little, so the slow, smooth Jacobi modes start almost converged.  From zero
(``warm_start: False``) those modes carry the capped solve's bias, the network
learns to undo it, and its rollout needs K ≈ 0.8 K_full to match full fidelity.
K_full counts the iterations from the guess to PETSc's default test ``‖r‖ ≤
10⁻⁶ ‖b‖`` (68 instead of 91 on ``paper``), so the baseline gains from the guess
too.  Any PETSc solver is one option away (``-heat2d_ksp_type cg
-heat2d_pc_type icc``); ``compare --routes cg/icc`` runs PRDP and full fidelity
with it as well and says which route is fastest.

Learning problem (the paper's mixed chain): a network N maps uⁿ to ûⁿ⁺¹, the
loss compares the *capped* solver step P_K(ûⁿ⁺¹) with the exact uⁿ⁺², so a
small K biases what N learns.  Training pairs (uₜ, uₜ₊₂) start at t = 0, …,
``spans`` − 1 of each training trajectory, so N sees the smoother states a rollout
meets, not only initial conditions.  N is a `prdp_petsc.training.modal.ModalNet`:
one learned weight per eigenmode of ``K φ = λ M φ`` (the mesh's Fourier basis;
the spectral layer of a Fourier neural operator), ``modes`` of them.  It replaced
`prdp_petsc.training.networks.MeshNet` (message passing over the mesh's edges),
which plateaued at ≈ 12 % rollout error here and diverged in 3D: the solve damps
the high-frequency part of N's error, so the loss barely constrains a local
network there, and Adam on correlated edge weights is badly conditioned.  Modal
coefficients are M-orthonormal, each weight is fitted by its own mode, and the
modes N drops are those the step damps most.  Validation metric: the mean
normalised error of a 10-step autoregressive rollout of N on held-out initial
conditions; the harness also records a 30-step rollout curve.

Presets: ``quick`` (tests), ``paper`` (5 457 unknowns, Δt κ/h² ≈ 1.2) and
``stiff`` (Δt κ/h² ≈ 6e3: damped Jacobi needs thousands of iterations, CG +
ICC about 70 — there the PC choice decides).  ``paper_mlp`` is ``paper`` with the
reference's emulator class instead of ModalNet (``net: "mlp"``: a
`~prdp_petsc.training.networks.ResidualMLP` over the nodal values) and 64 training
trajectories: the control experiment of the README, where the network does about
as well as the identity map (better on seed 0, worse on seed 1), so its own error
hides the solver's.

Run ``python demos/heat2d.py compare --preset paper --routes cg/icc --out results/heat2d``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
import torch
from skfem.models.poisson import laplace, mass

import prdp_petsc as pp
from prdp_petsc.training.modal import ModalNet
from prdp_petsc.training.networks import ResidualMLP
from prdp_petsc.training.rollout import rollout_errors
from prdp_petsc.training.scene import shuffled_batches

PRESETS = {
    "quick": {
        "mesh": "lshape",
        "refine": 0,
        "dt": 1e-3,
        "modes": 16,
        "spans": 4,
        "n_train": 8,
        "n_val": 4,
        "val_steps": 10,
        "rollout_steps": 20,
        "epochs": 8,
        "batch": 8,
        "lr": 3e-2,
        "gamma": 0.9,
        "k_init": 4,
        "k_step": 4,
    },
    "paper": {
        "mesh": "lshape",
        "refine": 1,
        "dt": 2e-4,
        "modes": 128,
        "spans": 6,
        "n_train": 32,
        "n_val": 8,
        "val_steps": 10,
        "rollout_steps": 30,
        "epochs": 20,
        "batch": 16,
        "lr": 2e-2,
        "gamma": 0.9,
        "k_init": 10,
        "k_step": 20,
    },
    "stiff": {
        "mesh": "lshape",
        "refine": 1,
        "dt": 1.0,
        "modes": 64,
        "spans": 4,
        "n_train": 16,
        "n_val": 8,
        "val_steps": 10,
        "rollout_steps": 20,
        "epochs": 10,
        "batch": 16,
        "lr": 2e-2,
        "gamma": 0.9,
        "k_init": 50,
        "k_step": 50,
    },
}

# the paper's emulator class: a residual MLP over the nodal values (see the docstring)
_MLP = {"net": "mlp", "width": 128, "depth": 2, "lr": 1e-3, "gamma": 0.95, "k_init": 4, "k_step": 4}
PRESETS["paper_mlp"] = {**PRESETS["paper"], **_MLP, "n_train": 64}

JACOBI = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.8}


def bumps(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` random fields: sums of 4 Gaussian bumps (centres in the bounding box)."""
    lo, hi = points.min(axis=1), points.max(axis=1)
    size = float(np.max(hi - lo))
    fields = np.zeros((count, points.shape[1]))
    for i in range(count):
        for _ in range(4):
            centre = lo + (hi - lo) * rng.random(len(lo))
            width = size * rng.uniform(0.08, 0.25)
            r2 = ((points - centre[:, None]) ** 2).sum(axis=0)
            fields[i] += rng.uniform(-1, 1) * np.exp(-r2 / (2 * width**2))
    return fields


def heat_step_system(mesh, dt: float, kappa: float = 1.0):
    """``(A, B, interior, basis)``: ``A = (M + Δt κ K)_II`` and ``B = M_II`` in CSR."""
    element = skfem.ElementTetP1() if mesh.dim() == 3 else skfem.ElementTriP1()
    basis = skfem.Basis(mesh, element)
    M, K = mass.assemble(basis), laplace.assemble(basis)
    interior = basis.complement_dofs(basis.get_dofs())
    A = (M + dt * kappa * K)[interior][:, interior].tocsr()
    B = M[interior][:, interior].tocsr()
    A.sort_indices()
    return A, B, interior, basis


def build_emulator(config: dict, seed: int, *, prefix: str) -> pp.Scene:
    """The heat emulator scene on ``config["mesh"]`` (2D or 3D); shared with heat3d."""
    mesh = pp.load_mesh(config["mesh"], refine=config["refine"])
    A, B, interior, _ = heat_step_system(mesh, config["dt"])
    n = A.shape[0]
    rng = np.random.default_rng(seed)
    steps = max(config["val_steps"], config["rollout_steps"], 2)
    u0 = bumps(mesh.p[:, interior], config["n_train"] + config["n_val"], rng)
    u0 = u0 * bubble(A, B, config["dt"])  # vanish smoothly on the boundary
    lu = spla.splu(A.tocsc())
    traj = [u0]
    for _ in range(max(steps, config["spans"] + 1)):
        traj.append(lu.solve(B @ traj[-1].T).T)
    traj = torch.from_numpy(np.stack(traj))  # (steps + 1, samples, n)
    n_train = config["n_train"]
    train_in, train_out = training_pairs(traj[:, :n_train], config["spans"])
    val_traj = traj[:, n_train:]
    scale = float(train_out.norm(dim=-1).mean())

    B_t = _torch_csr(B)
    warm = config.get("warm_start", True)
    solver = pp.KSPSolver(JACOBI, prefix=prefix, max_it=1)
    net = emulator_net(config, A, B)
    optimizer = torch.optim.Adam(net.parameters(), lr=config["lr"])
    n_train = len(train_in)

    def loss(idx):
        u1_hat = net(train_in[idx])
        rhs = (B_t @ u1_hat.T).T
        u2_hat = pp.solve(A, rhs, solver, x0=u1_hat if warm else None)
        return ((u2_hat - train_out[idx]) ** 2).sum(-1).mean() / scale**2

    def rollout():
        return rollout_errors(net, val_traj[0], val_traj[1 : config["rollout_steps"] + 1])

    def validate():
        return float(rollout_errors(net, val_traj[0], val_traj[1 : config["val_steps"] + 1]).mean())

    return pp.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=shuffled_batches(n_train, config["batch"]),
        loss=loss,
        validate=validate,
        rollout=rollout,
        probe=lambda: probe(A, B, val_traj[1].numpy(), warm),
        rtol_full=1e-6,
        epochs=config["epochs"],
        prdp={  # the rollout metric is deterministic and smooth: little smoothing needed
            "k_init": config["k_init"],
            "k_step": config["k_step"],
            "tau_step": 0.9,
            "ema_window": 2,
            "window": 2,
        },
        scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=config["gamma"]),
        info={"n": n, "nnz": int(A.nnz), "network_parameters": _count(net), **config},
    )


def emulator_net(config: dict, A, B) -> torch.nn.Module:
    """The network N: `ModalNet` (``net: "modal"``) or a residual MLP over nodal values."""
    kind = config.get("net", "modal")
    if kind == "modal":
        return ModalNet((A - B) / config["dt"], B, config["modes"])
    if kind == "mlp":
        return ResidualMLP(A.shape[0], config["width"], config["depth"])
    raise ValueError(f'net must be "modal" or "mlp", got {kind!r}')


def probe(A, B, states: np.ndarray, warm: bool) -> tuple:
    """K_full's probe: one step from `states` (from them as the guess if `warm`)."""
    rhs = (B @ states.T).T
    return (A, rhs, states) if warm else (A, rhs)


def bubble(A: sp.csr_matrix, B: sp.csr_matrix, dt: float) -> np.ndarray:
    """The bubble d (−Δd = 1, d = 0 on the boundary, max d = 1) on the unknowns.

    ``K = (A − B) / Δt`` recovers the stiffness matrix from ``A = M + Δt K``, ``B = M``.
    """
    d = spla.spsolve(((A - B) / dt).tocsc(), B @ np.ones(A.shape[0]))
    return d / d.max()


def training_pairs(traj: torch.Tensor, spans: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs ``(uₜ, uₜ₊₂)`` for t < `spans` from trajectories (steps + 1, samples, n).

    Several starting times show the network the smoother states it meets in a
    rollout, not only the initial conditions.  Each pair is scaled by ``‖uₜ‖`` (the
    step is linear), so late, decayed states weigh as much as early ones.
    """
    inputs = traj[:spans].reshape(-1, traj.shape[-1])
    norms = inputs.norm(dim=-1, keepdim=True)
    return inputs / norms, traj[2 : spans + 2].reshape(-1, traj.shape[-1]) / norms


def _torch_csr(M: sp.csr_matrix) -> torch.Tensor:
    M = M.tocoo()
    index = torch.from_numpy(np.vstack([M.row, M.col]).astype(np.int64))
    return torch.sparse_coo_tensor(
        index, torch.from_numpy(M.data), M.shape, check_invariants=True
    ).coalesce()


def _count(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def build(config: dict, seed: int) -> pp.Scene:
    return build_emulator(config, seed, prefix="heat2d_")


if __name__ == "__main__":
    from prdp_petsc.cli import scene_main

    raise SystemExit(scene_main(__file__))
