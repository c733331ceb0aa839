"""A(θ) as a torch operator for the unrolled iterations: ``A @ X`` with a cheap, exact backward.

Columns of X are samples.  The operator holds one set of CSR values (nnz,),
shared by every column, or one per sample (B, nnz) when θ has shape (B, p);
column i is then multiplied by ``A(θ_i)``.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import torch

from ..fem.parametric import ParametricMatrix

__all__ = ["UnrolledOperator"]


def _csr_tensor(indptr, indices, values, shape) -> torch.Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(
            torch.tensor(np.asarray(indptr, dtype=np.int64)),
            torch.tensor(np.asarray(indices, dtype=np.int64)),
            values,
            size=shape,
            check_invariants=False,
        )


class UnrolledOperator:
    """A(θ) inside the unrolled loop: ``A @ X`` for X of shape (n, columns).

    Entry k of the CSR values sits at ``(rows[k], cols[k])``.  The forward product
    of shared values uses a CSR tensor; a batch of operators (θ of shape (B, p))
    multiplies column i by ``A(θ_i)`` with one (nnz, B) product summed into rows.
    The backward is ``Aᵀ gY`` (the same values with rows and columns swapped, see
    `T`) and ``gY[rows] · X[cols]`` for the values, both written as
    differentiable products, so no iteration differentiates through torch's
    sparse kernels and second derivatives are exact.

    Parameters
    ----------
    A : ParametricMatrix or scipy.sparse matrix
    theta : torch.Tensor, shape (p,) or (B, p), optional
        Parameters of a ParametricMatrix; ``values`` is then ``a0 + G θ``
        (differentiable in θ), shape (nnz,) or (B, nnz).
    """

    def __init__(self, A, theta: torch.Tensor | None = None):
        if isinstance(A, ParametricMatrix):
            G = A.G.tocoo()
            G_t = torch.sparse_coo_tensor(
                np.vstack([G.row, G.col]), G.data, G.shape, check_invariants=False
            )
            theta = theta.cpu()
            columns = theta.T if theta.ndim == 2 else theta[:, None]
            values = torch.from_numpy(np.array(A.a0))[:, None] + torch.sparse.mm(G_t, columns)
            self.values = values.T if theta.ndim == 2 else values[:, 0]
            indptr, indices, shape = A.indptr, A.indices, A.shape
        else:
            A = sp.csr_matrix(A)
            A.sort_indices()
            self.values = torch.from_numpy(A.data.astype(np.float64))
            indptr, indices, shape = A.indptr, A.indices, A.shape
        self.shape = tuple(shape)
        self.rows = torch.from_numpy(np.repeat(np.arange(shape[0]), np.diff(indptr)))
        self.cols = torch.tensor(np.asarray(indices, dtype=np.int64))
        self.csr = self.csr_t = None
        if not self.batched:
            nnz = len(indices)
            T = sp.csr_matrix((np.arange(nnz), indices, indptr), shape=shape).T.tocsr()
            v = self.values.detach()
            self.csr = _csr_tensor(indptr, indices, v, shape)
            self.csr_t = _csr_tensor(T.indptr, T.indices, v[torch.from_numpy(T.data)], shape[::-1])
        self._transpose = None

    @property
    def batched(self) -> bool:
        """True for one operator per sample (values of shape (B, nnz))."""
        return self.values.ndim == 2

    @property
    def T(self) -> UnrolledOperator:
        """Aᵀ on the same values (entry k at ``(cols[k], rows[k])``), built once."""
        if self._transpose is None:
            t = object.__new__(UnrolledOperator)
            t.values, t.shape = self.values, self.shape[::-1]
            t.rows, t.cols = self.cols, self.rows
            t.csr, t.csr_t = self.csr_t, self.csr
            t._transpose = self
            self._transpose = t
        return self._transpose

    def __matmul__(self, X: torch.Tensor) -> torch.Tensor:
        return _SpMM.apply(self.values, X, self)

    def diagonal(self) -> torch.Tensor:
        """Diagonal of A, shape (n, 1), or (n, B) for a batch (differentiable in the values)."""
        on_diag = self.rows == self.cols
        values = self.values.T if self.batched else self.values[:, None]
        diag = torch.zeros(self.shape[0], values.shape[1], dtype=values.dtype)
        return diag.index_add(0, self.rows[on_diag], values[on_diag])

    def product(self, values: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
        """``A X`` outside autograd: the CSR tensor, or per-sample `values` (B, nnz)."""
        if not self.batched:
            return self.csr @ X
        products = values.T * X[self.cols]
        return torch.zeros(self.shape[0], X.shape[1], dtype=X.dtype).index_add_(
            0, self.rows, products
        )


class _SpMM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, X, op):
        ctx.op = op
        ctx.save_for_backward(values, X if ctx.needs_input_grad[0] else None)
        return op.product(values.detach(), X)

    @staticmethod
    def backward(ctx, gY):
        op = ctx.op
        values, X = ctx.saved_tensors
        g_values = g_X = None
        if ctx.needs_input_grad[0]:
            g_values = gY[op.rows] * X[op.cols]  # (nnz, columns)
            g_values = g_values.T if op.batched else g_values.sum(-1)
        if ctx.needs_input_grad[1]:
            g_X = _SpMM.apply(values, gY, op.T)  # differentiable again under create_graph
        return g_values, g_X, None
