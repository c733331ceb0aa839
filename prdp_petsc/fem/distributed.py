"""A parametric operator A(θ) = a₀ + Gθ of which every rank holds only its own rows.

The owned-layout counterpart of `prdp_petsc.fem.parametric.ParametricMatrix`:
each rank assembles its piece of a `prdp_petsc.fem.partition.PartitionedMesh`
with scikit-fem (any `ParametricMatrix` built on ``part.mesh``: `from_form`,
`diffusion_operator`, plus constant matrices) and keeps

* the rows of the vertices it owns, complete because the local mesh holds every
  element around them, as a `ParametricMatrix` of shape (owned rows × local
  columns), its columns the owned vertices and then the ghost ones;
* the part of G that maps the θ of its local elements (owned and ghost) to those
  rows; θ of the ghost elements comes from their owners by a halo exchange.

So with ``x`` and ``λ`` this rank's rows, a new θ, a product or a gradient
costs one ghost exchange (`prdp_petsc.core.ghosts.GhostedSpace`) and local
sparse products:

* ``values(θ) = a₀ + G θ_local``, θ_local = θ with its ghosts filled in;
* ``A v``: v's ghosts filled in, then the local product;
* ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x_local[cols])``: computed for the local elements, then
  the ghost elements' contributions added to their owners' (reverse exchange);
* ``Aᵀ w``: the local transpose product, the ghost columns added to their owners.

No array of global length exists on any rank.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..core.ghosts import GhostedSpace, exclusive_offset
from ..core.operator import OwnedCSR
from ..core.ownership import own
from ..errors import InputError, NonFiniteError
from .parametric import ParametricMatrix

if TYPE_CHECKING:
    from .partition import PartitionedMesh

__all__ = ["DistributedParametricMatrix"]


class DistributedParametricMatrix:
    """This rank's rows of ``A(θ) = a₀ + G θ`` (the owned layout; see the module notes).

    Parameters
    ----------
    local : ParametricMatrix
        Shape (``rows.owned``, ``cols.local_size``): the owned rows, columns in
        the local order of `cols`; its θ in the local order of `params`.
    rows, cols : GhostedSpace
        Row and column index spaces (the same object for a square operator).
    params : GhostedSpace
        Index space of θ.
    symmetric : bool
        Whether A(θ) = A(θ)ᵀ for every θ (decided by the caller, the same on every
        rank).

    Notes
    -----
    Made by `from_local` from an operator assembled on a partitioned mesh, and
    by `dirichlet_blocks`.  Every method that takes or returns vectors is
    collective.  θ is one vector of the owned parameters, shape
    (``params.owned``,): a batch of operators (θ of shape (B, p)) is not
    supported in this layout.
    """

    def __init__(
        self,
        local: ParametricMatrix,
        rows: GhostedSpace,
        cols: GhostedSpace,
        params: GhostedSpace,
        *,
        symmetric: bool,
    ) -> None:
        if local.shape != (rows.owned, cols.local_size) or local.n_params != params.local_size:
            raise InputError(
                f"local operator {local.shape} with {local.n_params} parameters does not fit "
                f"{rows.owned} owned rows, {cols.local_size} local columns and "
                f"{params.local_size} local parameters"
            )
        self.local, self.rows, self.cols, self.params = local, rows, cols, params
        self.symmetric = bool(symmetric)
        self.comm = rows.comm
        self.positive = local.positive
        # PETSc wants each row's global column indices sorted: keep the permutation
        global_cols = cols.global_ids[local.indices]
        self._order = np.lexsort((global_cols, local.rows))
        self._petsc_indices = np.asarray(global_cols[self._order], dtype=global_cols.dtype)
        self._petsc_indices.flags.writeable = False
        self._last: tuple | None = None

    @classmethod
    def from_local(
        cls,
        A: ParametricMatrix,
        part: PartitionedMesh,
        *,
        theta: str = "elements",
        symmetric: bool | None = None,
    ) -> DistributedParametricMatrix:
        """The owned rows of an operator assembled on ``part.mesh`` (collective).

        Parameters
        ----------
        A : ParametricMatrix
            Square, one row per local vertex (P1/Q1 unknowns on ``part.mesh``),
            e.g. ``pp.diffusion_operator(skfem.Basis(part.mesh, ElementTetP1()))``.
            Its rows of ghost vertices are incomplete and are dropped.
        part : PartitionedMesh
        theta : {"elements", "vertices"}
            Where θ lives: one entry per element (P0 coefficients) or per vertex
            (P1 coefficients).
        symmetric : bool, optional
            Declared structure; None takes ``A.is_symmetric`` (declared, or tested
            entry against mirror on the local assembly) on every rank, and-ed
            over the ranks.
        """
        spaces = {"elements": part.elements, "vertices": part.vertices}
        if theta not in spaces:
            raise InputError(f"theta must be 'elements' or 'vertices', got {theta!r}")
        params = spaces[theta]
        n = part.vertices.local_size
        if A.shape != (n, n) or A.n_params != params.local_size:
            vector = A.shape[0] % n == 0 and A.shape[0] > n
            raise InputError(
                f"A must be assembled on part.mesh with vertex dofs: shape ({n}, {n}) and "
                f"{params.local_size} parameters (one per local {theta[:-1]}), got "
                f"{A.shape} and {A.n_params}"
                + (
                    f"; {A.shape[0] // n} unknowns per vertex: the owned layout holds one "
                    "scalar unknown per mesh vertex (P1/Q1), not vector or mixed fields. "
                    "For those use the replicated layout (a scipy or ParametricMatrix "
                    "operator on every rank) or a distributed PETSc Mat of your own"
                    if vector
                    else ""
                )
            )
        if symmetric is None:
            symmetric = not _any_rank(part.comm, not A.is_symmetric)[0]
        owned = A.submatrix(np.arange(part.owned_vertices), np.arange(n))
        return cls(owned, part.vertices, part.vertices, params, symmetric=symmetric)

    # -- sizes -------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """Global shape."""
        return (self.rows.size, self.cols.size)

    @property
    def local_shape(self) -> tuple[int, int]:
        """(owned rows, owned columns): the lengths of this rank's b and x."""
        return (self.rows.owned, self.cols.owned)

    @property
    def n_params(self) -> int:
        """Number of θ entries this rank owns (the length of its θ)."""
        return self.params.owned

    @property
    def is_symmetric(self) -> bool:
        return self.symmetric

    # -- values ------------------------------------------------------------------------
    def check_theta(self, theta: np.ndarray) -> np.ndarray:
        """This rank's θ as float64, validated on every rank together (collective).

        Shape (n_params,), finite, and > 0 for a ``positive`` coefficient; a bad θ on
        any rank raises on every rank (`InputError`, `NonFiniteError`), so none is
        left waiting in a collective call.
        """
        theta = np.asarray(theta, dtype=np.float64)
        shape = theta.shape != (self.n_params,)
        finite = not shape and not np.all(np.isfinite(theta))
        negative = not (shape or finite) and self.positive and not np.all(theta > 0)
        shape, finite, negative = _any_rank(self.comm, shape, finite, negative)
        if shape:
            raise InputError(
                f"theta must hold each rank's own parameters (here {self.n_params}, shape "
                f"({self.n_params},)), got {theta.shape} on some rank; a batch of operators "
                "is not supported in the owned layout"
            )
        if finite:
            raise NonFiniteError("theta contains NaN or Inf (on some rank)")
        if negative:
            raise InputError("theta is a diffusion coefficient and must be > 0 (on some rank)")
        return theta

    def local_theta(self, theta: np.ndarray) -> np.ndarray:
        """θ of the local elements (vertices): this rank's, then the ghosts' (collective)."""
        return self.params.update(self.check_theta(theta))

    def values(self, theta: np.ndarray) -> np.ndarray:
        """Values of the owned rows, ``a0 + G θ_local``, in the local CSR order (collective).

        The last θ's values are kept: an equal θ returns the same read-only array
        after one collective comparison.
        """
        theta = np.asarray(theta, dtype=np.float64)
        last = self._last
        same = last is not None and np.array_equal(last[0], theta)
        if not _any_rank(self.comm, not same)[0]:
            return last[1]
        values = self.local.values(self.local_theta(theta))
        self._last = (theta.copy(), values)
        return values

    def owned_csr(self, theta: np.ndarray) -> OwnedCSR:
        """A(θ)'s owned rows for a `KSPSolver` (global, sorted column indices)."""
        values = self.values(theta)
        return self.csr_from_values(values)

    def csr_from_values(self, values: np.ndarray) -> OwnedCSR:
        """`OwnedCSR` of owned-row values given in the local CSR order."""
        data = own(values[self._order])
        return OwnedCSR(
            self.local.indptr,
            self._petsc_indices,
            data,
            self.shape,
            self.local_shape,
            self.comm,
            self.symmetric,
        )

    # -- products ----------------------------------------------------------------------
    def matvec(self, values: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``A v`` for this rank's entries of v (columns) → its rows (collective)."""
        return (self._local_matrix(values) @ self.cols.update(v).T).T

    def rmatvec(self, values: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``Aᵀ w`` for this rank's rows of w → its entries of the column space."""
        local = (self._local_matrix(values).T @ np.asarray(w).T).T
        return self.cols.accumulate(local)

    def theta_gradient(self, lam: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])`` for this rank's θ (collective).

        `lam` holds this rank's rows, `x` its entries of the column space, each
        ``(n,)`` or ``(B, n)`` (a batch sharing θ: contributions summed).
        """
        local = self.local.theta_gradient(np.asarray(lam), self.cols.update(x))
        return self.params.accumulate(local)

    def vjp_matvec(self, w: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``∂/∂θ ⟨w, A(θ) v⟩ = Gᵀ(w[rows] ⊙ v[cols])`` for this rank's θ (collective)."""
        return -self.theta_gradient(w, v)

    def _local_matrix(self, values: np.ndarray):
        import scipy.sparse as sp

        P = self.local
        return sp.csr_matrix((values, P.indices, P.indptr), shape=P.shape)

    # -- Dirichlet elimination ---------------------------------------------------------
    def dirichlet_blocks(self, boundary: np.ndarray) -> tuple:
        """``A_II``, ``A_IB`` and this rank's interior and boundary row positions (collective).

        Parameters
        ----------
        boundary : array of int
            Global indices of Dirichlet dofs; those this rank owns are used (each
            rank may pass its own, or all).

        Returns
        -------
        A_II, A_IB : DistributedParametricMatrix
            Interior rows by interior (boundary) columns, on new index spaces that
            number this rank's interior (boundary) dofs contiguously in rank order.
        interior, boundary : ndarray
            Positions, among this rank's rows, of its interior and boundary dofs.
        """
        if self.rows is not self.cols:
            raise InputError("Dirichlet elimination needs a square operator (rows are cols)")
        space = self.rows
        boundary = np.asarray(boundary, dtype=np.int64).ravel()
        if boundary.size and (boundary.min() < 0 or boundary.max() >= space.size):
            raise InputError(f"boundary indices must lie in [0, {space.size})")
        mine = boundary[(boundary >= space.start) & (boundary < space.end)] - space.start
        flag = np.zeros(space.owned)
        flag[mine] = 1.0
        is_boundary = space.update(flag) > 0.5  # every local column: boundary or not
        interior_space, interior_cols = _subspace(space, ~is_boundary)
        boundary_space, boundary_cols = _subspace(space, is_boundary)
        interior_rows = np.flatnonzero(~is_boundary[: space.owned])
        owned_boundary = np.flatnonzero(is_boundary[: space.owned])
        blocks = []
        for cols, col_space in ((interior_cols, interior_space), (boundary_cols, boundary_space)):
            local = self.local.submatrix(interior_rows, cols)
            blocks.append(
                DistributedParametricMatrix(
                    local,
                    interior_space,
                    col_space,
                    self.params,
                    symmetric=self.symmetric and col_space is interior_space,
                )
            )
        return blocks[0], blocks[1], interior_rows, owned_boundary

    def __repr__(self) -> str:
        return (
            f"DistributedParametricMatrix(shape={self.shape}, local_shape={self.local_shape}, "
            f"n_params={self.n_params} of {self.params.size})"
        )


def _subspace(space: GhostedSpace, keep: np.ndarray) -> tuple[GhostedSpace, np.ndarray]:
    """The index space of the local entries where `keep` (local length) holds, renumbered
    contiguously per rank, and the local positions of those entries (collective)."""
    owned_keep = keep[: space.owned]
    count = int(owned_keep.sum())
    start, _ = exclusive_offset(count, space.comm)
    new = np.full(space.owned, -1.0)
    new[owned_keep] = start + np.arange(count)
    numbers = space.update(new)  # ghosts learn their new number from their owners
    positions = np.flatnonzero(keep)  # owned ones first, then ghosts: the local order
    ghosts = numbers[positions[positions >= space.owned]].astype(np.int64)
    return GhostedSpace(count, ghosts, space.comm), positions


def _any_rank(comm, *flags: bool) -> list[bool]:
    """Each of `flags` or-ed over the ranks (one ``MPI_Allreduce``)."""
    if comm.getSize() == 1:
        return [bool(f) for f in flags]
    from mpi4py import MPI  # the owned layout on several ranks needs mpi4py

    values = np.array(flags, dtype=np.int8)
    comm.tompi4py().Allreduce(MPI.IN_PLACE, values, op=MPI.MAX)
    return [bool(v) for v in values]
