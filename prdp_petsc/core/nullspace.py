"""Null spaces of singular operators (pure Neumann, periodic) for `KSPSolver`.

A null space is given as ``"constant"`` or as vectors ``(k, n)``.  `KSPSolver`
attaches it to the PETSc matrix with ``MatSetNullSpace`` (and the transpose null
space with ``MatSetTransposeNullSpace``), so every Krylov method removes it from
its iterates and ``KSPSolve`` projects the right-hand side onto the range of A:
the result is the minimum-norm least-squares solution ``x = A⁺ b`` (orthogonal to
the null space), also for an incompatible right-hand side.
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from ..errors import InputError

__all__ = [
    "attach_nullspaces",
    "check_nullspace",
    "check_nullspaces",
    "normalize_nullspace",
    "petsc_nullspace",
]

#: ``‖A v‖ / (‖A‖_∞ ‖v‖)`` above which v is rejected as a null vector of A
NULL_TOLERANCE = 1e-8


def normalize_nullspace(spec, name: str = "nullspace"):
    """Validate a null-space specification: None, ``"constant"`` or an orthonormal basis.

    Parameters
    ----------
    spec : None, "constant" or array_like, shape (n,) or (k, n)
        Vectors spanning the null space (any basis; orthonormalised here).
    name : str
        Argument name for error messages.

    Returns
    -------
    None, "constant" or ndarray, shape (k, n)
        Rows orthonormal in the Euclidean inner product.
    """
    if spec is None:
        return None
    if isinstance(spec, str):
        if spec != "constant":
            raise InputError(f"{name} must be 'constant' or an array of vectors, got {spec!r}")
        return spec
    vecs = np.atleast_2d(np.asarray(spec, dtype=np.float64))
    if vecs.ndim != 2 or vecs.shape[1] == 0:
        raise InputError(f"{name} must have shape (n,) or (k, n), got {np.shape(spec)}")
    if not np.all(np.isfinite(vecs)):
        raise InputError(f"{name} contains NaN or Inf")
    q, r = np.linalg.qr(vecs.T)
    diag = np.abs(np.diag(r))
    if diag.size == 0 or diag.min() <= 1e-12 * max(diag.max(), 1e-300):
        raise InputError(f"{name} vectors must be non-zero and linearly independent")
    return np.ascontiguousarray(q.T)


def petsc_nullspace(spec, mat: PETSc.Mat) -> PETSc.NullSpace:
    """A PETSc ``MatNullSpace`` for a normalised `spec` on the layout of `mat`."""
    if isinstance(spec, str):
        return PETSc.NullSpace().create(constant=True, comm=mat.getComm())
    vecs = []
    for row in spec:
        v = mat.createVecRight()
        start, end = v.getOwnershipRange()
        if row.size == v.getSize():  # full length (the replicated layout, or one rank)
            row = row[start:end]
        elif v.getLocalSize() != row.size:
            raise InputError(
                f"null-space vectors have {row.size} entries, the operator has "
                f"{v.getSize()} columns ({v.getLocalSize()} on this rank)"
            )
        v.array[:] = row
        vecs.append(v)
    return PETSc.NullSpace().create(vectors=vecs, comm=mat.getComm())


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
    out = mat.createVecLeft()
    for v in vecs:
        (mat.multTranspose if transpose else mat.mult)(v, out)
        defect = out.norm() / (scale * v.norm()) if scale > 0 else 0.0
        if not defect <= NULL_TOLERANCE:
            op = "Aᵀ" if transpose else "A"
            raise InputError(
                f"{name} is not a null space of the operator: ‖{op} v‖/(‖A‖‖v‖) = "
                f"{defect:.2e} > {NULL_TOLERANCE:g}; PETSc would project the right-hand side "
                "and solve another problem. Pass the right vectors (or transpose_nullspace= "
                "for a non-symmetric operator) or none."
            )


def attach_nullspaces(mat: PETSc.Mat, nullspace, transpose_nullspace) -> None:
    """``MatSetNullSpace`` / ``MatSetTransposeNullSpace`` from normalised specs, checked."""
    mat.setNullSpace(petsc_nullspace(nullspace, mat))
    mat.setTransposeNullSpace(petsc_nullspace(transpose_nullspace, mat))
    check_nullspaces(mat)


def check_nullspaces(mat: PETSc.Mat) -> None:
    """`check_nullspace` for both null spaces attached to `mat` (after new values)."""
    check_nullspace(mat, mat.getNullSpace(), transpose=False, name="nullspace")
    check_nullspace(mat, mat.getTransposeNullSpace(), transpose=True, name="transpose_nullspace")
