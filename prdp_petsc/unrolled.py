"""The solver's K-step iteration written in torch, for unrolled gradients.

Autograd through these loops gives the exact derivative of the truncated
solver (the baseline a user would otherwise write by hand).  Supported, read
from the `KSPSolver`'s PETSc configuration so that the iteration is the same one
PETSc runs:

* ``richardson`` with ``jacobi`` or ``none``: ``x ← x + ω M⁻¹(b − A x)``, ω from
  ``-ksp_richardson_scale`` (default 1);
* ``cg`` with ``jacobi`` or ``none``: preconditioned conjugate gradients.

Both start from x = 0 and run exactly ``solver.max_it`` iterations.  Memory
grows linearly with K (every iterate is kept for backward).
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import scipy.sparse as sp
import torch
from petsc4py import PETSc

from .parametric import ParametricMatrix
from .solver import KSPSolver

__all__ = ["torch_csr", "unrolled_solve"]

_SUPPORTED = {("richardson", "jacobi"), ("richardson", "none"), ("cg", "jacobi"), ("cg", "none")}


def torch_csr(A, theta: torch.Tensor | None = None) -> torch.Tensor:
    """A (or A(θ), differentiable in θ) as a torch sparse CSR float64 tensor."""
    if isinstance(A, ParametricMatrix):
        G = A.G.tocoo()
        G_t = torch.sparse_coo_tensor(
            np.vstack([G.row, G.col]), G.data, G.shape, check_invariants=False
        )
        values = torch.from_numpy(A.a0) + torch.sparse.mm(G_t, theta.cpu()[:, None])[:, 0]
        indptr, indices, shape = A.indptr, A.indices, A.shape
    else:
        A = sp.csr_matrix(A)
        A.sort_indices()
        values = torch.from_numpy(A.data.astype(np.float64))
        indptr, indices, shape = A.indptr, A.indices, A.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(
            torch.from_numpy(indptr.astype(np.int64)),
            torch.from_numpy(indices.astype(np.int64)),
            values,
            size=shape,
            check_invariants=False,
        )


def _diagonal(A_t: torch.Tensor) -> torch.Tensor:
    crow = A_t.crow_indices()
    col = A_t.col_indices()
    rows = torch.repeat_interleave(torch.arange(len(crow) - 1), crow.diff())
    on_diag = rows == col
    diag = torch.zeros(A_t.shape[0], dtype=A_t.dtype)
    return diag.index_add(0, rows[on_diag], A_t.values()[on_diag])


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
    solver.setup()  # the configured KSP/PC types are read back from PETSc
    ksp_type, pc_type, scale = method_of(solver)
    if (ksp_type, pc_type) not in _SUPPORTED:
        raise ValueError(
            f"mode='unrolled' supports {sorted(_SUPPORTED)}, the solver is "
            f"{ksp_type}/{pc_type}; use mode='implicit' for other KSP/PC pairs"
        )
    t0 = time.perf_counter()
    A_t = torch_csr(A, theta)
    inv_m = 1.0 / _diagonal(A_t) if pc_type == "jacobi" else None
    B = b.cpu().reshape(-1, b.shape[-1]).T  # (n, batch): columns are right-hand sides
    k = solver.max_it
    if ksp_type == "richardson":
        x = _richardson(A_t, B, inv_m, scale, k)
    else:
        x = _cg(A_t, B, inv_m, k)
    stats = solver.stats
    stats.forward_solves += B.shape[1]
    stats.forward_iterations += k * B.shape[1]
    stats.forward_time += time.perf_counter() - t0
    if torch.is_grad_enabled() and (b.requires_grad or (theta is not None and theta.requires_grad)):
        stats.adjoint_solves += B.shape[1]
        stats.adjoint_iterations += k * B.shape[1]
    return x.T.reshape(b.shape).to(b.device)


def _precondition(inv_m, r):
    return r if inv_m is None else inv_m[:, None] * r


def _richardson(A_t, B, inv_m, scale, k):
    x = scale * _precondition(inv_m, B)
    for _ in range(k - 1):
        x = x + scale * _precondition(inv_m, B - A_t @ x)
    return x


def _cg(A_t, B, inv_m, k):
    x = torch.zeros_like(B)
    r = B
    z = _precondition(inv_m, r)
    p = z
    rho = (r * z).sum(0)
    for _ in range(k):
        q = A_t @ p
        pq = (p * q).sum(0)
        alpha = torch.where(pq != 0, rho / torch.where(pq != 0, pq, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * q
        z = _precondition(inv_m, r)
        rho_new = (r * z).sum(0)
        beta = torch.where(rho != 0, rho_new / torch.where(rho != 0, rho, 1.0), 0.0)
        p = z + beta * p
        rho = rho_new
    return x
