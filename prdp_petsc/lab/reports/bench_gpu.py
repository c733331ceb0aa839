"""prdp_petsc on one GPU against jax, lineax and a hand-written torch CG, fwd + bwd.

``prdp-petsc bench gpu --out DIR`` writes ``DIR/bench_gpu.json``.  One process on one
device (the GPU is the contended resource, not the host cores), every contender on the
same problems with the same right-hand side; on a machine without CUDA everything runs
on the CPU with PETSc's default types, so the harness is tested there.

Problems (``--problems``, names parsed by `problem`)
    ``lshape<r>``: P1 Poisson ``−Δu`` on ``skfem.MeshTri.init_lshaped().refined(r)``
    with its interior vertices jittered (seeded, at most 0.15 of the shortest edge per
    coordinate), Dirichlet boundary eliminated: r = 6, 8, 9 give 12 033, 195 585 and
    784 385 unknowns.  ``heat3d<m>``: one implicit heat step ``M + dt K`` (dt = 0.01)
    on ``skfem.MeshTet.init_tensor`` with m points per axis of the unit cube, Dirichlet
    boundary eliminated (m = 41: 59 319 unknowns).  Both assembled with the library's
    `prdp_petsc.diffusion_operator` (κ = 1) and `prdp_petsc.mass_matrix`; SPD.
Loss and what is timed
    ``L(b) = ½‖x_K(b) − x_ref‖²`` with ``x_K`` K iterations of Jacobi-preconditioned CG
    from x = 0 in fixed mode (no tolerance: exactly K), b and x_ref seeded normal
    vectors, float64.  One call is the forward solve, the loss's cotangent
    ``x − x_ref`` and the adjoint solve (gradient in b, ``∂L/∂b = λ``, ``A λ = x − x_ref``),
    ending with a device synchronisation (``torch.cuda.synchronize`` /
    ``block_until_ready``), so a call's time is the time its results are ready.
Contenders (each optional: one that cannot run here is skipped with its note)
    ``prdp_petsc``: ``pp.solve(A, b, pp.KSPSolver({"ksp_type": "cg", "pc_type":
    "jacobi", "vec_type": "cuda", "mat_type": "aijcusparse"}, max_it=K))`` with b a
    CUDA tensor, then ``loss.backward()`` (on the CPU without the two type options);
    ``prdp_petsc_sr`` adds ``ksp_cg_single_reduction`` (one reduction per CG iteration
    instead of two).  ``raw_petsc`` (and ``raw_petsc_sr``): the floor, petsc4py only,
    the same Mat type and KSP settings, Vecs wrapping torch tensors by DLPack
    (``Vec.createWithDLPack``), forward ``KSPSolve``, cotangent by torch, adjoint
    ``KSPSolve`` (what the bridge runs for a symmetric operator and a symmetric PC), no
    autograd, no checks; ``raw_petsc_transpose`` runs the adjoint as
    ``KSPSolveTranspose``.  ``jax_cg``: ``jax.jit(jax.grad(loss))`` around
    ``jax.scipy.sparse.linalg.cg`` (``M = d⁻¹``, BCOO matvec, or BCSR with
    ``--jax-matrix bcsr``; jax differentiates it implicitly, a second CG).
    ``lineax_cg``: ``lineax.linear_solve`` with ``lx.CG`` and the diagonal
    preconditioner, also implicit.  ``torch_pcg``: a hand-written
    Jacobi PCG on a torch sparse CSR tensor; its gradient is a second PCG on the
    cotangent (implicit: A is SPD), not autograd through the iterations.
Figures
    Per cell (problem, K): the median fwd + bwd time of each contender (``--rounds``
    paired rounds in rotating order, each timing ``--calls`` calls; per round the
    median; the ratio within each round; the median over rounds and the interquartile
    range over the median as ``noise``), the ratios ``prdp_petsc / raw_petsc`` (same
    KSP settings) and ``<contender> / jax_cg``, and every contender's x and gradient
    against prdp_petsc's (max |difference| / max |reference|; fixed-mode CG is the same
    arithmetic everywhere, so rounding).  ``cpu_gpu_agreement``: prdp_petsc on the
    GPU against prdp_petsc on the CPU at K = 10.  ``time_to_tolerance`` (problems of
    ``--tol-problems``): the reference gradient (SuperLU up to ``--direct-max-n``
    unknowns, above that a Jacobi CG in torch on the device, iteratively refined on its
    true residual until a correction changes the solution by less than 1e-11),
    the smallest K whose gradient is within ``--tol`` (1e-6) of it for Jacobi CG
    (found with torch_pcg, then checked and timed for every contender), and for
    prdp_petsc with ``pc_type gamg`` (the PC set up once: its first call's extra time
    is reported as ``setup_s``, beside the per-call time).

``--budget-s`` bounds the run: a step that would start after that many seconds is
skipped and listed in ``skipped``.  Where the lab's plotting packages are not
installed, ``python -m prdp_petsc.lab.reports.bench_gpu --out DIR`` runs the same
benchmark (PETSc options then through ``PETSC_OPTIONS``).  PETSc command-line options
reach the contenders' KSPs by prefix (``-prdp_petsc_ksp_view``,
``-raw_petsc_ksp_norm_type none``).  Never assert these times in tests; they describe
one machine.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import statistics
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..provenance import machine, provenance, versions, write_result
from .kinds import DataSet, ReportKind, markdown_table

__all__ = [
    "CONTENDERS",
    "GAMG",
    "Case",
    "Env",
    "HeatStep",
    "JaxCG",
    "KIND",
    "LShape",
    "PrdpPetsc",
    "RawPetsc",
    "Run",
    "TorchPCG",
    "bench_cell",
    "cpu_gpu_agreement",
    "format_report",
    "main",
    "pcg",
    "problem",
    "reference_gradient",
    "tight_cg",
    "time_to_tolerance",
    "verdicts",
]

logger = logging.getLogger(__name__)

DEFAULT_PROBLEMS = ("lshape6", "heat3d41", "lshape8", "lshape9")
DEFAULT_K = (10, 100, 300)
TARGETS = (
    "prdp_petsc / raw_petsc <= 1.15 (same KSP settings); prdp_petsc / jax_cg <= 2 from "
    "59 k unknowns up, <= 1.3 at 784 k, <= 3.5 at 12 k; CPU and GPU paths agree to 1e-10 "
    "at K = 10; prdp_petsc with GAMG reaches the 1e-6 gradient before every GPU peer's "
    "Jacobi CG"
)


# -- problems ------------------------------------------------------------------------------
@dataclass(frozen=True)
class LShape:
    """P1 ``−Δu`` on the jittered, `refine` times refined L-shape, Dirichlet eliminated."""

    refine: int
    jitter: float = 0.15
    seed: int = 0

    @property
    def name(self) -> str:
        return f"lshape{self.refine}"

    @property
    def label(self) -> str:
        return "L-shape P1"

    def matrix(self) -> sp.csr_matrix:
        import skfem

        import prdp_petsc as pp

        mesh = skfem.MeshTri.init_lshaped().refined(self.refine)
        edges = mesh.p[:, mesh.facets]
        h = float(np.linalg.norm(edges[:, 0] - edges[:, 1], axis=0).min())
        interior = np.setdiff1d(np.arange(mesh.nvertices), mesh.boundary_nodes())
        p = mesh.p.copy()
        rng = np.random.default_rng(self.seed)
        p[:, interior] += rng.uniform(-self.jitter * h, self.jitter * h, (2, interior.size))
        jittered = skfem.MeshTri(p, mesh.t)
        if np.any(_signed_areas(jittered) * _signed_areas(mesh) <= 0):
            raise RuntimeError(f"{self.name}: the jitter folded a triangle")
        mesh = jittered
        basis = skfem.Basis(mesh, skfem.ElementTriP1())
        stiffness = pp.diffusion_operator(basis)
        A = stiffness.matrix(np.ones(stiffness.n_params))
        return _interior(A, basis.complement_dofs(mesh.boundary_nodes()))


@dataclass(frozen=True)
class HeatStep:
    """One implicit heat step ``M + dt K`` (P1) on `axis`³ points of the unit cube,
    Dirichlet eliminated."""

    axis: int
    dt: float = 0.01

    @property
    def name(self) -> str:
        return f"heat3d{self.axis}"

    @property
    def label(self) -> str:
        return "3D heat step P1"

    def matrix(self) -> sp.csr_matrix:
        import skfem

        import prdp_petsc as pp

        line = np.linspace(0.0, 1.0, self.axis)
        mesh = skfem.MeshTet.init_tensor(line, line, line)
        basis = skfem.Basis(mesh, skfem.ElementTetP1())
        stiffness = pp.diffusion_operator(basis)
        A = pp.mass_matrix(basis) + self.dt * stiffness.matrix(np.ones(stiffness.n_params))
        return _interior(A, basis.complement_dofs(mesh.boundary_nodes()))


def _signed_areas(mesh) -> np.ndarray:
    corners = mesh.p[:, mesh.t]
    d1, d2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return d1[0] * d2[1] - d1[1] * d2[0]


def _interior(A: sp.spmatrix, keep: np.ndarray) -> sp.csr_matrix:
    A = sp.csr_matrix(A)[keep][:, keep].tocsr()
    A.sort_indices()
    return A


def problem(name: str) -> LShape | HeatStep:
    """The problem a ``--problems`` name stands for: ``lshape<r>`` or ``heat3d<m>``."""
    if m := re.fullmatch(r"lshape(\d+)", name):
        return LShape(int(m[1]))
    if (m := re.fullmatch(r"heat3d(\d+)", name)) and int(m[1]) >= 3:
        return HeatStep(int(m[1]))
    raise argparse.ArgumentTypeError(
        f"unknown problem {name!r}: lshape<refinements> (lshape6: 12 033 unknowns) or "
        "heat3d<points per axis> (heat3d41: 59 319)"
    )


# -- the environment and one problem's data ----------------------------------------------
@dataclass
class Env:
    """Where the run happens: the torch device and what can run there."""

    device: str  # "cuda" or "cpu"
    petsc_cuda: bool
    jax_note: str | None  # None when jax (and the device's jax backend) is usable

    @property
    def cuda(self) -> bool:
        return self.device == "cuda"

    def sync(self) -> None:
        if self.cuda:
            import torch

            torch.cuda.synchronize()


@dataclass
class Case:
    """One problem's matrix, b and x_ref, and their copies kept on the device."""

    name: str
    A: sp.csr_matrix
    b: np.ndarray
    x_ref: np.ndarray
    env: Env
    jax_matrix: str = "bcoo"  # jax's sparse format: "bcoo" or "bcsr"
    _cache: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.A.shape[0]

    def release(self) -> None:
        """Drop the device copies (the next problem's need the memory)."""
        self._cache.clear()

    def torch(self):
        """(A as a torch sparse CSR tensor, 1/diag(A), b, x_ref) on the device."""
        if "torch" not in self._cache:
            import torch

            dev = self.env.device
            A = self.A
            with warnings.catch_warnings():  # "sparse CSR support is in beta"
                warnings.simplefilter("ignore", UserWarning)
                At = torch.sparse_csr_tensor(
                    torch.as_tensor(A.indptr, dtype=torch.int64),
                    torch.as_tensor(A.indices, dtype=torch.int64),
                    torch.as_tensor(A.data),
                    size=A.shape,
                    check_invariants=False,
                ).to(dev)
            inv = torch.as_tensor(1.0 / A.diagonal()).to(dev)
            self._cache["torch"] = (At, inv, _tensor(self.b, dev), _tensor(self.x_ref, dev))
        return self._cache["torch"]

    def jax(self):
        """(jax module, jnp, A as a BCOO (or BCSR) array, 1/diag(A), b, x_ref) on jax's
        device."""
        if "jax" not in self._cache:
            import jax

            jax.config.update("jax_enable_x64", True)
            import jax.numpy as jnp
            from jax.experimental import sparse as jsparse

            self._cache["jax"] = (
                jax,
                jnp,
                getattr(jsparse, self.jax_matrix.upper()).from_scipy_sparse(self.A),
                jnp.asarray(1.0 / self.A.diagonal()),
                jnp.asarray(self.b),
                jnp.asarray(self.x_ref),
            )
        return self._cache["jax"]


