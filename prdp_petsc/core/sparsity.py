"""CSR pattern helpers: transposed positions and symmetry up to rounding."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["nearly_equal", "transpose_permutation"]


def nearly_equal(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal up to rounding: ``max|a − b| ≤ 1e-14 max|a|`` (assembly sums in any order)."""
    scale = np.abs(a).max(initial=0.0)
    return bool(np.abs(a - b).max(initial=0.0) <= 1e-14 * scale)


def transpose_permutation(indptr, indices, shape) -> np.ndarray | None:
    """Position of entry (j, i) for each CSR entry (i, j); None if the pattern is not symmetric."""
    if shape[0] != shape[1]:
        return None
    nnz = len(indices)
    T = sp.csr_matrix((np.arange(nnz) + 1, indices, indptr), shape=shape).T.tocsr()
    T.sort_indices()
    if not (np.array_equal(T.indptr, indptr) and np.array_equal(T.indices, indices)):
        return None
    return T.data - 1
