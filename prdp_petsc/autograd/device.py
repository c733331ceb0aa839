"""The implicit solve on a solver's device path: torch memory shared with PETSc by DLPack.

A `~prdp_petsc.core.solver.KSPSolver` whose options name a ``vec_type`` or ``mat_type``
(its `~KSPSolver.vec_type` is not None) solves in the caller's memory
(`prdp_petsc.core.device`); `prdp_petsc.solve` then runs here instead of through numpy:

* b (and the cotangent g in the backward) is handed to PETSc by DLPack, and x (λ) is
  written into a tensor allocated by torch on b's device (``torch.empty_like``), row
  by row for a batch: no copy of a vector in either direction.  A right-hand side that
  is not contiguous (``b.expand(B, -1)``) is made contiguous by torch on its device
  first.
* A `~prdp_petsc.fem.parametric.ParametricMatrix`'s values ``a0 + G θ`` are computed
  by torch on θ's device (`DeviceParametric`: G and Gᵀ kept there as sparse CSR
  tensors, once per matrix and device) and set on the solver's Mat from that memory
  (`~prdp_petsc.core.operator.DLPackCSR`); ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])`` is a
  torch product on the same device.  The values of the last θ are kept, so an
  unchanged θ (compared on the device: one boolean crosses) sets nothing and sets no
  PC up.  A batch of operators (θ of shape (B, p)) is one (B, nnz) product; sample i
  solves on its row of values.
* A scipy operator is host memory: its values reach the Mat once per change (the
  solver keeps and compares them on the host, as on the default path: one pass over
  the values per call).  A constant operator whose values are already in the solver's
  memory is a `~prdp_petsc.core.operator.DLPackCSR` (values a torch tensor there):
  recognised by the values tensor's identity, so an unchanged one costs nothing per
  call (a tensor edited in place is not seen: pass a new tensor for new values).
* What crosses to the host per call: PETSc's scalars (norms, iterations, reasons) and
  the booleans of θ's checks (finite, positive, unchanged).

The checks of the default path hold, computed where the data lives: NaN or Inf in b
or the cotangent is refused from a PETSc norm, in θ from a torch reduction; a tensor
in memory other than the solver's types' raises `~prdp_petsc.errors.InputError`
naming the fix (never a silent copy).
"""

from __future__ import annotations

import warnings
import weakref

import scipy.sparse as sp
import torch

from ..core.operator import DLPackCSR, as_csr
from ..core.results import CallInfo, SolverError
from ..core.solution import LinearSolution
from ..core.solver import KSPSolver
from ..errors import InputError, NonFiniteError
from ..fem.parametric import ParametricMatrix
from .once import once_differentiable

__all__ = ["DeviceOperator", "DeviceParametric", "DeviceSolve", "device_matvec", "device_solve"]


class DeviceParametric:
    """A `ParametricMatrix` on one torch device: ``a0 + G θ`` and ``−Gᵀ(λ[rows] ⊙ x[cols])``.

    Made once per matrix and device (`for_device`) and kept while the matrix lives;
    holds a0, the pattern's row and column of every value, G and Gᵀ (sparse CSR) as
    tensors on `device`.
    """

    def __init__(self, P: ParametricMatrix, device: torch.device) -> None:
        self.P = P
        self.device = device
        f64 = {"dtype": torch.float64, "device": device}
        self.a0 = torch.tensor(P.a0, **f64)  # a copy: P's arrays are read-only
        self.rows = torch.tensor(P.rows, dtype=torch.int64, device=device)
        self.cols = torch.tensor(P.indices, dtype=torch.int64, device=device)
        self.G = _csr_tensor(P.G, device)
        self.Gt = _csr_tensor(P.G.T.tocsr(), device)
        self._last: tuple[torch.Tensor, torch.Tensor] | None = None  # (θ, values)

    @classmethod
    def for_device(cls, P: ParametricMatrix, device: torch.device) -> DeviceParametric:
        """The one kept for `P` on `device` (made at first use)."""
        kept = _KEPT.setdefault(P, {})
        if device not in kept:
            kept[device] = cls(P, device)
        return kept[device]

    def values(self, theta: torch.Tensor) -> torch.Tensor:
        """``a0 + G θ``: (nnz,) for θ (p,), (B, nnz) for θ (B, p); θ checked (shape, finite,
        positive where `P.positive`) on its device.  The values of the last single θ
        are returned again, the same tensor, while θ is equal to it."""
        last = self._last
        if last is not None and last[0].shape == theta.shape and torch.equal(last[0], theta):
            return last[1]
        self._check(theta)
        theta = theta.detach()
        with torch.no_grad():
            if theta.ndim == 2:
                values = (self.G @ theta.T).T.contiguous() + self.a0
            else:
                values = self.G @ theta + self.a0
        if theta.ndim == 1:
            self._last = (theta.clone(), values)
        return values

    def _check(self, theta: torch.Tensor) -> None:
        p = self.P.n_params
        if theta.ndim not in (1, 2) or theta.shape[-1] != p or theta.numel() == 0:
            raise InputError(
                f"theta must have shape ({p},) or (batch, {p}), got {tuple(theta.shape)}"
            )
        if not bool(torch.isfinite(theta).all()):
            raise NonFiniteError("theta contains NaN or Inf")
        if self.P.positive and not bool((theta > 0).all()):
            raise InputError(
                f"theta is a diffusion coefficient and must be > 0 (min {theta.min().item():.3g})"
            )

    def theta_gradient(
        self, lam: torch.Tensor, x: torch.Tensor, *, per_sample: bool
    ) -> torch.Tensor:
        """``−Gᵀ(λ[rows] ⊙ x[cols])`` (`ParametricMatrix.theta_gradient`) by torch on the
        device: (p,) summed over a batch, or (B, p) with `per_sample`."""
        dA = lam.index_select(-1, self.rows) * x.index_select(-1, self.cols)
        if per_sample:
            return -(self.Gt @ dA.T).T
        if dA.ndim == 2:
            dA = dA.sum(0)
        return -(self.Gt @ dA)


