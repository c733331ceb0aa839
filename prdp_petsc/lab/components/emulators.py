"""Heat emulators on a mesh: the implicit-Euler P1 step, its data, and a scene that learns it.

The heat scenes ``demos/heat2d.py`` (L-shape) and ``demos/heat3d.py`` (unit cube) are
one learning problem on two meshes, built from a preset by `heat_emulator_build` (what
differs between them is their presets and options prefix) and from arguments by
`heat_emulator_scene`: a network N maps
uⁿ to ûⁿ⁺¹, and the loss compares the *capped* solver step P_K(ûⁿ⁺¹) with the exact
uⁿ⁺² (the paper's mixed chain), or, unrolled m times, each state of the chain
sⁿ⁺² = P_K(N(sⁿ)) with the exact one.  The pieces it is made of are public, so that
tests and other scenes use the same physics and data: `heat_step_system` (the
matrices of one step), `gaussian_bumps` and `bubble` (the initial conditions;
``poisson_sip`` draws its sources with `gaussian_bumps` too), `training_pairs`,
`training_windows` and `emulator_net`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
import torch
from skfem.models.poisson import laplace, mass

from prdp_petsc import KSPSolver, load_mesh, solve

from ..training.rollout import rollout_errors
from ..training.routes import parse_routes
from ..training.scene import Scene, shuffled_batches
from ..training.unroll import windows
from .modal import ModalNet
from .networks import ResidualMLP

__all__ = [
    "DAMPED_JACOBI",
    "HEAT_EMULATOR_SETTINGS",
    "NETWORKS",
    "bubble",
    "emulator_net",
    "gaussian_bumps",
    "heat_emulator_build",
    "heat_emulator_scene",
    "heat_step_system",
    "training_pairs",
    "torch_sparse",
    "training_windows",
]

#: The paper's solver: damped Jacobi (Richardson, scale 0.8, with PCJACOBI).
DAMPED_JACOBI = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.8}

#: The networks `emulator_net` builds.
NETWORKS = ("modal", "mlp")


def gaussian_bumps(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Random smooth fields: each a sum of 4 Gaussian bumps.

    Parameters
    ----------
    points : numpy.ndarray, shape (dim, n)
        Where the fields are evaluated (a mesh's nodes).
    count : int
        Number of fields.
    rng : numpy.random.Generator
        Draws, per bump, a centre (uniform in the bounding box of `points`), a width
        (8-25 % of the box's largest side) and an amplitude (uniform in [-1, 1]).

    Returns
    -------
    numpy.ndarray, shape (count, n)
    """
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


def heat_step_system(mesh, dt: float, kappa: float = 1.0) -> tuple:
    """The matrices of one implicit-Euler step of ``u_t = κ Δu`` with P1 elements.

    Parameters
    ----------
    mesh : skfem.Mesh
        A triangle (2D) or tetrahedron (3D) mesh; u = 0 on its whole boundary.
    dt, kappa : float
        Time step and diffusivity.

    Returns
    -------
    A, B : scipy.sparse.csr_matrix, shape (n, n)
        ``A = (M + Δt κ K)_II`` (sorted indices) and ``B = M_II`` on the n interior
        nodes, so that a step is ``A uⁿ⁺¹ = B uⁿ``.
    interior : numpy.ndarray
        The interior nodes' indices.
    basis : skfem.Basis
        The P1 basis on `mesh`.
    """
    element = skfem.ElementTetP1() if mesh.dim() == 3 else skfem.ElementTriP1()
    basis = skfem.Basis(mesh, element)
    M, K = mass.assemble(basis), laplace.assemble(basis)
    interior = basis.complement_dofs(basis.get_dofs())
    A = (M + dt * kappa * K)[interior][:, interior].tocsr()
    B = M[interior][:, interior].tocsr()
    A.sort_indices()
    return A, B, interior, basis


def bubble(A: sp.csr_matrix, B: sp.csr_matrix, dt: float) -> np.ndarray:
    """The bubble d (−Δd = 1, d = 0 on the boundary, max d = 1) on the interior nodes.

    Multiplying `gaussian_bumps` by it gives fields that vanish smoothly on the
    boundary, so a step from them carries no boundary layer.

    Parameters
    ----------
    A, B : scipy.sparse matrix
        The step matrices of `heat_step_system`: ``K = (A − B) / Δt`` recovers the
        stiffness matrix from ``A = M + Δt K`` and ``B = M``.
    dt : float
        The time step `A` was built with.
    """
    d = spla.spsolve(((A - B) / dt).tocsc(), B @ np.ones(A.shape[0]))
    return d / d.max()


