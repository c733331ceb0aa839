"""The PETSc Mat behind a `KSPSolver`, kept in step with the caller's operator.

One class per operator layout, behind one interface (`OperatorLayout`: `update`
returns a `Change`; ``mat``, ``csr``, ``norm``, ``symmetric``, ``arrays``,
``destroy``): `ReplicatedCSR` (a CSR matrix every rank holds in full), `CallerMat` (a
caller's PETSc Mat, used as given), `OwnedRows` (this rank's rows, `OwnedCSR`) and
`DeviceCSR` (a CSR pattern with values in DLPack memory, `DLPackCSR`, set on a Mat of
the solver's ``mat_type`` by COO assembly).  `layout_for` picks the class once per
operator kind.

On the device path (a solver whose options name ``vec_type``/``mat_type``,
`prdp_petsc.core.device`) every Mat made here is of the solver's ``mat_type`` with
its ``vec_type``: a scipy operator's values are host memory and reach such a Mat once
per change of values (PETSc copies them to the device at assembly); a `DLPackCSR`'s
values are set from the memory they are in, device memory included, so a new θ
never crosses to the host.

A scipy CSR matrix (or a tuple ``(indptr, indices, data, shape)``) becomes a
``MATAIJ`` once (sequential, or on a larger communicator an MPIAIJ that holds
this rank's rows of the full CSR matrix every rank passes: see
`prdp_petsc.core.parallel`); later operators with the same pattern only update its values
(``MatSetValuesCSR``), and operators with unchanged values change nothing, so
PETSc sets the preconditioner up again only when the values really changed.
Symmetry decides which maths the adjoint runs, so it is declared by the caller
where known, otherwise tested entry against mirror whenever the values change.

What is kept, and what is copied (the operator contract: an autograd backward uses
exactly the operator its forward used, whatever the caller does in between).  The
values are kept as an array nobody can change: the library's own when it made them
(`own`: the values a `~prdp_petsc.fem.parametric.ParametricMatrix` computes for θ),
otherwise a copy made when the values change, never per call (a caller's read-only
array may have writeable views, so it is copied too).  The pattern is kept the same way, a copy
made once per new pattern.  An array is never edited in place once kept: new values
replace it.  `ReplicatedCSR.csr` hands out these arrays, so a backward that holds them
can set its operator again after another solve replaced it, at no extra copy; an
unchanged caller's matrix passed again costs one comparison of its values (by
identity, without a pass, when the library owns them).  The comparison is needed
anyway (it decides whether the PC is set up again), so a snapshot per call would
only add a copy, and a hash would cost the same pass as the comparison.  The
caller's pattern arrays are recognised by identity (a structure edited in place,
``A.indices[...] = ...``, is not detected; the kept copy, which a backward uses,
is unaffected).

A block size (the d unknowns of a node of a d-dimensional vector field) is given
to every Mat made here (``MatSetBlockSize``), and the rows of the replicated
layout are split between the ranks by whole blocks; a caller's Mat gets it too.

An `OwnedCSR` holds only this rank's rows of a distributed matrix (the *owned*
layout of `prdp_petsc.core.parallel`); it becomes an MPIAIJ Mat built from those
rows alone, and later values with the same pattern are set the same way.  Every
rank then decides together (one small ``MPI_Allreduce``) whether the Mat is new,
has new values or is unchanged, since each of those steps is collective.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from ..errors import InputError, NonFiniteError
from .device import DeviceTypes, nonfinite, set_values_coo, wrap
from .ownership import immutable, own
from .parallel import ownership_range
from .safeguards import operator_norm
from .sparsity import DIAGONAL_RTOL, csr_symmetric, transpose_permutation

__all__ = [
    "LAYOUTS",
    "CallerMat",
    "Change",
    "DLPackCSR",
    "DeviceCSR",
    "OperatorLayout",
    "OwnedCSR",
    "OwnedRows",
    "ReplicatedCSR",
    "as_csr",
    "frozen_csr",
    "layout_for",
]


def as_csr(A, *, finite: bool = True) -> tuple:
    """``(indptr, indices, data, shape)`` of a scipy matrix or such a tuple (validated).

    `finite`: also refuse NaN or Inf values (`NonFiniteError`); `ReplicatedCSR.update`
    tests only values it has not seen, so an unchanged operator costs no pass.
    """
    if isinstance(A, tuple):
        indptr, indices, data, shape = A
    else:
        if not sp.issparse(A):
            raise TypeError(f"A must be a scipy sparse matrix or PETSc.Mat, got {type(A)}")
        A = A.tocsr()
        if not A.has_sorted_indices:
            A = A.sorted_indices()
        indptr, indices, data, shape = A.indptr, A.indices, A.data, A.shape
    if shape[0] != shape[1]:
        raise InputError(f"A must be square, got shape {shape}")
    data = np.asarray(data, dtype=np.float64)
    if finite:
        check_values(data)
    return indptr, indices, data, tuple(shape)


def check_values(data: np.ndarray) -> None:
    """`NonFiniteError` if the operator's values hold NaN or Inf (a sum first: no temporary)."""
    if not (np.isfinite(data.sum()) or np.all(np.isfinite(data))):
        raise NonFiniteError("A has NaN or Inf entries")


