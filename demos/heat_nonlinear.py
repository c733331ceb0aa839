"""Nonlinear heat emulator on an unstructured mesh, trained through capped Newton steps.

PDE: u_t = ∇·(κ(u)∇u) with κ(u) = 1 + α u² (α = 2), on the L-shaped domain (the
shipped gmsh mesh ``lshape``), u = 0 on the boundary.  Discretisation: P1 finite
elements (scikit-fem, 1 325 unknowns), implicit Euler with Δt = 2e-3 (Δt κ/h² ≈ 3–18
with the mean edge h = 0.025); each step is the root of
``R(u) = M(u − uⁿ) + Δt K(κ(u)) u`` on the interior nodes (`NonlinearHeat` below,
docs/maths.md §8).  Initial conditions: three random Gaussian bumps times the bubble
(−Δd = 1), max |u| in [0.75, 1.5], so κ varies by a factor of up to 5.5.

Learning problem (the paper's mixed chain, as heat1d and heat): a network N maps uⁿ
to ûⁿ⁺¹, and the loss compares the capped Newton step ``Newton_K(ûⁿ⁺¹)`` with the
exact uⁿ⁺²; with small K the step falls short and N learns a biased map.  N is
`MeshNet` (below: message passing over the mesh's edges, 3 layers, 8 channels, node
coordinates as extra inputs; the linear heat scene's network before it moved to
``ModalNet``), here with GELU, since the step is nonlinear.  Validation metric: the
mean normalised error ``mean_t ‖ûₜ − uₜ‖/‖uₜ‖`` of a 10-step autoregressive rollout of
N against the exact trajectories of held-out initial conditions (the harness also
records a 20-step curve); the exact steps are Newton with a PETSc LU solve to ‖R‖ ≤
1e-10 ‖R₀‖.  This small local network cannot emulate the implicit step closely, but
the capped K still shows in its error (the known limitations).

Warm starts across epochs (``warm_start_epochs: True``; default False): each training
sample's Newton loop starts from that sample's capped result of the last epoch
(`prdp_petsc.autograd.warm_starts.WarmStarts`) instead of from ûⁿ⁺¹, so the two capped Newton
steps of every epoch continue where the last epoch's stopped; the gradient is the
implicit one at the returned iterate either way (the start receives none).
``pc_lag: N`` (default 1) sets the Jacobian's PC up only at every N-th Jacobian
(`prdp_petsc.KSPSolver`'s ``pc_lag``), for the ``gmres/gamg`` route's dear set-up.

Presets: ``quick`` (tests) and ``paper``.  R and J are assembled element by element,
so the inner GMRES iterations are a smaller share of an epoch than in the linear
scenes, and saved iterations save less wall time (results pages heat_nonlinear_speedup
and heat_nonlinear_ablation).

Run ``python demos/heat_nonlinear.py compare --preset paper --out results/heat_nonlinear``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
import torch
from petsc4py import PETSc

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.autograd.once import once_differentiable
from prdp_petsc.autograd.warm_starts import WarmStarts
from prdp_petsc.fem.parametric import csr_pattern
from prdp_petsc.lab.components.emulators import gaussian_bumps
from prdp_petsc.lab.training.rollout import rollout_errors
from prdp_petsc.lab.training.routes import parse_routes
from prdp_petsc.lab.training.scene import shuffled_batches
from prdp_petsc.prdp import PAPER

# -- 1. The mesh --------------------------------------------------------------------------
# ``load_mesh("lshape", refine=r)`` reads the shipped gmsh L-shape; with P1 triangles its
# interior nodes I are the 1 325 unknowns, the boundary nodes B carry u = g (zero here).

# -- 2. Assembly: the residual of one implicit-Euler step and its Jacobian ----------------
# The step from u_prev of ``u_t = ∇·(κ(u)∇u) + f`` is the root of the residual on I
# (φ_i the hat functions, u = g on B; docs/maths.md §8)
#
#     R_i(u) = ∫ (u − u_prev − Δt f) φ_i + Δt ∫ κ(u) ∇u·∇φ_i .
#
# Newton needs its Jacobian ``J = M + Δt K(κ(u)) + Δt C(u)``, whose term
# ``C_ij = ∫ κ'(u) φ_j ∇u·∇φ_i`` (κ' = 2αu) makes J non-symmetric; Picard the
# frozen-coefficient operator ``M + Δt K(κ(u))`` (SPD); the implicit gradient the
# products ``λᵀ ∂R/∂p`` for the inputs p = (u_prev, f, g, α).
#
# On P1 simplices ∇φ is constant on each element T, so κ(u) enters only through
# ``∫_T u² = u_Tᵀ M_T u_T`` and κ'(u) only through ``∫_T u φ_j = (M_T u_T)_j``: with
# ``K_T = |T| ∇φ ∇φᵀ`` and κ̄_T = 1 + α ∫_T u² / |T| (the mean of κ on T), the flux is
# ``κ̄_T K_T u_T``, the Picard block ``M_T + Δt κ̄_T K_T`` and the Jacobian block that
# plus the rank-one ``Δt 2α (K_T u_T / |T|) (M_T u_T)ᵀ``.  Each is a small dense
# matrix per element, summed into a CSR pattern fixed once: 0.18 ms per residual and
# 0.40 ms per Jacobian on the L-shape, against 0.98 and 3.1 ms for assembling the same
# forms with scikit-fem (tests/lab/test_nonlinear_heat.py compares the two).


class NonlinearHeat:
    """Residual, Jacobian and adjoint products of one implicit nonlinear heat step.

    The problem protocol of `prdp_petsc.newton_solve` (``n``, ``residual``,
    ``jacobian``, ``picard``, ``vjp`` and the symmetry declarations).

    Parameters
    ----------
    basis : skfem.CellBasis
        P1 on lines, triangles or tetrahedra; its boundary nodes
        (``basis.get_dofs()``) are the Dirichlet nodes B, the others the unknowns I.
    dt : float
        Time step Δt > 0.

    Notes
    -----
    Every callable takes the unknowns u_I (length `n`) and then the inputs
    ``(u_prev, f, g, alpha)``: nodal vectors u_prev and f (``basis.N``), the
    boundary values g (``len(boundary)``) and a scalar α.
    """

    jacobian_symmetric = False
    picard_symmetric = True

    def __init__(self, basis: skfem.CellBasis, dt: float) -> None:
        if not (np.isfinite(dt) and dt > 0):
            raise pp.InputError(f"dt must be finite and > 0, got {float(dt)!r}")
        if type(basis.elem) not in (skfem.ElementLineP1, skfem.ElementTriP1, skfem.ElementTetP1):
            raise pp.InputError(f"NonlinearHeat needs a P1 basis, got {type(basis.elem).__name__}")
        self.basis, self.dt = basis, float(dt)
        self.boundary = np.unique(np.asarray(basis.get_dofs(), dtype=np.int64))
        self.interior = np.setdiff1d(np.arange(basis.N), self.boundary)
        self.M = pp.mass_matrix(basis)
        self._M_I = self.M[self.interior].tocsr()  # rows I of M: the residual's mass term
        # per element T: ∇φ_i, |T|, K_T = |T| ∇φ ∇φᵀ and M_T = |T| (1 + δ_ij) / ((d+1)(d+2))
        self._dofs = np.ascontiguousarray(basis.element_dofs.T)  # (elements, d + 1)
        grads = np.stack([b[0].grad[..., 0] for b in basis.basis], axis=-1)  # (d, E, d+1)
        self._vol = np.asarray(basis.dx).sum(axis=1)
        self._K_T = self._vol[:, None, None] * np.einsum("kei,kej->eij", grads, grads)
        m = basis.mesh.dim() + 1
        self._M_T = self._vol[:, None, None] * ((1.0 + np.eye(m)) / (m * (m + 1)))
        rows = np.repeat(self._dofs, m, axis=1).ravel()  # local (i, j) -> node rows
        cols = np.tile(self._dofs, (1, m)).ravel()
        self._blocks = {
            name: _CSRBlock(rows, cols, self.interior, columns, basis.N)
            for name, columns in (("interior", self.interior), ("boundary", self.boundary))
        }

    @property
    def n(self) -> int:
        """Number of unknowns (interior nodes)."""
        return len(self.interior)

    def expand(self, u_i: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Full nodal vector with ``u[I] = u_i`` and ``u[B] = g``."""
        u = np.empty(self.basis.N)
        u[self.interior] = u_i
        u[self.boundary] = g
        return u

    def _element(self, u: np.ndarray) -> tuple:
        """K_T u_T, M_T u_T and the mean of u² on each element."""
        u_t = u[self._dofs]  # (E, d + 1)
        k_u = np.einsum("eij,ej->ei", self._K_T, u_t)
        m_u = np.einsum("eij,ej->ei", self._M_T, u_t)
        return k_u, m_u, np.einsum("ei,ei->e", u_t, m_u) / self._vol

    def _nodal(self, local: np.ndarray) -> np.ndarray:
        """Element vectors (E, d+1) summed into a nodal vector."""
        return np.bincount(self._dofs.ravel(), weights=local.ravel(), minlength=self.basis.N)

    def residual(
        self, u_i: np.ndarray, u_prev: np.ndarray, f: np.ndarray, g: np.ndarray, alpha: float
    ) -> np.ndarray:
        """``R(u_I)`` on the unknowns, shape ``(n,)``."""
        u = self.expand(u_i, g)
        k_u, _, mean_u2 = self._element(u)
        flux = self._nodal((1.0 + alpha * mean_u2)[:, None] * k_u)
        return self._M_I @ (u - u_prev - self.dt * f) + self.dt * flux[self.interior]

    def _operator(self, u_i, g, alpha, newton: bool, columns: str = "interior") -> sp.csr_matrix:
        """Rows I and the `columns` (interior or boundary) of the Jacobian or Picard operator."""
        k_u, m_u, mean_u2 = self._element(self.expand(u_i, g))
        local = self._M_T + self.dt * (1.0 + alpha * mean_u2)[:, None, None] * self._K_T
        if newton:  # the κ'(u) term: 2α Δt (K_T u_T / |T|) (M_T u_T)ᵀ
            grad_flux = k_u / self._vol[:, None]
            local += (2.0 * self.dt * alpha) * grad_flux[:, :, None] * m_u[:, None, :]
        return self._blocks[columns].assemble(local.ravel())

    def jacobian(
        self, u_i: np.ndarray, u_prev: np.ndarray, f: np.ndarray, g: np.ndarray, alpha: float
    ) -> sp.csr_matrix:
        """Newton Jacobian ``∂R/∂u_I`` (non-symmetric: it holds the κ'(u) term)."""
        return self._operator(u_i, g, alpha, newton=True)

    def picard(
        self, u_i: np.ndarray, u_prev: np.ndarray, f: np.ndarray, g: np.ndarray, alpha: float
    ) -> sp.csr_matrix:
        """Picard operator ``M + Δt K(κ(u))`` on the unknowns (symmetric positive definite)."""
        return self._operator(u_i, g, alpha, newton=False)

    def vjp(
        self,
        u_i: np.ndarray,
        lam: np.ndarray,
        u_prev: np.ndarray,
        f: np.ndarray,
        g: np.ndarray,
        alpha: float,
        *,
        needs: tuple[bool, bool, bool, bool] = (True, True, True, True),
    ) -> tuple:
        """``λᵀ ∂R/∂p`` for p = (u_prev, f, g, α); None where `needs` is False.

        ``∂R/∂u_prev = −M_I·``, ``∂R/∂f = −Δt M_I·``, ``∂R/∂g = J_IB`` (the full
        Jacobian's boundary columns) and ``∂R/∂α = Δt ∫ u² ∇u·∇φ_i``.
        """
        mt_lam = self._M_I.T @ lam  # M_Iᵀ λ, a nodal vector
        out = [
            -mt_lam if needs[0] else None,
            -self.dt * mt_lam if needs[1] else None,
            None,
            None,
        ]
        if needs[2]:
            out[2] = self._operator(u_i, g, alpha, newton=True, columns="boundary").T @ lam
        if needs[3]:
            k_u, _, mean_u2 = self._element(self.expand(u_i, g))
            d_alpha = self._nodal(mean_u2[:, None] * k_u)
            out[3] = np.asarray(self.dt * (d_alpha[self.interior] @ lam))
        return tuple(out)


