"""Heat on a mesh: a learned time stepper, trained through a capped PETSc solve.

PDE: u_t = ∇·(κ∇u), κ = 1, u = 0 on the boundary, on one of two shipped gmsh meshes:
the L-shaped domain ``lshape`` (triangles, presets ``quick``, ``paper``, ``stiff``,
``paper_mlp``) or the unit cube ``box3d`` (tetrahedra, presets ``quick3d`` and
``paper3d``).  Discretisation: P1 finite elements (scikit-fem), implicit Euler, one
step ``(M + Δt K) uⁿ⁺¹ = M uⁿ`` on the interior nodes (Dirichlet nodes eliminated).

What it shows: a network N learns the step through a solver it cannot run to
convergence.  The loss compares the *capped* solver step P_K(ûⁿ⁺¹) (damped Jacobi,
K iterations, implicit gradients) with the exact uⁿ⁺² (the paper's mixed chain), so a
small K biases what N learns, and PRDP raises K only as far as N's rollouts need.
The file reads top to bottom: the mesh, the assembly of a step, the capped
`KSPSolver`, the network, the training data, and the scene it hands to the harness,
which runs the PRDP loop.

Run ``python demos/heat.py compare --preset paper --routes cg/icc --out results/heat2d``
(``--preset paper3d`` for the cube).  The results pages recorded the 2D presets as
``demos/heat2d.py`` and the 3D ones as ``demos/heat3d.py --preset quick|paper``, before
the two scenes became this file.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
import torch
from skfem.models.poisson import laplace, mass

from prdp_petsc import KSPSolver, load_mesh, solve
from prdp_petsc.lab.components.emulators import gaussian_bumps, torch_sparse
from prdp_petsc.lab.components.networks import mlp
from prdp_petsc.lab.training.rollout import rollout_errors
from prdp_petsc.lab.training.routes import parse_routes
from prdp_petsc.lab.training.scene import Scene, shuffled_batches
from prdp_petsc.lab.training.unroll import windows
from prdp_petsc.prdp import PAPER

# -- 1. The mesh --------------------------------------------------------------------------
# ``load_mesh(name, refine=r)`` reads a shipped gmsh mesh and refines it r times:
# ``lshape`` has 1 325 interior nodes, 5 457 once refined; ``box3d`` 465 and 5 146.
# The setting ``mesh`` picks it, and with it the solver's options prefix (below).

# -- 2. Assembly: one implicit-Euler step --------------------------------------------------


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

    Initial conditions are `gaussian_bumps` times d, so they vanish smoothly on the
    boundary and a step from them carries no boundary layer.  ``K = (A − B) / Δt``
    recovers the stiffness matrix from the step matrices of `heat_step_system`.
    """
    d = spla.spsolve(((A - B) / dt).tocsc(), B @ np.ones(A.shape[0]))
    return d / d.max()


# -- 3. The solver in the loop -------------------------------------------------------------
# The paper's solver, damped Jacobi: Richardson with scale 0.8 and PCJACOBI.  The harness
# sets ``max_it`` = K each epoch and the solver runs exactly K iterations (``rtol`` 0).
# Every KSP option also comes from the command line under the prefix ``heat2d_`` on the
# L-shape and ``heat3d_`` on the cube (``-heat2d_ksp_type cg -heat2d_pc_type icc``,
# ``-heat3d_ksp_monitor``): the prefixes the two meshes had as two scenes, so the
# commands on the docs pages keep working.  The step matrix M + Δt K is SPD, so CG with
# ICC or GAMG solves it too: the ``routes`` that ``compare`` also runs.
DAMPED_JACOBI = {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 0.8}

# -- 4. The network ------------------------------------------------------------------------