def _kept(arr, dtype=None) -> np.ndarray:
    """`arr` itself if the library owns it (and it is of `dtype`), else a copy it owns."""
    out = np.asarray(arr, dtype=dtype)
    if out is arr and immutable(out):
        return out
    if out is arr or out.base is not None:  # not a fresh conversion of our own
        out = np.array(out, copy=True)
    return own(out)


_CHUNK = 1 << 16  # a 64 KiB temporary at most


def equal(a: np.ndarray, b: np.ndarray) -> bool:
    """``np.array_equal`` in chunks: no temporary of the arrays' size, and an early exit
    at the first chunk that differs (new values usually differ everywhere)."""
    if a is b:
        return True
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        return False
    a, b = a.reshape(-1), b.reshape(-1)
    for start in range(0, a.size, _CHUNK):
        end = start + _CHUNK
        if not np.array_equal(a[start:end], b[start:end]):
            return False
    return True


def frozen_csr(A) -> tuple:
    """`as_csr` of `A` as arrays the caller cannot change afterwards: the arrays
    themselves where the library owns them (`prdp_petsc.core.ownership`), copies of
    the others.

    The implicit solve does not need this (the solver keeps the forward's operator,
    `ReplicatedCSR.csr`); a constant matrix product whose backward needs the forward's
    matrix does.
    """
    indptr, indices, data, shape = as_csr(A)
    return (_kept(indptr), _kept(indices), _kept(data), shape)


@dataclass(frozen=True, eq=False)
class OwnedCSR:
    """This rank's rows of a distributed sparse matrix: the owned layout's operator.

    Parameters
    ----------
    indptr : ndarray
        Row pointers of the owned rows (``local_shape[0] + 1`` entries).
    indices : ndarray
        *Global* column indices, sorted within each row.
    data : ndarray, shape (nnz,)
        Values (finite).
    shape : tuple of int
        Global shape (M, N).
    local_shape : tuple of int
        ``(m, n)``: rows this rank owns, and entries of x it owns (the column
        block of the same rank); the ranks' blocks follow each other in rank order.
    comm : PETSc.Comm
        Communicator of the distributed matrix.
    symmetric : bool, optional
        Declared structure; None: PETSc tests it (``MatIsSymmetric``) whenever the
        values change, which transposes the matrix.

    Notes
    -----
    The arrays are the caller's and are not copied: a `KSPSolver` recognises the
    same `indptr` and `indices` objects as an unchanged pattern, and compares the
    values with its own copy.  `prdp_petsc.fem.distributed.DistributedParametricMatrix`
    makes these.
    """

    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    shape: tuple
    local_shape: tuple
    comm: PETSc.Comm
    symmetric: bool | None = None

    def __post_init__(self):
        m = self.local_shape[0]
        if len(self.indptr) != m + 1 or len(self.data) != len(self.indices):
            raise InputError(
                f"OwnedCSR: indptr needs {m + 1} entries and data one per column index"
            )
        if not np.all(np.isfinite(self.data)):
            raise NonFiniteError("A has NaN or Inf entries")


