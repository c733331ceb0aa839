"""CSR pattern helpers: transposed positions and a scale-proof symmetry test."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["SYMMETRY_RTOL", "mirror_symmetric", "transpose_permutation"]

#: entries may differ from their mirror by this fraction of their own size (assembly
#: sums contributions in any order)
SYMMETRY_RTOL = 1e-14


def mirror_symmetric(a: np.ndarray, mirror: np.ndarray, rtol: float = SYMMETRY_RTOL) -> bool:
    """True when every entry equals its mirror up to rounding of its own size.

    ``|a_ij − a_ji| ≤ rtol · max(|a_ij|, |a_ji|)`` entry by entry: no other entry
    sets the scale, so a huge diagonal (a penalty ``1/ε``) cannot hide an
    asymmetry elsewhere.  An entry against an exact zero must be zero itself.
    """
    diff = np.abs(a - mirror)
    return bool(np.all(diff <= rtol * np.maximum(np.abs(a), np.abs(mirror))))


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
