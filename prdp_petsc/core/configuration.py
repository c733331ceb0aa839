"""How a `KSPSolver` is configured: tolerances (properties on both KSPs) and options.

The PRDP controller owns ``max_it``, so tolerances are set by the program, never
by options: `refuse_tolerance_options` says so for ``-<prefix>ksp_max_it`` and
friends, `rejected_options_message` names an option PETSc refused, and
`UnusedOptionWarning` reports options PETSc never read.
"""

from __future__ import annotations

import warnings

from petsc4py import PETSc

from ..errors import UnusedOptionWarning
from .options import option_value, prefixed_options
from .settings import check_tolerances

__all__ = [
    "Configuration",
    "UnusedOptionWarning",
    "refuse_tolerance_options",
    "rejected_options_message",
]

_TOLERANCE_KEYS = ("ksp_rtol", "ksp_atol", "ksp_max_it", "ksp_divtol")
_OFF = ("0", "false", "no")


class Configuration:
    """``max_it``, ``rtol``, ``atol``, ``divtol``, the adjoint cap and the options of a
    `KSPSolver`: what PETSc is told, and what it never read.

    Each setter validates the value and applies it to the forward and adjoint KSPs
    at once (``KSPSetTolerances``), so it holds from the next solve on.  The class
    expects ``_max_it``, ``_rtol``, ``_atol``, ``_divtol``, ``adjoint``, ``_ksp``,
    ``_adj``, ``options``, ``_adjoint_own``, the prefixes and ``_used`` on the
    instance.
    """

    def _option_items(self) -> list[tuple[str, object]]:
        """(name, value) pairs this solver writes into PETSc's database.

        The adjoint inherits the forward options *as the forward KSP sees them*, so
        ``-fwd_ksp_type cg`` on the command line changes both solves unless
        ``-fwd_adj_ksp_type`` says otherwise.
        """
        exclude = self.adjoint_prefix if self.adjoint_prefix.startswith(self.prefix) else None
        forward = {**self.options, **prefixed_options(self.prefix, exclude)}
        adjoint = {**forward, **self._adjoint_own}
        return [(self.prefix + k, v) for k, v in self.options.items()] + [
            (self.adjoint_prefix + k, v) for k, v in adjoint.items()
        ]

    def _shares_pc(self) -> bool:
        if any(k.startswith("pc_") for k in self._adjoint_own):
            return False
        cmdline = prefixed_options(self.adjoint_prefix)
        # an explicit transpose re-points the adjoint's operators (and a shared PC) to Aᵀ
        explicit = "ksp_use_explicittranspose"
        for given in (self.adjoint_options, cmdline):
            if explicit in given and option_value(given[explicit]) not in _OFF:
                return False
        return not any(k.startswith("pc_") for k in cmdline)

    def _warn_unused(self, kind: str) -> None:
        """Warn (`UnusedOptionWarning`) about options of this solver PETSc never read."""
        prefix = self.adjoint_prefix if kind == "adjoint" else self.prefix
        given = self._adjoint_own if kind == "adjoint" else self.options
        names = {prefix + k for k in given}
        if prefix:  # the command line under a prefix of its own
            exclude = None if kind == "adjoint" else self.adjoint_prefix
            names |= {prefix + k for k in prefixed_options(prefix, exclude)}
        opts = PETSc.Options()
        unused = sorted(n for n in names if n not in self._used and not opts.used(n))
        if unused:
            warnings.warn(
                f"PETSc never read these options of the {kind} KSP (prefix {prefix!r}, "
                f"{self._types(kind)}): "
                + ", ".join("-" + n for n in unused)
                + "; check their spelling (-help lists the options PETSc reads)",
                UnusedOptionWarning,
                stacklevel=4,
            )

    def _types(self, kind: str) -> str:
        ksp = self._adj if kind == "adjoint" else self._ksp
        return f"{ksp.getType()}/{ksp.getPC().getType()}"

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

    def describe(self) -> dict:
        """JSON-ready record of the solver: prefixes, tolerances, options and the
        KSP/PC types PETSc really uses (command-line options included)."""
        return {
            "prefix": self.prefix,
            "adjoint_prefix": self.adjoint_prefix,
            "options": {k: option_value(v) for k, v in self.options.items()},
            "adjoint_options": {k: option_value(v) for k, v in self._adjoint_own.items()},
            "max_it": self._max_it,
            "rtol": self._rtol,
            "atol": self._atol,
            "adjoint_max_it": self.adjoint_max_it,
            "forward": {"ksp_type": self.ksp.getType(), "pc_type": self.ksp.getPC().getType()},
            "adjoint": {"ksp_type": self._adj.getType(), "pc_type": self._adj.getPC().getType()},
            "ranks": self.ksp.getComm().getSize(),
        }

    def clone(self, **changes) -> Configuration:
        """A new solver with the same settings, some of them changed.

        Options, prefix, tolerances, adjoint settings, ``divtol``, null spaces, the
        symmetry declaration and the communicator are copied; keyword arguments
        (any of `KSPSolver`'s) replace them.
        """
        kwargs = {
            "options": dict(self.options),
            "prefix": self.prefix,
            "max_it": self._max_it,
            "rtol": self._rtol,
            "atol": self._atol,
            "adjoint": self.adjoint,
            "divtol": self._divtol,
            "nullspace": self.nullspace,
            "transpose_nullspace": self.transpose_nullspace,
            "symmetric": self.declared_symmetric,
            "check_structure": self.check_structure,
            "comm": self.comm,
        }
        kwargs.update(changes)
        return type(self)(**kwargs)


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
