"""CSR pattern helpers: transposed positions and a scale-proof symmetry test."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = [
    "DIAGONAL_RTOL",
    "SYMMETRY_RTOL",
    "csr_symmetric",
    "diagonal_scale",
    "mirror_symmetric",
    "transpose_permutation",
]

#: entries may differ from their mirror by this fraction of their own size (assembly
#: sums contributions in any order)
SYMMETRY_RTOL = 1e-14
#: ... or by this fraction of sqrt(|a_ii a_jj|): an entry that is the sum of element
#: contributions of that size (with cancellation) carries their rounding error
DIAGONAL_RTOL = 1e-12


def mirror_symmetric(
    a: np.ndarray, mirror: np.ndarray, rtol: float = SYMMETRY_RTOL, scale=None
) -> bool:
    """True when every entry equals its mirror up to rounding of its own size.

    ``|a_ij − a_ji| ≤ rtol · max(|a_ij|, |a_ji|) + DIAGONAL_RTOL · scale_ij`` entry
    by entry, with ``scale_ij = sqrt(|a_ii a_jj|)`` (`diagonal_scale`; none if
    not given).  No entry but the pair's own and their rows' diagonals sets the
    scale, so a huge diagonal (a penalty ``1/ε``) cannot hide an asymmetry
    elsewhere, and the scaled test is that of ``D^{-1/2} A D^{-1/2}``: an entry
    that cancelled down from element contributions of diagonal size (a rotated
    anisotropy) keeps their rounding error and is still symmetric.  An entry
    against an exact zero must be zero itself (or within the diagonal bound).
    """
    diff = np.abs(a - mirror)
    bound = rtol * np.maximum(np.abs(a), np.abs(mirror))
    if scale is not None:
        bound = bound + DIAGONAL_RTOL * scale
    return bool(np.all(diff <= bound))


def diagonal_scale(indptr, indices, data, shape) -> np.ndarray:
    """``sqrt(|a_ii a_jj|)`` for every CSR entry (i, j) (0 where a diagonal is missing)."""
    rows = np.repeat(np.arange(shape[0]), np.diff(indptr))
    on_diag = rows == indices
    diag = np.zeros(shape[0])
    np.add.at(diag, rows[on_diag], np.abs(data[on_diag]))
    return np.sqrt(diag[rows] * diag[np.asarray(indices)])


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


def csr_symmetric(indptr, indices, data, shape, perm=None) -> bool:
    """True when the CSR matrix equals its transpose to rounding (`mirror_symmetric` with
    the diagonal scale); `perm` is its `transpose_permutation` if known."""
    perm = transpose_permutation(indptr, indices, shape) if perm is None else perm
    if perm is None:
        return False
    data = np.asarray(data)
    if mirror_symmetric(data, data[perm]):  # the common, cheap case
        return True
    return mirror_symmetric(data, data[perm], scale=diagonal_scale(indptr, indices, data, shape))
