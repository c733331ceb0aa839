"""The solver's K-step iteration written in torch, for unrolled gradients.

Autograd through these loops gives the exact derivative of the truncated
solver (the baseline a user would otherwise write by hand).  Supported, read
from the `KSPSolver`'s PETSc configuration so that the iteration is the same one
PETSc runs:

* ``richardson`` with ``jacobi`` or ``none``: ``x ← x + ω M⁻¹(b − A x)``, ω from
  ``-ksp_richardson_scale`` (default 1);
* ``cg`` with ``jacobi`` or ``none``: preconditioned conjugate gradients.

Both start from x = 0 and run at most ``solver.max_it`` iterations, stopping
where PETSc's default convergence test would (the solver's rtol and atol, the
KSP's norm type), so in fixed mode (``rtol = atol = 0``) exactly K run and the
iterates equal PETSc's.  Memory grows linearly with K (every iterate is kept
for backward).
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import scipy.sparse as sp
import torch
from petsc4py import PETSc

from ..fem.parametric import ParametricMatrix
from ..core.solver import KSPSolver, SolveInfo

__all__ = ["UnrolledOperator", "unrolled_solve"]

_SUPPORTED = {("richardson", "jacobi"), ("richardson", "none"), ("cg", "jacobi"), ("cg", "none")}


def _csr_tensor(indptr, indices, values, shape) -> torch.Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(
            torch.from_numpy(np.asarray(indptr, dtype=np.int64)),
            torch.from_numpy(np.asarray(indices, dtype=np.int64)),
            values,
            size=shape,
            check_invariants=False,
        )


class UnrolledOperator:
    """A(θ) inside the unrolled loop: ``A @ X`` with a cheap, exact backward.

    The forward product uses a CSR tensor; backward uses the transpose, built once
    per solve, for ``∂/∂X`` and ``(gY[rows] · X[cols])`` for ``∂/∂values``, so
    no iteration differentiates through torch's sparse kernels.  ``values`` is
    ``a0 + G θ`` (differentiable in θ) or the constant CSR data.
    """

    def __init__(self, A, theta: torch.Tensor | None = None):
        if isinstance(A, ParametricMatrix):
            G = A.G.tocoo()
            G_t = torch.sparse_coo_tensor(
                np.vstack([G.row, G.col]), G.data, G.shape, check_invariants=False
            )
            self.values = torch.from_numpy(A.a0) + torch.sparse.mm(G_t, theta.cpu()[:, None])[:, 0]
            indptr, indices, shape = A.indptr, A.indices, A.shape
        else:
            A = sp.csr_matrix(A)
            A.sort_indices()
            self.values = torch.from_numpy(A.data.astype(np.float64))
            indptr, indices, shape = A.indptr, A.indices, A.shape
        nnz = len(indices)
        T = sp.csr_matrix((np.arange(nnz), indices, indptr), shape=shape).T.tocsr()
        self.shape = shape
        self.rows = torch.from_numpy(np.repeat(np.arange(shape[0]), np.diff(indptr)))
        self.cols = torch.from_numpy(np.asarray(indices, dtype=np.int64))
        v = self.values.detach()
        self.csr = _csr_tensor(indptr, indices, v, shape)
        self.csr_t = _csr_tensor(T.indptr, T.indices, v[torch.from_numpy(T.data)], shape[::-1])

    def __matmul__(self, X: torch.Tensor) -> torch.Tensor:
        return _SpMM.apply(self.values, X, self)

    def diagonal(self) -> torch.Tensor:
        """Diagonal of A (differentiable in the values)."""
        on_diag = self.rows == self.cols
        diag = torch.zeros(self.shape[0], dtype=self.values.dtype)
        return diag.index_add(0, self.rows[on_diag], self.values[on_diag])


class _SpMM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, X, op):
        ctx.op = op
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(X)
        return op.csr @ X

    @staticmethod
    def backward(ctx, gY):
        op = ctx.op
        g_values = g_X = None
        if ctx.needs_input_grad[0]:
            (X,) = ctx.saved_tensors
            g_values = (gY[op.rows] * X[op.cols]).sum(-1)
        if ctx.needs_input_grad[1]:
            g_X = op.csr_t @ gY
        return g_values, g_X, None


def _jacobi(op: UnrolledOperator) -> torch.Tensor:
    diag = op.diagonal()
    return 1.0 / torch.where(diag == 0, 1.0, diag)  # PCJacobi replaces a zero diagonal by 1


def method_of(solver: KSPSolver) -> tuple[str, str, float]:
    """(ksp_type, pc_type, richardson_scale) of the solver's forward KSP."""
    ksp = solver.ksp
    scale = PETSc.Options().getReal(
        solver.prefix + "ksp_richardson_scale",
        float(solver.options.get("ksp_richardson_scale", 1.0)),
    )
    return ksp.getType(), ksp.getPC().getType(), scale


