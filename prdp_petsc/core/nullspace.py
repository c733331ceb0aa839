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
when they are attached, with the inner products of the whole distributed vector.
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from ..errors import InputError

__all__ = [
    "attach_near_nullspace",
    "attach_nullspaces",
    "check_nullspace",
    "check_nullspaces",
    "normalize_nullspace",
    "petsc_nullspace",
]

#: ``‖A v‖ / (‖A‖_∞ ‖v‖)`` above which v is rejected as a null vector of A
NULL_TOLERANCE = 1e-8


def normalize_nullspace(spec, name: str = "nullspace"):
    """Validate a (near-)null-space specification: None, ``"constant"`` or vectors.

    Parameters
    ----------
    spec : None, "constant", array_like, shape (n,) or (k, n), or PETSc.NullSpace
        Vectors spanning the space (any basis: `petsc_nullspace` orthonormalises
        them when it attaches them); a ``PETSc.NullSpace`` gives its vectors (this
        rank's entries) and, if it has one, the constant vector.
    name : str
        Argument name for error messages.

    Returns
    -------
    None, "constant" or ndarray, shape (k, n)
        A read-only float64 copy of the vectors.
    """
    if spec is None:
        return None
    if isinstance(spec, str):
        if spec != "constant":
            raise InputError(f"{name} must be 'constant' or an array of vectors, got {spec!r}")
        return spec
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


def petsc_nullspace(spec, mat: PETSc.Mat, name: str = "nullspace") -> PETSc.NullSpace:
    """A PETSc ``MatNullSpace`` for a normalised `spec` on the layout of `mat`.

    The vectors are orthonormalised here (modified Gram–Schmidt, twice, with the
    distributed inner products), as ``MatNullSpaceCreate`` requires; vectors that
    are not linearly independent raise `InputError`.
    """
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
                f"{name} vectors have {row.size} entries, the operator has "
                f"{v.getSize()} columns ({v.getLocalSize()} on this rank)"
            )
        v.array[:] = row
        vecs.append(v)
    return PETSc.NullSpace().create(vectors=_orthonormal(vecs, name), comm=mat.getComm())


def _orthonormal(vecs: list, name: str) -> list:
    """`vecs` orthonormalised in place (collective); `InputError` if they are dependent."""
    done = []
    for v in vecs:
        before = v.norm()
        for _ in range(2):  # Gram–Schmidt twice is enough (Kahan)
            for q in done:
                v.axpy(-q.dot(v), q)
        after = v.norm()
        if not after > 1e-10 * before:
            raise InputError(f"{name} vectors must be non-zero and linearly independent")
        v.scale(1.0 / after)
        done.append(v)
    return done


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
    mat.setTransposeNullSpace(petsc_nullspace(transpose_nullspace, mat, "transpose_nullspace"))
    check_nullspaces(mat)


def attach_near_nullspace(mat: PETSc.Mat, near_nullspace) -> None:
    """``MatSetNearNullSpace`` from a normalised spec (not checked against the operator)."""
    mat.setNearNullSpace(petsc_nullspace(near_nullspace, mat, "near_nullspace"))


def check_nullspaces(mat: PETSc.Mat) -> None:
    """`check_nullspace` for both null spaces attached to `mat` (after new values)."""
    check_nullspace(mat, mat.getNullSpace(), transpose=False, name="nullspace")
    check_nullspace(mat, mat.getTransposeNullSpace(), transpose=True, name="transpose_nullspace")
