"""What several scenes and reports share: random smooth fields and torch sparse matrices.

`gaussian_bumps` draws the initial conditions of ``demos/heat.py`` and the sources of
``demos/poisson_sip.py``; `torch_sparse` (COO) and `torch_csr` carry a SciPy matrix into
torch for the scenes and benchmarks that multiply by one.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import torch

__all__ = ["gaussian_bumps", "torch_csr", "torch_sparse"]


def gaussian_bumps(
    points: np.ndarray, count: int, rng: np.random.Generator, *, bumps: int = 4,
    widths: tuple[float, float] = (0.08, 0.25),
) -> np.ndarray:  # fmt: skip
    """Random smooth fields: each a sum of `bumps` Gaussian bumps.

    Parameters
    ----------
    points : numpy.ndarray, shape (dim, n)
        Where the fields are evaluated (a mesh's nodes).
    count : int
        Number of fields.
    rng : numpy.random.Generator
        Draws, per bump, a centre (uniform in the bounding box of `points`), a width
        (a fraction of the box's largest side, uniform in `widths`) and an amplitude
        (uniform in [-1, 1]).
    bumps : int
        Bumps per field.
    widths : (float, float)
        Range of the widths, as fractions of the box's largest side.

    Returns
    -------
    numpy.ndarray, shape (count, n)
    """
    lo, hi = points.min(axis=1), points.max(axis=1)
    size = float(np.max(hi - lo))
    fields = np.zeros((count, points.shape[1]))
    for i in range(count):
        for _ in range(bumps):
            centre = lo + (hi - lo) * rng.random(len(lo))
            width = size * rng.uniform(*widths)
            r2 = ((points - centre[:, None]) ** 2).sum(axis=0)
            fields[i] += rng.uniform(-1, 1) * np.exp(-r2 / (2 * width**2))
    return fields


def torch_sparse(M: sp.spmatrix) -> torch.Tensor:
    """`M` as a coalesced torch sparse COO tensor."""
    M = M.tocoo()
    index = torch.from_numpy(np.vstack([M.row, M.col]).astype(np.int64))
    return torch.sparse_coo_tensor(
        index, torch.from_numpy(M.data), M.shape, check_invariants=True
    ).coalesce()


def torch_csr(M: sp.spmatrix) -> torch.Tensor:
    """`M` as a torch sparse CSR tensor (float64, int64 indices), without torch's warning
    that sparse CSR support is in beta."""
    M = M.tocsr()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            torch.from_numpy(M.indptr.astype(np.int64)),
            torch.from_numpy(M.indices.astype(np.int64)),
            torch.from_numpy(M.data.astype(np.float64)),
            size=M.shape,
            check_invariants=False,
        )