def _tensor(array: np.ndarray, device: str):
    import torch

    return torch.as_tensor(np.ascontiguousarray(array), dtype=torch.float64).to(device)


@dataclass
class Run:
    """One contender built for one (problem, K): `call` runs fwd + bwd (synchronised),
    `result` returns (x, gradient) on the host (after a call), `info` what ran."""

    call: object
    result: object
    info: object  # info() -> dict
    set_k: object = None  # move K without building again (prdp_petsc only)


# -- contenders ----------------------------------------------------------------------------
@dataclass(frozen=True)
class PrdpPetsc:
    """``pp.solve`` with a KSPSolver of these options, ``loss.backward()``."""

    name: str
    pc_type: str = "jacobi"
    single_reduction: bool = False

    @property
    def describe(self) -> str:
        extra = ", ksp_cg_single_reduction" if self.single_reduction else ""
        return (
            f"pp.solve + backward, cg/{self.pc_type}{extra} (on the GPU with vec_type cuda, "
            "mat_type aijcusparse)"
        )

    def missing(self, env: Env) -> str | None:
        if env.cuda and not env.petsc_cuda:
            return "PETSc is built without CUDA (PETSc.Sys.hasExternalPackage('cuda') False)"
        return None

    def options(self, cuda: bool) -> dict:
        options = {"ksp_type": "cg", "pc_type": self.pc_type}
        if cuda:
            options.update(vec_type="cuda", mat_type="aijcusparse")
        if self.single_reduction:
            options["ksp_cg_single_reduction"] = True
        return options

    def build(self, case: Case, k: int, *, on: str | None = None) -> Run:
        import torch

        import prdp_petsc as pp

        device = on or case.env.device
        solver = pp.KSPSolver(self.options(device == "cuda"), prefix=f"{self.name}_", max_it=k)
        b = _tensor(case.b, device).requires_grad_(True)
        x_ref = _tensor(case.x_ref, device)
        out = {}

        def call():
            b.grad = None
            x = pp.solve(case.A, b, solver)
            (0.5 * torch.sum((x - x_ref) ** 2)).backward()
            if device == "cuda":
                torch.cuda.synchronize()
            out["x"] = x

        def result():
            return out["x"].detach().cpu().numpy(), b.grad.cpu().numpy()

        def set_k(new_k):
            solver.max_it = new_k

        def info():
            stats = solver.stats
            mat = solver.ksp.getOperators()[0]
            return {
                "options": self.options(device == "cuda"),
                "ksp": [solver.ksp.getType(), solver.ksp.getPC().getType()],
                "mat_type": mat.getType() if mat.handle else None,
                "forward_iterations_per_solve": stats.forward_iterations
                / max(stats.forward_solves, 1),
                "adjoint_iterations_per_solve": stats.adjoint_iterations
                / max(stats.adjoint_solves, 1),
                "pc_setups": stats.pc_setups,
            }

        return Run(call, result, info, set_k)


