"""PETSc option specifications: dicts or option strings, as PETSc's database wants them."""

from __future__ import annotations

import shlex

from ..errors import InputError

__all__ = [
    "KSP_ROOTS",
    "PushedOptions",
    "is_number",
    "option_value",
    "parse_options",
    "prefixed_options",
    "split_petsc_options",
]


def parse_options(options: dict | str | None) -> dict:
    """Turn ``{"ksp_type": "cg"}`` or ``"-ksp_type cg -ksp_monitor"`` into a dict."""
    if options is None:
        return {}
    if isinstance(options, dict):
        return {str(k).lstrip("-"): v for k, v in options.items()}
    if not isinstance(options, str):
        raise TypeError(f"options must be a dict or a PETSc option string, got {type(options)}")
    out: dict = {}
    tokens = shlex.split(options)
    i = 0
    while i < len(tokens):
        tok = tokens[i]
        if not tok.startswith("-") or is_number(tok):
            raise InputError(f"options: expected '-name', got {tok!r} in {options!r}")
        value = None
        if i + 1 < len(tokens) and (not tokens[i + 1].startswith("-") or is_number(tokens[i + 1])):
            value = tokens[i + 1]
            i += 1
        out[tok.lstrip("-")] = value
        i += 1
    return out


def is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def split_petsc_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """Separate PETSc options (``-name [value]``, one dash) from a script's own
    (``--name``, ``-h`` and everything after a bare ``--``): ``(ours, petsc)``.

    A script that takes PETSc options on its command line hands them to PETSc before
    PETSc is first imported::

        from prdp_petsc.core.options import split_petsc_options

        ours, petsc = split_petsc_options(sys.argv[1:])
        petsc4py.init([sys.argv[0], *petsc])  # then every KSPSolver reads them
        args = parser.parse_args(ours)

    A negative number (``--seed -10``) is a value, not an option name.  A token after a
    PETSc option that does not start with ``-`` is taken as its value, so a flag such as
    ``-log_view`` goes after the script's positional arguments.  Plain
    Python: it imports neither PETSc nor torch.
    """
    ours, petsc = [], []
    i = 0
    while i < len(argv):
        tok = argv[i]
        if tok == "--":
            ours.extend(argv[i:])
            break
        if (
            tok.startswith("-")
            and not tok.startswith("--")
            and tok != "-h"
            and len(tok) > 2
            and not is_number(tok)  # "--seed -10": a value of ours
        ):
            petsc.append(tok)
            nxt = argv[i + 1] if i + 1 < len(argv) else None
            if nxt is not None and (not nxt.startswith("-") or is_number(nxt)):
                petsc.append(nxt)
                i += 1
        else:
            ours.append(tok)
        i += 1
    return ours, petsc


def option_value(value) -> str | None:
    if value is None or value is True:
        return None
    if value is False:
        return "false"
    return str(value)


#: option roots that belong to a KSP and its PC (sub-solvers included); with the
#: empty prefix only these are read as the forward solver's, e.g. not ``-log_view``
KSP_ROOTS = ("ksp_", "pc_", "mg_", "sub_", "fieldsplit_", "redundant_", "telescope_")


def prefixed_options(prefix: str, exclude: str | None = None) -> dict:
    """Options in PETSc's database under `prefix` (prefix removed), except under `exclude`.

    With the empty prefix, only names with a KSP/PC root (`KSP_ROOTS`) are taken.
    """
    from petsc4py import PETSc

    out = {}
    for name, value in PETSc.Options().getAll().items():
        if not name.startswith(prefix) or (exclude and name.startswith(exclude)):
            continue
        key = name[len(prefix) :]
        if prefix or key.startswith(KSP_ROOTS):
            out[key] = value
    return out


class PushedOptions:
    """Options written into PETSc's database while a block runs, removed afterwards.

    Names already in the database (the command line) are left alone: they win.
    With ``watch=True`` the names that PETSc read during the block are collected
    in `used` (``PetscOptionsUsed``) before they are removed.
    """

    def __init__(self, items: list[tuple[str, object]], *, watch: bool = False):
        self.items = [(name, option_value(value)) for name, value in items]
        self.watch = watch
        self.used: set[str] = set()
        self._pushed: list[str] = []

    def __enter__(self) -> PushedOptions:
        if not self.items:
            return self
        from petsc4py import PETSc

        opts = PETSc.Options()
        for name, value in self.items:
            if not opts.hasName(name):
                opts.setValue(name, value)
                self._pushed.append(name)
        return self

    def __exit__(self, *exc) -> bool:
        if not self.items:
            return False
        from petsc4py import PETSc

        opts = PETSc.Options()
        if self.watch:
            self.used = {name for name, _ in self.items if opts.used(name)}
        for name in self._pushed:
            opts.delValue(name)
        self._pushed = []
        return False
