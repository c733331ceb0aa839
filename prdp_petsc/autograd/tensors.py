"""What the torch bridge accepts: float64 tensors of the right shape, finite.

Shared by `prdp_petsc.autograd.bridge`, `~prdp_petsc.autograd.dirichlet` and
`~prdp_petsc.autograd.nonlinear`, so every entry point refuses the same inputs
with the same errors: a wrong type is a ``TypeError``, a wrong shape an
`prdp_petsc.errors.InputError`, NaN or Inf a `prdp_petsc.errors.NonFiniteError`.

PETSc solves numbers, so every tensor is read as a numpy array.  Under a
``torch.func`` transform (``vmap``, ``grad``, ``jacrev``, ...) the tensors a
function sees are wrappers without storage, which no numpy code (and so no PETSc
solve) can read: they are refused with an `InputError` that names what works
instead (a batch of operators θ of shape (B, p); ``torch.autograd`` for
gradients), rather than torch's own "Cannot access data pointer" error.
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError, NonFiniteError

__all__ = ["as_numpy", "check_finite", "check_tensor", "check_vector"]


def as_numpy(t: torch.Tensor, name: str, *, finite: bool = True) -> np.ndarray:
    """float64 numpy view of tensor `t` (no copy on the CPU).

    Raises ``TypeError`` unless `t` is a float64 tensor; with `finite`,
    `NonFiniteError` if it holds NaN or Inf.
    """
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype != torch.float64:
        raise TypeError(f"{name} must be float64 (got {t.dtype}); call .double() first")
    try:
        arr = t.detach().cpu().numpy()
    except RuntimeError as err:
        if "storage" not in str(err):
            raise
        raise InputError(
            f"{name} is a tensor without storage, as torch.func transforms (vmap, grad, "
            "jacrev, ...) pass them: they cannot see inside a PETSc solve. For one solve per "
            "sample pass a batch of operators, theta of shape (B, p) with b of shape (B, n), "
            "in one call (each sample gets its own dL/dtheta_i); for gradients use "
            "torch.autograd (loss.backward() or torch.autograd.grad)"
        ) from err
    if finite:
        check_finite(arr, name)
    return arr


def check_finite(arr: np.ndarray, name: str) -> None:
    """`NonFiniteError` naming `name` if `arr` holds NaN or Inf (a sum first: fast path)."""
    if not (np.isfinite(arr.sum()) or np.all(np.isfinite(arr))):
        raise NonFiniteError(f"{name} contains NaN or Inf")


def check_vector(arr: np.ndarray, n: int, name: str) -> None:
    """`InputError` unless `arr` has shape ``(n,)`` or ``(batch, n)``."""
    if arr.ndim not in (1, 2) or arr.shape[-1] != n:
        raise InputError(f"{name} must have shape ({n},) or (batch, {n}), got {tuple(arr.shape)}")


def check_tensor(t: torch.Tensor, n: int, name: str) -> None:
    """`check_vector` of a float64 tensor, finite, where it lives: a CPU tensor as a numpy
    view (`as_numpy`), a GPU tensor by torch on its device (one boolean crosses to the
    host, no copy of the entries)."""
    if not isinstance(t, torch.Tensor) or t.device.type == "cpu":
        check_vector(as_numpy(t, name), n, name)
        return
    if t.dtype != torch.float64:
        raise TypeError(f"{name} must be float64 (got {t.dtype}); call .double() first")
    if t.ndim not in (1, 2) or t.shape[-1] != n:
        raise InputError(f"{name} must have shape ({n},) or (batch, {n}), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise NonFiniteError(f"{name} contains NaN or Inf")