class Change(Enum):
    """What `OperatorLayout.update` changed, and so what the solver must do."""

    #: a new Mat (pattern, size or communicator): attach it under the KSPs
    NEW = "new"
    #: new values in the same Mat: the PC is set up again (every `pc_lag`-th time)
    VALUES = "values"
    #: the same values, only the caller's symmetry declaration changed
    SYMMETRY = "symmetry"
    #: nothing
    NONE = "none"


class OperatorLayout:
    """One layout of the operator behind a `KSPSolver`: one PETSc Mat and what is kept of it.

    One subclass per layout (`ReplicatedCSR`, `CallerMat`, `OwnedRows`), each saying
    which operators it takes (`accepts`); `layout_for` chooses among them once per
    operator kind, so another layout (device matrices) is one more class in
    `LAYOUTS`.

    Attributes
    ----------
    mat : PETSc.Mat or None
    symmetric : bool or None
        Whether A = Aᵀ (declared, or tested on the values); None for a caller's
        Mat whose structure nobody declared.
    version : int
        Increases whenever the Mat or its values change: a caller that remembers
        it can tell in O(1) whether the Mat still holds its operator.  A new layout
        continues the count of the one it replaces.
    replicated : bool
        True when every rank holds the full operator and full-length vectors (a Mat
        made here from a CSR matrix every rank passes), False when vectors hold the
        rank's own rows.
    made_here : bool
        Whether the Mat was made here (and so cannot be edited by a caller).
    block_size : int
        Rows per block (``MatSetBlockSize``) of the Mat held here.
    """

    replicated: bool = True
    made_here: bool = True

    def __init__(
        self, comm=None, block_size: int = 1, version: int = 0, types: DeviceTypes | None = None
    ):
        self.comm = PETSc.COMM_SELF if comm is None else comm
        self.block_size = int(block_size)
        #: the solver's Mat and Vec types on the device path (None: PETSc's default AIJ)
        self.types = types
        self.mat: PETSc.Mat | None = None
        self.symmetric: bool | None = False
        self.version = version
        self._declared: bool | None = None  # the caller's word on symmetry
        self._norm: tuple[int, float] | None = None  # (version, ‖A‖) of `norm`

    @classmethod
    def accepts(cls, A) -> bool:
        """Whether operator `A` is of this layout's kind."""
        raise NotImplementedError

    def update(self, A, known_symmetric: bool | None = None) -> Change:
        """Hold operator `A` (of this layout's kind, or the Mat held); return what changed.

        `known_symmetric`: whether A = Aᵀ, if the caller knows; None to test it (or
        ask PETSc)."""
        if A is self.mat:
            return Change.NONE
        return self._update(A, known_symmetric)

    def _update(self, A, known_symmetric: bool | None) -> Change:
        raise NotImplementedError

    def csr(self) -> tuple | None:
        """``(indptr, indices, data, shape)`` of the operator held, as kept here: arrays
        nobody changes (new values replace `data`, never edit it), so a caller may hold
        them and set them again later (`update` recognises them without a comparison).
        None unless the layout keeps the full CSR matrix (`ReplicatedCSR`)."""
        return None

    def refresh_symmetry(self) -> None:
        """Ask the Mat again whether it is symmetric, where a caller may have edited it."""

    def norm(self) -> float:
        """``max(‖A‖₁, ‖A‖_∞)`` ≥ ‖A‖₂ of the current values, kept until they change
        (collective; a caller's Mat edited in place keeps its old norm)."""
        if self._norm is None or self._norm[0] != self.version:
            self._norm = (self.version, operator_norm(self.mat))
        return self._norm[1]

    def arrays(self) -> list[np.ndarray]:
        """The numpy arrays kept here (values, pattern, transpose permutation)."""
        return []

    def _typed(self, mat: PETSc.Mat) -> PETSc.Mat:
        """`mat` (made here) of the solver's types on the device path, as it is otherwise."""
        if self.types is not None:
            mat.convert(self.types.mat_type, out=mat)  # in place; the same type: nothing
            mat.setVecType(self.types.vec_type)
        return mat

    def destroy(self) -> None:
        """Free a Mat made here (a caller's Mat is left alone) and forget the operator."""
        if self.made_here and self.mat is not None:
            self.mat.destroy()
        self.mat = None

    def _redeclare(self, known_symmetric: bool | None) -> Change:
        """Unchanged values: `Change.NONE`, unless the symmetry declaration changed."""
        if known_symmetric == self._declared:
            return Change.NONE
        self._mark_symmetry(known_symmetric)
        self.version += 1
        return Change.SYMMETRY

    def _mark_symmetry(self, known_symmetric: bool | None) -> None:
        """Take the declaration, or test A = Aᵀ (`_tested_symmetric`), and tell PETSc."""
        self._declared = known_symmetric
        symmetric = self._tested_symmetric() if known_symmetric is None else known_symmetric
        self.symmetric = bool(symmetric)
        self.mat.setOption(PETSc.Mat.Option.SYMMETRIC, self.symmetric)

    def _tested_symmetric(self) -> bool:
        raise NotImplementedError


