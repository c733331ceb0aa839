"""Scale-invariant physics (SIP) against differentiable physics (DP) through a capped CG solve.

PDE: −∇·(κ∇y) = x on the L-shaped domain (the shipped gmsh mesh ``lshape``), y = 0 on
the boundary.  Discretisation: P1 finite elements (scikit-fem) on the interior nodes,
``A y = M x`` with A the stiffness matrix (``pp.diffusion_operator(basis, "P0")``, κ per
element) and M the mass matrix, so the physics is ``y = P(x) = A⁻¹ M x``.  κ = 1, or
(``contrast``) κ = 1e3 in a disc of radius 0.15 around (0.25, 0.25): the ill-conditioned
variant, where P's singular values spread over many more decades.

Learning problem (Holl et al., "Scale-invariant learning by physics inversion"): a
network f(y*; φ) maps an observed solution y* = P(x_true) to the source x, for random
smooth sources x_true (sums of Gaussian bumps, as in ``heat``:
`prdp_petsc.lab.components.emulators.gaussian_bumps`).  f is a learnable sparse linear map
on A's pattern (`SparseLinear`, one value per entry, starting at zero; input divided
and output multiplied by fixed data scales): the class of the inverse physics
``M⁻¹ A`` it has to learn, up to mass lumping.  ``method`` selects the training rule:

``dp_adam``
    loss ½‖P_K(f(y*)) − y*‖² / s_y², gradient through the implicit adjoint (one
    transpose solve per sample), Adam.
``dp_sgd``
    the same loss and gradient, plain gradient descent (SGD, no momentum).
``sip``
    x = f(y*), y = P_K(x) (forward capped solve, no gradient through it), the inverse
    simulator ``P⁻¹(y) = M⁻¹ A y`` (a sparse product and a splu solve with M; no solve
    with A), ``Δx = P⁻¹(y + η(y* − y)) − x``, proxy loss ½‖x − stopgrad(x + Δx)‖² / s_x²,
    Adam.  For η = 1 the update is ``P⁻¹(y*) − x`` and does not depend on the forward
    solve at all (supervised learning against P⁻¹(y*)); the default η = 0.5 keeps K
    in the update: ``Δx = η(x_true − x) − (1 − η) M⁻¹ r_K`` with ``r_K = M x − A y_K``
    the capped solve's residual, so a small K biases the fixed point and PRDP has
    something to decide.

Validation metric (what PRDP watches): the x-space error ``‖f(y*) − x_true‖/‖x_true‖``
averaged over the validation samples (why x and not y: the scenes guide).  After
training, ``Scene.rollout`` returns the y-space error ``‖P(f(y*)) − y*‖/‖y*‖`` per
validation sample (P solved exactly by splu) and writes both means into
``Scene.info["final"]``.

Solver in the loop: CG + Jacobi (prefix ``sip_``: ``-sip_ksp_type``,
``-sip_pc_type``), K = ``max_it`` iterations from zero (rtol = atol = 0); PRDP raises K
for all three methods.  K_full is measured on A with right-hand sides ``M x_true``.

Presets: ``quick`` (DP + Adam, κ = 1; tests), ``paper`` (DP + Adam, κ contrast), and
one per method and conditioning: ``quick_{dp_sgd,sip}``, ``contrast_{dp_adam,dp_sgd,sip}``.

Run ``python demos/poisson_sip.py run --preset contrast_sip --out DIR``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
import torch
from skfem.models.poisson import mass

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.lab.components.emulators import gaussian_bumps
from prdp_petsc.lab.training.scene import shuffled_batches
from prdp_petsc.prdp import PAPER

METHODS = ("dp_adam", "dp_sgd", "sip")

_BASE = {
    "refine": 0,
    "contrast": 1.0,
    "method": "dp_adam",
    "eta": 0.5,
    "n_train": 64,
    "n_val": 8,
    "epochs": 30,
    "batch": 8,
    "lr": 3e-3,
    "lr_sgd": 3e-2,
    "k_init": 10,
    "k_step": 10,
}


def _preset(**changes) -> dict:
    return {**_BASE, **changes}


PRESETS = {
    "quick": _preset(epochs=6),
    "paper": _preset(contrast=1e3, epochs=40),
    **{f"quick_{m}": _preset(method=m, epochs=6) for m in METHODS[1:]},
    **{f"contrast_{m}": _preset(method=m, contrast=1e3) for m in METHODS},
}

PREFIX = "sip_"


def physics(refine: int = 0, contrast: float = 1.0):
    """``(A, M, points)``: stiffness and mass matrices on the interior nodes (CSR) and
    the interior nodes' coordinates (2, n); κ = `contrast` in the inclusion, 1 elsewhere."""
    mesh = pp.load_mesh("lshape", refine=refine)
    basis = skfem.Basis(mesh, skfem.ElementTriP1())
    centroids = mesh.p[:, mesh.t].mean(axis=1)
    inside = ((centroids - np.array([[0.25], [0.25]])) ** 2).sum(axis=0) < 0.15**2
    kappa = np.where(inside, contrast, 1.0)
    interior = basis.complement_dofs(basis.get_dofs())
    A = pp.diffusion_operator(basis, "P0").matrix(kappa)[interior][:, interior].tocsr()
    M = mass.assemble(basis)[interior][:, interior].tocsr()
    A.sort_indices()
    return A, M, mesh.p[:, interior]


