"""The contenders of ``prdp-petsc bench gpu`` (`prdp_petsc.lab.reports.bench_gpu`): its
problems, and one capped Jacobi-CG gradient in b (K iterations forward from x = 0, the
cotangent ``x − x_ref``, K iterations on the adjoint) as each implementation runs it:
prdp_petsc's bridge, raw petsc4py on DLPack Vecs, jax's and lineax's CG under
``jax.grad``, and a hand-written torch PCG.  Each `Contender` builds a `Run` for one
(problem, K) on the device of the `Case`; what a contender needs that a machine lacks
(`Contender.needs`) is for the benchmark to say.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, partial
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import skfem
import torch

import prdp_petsc as pp
from prdp_petsc.core.operator import DLPackCSR

from ..components.emulators import torch_csr
from .problems import five_point

__all__ = [
    "CONTENDERS",
    "GAMG",
    "PAIRS",
    "PROBLEMS",
    "Case",
    "Contender",
    "Run",
    "heat_step",
    "lshape",
    "pcg",
    "problem",
]


# -- problems ------------------------------------------------------------------------------
def lshape(refine: int, jitter: float = 0.15, seed: int = 0) -> sp.csr_matrix:
    """P1 ``−Δu`` on the `refine` times refined L-shape, its interior vertices jittered
    by up to `jitter` of the shortest edge (r = 6, 8, 9: 12 033, 195 585, 784 385 unknowns)."""
    mesh = skfem.MeshTri.init_lshaped().refined(refine)
    h = np.linalg.norm(np.diff(mesh.p[:, mesh.facets], axis=1), axis=0).min()
    p, inner = mesh.p.copy(), mesh.interior_nodes()
    p[:, inner] += np.random.default_rng(seed).uniform(-jitter * h, jitter * h, (2, inner.size))
    jittered = skfem.MeshTri(p, mesh.t)
    if np.any(_areas(jittered) * _areas(mesh) <= 0):
        raise RuntimeError(f"lshape{refine}: the jitter folded a triangle")
    return _interior(skfem.Basis(jittered, skfem.ElementTriP1()))


def heat_step(axis: int, dt: float = 0.01) -> sp.csr_matrix:
    """One implicit heat step ``M + dt K`` (P1) on `axis`³ points of the unit cube."""
    line = np.linspace(0.0, 1.0, axis)
    mesh = skfem.MeshTet.init_tensor(line, line, line)
    return _interior(skfem.Basis(mesh, skfem.ElementTetP1()), dt)


def _areas(mesh) -> np.ndarray:
    d1, d2 = (mesh.p[:, mesh.t[i]] - mesh.p[:, mesh.t[0]] for i in (1, 2))
    return d1[0] * d2[1] - d1[1] * d2[0]


def _interior(basis, dt: float | None = None) -> sp.csr_matrix:
    """``K`` (κ = 1), or ``M + dt K``, on the dofs of `basis` off the boundary."""
    stiffness = pp.diffusion_operator(basis)
    A = stiffness.matrix(np.ones(stiffness.n_params))
    if dt is not None:
        A = pp.mass_matrix(basis) + dt * A
    keep = basis.complement_dofs(basis.mesh.boundary_nodes())
    A = sp.csr_matrix(A)[keep][:, keep]
    A.sort_indices()
    return A


#: a ``--problems`` name's stem -> (its label in the tables, its matrix of a size)
PROBLEMS = {
    "lshape": ("L-shape P1", lshape),
    "heat3d": ("3D heat step P1", heat_step),
    "five_point": ("5-point -Δ", lambda side: five_point(side)[0]),  # bench jax's
}


def problem(name: str) -> tuple[str, Callable[[], sp.csr_matrix]]:
    """The label and the matrix builder a ``--problems`` name stands for."""
    m = re.fullmatch(r"(lshape|heat3d|five_point)(\d+)", name)
    if m is None or (m[1] == "heat3d" and int(m[2]) < 3):
        raise argparse.ArgumentTypeError(
            f"unknown problem {name!r}: lshape<refinements> (lshape6: 12 033 unknowns), "
            "heat3d<points per axis> (heat3d41: 59 319) or five_point<side> (five_point110: "
            "12 100)"
        )
    label, matrix = PROBLEMS[m[1]]
    return label, partial(matrix, int(m[2]))


# -- one problem's data, one contender's run ----------------------------------------------
@dataclass(eq=False)
class Case:
    """One problem's matrix, b and x_ref, the torch device of the run and their copies there."""

    name: str
    A: sp.csr_matrix
    b: np.ndarray
    x_ref: np.ndarray
    device: str = "cpu"  # or "cuda"
    jax_matrix: str = "bcoo"  # jax's sparse format: "bcoo" or "bcsr"

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @cached_property
    def on_device(self) -> tuple:
        """(A as a torch sparse CSR tensor, 1/diag(A), b, x_ref) on the device."""
        A = torch_csr(self.A)
        inv_diag = _tensor(1.0 / self.A.diagonal(), self.device)
        return A.to(self.device), inv_diag, *self.tensors(self.device)

    def tensors(self, device: str) -> tuple:
        """b and x_ref as torch tensors on `device`."""
        return _tensor(self.b, device), _tensor(self.x_ref, device)

    def release(self) -> None:
        """Drop the device copies (the next problem's need the memory)."""
        self.__dict__.pop("on_device", None)
        if self.device == "cuda":
            torch.cuda.empty_cache()