class _KeptCSR(OperatorLayout):
    """What the layouts whose Mat is made here from CSR arrays share: the kept values
    and pattern, and the caller's pattern arrays recognised by identity."""

    def __init__(self, comm=None, block_size: int = 1, version: int = 0, types=None):
        super().__init__(comm, block_size, version, types)
        self._indptr: np.ndarray | None = None  # the pattern as kept, PETSc ints
        self._indices: np.ndarray | None = None
        self._source: tuple | None = None  # the caller's (indptr, indices), for an `is` test
        self._values: np.ndarray | None = None  # the library's own, or a copy it owns

    def arrays(self) -> list[np.ndarray]:
        kept = [self._values, self._indptr, self._indices]
        return [a for a in kept if a is not None]

    def destroy(self) -> None:
        super().destroy()
        self._indptr = self._indices = self._source = self._values = None


class ReplicatedCSR(_KeptCSR):
    """A scipy CSR matrix (or ``(indptr, indices, data, shape)``) every rank holds in
    full, as a ``MATAIJ`` made here: sequential, or on a larger communicator an MPIAIJ
    holding this rank's rows (split by whole blocks; `prdp_petsc.core.parallel`).
    Symmetry is declared or tested entry against mirror."""

    def __init__(self, comm=None, block_size: int = 1, version: int = 0, types=None):
        super().__init__(comm, block_size, version, types)
        self._shape: tuple | None = None
        self._tperm: np.ndarray | None = None

    @classmethod
    def accepts(cls, A) -> bool:
        return isinstance(A, tuple) or sp.issparse(A)

    def _update(self, A, known_symmetric: bool | None) -> Change:
        if isinstance(A, tuple) and A[2] is self._values and self._known(A[0], A[1]):
            # the values kept (the library's own): this operator's `csr`, or values the
            # library made and set last; nothing to compare
            return self._redeclare(known_symmetric)
        indptr, indices, data, shape = as_csr(A, finite=False)
        if self._same_pattern(indptr, indices, shape):
            # compare with the kept values: the caller may have changed `data` in place
            if equal(data, self._values):
                return self._redeclare(known_symmetric)  # kept values were tested finite
            check_values(data)
            self._set_values(data)
            self._values = _kept(data)  # replaced, never edited: a backward may hold it
            self._source = (indptr, indices)
            self._mark_symmetry(known_symmetric)
            self.version += 1
            return Change.VALUES
        check_values(data)
        if shape[0] % self.block_size:
            raise InputError(
                f"the operator has {shape[0]} rows, not a multiple of block_size={self.block_size}"
            )
        self.destroy()
        self._indptr, self._indices = _kept(indptr, PETSc.IntType), _kept(indices, PETSc.IntType)
        self._shape = shape
        self._make_mat(data)
        self._source = (indptr, indices)
        self._values = _kept(data)
        self._tperm = transpose_permutation(self._indptr, self._indices, shape)
        self._mark_symmetry(known_symmetric)
        self.version += 1
        return Change.NEW

    def csr(self) -> tuple | None:
        if self._indptr is None:
            return None
        return self._indptr, self._indices, self._values, self._shape

    def arrays(self) -> list[np.ndarray]:
        return [*super().arrays(), *([self._tperm] if self._tperm is not None else [])]

    def destroy(self) -> None:
        super().destroy()
        self._shape = self._tperm = None

    def _local_rows(self, data: np.ndarray) -> tuple:
        """This rank's rows of the CSR pattern and of `data` (all of them on one rank)."""
        ip, ix = self._indptr, self._indices
        if self.comm.getSize() == 1:
            return ip, ix, data
        start, end = ownership_range(self._shape[0], self.comm, self.block_size)
        lo, hi = int(ip[start]), int(ip[end])
        return ip[start : end + 1] - ip[start], ix[lo:hi], data[lo:hi]

    def _make_mat(self, data: np.ndarray) -> None:
        shape = self._shape
        ip, ix, local = self._local_rows(data)
        if self.comm.getSize() == 1:
            size = shape
        else:
            rows = len(ip) - 1
            size = ((rows, shape[0]), (rows, shape[1]))
        self.mat = PETSc.Mat().createAIJ(
            size=size, bsize=self.block_size, csr=(ip, ix, local), comm=self.comm
        )
        self.mat.assemble()
        if self.types is not None:
            self._typed(self.mat)

    def _set_values(self, data: np.ndarray) -> None:
        ip, ix, local = self._local_rows(data)
        self.mat.setValuesCSR(ip, ix, local)
        self.mat.assemble()

    def _known(self, indptr, indices) -> bool:
        """Whether (indptr, indices) are the arrays of the pattern held (no comparison)."""
        if self._indptr is None:
            return False
        return (indptr is self._source[0] and indices is self._source[1]) or (
            indptr is self._indptr and indices is self._indices
        )

    def _same_pattern(self, indptr, indices, shape) -> bool:
        if self._indptr is None or self._shape != shape:
            return False
        if self._known(indptr, indices):
            return True
        return equal(self._indptr, indptr) and equal(self._indices, indices)

    def _tested_symmetric(self) -> bool:
        """Entry against mirror, on the kept values."""
        return self._tperm is not None and csr_symmetric(
            self._indptr, self._indices, self._values, self._shape, self._tperm
        )