def training_pairs(traj: torch.Tensor, spans: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs ``(uₜ, uₜ₊₂)`` for t < `spans` from trajectories of shape (steps + 1, samples, n).

    Several starting times show the network the smoother states it meets in a
    rollout, not only the initial conditions.  Each pair is scaled by ``‖uₜ‖`` (the
    step is linear), so late, decayed states weigh as much as early ones.  The
    windows of `training_windows` with one step.
    """
    inputs, outputs = training_windows(traj, spans, 1)
    return inputs, outputs


def training_windows(traj: torch.Tensor, spans: int, steps: int) -> torch.Tensor:
    """Windows ``(uₜ, uₜ₊₂, …, uₜ₊₂ₘ)``, m = `steps`, for t < `spans`, scaled by ``‖uₜ‖``.

    The targets of an m-step unroll of the mixed chain, each of whose steps spans two
    time steps; ``steps=1`` gives the pairs of `training_pairs`.

    Parameters
    ----------
    traj : torch.Tensor, shape (T + 1, samples, n)
        Exact trajectories, T + 1 ≥ `spans` + 2 `steps`.
    spans, steps : int
        Number of starting times and of chain steps, both ≥ 1.

    Returns
    -------
    torch.Tensor, shape (steps + 1, spans · samples, n)
        Ordered by starting time, then by trajectory; window i is divided by the
        norm of its first state.
    """
    if spans < 1 or steps < 1:
        raise ValueError(f"spans and steps must be >= 1, got {spans}, {steps}")
    if len(traj) < spans + 2 * steps:
        raise ValueError(
            f"{spans} starts of {steps}-step windows need {spans + 2 * steps} states, "
            f"the trajectories have {len(traj)}"
        )
    w = windows(traj[: spans + 2 * steps], 2 * steps + 1)[::2]  # by start, then trajectory
    return w / w[0].norm(dim=-1, keepdim=True)


def emulator_net(
    net: str, A: sp.csr_matrix, B: sp.csr_matrix, *, dt: float, modes: int, width: int, depth: int
) -> torch.nn.Module:
    """The network N of a heat emulator.

    Parameters
    ----------
    net : {"modal", "mlp"}
        ``"modal"``: a `~prdp_petsc.lab.components.modal.ModalNet` with one weight for each
        of the `modes` lowest eigenmodes of ``K φ = λ M φ``.  ``"mlp"``: a
        `~prdp_petsc.lab.components.networks.ResidualMLP` over the nodal values, `width`
        wide and `depth` hidden layers deep (the reference's emulator class).
    A, B, dt
        The step matrices of `heat_step_system` and their time step.
    modes, width, depth : int
        The sizes above; each network reads only its own.
    """
    if net == "modal":
        return ModalNet((A - B) / dt, B, modes)
    if net == "mlp":
        return ResidualMLP(A.shape[0], width, depth)
    raise ValueError(f'net must be "modal" or "mlp", got {net!r}')


def heat_emulator_scene(
    mesh,
    seed: int,
    *,
    prefix: str,
    dt: float,
    net: str,
    modes: int,
    width: int,
    depth: int,
    warm_start: bool,
    spans: int,
    n_train: int,
    n_val: int,
    val_steps: int,
    rollout_steps: int,
    unroll: int,
    epochs: int,
    batch: int,
    lr: float,
    gamma: float,
    k_init: int,
    k_step: int,
    info: dict | None = None,
    options: dict | None = None,
) -> Scene:
    """The heat emulator scene on `mesh`: N learns the step through a capped solve.

    Data: ``n_train + n_val`` initial conditions (`gaussian_bumps` times `bubble`,
    drawn from ``numpy.random.default_rng(seed)``) stepped exactly (splu) for
    ``max(val_steps, rollout_steps, spans + 2 unroll − 1)`` steps.  Training windows
    (`training_windows`) start at t < `spans` of the training trajectories; the
    validation metric is the mean normalised error of a `val_steps`-step rollout
    of N from the held-out initial conditions, and ``Scene.rollout`` the per-step
    error of a `rollout_steps`-step one.

    Loss: the chain s ← P_K(B N(s)) (``A s' = B N(s)`` capped at K iterations) runs
    ``unroll`` = m times from uₜ under autograd; the k-th state is compared with the
    exact uₜ₊₂ₖ, each term ‖·‖² averaged over the batch and divided by the square of
    the mean norm of the targets uₜ₊₂, and the loss is their sum over k = 1 … m.
    m = 1 is the one-step mixed chain.

    Parameters
    ----------
    mesh : skfem.Mesh
        A triangle or tetrahedron mesh (`prdp_petsc.load_mesh`).
    seed : int
        Seed of the data (the network's initial weights come from torch's seed).
    prefix : str
        Options prefix of the scene's solver.
    dt : float
        Time step (κ = 1).
    net, modes, width, depth
        The network, see `emulator_net`.
    warm_start : bool
        Start each capped solve from its input ûⁿ⁺¹ (PETSc's nonzero initial guess),
        as a time stepper would, and K_full's probe from the states it steps; else
        from zero.
    spans, n_train, n_val, val_steps, rollout_steps : int
        Data sizes, as above.
    unroll : int
        m, the chain steps of the loss (≥ 1), as above.
    epochs, batch : int
        Default number of epochs and mini-batch size.
    lr, gamma : float
        Adam's learning rate and its decay per epoch.
    k_init, k_step : int
        PRDP's K₀ and ΔK.
    info : dict, optional
        Settings to record in ``Scene.info`` after the sizes (a scene's preset).
    options : dict, optional
        PETSc options of the solver; default `DAMPED_JACOBI`.

    Returns
    -------
    Scene
        One solver (fixed mode, implicit gradients); the probe is one step from the
        first validation states.

    Notes
    -----
    The solver takes ``-{prefix}ksp_type``, ``-{prefix}pc_type`` and every other
    KSP option from the command line (``-heat2d_ksp_type cg -heat2d_pc_type icc``).
    """
    if net not in NETWORKS:
        raise ValueError(f'net must be "modal" or "mlp", got {net!r}')
    if spans < 1 or n_train < 1 or n_val < 1:
        raise ValueError(f"spans, n_train and n_val must be >= 1, got {spans}, {n_train}, {n_val}")
    if unroll < 1:
        raise ValueError(f"unroll must be >= 1, got {unroll}")
    A, B, interior, _ = heat_step_system(mesh, dt)
    n = A.shape[0]
    rng = np.random.default_rng(seed)
    steps = max(val_steps, rollout_steps, 2)
    u0 = gaussian_bumps(mesh.p[:, interior], n_train + n_val, rng)
    u0 = u0 * bubble(A, B, dt)  # vanish smoothly on the boundary
    lu = spla.splu(A.tocsc())
    traj = [u0]
    for _ in range(max(steps, spans + 2 * unroll - 1)):
        traj.append(lu.solve(B @ traj[-1].T).T)
    traj = torch.from_numpy(np.stack(traj))  # (steps + 1, samples, n)
    targets = training_windows(traj[:, :n_train], spans, unroll)  # (m + 1, windows, n)
    val_traj = traj[:, n_train:]
    scale = float(targets[1].norm(dim=-1).mean())

    B_t = torch_sparse(B)
    solver = KSPSolver(DAMPED_JACOBI if options is None else options, prefix=prefix, max_it=1)
    model = emulator_net(net, A, B, dt=dt, modes=modes, width=width, depth=depth)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)

    def loss(idx):
        state, total = targets[0, idx], 0
        for target in targets[1:, idx]:
            u1_hat = model(state)
            rhs = (B_t @ u1_hat.T).T
            state = solve(A, rhs, solver, x0=u1_hat if warm_start else None)
            total = total + ((state - target) ** 2).sum(-1).mean() / scale**2
        return total

    def rollout():
        return rollout_errors(model, val_traj[0], val_traj[1 : rollout_steps + 1])

    def validate():
        return float(rollout_errors(model, val_traj[0], val_traj[1 : val_steps + 1]).mean())

    def probe():
        """One step from the first validation states (from them as the guess if warm)."""
        states = val_traj[1].numpy()
        return A, (B @ states.T).T, states if warm_start else None

    return Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=shuffled_batches(targets.shape[1], batch),
        loss=loss,
        validate=validate,
        rollout=rollout,
        probe=probe,
        rtol_full=1e-6,
        epochs=epochs,
        prdp={  # the rollout metric is deterministic and smooth: little smoothing needed
            "k_init": k_init,
            "k_step": k_step,
            "tau_step": 0.9,
            "ema_window": 2,
            "window": 2,
        },
        scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=gamma),
        info={
            "n": n,
            "nnz": int(A.nnz),
            "network_parameters": sum(p.numel() for p in model.parameters()),
            **(info or {}),
        },
    )


#: The settings `heat_emulator_build` passes to `heat_emulator_scene` by name; a heat
#: emulator preset names these, ``mesh``, ``refine`` and ``routes``.
HEAT_EMULATOR_SETTINGS = (
    "dt", "net", "modes", "width", "depth", "warm_start", "spans", "n_train", "n_val",
    "val_steps", "rollout_steps", "unroll", "epochs", "batch", "lr", "gamma", "k_init",
    "k_step",
)  # fmt: skip


def heat_emulator_build(config: dict, seed: int, *, prefix: str) -> Scene:
    """The ``build`` of a heat emulator scene (``demos/heat2d.py``, ``demos/heat3d.py``).

    Loads the shipped mesh ``config["mesh"]`` refined ``config["refine"]`` times
    (`prdp_petsc.load_mesh`), checks ``config["routes"]`` (the KSP/PC pairs that
    ``compare`` also runs, `prdp_petsc.lab.training.routes.parse_routes`; a malformed
    one fails here), and returns `heat_emulator_scene` with every setting of
    `HEAT_EMULATOR_SETTINGS` read from `config`, the solver's options prefix `prefix`
    and the whole preset recorded in ``Scene.info``.
    """
    parse_routes(config["routes"])
    mesh = load_mesh(config["mesh"], refine=config["refine"])
    settings = {key: config[key] for key in HEAT_EMULATOR_SETTINGS}
    return heat_emulator_scene(mesh, seed, prefix=prefix, info=config, **settings)


def torch_sparse(M: sp.spmatrix) -> torch.Tensor:
    """`M` as a coalesced torch sparse COO tensor."""
    M = M.tocoo()
    index = torch.from_numpy(np.vstack([M.row, M.col]).astype(np.int64))
    return torch.sparse_coo_tensor(
        index, torch.from_numpy(M.data), M.shape, check_invariants=True
    ).coalesce()