@dataclass(frozen=True)
class RawPetsc:
    """petsc4py only: forward KSPSolve, cotangent in torch, adjoint KSPSolve(Transpose)."""

    name: str
    single_reduction: bool = False
    transpose: bool = False

    @property
    def describe(self) -> str:
        adjoint = "KSPSolveTranspose" if self.transpose else "KSPSolve"
        extra = ", ksp_cg_single_reduction" if self.single_reduction else ""
        return f"petsc4py KSPSolve + {adjoint} on DLPack Vecs, cg/jacobi{extra}"

    missing = PrdpPetsc.missing

    def build(self, case: Case, k: int) -> Run:
        import torch
        from petsc4py import PETSc

        cuda = case.env.cuda
        A = case.A
        mat = PETSc.Mat().create(comm=PETSc.COMM_SELF)
        mat.setSizes(A.shape)
        mat.setType("aijcusparse" if cuda else "aij")
        indptr, indices = (a.astype(PETSc.IntType) for a in (A.indptr, A.indices))
        mat.setPreallocationCSR((indptr, indices, A.data))
        mat.assemble()
        mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        prefix = f"{self.name}_"
        options = PETSc.Options()
        options[f"{prefix}ksp_cg_single_reduction"] = bool(self.single_reduction)
        ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
        ksp.setOptionsPrefix(prefix)
        ksp.setType("cg")
        ksp.getPC().setType("jacobi")
        ksp.setOperators(mat)
        ksp.setTolerances(rtol=0.0, atol=0.0, max_it=k)
        ksp.setFromOptions()
        ksp.setUp()
        _, _, b, x_ref = case.torch()
        x, g, lam = (torch.zeros_like(b) for _ in range(3))
        vb, vx, vg, vlam = (PETSc.Vec().createWithDLPack(t, comm=PETSc.COMM_SELF)
                            for t in (b, x, g, lam))  # fmt: skip
        for v in (vb, vx, vg, vlam):
            v.stateIncrease()  # a fresh Vec's state 0 would read PETSc's norm cache as 0
        adjoint = ksp.solveTranspose if self.transpose else ksp.solve
        iterations = set()

        def call():
            ksp.solve(vb, vx)
            iterations.add(ksp.getIterationNumber())
            torch.sub(x, x_ref, out=g)
            vg.stateIncrease()  # torch wrote g behind PETSc's back
            adjoint(vg, vlam)
            iterations.add(ksp.getIterationNumber())
            if cuda:
                torch.cuda.synchronize()

        def result():
            return x.cpu().numpy(), lam.cpu().numpy()

        def info():
            return {
                "ksp": [ksp.getType(), ksp.getPC().getType()],
                "mat_type": mat.getType(),
                "vec_type": vb.getType(),
                "single_reduction": options.getBool(f"{prefix}ksp_cg_single_reduction"),
                "iterations_per_solve": sorted(iterations),
            }

        return Run(call, result, info)