class _CSRBlock:
    """Sums element entries into the CSR block (rows `row_nodes`, columns `col_nodes`)."""

    def __init__(self, rows, cols, row_nodes, col_nodes, n):
        row_of, col_of = np.full(n, -1), np.full(n, -1)
        row_of[row_nodes], col_of[col_nodes] = np.arange(len(row_nodes)), np.arange(len(col_nodes))
        r, c = row_of[rows], col_of[cols]
        self.keep = np.flatnonzero((r >= 0) & (c >= 0))  # entries of the block
        self.shape = (len(row_nodes), len(col_nodes))
        self.indptr, self.indices, self.slot = csr_pattern(r[self.keep], c[self.keep], self.shape)

    def assemble(self, values):
        data = np.bincount(self.slot, weights=values[self.keep], minlength=len(self.indices))
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)


# -- 3. The solver in the loop: Newton with capped GMRES ----------------------------------
# `prdp_petsc.newton_solve` takes ``max_newton`` = 2 outer steps from the input state,
# each linear step ``J δ = −R`` solved by GMRES + Jacobi in fixed mode with K = ``max_it``
# iterations from zero; PRDP schedules K.  GMRES, because J is not symmetric and CG
# would be wrong on it; Newton rather than Picard (whose SPD operator CG could solve)
# because it needs fewer outer steps, hence fewer assemblies, and the adjoint needs J
# either way.  ``ksp_gmres_restart`` is 200, so K is the Krylov dimension.  Gradients are
# implicit: one transpose GMRES solve with J(u*) per sample.  K_full is measured with
# rtol 1e-6 on the first Newton system of a held-out step.
GMRES = {"ksp_type": "gmres", "pc_type": "jacobi", "ksp_gmres_restart": 200}
# the exact steps of the data (`trajectories`): Newton with LU
EXACT = {"ksp_type": "preonly", "pc_type": "lu"}

