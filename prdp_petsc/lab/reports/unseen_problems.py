"""Problems PRDP was never tuned on, each a plain torch loop a new user would write.

Each uses the library's public API only and offers what ``PRDP.for_problem`` needs: a
solver and a representative system (``probe``, for `prdp_petsc.find_k_full`), one epoch
of training, the metric, and a ``check`` (the gradient of the validation loss through
the solve capped at k); `prdp_petsc.lab.reports.unseen` runs them.  They differ in
everything the controller could have been tuned to:

``lshape_mlp``, ``box3d_regions``, ``sliver_mlp`` (`LogCoefficient`)
    −∇·(κ∇u) = 1, u = 0 on the boundary, κ = exp(Σ c_j φ_j) per element from smooth
    modes, on the L-shape (CG + Jacobi, Adam with a cosine schedule), the tetrahedral
    box (CG + GAMG, SGD with reduce-on-plateau) and the sliver mesh (CG + SOR, AdamW
    with a step decay, a Huber loss); an MLP maps noisy observations of u to c; metric:
    the relative error of c (independent of K).
``heat_sink``
    SIMP topology optimisation of a conductor (κ = 10⁻³ + ρ³(1 − 10⁻³)) on a unit square
    of quadrilaterals: uniform source, a cold sink on the left edge, minimal thermal
    compliance fᵀu at 40 % volume with a density filter and optimality-criteria updates;
    CG + ICC.  The metric, the compliance through the capped solve, reads low at small K.
``annulus_inverse``
    A nodal log-conductivity on the annulus fitted to noisy observations of u with a
    smoothness penalty; Adam with an exponential decay; CG + Jacobi.
``advection_source``
    −∇·(ε∇u) + β·∇u = s on the annulus (a spiral wind: non-symmetric), s from eight
    modes; an MLP maps u at 48 sensors to the modes' coefficients; GMRES + Jacobi; SGD
    with momentum and a step decay; smooth-L1 loss.
``plate_backward_heat``
    One implicit heat step (M + Δt K) u¹ = M u⁰ on the plate with three holes; an MLP
    maps u¹ to the modal coefficients of u⁰; CG + ICC; RMSprop with a one-cycle schedule.
``plate_source``
    A nodal source s on the plate with holes fitted to noisy u (−Δu = M s: the operator
    does not depend on what is trained) with a Tikhonov term; RMSprop; CG + SOR.

``sliver_mlp`` and ``plate_source`` were written after the controller's rules were
chosen on the other six and kept out of that choice (`HELD_OUT`).  The optimisation
problems have no network: their metric is the objective through the capped solve and
their final error (`Problem.score`) the objective at a direct solve.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from prdp_petsc import Dirichlet, KSPSolver, diffusion_operator, gradient_check, load_mesh, solve
from prdp_petsc import mass_matrix as fem_mass
from prdp_petsc.autograd.check import GradientCheck

from ..components.emulators import torch_sparse
from ..components.networks import mlp
from .problems import spiral_wind, unit_load

__all__ = ["HELD_OUT", "PROBLEMS", "RTOL_FULL", "Problem", "build"]

#: what "converged" means for every problem here
RTOL_FULL = 1e-8


class Problem:
    """One training or optimisation loop, driven epoch by epoch.

    Subclasses set `solver`, `epochs` and `probe` (A, b) and implement `train_epoch`,
    `metric`, `validation_loss` and, where the final error is scored apart, `score`.
    """

    name = ""
    solver: KSPSolver
    epochs: int
    probe: tuple

    def train_epoch(self, epoch: int) -> None:
        raise NotImplementedError

    def metric(self) -> float:
        """What the controller watches (lower is better)."""
        raise NotImplementedError

    def validation_loss(self) -> torch.Tensor:
        """The validation loss through the solver at its current cap (differentiable)."""
        raise NotImplementedError

    def trained(self) -> list[torch.Tensor]:
        """What the loop trains (network weights, or the design)."""
        raise NotImplementedError

    def score(self) -> float:
        """The final error reported for the run (default: the metric)."""
        return self.metric()

    def check(self) -> GradientCheck:
        """The controller's check, `prdp_petsc.gradient_check`: ``check(k)`` is the
        gradient of `validation_loss` with the solver capped at `k` (no training step),
        and ``check.spent()`` what the checks and the whole run cost so far."""
        return gradient_check(self.validation_loss, self.trained(), self.solver)


def _start(seed: int, offset: int, mesh: str, element: str = "ElementTriP1"):
    """The generator of a problem's data (seed ``offset + seed``; torch's seed `seed`, for
    its network), and a basis of the scikit-fem element class `element` on `mesh`."""
    import skfem

    rng = np.random.default_rng(offset + seed)
    torch.manual_seed(seed)
    return rng, skfem.Basis(load_mesh(mesh), getattr(skfem, element)())


def _modes(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` smooth random Fourier modes at `points` (d, N): shape (N, count)."""
    lo, hi = points.min(axis=1, keepdims=True), points.max(axis=1, keepdims=True)
    x = (points - lo) / (hi - lo)
    freq = rng.integers(1, 3, size=(count, x.shape[0]))
    phase = rng.uniform(0, 2 * np.pi, size=(count, x.shape[0]))
    out = np.ones((x.shape[1], count))
    for j in range(count):
        for d in range(x.shape[0]):
            out[:, j] *= np.cos(np.pi * freq[j, d] * x[d] + phase[j, d])
    return out