def _tensor(array: np.ndarray, device: str) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(array), dtype=torch.float64).to(device)


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


class Run(NamedTuple):
    """One contender built for one (problem, K): `call` runs fwd + bwd (synchronised),
    `result` gives (x, gradient) on the host after a call, `info` what ran; `set_k`
    moves K without building again."""

    call: Callable[[], None]
    result: Callable[[], tuple[np.ndarray, np.ndarray]]
    info: Callable[[], dict]
    set_k: Callable[[int], None] | None = None


class Contender(NamedTuple):
    """One implementation of fwd + bwd, ``build(name, case, k) -> Run``, and what it needs
    (``petsc``: PETSc with CUDA on a GPU, ``jax``, ``lineax``; `environment` says where)."""

    name: str
    describe: str
    build: Callable[..., Run]
    needs: str | None = None

    def start(self, case: Case, k: int, **kwargs) -> Run:
        """Build for `case` at K and call once (set-up, compilation)."""
        run = self.build(self.name, case, k, **kwargs)
        run.call()
        return run


# -- contenders ----------------------------------------------------------------------------
def _prdp_petsc(name, case, k, *, pc_type="jacobi", single_reduction=False, on=None) -> Run:
    device = on or case.device
    options = {"ksp_type": "cg", "pc_type": pc_type}
    if device == "cuda":
        options.update(vec_type="cuda", mat_type="aijcusparse")
    if single_reduction:
        options["ksp_cg_single_reduction"] = True
    solver = pp.KSPSolver(options, prefix=f"{name}_", max_it=k)
    b, x_ref = case.tensors(device)
    b.requires_grad_(True)
    A = case.A
    if device == "cuda":  # a constant operator already on the GPU: no per-call comparison
        values = torch.as_tensor(A.data, device=device)
        A = DLPackCSR(A.indptr, A.indices, values, A.shape)
    out = {}

    def call():
        b.grad = None
        out["x"] = pp.solve(A, b, solver)
        (0.5 * torch.sum((out["x"] - x_ref) ** 2)).backward()
        _sync(device)

    def info():
        ksp, stats = solver.ksp, solver.stats
        mat = ksp.getOperators()[0]
        return {
            "options": options,
            "ksp": [ksp.getType(), ksp.getPC().getType()],
            "mat_type": mat.getType() if mat.handle else None,
            "forward_iterations_per_solve": stats.forward_iterations / max(stats.forward_solves, 1),
            "adjoint_iterations_per_solve": stats.adjoint_iterations / max(stats.adjoint_solves, 1),
            "pc_setups": stats.pc_setups,
        }

    def set_k(new_k):
        solver.max_it = new_k

    return Run(call, lambda: (out["x"].detach().cpu().numpy(), b.grad.cpu().numpy()), info, set_k)