class CallerMat(OperatorLayout):
    """A caller's PETSc Mat, used as given (any communicator: vectors hold the rank's own
    rows).  Nothing is kept or copied: the caller may edit it, so its symmetry is asked
    again (``MatIsSymmetricKnown``) before it decides the adjoint's maths."""

    replicated = False
    made_here = False

    @classmethod
    def accepts(cls, A) -> bool:
        return isinstance(A, PETSc.Mat)

    def _update(self, A: PETSc.Mat, known_symmetric: bool | None) -> Change:
        self._set_block_size(A)
        self.destroy()
        self.mat = A
        self._declared = known_symmetric
        self.refresh_symmetry()
        self.version += 1
        return Change.NEW

    def refresh_symmetry(self) -> None:
        if self.mat is None:
            return
        if self._declared is not None:
            self.symmetric = bool(self._declared)
        else:
            known, flag = self.mat.isSymmetricKnown()
            self.symmetric = bool(flag) if known else None

    def _set_block_size(self, mat: PETSc.Mat) -> None:
        """Give a caller's Mat the block size (``MatSetBlockSize``), if it has another."""
        if self.block_size == 1 or mat.getBlockSize() == self.block_size:
            return
        try:
            mat.setBlockSize(self.block_size)
        except PETSc.Error as err:
            raise InputError(
                f"the caller's Mat has block size {mat.getBlockSize()} and PETSc refused "
                f"block_size={self.block_size} ({err}); create it with that block size "
                "(MatSetBlockSize before its preallocation)"
            ) from err