def laplacian_modes(stiffness, mass, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The `count` smallest eigenpairs of ``K φ = λ M φ`` (shift-invert around 0).

    Parameters
    ----------
    stiffness, mass : scipy.sparse matrix, shape (n, n)
        Symmetric positive definite stiffness K (Dirichlet nodes eliminated) and mass M.
    count : int
        Number of modes, ``1 <= count < n``.

    Returns
    -------
    eigenvalues : numpy.ndarray, shape (count,)
        Ascending.
    modes : numpy.ndarray, shape (n, count)
        M-orthonormal: ``modesᵀ M modes = I``.
    """
    n = stiffness.shape[0]
    if not 1 <= count < n:
        raise ValueError(f"count must lie in [1, {n - 1}], got {count}")
    K, M = sp.csc_matrix(stiffness), sp.csc_matrix(mass)
    start = np.ones(n)  # a fixed start vector: the same modes (and signs) every call
    values, modes = spla.eigsh(K, k=count, M=M, sigma=0.0, which="LM", v0=start)
    order = np.argsort(values)
    return values[order], modes[:, order]


class ModalNet(torch.nn.Module):
    """``N(u) = Φ (w ⊙ Φᵀ M u)``: a learned multiplier per Laplacian eigenmode.

    Parameters
    ----------
    stiffness, mass : scipy.sparse matrix, shape (n, n)
        Stiffness and mass of the unknowns (see `laplacian_modes`).
    modes : int
        Number m of eigenmodes kept.

    Notes
    -----
    The spectral layer of a Fourier neural operator, with one channel, in the mesh's
    own eigenbasis: input and output have shape (B, n) or (n,) (float64).  A weight per
    mode, rather than a dense m × m matrix, keeps rollouts sound: a dense matrix trained
    through the solve reached a small one-step loss yet had eigenvalues above one in
    directions the data barely excite, and its rollouts grew.  Each weight is fitted by
    its own mode's content and is the map's eigenvalue there.  The weights start at
    one, so N starts as the M-orthogonal projection onto the kept modes; the modes it
    drops are those the step damps most, and a rollout cannot amplify them.
    """

    def __init__(self, stiffness, mass, modes: int):
        super().__init__()
        eigenvalues, phi = laplacian_modes(stiffness, mass, modes)
        self.register_buffer("eigenvalues", torch.from_numpy(eigenvalues))
        self.register_buffer("phi", torch.from_numpy(np.ascontiguousarray(phi)))
        self.register_buffer(
            "project", torch.from_numpy(np.ascontiguousarray((sp.csr_matrix(mass) @ phi).T))
        )
        self.n = phi.shape[0]
        self.weight = torch.nn.Parameter(torch.ones(modes, dtype=torch.float64))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        if u.shape[-1] != self.n:
            raise ValueError(f"ModalNet expects (batch, {self.n}), got {tuple(u.shape)}")
        return ((u @ self.project.T) * self.weight) @ self.phi.T


class ResidualMLP(torch.nn.Module):
    """``N(u) = u + MLP(u)`` over a field's n nodal values (float64, GELU).

    Parameters
    ----------
    n : int
        Number of values in and out.
    width, depth : int
        Hidden width and number of hidden layers (``Linear → GELU`` each).

    Notes
    -----
    The last layer starts at zero, so N starts as the identity: a time step of a
    smooth field is close to it.  N sees the field as a vector, not the mesh: it
    learns the step from data alone, and with few samples against n inputs its
    error stays far above a mesh-aware network's (the ``paper_mlp`` preset).
    """

    def __init__(self, n: int, width: int, depth: int):
        super().__init__()
        self.mlp = mlp(n, n, width, depth)
        torch.nn.init.zeros_(self.mlp[-1].weight)
        torch.nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return u + self.mlp(u)


def emulator_net(
    net: str, A: sp.csr_matrix, B: sp.csr_matrix, *, dt: float, modes: int, width: int, depth: int
) -> torch.nn.Module:
    """The network N: ``"modal"``, a `ModalNet` on the `modes` lowest eigenmodes, or
    ``"mlp"``, the reference's emulator class (a `ResidualMLP` over the nodal values,
    `width` wide and `depth` hidden layers deep).  `A`, `B` and `dt` are those of
    `heat_step_system`; each network reads only its own sizes."""
    if net == "modal":
        return ModalNet((A - B) / dt, B, modes)
    if net == "mlp":
        return ResidualMLP(A.shape[0], width, depth)
    raise ValueError(f'net must be "modal" or "mlp", got {net!r}')


# -- 5. The training data ------------------------------------------------------------------


def training_windows(traj: torch.Tensor, spans: int, steps: int) -> torch.Tensor:
    """Windows ``(uₜ, uₜ₊₂, …, uₜ₊₂ₘ)``, m = `steps`, for t < `spans`, scaled by ``‖uₜ‖``.

    The targets of an m-step unroll of the mixed chain, each of whose steps spans two
    time steps.  Several starting times show N the smoother states it meets in a
    rollout, not only initial conditions; the scaling (the step is linear) makes late,
    decayed states weigh as much as early ones.

    Parameters
    ----------
    traj : torch.Tensor, shape (T + 1, samples, n)
        Exact trajectories, T + 1 ≥ `spans` + 2 `steps`.
    spans, steps : int
        Number of starting times and of chain steps, both ≥ 1.

    Returns
    -------
    torch.Tensor, shape (steps + 1, spans · samples, n)
        Ordered by starting time, then by trajectory.
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