@dataclass(frozen=True)
class JaxCG:
    """``jax.jit(jax.grad)`` around jax.scipy's CG (``lineax``: lineax's CG)."""

    name: str
    lineax: bool = False

    @property
    def describe(self) -> str:
        if self.lineax:
            return "jax.jit(jax.grad) of lineax.linear_solve(lx.CG, diagonal preconditioner)"
        return "jax.jit(jax.grad) of jax.scipy.sparse.linalg.cg(M = 1/diag), sparse matvec"

    def missing(self, env: Env) -> str | None:
        if env.jax_note:
            return env.jax_note
        if self.lineax:
            try:
                import lineax  # noqa: F401
            except ImportError:
                return "lineax is not installed"
        return None

    def build(self, case: Case, k: int) -> Run:
        jax, jnp, A, inv_diag, b, x_ref = case.jax()
        # the matrix is an argument, not a closure: a constant of 10⁶ entries baked
        # into the compiled program would slow its compilation down
        if self.lineax:
            import lineax as lx

            tags = (lx.symmetric_tag, lx.positive_semidefinite_tag)
            shape = jax.ShapeDtypeStruct(b.shape, b.dtype)
            cg = lx.CG(rtol=0.0, atol=0.0, max_steps=k)

            def solve(b, A, inv_diag):
                op = lx.FunctionLinearOperator(lambda x: A @ x, shape, tags=tags)
                precond = lx.TaggedLinearOperator(lx.DiagonalLinearOperator(inv_diag), tags)
                options = {"preconditioner": precond}
                return lx.linear_solve(op, b, cg, options=options, throw=False).value
        else:

            def solve(b, A, inv_diag):
                cg = jax.scipy.sparse.linalg.cg
                M = lambda r: inv_diag * r  # noqa: E731
                return cg(lambda x: A @ x, b, tol=0.0, atol=0.0, maxiter=k, M=M)[0]

        def loss(b, A, inv_diag, x_ref):
            x = solve(b, A, inv_diag)
            return 0.5 * jnp.sum((x - x_ref) ** 2), x

        grad = jax.jit(jax.grad(loss, has_aux=True))
        out = {}

        def call():
            out["g"], out["x"] = jax.block_until_ready(grad(b, A, inv_diag, x_ref))

        def result():
            return np.asarray(out["x"]), np.asarray(out["g"])

        def info():
            matvec = f"{case.jax_matrix.upper()} @ x"
            return {"device": str(next(iter(b.devices()))), "matvec": matvec}

        return Run(call, result, info)


@dataclass(frozen=True)
class TorchPCG:
    """A hand-written Jacobi PCG on a torch sparse CSR tensor; gradient by a second PCG."""

    name: str

    @property
    def describe(self) -> str:
        return (
            "hand-written torch Jacobi PCG (sparse CSR matvec); gradient: a second PCG on "
            "x - x_ref (implicit, A SPD), no autograd through the iterations"
        )

    def missing(self, env: Env) -> str | None:
        return None

    def build(self, case: Case, k: int) -> Run:
        import torch

        A, inv_diag, b, x_ref = case.torch()
        out = {}

        def call():
            x = pcg(A, inv_diag, b, k)
            out["x"], out["g"] = x, pcg(A, inv_diag, x - x_ref, k)
            if case.env.cuda:
                torch.cuda.synchronize()

        def result():
            return out["x"].cpu().numpy(), out["g"].cpu().numpy()

        return Run(call, result, lambda: {"matvec": "torch sparse CSR @ x"})


def pcg(A, inv_diag, rhs, k: int, *, rtol: float | None = None, every: int = 100):
    """K iterations of Jacobi-preconditioned CG from zero, scalars kept on the device
    (no host synchronisation inside).  With `rtol`, stop once ``‖r‖ ≤ rtol ‖rhs‖``,
    read on the host every `every` iterations."""
    import torch

    x = torch.zeros_like(rhs)
    r = rhs.clone()
    z = inv_diag * r
    p = z.clone()
    rz = torch.dot(r, z)
    stop = None if rtol is None else rtol * float(torch.linalg.vector_norm(rhs))
    for i in range(k):
        q = A @ p
        alpha = rz / torch.dot(p, q)
        x.add_(alpha * p)
        r.sub_(alpha * q)
        torch.mul(inv_diag, r, out=z)
        rz_new = torch.dot(r, z)
        p.mul_(rz_new / rz).add_(z)
        rz = rz_new
        if stop is not None and i % every == every - 1:
            if float(torch.linalg.vector_norm(r)) <= stop:
                break
    return x


#: Every contender, in the order the tables list them.
CONTENDERS = (
    PrdpPetsc("prdp_petsc"),
    PrdpPetsc("prdp_petsc_sr", single_reduction=True),
    RawPetsc("raw_petsc"),
    RawPetsc("raw_petsc_sr", single_reduction=True),
    RawPetsc("raw_petsc_transpose", transpose=True),
    JaxCG("jax_cg"),
    JaxCG("lineax_cg", lineax=True),
    TorchPCG("torch_pcg"),
)
GAMG = PrdpPetsc("prdp_petsc_gamg", pc_type="gamg")
#: (numerator, denominator) of the ratios reported per cell, besides ``c / jax_cg``
PAIRS = (
    ("prdp_petsc", "raw_petsc"),
    ("prdp_petsc_sr", "raw_petsc_sr"),
    ("prdp_petsc", "raw_petsc_transpose"),
)


# -- measuring -----------------------------------------------------------------------------
class Budget:
    """The run's time budget: `allows` says whether a step may still start."""

    def __init__(self, seconds: float | None) -> None:
        self.seconds, self.start, self.skipped = seconds, time.perf_counter(), []

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def allows(self, what: str) -> bool:
        if self.seconds is None or self.elapsed() < self.seconds:
            return True
        self.skipped.append({"what": what, "why": f"budget of {self.seconds:g} s spent"})
        logger.warning("skipped %s: budget spent", what)
        return False


def _time_calls(run: Run, calls: int) -> list[float]:
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        run.call()
        times.append(time.perf_counter() - t)
    return times


def _rel(a: np.ndarray, ref: np.ndarray) -> float:
    scale = float(np.abs(ref).max())
    return float(np.abs(a - ref).max() / scale) if scale > 0 else float(np.abs(a).max())


def _summary(r: np.ndarray) -> dict:
    q1, q2, q3 = np.percentile(r, [25, 50, 75])
    return {"median": float(q2), "q1": float(q1), "q3": float(q3), "noise": float((q3 - q1) / q2)}


def _build(contender, case: Case, k: int, notes: dict, **kwargs) -> Run | None:
    """Build and call once (set-up, compilation); None, with a note, if that fails."""
    try:
        run = contender.build(case, k, **kwargs)
        run.call()
        return run
    except Exception as err:  # one contender failing must not stop the others
        notes[contender.name] = f"failed: {type(err).__name__}: {err}"
        logger.warning("%s on %s, K = %d: %s", contender.name, case.name, k, err)
        return None


