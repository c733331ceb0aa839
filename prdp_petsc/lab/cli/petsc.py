"""PETSc on the command line: its options told from ours (`split_petsc_options`),
PETSc started with them (`init_petsc`), and the warning filters that name this
package's categories (`apply_warning_options`).  Nothing here imports PETSc or torch
at module level: `init_petsc` must run first."""

from __future__ import annotations

import importlib
import re
import sys
import warnings

from prdp_petsc.core.options import split_petsc_options

__all__ = ["apply_warning_options", "init_petsc", "split_petsc_options"]


_ACTIONS = ("default", "always", "ignore", "module", "once", "error")


def apply_warning_options(options: list[str] | None = None) -> None:
    """Apply the warning filters of `options` (default ``sys.warnoptions``) whose
    category is one of prdp_petsc's, with Python's meaning.

    Python reads ``-W`` and ``PYTHONWARNINGS`` before site-packages are importable, so
    it drops ``-W error::prdp_petsc.errors.UnusedOptionWarning`` (``Invalid -W option
    ignored``); the command line calls this first thing, so the filter applies after all.
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
    """Start PETSc with the command line's PETSc options (``petsc4py.init``, before the
    first ``from petsc4py import PETSc``, so that ``-log_view`` works); if PETSc already
    runs (the CLI called in-process), insert them into its options database."""
    if "petsc4py.PETSc" in sys.modules:
        if options:
            from petsc4py import PETSc

            PETSc.Options().insertString(" ".join(options))
        return
    import petsc4py

    petsc4py.init([sys.argv[0] or "prdp-petsc", *options])