# -- 6. The scene, handed to the harness ---------------------------------------------------


def build(config: dict, seed: int) -> Scene:
    """The heat emulator scene of a preset: N learns the step through a capped solve.

    Data: ``n_train + n_val`` initial conditions (`gaussian_bumps` times `bubble`, from
    ``numpy.random.default_rng(seed)``) stepped exactly (splu).  Loss: the chain
    s ← P_K(B N(s)) (``A s' = B N(s)`` capped at K iterations, from N(s) as the initial
    guess where ``warm_start``) runs ``unroll`` = m times from uₜ under autograd; its
    k-th state is compared with the exact uₜ₊₂ₖ, each term ‖·‖² averaged over the batch
    and divided by the square of the targets' mean norm.  Validation metric: the mean
    normalised error of a ``val_steps``-step rollout of N from the held-out initial
    conditions; ``Scene.rollout`` is the per-step error of a ``rollout_steps``-step one.
    The network's initial weights come from torch's seed.
    """
    parse_routes(config["routes"])  # a malformed route fails here, not in `compare`
    spans, n_train, n_val, unroll = (config[k] for k in ("spans", "n_train", "n_val", "unroll"))
    if spans < 1 or n_train < 1 or n_val < 1:
        raise ValueError(f"spans, n_train and n_val must be >= 1, got {spans}, {n_train}, {n_val}")
    if unroll < 1:
        raise ValueError(f"unroll must be >= 1, got {unroll}")
    if config["net"] not in ("modal", "mlp"):
        raise ValueError(f'net must be "modal" or "mlp", got {config["net"]!r}')
    dt, warm_start = config["dt"], config["warm_start"]
    val_steps, rollout_steps = config["val_steps"], config["rollout_steps"]

    # mesh and assembly (sections 1 and 2)
    mesh = load_mesh(config["mesh"], refine=config["refine"])
    A, B, interior, _ = heat_step_system(mesh, dt)

    # exact trajectories: training windows from the first n_train, validation the rest
    rng = np.random.default_rng(seed)
    u0 = gaussian_bumps(mesh.p[:, interior], n_train + n_val, rng) * bubble(A, B, dt)
    steps = max(val_steps, rollout_steps, 2, spans + 2 * unroll - 1)
    lu = spla.splu(A.tocsc())
    traj = [u0]
    for _ in range(steps):
        traj.append(lu.solve(B @ traj[-1].T).T)
    traj = torch.from_numpy(np.stack(traj))  # (steps + 1, samples, n)
    targets = training_windows(traj[:, :n_train], spans, unroll)  # (m + 1, windows, n)
    val_traj = traj[:, n_train:]
    scale = float(targets[1].norm(dim=-1).mean())

    # the capped solver (section 3) and the network (section 4)
    solver = KSPSolver(DAMPED_JACOBI, prefix=f"heat{mesh.dim()}d_", max_it=1)
    B_t = torch_sparse(B)
    model = emulator_net(config["net"], A, B, dt=dt, modes=config["modes"],
                         width=config["width"], depth=config["depth"])  # fmt: skip
    optimizer = torch.optim.Adam(model.parameters(), lr=config["lr"])

    def loss(idx):
        state, total = targets[0, idx], 0
        for target in targets[1:, idx]:
            u1_hat = model(state)
            rhs = (B_t @ u1_hat.T).T
            state = solve(A, rhs, solver, x0=u1_hat if warm_start else None)
            total = total + ((state - target) ** 2).sum(-1).mean() / scale**2
        return total

    def validate():
        return float(rollout_errors(model, val_traj[0], val_traj[1 : val_steps + 1]).mean())

    def rollout():
        return rollout_errors(model, val_traj[0], val_traj[1 : rollout_steps + 1])

    def probe():
        """One step from the first validation states (from them as the guess if warm):
        what K_full, the iterations of a converged solve, is measured on."""
        states = val_traj[1].numpy()
        return A, (B @ states.T).T, states if warm_start else None

    # The harness runs the PRDP loop on this: each epoch it sets solver.max_it = K, trains
    # on shuffled batches, validates, and the controller raises K by k_step when the
    # validation metric plateaus.  The paper's controller, with less smoothing: the
    # rollout metric is deterministic and smooth.
    return Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=shuffled_batches(targets.shape[1], config["batch"]),
        loss=loss,
        validate=validate,
        rollout=rollout,
        probe=probe,
        rtol_full=1e-6,
        epochs=config["epochs"],
        prdp={
            **PAPER,
            "k_init": config["k_init"],
            "k_step": config["k_step"],
            "tau_step": 0.9,
            "ema_window": 2,
            "window": 2,
        },
        scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=config["gamma"]),
        info={
            "n": A.shape[0],
            "nnz": int(A.nnz),
            "network_parameters": sum(p.numel() for p in model.parameters()),
            **config,
        },
    )


