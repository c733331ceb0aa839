"""Topology optimisation of a 3D cantilever (SIMP) with capped CG + GAMG solves.

PDE: linear elasticity −∇·σ(u) = 0 on the box [0, 2] × [0, 1] × [0, 1], σ = E(ρ)
(λ̂ tr ε I + 2 μ̂ ε), ν = 0.3, clamped at x = 0, a downward traction of total force 1
on a band of the face x = 2 (|z − z_c| ≤ 1/4).  The load case is the seed: z_c = 0,
½, 1 for seeds 0, 1, 2 (bottom, middle, top edge; seed s uses case s mod 3).

Discretisation: trilinear vector hexahedra (Q1, ``ElementVector(ElementHex1())``) on a
2n × n × n grid; Young's modulus per element ``θ = E_min + ρᵖ (E_0 − E_min)``
(modified SIMP, p = 3, E_0 = 1, E_min = ``e_min``) through
``pp.elasticity_operator(basis, "P0")``, the clamp eliminated (`prdp_petsc.Dirichlet`).
The design x (one value per element) is smoothed by a density filter
``ρ = H x`` (linear hat of radius ``rmin`` element widths, sparse, built once).

Optimisation: minimise the compliance C = fᵀu subject to mean(ρ) = ``volfrac`` with
optimality criteria (`OptimalityCriteria`, a ``torch.optim.Optimizer``: the
heuristic update of Sigmund's 99-line code with move limit ``move`` and a bisection
on the volume multiplier).  The sensitivity dC/dx comes from torch autograd through
the filter, the SIMP law and the differentiable solve (`prdp_petsc.solve`, implicit
adjoint): the library's bridge gives −λᵀ (∂A/∂θ) u with λ from the capped adjoint.

Solver in the loop: CG + GAMG with block size 3, the six rigid-body modes as near-null
space, and Richardson + SOR smoothers (GAMG's default Chebyshev smoothers break down
on SIMP contrast with ``DIVERGED_INDEFINITE_PC``, see the vector-problems guide).
Fixed mode (``rtol = 0``): K = ``max_it`` iterations per solve, forward and adjoint.
Options prefix ``to_`` (``-to_ksp_monitor``, ``-to_pc_gamg_threshold 0.01``).

**The metric the controller watches** is the design change per iteration,
``max |x_t − x_{t−1}|`` (the stopping test of the classic SIMP codes).  It costs no
solve and is defined without K: the compliance of a capped solve reads low at small K
(u_K underestimates the displacement), so a controller watching it sees the metric
*rise* when it refines and refines again to K_full.  A compliance from a converged
validation solve would be K-independent too, but costs a converged solve per design
iteration (about K_full iterations) which the savings would have to pay.  The design
change only says *when* to ask; whether to refine is decided by the ``auto``
schedule's gradient check (``PRDP.for_problem`` and ``check``: the compliance
gradient at K against K_full on the current design).  The results command scores
every design iteration with a converged solve afterwards, outside the clock.

Presets: ``quick`` (n = 3: 6 × 3 × 3 elements; tests), ``paper`` (n = 10: 20 × 10 × 10
= 2 000 elements, 7 623 unknowns) and ``large`` (n = 40: 128 000 elements,
393 600 unknowns; not run by the tests).  ``--parallel domain`` runs in the replicated
layout (each solve one distributed PETSc solve, rows split by whole nodes); the owned
layout (`prdp_petsc.fem.distributed.DistributedParametricMatrix`) refuses it: it holds one scalar
unknown per mesh vertex, not vector fields.

Run ``python demos/topopt3d.py run --preset paper --schedule auto --out DIR`` for one
optimisation; ``python demos/topopt3d.py results --preset paper --out DIR`` for the
comparison of schedules (converged, constant K, PRDP, rtol) on three load cases,
and ``prdp-petsc pages record topopt3d_paper -- scene demos/topopt3d.py results ...``
to record it for the results page.  Things to try: ``--set e_min=1e-6``,
``-to_mg_levels_ksp_type chebyshev`` (watch it fail), ``--set rmin=2.5``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import skfem
import torch
from scipy.spatial import cKDTree

import prdp_petsc as pp
from prdp_petsc import lab
from prdp_petsc.lab.components.emulators import torch_sparse
from prdp_petsc.lab.reports import topopt as topopt_reports
from prdp_petsc.prdp import PAPER

#: the settings every preset shares: SIMP p = 3, E_min = 1e-9 E_0, 30 % volume, a filter
#: of 1.5 element widths, OC's move limit 0.2, fixed-K solves (rtol 0)
_SETTINGS = {
    "volfrac": 0.3,
    "penal": 3.0,
    "e_min": 1e-9,
    "rmin": 1.5,
    "move": 0.2,
    "rtol": 0.0,
    "norm": "preconditioned",
    "k_init": 4,
    "k_step": 4,
}

PRESETS = {
    "quick": {"n": 3, "epochs": 20, **_SETTINGS},
    "paper": {"n": 10, "epochs": 50, **_SETTINGS},
    "large": {"n": 40, "epochs": 50, **_SETTINGS},
}

PREFIX = "to_"

#: CG + GAMG with smoothers that need no eigenvalue estimate (SIMP contrast)
GAMG = {
    "ksp_type": "cg",
    "pc_type": "gamg",
    "mg_levels_ksp_type": "richardson",
    "mg_levels_pc_type": "sor",
}

#: load cases (seed mod 3): the height z_c of the loaded band on the face x = 2
LOAD_HEIGHTS = (0.0, 0.5, 1.0)


class Cantilever:
    """Vector Q1 elasticity on [0, lx] × [0, ly] × [0, lz], clamped at x = 0, with a
    downward traction of total force `force` on the band |z − z_c| ≤ `half_width` of
    the face x = lx.

    ``A`` is ``pp.elasticity_operator(basis, "P0")`` (E = θ per element), ``bc`` its
    Dirichlet elimination, ``b`` the load on the unknowns; `compliance` solves to
    convergence.  Elements are numbered as scikit-fem's ``MeshHex.init_tensor``.
    """

    def __init__(self, shape, size=(2.0, 1.0, 1.0), *, z_c=0.5, half_width=0.25, force=1.0):
        (nx, ny, nz), (lx, ly, lz) = shape, size
        self.mesh = skfem.MeshHex.init_tensor(
            np.linspace(0, lx, nx + 1), np.linspace(0, ly, ny + 1), np.linspace(0, lz, nz + 1)
        )
        element = skfem.ElementVector(skfem.ElementHex1())
        self.basis = skfem.Basis(self.mesh, element, intorder=3)  # 2 × 2 × 2 Gauss
        self.A = pp.elasticity_operator(self.basis, "P0", poisson_ratio=0.3)
        self.bc = pp.Dirichlet(self.A, self.basis.get_dofs(lambda x: np.isclose(x[0], 0)).all())
        facets = self.mesh.facets_satisfying(
            lambda x: np.isclose(x[0], lx) & (np.abs(x[2] - z_c) <= half_width + 1e-12)
        )
        face = skfem.FacetBasis(self.mesh, element, facets=facets)
        area = float(skfem.Functional(lambda w: 1.0 + 0.0 * w.x[0]).assemble(face))
        traction = force / area
        f = skfem.LinearForm(lambda v, w: -traction * v[2]).assemble(face)
        self.b = f[self.bc.interior]
        self.centroids = self.mesh.p[:, self.mesh.t].mean(axis=1)

    def solver(
        self, max_it: int, rtol: float = 0.0, prefix: str = PREFIX, norm: str = "preconditioned"
    ) -> pp.KSPSolver:
        """CG + GAMG (Richardson + SOR smoothers) with block size 3 and the rigid-body
        modes of the kept dofs as near-null space; `norm` is PETSc's ``ksp_norm_type``
        (the residual an rtol test reads)."""
        options = GAMG if norm == "preconditioned" else {**GAMG, "ksp_norm_type": norm}
        return pp.KSPSolver(
            options,
            prefix=prefix,
            max_it=max_it,
            rtol=rtol,
            structure=pp.Structure(
                block_size=3, near_nullspace=pp.rigid_body_modes(self.basis, self.bc.interior)
            ),
        )

    def compliance(self, theta: np.ndarray, solver: pp.KSPSolver) -> float:
        """bᵀu with A(θ) u = b solved by `solver` (give it a tolerance: converged)."""
        solver.set_operator(self.bc.A_II.matrix(np.asarray(theta, dtype=np.float64)))
        sol = solver.solve(self.b)
        if not sol.converged:
            raise pp.SolverError(f"the scoring solve did not converge: {sol.reason}")
        return float(self.b @ sol.value)


def density_filter(centroids: np.ndarray, radius: float) -> sp.csr_matrix:
    """Row-normalised linear-hat filter ``H_ij ∝ max(0, r − |c_i − c_j|)`` (sparse)."""
    tree = cKDTree(centroids.T)
    dist = tree.sparse_distance_matrix(tree, radius, output_type="coo_matrix")
    weights = sp.coo_matrix((radius - dist.data, (dist.row, dist.col)), shape=dist.shape)
    weights = (weights + sp.identity(dist.shape[0]) * radius).tocsr()  # the diagonal (d = 0)
    return sp.diags(1.0 / np.asarray(weights.sum(axis=1)).ravel()) @ weights


def simp(rho: torch.Tensor, penal: float, e_min: float) -> torch.Tensor:
    """Young's modulus of density ρ: ``E_min + ρᵖ (1 − E_min)`` (E_0 = 1)."""
    return e_min + rho**penal * (1.0 - e_min)