class OwnedRows(_KeptCSR):
    """This rank's rows of a distributed matrix (`OwnedCSR`, the owned layout): an MPIAIJ
    Mat made here from those rows alone.  Every rank decides together (one small
    ``MPI_Allreduce``) whether the Mat is new, has new values or is unchanged, since
    each of those steps is collective; symmetry is declared or asked of PETSc."""

    replicated = False

    def __init__(self, comm=None, block_size: int = 1, version: int = 0, types=None):
        super().__init__(comm, block_size, version, types)
        self._sizes: tuple | None = None  # (shape, local_shape) of the pattern held

    @classmethod
    def accepts(cls, A) -> bool:
        return isinstance(A, OwnedCSR)

    def _update(self, A: OwnedCSR, known_symmetric: bool | None) -> Change:
        if known_symmetric is None:
            known_symmetric = A.symmetric
        same_pattern = (
            self._indptr is not None
            and self._sizes == (A.shape, A.local_shape)
            and (
                (self._source[0] is A.indptr and self._source[1] is A.indices)
                or (
                    np.array_equal(self._indptr, A.indptr)
                    and np.array_equal(self._indices, A.indices)
                )
            )
        )
        same_values = same_pattern and equal(A.data, self._values)
        same_pattern, same_values = _all_ranks(A.comm, same_pattern, same_values)
        if same_values:
            return self._redeclare(known_symmetric)
        if same_pattern:
            self.mat.setValuesCSR(self._indptr, self._indices, A.data)
            self.mat.assemble()
        else:
            (m, n), (M, N) = A.local_shape, A.shape
            if not _all_ranks(A.comm, m % self.block_size == 0 and n % self.block_size == 0)[0]:
                raise InputError(
                    f"block_size={self.block_size} does not divide the rows of every rank "
                    f"(here {m}): the owned layout splits rows by mesh vertices, so it "
                    "carries a block size only if every rank owns whole blocks"
                )
            self.destroy()
            self._indptr = np.asarray(A.indptr, dtype=PETSc.IntType)
            self._indices = np.asarray(A.indices, dtype=PETSc.IntType)
            self._sizes = (A.shape, A.local_shape)
            self.mat = PETSc.Mat().createAIJ(
                size=((m, M), (n, N)),
                bsize=self.block_size,
                csr=(self._indptr, self._indices, A.data),
                comm=A.comm,
            )
            self.mat.assemble()
        self._source = (A.indptr, A.indices)
        self._values = _kept(A.data, np.float64)
        self._mark_symmetry(known_symmetric)
        self.version += 1
        return Change.VALUES if same_pattern else Change.NEW

    def destroy(self) -> None:
        super().destroy()
        self._sizes = None

    def _tested_symmetric(self) -> bool:
        """This rank's rows only: PETSc's ``MatIsSymmetric`` (it transposes the Mat)."""
        scale = self.mat.norm(PETSc.NormType.INFINITY)
        return self.mat.isSymmetric(DIAGONAL_RTOL * scale)


