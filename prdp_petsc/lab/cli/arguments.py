"""The command line's shared arguments: one spelling per concept, one parser per value.

Every sub-command, the report tools' and the scenes' commands included, reads a
concept the same way:

* the scene: a positional ``SCENE_FILE``;
* problem size: ``--preset NAME`` (the report tools: ``quick`` or ``paper``,
  `add_size_preset`);
* KSP/PC solvers: ``--routes ksp/pc,...`` (`routes`);
* seeds: ``--seeds 0-3`` or ``--seeds 0,2,5`` (`seeds`);
* the fixed K of every solve: ``--k K`` (several: ``--k K K ...``); an upper bound
  on K: ``--k-max K``;
* counts (``--epochs``, ``--threads``, ``--repeats``, ...): integers >= 1
  (`positive`).

Old spellings keep working for one release, each with one line on stderr
(`deprecated`, `DeprecatedFlag`, `DeprecatedAlias`): ``--quick`` (``--preset
quick``), ``--ksp-type``/``--pc-type`` (``--routes ksp/pc``), ``--scene FILE`` (the
positional scene file), ``unseen --seeds 0 1 2`` (``--seeds 0-2``) and topopt3d's
``results --ks 2,4,8`` (``--k 2 4 8``).
"""

from __future__ import annotations

import argparse
import sys

from ..parsing import parse_seeds, positive_int

__all__ = [
    "DeprecatedAlias",
    "DeprecatedFlag",
    "add_debug",
    "add_size_preset",
    "deprecated",
    "positive",
    "routes",
    "seeds",
]

#: The sizes of the report tools' ``--preset``: quick (seconds: a smoke test) or paper
SIZE_PRESETS = ("quick", "paper")


def deprecated(old: str, new: str) -> None:
    """Say on stderr that the spelling `old` goes in the next release, for `new`."""
    print(
        f"prdp-petsc: {old} is deprecated and goes in the next release; use {new}", file=sys.stderr
    )


def positive(text: str) -> int:
    """An argument that is an integer >= 1 (`prdp_petsc.lab.parsing.positive_int`)."""
    try:
        return positive_int(int(text), "the value")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None


def seeds(text: str) -> list[int]:
    """``--seeds``: ``0-3``, ``0,2,5`` or a mix (`prdp_petsc.lab.parsing.parse_seeds`)."""
    try:
        return parse_seeds(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def routes(text: str) -> tuple[str, ...]:
    """``--routes``: the comma-separated routes, split (the command checks them against
    the scene or problem: `prdp_petsc.lab.training.routes.parse_routes`)."""
    return tuple(r.strip() for r in text.split(",") if r.strip())


class DeprecatedFlag(argparse.Action):
    """An old flag without a value that stands for ``NEW VALUE``: stores `const` in
    `dest` (the new option's) and says so (`deprecated`)."""

    def __init__(self, option_strings, dest, *, const, new: str, **kwargs):
        super().__init__(option_strings, dest, nargs=0, const=const, **kwargs)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        deprecated(option_string, self.new)
        setattr(namespace, self.dest, self.const)


class DeprecatedAlias(argparse.Action):
    """An old option with a value, stored in `dest` as before, and said so."""

    def __init__(self, option_strings, dest, *, new: str, **kwargs):
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        deprecated(option_string, self.new)
        setattr(namespace, self.dest, values)


def add_debug(parser: argparse.ArgumentParser) -> None:
    """``--debug``: show the traceback of an error (otherwise one line, exit status 1)."""
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")


def add_size_preset(parser: argparse.ArgumentParser, quick: str = "small sizes") -> None:
    """A report tool's ``--preset quick|paper`` (default paper; `quick` says what quick
    does), and the old ``--quick`` for ``--preset quick``."""
    parser.add_argument(
        "--preset",
        choices=SIZE_PRESETS,
        default="paper",
        help=f"paper (the default) or quick: {quick}",
    )
    parser.add_argument(
        "--quick", action=DeprecatedFlag, dest="preset", const="quick", new="--preset quick",
        help=argparse.SUPPRESS,
    )  # fmt: skip