class OptimalityCriteria(torch.optim.Optimizer):
    """Optimality-criteria update of a density design under a volume constraint.

    ``x ← clamp(x (−∂C/∂x / (λ ∂V/∂x))^η, x ± move, [0, 1])`` with λ found by
    bisection so that ``volume(x) = volfrac``.  The gradient of the objective is the
    parameter's ``.grad``; `volume` maps a design to its volume fraction and
    `volume_grad` is its (constant) gradient.
    """

    def __init__(self, params, *, volume: Callable, volume_grad: torch.Tensor, volfrac: float,
                 move: float = 0.2, eta: float = 0.5):  # fmt: skip
        if not 0 < volfrac < 1:
            raise ValueError(f"volfrac must lie in (0, 1), got {volfrac}")
        if move <= 0:
            raise ValueError(f"move must be > 0, got {move}")
        super().__init__(params, {"move": move, "eta": eta})
        self.volume, self.volume_grad, self.volfrac = volume, volume_grad, volfrac

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            for x in group["params"]:
                if x.grad is None:
                    continue
                sensitivity = (-x.grad).clamp(min=0.0)
                lo, hi = 0.0, 1e9 * float(sensitivity.max() / self.volume_grad.min()) + 1e-300
                move = group["move"]
                while hi - lo > 1e-9 * (lo + hi):
                    mid = 0.5 * (lo + hi)
                    new = x * (sensitivity / (mid * self.volume_grad)) ** group["eta"]
                    new = torch.minimum(torch.maximum(new, x - move), x + move).clamp(0.0, 1.0)
                    lo, hi = (mid, hi) if self.volume(new) > self.volfrac else (lo, mid)
                x.copy_(new)