class NetworkInverse(Problem):
    """A network maps observations to the coefficients c of the physics; the loss
    compares the physics of its c, through the capped solve, with the observations."""

    batch = 8
    step_per_batch = False  # the scheduler steps after every batch, not every epoch
    loss_fn: Callable

    def setup(self, obs, coef, net, optimizer, scheduler, n_val: int, seed: int):
        self.obs_train, self.obs_val = obs[n_val:], obs[:n_val]
        self.coef_train, self.coef_val = coef[n_val:], coef[:n_val]
        self.scale = self.obs_train.std(dim=0, keepdim=True) + 1e-12
        self.mean = self.obs_train.mean(dim=0, keepdim=True)
        self.net, self.optimizer, self.scheduler = net, optimizer, scheduler
        self.order = torch.Generator().manual_seed(seed)

    def predict(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net((obs - self.mean) / self.scale)

    def physics(self, coef: torch.Tensor) -> torch.Tensor:
        """Observations of the physics for coefficients (B, m), through the solver."""
        raise NotImplementedError

    def train_epoch(self, epoch: int) -> None:
        perm = torch.randperm(len(self.obs_train), generator=self.order)
        for start in range(0, len(perm), self.batch):
            idx = perm[start : start + self.batch]
            self.optimizer.zero_grad()
            loss = self.loss_fn(self.physics(self.predict(self.obs_train[idx])),
                                self.obs_train[idx])  # fmt: skip
            loss.backward()
            self.optimizer.step()
            if self.step_per_batch:  # a one-cycle schedule steps with the optimiser
                self.scheduler.step()
        if isinstance(self.scheduler, torch.optim.lr_scheduler.ReduceLROnPlateau):
            with torch.no_grad():
                self.scheduler.step(float(self.validation_loss()))
        elif self.scheduler is not None and not self.step_per_batch:
            self.scheduler.step()

    def metric(self) -> float:
        with torch.no_grad():
            pred = self.predict(self.obs_val)
        return float(torch.linalg.norm(pred - self.coef_val) / torch.linalg.norm(self.coef_val))

    def validation_loss(self) -> torch.Tensor:
        return self.loss_fn(self.physics(self.predict(self.obs_val)), self.obs_val)

    def trained(self) -> list[torch.Tensor]:
        return list(self.net.parameters())


def _exact_solutions(A: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    lu = spla.splu(sp.csc_matrix(A))
    return np.stack([lu.solve(r) for r in rhs])


class LogCoefficient(NetworkInverse):
    """−∇·(κ∇u) = 1, u = 0 on the boundary, κ = exp(Σ c_j φ_j) per element from smooth
    modes; an MLP maps noisy observations of u to c (one operator per sample).

    A subclass declares its ``mesh`` and ``element`` and ``rng_offset`` (`_start`), number
    of ``modes``, observation ``noise``, ``samples`` and ``epoch_counts`` (quick, full),
    hidden ``width``, the CG ``pc`` and options ``prefix``, and builds its optimiser and
    schedule (`optimiser`).
    """

    def __init__(self, seed: int, quick: bool = False):
        rng, basis = _start(seed, self.rng_offset, self.mesh, self.element)
        mesh, n = basis.mesh, self.samples[0] if quick else self.samples[1]
        self.dir = Dirichlet(diffusion_operator(basis, "P0"), basis.get_dofs().all())
        self.phi = torch.from_numpy(_modes(mesh.p[:, mesh.t].mean(axis=1), self.modes, rng))
        coef = rng.normal(0.0, 0.5, size=(n, self.modes))
        theta = np.exp(coef @ self.phi.numpy().T)
        b = unit_load(basis)[self.dir.interior]
        u = np.stack([spla.spsolve(sp.csc_matrix(self.dir.A_II.matrix(t)), b) for t in theta])
        u *= 1.0 + self.noise * rng.standard_normal(u.shape)
        self.b = torch.from_numpy(b)
        self.probe = (self.dir.A_II.matrix(theta[0]), b)
        self.solver = KSPSolver({"ksp_type": "cg", "pc_type": self.pc}, prefix=self.prefix,
                                max_it=1)  # fmt: skip
        net = mlp(u.shape[1], self.modes, self.width, 2, torch.nn.Tanh)
        self.epochs = self.epoch_counts[0] if quick else self.epoch_counts[1]
        optimizer, scheduler = self.optimiser(net)
        self.setup(torch.from_numpy(u), torch.from_numpy(coef), net, optimizer, scheduler,
                   n // 4, seed)  # fmt: skip

    def optimiser(self, net) -> tuple:
        """(optimizer, scheduler) for the parameters of `net`."""
        raise NotImplementedError

    def loss_fn(self, pred, obs):
        return torch.mean((pred - obs) ** 2) / torch.mean(obs**2)

    def physics(self, coef):
        theta = torch.exp(coef @ self.phi.T)
        return solve(self.dir.A_II, self.b.expand(len(coef), -1), self.solver, theta=theta)


class LShapeMLP(LogCoefficient):
    name = "lshape_mlp"
    mesh, element, modes, noise = "lshape", "ElementTriP1", 6, 0.005
    samples, epoch_counts, width = (64, 160), (20, 60), 64
    pc, prefix, rng_offset = "jacobi", "u1_", 1000

    def optimiser(self, net) -> tuple:
        opt = torch.optim.Adam(net.parameters(), lr=3e-3)
        return opt, torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=self.epochs)


class Box3DRegions(LogCoefficient):
    name = "box3d_regions"
    mesh, element, modes, noise = "box3d", "ElementTetP1", 4, 0.002
    samples, epoch_counts, width = (48, 128), (15, 40), 32
    pc, prefix, rng_offset = "gamg", "u6_", 4000

    def optimiser(self, net) -> tuple:
        opt = torch.optim.SGD(net.parameters(), lr=0.02, momentum=0.9)
        return opt, torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.3, patience=3)


class SliverMLP(LogCoefficient):
    name = "sliver_mlp"
    mesh, element, modes, noise = "sliver", "ElementTriP1", 5, 0.003
    samples, epoch_counts, width = (64, 160), (20, 50), 48
    pc, prefix, rng_offset = "sor", "u7_", 7000

    def optimiser(self, net) -> tuple:
        opt = torch.optim.AdamW(net.parameters(), lr=3e-3, weight_decay=1e-4)
        return opt, torch.optim.lr_scheduler.StepLR(opt, step_size=self.epochs // 2, gamma=0.3)

    def loss_fn(self, pred, obs):
        scale = obs.abs().mean()
        return torch.nn.functional.huber_loss(pred / scale, obs / scale, delta=0.05)


class AdvectionSource(NetworkInverse):
    name = "advection_source"

    def __init__(self, seed: int, quick: bool = False):
        from skfem import BilinearForm
        from skfem.helpers import dot, grad

        rng, basis = _start(seed, 2000, "annulus")
        mesh = basis.mesh

        @BilinearForm
        def operator(u, v, w):
            wind = spiral_wind(*w.x)
            return 0.02 * dot(grad(u), grad(v)) + (wind[0] * grad(u)[0] + wind[1] * grad(u)[1]) * v

        interior = basis.complement_dofs(basis.get_dofs())
        A = operator.assemble(basis).tocsr()[interior][:, interior]
        psi = _modes(mesh.p, 8, rng)[interior]
        n = 64 if quick else 160
        coef = rng.normal(0.0, 1.0, size=(n, 8))
        self.A, self.psi = A, torch.from_numpy(psi)
        u = _exact_solutions(A, coef @ psi.T)
        self.sensors = torch.from_numpy(np.sort(rng.choice(len(interior), 48, replace=False)))
        obs = u[:, self.sensors.numpy()] * (1.0 + 0.002 * rng.standard_normal((n, 48)))
        self.solver = KSPSolver({"ksp_type": "gmres", "pc_type": "jacobi"}, prefix="u4_",
                                max_it=1)  # fmt: skip
        self.probe = (A, (coef @ psi.T)[0])
        net = mlp(48, 8, 64, 2, torch.nn.Tanh)
        opt = torch.optim.SGD(net.parameters(), lr=0.05, momentum=0.9)
        self.epochs = 20 if quick else 60
        sched = torch.optim.lr_scheduler.StepLR(opt, step_size=self.epochs // 3, gamma=0.3)
        scale = float(np.abs(obs).mean())
        self.loss_fn = lambda pred, o: torch.nn.functional.smooth_l1_loss(
            pred / scale, o / scale, beta=0.1
        )
        self.setup(torch.from_numpy(obs), torch.from_numpy(coef), net, opt, sched, n // 4, seed)

    def physics(self, coef):
        u = solve(self.A, coef @ self.psi.T, self.solver)
        return u[:, self.sensors]


class PlateBackwardHeat(NetworkInverse):
    name = "plate_backward_heat"
    step_per_batch = True

    def __init__(self, seed: int, quick: bool = False):
        rng, basis = _start(seed, 3000, "plate_holes")
        mesh = basis.mesh
        M = sp.csr_matrix(fem_mass(basis))
        K = diffusion_operator(basis, "P0").matrix(np.ones(mesh.t.shape[1]))
        A = (M + 2e-3 * K).tocsr()
        phi = _modes(mesh.p, 10, rng)
        n = 64 if quick else 160
        coef = rng.normal(0.0, 1.0, size=(n, 10))
        u1 = _exact_solutions(A, (M @ (phi @ coef.T)).T)
        u1 *= 1.0 + 0.002 * rng.standard_normal(u1.shape)
        self.A = A
        self.Mphi = torch.from_numpy(M @ phi)
        self.solver = KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, prefix="u5_", max_it=1)
        self.probe = (A, M @ phi @ coef[0])
        net = mlp(u1.shape[1], 10, 64, 2, torch.nn.Tanh)
        opt = torch.optim.RMSprop(net.parameters(), lr=1e-3)
        self.epochs = 20 if quick else 60
        steps = self.epochs * -(-(n - n // 4) // self.batch)
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=3e-3, total_steps=steps)
        self.loss_fn = lambda pred, o: torch.mean(
            torch.linalg.norm(pred - o, dim=-1) / torch.linalg.norm(o, dim=-1)
        )
        self.setup(torch.from_numpy(u1), torch.from_numpy(coef), net, opt, sched, n // 4, seed)

    def physics(self, coef):
        return solve(self.A, coef @ self.Mphi.T, self.solver)


class DesignProblem(Problem):
    """An optimisation loop without a network: `theta` is the design, the metric is
    the objective through the capped solve, the score the objective at a direct solve."""

    def trained(self) -> list[torch.Tensor]:
        return [self.theta]

    def metric(self) -> float:
        with torch.no_grad():
            return float(self.objective())

    def validation_loss(self) -> torch.Tensor:
        return self.objective()

    def objective(self) -> torch.Tensor:
        raise NotImplementedError

    def train_epoch(self, epoch: int) -> None:
        """One step of the optimiser on the objective, then one of the schedule."""
        self.optimizer.zero_grad()
        self.objective().backward()
        self.optimizer.step()
        self.scheduler.step()


class FieldFit(DesignProblem):
    """A nodal field `theta` fitted to noisy observations `data` of u with a penalty
    ``penalty · θᵀ R θ``; `state` is u through a solver, `direct` u by a direct solve."""

    penalty: float

    def state(self) -> torch.Tensor:
        raise NotImplementedError

    def direct(self) -> np.ndarray:
        raise NotImplementedError

    def misfit(self, u: torch.Tensor) -> torch.Tensor:
        fit = torch.sum((u - self.data) ** 2) / torch.sum(self.data**2)
        return fit + self.penalty * self.theta @ (self.R @ self.theta)

    def objective(self) -> torch.Tensor:
        return self.misfit(self.state())

    def score(self) -> float:
        with torch.no_grad():
            return float(self.misfit(torch.from_numpy(self.direct())))


class AnnulusInverse(FieldFit):
    name = "annulus_inverse"

    def __init__(self, seed: int, quick: bool = False):
        rng, basis = _start(seed, 5000, "annulus")
        mesh = basis.mesh
        self.dir = Dirichlet(diffusion_operator(basis, "P1"), basis.get_dofs().all())
        truth = _modes(mesh.p, 5, rng) @ rng.normal(0.0, 0.4, 5)
        b = unit_load(basis)[self.dir.interior]
        u = spla.spsolve(sp.csc_matrix(self.dir.A_II.matrix(np.exp(truth))), b)
        self.data = torch.from_numpy(u * (1.0 + 0.01 * rng.standard_normal(u.shape)))
        self.b = torch.from_numpy(b)
        self.R = torch_sparse(diffusion_operator(basis, "P1").matrix(np.ones(basis.N)))
        self.penalty = 1e-5
        self.theta = torch.zeros(basis.N, dtype=torch.float64, requires_grad=True)
        self.solver = KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, prefix="u3_",
                                max_it=1)  # fmt: skip
        self.probe = (self.dir.A_II.matrix(np.ones(basis.N)), b)
        self.optimizer = torch.optim.Adam([self.theta], lr=0.05)
        self.epochs = 40 if quick else 120
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma=0.98)

    def state(self) -> torch.Tensor:
        return solve(self.dir.A_II, self.b, self.solver, theta=torch.exp(self.theta))

    def direct(self) -> np.ndarray:
        A = sp.csc_matrix(self.dir.A_II.matrix(np.exp(self.theta.numpy())))
        return spla.spsolve(A, self.b.numpy())


class HeatSink(DesignProblem):
    name = "heat_sink"

    def __init__(self, seed: int, quick: bool = False):
        from skfem import Basis, ElementQuad1, MeshQuad

        rng = np.random.default_rng(6000 + seed)
        n = 24 if quick else 40
        mesh = MeshQuad.init_tensor(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
        basis = Basis(mesh, ElementQuad1())
        sink = basis.get_dofs(lambda x: (x[0] < 1e-9) & (abs(x[1] - 0.5) < 0.1 + 0.05 * seed))
        self.dir = Dirichlet(diffusion_operator(basis, "P0"), sink.all())
        self.f = torch.from_numpy(unit_load(basis))
        self.b = self.f[self.dir.interior]
        centres = mesh.p[:, mesh.t].mean(axis=1)
        dist = np.linalg.norm(centres[:, :, None] - centres[:, None, :], axis=0)
        weights = np.maximum(0.0, 1.5 / n - dist)
        self.filter = torch.from_numpy(weights / weights.sum(axis=1, keepdims=True))
        self.volume = 0.4
        start = self.volume + 0.02 * rng.standard_normal(mesh.t.shape[1])
        self.theta = torch.tensor(np.clip(start, 0.01, 1.0), requires_grad=True)
        self.solver = KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, prefix="u2_", max_it=1)
        self.probe = (self.dir.A_II.matrix(self._kappa().detach().numpy()), self.b.numpy())
        self.epochs = 30 if quick else 60

    def _kappa(self) -> torch.Tensor:
        rho = self.filter @ self.theta
        return 1e-3 + rho**3 * (1.0 - 1e-3)

    def objective(self) -> torch.Tensor:
        u = solve(self.dir.A_II, self.b, self.solver, theta=self._kappa())
        return self.b @ u

    def train_epoch(self, epoch: int) -> None:
        """One optimality-criteria update (move 0.2, bisection on the volume)."""
        self.theta.grad = None
        self.objective().backward()
        dc = (-self.theta.grad).clamp(min=1e-30).detach()
        rho = self.theta.detach()
        lo, hi = 1e-9, 1e9
        while hi / lo > 1 + 1e-6:
            mid = math.sqrt(lo * hi)
            new = torch.clamp(rho * torch.sqrt(dc / mid), rho - 0.2, rho + 0.2).clamp(1e-3, 1.0)
            lo, hi = (mid, hi) if new.mean() > self.volume else (lo, mid)
        with torch.no_grad():
            self.theta.copy_(new)

    def score(self) -> float:
        with torch.no_grad():
            A = sp.csc_matrix(self.dir.A_II.matrix(self._kappa().numpy()))
            return float(self.b.numpy() @ spla.spsolve(A, self.b.numpy()))


class PlateSource(FieldFit):
    name = "plate_source"

    def __init__(self, seed: int, quick: bool = False):
        rng, basis = _start(seed, 8000, "plate_holes")
        interior = basis.complement_dofs(basis.get_dofs())
        A = diffusion_operator(basis, "P1").matrix(np.ones(basis.N)).tocsr()
        M = fem_mass(basis).tocsr()
        self.A = A[interior][:, interior]
        self.M = self.R = torch_sparse(M[interior][:, interior])
        self.penalty = 1e-7
        truth = _modes(basis.doflocs, 6, rng)[interior] @ rng.normal(0.0, 1.0, 6)
        u = spla.spsolve(sp.csc_matrix(self.A), M[interior][:, interior] @ truth)
        self.data = torch.from_numpy(u * (1.0 + 0.01 * rng.standard_normal(u.shape)))
        self.theta = torch.zeros(len(interior), dtype=torch.float64, requires_grad=True)
        self.solver = KSPSolver({"ksp_type": "cg", "pc_type": "sor"}, prefix="u8_", max_it=1)
        self.probe = (self.A, M[interior][:, interior] @ truth)
        self.epochs = 30 if quick else 80
        self.optimizer = torch.optim.RMSprop([self.theta], lr=0.02)
        self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(self.optimizer, self.epochs)

    def state(self) -> torch.Tensor:
        return solve(self.A, self.M @ self.theta, self.solver)

    def direct(self) -> np.ndarray:
        return spla.spsolve(sp.csc_matrix(self.A), (self.M @ self.theta).numpy())


#: problem name -> class
PROBLEMS = {cls.name: cls for cls in (LShapeMLP, HeatSink, AnnulusInverse, AdvectionSource,
                                        PlateBackwardHeat, Box3DRegions)}  # fmt: skip
#: the held-out problems (written after the rules were chosen on `PROBLEMS`): name -> class
HELD_OUT = {cls.name: cls for cls in (SliverMLP, PlateSource)}


def build(name: str, seed: int, quick: bool = False) -> Problem:
    """Problem `name` of `PROBLEMS` or `HELD_OUT` with its data and initial weights from
    `seed`."""
    return {**PROBLEMS, **HELD_OUT}[name](seed, quick=quick)
