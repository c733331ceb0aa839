"""The solver's K-step iteration written in torch, for unrolled gradients.

Autograd through these loops gives the exact derivative of the truncated
solver (the baseline a user would otherwise write by hand).  Supported, read
from the `KSPSolver`'s PETSc configuration so that the iteration is the same one
PETSc runs:

* ``richardson`` with ``jacobi`` or ``none``: ``x ← x + ω M⁻¹(b − A x)``, ω from
  ``-ksp_richardson_scale`` (default 1), step for step as ``KSPSolve_Richardson``;
* ``cg`` with ``jacobi`` or ``none``: preconditioned conjugate gradients, step
  for step as ``KSPSolve_CG``.

Both start from x = 0, run at most ``solver.max_it`` iterations and stop where
PETSc would (`prdp_petsc.autograd.convergence`: the KSP's rtol, atol, divtol and
norm type), so in fixed mode (``rtol = atol = 0``) exactly K run and the
iterates equal PETSc's.  θ of shape (B, p) runs B operators at once, one per
column.  Memory grows linearly with K (every iterate is kept for backward).

Failures are those of implicit mode: CG on an operator known to be non-symmetric
raises `prdp_petsc.errors.StructureError` (unless ``check_structure=False``), a NaN
or Inf cotangent `prdp_petsc.errors.NonFiniteError`; a divergence PETSc reports
(``DIVERGED_DTOL``, ``DIVERGED_NANORINF``, CG's ``DIVERGED_INDEFINITE_PC``/``_MAT``)
raises `SolverError` with the same reason name and, in its message, the failing
column's iterations and residual norm; a solve that returns reports every column's
iterations, reason and residual norm as implicit mode does (`LinearSolution.info`).
Right-hand sides beyond ``2^±100`` are scaled by a power of two
first, as `KSPSolver` does.  Not repeated from implicit mode: the rescue of
breakdowns at rounding level (`prdp_petsc.core.safeguards`); for the supported
methods with a positive diagonal, zᵀr is a sum of non-negative terms and those
breakdowns do not arise.

Statistics: the forward counts ``forward_solves``/``forward_iterations``/
``forward_time``.  The adjoint counters are advanced only when a backward pass
actually runs through the result (by one solve and the column's iterations per
column, each time it runs); ``adjoint_time`` is not recorded, the backward
being torch's.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from petsc4py import PETSc

from ..core import safeguards
from ..core.results import SolverError
from ..core.solution import LinearSolution
from ..core.solver import KSPSolver
from ..core.sparsity import csr_symmetric
from ..core.structure import check_structure, symmetric_only
from ..errors import InputError
from ..fem.parametric import ParametricMatrix
from .convergence import Convergence, Reason
from .tensors import check_finite
from .unrolled_operator import UnrolledOperator

__all__ = ["UnrolledOperator", "method_of", "unrolled_solve"]

_SUPPORTED = {("richardson", "jacobi"), ("richardson", "none"), ("cg", "jacobi"), ("cg", "none")}


def method_of(solver: KSPSolver) -> tuple[str, str, float]:
    """(ksp_type, pc_type, richardson_scale) of the solver's forward KSP."""
    ksp = solver.ksp
    scale = PETSc.Options().getReal(
        solver.prefix + "ksp_richardson_scale",
        float(solver.options.get("ksp_richardson_scale", 1.0)),
    )
    return ksp.getType(), ksp.getPC().getType(), scale


def unrolled_solve(A, b: torch.Tensor, solver: KSPSolver, *, theta=None) -> LinearSolution:
    """K steps of the solver's method in torch; differentiable in b and θ.

    Returns
    -------
    LinearSolution
        x as ``.value`` (a tensor) with every sample's outcome; ``.adjoint`` stays
        None (the backward is torch's, no transpose solve).

    Raises
    ------
    SolverError
        When PETSc would report a divergence (same reason name as implicit mode).
    """
    if solver.structure.nullspace is not None:
        raise InputError(
            "mode='unrolled' does not project null spaces as PETSc does; use mode='implicit' "
            "for a solver with a nullspace"
        )
    ksp_type, pc_type, scale = method_of(solver)
    if (ksp_type, pc_type) not in _SUPPORTED:
        raise InputError(
            f"mode='unrolled' supports {sorted(_SUPPORTED)}, the solver is "
            f"{ksp_type}/{pc_type}; use mode='implicit' for other KSP/PC pairs"
        )
    if solver.check_structure and symmetric_only(solver.ksp):  # CG: A must be symmetric
        check_structure(solver.ksp, _symmetric(A), "unrolled forward")
    t0 = time.perf_counter()
    n = b.shape[-1]
    exponents = safeguards.rhs_exponents(b.detach().cpu().reshape(-1, n).numpy())
    B = _ldexp(b.cpu().reshape(-1, n).T, -exponents)  # (n, batch): columns are samples
    A_t = UnrolledOperator(A, theta)
    inv_m = _jacobi(A_t) if pc_type == "jacobi" else None
    conv = Convergence(solver.ksp, exponents)
    if ksp_type == "richardson":
        x = _richardson(A_t, B, inv_m, scale, solver.max_it, conv)
    else:
        x = _cg(A_t, B, inv_m, solver.max_it, conv)
    conv.check(f"{ksp_type}/{pc_type}")
    x = _ldexp(x, exponents)
    if not bool(torch.isfinite(x).all()):  # e.g. -ksp_norm_type none: PETSc tests nothing
        raise SolverError(
            f"unrolled forward solve ({ksp_type}/{pc_type}) returned NaN/Inf",
            reason="DIVERGED_NANORINF",
        )
    its = int(conv.iterations.sum())
    stats = solver.stats
    stats.forward_solves += B.shape[1]
    stats.forward_iterations += its
    stats.forward_time += time.perf_counter() - t0
    x = x.T.reshape(b.shape).to(b.device)
    # every sample's outcome, as implicit mode reports them (no adjoint solve will run)
    return LinearSolution(_AdjointCount.apply(x, solver, B.shape[1], its), conv.call_info())