def _raw_petsc(name, case, k, *, single_reduction=False, transpose=False) -> Run:
    from petsc4py import PETSc

    mat = PETSc.Mat().create(comm=PETSc.COMM_SELF)
    mat.setSizes(case.A.shape)
    mat.setType("aijcusparse" if case.device == "cuda" else "aij")
    indptr, indices = (a.astype(PETSc.IntType) for a in (case.A.indptr, case.A.indices))
    mat.setPreallocationCSR((indptr, indices, case.A.data))
    mat.assemble()
    mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    PETSc.Options()[f"{name}_ksp_cg_single_reduction"] = single_reduction
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setOptionsPrefix(f"{name}_")
    ksp.setType("cg")
    ksp.getPC().setType("jacobi")
    ksp.setOperators(mat)
    ksp.setTolerances(rtol=0.0, atol=0.0, max_it=k)
    ksp.setFromOptions()
    ksp.setUp()
    _, _, b, x_ref = case.on_device
    x, g, lam = (torch.zeros_like(b) for _ in range(3))
    vecs = [PETSc.Vec().createWithDLPack(t, comm=PETSc.COMM_SELF) for t in (b, x, g, lam)]
    for v in vecs:
        v.stateIncrease()  # a fresh Vec's state 0 would read PETSc's norm cache as 0
    vb, vx, vg, vlam = vecs
    adjoint = ksp.solveTranspose if transpose else ksp.solve
    iterations = set()

    def call():
        ksp.solve(vb, vx)
        iterations.add(ksp.getIterationNumber())
        torch.sub(x, x_ref, out=g)
        vg.stateIncrease()  # torch wrote g behind PETSc's back
        adjoint(vg, vlam)
        iterations.add(ksp.getIterationNumber())
        _sync(case.device)

    def info():
        return {
            "ksp": [ksp.getType(), ksp.getPC().getType()],
            "mat_type": mat.getType(),
            "vec_type": vb.getType(),
            "single_reduction": single_reduction,
            "iterations_per_solve": sorted(iterations),
        }

    return Run(call, lambda: (x.cpu().numpy(), lam.cpu().numpy()), info)


def _jax_cg(name, case, k, *, lineax=False) -> Run:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from jax.experimental import sparse

    A = getattr(sparse, case.jax_matrix.upper()).from_scipy_sparse(case.A)
    inv_diag, b, x_ref = (jnp.asarray(a) for a in (1.0 / case.A.diagonal(), case.b, case.x_ref))
    # the matrix is an argument, not a closure: a constant of 10⁶ entries baked into the
    # compiled program would slow its compilation down
    if lineax:
        import lineax as lx

        tags = (lx.symmetric_tag, lx.positive_semidefinite_tag)
        cg, shape = lx.CG(rtol=0.0, atol=0.0, max_steps=k), jax.ShapeDtypeStruct(b.shape, b.dtype)

        def solve(b, A, inv_diag):
            op = lx.FunctionLinearOperator(lambda x: A @ x, shape, tags=tags)
            precond = lx.TaggedLinearOperator(lx.DiagonalLinearOperator(inv_diag), tags)
            options = {"preconditioner": precond}
            return lx.linear_solve(op, b, cg, options=options, throw=False).value
    else:

        def solve(b, A, inv_diag):
            M = lambda r: inv_diag * r  # noqa: E731
            cg = jax.scipy.sparse.linalg.cg
            return cg(lambda x: A @ x, b, tol=0.0, atol=0.0, maxiter=k, M=M)[0]

    def loss(b, A, inv_diag, x_ref):
        x = solve(b, A, inv_diag)
        return 0.5 * jnp.sum((x - x_ref) ** 2), x

    grad = jax.jit(jax.grad(loss, has_aux=True))
    out = {}

    def call():
        out["g"], out["x"] = jax.block_until_ready(grad(b, A, inv_diag, x_ref))

    def info():
        return {"device": str(next(iter(b.devices()))), "matvec": f"{case.jax_matrix.upper()} @ x"}

    return Run(call, lambda: (np.asarray(out["x"]), np.asarray(out["g"])), info)