#: `DeviceParametric` per ParametricMatrix and device, freed with the matrix
_KEPT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _csr_tensor(M: sp.csr_matrix, device: torch.device) -> torch.Tensor:
    """scipy CSR `M` as a torch sparse CSR tensor on `device`."""
    M = sp.csr_matrix(M)
    with warnings.catch_warnings():  # torch's note that sparse CSR support is in beta
        warnings.filterwarnings("ignore", "Sparse CSR tensor support", UserWarning)
        return torch.sparse_csr_tensor(
            torch.tensor(M.indptr, dtype=torch.int64),
            torch.tensor(M.indices, dtype=torch.int64),
            torch.tensor(M.data, dtype=torch.float64),
            size=M.shape,
            check_invariants=True,
        ).to(device)


class DeviceOperator:
    """The operator of one implicit solve on the device path, as its forward set it and
    its backward needs it (the `~prdp_petsc.autograd.implicit.SolveOperator` of this
    path).

    Parameters
    ----------
    operator : DLPackCSR or tuple
        What the solver is given: values in torch memory, with `values` of shape
        (B, nnz) for a batch of operators (sample i solves on ``values[i]``); or a
        scipy operator's CSR tuple (host values).
    device : DeviceParametric or None
        Gives ``∂L/∂θ``; None for a scipy operator.
    values : torch.Tensor or None
        The (B, nnz) values of a batch of operators.
    known_symmetric : bool, optional
        Whether A = Aᵀ, if known; None: the solver tests it.

    Notes
    -----
    While the solver still holds this operator (its `~KSPSolver.operator_version`
    unchanged since the forward) the backward solves on the Mat as it is; after
    another solve replaced it, the same values tensor is set again (no comparison).
    A batch's per-sample operators are made once, so the backward, which visits the
    samples in reverse, finds the last one still set.
    """

    def __init__(self, operator, device: DeviceParametric | None, values, known_symmetric):
        self.operator = operator
        self.device = device
        self.known_symmetric = known_symmetric
        self.samples: list[DLPackCSR] | None = None
        if values is not None and values.ndim == 2:
            indptr, indices, shape = operator.indptr, operator.indices, operator.shape
            self.samples = [DLPackCSR(indptr, indices, v, shape) for v in values.unbind(0)]
        self.version: int | None = None
        self.forward: CallInfo | None = None

    @property
    def per_sample(self) -> bool:
        return self.samples is not None

    def solve(self, solver: KSPSolver, rhs: torch.Tensor, *, transpose: bool):
        """``A x = rhs`` (``Aᵀ λ = rhs``) into a new tensor on rhs's device; returns it
        with the call's `CallInfo`."""
        rhs = rhs.detach().contiguous()
        out = torch.empty_like(rhs)
        if rhs.is_cuda:
            _join_streams(rhs.device)
        run = solver.solve_transpose if transpose else solver.solve
        if self.samples is not None:
            calls = {}
            order = reversed(range(len(rhs))) if transpose else range(len(rhs))
            for i in order:
                solver.set_operator(self.samples[i], known_symmetric=self.known_symmetric)
                try:
                    calls[i] = run(rhs[i], out=out[i]).info
                except SolverError as err:
                    raise type(err)(f"sample {i} of the batch: {err}", reason=err.reason) from err
            return out, CallInfo.concat(calls[i] for i in range(len(rhs)))
        if self.version is None or self.version != solver.operator_version:
            solver.set_operator(self.operator, known_symmetric=self.known_symmetric)
            self.version = solver.operator_version
        rows_in = rhs if rhs.ndim == 1 else rhs.unbind(0)
        rows_out = out if out.ndim == 1 else out.unbind(0)
        return out, run(rows_in, out=rows_out).info

    def theta_gradient(self, lam: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return self.device.theta_gradient(lam, x, per_sample=self.per_sample)


def _join_streams(device: torch.device) -> None:
    """Let PETSc see what torch wrote: PETSc works on the device's default stream, which
    orders itself after torch's default stream but not after a side stream the caller
    made current (``torch.cuda.stream(s)``); that one is waited for.  PETSc's writes are
    complete when the solve returns (its last step reads a norm on the host)."""
    stream = torch.cuda.current_stream(device)
    if stream != torch.cuda.default_stream(device):
        stream.synchronize()


class DeviceSolve(torch.autograd.Function):
    """``x = A(θ)⁻¹ b`` on the device path: ``apply(b, theta, operator, solver, outcome)``
    with a `DeviceOperator` (which keeps the forward's `CallInfo`); `outcome`, the
    result's `~prdp_petsc.core.solution.AdjointSlot`, gets the adjoint's."""

    @staticmethod
    def forward(ctx, b, theta, operator: DeviceOperator, solver: KSPSolver, outcome):
        x, operator.forward = operator.solve(solver, b, transpose=False)
        ctx.operator, ctx.solver, ctx.outcome = operator, solver, outcome
        if ctx.needs_input_grad[1]:  # ∂L/∂θ needs x; saved so in-place edits of x are caught
            ctx.save_for_backward(x)
        return x

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_x):
        need_b, need_theta = ctx.needs_input_grad[:2]
        if not (need_b or need_theta):
            return None, None, None, None, None
        lam, ctx.outcome.info = ctx.operator.solve(ctx.solver, grad_x, transpose=True)
        grad_theta = None
        if need_theta:
            (x,) = ctx.saved_tensors
            grad_theta = ctx.operator.theta_gradient(lam, x)
        return (lam if need_b else None), grad_theta, None, None, None


