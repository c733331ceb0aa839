"""Finite-difference Laplacians on structured grids of the unit interval, square or cube.

The operators are the standard second-order 3-, 5- and 7-point stencils, built as
Kronecker sums of 1D second-difference matrices and returned as scipy CSR
matrices in float64.

Ordering
--------
Unknowns are numbered in C order (row-major, last axis fastest): on a grid of
shape ``(n0, n1, n2)`` the unknown with multi-index ``(i, j, k)`` has number
``(i * n1 + j) * n2 + k``, i.e. ``np.ravel_multi_index((i, j, k), shape)``. A
field ``u`` of that shape maps to the vector ``u.ravel()`` and back with
``v.reshape(shape)``. :func:`grid_points` lists coordinates in the same order.

Boundary conditions, per axis
-----------------------------
``"dirichlet"``
    ``n`` interior unknowns ``x_i = i h``, ``i = 1..n``, with ``h = 1 / (n + 1)``
    by default; the (homogeneous) boundary values ``x_0`` and ``x_{n+1}`` are
    eliminated. The operator is symmetric negative definite.
``"periodic"``
    ``n`` points ``x_i = i h``, ``i = 0..n-1``, with ``h = 1 / n`` by default;
    neighbours wrap around. The operator is symmetric negative semi-definite
    (constants are its null space), and every row sums to zero.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from ..errors import InputError, plain

__all__ = ["BCS", "grid_points", "laplacian", "second_difference"]

#: Boundary conditions understood per axis.
BCS = ("dirichlet", "periodic")


def _axes(shape, spacing, bc) -> list[tuple[int, float, str]]:
    """Normalise ``shape``, ``spacing`` and ``bc`` to one ``(n, h, bc)`` per axis."""
    dims = (shape,) if np.ndim(shape) == 0 else tuple(shape)
    if not 1 <= len(dims) <= 3:
        raise InputError(f"shape must be an int or a tuple of 1 to 3 ints, got {plain(shape)!r}")
    if not all(isinstance(n, int | np.integer) and n >= 1 for n in dims):
        raise InputError(f"shape entries must be integers >= 1, got {plain(shape)!r}")
    ndim = len(dims)

    bcs = (bc,) * ndim if isinstance(bc, str) else tuple(bc)
    if len(bcs) != ndim or any(b not in BCS for b in bcs):
        raise InputError(f"bc must be one of {BCS} or a tuple of them per axis, got {plain(bc)!r}")

    if spacing is None:
        hs = tuple(1.0 / (n + 1 if b == "dirichlet" else n) for n, b in zip(dims, bcs, strict=True))
    else:
        hs = (spacing,) * ndim if np.ndim(spacing) == 0 else tuple(spacing)
        if len(hs) != ndim or not all(np.isfinite(h) and h > 0 for h in hs):
            raise InputError(
                f"spacing must be a positive number or one per axis ({ndim}), "
                f"got {plain(spacing)!r}"
            )
    return [(int(n), float(h), b) for n, h, b in zip(dims, hs, bcs, strict=True)]


def second_difference(n: int, h: float, bc: str = "dirichlet") -> sp.csr_matrix:
    """Return the 1D second-difference matrix ``(u[i-1] - 2 u[i] + u[i+1]) / h**2``.

    Parameters
    ----------
    n : int
        Number of unknowns.
    h : float
        Grid spacing.
    bc : {"dirichlet", "periodic"}
        ``"dirichlet"`` drops the neighbours outside ``0..n-1`` (zero boundary
        values); ``"periodic"`` wraps them around.

    Returns
    -------
    scipy.sparse.csr_matrix
        ``n x n``, float64.
    """
    ((n, h, bc),) = _axes(n, h, bc)
    i = np.arange(n)
    rows = np.concatenate([i, i, i])
    cols = np.concatenate([i, i - 1, i + 1])
    vals = np.concatenate([np.full(n, -2.0), np.ones(n), np.ones(n)]) / h**2
    if bc == "periodic":
        cols %= n  # duplicates (n <= 2) are summed by the COO -> CSR conversion
    else:
        inside = (cols >= 0) & (cols < n)
        rows, cols, vals = rows[inside], cols[inside], vals[inside]
    return sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()


def laplacian(
    shape: int | Sequence[int],
    spacing: float | Sequence[float] | None = None,
    bc: str | Sequence[str] = "dirichlet",
) -> sp.csr_matrix:
    """Return the second-order finite-difference Laplacian on a structured grid.

    Parameters
    ----------
    shape : int or tuple of int
        Unknowns per axis (1 to 3 axes): interior points for Dirichlet axes,
        grid points for periodic ones.
    spacing : float or tuple of float, optional
        Grid spacing per axis; defaults to ``1 / (n + 1)`` (Dirichlet) or
        ``1 / n`` (periodic), i.e. the unit interval, square or cube.
    bc : str or tuple of str, optional
        ``"dirichlet"`` (default) or ``"periodic"``, for all axes or one per axis.

    Returns
    -------
    scipy.sparse.csr_matrix
        ``N x N`` with ``N = prod(shape)``, float64, symmetric, unknowns in C
        order (see the module docstring). Negative definite when any axis is
        Dirichlet, negative semi-definite when all are periodic.

    Notes
    -----
    ``L = sum_d I_(n_0...n_(d-1)) (x) D_d (x) I_(n_(d+1)...)``, the Kronecker sum
    of the 1D matrices :func:`second_difference`; with C order the first factor
    is the slowest axis.
    """
    axes = _axes(shape, spacing, bc)
    sizes = [n for n, _, _ in axes]
    total = sp.csr_matrix((int(np.prod(sizes)),) * 2)
    for d, (n, h, b) in enumerate(axes):
        before = sp.identity(int(np.prod(sizes[:d])), format="csr")
        after = sp.identity(int(np.prod(sizes[d + 1 :])), format="csr")
        total = total + sp.kron(sp.kron(before, second_difference(n, h, b)), after)
    total = sp.csr_matrix(total, dtype=np.float64)
    total.sum_duplicates()
    total.sort_indices()
    return total


def grid_points(
    shape: int | Sequence[int],
    spacing: float | Sequence[float] | None = None,
    bc: str | Sequence[str] = "dirichlet",
) -> np.ndarray:
    """Return the coordinates of the unknowns of :func:`laplacian`.

    Parameters
    ----------
    shape, spacing, bc
        As for :func:`laplacian`.

    Returns
    -------
    numpy.ndarray
        Shape ``(ndim, N)``, the scikit-fem convention (``x[0]`` is the first
        coordinate of every point), points in C order. Along a Dirichlet axis
        ``x_i = i h`` for ``i = 1..n``; along a periodic axis ``x_i = i h`` for
        ``i = 0..n-1``.
    """
    axes = _axes(shape, spacing, bc)
    ticks = [h * (np.arange(n) + (b == "dirichlet")) for n, h, b in axes]
    grids = np.meshgrid(*ticks, indexing="ij")
    return np.stack([g.ravel() for g in grids])