def bench_cell(case: Case, k: int, contenders, rounds: int, calls: int, warmup: int) -> dict:
    """Time every contender at K on `case` (paired rounds); agreement with prdp_petsc."""
    notes, runs, setup = {}, {}, {}
    for c in contenders:
        t = time.perf_counter()
        if (run := _build(c, case, k, notes)) is not None:
            setup[c.name] = time.perf_counter() - t
            _time_calls(run, warmup)
            runs[c.name] = run
    names = list(runs)
    timings = {name: [] for name in names}
    for r in range(rounds):
        order = names[r % len(names) :] + names[: r % len(names)] if names else []
        if r % 2:
            order.reverse()
        for name in order:
            timings[name].append(_time_calls(runs[name], calls))
    med = {name: np.array([statistics.median(t) for t in timings[name]]) for name in names}
    results = {name: runs[name].result() for name in names}
    reference = "prdp_petsc" if "prdp_petsc" in results else (names[0] if names else None)
    agreement = {}
    if reference is not None:
        x0, g0 = results[reference]
        for name in names:
            if name != reference:
                x, g = results[name]
                agreement[name] = {"x": _rel(x, x0), "grad": _rel(g, g0)}
    ratios = {}
    for num, den in PAIRS:
        if num in med and den in med:
            ratios[f"{num}/{den}"] = _summary(med[num] / med[den])
    if "jax_cg" in med:
        for name in names:
            if name != "jax_cg":
                ratios[f"{name}/jax_cg"] = _summary(med[name] / med["jax_cg"])
    return {
        "problem": case.name,
        "n": case.n,
        "k": k,
        "median_s": {name: float(np.median(med[name])) for name in names},
        "ratios": ratios,
        "reference": reference,
        "agreement": agreement,
        "setup_s": setup,
        "info": {name: runs[name].info() for name in names},
        "notes": notes,
        "round_medians_s": {name: med[name].tolist() for name in names},
        "timings_s": timings,
    }


def cpu_gpu_agreement(case: Case, k: int, devices=("cuda", "cpu")) -> dict:
    """prdp_petsc on the GPU (CUDA types) against prdp_petsc on the CPU (default types):
    the max relative difference of x and of the gradient (`devices`: the two runs)."""
    notes = {}
    runs = [_build(CONTENDERS[0], case, k, notes, on=device) for device in devices]
    if None in runs:
        return {"k": k, "note": "; ".join(notes.values())}
    (x1, g1), (x2, g2) = (run.result() for run in runs)
    return {"k": k, "x": _rel(x1, x2), "grad": _rel(g1, g2), "target": 1e-10}


# -- time to a gradient within tol of the direct one --------------------------------------
def reference_gradient(case: Case, direct_max_n: int) -> dict:
    """x* = A⁻¹b and ∇* = A⁻¹(x* − x_ref): scipy's spsolve up to `direct_max_n`
    unknowns, above that a tight Jacobi CG in torch on the device."""
    t = time.perf_counter()
    if case.n <= direct_max_n:
        import scipy.sparse.linalg as spla

        lu = spla.splu(case.A.tocsc())
        x = lu.solve(case.b)
        grad = lu.solve(x - case.x_ref)
        how = "scipy.sparse.linalg.splu (SuperLU, COLAMD)"
        last = {}
    else:
        x, change_x = tight_cg(case, case.torch()[2])
        grad, change_grad = tight_cg(case, x - case.torch()[3])
        x, grad = x.cpu().numpy(), grad.cpu().numpy()
        how = "torch Jacobi CG, iteratively refined until a correction is below 1e-11"
        last = {"last_corrections": [change_x, change_grad]}
    residual = [
        float(np.linalg.norm(case.A @ x - case.b) / np.linalg.norm(case.b)),
        float(np.linalg.norm(case.A @ grad - (x - case.x_ref)) / np.linalg.norm(x - case.x_ref)),
    ]
    return {
        "grad": grad,
        "method": how,
        "relative_residuals": residual,
        **last,
        "seconds": time.perf_counter() - t,
    }


def tight_cg(case: Case, rhs, inner_rtol: float = 1e-12, settled: float = 1e-11, rounds: int = 10):
    """Solve A x = rhs by iterative refinement: Jacobi CG on the true residual, each to
    `inner_rtol` of its own right-hand side, until a correction changes x by at most
    `settled` (relative), so the recursive residual's drift cannot fake convergence.
    Returns x and the relative size of the last correction."""
    import torch

    A, inv_diag, _, _ = case.torch()
    x = torch.zeros_like(rhs)
    for _ in range(rounds):
        d = pcg(A, inv_diag, rhs - A @ x, 100 * case.n, rtol=inner_rtol)
        x += d
        change = float(torch.linalg.vector_norm(d) / torch.linalg.vector_norm(x))
        if change <= settled:
            return x, change
    raise RuntimeError(f"{case.name}: the reference CG did not settle (last change {change:.1e})")


