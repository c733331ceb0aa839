"""Dirichlet conditions by elimination with lifting, differentiable in the boundary values.

For a system ``A(θ) u = f`` with prescribed values ``u_B = g`` on boundary
degrees of freedom B and unknowns I, the interior solve is

    A_II(θ) u_I = f_I − A_IB(θ) g.

`Dirichlet` splits a `ParametricMatrix` (or a scipy matrix) into ``A_II`` and
``A_IB`` once; `Dirichlet.solve` returns the full vector and is differentiable
in f, g and θ: the gradient with respect to g is ``−A_IBᵀ λ`` from the same
adjoint solve, computed by autograd through `prdp_petsc.autograd.bridge.matvec`.
θ of shape (B, p) gives every sample its own operator (``A_II(θ_i)``, ``A_IB(θ_i)``).

With a `prdp_petsc.fem.distributed.DistributedParametricMatrix` (the owned layout)
every rank eliminates its own boundary rows: f, g, θ and the solution hold this
rank's entries, and the interior and boundary dofs are numbered contiguously per
rank (`DistributedParametricMatrix.dirichlet_blocks`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp
import torch

from ..core.solution import LinearSolution
from ..core.solver import KSPSolver
from ..errors import InputError
from ..fem.distributed import DistributedParametricMatrix
from ..fem.parametric import ParametricMatrix
from .bridge import ConstMatVec, matvec, solve
from .tensors import check_tensor

__all__ = ["Dirichlet"]


class Dirichlet:
    """Elimination of boundary degrees of freedom.

    Parameters
    ----------
    A : ParametricMatrix, DistributedParametricMatrix or scipy.sparse matrix
        The full operator (all degrees of freedom).
    boundary : array of int
        Indices of the Dirichlet degrees of freedom (e.g. ``basis.get_dofs()``), each
        once.  The boundary values ``g`` are read **in this order**: ``g[j]`` is the
        value at ``boundary[j]``.  For a `DistributedParametricMatrix` global indices,
        increasing, of which each rank uses those it owns
        (``part.boundary_vertices()``); ``g`` then holds this rank's values in that
        order.

    Attributes
    ----------
    interior, boundary : ndarray
        Indices of the unknowns (increasing) and of the Dirichlet dofs (the caller's
        order): in the owned layout their positions among this rank's rows, so ``g``
        has ``len(boundary)`` entries on each rank.

    Raises
    ------
    InputError
        For an index outside the operator, a repeated index, or (owned layout)
        indices that are not increasing.
    """

    def __init__(
        self, A: ParametricMatrix | DistributedParametricMatrix | sp.spmatrix, boundary: np.ndarray
    ) -> None:
        boundary = _indices(boundary, A.shape[0])
        self._indices: dict = {}  # (which, device) -> index tensor, made once (`_index`)
        if isinstance(A, DistributedParametricMatrix):  # collective
            if np.any(np.diff(boundary) < 0):
                raise InputError(
                    "boundary indices of a DistributedParametricMatrix must be increasing "
                    "(g holds this rank's values in that order): pass np.sort(boundary) "
                    "and g in the same order"
                )
            self.A_II, self.A_IB, self.interior, self.boundary = A.dirichlet_blocks(boundary)
            self.n = A.local_shape[0]
            return
        n = A.shape[0]
        self.boundary = boundary  # the caller's order: g[j] is the value at boundary[j]
        self.interior = np.setdiff1d(np.arange(n), self.boundary)
        self.n = n
        if isinstance(A, ParametricMatrix):
            self.A_II = A.submatrix(self.interior, self.interior)
            self.A_IB = A.submatrix(self.interior, self.boundary)
        else:
            A = sp.csr_matrix(A)
            self.A_II = A[self.interior][:, self.interior].tocsr()
            self.A_IB = A[self.interior][:, self.boundary].tocsr()

    def rhs(
        self, f: torch.Tensor, g: torch.Tensor, theta: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Interior right-hand side ``f_I − A_IB(θ) g`` (differentiable).

        `f` is (n,) or (B, n), `g` is (n_B,) or (B, n_B).  With θ of shape (B, p)
        (one operator per sample) a shared f or g is used by every sample and the
        result is (B, n_I): row i is ``f_I − A_IB(θ_i) g_i``.
        """
        self._check_theta(theta)
        check_tensor(f, self.n, "f")  # where it lives: no host copy of a GPU tensor
        check_tensor(g, len(self.boundary), "g")
        f_i = f[..., self._index("interior", f.device)]
        if not isinstance(self.A_IB, ParametricMatrix | DistributedParametricMatrix):
            return f_i - ConstMatVec.apply(g, self.A_IB).to(f.device)
        if isinstance(theta, torch.Tensor) and theta.ndim == 2:  # one operator per sample
            batch = len(theta)
            for name, t in (("f", f), ("g", g)):
                if t.ndim == 2 and len(t) != batch:
                    raise InputError(
                        f"{name} has batch size {len(t)} but theta has {batch}; pass {name} "
                        f"of shape ({batch}, {t.shape[-1]}) or ({t.shape[-1]},)"
                    )
            g = g.expand(batch, -1)
        return f_i - matvec(self.A_IB, g, theta=theta)

    def _check_theta(self, theta) -> None:
        """θ is required for a ParametricMatrix and refused otherwise, as in `solve`."""
        if isinstance(self.A_II, ParametricMatrix | DistributedParametricMatrix):
            if theta is None:
                raise InputError("A is a ParametricMatrix: pass its parameters as theta=")
        elif theta is not None:
            raise InputError("theta= is only meaningful for a ParametricMatrix A")

    def expand(self, u_i: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """Full vector with ``u[I] = u_i`` and ``u[B] = g``."""
        u = torch.zeros(*u_i.shape[:-1], self.n, dtype=u_i.dtype, device=u_i.device)
        u = _scatter(u, self._index("interior", u.device), u_i)
        return _scatter(u, self._index("boundary", u.device), g.expand(*u_i.shape[:-1], -1))

    def _index(self, which: str, device: torch.device) -> torch.Tensor:
        """`interior` or `boundary` as an index tensor on `device`, made once per device."""
        key = (which, device)
        if key not in self._indices:
            self._indices[key] = torch.from_numpy(getattr(self, which)).to(device)
        return self._indices[key]

    def solve(
        self,
        f: torch.Tensor,
        g: torch.Tensor,
        solver: KSPSolver,
        *,
        theta: torch.Tensor | None = None,
        mode: str = "implicit",
        return_solution: bool = False,
    ) -> torch.Tensor | LinearSolution:
        """Solve with ``u_B = g``; returns the full vector, differentiable in f, g, θ.

        θ of shape (B, p) solves a batch of operators, one per sample (see
        `prdp_petsc.autograd.bridge.solve`); f and g may then be shared or per
        sample, as in `rhs`.  θ with a scipy matrix raises ValueError, as in `solve`.
        ``return_solution=True`` returns the interior solve's `LinearSolution` with the
        full vector as its ``value``.
        """
        rhs = self.rhs(f, g, theta)
        if not return_solution:
            return self.expand(solve(self.A_II, rhs, solver, theta=theta, mode=mode), g)
        sol = solve(self.A_II, rhs, solver, theta=theta, mode=mode, return_solution=True)
        return replace(sol, value=self.expand(sol.value, g))


def _indices(boundary, n: int) -> np.ndarray:
    """`boundary` as int64 indices in the caller's order; out-of-range or repeated
    indices raise `InputError` (a repeat would leave g's entries ambiguous)."""
    raw = np.asarray(boundary).ravel()
    if raw.size and not np.issubdtype(raw.dtype, np.integer):
        raise InputError(f"boundary must hold integer indices, got dtype {raw.dtype}")
    idx = raw.astype(np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise InputError(f"boundary indices must lie in [0, {n})")
    unique, counts = np.unique(idx, return_counts=True)
    if len(unique) != len(idx):
        repeated = unique[counts > 1][:5].tolist()
        raise InputError(
            f"boundary repeats indices {repeated}: give each Dirichlet dof once (g[j] is "
            "the value at boundary[j])"
        )
    return idx


def _scatter(u: torch.Tensor, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    return u.scatter(-1, index.expand(*values.shape[:-1], -1), values)
