"""Null spaces of singular operators and near-null spaces of multigrid, for `KSPSolver`.

A null space is given as ``"constant"`` or as vectors ``(k, n)``.  `KSPSolver`
attaches it to the PETSc matrix with ``MatSetNullSpace`` (and the transpose null
space with ``MatSetTransposeNullSpace``), so every Krylov method removes it from
its iterates and ``KSPSolve`` projects the right-hand side onto the range of A:
the result is the minimum-norm least-squares solution ``x = A⁺ b`` (orthogonal to
the null space), also for an incompatible right-hand side.

A *near*-null space (``MatSetNearNullSpace``) is what algebraic multigrid must
interpolate exactly: the vectors A maps to almost nothing when no boundary
condition holds them, such as the rigid-body modes of elasticity
(`prdp_petsc.fem.vector.rigid_body_modes`).  GAMG builds its coarse spaces from
them (the constants otherwise); other preconditioners ignore them.  It is not
checked against the operator: a near-null vector is not a null vector.

Vectors are given full length (every rank the same; each rank uses its rows) or,
in the owned layout, as this rank's entries; a ``PETSc.NullSpace`` is read once
(its vectors' entries on this rank, and its constant).  They are orthonormalised
when they are attached: full-length vectors with one Householder QR (LAPACK), this
rank's entries by Gram–Schmidt with the inner products of the whole distributed
vector.  PETSc then removes the space from every iterate with ``VecMDot`` over all
k vectors: k dot products per application of the preconditioner.

A large kernel is better given *sparse*: a scipy sparse matrix G, shape (n, k), whose
columns span it (they need not be orthogonal), such as the discrete gradient of a
Nédélec basis (`prdp_petsc.fem.nedelec.discrete_gradient`: k ≈ the vertex count).
On one process it is attached as the projection (`SparseSpan`)

    x ← x − G (GᵀG)⁻¹ Gᵀ x,

with ``GᵀG`` factored once (SuperLU), so no dense vector is ever built and a removal
costs two sparse products and one sparse triangular solve pair; it is checked
against the operator with one sparse product ``A G``.  On more processes its
columns become dense vectors.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from ..errors import InputError

__all__ = [
    "SparseSpan",
    "attach_near_nullspace",
    "attach_nullspaces",
    "check_nullspace",
    "check_nullspaces",
    "normalize_nullspace",
    "petsc_nullspace",
]

#: ``‖A v‖ / (‖A‖_∞ ‖v‖)`` above which v is rejected as a null vector of A
NULL_TOLERANCE = 1e-8
#: a vector whose part outside the span of the ones before it is below this fraction
#: of its norm counts as linearly dependent on them
DEPENDENT = 1e-10


def normalize_nullspace(spec, name: str = "nullspace"):
    """Validate a (near-)null-space specification: None, ``"constant"`` or vectors.

    Parameters
    ----------
    spec : None, "constant", array_like (n,) or (k, n), scipy sparse (n, k), or PETSc.NullSpace
        Vectors spanning the space, as the rows of an array (any basis:
        `petsc_nullspace` orthonormalises them when it attaches them), or as the
        columns of a sparse matrix (linearly independent; see `SparseSpan`); a
        ``PETSc.NullSpace`` gives its vectors (this rank's entries) and, if it has
        one, the constant vector.
    name : str
        Argument name for error messages.

    Returns
    -------
    None, "constant", ndarray, shape (k, n), or scipy.sparse.csr_matrix, shape (n, k)
        A read-only float64 copy of the vectors (of the sparse matrix).
    """
    if spec is None:
        return None
    if isinstance(spec, str):
        if spec != "constant":
            raise InputError(f"{name} must be 'constant' or an array of vectors, got {spec!r}")
        return spec
    if sp.issparse(spec):
        return _normalize_sparse(spec, name)
    if isinstance(spec, PETSc.NullSpace):
        rows = [v.getArray(readonly=True).copy() for v in spec.getVecs()]
        if spec.hasConstant():
            size = rows[0].size if rows else None
            if size is None:
                return "constant"
            rows.insert(0, np.ones(size))
        spec = np.array(rows)
    vecs = np.atleast_2d(np.array(spec, dtype=np.float64))
    if vecs.ndim != 2 or vecs.shape[1] == 0 or vecs.shape[0] == 0:
        raise InputError(f"{name} must have shape (n,) or (k, n), got {np.shape(spec)}")
    if not np.all(np.isfinite(vecs)):
        raise InputError(f"{name} contains NaN or Inf")
    if not np.all(np.abs(vecs).max(axis=1) > 0):
        raise InputError(f"{name} vectors must be non-zero and linearly independent")
    vecs.flags.writeable = False
    return vecs


def _normalize_sparse(spec, name: str) -> sp.csr_matrix:
    """A read-only float64 CSR copy of a sparse (n, k) spec, its columns checked."""
    if spec.ndim != 2 or min(spec.shape) == 0:
        raise InputError(f"{name} as a sparse matrix must have shape (n, k), got {spec.shape}")
    span = sp.csr_matrix(spec, dtype=np.float64, copy=True)
    if not np.all(np.isfinite(span.data)):
        raise InputError(f"{name} contains NaN or Inf")
    span.eliminate_zeros()
    if np.unique(span.indices).size != span.shape[1]:
        raise InputError(f"{name} columns must be non-zero and linearly independent")
    for array in (span.data, span.indices, span.indptr):
        array.flags.writeable = False
    return span


def petsc_nullspace(spec, mat: PETSc.Mat, name: str = "nullspace") -> PETSc.NullSpace:
    """A PETSc ``MatNullSpace`` for a normalised `spec` on the layout of `mat`.

    Vectors are orthonormalised here, as ``MatNullSpaceCreate`` requires: full-length
    ones by one Householder QR, this rank's entries of distributed ones by modified
    Gram–Schmidt, twice, with the distributed inner products.  A sparse spec becomes
    a `SparseSpan` on one process, its columns as vectors on more.  Vectors that are
    not linearly independent raise `InputError`.
    """
    comm = mat.getComm()
    if isinstance(spec, str):
        return PETSc.NullSpace().create(constant=True, comm=comm)
    if sp.issparse(spec):
        if comm.getSize() == 1:
            return SparseSpan(spec, name).nullspace(mat)
        spec = spec.T.toarray()  # more processes: the columns as distributed vectors
    template = mat.createVecRight()
    start, end = template.getOwnershipRange()
    size, local = template.getSize(), template.getLocalSize()
    template.destroy()
    if spec.shape[1] == size:  # full length (the replicated layout, or one rank)
        q = _orthonormal_columns(spec, name)[start:end]
        vecs = []
        for column in q.T:
            v = mat.createVecRight()
            v.array[:] = column
            vecs.append(v)
    elif spec.shape[1] == local:  # this rank's entries (the owned layout)
        vecs = []
        for row in spec:
            v = mat.createVecRight()
            v.array[:] = row
            vecs.append(v)
        vecs = _orthonormal(vecs, name)
    else:
        raise InputError(
            f"{name} vectors have {spec.shape[1]} entries, the operator has "
            f"{size} columns ({local} on this rank)"
        )
    return PETSc.NullSpace().create(vectors=vecs, comm=comm)


def _orthonormal_columns(rows: np.ndarray, name: str) -> np.ndarray:
    """An orthonormal basis (n, k) of the span of `rows` (k, n): Householder QR, one
    LAPACK call; `InputError` if they are dependent (|R_jj| ≤ `DEPENDENT` ‖row j‖)."""
    q, r = np.linalg.qr(rows.T)
    if not np.all(np.abs(np.diag(r)) > DEPENDENT * np.linalg.norm(rows, axis=1)):
        raise InputError(f"{name} vectors must be non-zero and linearly independent")
    return q


def _orthonormal(vecs: list, name: str) -> list:
    """`vecs` orthonormalised in place (collective); `InputError` if they are dependent."""
    done = []
    for v in vecs:
        before = v.norm()
        for _ in range(2):  # Gram–Schmidt twice is enough (Kahan)
            for q in done:
                v.axpy(-q.dot(v), q)
        after = v.norm()
        if not after > DEPENDENT * before:
            raise InputError(f"{name} vectors must be non-zero and linearly independent")
        v.scale(1.0 / after)
        done.append(v)
    return done


class SparseSpan:
    """The span of the columns of a sparse G, as the remove function of a PETSc null space.

    Removing the space from x is the orthogonal projection

        x ← x − G (GᵀG)⁻¹ Gᵀ x,

    with ``GᵀG`` (k × k, sparse: for a discrete gradient the graph Laplacian of the
    mesh) factored once here by SuperLU in symmetric mode; the columns need not be
    orthogonal, only linearly independent: a pivot of ``GᵀG`` at or below `DEPENDENT`
    times its diagonal entry (a column whose part outside the span of the others is
    below 1e-5 of its norm: the normal equations resolve no less) raises `InputError`.
    One process only (the vectors PETSc hands the function hold every entry).

    Parameters
    ----------
    span : scipy.sparse matrix, shape (n, k)
        As `normalize_nullspace` returns it.
    name : str
        Argument name for error messages.
    """

    def __init__(self, span: sp.csr_matrix, name: str = "nullspace") -> None:
        from scipy.sparse.linalg import splu

        self.name = name
        self.span = span.tocsr()
        self.transposed = span.T.tocsr()
        gram = (self.transposed @ self.span).tocsc()
        dependent = InputError(f"{name} columns must be non-zero and linearly independent")
        try:
            factor = splu(
                gram,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError as err:  # an exactly singular GᵀG
            raise dependent from err
        # the j-th pivot is that of the column perm_c maps to j; a pivot is the squared
        # norm of the column's part outside the span of those eliminated before it
        pivots = np.abs(factor.U.diagonal())
        if not np.all(pivots > DEPENDENT * gram.diagonal()[np.argsort(factor.perm_c)]):
            raise dependent
        self._solve = factor.solve
        self._mat: PETSc.Mat | None = None  # G as a PETSc Mat, for `check`

    def __call__(self, nullspace: PETSc.NullSpace, vec: PETSc.Vec) -> None:
        """PETSc's ``MatNullSpaceRemove`` callback: project `vec` in place."""
        x = vec.getArray()
        x -= self.span @ self._solve(self.transposed @ x)

    def nullspace(self, mat: PETSc.Mat) -> PETSc.NullSpace:
        """A PETSc null space (no vectors) that calls this projection, for `mat`."""
        columns = mat.getSize()[1]
        if self.span.shape[0] != columns:
            raise InputError(
                f"{self.name} has {self.span.shape[0]} rows, the operator has {columns} columns"
            )
        ns = PETSc.NullSpace().create(constant=False, vectors=[], comm=mat.getComm())
        ns.setFunction(self)
        return ns

    def defects(self, mat: PETSc.Mat, *, transpose: bool) -> np.ndarray:
        """``‖A g_j‖ / (‖A‖ ‖g_j‖)`` of every column (Aᵀ with `transpose`): one sparse
        product ``A G`` (a loop of products where `mat`'s type has none)."""
        if self._mat is None:
            csr = self.span
            self._mat = PETSc.Mat().createAIJ(
                size=csr.shape, csr=(csr.indptr, csr.indices, csr.data), comm=PETSc.COMM_SELF
            )
        scale = max(mat.norm(PETSc.NormType.INFINITY), mat.norm(PETSc.NormType.NORM_1))
        sizes = np.sqrt(np.asarray(self.span.multiply(self.span).sum(axis=0)).ravel())
        try:
            product = (mat.transposeMatMult if transpose else mat.matMult)(self._mat)
        except PETSc.Error:
            return self._defects_by_column(mat, transpose, scale, sizes)
        _, indices, data = product.getValuesCSR()
        product.destroy()
        norms = np.sqrt(np.bincount(indices, data**2, minlength=self.span.shape[1]))
        return norms / (scale * sizes) if scale > 0 else np.zeros_like(norms)

    def _defects_by_column(self, mat, transpose, scale, sizes) -> np.ndarray:
        v, out = mat.createVecs()
        norms = np.empty(self.span.shape[1])
        csc = self.span.tocsc()
        for j in range(csc.shape[1]):
            v.array[:] = csc[:, j].toarray().ravel()
            (mat.multTranspose if transpose else mat.mult)(v, out)
            norms[j] = out.norm()
        return norms / (scale * sizes) if scale > 0 else np.zeros_like(norms)


def check_nullspace(mat: PETSc.Mat, ns: PETSc.NullSpace, *, transpose: bool, name: str) -> None:
    """Raise ValueError unless ``A v ≈ 0`` (``Aᵀ v`` with `transpose`) for every null vector.

    A wrong null space would make PETSc project the right-hand side and return the
    solution of another problem without complaint; this check costs one product per
    vector.
    """
    vecs = list(ns.getVecs())
    if ns.hasConstant():
        one = mat.createVecRight()
        one.set(1.0)
        vecs.append(one)
    scale = max(mat.norm(PETSc.NormType.INFINITY), mat.norm(PETSc.NormType.NORM_1))
    defects = []
    out = mat.createVecLeft()
    for v in vecs:
        (mat.multTranspose if transpose else mat.mult)(v, out)
        defects.append(out.norm() / (scale * v.norm()) if scale > 0 else 0.0)
    function = ns.getFunction()
    if function is not None and isinstance(function[0], SparseSpan):
        defects.extend(function[0].defects(mat, transpose=transpose))
    worst = max(defects, default=0.0)
    if not worst <= NULL_TOLERANCE:
        op = "Aᵀ" if transpose else "A"
        raise InputError(
            f"{name} is not a null space of the operator: ‖{op} v‖/(‖A‖‖v‖) = "
            f"{worst:.2e} > {NULL_TOLERANCE:g}; PETSc would project the right-hand side "
            "and solve another problem. Pass the right vectors (or transpose_nullspace= "
            "for a non-symmetric operator) or none."
        )


def attach_nullspaces(
    mat: PETSc.Mat, nullspace, transpose_nullspace, made: dict | None = None
) -> None:
    """``MatSetNullSpace`` / ``MatSetTransposeNullSpace`` from normalised specs, checked.

    A transpose null space that is the null space itself (the default) is the same
    PETSc object.  `made`, a dict the caller keeps, holds the PETSc null spaces made
    for each layout of the columns, so that another Mat of that layout (a new
    pattern, a caller's new Mat) reuses them: the vectors are orthonormalised once.
    """
    key = (mat.getComm().getSize(), mat.getSizes()[1])
    spaces = None if made is None else made.get(key)
    if spaces is None:
        ns = petsc_nullspace(nullspace, mat)
        same = transpose_nullspace is nullspace
        tns = ns if same else petsc_nullspace(transpose_nullspace, mat, "transpose_nullspace")
        spaces = (ns, tns)
        if made is not None:
            made[key] = spaces
    mat.setNullSpace(spaces[0])
    mat.setTransposeNullSpace(spaces[1])
    check_nullspaces(mat)


def attach_near_nullspace(mat: PETSc.Mat, near_nullspace) -> None:
    """``MatSetNearNullSpace`` from a normalised spec (not checked against the operator);
    a sparse one's columns become vectors (multigrid reads vectors)."""
    if sp.issparse(near_nullspace):
        near_nullspace = near_nullspace.T.toarray()
    mat.setNearNullSpace(petsc_nullspace(near_nullspace, mat, "near_nullspace"))


def check_nullspaces(mat: PETSc.Mat) -> None:
    """`check_nullspace` for both null spaces attached to `mat` (after new values); once
    when they are one object and the operator is known to be symmetric."""
    ns, tns = mat.getNullSpace(), mat.getTransposeNullSpace()
    check_nullspace(mat, ns, transpose=False, name="nullspace")
    if tns.handle == ns.handle and mat.isSymmetricKnown() == (True, True):
        return
    check_nullspace(mat, tns, transpose=True, name="transpose_nullspace")