def _smallest_k(error, tol: float, k0: int, k_max: int) -> tuple[int | None, list]:
    """The smallest K (to 1 %) with ``error(K) <= tol``: doubling, then bisection."""
    trace, lo, k = [], 0, k0
    while True:
        e = error(k)
        trace.append([k, e])
        if e <= tol:
            break
        if k >= k_max:
            return None, trace
        lo, k = k, min(2 * k, k_max)
    hi = k
    while hi - lo > max(1, hi // 100):
        mid = (lo + hi) // 2
        e = error(mid)
        trace.append([mid, e])
        lo, hi = (lo, mid) if e <= tol else (mid, hi)
    return hi, trace


def time_to_tolerance(
    case: Case, contenders, tol: float, calls: int, direct_max_n: int, k_max: int, budget
) -> dict:
    """For each contender the smallest K reaching `tol` and its fwd + bwd time there."""
    ref = reference_gradient(case, direct_max_n)
    grad_ref = ref.pop("grad")
    out = {"tol": tol, "reference": ref, "contenders": {}, "notes": {}}

    def error_of(run: Run) -> float:
        return _rel_norm(run.result()[1], grad_ref)

    by_name = {c.name: c for c in contenders}  # torch_pcg searches fastest: no set-up
    searcher = by_name.get("torch_pcg", by_name.get("prdp_petsc"))
    if searcher is None:
        out["notes"]["jacobi"] = "neither torch_pcg nor prdp_petsc runs here: no K search"
    else:

        def error(k):
            run = searcher.build(case, k)
            run.call()
            return error_of(run)

        k_star, trace = _smallest_k(error, tol, 16, k_max)
        out["jacobi"] = {"k": k_star, "searched_with": searcher.name, "search": trace}
        for c in contenders if k_star is not None else ():
            if not budget.allows(f"time to {tol:g}: {c.name} on {case.name}"):
                continue
            out["contenders"][c.name] = _at_k(c, case, k_star, tol, calls, error_of, out["notes"])
    if GAMG.missing(case.env) is None and budget.allows(f"time to {tol:g}: GAMG on {case.name}"):
        out["gamg"] = _gamg(case, tol, calls, error_of, k_max, out["notes"])
    return out


def _rel_norm(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(a - ref) / np.linalg.norm(ref))


def _at_k(c, case: Case, k: int, tol: float, calls: int, error_of, notes: dict) -> dict | None:
    """`c` at K, raised by 5 % (at most twice) while its own gradient misses `tol`."""
    for _ in range(3):
        run = _build(c, case, k, notes)
        if run is None:
            return None
        err = error_of(run)
        if err <= tol:
            break
        k = int(np.ceil(1.05 * k))
    times = _time_calls(run, calls)
    return {"k": k, "grad_error": err, "median_s": statistics.median(times), "times_s": times}


def _gamg(case: Case, tol: float, calls: int, error_of, k_max: int, notes: dict) -> dict | None:
    """prdp_petsc with CG + GAMG: the PC set up once, K moved on the same solver."""
    t = time.perf_counter()
    run = _build(GAMG, case, 1, notes)  # the first call sets the PC up
    if run is None:
        return None
    first = time.perf_counter() - t
    again = _time_calls(run, 1)[0]  # the same call with the PC kept

    def error(k):
        run.set_k(k)
        run.call()
        return error_of(run)

    k_star, trace = _smallest_k(error, tol, 1, k_max)
    if k_star is None:
        return {"k": None, "search": trace, "note": f"no K <= {k_max} reached {tol:g}"}
    err = error(k_star)
    times = _time_calls(run, calls)
    return {
        "k": k_star,
        "grad_error": err,
        "median_s": statistics.median(times),
        "setup_s": max(first - again, 0.0),
        "first_call_s": first,
        "times_s": times,
        "search": trace,
        "info": run.info(),
    }


# -- the run -------------------------------------------------------------------------------
def environment(device: str) -> Env:
    """What can run where: `device` ``auto`` picks CUDA when torch sees a GPU."""
    import torch
    from petsc4py import PETSc

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda: torch sees no CUDA device")
    try:
        import jax

        backends = {d.platform for d in jax.devices()}
        jax_note = None
        if device == "cuda" and "gpu" not in backends and "cuda" not in backends:
            jax_note = f"jax has no GPU backend here (devices: {sorted(backends)})"
    except ImportError:
        jax_note = "jax is not installed"
    return Env(device, bool(PETSc.Sys.hasExternalPackage("cuda")), jax_note)


def device_info(env: Env) -> dict:
    """The device's name and the CUDA versions torch and PETSc run on."""
    import torch
    from petsc4py import PETSc

    info = {"kind": env.device, "petsc_cuda": env.petsc_cuda, "torch_cuda": torch.version.cuda}
    if env.cuda:
        info["name"] = torch.cuda.get_device_name()
        props = torch.cuda.get_device_properties(0)
        info["memory_gib"] = round(props.total_memory / 2**30, 1)
    else:
        from ..provenance import cpu

        info["name"] = cpu()
    info["petsc_version"] = PETSc.Sys.getVersionInfo()
    if env.jax_note is None:
        import jax

        info["jax_devices"] = [str(d) for d in jax.devices()]
    return info


def bench_gpu(args, env: Env, budget: Budget) -> dict:
    """Every problem, cell and time to tolerance of `args`; a JSON-ready dict."""
    import torch

    contenders, availability = [], {}
    for c in CONTENDERS:
        why = "left out by --skip" if c.name in args.skip else c.missing(env)
        availability[c.name] = {"describe": c.describe, "available": why is None, "note": why}
        if why is None:
            contenders.append(c)
    gamg_note = GAMG.missing(env)
    availability[GAMG.name] = {"describe": GAMG.describe, "available": gamg_note is None,
                               "note": gamg_note}  # fmt: skip
    problems, cells, agreement, tolerance = {}, [], {}, {}
    for name in args.problems:
        if not budget.allows(f"problem {name}"):
            continue
        t = time.perf_counter()
        spec = problem(name)
        A = spec.matrix()
        rng = np.random.default_rng(args.seed)
        b, x_ref = rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])
        case = Case(name, A, b, x_ref, env, args.jax_matrix)
        problems[name] = {"label": spec.label, "n": case.n, "nnz": int(A.nnz),
                          "build_s": time.perf_counter() - t}  # fmt: skip
        logger.info("%s: n = %d, nnz = %d", name, case.n, A.nnz)
        for k in args.k:
            if budget.allows(f"{name}, K = {k}"):
                cells.append(bench_cell(case, k, contenders, args.rounds, args.calls, args.warmup))
        if env.cuda and budget.allows(f"CPU/GPU agreement on {name}"):
            agreement[name] = cpu_gpu_agreement(case, 10)
        if name in args.tol_problems and budget.allows(f"time to {args.tol:g} on {name}"):
            tolerance[name] = time_to_tolerance(
                case, contenders, args.tol, args.tol_calls, args.direct_max_n, args.k_max, budget
            )
        case.release()
        if env.cuda:
            torch.cuda.empty_cache()
    if not env.cuda:
        agreement = {"note": "no CUDA device: the whole run is on the CPU path"}
    return {
        "device": device_info(env),
        "problems": problems,
        "contenders": availability,
        "cells": cells,
        "cpu_gpu_agreement": agreement,
        "time_to_tolerance": tolerance,
        "skipped": budget.skipped,
    }


