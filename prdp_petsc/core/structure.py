"""The structure of an operator: its declaration (`Structure`), and the check of
methods that assume a symmetric operator against it.

`Structure` gathers what is known about every operator a `KSPSolver` gets — symmetry,
null spaces, the near-null space, the block size and the fields of a block operator —
in one object, given once (``KSPSolver(structure=pp.Structure(...))``).


CG and its pipelined variants, MINRES, CR, SYMMLQ and the trust-region CGs
(``nash``, ``stcg``, ``gltr``, ``qcg``) build their iterates from a short
recurrence that is only valid for A = Aᵀ; ICC and Cholesky factor only one
triangle.  On a non-symmetric operator they run without error and, capped at K,
return an iterate that can be far from the solution, with the ordinary reason
``DIVERGED_MAX_IT`` (``tests/test_trust.py`` shows one on advection-diffusion).  A
`KSPSolver` therefore checks, whenever a new operator (or new values) is set up,
that no such method meets an operator *known* to be non-symmetric (declared
``symmetric=False``, or a CSR operator that failed the entry-against-mirror
test), and raises `prdp_petsc.errors.StructureError` naming a fitting
alternative.  An operator of unknown structure (a caller's PETSc Mat with no
``MAT_SYMMETRIC`` flag) is not refused: declared beats guessed.

The sub-solvers of block Jacobi and ASM are checked as well (they exist once the
PC is set up); those of fieldsplit and multigrid levels act on other matrices
and are not.  Experts turn the check off with ``KSPSolver(check_structure=False)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from petsc4py import PETSc

from ..errors import InputError, StructureError, plain
from .fields import normalize_fields
from .nullspace import normalize_nullspace

__all__ = [
    "SYMMETRIC_ONLY_KSP",
    "SYMMETRIC_ONLY_PC",
    "Structure",
    "check_structure",
    "symmetric_only",
]


@dataclass(frozen=True, eq=False)
class Structure:
    """What is known about every operator a solver gets, declared once.

    Parameters
    ----------
    symmetric : bool, optional
        ``True`` (A = Aᵀ), ``False``, or ``None`` (default) to take what the caller
        knows of each operator (`ParametricMatrix.is_symmetric`, the
        ``known_symmetric=`` of `KSPSolver.set_operator`) or else test every entry
        against its mirror whenever the values change (`KSPSolver.is_symmetric` says
        which it is).
    nullspace : "constant" or array_like (k, n), optional
        Null space of a singular operator (pure Neumann, periodic), attached to every
        Mat with ``MatSetNullSpace``: Krylov iterates stay orthogonal to it and the
        right-hand side is projected onto the range of A, so a solve returns the
        minimum-norm least-squares solution ``A⁺ b``.  It must not depend on θ, and
        it is checked against every new operator (``‖A v‖ ≤ 1e-8 ‖A‖ ‖v‖``).
    transpose_nullspace : "constant" or array_like (k, n), optional
        Null space of Aᵀ (``MatSetTransposeNullSpace``); defaults to `nullspace`,
        right for symmetric operators.
    near_nullspace : "constant", array_like (k, n) or PETSc.NullSpace, optional
        Vectors A maps to almost nothing without boundary conditions
        (``MatSetNearNullSpace``): GAMG builds its coarse spaces from them.  For
        elasticity the rigid-body modes (`prdp_petsc.fem.vector.rigid_body_modes`, on
        the dofs the operator keeps), with `block_size` the dimension.  Not checked
        against A (a near-null vector is no null vector).
    block_size : int
        Unknowns per node of a vector field (``MatSetBlockSize``): GAMG aggregates
        whole nodes, point-block preconditioners invert d × d blocks.  Only right
        when the dofs are numbered node by node and every node keeps all of its
        components (`prdp_petsc.fem.vector.block_size` computes it).  Default 1.
    fields : mapping of str to array of int, optional
        The fields of a block operator, e.g. ``{"u": u_dofs, "p": p_dofs}``: row
        indices (after any Dirichlet elimination), together covering every row once,
        given to the PCs with ``PCFieldSplitSetIS`` for ``pc_type fieldsplit`` (other
        PCs ignore them).  A split's solver reads ``-{prefix}fieldsplit_{name}_...``.
    """

    symmetric: bool | None = None
    nullspace: Any = None
    transpose_nullspace: Any = None
    near_nullspace: Any = None
    block_size: int = 1
    fields: Any = None

    def __post_init__(self):
        if self.symmetric is not None:
            if not isinstance(self.symmetric, bool | np.bool_):
                raise InputError(f"symmetric must be True, False or None, got {self.symmetric!r}")
            object.__setattr__(self, "symmetric", bool(self.symmetric))
        if self.transpose_nullspace is not None and self.nullspace is None:
            raise InputError(
                "transpose_nullspace without nullspace: a square operator's kernel and its "
                "transpose's have the same dimension; declare both"
            )
        size = self.block_size
        if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 1:
            raise InputError(f"block_size must be an integer >= 1, got {plain(size)!r}")
        nullspace = normalize_nullspace(self.nullspace)
        transpose = self.transpose_nullspace
        set_ = object.__setattr__
        set_(self, "nullspace", nullspace)
        set_(
            self,
            "transpose_nullspace",
            nullspace
            if transpose is None
            else normalize_nullspace(transpose, "transpose_nullspace"),
        )
        set_(self, "near_nullspace", normalize_nullspace(self.near_nullspace, "near_nullspace"))
        set_(self, "block_size", int(size))
        set_(self, "fields", normalize_fields(self.fields))


#: KSP types whose iteration is only valid for a symmetric operator (PETSc 3.26)
SYMMETRIC_ONLY_KSP = frozenset(
    {
        "cg",
        "pipecg",
        "pipecgrr",
        "pipelcg",
        "pipeprcg",
        "groppcg",
        "fcg",
        "pipefcg",
        "cr",
        "pipecr",
        "minres",
        "symmlq",
        "nash",
        "stcg",
        "gltr",
        "qcg",
    }
)
#: PC types that factor one triangle of a symmetric operator
SYMMETRIC_ONLY_PC = frozenset({"icc", "cholesky"})
#: a fitting alternative for a non-symmetric operator
_ALTERNATIVE = {"ksp": "gmres (or bcgs)", "pc": "ilu (or lu, or jacobi)"}


def symmetric_only(ksp: PETSc.KSP, *, set_up: bool = False) -> list[str]:
    """Options of `ksp` that name a symmetric-only method, e.g. ``["ksp_type cg"]``.

    With `set_up` the sub-KSPs of a block Jacobi or ASM preconditioner (which
    exist only after ``KSPSetUp``) are included, named by their option
    (``sub_ksp_type``, ``sub_pc_type``).
    """
    found = []
    _inspect(ksp, "", found)
    pc = ksp.getPC()
    if set_up and pc.getType() in ("bjacobi", "asm"):
        subs = pc.getBJacobiSubKSP() if pc.getType() == "bjacobi" else pc.getASMSubKSP()
        for sub in subs[:1]:  # every block has the same types
            _inspect(sub, "sub_", found)
    return found


def _inspect(ksp: PETSc.KSP, prefix: str, found: list) -> None:
    if ksp.getType() in SYMMETRIC_ONLY_KSP:
        found.append(f"{prefix}ksp_type {ksp.getType()}")
    if ksp.getPC().getType() in SYMMETRIC_ONLY_PC:
        found.append(f"{prefix}pc_type {ksp.getPC().getType()}")


def check_structure(ksp: PETSc.KSP, symmetric: bool | None, kind: str, *, set_up=False) -> None:
    """Raise `StructureError` if `ksp` runs a symmetric-only method on a non-symmetric A.

    Parameters
    ----------
    ksp : PETSc.KSP
    symmetric : bool or None
        The operator's structure: True, False (known non-symmetric) or None
        (unknown: nothing is refused).
    kind : str
        ``"forward"`` or ``"adjoint"``, for the message.
    set_up : bool
        Whether the PC is set up, so that its sub-solvers can be inspected.
    """
    if symmetric is not False:
        return
    found = symmetric_only(ksp, set_up=set_up)
    if not found:
        return
    prefix = ksp.getOptionsPrefix() or ""
    fixes = []
    for option in found:
        name = option.split()[0]
        what = "ksp" if name.endswith("ksp_type") else "pc"
        fixes.append(f"-{prefix}{name} {_ALTERNATIVE[what]}")
    raise StructureError(
        f"the {kind} solve uses {', '.join(found)} (prefix {prefix!r}), which assume a "
        "symmetric operator, but the operator is not symmetric (declared, or an entry "
        "differs from its mirror): capped, it would return a wrong answer without an "
        f"error. Use {'; '.join(fixes)}; or, if the operator is in fact symmetric, "
        "declare it (Structure(symmetric=True)); experts can turn this check off with "
        "KSPSolver(check_structure=False)."
    )