class InverseSimulator:
    """``P⁻¹(y) = M⁻¹ A y`` for ``P(x) = A⁻¹ M x``: one sparse product, one splu solve."""

    def __init__(self, A: sp.csr_matrix, M: sp.csr_matrix):
        self.A, self._mass = A, spla.splu(M.tocsc())

    def __call__(self, y: torch.Tensor) -> torch.Tensor:
        rhs = self.A @ np.atleast_2d(y.detach().numpy()).T
        return torch.from_numpy(self._mass.solve(rhs).T).reshape(y.shape)


def sip_update(x, y, y_star, inverse: InverseSimulator, eta: float) -> torch.Tensor:
    """``Δx = P⁻¹(y + η(y* − y)) − x`` (no gradient)."""
    return inverse(y + eta * (y_star - y)) - x.detach()


def build(config: dict, seed: int) -> lab.Scene:
    if config["method"] not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {config['method']!r}")
    if not 0 < config["eta"] <= 1:
        raise ValueError(f"eta must lie in (0, 1], got {config['eta']}")
    A, M, points = physics(config["refine"], config["contrast"])
    n = A.shape[0]
    rng = np.random.default_rng(seed)
    n_train = config["n_train"]
    x_true = gaussian_bumps(points, n_train + config["n_val"], rng)
    lu = spla.splu(A.tocsc())
    y_star = torch.from_numpy(lu.solve(M @ x_true.T).T)
    x_true = torch.from_numpy(x_true)
    s_x = float(x_true[:n_train].norm(dim=-1).mean())
    s_y = float(y_star[:n_train].norm(dim=-1).mean())
    inverse = InverseSimulator(A, M)

    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, prefix=PREFIX, max_it=1)
    lumped = np.asarray(M.sum(axis=1)).ravel()
    net = SparseLinear(A, scale=s_y / (s_x * lumped.mean()))

    def f(y):
        return s_x * net(y / s_y)

    method = config["method"]
    if method == "dp_sgd":
        optimizer = torch.optim.SGD(net.parameters(), lr=config["lr_sgd"])
    else:
        optimizer = torch.optim.Adam(net.parameters(), lr=config["lr"])

    def loss(idx):
        x = f(y_star[idx])
        if method == "sip":
            with torch.no_grad():
                y = pp.solve(A, torch.from_numpy((M @ x.detach().numpy().T).T), solver)
            target = x.detach() + sip_update(x, y, y_star[idx], inverse, config["eta"])
            return 0.5 * ((x - target) ** 2).sum(-1).mean() / s_x**2
        y = pp.solve(A, _mass_product(M, x), solver)
        return 0.5 * ((y - y_star[idx]) ** 2).sum(-1).mean() / s_y**2

    val = slice(n_train, None)

    def validate():
        with torch.no_grad():
            x = f(y_star[val])
        return float(((x - x_true[val]).norm(dim=-1) / x_true[val].norm(dim=-1)).mean())

    info = {"n": n, "nnz": int(A.nnz), "network_parameters": _count(net), **config}

    def rollout():
        with torch.no_grad():
            x = f(y_star[val])
        y = torch.from_numpy(lu.solve(M @ x.numpy().T).T)
        y_err = (y - y_star[val]).norm(dim=-1) / y_star[val].norm(dim=-1)
        info["final"] = {"x_error": validate(), "y_error": float(y_err.mean())}
        return [float(e) for e in y_err]

    return lab.Scene(
        solvers=[solver],
        optimizer=optimizer,
        batches=shuffled_batches(n_train, config["batch"]),
        loss=loss,
        validate=validate,
        rollout=rollout,
        probe=lambda: (A, (M @ x_true[val].numpy().T).T, None),
        rtol_full=1e-6,
        epochs=config["epochs"],
        prdp={**PAPER, "k_init": config["k_init"], "k_step": config["k_step"], "tau_step": 0.9},
        info=info,
    )


class SparseLinear(torch.nn.Module):
    """``x = c W y`` with W sparse on the pattern of `pattern`, one learnable value per
    entry (starting at zero) and a fixed scale c, so the values are O(1).

    The pattern of A is the stencil of the inverse physics ``M⁻¹A`` with a lumped
    mass, so this class can represent P⁻¹ up to the mass lumping.
    """

    def __init__(self, pattern: sp.csr_matrix, scale: float = 1.0):
        super().__init__()
        coo = sp.coo_matrix(pattern)
        self.register_buffer("rows", torch.from_numpy(coo.row.astype(np.int64)))
        self.register_buffer("cols", torch.from_numpy(coo.col.astype(np.int64)))
        self.n, self.scale = pattern.shape[0], scale
        self.values = torch.nn.Parameter(torch.zeros(coo.nnz, dtype=torch.float64))

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        products = y[..., self.cols] * (self.scale * self.values)
        out = y.new_zeros(y.shape)
        return out.index_add(-1, self.rows, products)


class _MassProduct(torch.autograd.Function):
    """``M xᵢ`` for a batch x (B, n) with a fixed symmetric scipy M."""

    @staticmethod
    def forward(ctx, x, M):
        ctx.M = M
        return torch.from_numpy((M @ x.detach().numpy().T).T)

    @staticmethod
    def backward(ctx, grad):
        return torch.from_numpy((ctx.M @ grad.contiguous().numpy().T).T), None


def _mass_product(M, x):
    return _MassProduct.apply(x, M)


def _count(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


# -- Things to try --------------------------------------------------------------------------
# * The three training rules on the ill-conditioned problem: ``--preset contrast_dp_adam``,
#   ``contrast_dp_sgd`` and ``contrast_sip``.
# * Another preconditioner: ``-sip_pc_type icc``; watch the solves with ``-sip_ksp_monitor``.


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
