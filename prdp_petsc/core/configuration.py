"""What a `KSPSolver` tells PETSc: options, prefixes and tolerances, as one value.

The PRDP controller owns ``max_it``, so tolerances are set by the program, never
by options: `refuse_tolerance_options` says so for ``-<prefix>ksp_max_it`` and
friends, `rejected_options_message` names an option PETSc refused, and
`Configuration.unused` lists options PETSc never read (reported as
`prdp_petsc.errors.UnusedOptionWarning`).  A `Configuration` holds no PETSc
object: `Configuration.apply` writes its tolerances into the KSPs it is given.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from petsc4py import PETSc

from ..errors import InputError, UnusedOptionWarning, plain
from .options import option_value, parse_options, prefixed_options
from .results import Side
from .settings import AdjointSettings, check_tolerances

__all__ = [
    "TYPE_KEYS",
    "Configuration",
    "UnusedOptionWarning",
    "refuse_tolerance_options",
    "rejected_options_message",
]

#: "not given" for `Configuration.set_tolerances` (None is a value to refuse)
KEEP = object()
_TOLERANCE_KEYS = ("ksp_rtol", "ksp_atol", "ksp_max_it", "ksp_divtol")
_OFF = ("0", "false", "no")
#: options that choose the solver's Mat and Vec types (`prdp_petsc.core.device`)
TYPE_KEYS = ("vec_type", "mat_type")


class Configuration:
    """Options, prefixes and tolerances of the forward and adjoint KSPs, validated.

    Parameters are those of `KSPSolver` (``options``, ``prefix``, ``max_it``,
    ``rtol``, ``atol``, ``adjoint``, ``divtol``).  Tolerances change through
    `set_tolerances` and `set_adjoint_max_it` (validated), and reach PETSc
    through `apply`.
    """

    def __init__(self, options, prefix: str, max_it, rtol, atol, adjoint, divtol):
        check_tolerances(max_it, rtol, atol)
        if divtol is not None and not (np.isfinite(divtol) and divtol > 0):
            raise InputError(f"divtol must be finite and > 0, got {plain(divtol)!r}")
        self.options = parse_options(options)
        refuse_tolerance_options(self.options, "options", "max_it=, rtol=, atol=, divtol=")
        if adjoint is None:
            adjoint = AdjointSettings()
        elif isinstance(adjoint, dict):
            adjoint = AdjointSettings(**adjoint)
        else:
            adjoint = dataclasses.replace(adjoint)  # ours to change (adjoint max_it)
        if adjoint.max_it is not None or adjoint.rtol is not None or adjoint.atol is not None:
            check_tolerances(
                max_it if adjoint.max_it is None else adjoint.max_it,
                0.0 if adjoint.rtol is None else adjoint.rtol,
                0.0 if adjoint.atol is None else adjoint.atol,
                "adjoint ",
            )
        self.adjoint = adjoint
        self.adjoint_own = parse_options(adjoint.options)
        refuse_tolerance_options(
            self.adjoint_own, "adjoint options", "AdjointSettings(max_it=, ...)"
        )
        if typed := [k for k in self.adjoint_own if k in TYPE_KEYS]:
            raise InputError(
                f"{typed} in the adjoint options: the adjoint solves with the forward's Mat "
                "and Vecs, so their types are the forward options' (KSPSolver options)"
            )
        self.adjoint_options = {**self.options, **self.adjoint_own}
        self.prefix = prefix
        self.adjoint_prefix = adjoint.prefix if adjoint.prefix is not None else prefix + "adj_"
        for p in dict.fromkeys((prefix, self.adjoint_prefix)):
            refuse_tolerance_options(
                prefixed_options(p), f"command-line options under prefix {p!r}", "the program"
            )
        self.max_it = int(max_it)
        self.rtol = float(rtol)
        self.atol = float(atol)
        self.divtol = divtol

    # -- options -------------------------------------------------------------------
    def option_items(self) -> list[tuple[str, object]]:
        """(name, value) pairs to write into PETSc's database for both KSPs.

        The adjoint inherits the forward options *as the forward KSP sees them*, so
        ``-fwd_ksp_type cg`` on the command line changes both solves unless
        ``-fwd_adj_ksp_type`` says otherwise.
        """
        exclude = self.adjoint_prefix if self.adjoint_prefix.startswith(self.prefix) else None
        forward = {**self.options, **prefixed_options(self.prefix, exclude)}
        adjoint = {**forward, **self.adjoint_own}
        return [(self.prefix + k, v) for k, v in self.options.items()] + [
            (self.adjoint_prefix + k, v) for k, v in adjoint.items()
        ]

    def shares_pc(self) -> bool:
        """Whether the adjoint KSP can share the forward PC (no PC options of its own)."""
        if any(k.startswith("pc_") for k in self.adjoint_own):
            return False
        cmdline = prefixed_options(self.adjoint_prefix)
        # an explicit transpose re-points the adjoint's operators (and a shared PC) to Aᵀ
        explicit = "ksp_use_explicittranspose"
        for given in (self.adjoint_options, cmdline):
            if explicit in given and option_value(given[explicit]) not in _OFF:
                return False
        return not any(k.startswith("pc_") for k in cmdline)

    def unused(self, kind: Side, used: set[str]) -> list[str]:
        """Option names of the `kind` KSP (forward or adjoint) that PETSc never read.

        `used` holds the names PETSc read while they were pushed; the command line
        under the KSP's own prefix is included.
        """
        adjoint = kind is Side.ADJOINT
        prefix = self.adjoint_prefix if adjoint else self.prefix
        given = self.adjoint_own if adjoint else self.options
        names = {prefix + k for k in given}
        if prefix:  # the command line under a prefix of its own
            exclude = None if adjoint else self.adjoint_prefix
            names |= {prefix + k for k in prefixed_options(prefix, exclude)}
        opts = PETSc.Options()
        return sorted(n for n in names if n not in used and not opts.used(n))

    # -- tolerances ------------------------------------------------------------------
    @property
    def adjoint_max_it(self) -> int:
        """Adjoint iteration cap: `AdjointSettings.max_it` or the forward `max_it`."""
        return self.adjoint.max_it if self.adjoint.max_it is not None else self.max_it

    def set_tolerances(self, *, max_it=KEEP, rtol=KEEP, atol=KEEP) -> None:
        """Change the forward tolerances (those not given are kept), validated together."""
        max_it = self.max_it if max_it is KEEP else max_it
        rtol = self.rtol if rtol is KEEP else rtol
        atol = self.atol if atol is KEEP else atol
        check_tolerances(max_it, rtol, atol)
        self.max_it, self.rtol, self.atol = int(max_it), float(rtol), float(atol)

    def set_adjoint_max_it(self, value: int | None) -> None:
        """Give the adjoint its own cap, or None to follow the forward one."""
        if value is not None:
            check_tolerances(value, 0.0, 0.0, "adjoint ")
        self.adjoint.max_it = None if value is None else int(value)

    def apply(self, ksp: PETSc.KSP, adj: PETSc.KSP) -> None:
        """``KSPSetTolerances`` on the forward and adjoint KSPs."""
        dt = self.divtol if self.divtol is not None else PETSc.DEFAULT
        ksp.setTolerances(rtol=self.rtol, atol=self.atol, divtol=dt, max_it=self.max_it)
        a = self.adjoint
        adj.setTolerances(
            rtol=self.rtol if a.rtol is None else a.rtol,
            atol=self.atol if a.atol is None else a.atol,
            divtol=dt,
            max_it=self.adjoint_max_it,
        )

    # -- records -----------------------------------------------------------------------
    def describe(self) -> dict:
        """JSON-ready record: prefixes, options and tolerances."""
        return {
            "prefix": self.prefix,
            "adjoint_prefix": self.adjoint_prefix,
            "options": {k: option_value(v) for k, v in self.options.items()},
            "adjoint_options": {k: option_value(v) for k, v in self.adjoint_own.items()},
            "max_it": self.max_it,
            "rtol": self.rtol,
            "atol": self.atol,
            "adjoint_max_it": self.adjoint_max_it,
        }

    def arguments(self) -> dict:
        """The `KSPSolver` keyword arguments that rebuild this configuration."""
        return {
            "options": dict(self.options),
            "prefix": self.prefix,
            "max_it": self.max_it,
            "rtol": self.rtol,
            "atol": self.atol,
            "adjoint": self.adjoint,
            "divtol": self.divtol,
        }


def refuse_tolerance_options(options: dict, where: str, use: str) -> None:
    bad = [k for k in options if k in _TOLERANCE_KEYS]
    if bad:
        raise InputError(
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
