"""torch autograd bridge: differentiable capped PETSc solves and parametric matvecs.

``x = solve(A, b, solver, theta=θ)`` runs ``KSPSolve`` forward.  Its backward runs
``KSPSolveTranspose`` with the solver's adjoint settings on the upstream gradient
g (a forward ``KSPSolve`` when A and the PC are symmetric): ``Aᵀ λ = g``, then
``∂L/∂b = λ`` and ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])``.  The forward solution is
kept, never recomputed, and nothing is computed for an input that does not need
a gradient.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from ..fem.parametric import ParametricMatrix
from ..core.solver import KSPSolver

__all__ = ["matvec", "solve"]


def _as_numpy(t: torch.Tensor, name: str) -> np.ndarray:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype != torch.float64:
        raise TypeError(f"{name} must be float64 (got {t.dtype}); call .double() first")
    arr = t.detach().cpu().numpy()
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or Inf")
    return arr


def _check_vector(arr: np.ndarray, n: int, name: str) -> None:
    if arr.ndim not in (1, 2) or arr.shape[-1] != n:
        raise ValueError(f"{name} must have shape ({n},) or (batch, {n}), got {tuple(arr.shape)}")


def _operator(A, theta: torch.Tensor | None):
    """Return (ParametricMatrix or None, CSR tuple ``(indptr, indices, data, shape)``)."""
    if isinstance(A, ParametricMatrix):
        if theta is None:
            raise ValueError("A is a ParametricMatrix: pass its parameters as theta=")
        values = A.values(_as_numpy(theta, "theta"))  # validates θ
        return A, (A.indptr, A.indices, values, A.shape)
    if theta is not None:
        raise ValueError("theta= is only meaningful for a ParametricMatrix A")
    if not sp.issparse(A):
        raise TypeError(f"A must be a scipy sparse matrix or ParametricMatrix, got {type(A)}")
    A = A.tocsr()
    if not A.has_sorted_indices:
        A = A.sorted_indices()
    if not np.all(np.isfinite(A.data)):
        raise ValueError("A has NaN or Inf entries")
    return None, (A.indptr, A.indices, A.data.astype(np.float64, copy=False), A.shape)


class _ImplicitSolve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, b, theta, P, csr, solver):
        ctx.symmetric = P.is_symmetric if P is not None else None  # None: solver checks values
        solver.set_operator(csr, symmetric=ctx.symmetric)
        x = torch.from_numpy(solver.solve(b.detach().cpu().numpy())).to(b.device)
        ctx.P, ctx.csr, ctx.solver = P, csr, solver
        if ctx.needs_input_grad[1]:  # ∂L/∂θ needs x; saved so in-place edits of x are caught
            ctx.save_for_backward(x)
        return x

    @staticmethod
    def backward(ctx, grad_x):
        need_b, need_theta = ctx.needs_input_grad[:2]
        if not (need_b or need_theta):
            return None, None, None, None, None
        # a no-op unless another solve changed A since the forward pass
        ctx.solver.set_operator(ctx.csr, symmetric=ctx.symmetric)
        lam = ctx.solver.solve_transpose(grad_x.detach().cpu().numpy())
        grad_b = torch.from_numpy(lam).to(grad_x.device) if need_b else None
        grad_theta = None
        if need_theta:
            (x,) = ctx.saved_tensors
            x = x.detach().cpu().numpy()
            grad_theta = torch.from_numpy(ctx.P.theta_gradient(lam, x)).to(grad_x.device)
        return grad_b, grad_theta, None, None, None


def solve(
    A,
    b: torch.Tensor,
    solver: KSPSolver,
    *,
    theta: torch.Tensor | None = None,
    mode: str = "implicit",
) -> torch.Tensor:
    """Differentiable capped solve ``x = A(θ)⁻¹ b`` with a PETSc KSP.

    Parameters
    ----------
    A : scipy.sparse matrix or ParametricMatrix
        The operator; a `ParametricMatrix` is evaluated at `theta`.
    b : torch.Tensor, float64, shape (n,) or (B, n)
        Right-hand side(s).  A batch shares one operator and one PC setup.
    solver : KSPSolver
        Carries the KSP/PC options, ``max_it`` (K) and the adjoint settings.
    theta : torch.Tensor, float64, shape (p,), optional
        Parameters of a ParametricMatrix.
    mode : {"implicit", "unrolled"}
        ``"implicit"``: PETSc forward solve, PETSc transpose solve in backward.
        ``"unrolled"``: the same K-step iteration in torch under autograd (exact
        derivative of the truncated solver); see `prdp_petsc.autograd.unrolled`.

    Returns
    -------
    torch.Tensor
        x, float64, on the device of `b`.  ``solver.last`` holds the last KSP's
        iterations, reason and residual norm.

    Notes
    -----
    Dirichlet values enter through the right-hand side; see `prdp_petsc.autograd.dirichlet`.
    """
    if mode not in ("implicit", "unrolled"):
        raise ValueError(f"mode must be 'implicit' or 'unrolled', got {mode!r}")
    if not isinstance(solver, KSPSolver):
        raise TypeError(f"solver must be a KSPSolver, got {type(solver).__name__}")
    P, csr = _operator(A, theta)
    _check_vector(_as_numpy(b, "b"), csr[3][0], "b")
    if mode == "unrolled":
        from .unrolled import unrolled_solve

        return unrolled_solve(A, b, solver, theta=theta)
    return _ImplicitSolve.apply(b, theta, P, csr, solver)


class _MatVec(torch.autograd.Function):
    @staticmethod
    def forward(ctx, v, theta, P, values):
        ctx.P, ctx.values = P, values
        ctx.save_for_backward(v)
        A = sp.csr_matrix((values, P.indices, P.indptr), shape=P.shape)
        return torch.from_numpy(np.asarray((A @ v.detach().cpu().numpy().T).T)).to(v.device)

    @staticmethod
    def backward(ctx, grad_y):
        (v,) = ctx.saved_tensors
        P = ctx.P
        g = grad_y.detach().cpu().numpy()
        grad_v = grad_theta = None
        if ctx.needs_input_grad[0]:
            A = sp.csr_matrix((ctx.values, P.indices, P.indptr), shape=P.shape)
            grad_v = torch.from_numpy(np.asarray((A.T @ g.T).T)).to(grad_y.device)
        if ctx.needs_input_grad[1]:
            gt = P.vjp_matvec(g, v.detach().cpu().numpy())
            grad_theta = torch.from_numpy(gt).to(grad_y.device)
        return grad_v, grad_theta, None, None


def matvec(A: ParametricMatrix, v: torch.Tensor, *, theta: torch.Tensor) -> torch.Tensor:
    """Differentiable ``A(θ) v`` for v of shape (m,) or (B, m) (used for Dirichlet lifting)."""
    if not isinstance(A, ParametricMatrix):
        raise TypeError("matvec expects a ParametricMatrix; for a constant matrix use torch")
    values = A.values(_as_numpy(theta, "theta"))  # validates θ
    _check_vector(_as_numpy(v, "v"), A.shape[1], "v")
    return _MatVec.apply(v, theta, A, values)
