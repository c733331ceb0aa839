"""Sparse operators whose values are affine in a parameter vector: A(θ) = a₀ + G θ.

Assembly of a bilinear form that is linear in a coefficient field is linear in
that field's degrees of freedom θ.  A `ParametricMatrix` stores the CSR pattern
once, the constant values a₀ (nnz,) and the sparse assembly map G (nnz × p), so

* assembling for a new θ is one sparse product, ``a₀ + G θ``;
* the gradient of a loss through ``x = A(θ)⁻¹ b`` is ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])``
  with λ the adjoint solution: one more sparse product, no re-assembly.

G is built from scikit-fem forms by `prdp_petsc.fem.forms.from_form`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from ..core.ownership import immutable, own
from ..core.sparsity import (
    DIAGONAL_RTOL,
    SYMMETRY_RTOL,
    diagonal_scale,
    mirror_symmetric,
    transpose_permutation,
)
from ..errors import InputError, NonFiniteError

__all__ = ["ParametricMatrix", "csr_pattern"]


@dataclass(frozen=True, eq=False)
class ParametricMatrix:
    """A CSR matrix with fixed pattern and values ``a0 + G @ theta``.

    Parameters
    ----------
    indptr, indices : ndarray
        CSR pattern (sorted column indices per row).
    shape : tuple of int
    a0 : ndarray, shape (nnz,)
        Values that do not depend on θ.
    G : scipy.sparse.csr_matrix, shape (nnz, p)
        Assembly map from parameters to values.
    positive : bool
        True when θ is a coefficient that must be > 0 (diffusivity); `check_theta`
        rejects other values before PETSc sees them.
    symmetric : bool, optional
        Declared structure: ``True`` if A(θ) = A(θ)ᵀ for every θ, ``False`` if not.
        ``None`` (default) tests it once on a₀ and G, entry against mirror.  A wrong
        declaration gives wrong gradients (the adjoint would solve with A).

    Notes
    -----
    Immutable: the arrays (pattern, a₀ and those of G) are read-only copies made
    at construction (arrays that are already read-only and own their memory are
    taken as they are), so ``A.a0[0] = 1`` raises instead of changing the
    operator under a pending backward pass.  Derive a new matrix instead
    (``A * 2``, ``A + M``, or the constructor with new arrays).
    """

    indptr: np.ndarray
    indices: np.ndarray
    shape: tuple
    a0: np.ndarray
    G: sp.csr_matrix
    positive: bool = False
    symmetric: bool | None = None

    def __post_init__(self):
        # plain ints: a shape from scikit-fem's int32 counts would print as np.int32(482)
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        # immutable: what a backward pass uses is what its forward used
        for name, dtype in (("indptr", None), ("indices", None), ("a0", np.float64)):
            object.__setattr__(self, name, _frozen(getattr(self, name), dtype))
        G = sp.csr_matrix(self.G)
        if not G.has_canonical_format:  # scipy sorts in place later: do it before freezing
            G = G.copy()
            G.sum_duplicates()
        G = sp.csr_matrix(
            (_frozen(G.data, np.float64), _frozen(G.indices), _frozen(G.indptr)),
            shape=G.shape,
            copy=False,
        )
        object.__setattr__(self, "G", G)
        counts = np.diff(self.indptr)  # entries per row
        counts.flags.writeable = False
        object.__setattr__(self, "_row_counts", counts)
        rows = np.repeat(np.arange(self.shape[0]), counts)
        rows.flags.writeable = False
        object.__setattr__(self, "rows", rows)
        if self.G.shape[0] != self.nnz or self.a0.shape != (self.nnz,):
            raise InputError(
                f"G {self.G.shape} and a0 {self.a0.shape} must have nnz={self.nnz} rows"
            )

    @property
    def nnz(self) -> int:
        return len(self.indices)

    @property
    def n_params(self) -> int:
        """Number of parameters p (columns of G)."""
        return self.G.shape[1]

    def check_theta(self, theta: np.ndarray) -> np.ndarray:
        """Validate parameters (shape, finiteness, positivity) and return them as float64.

        `theta` is one parameter vector, shape (p,), or a batch of them, shape
        (B, p): one operator per sample.
        """
        theta = np.asarray(theta, dtype=np.float64)
        p = self.n_params
        empty_batch = theta.ndim == 2 and len(theta) == 0
        if theta.ndim not in (1, 2) or theta.shape[-1] != p or empty_batch:
            raise InputError(f"theta must have shape ({p},) or (batch, {p}), got {theta.shape}")
        if not np.all(np.isfinite(theta)):
            raise NonFiniteError("theta contains NaN or Inf")
        if self.positive and not np.all(theta > 0):
            raise InputError(
                f"theta is a diffusion coefficient and must be > 0 (min {theta.min():.3g})"
            )
        return theta

    def values(self, theta: np.ndarray) -> np.ndarray:
        """CSR values ``a0 + G @ theta``: shape (nnz,), or (B, nnz) for θ of shape (B, p).

        The result is read-only (the library's own: a `KSPSolver` keeps it without a
        copy; ``.copy()`` it to edit).  The values of the last single θ are kept:
        calling again with an equal θ returns the same array without the sparse
        product.
        """
        last = self.__dict__.get("_last")
        if last is not None and np.array_equal(last[0], theta):
            return last[1]  # θ unchanged (a fixed operator): checked before, no product
        theta = self.check_theta(theta)
        if theta.ndim == 2:
            values = np.asarray(self.G @ theta.T).T + self.a0
            return own(values)  # the library's own: a solver keeps it uncopied
        values = self.G @ theta
        values += self.a0
        own(values)  # read-only, shared by later calls with the same θ
        object.__setattr__(self, "_last", (theta.copy(), values))
        return values

    def matrix(self, theta: np.ndarray) -> sp.csr_matrix:
        """The assembled scipy CSR matrix A(θ) for one θ of shape (p,)."""
        if np.ndim(theta) != 1:
            raise InputError(f"matrix() takes one theta of shape ({self.n_params},)")
        values = self.values(theta).copy()  # the cached array is shared and read-only
        return sp.csr_matrix((values, self.indices, self.indptr), shape=self.shape)

    def theta_gradient(
        self, lam: np.ndarray, x: np.ndarray, *, per_sample: bool = False
    ) -> np.ndarray:
        """``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])`` for ``x = A(θ)⁻¹ b``, ``Aᵀλ = ∂L/∂x``.

        Parameters
        ----------
        lam, x : ndarray, shape (n,) or (B, n)
            Adjoint and forward solutions.
        per_sample : bool
            False (default): one θ shared by the batch, the result (p,) sums the
            samples' contributions.  True: sample i has its own θ_i (θ of shape
            (B, p)); the result (B, p) holds one gradient per sample, computed as
            one (B, nnz) product and one sparse product with Gᵀ.
        """
        # dA = λ[rows] ⊙ x[cols], one entry per nonzero: built in place chunk by chunk,
        # so its size is the only one of nnz the gradient allocates.  Indexing, not
        # np.take: take copies a read-only index array (these are) before taking
        if per_sample:
            lam, x = np.atleast_2d(lam), np.atleast_2d(x)
            dA = lam[:, self.rows]
            for c in _chunks(self.nnz):
                dA[:, c] *= x[:, self.indices[c]]
            return -np.asarray(self.G.T @ dA.T).T
        if lam.ndim == 1 and x.ndim == 1:
            dA = np.repeat(lam, self._row_counts)  # λ[rows], a sequential pass
            for c in _chunks(self.nnz):
                dA[c] *= x[self.indices[c]]
        else:
            lam, x = np.atleast_2d(lam), np.atleast_2d(x)
            dA = np.empty(self.nnz)
            for c in _chunks(self.nnz, len(lam)):
                dA[c] = np.einsum("bk,bk->k", lam[:, self.rows[c]], x[:, self.indices[c]])
        grad = self.G.T @ dA  # Gᵀ as CSC: scatters into θ, faster than a CSR Gᵀ
        return np.negative(grad, out=grad)

    @cached_property
    def is_symmetric(self) -> bool:
        """True when A(θ) = A(θ)ᵀ for every θ: ``symmetric`` if declared, else tested.

        The test compares every entry of a₀ and of each column of G with its own
        mirror (`prdp_petsc.core.sparsity.mirror_symmetric`), so no large entry
        elsewhere can hide an asymmetry; the rounding allowance of an entry (i, j)
        is also scaled by ``sqrt(d_i d_j)``, d the diagonal of ``|a₀| + |G| 1``.
        """
        if self.symmetric is not None:
            return bool(self.symmetric)
        perm = transpose_permutation(self.indptr, self.indices, self.shape)
        if perm is None:
            return False
        G, mirror = self.G, self.G[perm]
        absolute = np.abs(self.a0) + np.asarray(abs(G) @ np.ones(self.n_params)).ravel()
        scale = diagonal_scale(self.indptr, self.indices, absolute, self.shape)
        if not mirror_symmetric(self.a0, self.a0[perm], scale=scale):
            return False
        excess = (abs(G - mirror) - abs(G).maximum(abs(mirror)) * SYMMETRY_RTOL).tocoo()
        return bool(np.all(excess.data <= DIAGONAL_RTOL * scale[excess.row]))

    def vjp_matvec(self, w: np.ndarray, v: np.ndarray, *, per_sample: bool = False) -> np.ndarray:
        """``∂/∂θ ⟨w, A(θ) v⟩ = Gᵀ(w[rows] ⊙ v[cols])``; `per_sample` as in `theta_gradient`."""
        return -self.theta_gradient(w, v, per_sample=per_sample)

    def matvecs(self, values: np.ndarray, v: np.ndarray, *, transpose: bool = False) -> np.ndarray:
        """``A_i v_i`` (or ``A_iᵀ v_i``) per sample for CSR values (B, nnz) and v (B, m).

        One (B, nnz) product and one sparse product that sums it into rows
        (columns for the transpose); no Python loop over samples.
        """
        if transpose:
            src, dst, size = self.rows, self.indices, self.shape[1]
        else:
            src, dst, size = self.indices, self.rows, self.shape[0]
        products = values * v[:, src]  # indexing: see theta_gradient
        gather = sp.csr_matrix(
            (np.ones(self.nnz), (dst, np.arange(self.nnz))), shape=(size, self.nnz)
        )
        return np.asarray(gather @ products.T).T

    def submatrix(self, rows: np.ndarray, cols: np.ndarray) -> ParametricMatrix:
        """The block ``A[rows][:, cols]`` as a ParametricMatrix with the same θ.

        Used for Dirichlet elimination: ``A_II`` and ``A_IB``.
        """
        rows = np.asarray(rows)
        cols = np.asarray(cols)
        col_map = np.full(self.shape[1], -1)
        col_map[cols] = np.arange(len(cols))
        row_map = np.full(self.shape[0], -1)
        row_map[rows] = np.arange(len(rows))
        new_rows = row_map[self.rows]
        new_cols = col_map[self.indices]
        keep = np.flatnonzero((new_rows >= 0) & (new_cols >= 0))
        # entries of the kept rows, reordered by new row index (CSR order)
        order = keep[np.lexsort((new_cols[keep], new_rows[keep]))]
        counts = np.bincount(new_rows[order], minlength=len(rows))
        indptr = np.concatenate([[0], np.cumsum(counts)])
        return ParametricMatrix(
            indptr,
            new_cols[order],
            (len(rows), len(cols)),
            self.a0[order],
            self.G[order],
            self.positive,
        )

    def __add__(self, other) -> ParametricMatrix:
        """Add a constant scipy matrix or another ParametricMatrix (θ stacked: [θ₁, θ₂])."""
        if isinstance(other, ParametricMatrix):
            if other.shape != self.shape:
                raise InputError(f"shape mismatch {self.shape} vs {other.shape}")
            return _union([self, other], [self.G, other.G], self.positive and other.positive)
        other = sp.csr_matrix(other)
        if other.shape != self.shape:
            raise InputError(f"shape mismatch {self.shape} vs {other.shape}")
        const = ParametricMatrix(
            other.indptr,
            other.indices,
            other.shape,
            other.data.astype(np.float64),
            sp.csr_matrix((other.nnz, self.n_params)),
        )
        return _union([self, const], [self.G, None], self.positive)

    __radd__ = __add__

    def __mul__(self, alpha: float) -> ParametricMatrix:
        alpha = float(alpha)
        return ParametricMatrix(
            self.indptr,
            self.indices,
            self.shape,
            alpha * self.a0,
            alpha * self.G,
            self.positive,
        )

    __rmul__ = __mul__


_CHUNK = 1 << 13  # entries of a temporary in `theta_gradient` (64 KiB of doubles)


def _chunks(size: int, rows: int = 1):
    """Slices covering ``range(size)`` with at most `_CHUNK` / `rows` entries each."""
    step = max(1, _CHUNK // rows)
    return [slice(start, start + step) for start in range(0, size, step)]


def _frozen(arr, dtype=None) -> np.ndarray:
    """`arr` as a read-only array the library owns (copied unless it already is)."""
    out = np.asarray(arr, dtype=dtype)
    if immutable(out):
        return out
    return own(np.array(out, copy=True))


def csr_pattern(rows: np.ndarray, cols: np.ndarray, shape) -> tuple:
    """CSR pattern of (possibly repeated) entries: ``(indptr, indices, position)``.

    ``position[k]`` is where entry k lands in the CSR value array (repeats share one).
    """
    keys = np.asarray(rows, dtype=np.int64) * shape[1] + cols
    union, position = np.unique(keys, return_inverse=True)
    prow, pcol = np.divmod(union, shape[1])
    indptr = np.concatenate([[0], np.cumsum(np.bincount(prow, minlength=shape[0]))])
    return indptr, pcol, position


def _union(mats: list[ParametricMatrix], gs: list, positive: bool) -> ParametricMatrix:
    """Sum of parametric matrices on the union of their patterns."""
    shape = mats[0].shape
    indptr, indices, inverse = csr_pattern(
        np.concatenate([m.rows for m in mats]), np.concatenate([m.indices for m in mats]), shape
    )
    nnz = len(indices)
    offsets = np.cumsum([0] + [m.nnz for m in mats])
    a0 = np.zeros(nnz)
    blocks = []
    n_params = sum(g.shape[1] for g in gs if g is not None) or mats[0].n_params
    col0 = 0
    for m, g, lo, hi in zip(mats, gs, offsets[:-1], offsets[1:], strict=True):
        pos = inverse[lo:hi]
        np.add.at(a0, pos, m.a0)
        if g is not None:
            scatter = sp.csr_matrix(
                (np.ones(len(pos)), (pos, np.arange(len(pos)))), shape=(nnz, len(pos))
            )
            g_full = sp.hstack(
                [
                    sp.csr_matrix((len(pos), col0)),
                    g,
                    sp.csr_matrix((len(pos), n_params - col0 - g.shape[1])),
                ]
            )
            blocks.append(scatter @ g_full)
            col0 += g.shape[1]
    G = sum(blocks[1:], blocks[0]).tocsr() if blocks else sp.csr_matrix((nnz, n_params))
    return ParametricMatrix(indptr, indices, shape, a0, G, positive)