def format_report(d: dict) -> str:
    """The printed summary of a `bench_gpu` result: the issue's table and the ratios."""
    dev = d["device"]
    lines = [f"device: {dev['name']} ({dev['kind']}; PETSc with CUDA: {dev['petsc_cuda']})"]
    for name, c in d["contenders"].items():
        if not c["available"]:
            lines.append(f"  skipped {name}: {c['note']}")
    names = [n for n in d["contenders"] if any(n in cell["median_s"] for cell in d["cells"])]
    lines += ["", "| problem (unknowns) | K | " + " | ".join(names) + " |",
              "|---|---|" + "---|" * len(names)]  # fmt: skip
    for pname, p in d["problems"].items():
        cells = [c for c in d["cells"] if c["problem"] == pname]
        if not cells:
            continue
        row = [
            f"{p['label']} ({p['n']:,})".replace(",", " "),
            " / ".join(str(c["k"]) for c in cells),
        ]
        for n in names:
            row.append(" / ".join(_ms(c["median_s"].get(n)) for c in cells) + " ms")
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "ratios (median over rounds; noise = IQR/median) and agreement with prdp_petsc:"]
    for c in d["cells"]:
        ratios = ", ".join(f"{k} {r['median']:.2f}" for k, r in c["ratios"].items())
        worst = max((max(a.values()) for a in c["agreement"].values()), default=float("nan"))
        lines.append(f"  {c['problem']} K={c['k']}: {ratios or '-'}; max rel. diff {worst:.1e}")
        for name, note in c["notes"].items():
            lines.append(f"    {name}: {note}")
    agreement = d["cpu_gpu_agreement"]
    if "note" in agreement:
        lines.append(f"CPU vs GPU path: {agreement['note']}")
    for pname, a in agreement.items():
        if isinstance(a, dict) and "grad" in a:
            lines.append(
                f"CPU vs GPU path, {pname} K={a['k']}: x {a['x']:.1e}, grad {a['grad']:.1e}"
            )
    for pname, t in d["time_to_tolerance"].items():
        ref = t["reference"]
        lines.append(
            f"time to a {t['tol']:g} gradient on {pname} (reference: {ref['method']}, "
            f"{ref['seconds']:.1f} s; residuals {ref['relative_residuals'][0]:.1e}, "
            f"{ref['relative_residuals'][1]:.1e}):"
        )
        for name, r in t["contenders"].items():
            if r is not None:
                lines.append(f"  {name:<20} K = {r['k']:>6}  {r['median_s'] * 1e3:9.2f} ms  "
                             f"(error {r['grad_error']:.1e})")  # fmt: skip
        if g := t.get("gamg"):
            if g.get("k") is not None:
                lines.append(f"  {'prdp_petsc + GAMG':<20} K = {g['k']:>6}  "
                             f"{g['median_s'] * 1e3:9.2f} ms  (error {g['grad_error']:.1e}; "
                             f"PC setup {g['setup_s'] * 1e3:.1f} ms once)")  # fmt: skip
            else:
                lines.append(f"  prdp_petsc + GAMG: {g.get('note')}")
        for name, note in t["notes"].items():
            lines.append(f"  {name}: {note}")
    for s in d["skipped"]:
        lines.append(f"skipped {s['what']}: {s['why']}")
    lines.append("targets:")
    for target, measured, met in verdicts(d):
        verdict = {True: "met", False: "NOT met", None: "-"}[met]
        lines.append(f"  {target}: {measured} [{verdict}]")
    return "\n".join(lines) + "\n"


def verdicts(d: dict) -> list[tuple[str, str, bool | None]]:
    """Each target of issue 36 against a `bench_gpu` result: (target, what was measured,
    met: True/False, or None where the run measured nothing to judge it by)."""
    cells, out = d["cells"], []
    if d["device"]["kind"] != "cuda":
        return [("the GPU targets", f"not judged: measured on {d['device']['name']}", None)]

    def worst(pair: str, keep=lambda c: True) -> tuple[str, float | None]:
        found = [(c["ratios"][pair]["median"], c) for c in cells if pair in c["ratios"] and keep(c)]
        if not found:
            return "not measured", None
        r, c = max(found, key=lambda rc: rc[0])
        return f"worst {r:.2f} ({c['problem']}, K = {c['k']})", r

    text, r = worst("prdp_petsc/raw_petsc")
    out.append(("bridge over raw petsc4py <= 1.15", text, None if r is None else r <= 1.15))
    for name in ("prdp_petsc", "prdp_petsc_sr"):
        for label, keep, bound in (
            ("12 k", lambda c: c["n"] < 59_000, 3.5),
            (">= 59 k", lambda c: c["n"] >= 59_000, 2.0),
            ("784 k", lambda c: c["n"] >= 700_000, 1.3),
        ):
            text, r = worst(f"{name}/jax_cg", keep)
            out.append((f"{name} / jax_cg <= {bound} at {label}", text,
                        None if r is None else r <= bound))  # fmt: skip
    diffs = [a for a in d["cpu_gpu_agreement"].values() if isinstance(a, dict) and "grad" in a]
    worst_diff = max((max(a["x"], a["grad"]) for a in diffs), default=None)
    out.append(("CPU and GPU paths agree to 1e-10 at K = 10",
                "not measured" if worst_diff is None else f"worst {worst_diff:.1e}",
                None if worst_diff is None else worst_diff <= 1e-10))  # fmt: skip
    for pname, t in d["time_to_tolerance"].items():
        gamg = t.get("gamg") or {}
        peers = {n: r["median_s"] for n, r in t["contenders"].items()
                 if r and n in ("jax_cg", "lineax_cg", "torch_pcg")}  # fmt: skip
        if gamg.get("k") is None or not peers:
            out.append((f"GAMG first to {t['tol']:g} on {pname}", "not measured", None))
            continue
        fastest = min(peers, key=peers.get)
        total = gamg["median_s"] + gamg["setup_s"]
        text = (f"GAMG {gamg['median_s'] * 1e3:.1f} ms per call (+ {gamg['setup_s'] * 1e3:.0f} "
                f"ms setup once) against {fastest} {peers[fastest] * 1e3:.1f} ms")  # fmt: skip
        out.append(
            (f"GAMG first to {t['tol']:g} on {pname}", text, gamg["median_s"] < peers[fastest])
        )
        label = f"GAMG first to {t['tol']:g} on {pname}, its setup counted"
        out.append((label, f"{total * 1e3:.1f} ms", total < peers[fastest]))
    return out