def _torch_pcg(name, case, k) -> Run:
    A, inv_diag, b, x_ref = case.on_device
    out = {}

    def call():
        out["x"] = pcg(A, inv_diag, b, k)
        out["g"] = pcg(A, inv_diag, out["x"] - x_ref, k)
        _sync(case.device)

    result = lambda: (out["x"].cpu().numpy(), out["g"].cpu().numpy())  # noqa: E731
    return Run(call, result, lambda: {"matvec": "torch sparse CSR @ x"})


def pcg(A, inv_diag, rhs, k: int, *, rtol: float | None = None, every: int = 100):
    """K iterations of Jacobi-preconditioned CG from zero, scalars kept on the device.
    With `rtol`, stop once ``‖r‖ ≤ rtol ‖rhs‖``, read on the host every `every` iterations."""
    x, r = torch.zeros_like(rhs), rhs.clone()
    z = inv_diag * r
    p, rz = z.clone(), torch.dot(r, z)
    stop = None if rtol is None else rtol * float(torch.linalg.vector_norm(rhs))
    for i in range(1, k + 1):
        q = A @ p
        alpha = rz / torch.dot(p, q)
        x.add_(alpha * p)
        r.sub_(alpha * q)
        torch.mul(inv_diag, r, out=z)
        rz_new = torch.dot(r, z)
        p.mul_(rz_new / rz).add_(z)
        rz = rz_new
        if stop is not None and i % every == 0 and torch.linalg.vector_norm(r) <= stop:
            break
    return x


_PRDP = "pp.solve + backward, cg/{} (on the GPU with vec_type cuda, mat_type aijcusparse)"
_RAW = "petsc4py KSPSolve + {} on DLPack Vecs, cg/jacobi"
_SR = ", ksp_cg_single_reduction"
_JAX = "jax.jit(jax.grad) of {}"
_SINGLE = {"single_reduction": True}
#: Every contender, in the order the tables list them.
# fmt: off
CONTENDERS = (
    Contender("prdp_petsc", _PRDP.format("jacobi"), _prdp_petsc, "petsc"),
    Contender("prdp_petsc_sr", _PRDP.format("jacobi" + _SR), partial(_prdp_petsc, **_SINGLE),
              "petsc"),
    Contender("raw_petsc", _RAW.format("KSPSolve"), _raw_petsc, "petsc"),
    Contender("raw_petsc_sr", _RAW.format("KSPSolve") + _SR, partial(_raw_petsc, **_SINGLE),
              "petsc"),
    Contender("raw_petsc_transpose", _RAW.format("KSPSolveTranspose"),
              partial(_raw_petsc, transpose=True), "petsc"),
    Contender("jax_cg", _JAX.format("jax.scipy.sparse.linalg.cg(M = 1/diag), sparse matvec"),
              _jax_cg, "jax"),
    Contender("lineax_cg", _JAX.format("lineax.linear_solve(lx.CG, diagonal preconditioner)"),
              partial(_jax_cg, lineax=True), "lineax"),
    Contender("torch_pcg", "hand-written torch Jacobi PCG (sparse CSR matvec); gradient: a "
              "second PCG on x - x_ref (implicit, A SPD), no autograd through the iterations",
              _torch_pcg),
)
GAMG = Contender("prdp_petsc_gamg", _PRDP.format("gamg"), partial(_prdp_petsc, pc_type="gamg"),
                 "petsc")
#: (numerator, denominator) of the ratios reported per cell, besides ``c / jax_cg``
PAIRS = (("prdp_petsc", "raw_petsc"), ("prdp_petsc_sr", "raw_petsc_sr"),
         ("prdp_petsc", "raw_petsc_transpose"))
# fmt: on