@dataclass(frozen=True, eq=False)
class DLPackCSR:
    """A CSR operator whose values live in DLPack memory (host or device): the device
    layout's operator.

    Parameters
    ----------
    indptr, indices : ndarray
        The CSR pattern on the host (sorted column indices per row), kept by identity:
        the same arrays again are the same pattern at no cost.
    data : array with ``__dlpack__``, shape (nnz,)
        The values, C-contiguous float64, in the memory of the solver's types (a torch
        tensor on the GPU for ``mat_type aijcusparse``).  Never edited by the solver;
        the caller must not edit them either while a solve may need them again (the
        same object again is taken as unchanged values, without a comparison).
    shape : tuple of int

    Notes
    -----
    `prdp_petsc.solve` makes these from a `~prdp_petsc.fem.parametric.ParametricMatrix`
    on the device path: values ``a0 + G θ`` computed by torch where θ lives.
    """

    indptr: np.ndarray
    indices: np.ndarray
    data: object
    shape: tuple


class DeviceCSR(OperatorLayout):
    """A `DLPackCSR` as a Mat of the solver's ``mat_type`` (``aij`` without device
    types) made here by COO assembly: ``MatSetPreallocationCOO`` once per pattern (host
    index arrays), then ``MatSetValuesCOO`` from the values' own memory for every new
    values object (`prdp_petsc.core.device.set_values_coo`), so values on the GPU stay
    there.

    Which values are new is decided by identity: the same `data` object is unchanged
    values (`Change.NONE`, no PC set-up), another one is new values (`Change.VALUES`),
    with no comparison of entries (that would cost a pass over device memory per
    call; the caller keeps one values object per θ).  NaN or Inf values are refused
    from one PETSc norm of the values (`NonFiniteError`).  Symmetry is declared, or
    asked of PETSc (``MatIsSymmetric``) whenever the values change.  One process.
    """

    def __init__(self, comm=None, block_size: int = 1, version: int = 0, types=None):
        super().__init__(comm, block_size, version, types)
        self._pattern: tuple | None = None  # (indptr, indices, shape) of the Mat held
        self._data = None  # the values object set last
        self._sums: PETSc.Mat | None = None  # `norm`'s row and column summing Mat

    @classmethod
    def accepts(cls, A) -> bool:
        return isinstance(A, DLPackCSR)

    def _update(self, A: DLPackCSR, known_symmetric: bool | None) -> Change:
        shape = tuple(int(n) for n in A.shape)
        held = self._pattern
        same_pattern = held is not None and (
            (held[0] is A.indptr and held[1] is A.indices and held[2] == shape)
            or (held[2] == shape and equal(held[0], A.indptr) and equal(held[1], A.indices))
        )
        if same_pattern and A.data is self._data:
            return self._redeclare(known_symmetric)
        memory = self.types.memory if self.types is not None else "cpu"
        values = wrap(A.data, len(A.indices), "the operator's values", memory)
        try:
            if nonfinite(values):
                raise NonFiniteError("A has NaN or Inf entries")
            if not same_pattern:
                self._make_mat(A, shape)
            set_values_coo(self.mat, values)
        finally:
            values.destroy()
        self._data = A.data
        self._mark_symmetry(known_symmetric)
        self.version += 1
        return Change.VALUES if same_pattern else Change.NEW

    def _make_mat(self, A: DLPackCSR, shape: tuple) -> None:
        if shape[0] != shape[1]:
            raise InputError(f"A must be square, got shape {shape}")
        if shape[0] % self.block_size:
            raise InputError(
                f"the operator has {shape[0]} rows, not a multiple of block_size={self.block_size}"
            )
        if self.comm.getSize() > 1:
            raise InputError("values in DLPack memory (the device path) run on one process")
        self.destroy()
        indptr = np.asarray(A.indptr)
        rows = np.repeat(np.arange(shape[0], dtype=PETSc.IntType), np.diff(indptr))
        mat = PETSc.Mat().create(comm=self.comm)
        mat.setSizes(shape, bsize=self.block_size)
        mat.setType(self.types.mat_type if self.types is not None else "aij")
        if self.types is not None:
            mat.setVecType(self.types.vec_type)
        mat.setPreallocationCOO(rows, np.asarray(A.indices, dtype=PETSc.IntType))
        self.mat = mat
        self._pattern = (A.indptr, A.indices, shape)

    def destroy(self) -> None:
        super().destroy()
        if self._sums is not None:
            self._sums.destroy()
        self._pattern = self._data = self._sums = None

    def norm(self) -> float:
        """``max(‖A‖₁, ‖A‖_∞)`` computed where the values live: one product of a 0/1
        matrix S (a row per row of A, then a row per column, each summing that line's
        entries) with the values' absolute values, and one PETSc norm, so only the
        result crosses to the host (PETSc's ``MatNorm`` of a CUDA Mat copies the whole
        Mat to the host first).  Kept until the values change."""
        if self.types is None:  # host values: PETSc's MatNorm reads them in place
            return super().norm()
        if self._norm is not None and self._norm[0] == self.version:
            return self._norm[1]
        indptr, indices, shape = self._pattern
        nnz = len(indices)
        if self._sums is None:  # once per pattern
            rows = np.repeat(np.arange(shape[0], dtype=PETSc.IntType), np.diff(indptr))
            self._sums = PETSc.Mat().create(comm=PETSc.COMM_SELF)
            self._sums.setSizes((shape[0] + shape[1], nnz))
            self._sums.setType(self.mat.getType())
            self._sums.setVecType(self.types.vec_type)
            lines = np.concatenate([rows, shape[0] + np.asarray(indices, dtype=PETSc.IntType)])
            entries = np.tile(np.arange(nnz, dtype=PETSc.IntType), 2)
            self._sums.setPreallocationCOO(lines, entries)
            self._sums.setValuesCOO(np.ones(2 * nnz))
        values = wrap(self._data, nnz, "the operator's values", self.types.memory)
        absolute, sums = self._sums.createVecs()
        try:
            values.copy(absolute)
            absolute.abs()
            self._sums.mult(absolute, sums)
            norm = sums.norm(PETSc.NormType.INFINITY)
        finally:
            for vec in (values, absolute, sums):
                vec.destroy()
        self._norm = (self.version, norm)
        return norm

    def _tested_symmetric(self) -> bool:
        """PETSc's ``MatIsSymmetric`` on the values set."""
        scale = self.mat.norm(PETSc.NormType.INFINITY)
        return self.mat.isSymmetric(DIAGONAL_RTOL * scale)