# -- 4. The training data ------------------------------------------------------------------


def initial_conditions(heat, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` smooth fields on the unknowns, zero on the boundary, max |u| in [0.75, 1.5].

    Sums of three Gaussian bumps (random centres, widths 10–25 % of the domain, signed
    amplitudes) times the bubble d (−Δd = 1, d = 0 on the boundary, max d = 1), so the
    first steps carry no boundary layer.
    """
    from skfem.models.poisson import laplace, unit_load

    basis, interior = heat.basis, heat.interior
    K, load = laplace.assemble(basis), unit_load.assemble(basis)
    bubble = spla.spsolve(K[interior][:, interior].tocsc(), load[interior])
    points = basis.doflocs[:, interior]
    fields = gaussian_bumps(points, count, rng, bumps=3, widths=(0.1, 0.25)) * bubble
    peak = np.abs(fields).max(axis=1, keepdims=True)
    return fields * rng.uniform(0.75, 1.5, size=(count, 1)) / peak


def trajectories(heat, u0: np.ndarray, steps: int, alpha: float) -> np.ndarray:
    """Exact implicit-Euler trajectories (steps + 1, count, n) of the unknowns."""
    zero_f, zero_g = np.zeros(heat.basis.N), np.zeros(len(heat.boundary))
    # the data come from a serial LU solve on every rank, also under --parallel domain
    # (PETSc's own LU is sequential; the trained solver is the distributed one)
    solver = pp.KSPSolver(EXACT, prefix="heatnl_exact_", max_it=1, comm=PETSc.COMM_SELF)
    out = [u0]
    with torch.no_grad():
        for _ in range(steps):
            row = []
            for u in out[-1]:
                u_t = torch.from_numpy(u)
                sol = pp.newton_solve(
                    heat, u_t, heat.expand(u, zero_g), zero_f, zero_g, alpha,
                    solver=solver, rtol=1e-10, max_newton=20, require_convergence=True,
                )  # fmt: skip
                row.append(sol.value.numpy())
            out.append(np.stack(row))
    solver.destroy()
    return np.stack(out)


# -- 5. The network: message passing over the mesh's edges --------------------------------
# Each layer sums the neighbours' channel vectors with a learnable weight per edge (the
# sparsity pattern of the Jacobian), mixes the channels and applies GELU: its receptive
# field grows by one ring of neighbours per layer, its cost is linear in the number of
# edges, and it runs on any mesh without a regular grid.  The edge sum is a SciPy CSR
# product inside a small autograd function (no torch-geometric dependency).


class MeshNet(torch.nn.Module):
    """Residual message passing on a mesh graph: ``h ← h + σ(Θ_l (W_l h))``.

    Parameters
    ----------
    adjacency : scipy.sparse matrix, shape (n, n)
        Graph of the nodes (e.g. the pattern of the FE operator on the unknowns);
        self-loops are added.  Edge weights start at the row-normalised adjacency.
    channels : int
        Hidden channels per node.
    layers : int
        Message-passing layers (receptive field: `layers` rings of neighbours).
    features : array_like, shape (n, f), optional
        Fixed per-node inputs appended to u (e.g. coordinates), so the network can
        tell the boundary layer from the interior.
    activation : {"gelu", None}
        Nonlinearity after each layer; None makes the network linear in its inputs
        (a product of learnable sparse operators), the right class for the step of
        a linear PDE.

    Notes
    -----
    Input and output have shape (B, n) (float64).  u is lifted to `channels`
    channels (channel 0 carries u itself), each layer adds ``σ(Θ_l (W_l h))`` with
    ``W_l`` the edge-weighted neighbour sum, and a linear readout gives û.  All
    channel mixings start at zero, so the network starts as the identity map, the
    natural first guess for a small time step, and trains like a residual network.
    """

    def __init__(
        self, adjacency, channels: int = 4, layers: int = 3, features=None, activation="gelu"
    ):
        super().__init__()
        if activation not in ("gelu", None):
            raise ValueError(f"activation must be 'gelu' or None, got {activation!r}")
        self.activation = activation
        A = sp.csr_matrix(adjacency, dtype=np.float64)
        A = (abs(A) + sp.identity(A.shape[0], format="csr")).tocsr()
        A.data[:] = 1.0
        A = sp.diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
        A = A.tocsr()
        A.sort_indices()
        self._pattern = _Pattern(A.indptr, A.indices, A.shape)
        feats = np.zeros((A.shape[0], 0)) if features is None else np.asarray(features)
        if feats.shape[0] != A.shape[0]:
            raise ValueError(f"features must have {A.shape[0]} rows, got {feats.shape}")
        self.register_buffer("features", torch.from_numpy(feats.astype(np.float64)))
        self.n = A.shape[0]
        start = torch.from_numpy(A.data)
        self.edge_weights = torch.nn.ParameterList(
            [torch.nn.Parameter(start.clone()) for _ in range(layers)]
        )
        self.lift = torch.nn.Linear(1 + feats.shape[1], channels).double()
        self.mix = torch.nn.ModuleList(
            [torch.nn.Linear(channels, channels).double() for _ in range(layers)]
        )
        self.readout = torch.nn.Linear(channels, 1).double()
        with torch.no_grad():  # start as the identity map: channel 0 carries u through
            self.lift.weight[0].zero_()
            self.lift.weight[0, 0] = 1.0
            self.lift.bias[0] = 0.0
            for mix in self.mix:
                mix.weight.zero_()
                mix.bias.zero_()
            self.readout.weight.zero_()
            self.readout.weight[0, 0] = 1.0
            self.readout.bias.zero_()

    def _propagate(self, h: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Edge-weighted neighbour sum of h, shape (n, B, C)."""
        flat = h.reshape(self.n, -1)
        return _EdgeSum.apply(weights, flat, self._pattern).reshape(h.shape)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        if u.shape[-1] != self.n:
            raise ValueError(f"MeshNet expects (batch, {self.n}), got {tuple(u.shape)}")
        squeeze = u.ndim == 1
        u = u[None] if squeeze else u
        inputs = [u.T[..., None]]  # nodes first: (n, B, 1)
        if self.features.shape[1]:
            inputs.append(self.features[:, None, :].expand(-1, u.shape[0], -1))
        h = self.lift(torch.cat(inputs, dim=-1))
        for weights, mix in zip(self.edge_weights, self.mix, strict=True):
            update = mix(self._propagate(h, weights))
            h = h + (torch.nn.functional.gelu(update) if self.activation else update)
        out = self.readout(h)[..., 0].T
        return out[0] if squeeze else out


class _Pattern:
    """CSR pattern of the graph with the positions needed by `_EdgeSum`'s backward."""

    def __init__(self, indptr, indices, shape):
        self.indptr, self.indices, self.shape = indptr, indices, shape
        self.rows = np.repeat(np.arange(shape[0]), np.diff(indptr))


class _EdgeSum(torch.autograd.Function):
    """``Y = W X`` for a sparse W with learnable values on a fixed pattern (scipy CSR)."""

    @staticmethod
    def forward(ctx, values, X, pattern):
        W = sp.csr_matrix(
            (values.detach().numpy(), pattern.indices, pattern.indptr), shape=pattern.shape
        )
        ctx.W, ctx.pattern = W, pattern
        ctx.save_for_backward(X)
        return torch.from_numpy(W @ X.detach().numpy())

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        (X,) = ctx.saved_tensors
        g = grad.contiguous().numpy()
        pattern = ctx.pattern
        grad_values = grad_X = None
        if ctx.needs_input_grad[0]:
            x = X.detach().numpy()
            grad_values = torch.from_numpy(
                np.einsum("km,km->k", g[pattern.rows], x[pattern.indices])
            )
        if ctx.needs_input_grad[1]:
            grad_X = torch.from_numpy(ctx.W.T @ g)
        return grad_values, grad_X, None


# -- 6. The scene, handed to the harness ---------------------------------------------------


def build(config: dict, seed: int) -> lab.Scene:
    parse_routes(config["routes"])  # `compare` runs them; a malformed one fails here too
    mesh = pp.load_mesh(config["mesh"], refine=config["refine"])
    basis = skfem.Basis(mesh, skfem.ElementTriP1())
    heat = NonlinearHeat(basis, config["dt"])
    alpha, interior, N = config["alpha"], heat.interior, basis.N
    zero_f, zero_g = np.zeros(N), np.zeros(len(heat.boundary))
    rng = np.random.default_rng(seed)

    n_train, n_val = config["n_train"], config["n_val"]
    u0 = initial_conditions(heat, n_train + n_val, rng)
    steps = max(config["train_steps"], config["val_steps"], config["rollout_steps"])
    train_traj = trajectories(heat, u0[:n_train], config["train_steps"], alpha)
    val_traj = torch.from_numpy(trajectories(heat, u0[n_train:], steps, alpha))
    # training pairs (uⁿ, uⁿ⁺²) from every step of the training trajectories
    train_in = torch.from_numpy(train_traj[:-2].reshape(-1, heat.n))
    train_out = torch.from_numpy(train_traj[2:].reshape(-1, heat.n))
    scale = float(train_out.norm(dim=-1).mean())

    solver = pp.KSPSolver(GMRES, prefix="heatnl_", max_it=config["k_init"], pc_lag=config["pc_lag"])
    J0 = heat.jacobian(u0[n_train], heat.expand(u0[n_train], zero_g), zero_f, zero_g, alpha)
    coords = basis.doflocs[:, interior].T
    coords = (coords - coords.mean(axis=0)) / coords.std(axis=0)
    net = MeshNet(J0, channels=config["channels"], layers=3, features=coords, activation="gelu")
    optimizer = torch.optim.Adam(net.parameters(), lr=config["lr"])
    interior_t = torch.from_numpy(interior)
    newton = {"solves": 0, "steps": 0}  # running totals, written with the results
    starts = WarmStarts() if config["warm_start_epochs"] else None

    def newton_step(u_hat: torch.Tensor, sample: int) -> torch.Tensor:
        """Newton_K(û): the capped step from û, differentiable in û; the Newton loop starts
        from û, or with warm starts from this sample's result of the last epoch."""
        u_prev = torch.zeros(N, dtype=torch.float64).index_copy(0, interior_t, u_hat)
        u0 = u_hat.detach() if starts is None else starts.guess(sample, fill=u_hat)
        sol = pp.newton_solve(
            heat, u0, u_prev, zero_f, zero_g, alpha,
            solver=solver, max_newton=config["max_newton"], rtol=1e-10,
        )  # fmt: skip
        newton["solves"] += 1
        newton["steps"] += sol.iterations
        if starts is not None:
            starts.store(sample, sol.value)
        return sol.value

    def loss(idx):
        u1_hat = net(train_in[idx])
        u2_hat = torch.stack([newton_step(u, i) for u, i in zip(u1_hat, idx.tolist(), strict=True)])
        return ((u2_hat - train_out[idx]) ** 2).sum(-1).mean() / scale**2

    def rollout():
        return rollout_errors(net, val_traj[0], val_traj[1 : config["rollout_steps"] + 1])

    def validate():
        return float(rollout_errors(net, val_traj[0], val_traj[1 : config["val_steps"] + 1]).mean())

    def probe():
        """The first Newton system of a held-out step: J(uⁿ) δ = −R(uⁿ)."""
        u = val_traj[0, 0].numpy()
        params = (heat.expand(u, zero_g), zero_f, zero_g, alpha)
        return heat.jacobian(u, *params), -heat.residual(u, *params), None

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=shuffled_batches(len(train_in), config["batch"]),
        loss=loss,
        validate=validate,
        rollout=rollout,
        probe=probe,
        rtol_full=1e-6,
        epochs=config["epochs"],
        prdp={**PAPER, "k_init": config["k_init"], "k_step": config["k_step"], "tau_step": 0.9},
        scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=config["gamma"]),
        info={
            "n": heat.n,
            "nnz": int(J0.nnz),
            "train_pairs": len(train_in),
            "network_parameters": sum(p.numel() for p in net.parameters()),
            "newton_totals": newton,
            **config,
        },
    )


# -- 7. The presets ------------------------------------------------------------------------
# ``routes``: the KSP/PC pairs `compare` also runs (``--routes`` overrides them).  The
# Newton Jacobian is not symmetric (CG and ICC are refused), so GMRES with ILU or GAMG.
PRESETS = {
    "quick": {
        "mesh": "lshape",
        "refine": 0,
        "dt": 2e-3,
        "alpha": 2.0,
        "n_train": 4,
        "train_steps": 4,
        "n_val": 2,
        "val_steps": 10,
        "rollout_steps": 10,
        "max_newton": 2,
        "channels": 8,
        "epochs": 6,
        "batch": 6,
        "lr": 3e-3,
        "gamma": 0.97,
        "warm_start_epochs": False,
        "pc_lag": 1,
        "k_init": 1,
        "k_step": 1,
        "routes": "gmres/ilu",
    },
}
PRESETS["paper"] = {
    **PRESETS["quick"],
    "n_train": 12,
    "train_steps": 6,
    "n_val": 4,
    "rollout_steps": 20,
    "epochs": 40,
    "batch": 8,
    "routes": "gmres/ilu,gmres/gamg",
}


# -- Things to try --------------------------------------------------------------------------
# * Newton from last epoch's capped results: ``--set warm_start_epochs=true``.
# * GAMG on the Newton systems, set up at every fourth Jacobian:
#   ``compare --routes gmres/gamg --set pc_lag=4``.
# * The linear step as a control: ``--set alpha=0``.
# * Watch the capped GMRES: ``-heatnl_ksp_monitor``.


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
