"""Fields of a block operator (a saddle point) for PETSc's ``PCFIELDSPLIT``.

A Stokes system ``[[A, Bᵀ], [B, 0]]`` or any coupled problem is solved well by a
preconditioner that treats each field on its own (``-pc_type fieldsplit``, with a
Schur complement for a saddle point).  PETSc has to be told which rows belong to
which field; `Structure(fields={"u": u_dofs, "p": p_dofs})` says it once, and
`attach_fields` gives every PC that needs them the index sets
(``PCFieldSplitSetIS``) in the order the mapping lists them.

The names become PETSc's split names, so the options of a split's solver are
``-{prefix}fieldsplit_{name}_ksp_type``, ``-{prefix}fieldsplit_{name}_pc_type`` and
so on (``fieldsplit_u_pc_type gamg`` in an options dict), exactly as PETSc names
them.  The index sets are set on a PC once in its life: PETSc keeps them when the
operator's values or its Mat change, drops them at ``KSPReset`` (another size),
and would add a second copy of every field if they were set again.

Indices are the operator's row numbers (global ones in a distributed run; each
rank uses those it owns, so every rank may pass them all, or only its own).  They
must cover every row exactly once.
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from ..errors import InputError

__all__ = ["attach_fields", "field_index_sets", "normalize_fields"]


def normalize_fields(fields) -> dict[str, np.ndarray] | None:
    """Validate ``fields``: a mapping of split names to integer index arrays, or None.

    Returns a dict of read-only sorted int64 arrays, in the mapping's order.  Names
    are PETSc option words (letters, digits, ``_``); at least two fields are needed.
    """
    if fields is None:
        return None
    if not hasattr(fields, "items"):
        raise InputError(
            f"fields must map split names to index arrays, e.g. {{'u': u_dofs, 'p': p_dofs}}; "
            f"got {type(fields).__name__}"
        )
    out = {}
    for name, indices in fields.items():
        if not (isinstance(name, str) and name and name.replace("_", "a").isalnum()):
            raise InputError(
                f"fields: split name {name!r} must be a word (letters, digits, _): it becomes "
                "part of the option prefix fieldsplit_<name>_"
            )
        idx = np.asarray(indices)
        if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
            raise InputError(f"fields[{name!r}] must be a 1-d array of integer dof indices")
        idx = np.unique(idx.astype(np.int64))
        if idx.size != np.asarray(indices).size:
            raise InputError(f"fields[{name!r}] lists a dof more than once")
        idx.flags.writeable = False
        out[name] = idx
    if len(out) < 2:
        raise InputError(f"fields needs at least two fields, got {list(out)}")
    return out


def field_index_sets(fields: dict[str, np.ndarray], mat: PETSc.Mat) -> list[tuple[str, PETSc.IS]]:
    """(name, IS of this rank's rows of the field) for every field, checked against `mat`.

    Every row of `mat` this rank owns must belong to exactly one field, and no index
    may lie outside the operator.
    """
    start, end = mat.getOwnershipRange()
    n = mat.getSize()[0]
    owned = []
    for name, idx in fields.items():
        if idx.size and (idx[0] < 0 or idx[-1] >= n):
            raise InputError(
                f"fields[{name!r}] has indices outside [0, {n}): the operator has {n} rows "
                "(fields number the rows of the operator the solver gets, e.g. the interior "
                "dofs after Dirichlet elimination)"
            )
        owned.append(idx[(idx >= start) & (idx < end)])
    rows = np.concatenate(owned)
    if rows.size != end - start or np.unique(rows).size != rows.size:
        counts = ", ".join(f"{name} {int(idx.size)}" for name, idx in fields.items())
        raise InputError(
            f"fields must cover every row of the operator exactly once: they hold {counts} "
            f"indices for {n} rows ({end - start} on this rank)"
            + ("; some row is in two fields" if np.unique(rows).size != rows.size else "")
        )
    comm = mat.getComm()
    return [
        (name, PETSc.IS().createGeneral(idx.astype(PETSc.IntType), comm=comm))
        for name, idx in zip(fields, owned, strict=True)
    ]


def attach_fields(pc: PETSc.PC, fields: dict[str, np.ndarray], mat: PETSc.Mat) -> None:
    """``PCFieldSplitSetIS`` for every field (a PC of another type ignores them).

    Call once per PC life (after it is created or reset), before its set-up.
    """
    pc.setFieldSplitIS(*field_index_sets(fields, mat))