#: the operator layouts, each taking one kind of operator (`OperatorLayout.accepts`)
LAYOUTS: tuple[type[OperatorLayout], ...] = (ReplicatedCSR, CallerMat, OwnedRows, DeviceCSR)


def layout_for(
    A, held: OperatorLayout | None = None, *, comm=None, block_size: int = 1, types=None
) -> OperatorLayout:
    """The layout that holds operator `A`: `held` if it is of A's kind (or holds A's
    Mat), else a new one of the kind that accepts A, continuing `held`'s version (the
    old one destroyed).  `TypeError` for an operator no layout takes.  `types`: the
    solver's `~prdp_petsc.core.device.DeviceTypes` (None: the default path)."""
    if held is not None and held.types == types and (A is held.mat or held.accepts(A)):
        return held
    for kind in LAYOUTS:
        if kind.accepts(A):
            break
    else:
        raise TypeError(
            "A must be a scipy sparse matrix, a CSR tuple, a PETSc.Mat, an OwnedCSR or a "
            f"DLPackCSR, got {type(A)}"
        )
    version = 0
    if held is not None:
        version = held.version
        held.destroy()
    return kind(comm, block_size, version, types)


def _all_ranks(comm: PETSc.Comm, *flags: bool) -> list[bool]:
    """Each of `flags` and-ed over the ranks of `comm` (one ``MPI_Allreduce``)."""
    if comm.getSize() == 1:
        return [bool(f) for f in flags]
    from mpi4py import MPI  # the owned layout on several ranks needs mpi4py

    values = np.array(flags, dtype=np.int8)
    comm.tompi4py().Allreduce(MPI.IN_PLACE, values, op=MPI.MIN)
    return [bool(v) for v in values]
