"""The command line's shared arguments: one spelling per concept, declared once.

A positional ``SCENE_FILE``; ``--preset NAME``; ``--routes ksp/pc,...``; ``--seeds 0-3``
or ``0,2,5``; ``--k K [K ...]`` for fixed Ks and ``--k-max K`` for a bound; counts are
integers >= 1; ``--out DIR``, ``--threads T`` and ``--debug`` mean the same in every
command.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..parsing import parse_seeds, positive_int

__all__ = [
    "add_debug",
    "add_epochs",
    "add_k",
    "add_out",
    "add_preset",
    "add_routes",
    "add_schedules",
    "add_seeds",
    "add_size_preset",
    "add_threads",
    "positive",
    "routes",
    "schedules",
    "seeds",
]

#: The sizes of the report tools' ``--preset``: quick (seconds: a smoke test) or paper
SIZE_PRESETS = ("quick", "paper")


def positive(text: str) -> int:
    """An argument that is an integer >= 1."""
    try:
        return positive_int(int(text), "the value")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None


def seeds(text: str) -> list[int]:
    """``--seeds``: ``0-3``, ``0,2,5`` or a mix."""
    try:
        return parse_seeds(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def routes(text: str) -> tuple[str, ...]:
    """``--routes``: the comma-separated routes (the command checks them)."""
    return tuple(r.strip() for r in text.split(",") if r.strip())


def schedules(text: str) -> tuple[str, ...]:
    """``--schedules``: the comma-separated names, each once (`compare` checks them:
    importing it here would start PETSc before `init_petsc`)."""
    names = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    if not names:
        raise argparse.ArgumentTypeError(f"expected e.g. prdp,rtol, got {text!r}")
    return names


def add_debug(parser) -> None:
    """``--debug``: show the traceback of an error (otherwise one line, exit status 1)."""
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")


def add_out(parser, help: str = "output folder", required: bool = True) -> None:
    """``--out DIR``: the folder the command writes into, a `Path`."""
    parser.add_argument("--out", type=Path, required=required, metavar="DIR", help=help)


def add_preset(parser, default: str | None = "quick", help: str | None = None) -> None:
    """``--preset NAME``: one of the scene's presets (default `default`)."""
    parser.add_argument("--preset", default=default, help=help or f"preset (default {default})")


def add_k(parser, default: int | list[int] | None, help: str) -> None:
    """``--k K``, the fixed K of every solve, an integer >= 1; a list `default` takes
    several, ``--k K [K ...]`` (None: the command's own default, which `help` says)."""
    several = isinstance(default, list)
    if default is not None:
        help += f" (default {' '.join(map(str, default)) if several else default})"
    parser.add_argument(
        "--k", type=positive, nargs="+" if several else None, default=default, metavar="K",
        help=help,
    )  # fmt: skip


def add_epochs(parser, default: int | None = None, help: str = "epochs") -> None:
    """``--epochs N``: how many epochs to train (None: the preset's)."""
    what = "the preset's" if default is None else default
    help = f"{help} (default: {what})"
    parser.add_argument("--epochs", type=positive, default=default, help=help)


def add_routes(parser) -> None:
    """``--routes``: the solvers a comparison runs PRDP and full fidelity with."""
    parser.add_argument(
        "--routes", type=routes,
        help="other solvers to run PRDP and full fidelity with: ksp/pc[:option=value,...] "
        "(cg/icc,cg/gamg) or the scene's ROUTES names (default: its preset's; '' none; "
        "auto: a short pilot at full fidelity picks one)",
    )  # fmt: skip


def add_schedules(parser, default: str = "prdp") -> None:
    """``--schedules``: the reduced-fidelity schedules a comparison runs on every route."""
    parser.add_argument(
        "--schedules", type=schedules, default=default,
        help="reduced-fidelity schedules to run on every route, comma-separated: prdp (PRDP "
        f"on the iteration cap K), auto or rtol (PRDP on PETSc's rtol) (default {default})",
    )  # fmt: skip


def add_size_preset(parser, quick: str = "small sizes") -> None:
    """A report tool's ``--preset quick|paper`` (default paper); `quick` says what it runs."""
    parser.add_argument(
        "--preset", choices=SIZE_PRESETS, default="paper",
        help=f"paper (the default) or quick: {quick}",
    )  # fmt: skip


def add_seeds(parser, default: str | None = "0-2", help: str = "seeds") -> None:
    """``--seeds 0-3`` or ``0,2,5`` (`default` in the same spelling; None: no default)."""
    suffix = "" if default is None else f" (default {default})"
    parser.add_argument(
        "--seeds", type=seeds, default=default, help=f"{help}, e.g. 0-3 or 0,2,5{suffix}"
    )


def add_threads(parser) -> None:
    """``--threads T``: torch's thread count, default 1 (honest wall times when shared)."""
    parser.add_argument(
        "--threads", type=positive, default=1,
        help="torch threads (default 1: honest wall times on a shared machine)",
    )  # fmt: skip
