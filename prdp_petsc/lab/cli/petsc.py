"""PETSc on the command line: its options told from ours (`split_petsc_options`),
PETSc started with them (`init_petsc`), and the warning filters that name this
package's categories (`apply_warning_options`).

Arguments that start with a single ``-`` and are not ours are PETSc options
(``-heat_ksp_type cg -heat_ksp_monitor -log_view``): PETSc starts with them
(``petsc4py.init``), so the scene's KSPs read them at ``KSPSetFromOptions`` and
start-up options such as ``-log_view`` work as in any PETSc program.  Nothing here
imports PETSc (or torch) at module level: `init_petsc` must run first.
"""

from __future__ import annotations

import importlib
import re
import sys
import warnings

from prdp_petsc.core.options import split_petsc_options

__all__ = ["apply_warning_options", "init_petsc", "split_petsc_options"]


_ACTIONS = ("default", "always", "ignore", "module", "once", "error")


def apply_warning_options(options: list[str] | None = None) -> None:
    """Apply the warning filters of `options` whose category is one of prdp_petsc's.

    Python reads ``-W`` and ``PYTHONWARNINGS`` (both end up in ``sys.warnoptions``,
    the default of `options`) before its site-packages are on ``sys.path``, so it
    cannot import ``prdp_petsc.errors`` for
    ``-W error::prdp_petsc.errors.UnusedOptionWarning``: it prints ``Invalid -W
    option ignored: invalid module name`` and drops the filter.  The command line
    calls this first thing, so those filters apply after all.

    Parameters
    ----------
    options : list of str, optional
        Filters in Python's syntax, ``action:message:category:module:lineno``,
        with Python's meaning (an abbreviated action, a message matched from its
        start, a module matched whole, later filters first).  Filters whose
        category is not in ``prdp_petsc`` are left to Python, which applied them.
        They go before the filters Python set at start-up.
    """
    for option in sys.warnoptions if options is None else options:
        fields = [field.strip() for field in option.split(":")]
        fields += [""] * (5 - len(fields))
        if len(fields) != 5 or not fields[2].startswith("prdp_petsc."):
            continue
        action, message, category, module, lineno = fields
        try:
            action = _warning_action(action)
            owner, _, name = category.rpartition(".")
            cls = getattr(importlib.import_module(owner), name, None)
            if not (isinstance(cls, type) and issubclass(cls, Warning)):
                raise ValueError(f"{category} is not a warning category")
            line = int(lineno or 0)
            if line < 0:
                raise ValueError(f"invalid line number {lineno!r}")
        except (ImportError, ValueError) as err:
            print(f"prdp-petsc: invalid warning filter {option!r} ignored: {err}", file=sys.stderr)
            continue
        module = re.escape(module) + r"\Z" if module else ""
        warnings.filterwarnings(action, re.escape(message), cls, module, line)


def _warning_action(text: str) -> str:
    """Python's reading of a ``-W`` action: empty is ``default``, a prefix names one."""
    if not text:
        return "default"
    if text == "all":
        return "always"
    for action in _ACTIONS:
        if action.startswith(text):
            return action
    raise ValueError(f"invalid action {text!r}")


def init_petsc(options: list[str]) -> None:
    """Start PETSc with the command line's PETSc options, as petsc4py's demos do.

    ``petsc4py.init`` must come before the first ``from petsc4py import PETSc``:
    options read only at ``PetscInitialize`` (``-log_view``, ``-malloc_debug``)
    work only then.  If PETSc is already running (the CLI called in-process, as in
    tests), the options go into its options database instead.
    """
    if "petsc4py.PETSc" in sys.modules:
        if options:
            from petsc4py import PETSc

            PETSc.Options().insertString(" ".join(options))
        return
    import petsc4py

    petsc4py.init([sys.argv[0] or "prdp-petsc", *options])