# -- 7. The presets ------------------------------------------------------------------------
# ``quick`` (the tests' preset), ``paper`` (5 457 unknowns, Δt κ/h² ≈ 1.2) and ``stiff``
# (Δt κ/h² ≈ 6e3, where damped Jacobi is slow and the PC choice decides) on the L-shape;
# ``paper_mlp`` is ``paper`` with the reference's emulator class and 64 training
# trajectories.  ``quick3d`` and ``paper3d`` (5 146 unknowns, 39 544 tetrahedra,
# Δt κ/h² ≈ 0.7) are the cube.  ``unroll`` = m > 1 trains on m chained steps.
_EMULATOR = {
    "net": "modal", "width": 128, "depth": 2, "warm_start": True, "val_steps": 10,
    "unroll": 1, "gamma": 0.9,
}  # fmt: skip
_QUICK = {**_EMULATOR, "modes": 16, "spans": 4, "n_train": 8, "n_val": 4, "rollout_steps": 20,
          "epochs": 8, "batch": 8, "lr": 3e-2, "routes": "cg/icc"}  # fmt: skip
_PAPER = {**_EMULATOR, "modes": 128, "spans": 6, "n_train": 32, "n_val": 8, "epochs": 20,
          "batch": 16, "lr": 2e-2, "k_init": 10, "k_step": 20,
          "routes": "cg/icc,cg/gamg"}  # fmt: skip
PRESETS = {
    "quick": {"mesh": "lshape", "refine": 0, "dt": 1e-3, **_QUICK, "k_init": 4, "k_step": 4},
    "paper": {"mesh": "lshape", "refine": 1, "dt": 2e-4, **_PAPER, "rollout_steps": 30},
    "stiff": {"mesh": "lshape", "refine": 1, "dt": 1.0, **_PAPER, "modes": 64, "spans": 4,
              "n_train": 16, "rollout_steps": 20, "epochs": 10, "k_init": 50, "k_step": 50},
    "quick3d": {"mesh": "box3d", "refine": 0, "dt": 1e-2, **_QUICK, "k_init": 16, "k_step": 16},
    "paper3d": {"mesh": "box3d", "refine": 1, "dt": 3e-3, **_PAPER, "rollout_steps": 20},
}  # fmt: skip
# the reference's emulator class: a residual MLP over the nodal values
PRESETS["paper_mlp"] = {**PRESETS["paper"], "net": "mlp", "lr": 1e-3, "gamma": 0.95,
                        "k_init": 4, "k_step": 4, "n_train": 64}  # fmt: skip

# -- Things to try -------------------------------------------------------------------------
# * Another solver in the loop: ``python demos/heat.py run --out results/h
#   -heat2d_ksp_type cg -heat2d_pc_type icc``; watch it with ``-heat2d_ksp_monitor``.
# * Which route is fastest to full fidelity's accuracy: ``compare --routes cg/icc,cg/gamg``.
# * The stiff step, where the PC choice decides: ``compare --preset stiff
#   --routes cg/jacobi,cg/icc``.
# * Start the capped solve from zero instead of N's guess: ``--set warm_start=false``.
# * Train on two chained steps: ``--preset "quick unroll=2"``; fewer modes: ``--set modes=16``.
# * The reference's MLP emulator, which fits the step but not the rollout:
#   ``--preset paper_mlp``.
# * The cube, with the domain split over two ranks:
#   ``mpiexec -n 2 python demos/heat.py run --preset quick3d --parallel domain --out DIR``.

if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