def load_case(seed: int) -> float:
    """The height z_c of the loaded band for `seed` (three load cases)."""
    return LOAD_HEIGHTS[seed % len(LOAD_HEIGHTS)]


@dataclass
class TopOptScene(lab.Scene):
    """A `~prdp_petsc.lab.training.scene.Scene` that keeps what scoring its designs
    afterwards needs (the ``results`` command, the tests): the problem and the filtered
    design ρ after every design iteration."""

    problem: Cantilever | None = None
    designs: list[np.ndarray] = field(default_factory=list)


def build(config: dict, seed: int) -> TopOptScene:
    n = config["n"]
    problem = Cantilever((2 * n, n, n), z_c=load_case(seed))
    H = density_filter(problem.centroids, config["rmin"] / n)
    H_torch = torch_sparse(H)
    volfrac, penal, e_min = config["volfrac"], config["penal"], config["e_min"]
    count = H.shape[0]

    def filtered(x: torch.Tensor) -> torch.Tensor:
        return H_torch @ x

    volume_grad = torch.from_numpy(np.asarray(H.sum(axis=0)).ravel() / count)
    x = torch.full((count,), volfrac, dtype=torch.float64, requires_grad=True)
    optimizer = OptimalityCriteria(
        [x], volume=lambda d: float(filtered(d).mean()), volume_grad=volume_grad,
        volfrac=volfrac, move=config["move"],
    )  # fmt: skip
    solver = problem.solver(config["k_init"], rtol=config["rtol"], norm=config["norm"])
    b = torch.from_numpy(problem.b)
    designs: list[np.ndarray] = []  # ρ after every design iteration (for scoring)
    last = [x.detach().clone()]

    def stiffness() -> torch.Tensor:
        return simp(filtered(x), penal, e_min)

    def loss(_):
        """The compliance bᵀu through the capped solve."""
        return b @ pp.solve(problem.bc.A_II, b, solver, theta=stiffness())

    def validate() -> float:
        """The design change max |x_t − x_{t−1}| (no solve; see the module docstring)."""
        current = x.detach().clone()
        change = float((current - last[0]).abs().max())
        last[0] = current
        designs.append(filtered(current).numpy().astype(np.float32))
        return change

    probe_theta = simp(torch.full((count,), volfrac, dtype=torch.float64), penal, e_min)
    return TopOptScene(
        solvers=[solver],
        optimizer=optimizer,
        batches=lambda epoch, generator: [None],
        loss=loss,
        validate=validate,
        probe=lambda: (problem.bc.A_II.matrix(probe_theta.numpy()), problem.b, None),
        rtol_full=1e-6,
        epochs=config["epochs"],
        prdp={**PAPER, "k_init": config["k_init"], "k_step": config["k_step"]},
        info={
            "elements": int(count),
            "unknowns": int(len(problem.bc.interior)),
            "load_height": load_case(seed),
            **config,
        },
        problem=problem,
        designs=designs,
    )


# the comparison of schedules on three load cases (`prdp_petsc.lab.reports.topopt`):
# ``prdp-petsc scene demos/topopt3d.py results ...``
COMMANDS = topopt_reports.commands(sys.modules[__name__])


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