def _check_tensor(t, n: int, name: str) -> None:
    """A float64 tensor of shape (n,) or (B, n), checked without reading its entries."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype != torch.float64:
        raise TypeError(f"{name} must be float64 (got {t.dtype}); call .double() first")
    if t.ndim not in (1, 2) or t.shape[-1] != n:
        raise InputError(f"{name} must have shape ({n},) or (batch, {n}), got {tuple(t.shape)}")


def device_solve(A, b, solver: KSPSolver, theta, outcome) -> LinearSolution:
    """`prdp_petsc.solve` (implicit mode, no x0) on `solver`'s device path: x on b's
    device, with the forward's `CallInfo`; `outcome` gets the adjoint's."""
    if isinstance(A, ParametricMatrix):
        if theta is None:
            raise InputError("A is a ParametricMatrix: pass its parameters as theta=")
        _check_tensor(b, A.shape[0], "b")
        if not isinstance(theta, torch.Tensor) or theta.dtype != torch.float64:
            raise TypeError("theta must be a float64 torch.Tensor")
        if theta.device != b.device:
            raise InputError(
                f"theta is on {theta.device} and b on {b.device}: the operator's values are "
                "computed where theta is, so put both on one device"
            )
        device = DeviceParametric.for_device(A, theta.device)
        values = device.values(theta)
        if values.ndim == 2 and (b.ndim != 2 or len(b) != len(values)):
            batch, p = len(values), A.n_params
            raise InputError(
                f"theta must have shape ({p},) for b of shape {tuple(b.shape)}: theta of shape "
                f"({batch}, {p}) is a batch of operators and needs b of shape ({batch}, "
                f"{b.shape[-1]}); for a shared b pass b.expand({batch}, -1)"
            )
        csr = DLPackCSR(A.indptr, A.indices, values, A.shape)
        operator = DeviceOperator(csr, device, values, A.is_symmetric)
    else:
        if theta is not None:
            raise InputError("theta= is only meaningful for a ParametricMatrix A")
        if isinstance(A, DLPackCSR):  # values already in the solver's memory
            _check_tensor(b, int(A.shape[0]), "b")
            operator = DeviceOperator(A, None, None, None)
        elif sp.issparse(A):
            csr = as_csr(A, finite=False)  # the solver tests values it has not seen
            _check_tensor(b, csr[3][0], "b")
            operator = DeviceOperator(csr, None, None, None)
        else:
            raise TypeError(
                f"A must be a scipy sparse matrix, a DLPackCSR or a ParametricMatrix, got {type(A)}"
            )
    x = DeviceSolve.apply(b, theta, operator, solver, outcome)
    return LinearSolution(x, operator.forward, outcome)


def device_matvec(A: ParametricMatrix, v: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``A(θ) v`` by torch on θ's device, differentiable in θ and v (torch's own autograd:
    the values ``a0 + G θ`` and the row sums ``Σ_k values_k v[cols_k]``); v (n,) or (B, n),
    with θ (B, p) sample i's own operator.  The correction form of an initial guess
    (``b − A(θ) x0``) on the device path uses it."""
    device = DeviceParametric.for_device(A, theta.device)
    device.values(theta)  # checks θ (and keeps its values for the solve that follows)
    values = device.G @ (theta.T if theta.ndim == 2 else theta)
    values = (values.T if theta.ndim == 2 else values) + device.a0
    products = values * v[..., device.cols]
    shape = (*products.shape[:-1], A.shape[0])
    return products.new_zeros(shape).index_add(-1, device.rows, products)