def _symmetric(A) -> bool:
    """Whether the operator is symmetric: declared or tested (`ParametricMatrix`), or
    tested entry against mirror (a scipy matrix)."""
    if isinstance(A, ParametricMatrix):
        return A.is_symmetric
    A = A.tocsr()
    return csr_symmetric(A.indptr, A.indices, A.data, A.shape)


class _AdjointCount(torch.autograd.Function):
    """Identity on the unrolled solution whose backward records the adjoint work.

    The backward of the unrolled graph is the K transposed steps of every column;
    it is counted in ``solver.stats`` when it runs, not when the forward does.
    """

    @staticmethod
    def forward(ctx, x, solver, solves, iterations):
        ctx.solver, ctx.solves, ctx.iterations = solver, solves, iterations
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        check_finite(grad.detach().cpu().numpy(), "the cotangent of the unrolled solve")
        stats = ctx.solver.stats  # looked up now: reset_stats() may have replaced it
        stats.adjoint_solves += ctx.solves
        stats.adjoint_iterations += ctx.iterations
        return grad, None, None, None


def _ldexp(x: torch.Tensor, exponents: np.ndarray) -> torch.Tensor:
    """``x · 2^e`` per column, exactly (two factors, so that 2^e never overflows)."""
    if not exponents.any():
        return x
    half = exponents // 2
    for e in (half, exponents - half):
        x = x * torch.from_numpy(np.ldexp(1.0, e))
    return x


def _jacobi(op: UnrolledOperator) -> torch.Tensor:
    diag = op.diagonal()
    return 1.0 / torch.where(diag == 0, 1.0, diag)  # PCJacobi replaces a zero diagonal by 1


def _precondition(inv_m, r):
    return r if inv_m is None else inv_m * r


def _richardson(A_t, B, inv_m, scale, k, conv):
    """``x ← x + ω M⁻¹(b − A x)`` from x = 0, step for step as ``KSPSolve_Richardson``."""
    x = torch.zeros_like(B)
    r = B
    for i in range(k):
        z = _precondition(inv_m, r)
        conv.test(i, conv.residual_norm(r, z, None))
        active = conv.active
        if not active.any():
            return x
        x = x + scale * torch.where(active, z, 0.0)
        conv.count(i + 1)
        r = B - A_t @ x
    # PETSc tests the residual after the last step too
    conv.test(k, conv.residual_norm(r, _precondition(inv_m, r), None))
    none = conv.norm_type == PETSc.KSP.NormType.NONE
    conv.finish(Reason.CONVERGED_ITS if none else Reason.DIVERGED_MAX_IT)
    return x


def _cg(A_t, B, inv_m, k, conv):
    """Preconditioned CG from x = 0, step for step as ``KSPSolve_CG``.

    Besides the convergence test a column stops as PETSc's does: ``zᵀr = 0``
    (``CONVERGED_ATOL``), a sign change of ``zᵀr`` (``DIVERGED_INDEFINITE_PC``),
    ``pᵀAp = 0`` or a sign change of it (``DIVERGED_INDEFINITE_MAT``), a NaN or Inf
    inner product (``DIVERGED_NANORINF``).  Stopped columns are frozen with safe
    divisions, so their gradients stay finite.
    """
    x = torch.zeros_like(B)
    r = B
    z = _precondition(inv_m, r)
    rho = (r * z).sum(0)
    conv.test(0, conv.residual_norm(r, z, rho))
    conv.check_finite(rho)
    p = z
    rho_old = pq_old = None
    for i in range(k):
        if not conv.active.any():
            return x
        conv.count(i + 1)  # PETSc counts the iteration before its breakdown checks
        conv.stop(rho == 0, Reason.CONVERGED_ATOL)
        if i > 0:
            conv.stop(rho * rho_old < 0, Reason.DIVERGED_INDEFINITE_PC)
            p = z + _safe_ratio(rho, rho_old, conv.active) * p
        q = A_t @ p
        pq = (p * q).sum(0)
        conv.check_finite(pq)
        curvature_lost = pq == 0
        if i > 0:
            curvature_lost |= torch.sign(pq) * torch.sign(pq_old) < 0
        conv.stop(curvature_lost, Reason.DIVERGED_INDEFINITE_MAT)
        alpha = _safe_ratio(rho, pq, conv.active)
        x = x + alpha * p
        r = r - alpha * q
        z = _precondition(inv_m, r)
        rho_old, pq_old = rho, pq
        rho = (r * z).sum(0)
        conv.test(i + 1, conv.residual_norm(r, z, rho))
        conv.check_finite(rho)
    conv.finish(Reason.DIVERGED_MAX_IT)
    return x


def _safe_ratio(num, den, active):
    """``num / den`` on the active columns, 0 on the others (no division by their 0)."""
    return torch.where(active, num / torch.where(active, den, 1.0), 0.0)
