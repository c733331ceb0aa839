"""Tolerances of a `KSPSolver` (properties applied to both KSPs) and option checks.

The PRDP controller owns ``max_it``, so tolerances are set by the program, never
by options: `refuse_tolerance_options` says so for ``-<prefix>ksp_max_it`` and
friends, `rejected_options_message` names an option PETSc refused, and
`UnusedOptionWarning` reports options PETSc never read.
"""

from __future__ import annotations

from petsc4py import PETSc

from .options import option_value
from .settings import check_tolerances

__all__ = [
    "Tolerances",
    "UnusedOptionWarning",
    "refuse_tolerance_options",
    "rejected_options_message",
]

_TOLERANCE_KEYS = ("ksp_rtol", "ksp_atol", "ksp_max_it", "ksp_divtol")


class UnusedOptionWarning(UserWarning):
    """Options of a `KSPSolver` that PETSc never read (misspelt, or meant for another type).

    A warning, not an error: ``-fwd_ksp_type cg`` on the command line legitimately
    leaves a scene's ``ksp_richardson_scale`` unread.  Turn it into an error with
    ``warnings.simplefilter("error", UnusedOptionWarning)`` (or ``-W error::...``).
    """


class Tolerances:
    """``max_it``, ``rtol``, ``atol``, ``divtol`` and the adjoint cap of a `KSPSolver`.

    Each setter validates the value and applies it to the forward and adjoint KSPs
    at once (``KSPSetTolerances``), so it holds from the next solve on.  The class
    expects ``_max_it``, ``_rtol``, ``_atol``, ``_divtol``, ``adjoint``, ``_ksp``
    and ``_adj`` on the instance.
    """

    @property
    def max_it(self) -> int:
        """Forward iteration cap K (the adjoint follows unless set on its own)."""
        return self._max_it

    @max_it.setter
    def max_it(self, value: int) -> None:
        check_tolerances(value, self._rtol, self._atol)
        self._max_it = int(value)
        self._apply_tolerances()

    @property
    def rtol(self) -> float:
        """Forward relative tolerance (0: off)."""
        return self._rtol

    @rtol.setter
    def rtol(self, value: float) -> None:
        self.set_tolerances(rtol=value)

    @property
    def atol(self) -> float:
        """Forward absolute tolerance (0: off)."""
        return self._atol

    @atol.setter
    def atol(self, value: float) -> None:
        self.set_tolerances(atol=value)

    @property
    def divtol(self) -> float | None:
        """Divergence tolerance (None: PETSc's default, 1e5)."""
        return self._divtol

    @property
    def adjoint_max_it(self) -> int:
        """Adjoint iteration cap: `AdjointSettings.max_it` or the forward `max_it`."""
        return self.adjoint.max_it if self.adjoint.max_it is not None else self._max_it

    @adjoint_max_it.setter
    def adjoint_max_it(self, value: int | None) -> None:
        if value is not None:
            check_tolerances(value, 0.0, 0.0, "adjoint ")
        self.adjoint.max_it = None if value is None else int(value)
        self._apply_tolerances()

    def set_tolerances(self, *, rtol: float | None = None, atol: float | None = None) -> None:
        """Change the forward stopping tolerances (e.g. for an rtol schedule)."""
        rtol = self._rtol if rtol is None else rtol
        atol = self._atol if atol is None else atol
        check_tolerances(self._max_it, rtol, atol)
        self._rtol, self._atol = float(rtol), float(atol)
        self._apply_tolerances()

    def _apply_tolerances(self) -> None:
        if self._ksp is None:
            return
        dt = self._divtol if self._divtol is not None else PETSc.DEFAULT
        self._ksp.setTolerances(rtol=self._rtol, atol=self._atol, divtol=dt, max_it=self._max_it)
        adj = self.adjoint
        self._adj.setTolerances(
            rtol=self._rtol if adj.rtol is None else adj.rtol,
            atol=self._atol if adj.atol is None else adj.atol,
            divtol=dt,
            max_it=self.adjoint_max_it,
        )


def refuse_tolerance_options(options: dict, where: str, use: str) -> None:
    bad = [k for k in options if k in _TOLERANCE_KEYS]
    if bad:
        raise ValueError(
            f"{bad} in {where}: a KSPSolver's tolerances are set by {use} (the PRDP "
            "schedule owns max_it); pass them as keyword arguments (max_it=, rtol=, atol=, "
            "divtol=, or AdjointSettings for the adjoint)"
        )


def rejected_options_message(items: list[tuple[str, object]], err: PETSc.Error) -> str:
    """Message for options that PETSc refused at ``KSPSetFromOptions``, naming the culprit."""
    known = {
        "ksp_type": {v for k, v in vars(PETSc.KSP.Type).items() if k.isupper()},
        "pc_type": {v for k, v in vars(PETSc.PC.Type).items() if k.isupper()},
    }
    for name, value in items:
        for key, names in known.items():
            if name.endswith(key) and option_value(value) not in names:
                return f"-{name} {option_value(value)}: not a PETSc {key[:-5].upper()} type"
    given = " ".join(f"-{n}" + (f" {option_value(v)}" if v is not None else "") for n, v in items)
    return f"PETSc refused the options {given!r} at KSPSetFromOptions ({err})"
