"""Methods that assume a symmetric operator, checked against the operator's structure.

CG and its pipelined variants, MINRES, CR, SYMMLQ and the trust-region CGs
(``nash``, ``stcg``, ``gltr``, ``qcg``) build their iterates from a short
recurrence that is only valid for A = Aᵀ; ICC and Cholesky factor only one
triangle.  On a non-symmetric operator they run without error and, capped at K,
return an iterate that can be far from the solution (measured: 1-45x off on an
advection-diffusion operator at K = 40, with reason ``DIVERGED_MAX_IT``).  A
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

from petsc4py import PETSc

from ..errors import StructureError

__all__ = ["SYMMETRIC_ONLY_KSP", "SYMMETRIC_ONLY_PC", "check_structure", "symmetric_only"]

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
        "declare it (symmetric=True); experts can turn this check off with "
        "KSPSolver(check_structure=False)."
    )