def unrolled_solve(A, b: torch.Tensor, solver: KSPSolver, *, theta=None) -> torch.Tensor:
    """K steps of the solver's method in torch; differentiable in b and θ."""
    if solver.nullspace is not None:
        raise ValueError(
            "mode='unrolled' does not project null spaces as PETSc does; use mode='implicit' "
            "for a solver with a nullspace"
        )
    solver.setup()  # the configured KSP/PC types are read back from PETSc
    ksp_type, pc_type, scale = method_of(solver)
    if (ksp_type, pc_type) not in _SUPPORTED:
        raise ValueError(
            f"mode='unrolled' supports {sorted(_SUPPORTED)}, the solver is "
            f"{ksp_type}/{pc_type}; use mode='implicit' for other KSP/PC pairs"
        )
    t0 = time.perf_counter()
    A_t = UnrolledOperator(A, theta)
    inv_m = _jacobi(A_t) if pc_type == "jacobi" else None
    B = b.cpu().reshape(-1, b.shape[-1]).T  # (n, batch): columns are right-hand sides
    stop = _Stopping(solver)
    if ksp_type == "richardson":
        x = _richardson(A_t, B, inv_m, scale, solver.max_it, stop)
    else:
        x = _cg(A_t, B, inv_m, solver.max_it, stop)
    its = int(stop.iterations.sum())
    solver.last = stop.info()
    stats = solver.stats
    stats.forward_solves += B.shape[1]
    stats.forward_iterations += its
    stats.forward_time += time.perf_counter() - t0
    if torch.is_grad_enabled() and (b.requires_grad or (theta is not None and theta.requires_grad)):
        stats.adjoint_solves += B.shape[1]
        stats.adjoint_iterations += its
    return x.T.reshape(b.shape).to(b.device)


class _Stopping:
    """PETSc's default convergence test (``KSPConvergedDefault``), one flag per column.

    A column stops when its residual norm (of the KSP's norm type) falls to
    ``max(rtol * ‖r₀‖, atol)``; with ``rtol = atol = 0`` only an exactly zero
    residual stops it, as in PETSc.  Norms are compared, never differentiated.
    """

    def __init__(self, solver: KSPSolver):
        norm_type = solver.ksp.getNormType()
        self.norm_type = "none" if norm_type == PETSc.KSP.NormType.NONE else norm_type
        self.rtol, self.atol = solver.rtol, solver.atol
        self.ttol = None
        self.active = None
        self.iterations = None
        self.norm = None
        self.by_atol = None

    def norm_of(self, r, z, rz) -> torch.Tensor:
        with torch.no_grad():
            if self.norm_type == PETSc.KSP.NormType.UNPRECONDITIONED:
                return torch.linalg.vector_norm(r, dim=0)
            if self.norm_type == PETSc.KSP.NormType.NATURAL:
                return rz.abs().sqrt()
            return torch.linalg.vector_norm(z, dim=0)  # preconditioned (PETSc's default)

    def check(self, r, z, rz) -> torch.Tensor:
        """Update and return the mask of columns still iterating."""
        if self.active is None:
            self.active = torch.ones(r.shape[1], dtype=torch.bool)
            self.iterations = torch.zeros(r.shape[1], dtype=torch.int64)
            self.by_atol = torch.zeros(r.shape[1], dtype=torch.bool)
        if self.norm_type == "none":
            return self.active
        norm = self.norm_of(r, z, rz)
        if self.ttol is None:
            self.ttol = torch.clamp(self.rtol * norm, min=self.atol)
        self.norm = norm
        done = self.active & (norm <= self.ttol)
        self.by_atol |= done & (norm < self.atol)
        self.active = self.active & ~done
        return self.active

    def info(self) -> SolveInfo:
        """`SolveInfo` of the last column, as PETSc reports it."""
        last = -1
        converged = not bool(self.active[last])
        norm = float("nan") if self.norm is None else float(self.norm[last])
        reason = "DIVERGED_MAX_IT"
        if converged:
            reason = "CONVERGED_ATOL" if bool(self.by_atol[last]) else "CONVERGED_RTOL"
        return SolveInfo(int(self.iterations[last]), reason, norm)


def _precondition(inv_m, r):
    return r if inv_m is None else inv_m[:, None] * r


def _richardson(A_t, B, inv_m, scale, k, stop):
    """``x ← x + ω M⁻¹(b − A x)`` from x = 0, as ``KSPSolve_Richardson``."""
    x = torch.zeros_like(B)
    r = B
    for _ in range(k):
        z = _precondition(inv_m, r)
        active = stop.check(r, z, None)
        if not active.any():
            break
        x = x + scale * torch.where(active, z, 0.0)
        stop.iterations += active
        r = B - A_t @ x
    else:  # PETSc tests the residual after the last step too
        stop.check(r, _precondition(inv_m, r), None)
    return x


def _cg(A_t, B, inv_m, k, stop):
    """Preconditioned CG from x = 0, step for step as ``KSPSolve_CG``.

    A column stops on PETSc's convergence test or when ``zᵀr`` or ``pᵀAp`` is
    exactly zero (PETSc: converged, or breakdown); stopped columns are frozen
    with safe divisions, so their gradients stay finite.
    """
    x = torch.zeros_like(B)
    r = B
    z = _precondition(inv_m, r)
    rho = (r * z).sum(0)
    active = stop.check(r, z, rho)
    p = z
    for _ in range(k):
        active = active & (rho != 0)
        if not active.any():
            break
        q = A_t @ p
        pq = (p * q).sum(0)
        active = active & (pq != 0)
        alpha = torch.where(active, rho / torch.where(active, pq, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * q
        z = _precondition(inv_m, r)
        stop.iterations += active
        rho_new = (r * z).sum(0)
        active = active & stop.check(r, z, rho_new)
        beta = torch.where(active, rho_new / torch.where(active, rho, 1.0), 0.0)
        p = z + beta * p
        rho = rho_new
    return x
