"""The implicit solve and the parametric product as torch autograd functions, for every
operator layout.

`ImplicitSolve`: forward ``KSPSolve`` of ``A(θ) x = b``; backward one transpose solve
``Aᵀλ = g``, then ``∂L/∂b = λ`` and ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])``.  `MatVec`:
``A(θ) v``, backward ``Aᵀ g`` and ``∂(gᵀ A(θ) v)/∂θ``.  The maths is the same whether
every rank holds the whole operator (`prdp_petsc.autograd.bridge`) or only its own rows
(`prdp_petsc.autograd.owned`); what differs is the form of the operator, which a small
object carries: a `SolveOperator` (what the solver is given, a CSR tuple or an
`~prdp_petsc.core.operator.OwnedCSR`) and a `Product` (the layout's own products).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from ..core.results import CallInfo, SolverError
from ..core.solution import AdjointSlot, LinearSolution
from ..core.solver import KSPSolver
from .once import once_differentiable

__all__ = ["ImplicitSolve", "MatVec", "Product", "SolveOperator"]


class SolveOperator:
    """The operator of one implicit solve, as its forward set it and its backward needs it.

    Parameters
    ----------
    P : ParametricMatrix or DistributedParametricMatrix
        Gives ``∂L/∂θ`` (``P.theta_gradient``).
    operator : tuple or OwnedCSR
        What `KSPSolver.set_operator` takes: ``(indptr, indices, data, shape)`` with
        `data` of shape ``(nnz,)``, or ``(B, nnz)`` for a batch of operators (sample i
        solves with its own ``data[i]``); or this rank's rows (`OwnedCSR`).
    known_symmetric : bool, optional
        Whether A = Aᵀ, if known (``P.is_symmetric``); None: the solver tests it.

    Notes
    -----
    After the forward the operator is the one the solver keeps (`KSPSolver.operator_csr`:
    read-only arrays, never edited), with its `~KSPSolver.operator_version`: while the
    solver still holds it, the backward solves on the solver's Mat as it is; after
    another solve replaced it, the kept operator is set again (no copy, no comparison).
    """

    __slots__ = ("P", "forward", "known_symmetric", "operator", "per_sample", "version")

    def __init__(self, P, operator, known_symmetric: bool | None = None) -> None:
        self.P = P
        self.operator = operator
        self.known_symmetric = known_symmetric
        #: a batch of operators, one per sample
        self.per_sample = isinstance(operator, tuple) and operator[2].ndim == 2
        #: the solver's `operator_version` while it holds this operator (None: unknown)
        self.version: int | None = None
        #: the `CallInfo` of the forward solve on it (set by `ImplicitSolve`)
        self.forward: CallInfo | None = None

    def solve(self, solver: KSPSolver, rhs: np.ndarray, *, transpose: bool) -> LinearSolution:
        """``A x = rhs`` (``Aᵀ λ = rhs`` with `transpose`), the operator set only if the
        solver no longer holds it."""
        run = solver.solve_transpose if transpose else solver.solve
        if self.version is not None and self.version == solver.operator_version:
            return run(rhs)
        if self.per_sample:
            return self._solve_each(solver, rhs, transpose)
        solver.set_operator(self.operator, known_symmetric=self.known_symmetric)
        out = run(rhs)
        self.operator = solver.operator_csr() or self.operator  # the solver's kept arrays
        self.version = solver.operator_version
        return out

    def _solve_each(self, solver: KSPSolver, rhs: np.ndarray, transpose: bool) -> LinearSolution:
        """A batch of operators: one ``set_operator`` and one solve per sample, one
        result of them all; the backward visits them in reverse, so the forward's last
        operator is still set."""
        run = solver.solve_transpose if transpose else solver.solve
        indptr, indices, data, shape = self.operator
        out = np.empty_like(rhs)
        order = reversed(range(len(data))) if transpose else range(len(data))
        calls = {}
        for i in order:
            solver.set_operator(
                (indptr, indices, data[i], shape), known_symmetric=self.known_symmetric
            )
            try:
                sol = run(rhs[i])
            except SolverError as err:
                raise type(err)(f"sample {i} of the batch: {err}", reason=err.reason) from err
            out[i], calls[i] = sol.value, sol.info
        # one record of the whole batch, in batch order (the solves ran one per sample)
        return LinearSolution(out, CallInfo.concat(calls[i] for i in range(len(data))))


def _gradients(ctx, lam: np.ndarray, grad_x: torch.Tensor, *, per_sample=False):
    """``(∂L/∂b, ∂L/∂θ)`` of an implicit solve's backward from the adjoint λ:
    ``∂L/∂b = λ`` and ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])`` (``ctx.P.theta_gradient`` with
    the saved x), each None where ``ctx.needs_input_grad`` says it is not needed."""
    need_b, need_theta = ctx.needs_input_grad[:2]
    device = grad_x.device
    grad_b = grad_theta = None
    if need_b:
        grad_b = torch.from_numpy(lam) if grad_x.is_cpu else torch.from_numpy(lam).to(device)
    if need_theta:
        (x,) = ctx.saved_tensors
        x = x.detach().cpu().numpy()
        gt = (
            ctx.P.theta_gradient(lam, x, per_sample=True)
            if per_sample
            else ctx.P.theta_gradient(lam, x)
        )
        grad_theta = torch.from_numpy(gt).to(device)
    return grad_b, grad_theta


class ImplicitSolve(torch.autograd.Function):
    """``x = A(θ)⁻¹ b`` with a `KSPSolver`: ``apply(b, theta, operator, solver, outcome)``
    with a `SolveOperator`, which keeps the forward's `CallInfo` (``operator.forward``);
    `outcome`, the result's `AdjointSlot`, gets the adjoint's."""

    @staticmethod
    def forward(ctx, b, theta, operator: SolveOperator, solver: KSPSolver, outcome):
        sol = operator.solve(solver, b.detach().cpu().numpy(), transpose=False)
        operator.forward = sol.info
        x = torch.from_numpy(sol.value) if b.is_cpu else torch.from_numpy(sol.value).to(b.device)
        ctx.operator, ctx.P, ctx.solver, ctx.outcome = operator, operator.P, solver, outcome
        if ctx.needs_input_grad[1]:  # ∂L/∂θ needs x; saved so in-place edits of x are caught
            ctx.save_for_backward(x)
        return x

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_x):
        need_b, need_theta = ctx.needs_input_grad[:2]
        if not (need_b or need_theta):
            return None, None, None, None, None
        # a NaN or Inf cotangent raises NonFiniteError in the solver (never a zero λ)
        g = grad_x.detach().cpu().numpy()
        sol = ctx.operator.solve(ctx.solver, g, transpose=True)
        outcome: AdjointSlot = ctx.outcome
        outcome.info = sol.info  # the result's `adjoint`
        per_sample = ctx.operator.per_sample
        return *_gradients(ctx, sol.value, grad_x, per_sample=per_sample), None, None, None


class Product(Protocol):
    """The products of one parametric operator's values in one layout."""

    def apply(self, v: np.ndarray) -> np.ndarray:
        """``A v``."""

    def apply_transpose(self, g: np.ndarray) -> np.ndarray:
        """``Aᵀ g``."""

    def theta_vjp(self, g: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``∂(gᵀ A(θ) v)/∂θ``."""


class MatVec(torch.autograd.Function):
    """``A(θ) v``: ``apply(v, theta, product)`` with a `Product` of ``A(θ)``'s values."""

    @staticmethod
    def forward(ctx, v, theta, product: Product):
        ctx.product = product
        ctx.save_for_backward(v, theta)  # θ: a second derivative must see it (see .once)
        return torch.from_numpy(product.apply(v.detach().cpu().numpy())).to(v.device)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_y):
        v, _ = ctx.saved_tensors
        g = grad_y.detach().cpu().numpy()
        grad_v = grad_theta = None
        if ctx.needs_input_grad[0]:
            grad_v = torch.from_numpy(ctx.product.apply_transpose(g)).to(grad_y.device)
        if ctx.needs_input_grad[1]:
            gt = ctx.product.theta_vjp(g, v.detach().cpu().numpy())
            grad_theta = torch.from_numpy(gt).to(grad_y.device)
        return grad_v, grad_theta, None
