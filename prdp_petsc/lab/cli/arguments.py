"""The command line's shared arguments: one spelling per concept, one parser per value.

A positional ``SCENE_FILE``; ``--preset NAME``; ``--routes ksp/pc,...``; ``--seeds 0-3``
or ``0,2,5``; ``--k K [K ...]`` for fixed Ks and ``--k-max K`` for a bound; counts are
integers >= 1.  Old spellings (``--quick``, ``--ksp-type``/``--pc-type``, ``--scene
FILE``, ``--seeds 0 1 2``, ``--ks 2,4,8``) still parse and say on stderr that they go
in the next release.
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


class DeprecatedAlias(argparse.Action):
    """An old option, stored in `dest` as the new one would, said so on stderr; without a
    value (``nargs=0``) it stores `const`."""

    def __init__(self, option_strings, dest, *, new: str, **kwargs):
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        deprecated(option_string, self.new)
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)


class DeprecatedFlag(DeprecatedAlias):
    """An old flag without a value that stands for ``NEW VALUE`` (`const`)."""

    def __init__(self, option_strings, dest, *, const, new: str, **kwargs):
        super().__init__(option_strings, dest, nargs=0, const=const, new=new, **kwargs)


def add_debug(parser: argparse.ArgumentParser) -> None:
    """``--debug``: show the traceback of an error (otherwise one line, exit status 1)."""
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")


def add_size_preset(parser: argparse.ArgumentParser, quick: str = "small sizes") -> None:
    """A report tool's ``--preset quick|paper`` (default paper) and the old ``--quick``."""
    parser.add_argument(
        "--preset", choices=SIZE_PRESETS, default="paper",
        help=f"paper (the default) or quick: {quick}",
    )  # fmt: skip
    parser.add_argument(
        "--quick", action=DeprecatedFlag, dest="preset", const="quick", new="--preset quick",
        help=argparse.SUPPRESS,
    )  # fmt: skip