def _ms(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    ms = seconds * 1e3
    return f"{ms:.3g}" if ms < 100 else f"{ms:.0f}"


def _names(text: str) -> tuple[str, ...]:
    return tuple(name for name in text.split(",") if name)


def _problems(text: str) -> tuple[str, ...]:
    names = _names(text)
    for name in names:
        problem(name)  # raises ArgumentTypeError for an unknown name
    return names


def _ks(text: str) -> tuple[int, ...]:
    from ..cli.arguments import positive

    return tuple(positive(k) for k in _names(text))


def _contenders(text: str) -> tuple[str, ...]:
    names = _names(text)
    known = [c.name for c in CONTENDERS]
    if unknown := [n for n in names if n not in known]:
        raise argparse.ArgumentTypeError(f"unknown contender(s) {unknown}; known: {known}")
    return names


def _parser() -> argparse.ArgumentParser:
    from ..cli.arguments import add_debug, add_size_preset, positive

    p = argparse.ArgumentParser(prog="prdp-petsc bench gpu", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for bench_gpu.json")
    p.add_argument(
        "--problems",
        type=_problems,
        default=DEFAULT_PROBLEMS,
        help="lshape<r>,heat3d<m>,... (default lshape6,heat3d41,lshape8,lshape9)",
    )
    p.add_argument("--k", type=_ks, default=DEFAULT_K, help="CG iterations K (10,100,300)")
    p.add_argument("--rounds", type=positive, default=5, help="paired rounds per cell (5)")
    p.add_argument("--calls", type=positive, default=5, help="timed calls per round (5)")
    p.add_argument("--warmup", type=int, default=2, help="untimed calls after set-up (2)")
    p.add_argument("--tol", type=float, default=1e-6, help="gradient tolerance (1e-6)")
    p.add_argument(
        "--tol-problems",
        type=_names,
        default=("lshape8", "lshape9"),
        help="problems timed to --tol (default lshape8,lshape9; '' for none)",
    )
    p.add_argument("--tol-calls", type=positive, default=2, help="timed calls at that K (2)")
    p.add_argument(
        "--direct-max-n",
        type=positive,
        default=60_000,
        help="largest n whose reference is spsolve, else a tight CG (60000)",
    )
    p.add_argument("--k-max", type=positive, default=20_000, help="largest K searched (20000)")
    p.add_argument("--device", choices=("auto", "cuda", "cpu"), default="auto")
    p.add_argument("--skip", type=_contenders, default=(), help="contenders to leave out")
    p.add_argument("--jax-matrix", choices=("bcoo", "bcsr"), default="bcoo",
                   help="jax's sparse format of A (bcoo)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="seed of b and x_ref (0)")
    p.add_argument("--threads", type=positive, default=1, help="torch CPU threads (1)")
    p.add_argument(
        "--budget-s",
        type=float,
        default=420.0,
        help="start no step after this many seconds (420; 0: no limit)",
    )
    add_size_preset(p, "lshape3 and heat3d5, K = 2, 5, 2 rounds of 2 calls (a smoke test)")
    add_debug(p)  # fmt: skip
    return p


def main(argv: list[str]) -> int:
    """Run ``bench gpu``; write ``<out>/bench_gpu.json``; return an exit code."""
    args = _parser().parse_args(argv)
    if args.preset == "quick":
        args.problems, args.k, args.rounds, args.calls, args.warmup = (
            ("lshape3", "heat3d5"),
            (2, 5),
            2,
            2,
            1,
        )
        args.tol_problems, args.tol_calls = ("lshape3",), 2
    # jax takes 75 % of the GPU's memory at its first array unless told not to
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    import torch

    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    env = environment(args.device)
    budget = Budget(args.budget_s or None)
    result = {
        "benchmark": "gpu",
        **bench_gpu(args, env, budget),
        "targets": TARGETS,
        "settings": {
            "problems": list(args.problems),
            "k": list(args.k),
            "rounds": args.rounds,
            "calls": args.calls,
            "warmup": args.warmup,
            "tol": args.tol,
            "tol_problems": list(args.tol_problems),
            "direct_max_n": args.direct_max_n,
            "k_max": args.k_max,
            "budget_s": args.budget_s,
            "seed": args.seed,
            "jax_matrix": args.jax_matrix,
            "torch_threads": args.threads,
            "preset": args.preset,
            "dtype": "float64 (jax_enable_x64)",
            "ksp": "cg + jacobi, rtol = atol = 0 (exactly K iterations), x0 = 0",
            "loss": "0.5 * ||x_K(b) - x_ref||^2, gradient in b",
            "clock": "time.perf_counter around a call that ends with torch.cuda.synchronize "
            "or block_until_ready",
            "statistic": "per round: median of `calls` fwd+bwd calls per contender; ratio "
            "within each round; median (IQR/median as noise) over rounds",
        },
        "provenance": provenance(torch.get_num_threads(), 1),
        "machine": machine(),
        "versions": versions("jax", "jaxlib", "lineax", "equinox", "cupy", "jax-cuda13-plugin"),
        "wall_s": time.perf_counter() - t0,
    }
    write_result(args.out, "bench_gpu.json", result)
    print(format_report(result), end="")
    return 0


def _headline(ds: DataSet) -> list[tuple[str, str]]:
    """The index's rows: the bridge over raw petsc4py, prdp_petsc over jax's CG."""
    judged = {target: measured for target, measured, _ in verdicts(ds.main)}
    if "the GPU targets" in judged:
        return [
            ("prdp_petsc against jax, lineax and torch CG on one GPU", judged["the GPU targets"])
        ]
    rows = ("bridge over raw petsc4py <= 1.15", "prdp_petsc / jax_cg <= 2.0 at >= 59 k")
    return [(f"GPU, fwd + bwd of capped Jacobi CG: {row}", judged[row]) for row in rows]


def _verdict_table(ds: DataSet) -> list[str]:
    rows = [(target, measured, {True: "met", False: "**not met**", None: "not judged"}[met])
            for target, measured, met in verdicts(ds.main)]  # fmt: skip
    return ["Each target of issue 36, read from this run:",
            markdown_table(("target", "measured", "verdict"), rows)]  # fmt: skip


KIND = ReportKind(
    name="bench-gpu",
    reads="bench_gpu.json",
    title=lambda ds: "Capped CG gradients on one GPU: prdp_petsc against jax, lineax and torch",
    headline=_headline,
    intro="What `prdp-petsc bench gpu` printed: the gradient in b of ½‖x_K(b) − x_ref‖², K "
    "capped Jacobi-CG iterations forward and K on the adjoint, every contender in one process "
    "on one device, paired rounds; the time to a gradient within 1e-6 of the direct one with "
    "Jacobi CG and with GAMG. Exactly what each contender runs is in the docstring of "
    "`prdp_petsc.lab.reports.bench_gpu`.",
    output=lambda ds: format_report(ds.main).rstrip("\n"),
    after=_verdict_table,
)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    sys.exit(main(sys.argv[1:]))
