"""Incompressible Navier–Stokes on a periodic MAC (staggered) grid, finite differences.

One implicit Euler step with one Picard linearisation about the previous velocity
(the advecting "wind" a = uⁿ) and first-order upwind advection,

    uⁿ⁺¹/Δt + (a·∇)uⁿ⁺¹ − ν Δuⁿ⁺¹ + ∇pⁿ⁺¹ = uⁿ/Δt,      ∇·uⁿ⁺¹ = 0,

is one monolithic linear system in (u, v, p) on the periodic unit square with N × N
cells of width h = 1/N.  Layout (arrays ``[j, i]``, axis −1 is x, axis −2 is y):
``p[j, i]`` at the cell centre ((i + ½)h, (j + ½)h), ``u[j, i]`` on the cell's right
face ((i + 1)h, (j + ½)h), ``v[j, i]`` on its top face ((i + ½)h, (j + 1)h).  The
pressure gradient is the forward difference, the divergence the backward one, so
the gradient is minus the transpose of the divergence and constant pressures are
the null space of the operator and of its transpose.  The unknowns are ordered
``[u, v, p]`` (each row-major), n = 3N².

Upwind advection makes every entry linear in a⁺ = max(a, 0) and a⁻ = min(a, 0)
of the wind at the face, so the operator is a `ParametricMatrix`
``A(θ) = A₀ + G θ`` with θ = [a⁺; a⁻].  The wind itself is linear in the state,
a = W s (`wind_matrix`): the wind at a u-face is (u, v̄) with v̄ the mean of the
four surrounding v's, at a v-face (ū, v) likewise.  A torch caller computes
θ = [relu(W s); −relu(−W s)] under autograd, so gradients flow into the previous
velocity through the operator; `picard_parameters` is the numpy version.
Like the rest of this layer, nothing here imports torch or PETSc.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from prdp_petsc import InputError, ParametricMatrix
from prdp_petsc.fem.parametric import csr_pattern

__all__ = [
    "divergence",
    "from_streamfunction",
    "ns_operator",
    "nullspace",
    "picard_parameters",
    "random_states",
    "restrict",
    "rhs_scale",
    "simulate",
    "solve_direct",
    "wind_matrix",
]


def _index(n: int) -> np.ndarray:
    return np.arange(n * n).reshape(n, n)


def _shift(idx: np.ndarray, dj: int, di: int) -> np.ndarray:
    """Index of the neighbour at (j + dj, i + di), periodic."""
    return np.roll(idx, (-dj, -di), axis=(0, 1))


def ns_operator(n: int, dt: float, nu: float) -> ParametricMatrix:
    """The Picard-linearised implicit Euler MAC operator as ``A₀ + G θ``.

    Parameters
    ----------
    n : int
        Cells per direction (≥ 3); the system has 3n² unknowns.
    dt, nu : float
        Time step and kinematic viscosity (> 0 and ≥ 0).

    Returns
    -------
    ParametricMatrix
        Shape (3n², 3n²), 8n² parameters θ = [a⁺; a⁻], each half ordered
        [a_x at u, a_y at u, a_x at v, a_y at v] (the rows of `wind_matrix`).
    """
    if n < 3 or dt <= 0 or nu < 0:
        raise InputError(f"need n >= 3, dt > 0, nu >= 0; got n={n}, dt={dt}, nu={nu}")
    h = 1.0 / n
    m = n * n
    idx = _index(n).ravel()
    rows, cols, vals, params, coefs = [], [], [], [], []

    def add(r, c, v=0.0, param=-1, coef=0.0):
        r, c = np.broadcast_arrays(r, c)
        rows.append(r.ravel())
        cols.append(c.ravel())
        vals.append(np.broadcast_to(v, r.shape).ravel().astype(float))
        params.append(np.broadcast_to(param, r.shape).ravel())
        coefs.append(np.broadcast_to(coef, r.shape).ravel().astype(float))

    grid = _index(n)
    for block in (0, 1):  # momentum of u (block 0) and v (block 1)
        off = block * m
        r = off + idx
        add(r, r, 1.0 / dt + 4.0 * nu / h**2)
        for dj, di in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            add(r, off + _shift(grid, dj, di).ravel(), -nu / h**2)
        for axis, (dj, di) in enumerate(((0, 1), (1, 0))):  # wind component x, y
            k = (2 * block + axis) * m + idx  # parameter of a⁺; a⁻ is 4m later
            fwd = off + _shift(grid, dj, di).ravel()
            bwd = off + _shift(grid, -dj, -di).ravel()
            add(r, r, 0.0, k, 1.0 / h)  # a⁺ (u_i − u_{i−1})/h
            add(r, bwd, 0.0, k, -1.0 / h)
            add(r, r, 0.0, 4 * m + k, -1.0 / h)  # a⁻ (u_{i+1} − u_i)/h
            add(r, fwd, 0.0, 4 * m + k, 1.0 / h)
        # pressure gradient, forward difference: (p[j, i+1] − p[j, i])/h for u
        dj, di = ((0, 1), (1, 0))[block]
        add(r, 2 * m + idx, -1.0 / h)
        add(r, 2 * m + _shift(grid, dj, di).ravel(), 1.0 / h)
    # divergence, backward difference
    r = 2 * m + idx
    add(r, idx, 1.0 / h)
    add(r, _shift(grid, 0, -1).ravel(), -1.0 / h)
    add(r, m + idx, 1.0 / h)
    add(r, m + _shift(grid, -1, 0).ravel(), -1.0 / h)

    rows, cols = np.concatenate(rows), np.concatenate(cols)
    vals, params, coefs = map(np.concatenate, (vals, params, coefs))
    shape = (3 * m, 3 * m)
    indptr, indices, position = csr_pattern(rows, cols, shape)
    a0 = np.bincount(position, weights=vals, minlength=len(indices))
    has = params >= 0
    G = sp.csr_matrix((coefs[has], (position[has], params[has])), shape=(len(indices), 8 * m))
    return ParametricMatrix(indptr, indices, shape, a0, G, symmetric=False)


def wind_matrix(n: int) -> sp.csr_matrix:
    """W (4n² × 3n²) with a = W s the winds [a_x at u, a_y at u, a_x at v, a_y at v]."""
    m = n * n
    grid = _index(n)
    idx = grid.ravel()
    rows, cols = [idx, 3 * m + idx], [idx, m + idx]  # a_x at u = u, a_y at v = v
    vals = [np.ones(m), np.ones(m)]
    # v at the u-face (right face of cell (j, i)): v[j, i], v[j, i+1], v[j−1, i], v[j−1, i+1]
    for dj, di in ((0, 0), (0, 1), (-1, 0), (-1, 1)):
        rows.append(m + idx)
        cols.append(m + _shift(grid, dj, di).ravel())
        vals.append(np.full(m, 0.25))
    # u at the v-face (top face of cell (j, i)): u[j, i], u[j, i−1], u[j+1, i], u[j+1, i−1]
    for dj, di in ((0, 0), (0, -1), (1, 0), (1, -1)):
        rows.append(2 * m + idx)
        cols.append(_shift(grid, dj, di).ravel())
        vals.append(np.full(m, 0.25))
    W = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(4 * m, 3 * m)
    )
    return W


def picard_parameters(state: np.ndarray, W: sp.spmatrix) -> np.ndarray:
    """θ = [max(W s, 0); min(W s, 0)] of `ns_operator` for states (…, 3n²)."""
    a = np.asarray(W @ np.atleast_2d(state).T).T
    theta = np.concatenate([np.maximum(a, 0), np.minimum(a, 0)], axis=-1)
    return theta.reshape(*np.shape(state)[:-1], theta.shape[-1])


def rhs_scale(n: int, dt: float) -> np.ndarray:
    """The right-hand side is ``b = rhs_scale * s`` = [uⁿ/Δt, vⁿ/Δt, 0] (elementwise)."""
    return np.concatenate([np.full(2 * n * n, 1.0 / dt), np.zeros(n * n)])


def nullspace(n: int) -> np.ndarray:
    """The constant-pressure null vector (1, 3n²) of the operator and of its transpose."""
    vec = np.zeros((1, 3 * n * n))
    vec[0, 2 * n * n :] = 1.0
    return vec


def divergence(state: np.ndarray, n: int) -> np.ndarray:
    """Discrete divergence (…, n, n) of states (…, 3n²) (cell-centred, backward differences)."""
    s = np.asarray(state).reshape(*np.shape(state)[:-1], 3, n, n)
    u, v = s[..., 0, :, :], s[..., 1, :, :]
    return (u - np.roll(u, 1, -1) + v - np.roll(v, 1, -2)) * n


def from_streamfunction(psi: np.ndarray) -> np.ndarray:
    """Discretely divergence-free states (…, 3n²) from ψ at the cell corners (…, n, n).

    ψ[j, i] sits at the top-right corner of cell (j, i); u = ∂ψ/∂y, v = −∂ψ/∂x,
    pressure zero.
    """
    n = psi.shape[-1]
    u = (psi - np.roll(psi, 1, -2)) * n
    v = -(psi - np.roll(psi, 1, -1)) * n
    out = np.stack([u, v, np.zeros_like(psi)], axis=-3)
    return out.reshape(*psi.shape[:-2], 3 * n * n)


def restrict(state: np.ndarray, n_fine: int) -> np.ndarray:
    """Fine states (…, 3n_f²) on a grid twice as coarse (n_f even): face averages.

    A coarse face value is the mean of the two fine faces that tile it, the coarse
    pressure the mean of the four fine cells, so the coarse divergence of a cell
    is the mean of its four fine divergences: divergence-free stays divergence-free.
    """
    if n_fine % 2:
        raise InputError(f"n_fine must be even, got {n_fine}")
    s = np.asarray(state).reshape(*np.shape(state)[:-1], 3, n_fine, n_fine)
    u, v, p = s[..., 0, :, :], s[..., 1, :, :], s[..., 2, :, :]
    uc = (u[..., 0::2, 1::2] + u[..., 1::2, 1::2]) / 2
    vc = (v[..., 1::2, 0::2] + v[..., 1::2, 1::2]) / 2
    pc = (p[..., 0::2, 0::2] + p[..., 0::2, 1::2] + p[..., 1::2, 0::2] + p[..., 1::2, 1::2]) / 4
    nc = n_fine // 2
    return np.stack([uc, vc, pc], axis=-3).reshape(*np.shape(state)[:-1], 3 * nc * nc)


def solve_direct(A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """Direct solve of the singular MAC system: the solution with zero-mean pressure.

    The continuity rows sum to zero, so one of them is redundant for a compatible
    b (zero-sum continuity right-hand side): it is replaced by ``p₀ = 0``, which makes
    the matrix nonsingular and keeps it sparse; the mean pressure is then removed,
    which gives the minimum-norm solution Krylov methods with the null space
    attached return.  `b` is (n,) or (B, n).
    """
    n = A.shape[0]
    m = n // 3
    A = sp.csr_matrix(A, copy=True).tolil()
    A.rows[2 * m] = [2 * m]
    A.data[2 * m] = [1.0]
    lu = spla.splu(A.tocsc())
    b2 = np.array(np.atleast_2d(b), dtype=np.float64)
    b2[:, 2 * m] = 0.0
    x = lu.solve(b2.T).T
    x[:, 2 * m :] -= x[:, 2 * m :].mean(axis=1, keepdims=True)
    return x.reshape(np.shape(b))


def simulate(state: np.ndarray, n: int, dt: float, nu: float, steps: int) -> np.ndarray:
    """Trajectories (steps + 1, count, 3n²) from states (count, 3n²), direct solves."""
    A, W, scale = ns_operator(n, dt, nu), wind_matrix(n), rhs_scale(n, dt)
    traj = [state]
    for _ in range(steps):
        theta, b = picard_parameters(traj[-1], W), traj[-1] * scale
        traj.append(np.stack([solve_direct(A.matrix(t), r) for t, r in zip(theta, b, strict=True)]))
    return np.stack(traj)


def random_states(n: int, count: int, rng: np.random.Generator, decay: float = 0.12):
    """``count`` smooth random divergence-free states (count, 3n²), velocity std 1.

    The stream function has random Fourier coefficients with amplitude
    ``exp(−decay |k|²)/|k|`` (k the integer wavenumber), so the velocity spectrum
    falls like ``exp(−decay |k|²)``; the pressure is zero.
    """
    k = np.fft.fftfreq(n, 1.0 / n)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    amplitude = np.where(k2 > 0, np.exp(-decay * k2) / np.sqrt(np.maximum(k2, 1)), 0.0)
    noise = rng.standard_normal((count, n, n)) + 1j * rng.standard_normal((count, n, n))
    states = from_streamfunction(np.fft.ifft2(noise * amplitude).real)
    velocity = states.reshape(count, 3, -1)[:, :2]
    return states / velocity.std(axis=(1, 2))[:, None]
