"""Which code runs a sub-command: one table (`COMMANDS`) for every one of them.

A command is either one of the command line's own (``run``, ``compare``, ``scene``:
`Command.own`, which applies the conventions itself, parsing its arguments before
PETSc starts) or a report tool, a module with ``main(argv)`` and its own parser: the
table's conventions apply around it (PETSc options start PETSc, ``--debug`` shows
tracebacks, an error prints one line).  `main` is the ``prdp-petsc`` console script,
`scene_main` the ``__main__`` of every scene file.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

from . import scene_commands, training
from .guard import debug_flag, guarded
from .petsc import apply_warning_options, init_petsc, split_petsc_options

__all__ = ["COMMANDS", "Command", "main", "missing_lab_packages", "scene_main"]


@dataclass(frozen=True)
class Command:
    """One sub-command: what it does, and the module that runs it (a report tool's
    `module` is imported only once PETSc started: it may import PETSc)."""

    summary: str
    module: str | None = None  # a report tool: module.main(argv)
    own: object = None  # the command line's own: own(name, argv)

    def __call__(self, name: str, argv: list[str]) -> int:
        if self.own is not None:
            return self.own(name, argv)
        ours, petsc = split_petsc_options(argv)
        init_petsc(petsc)
        tool = importlib.import_module(self.module)
        return guarded(lambda: tool.main(ours), debug_flag(ours))


def _training(name: str, argv: list[str]) -> int:
    return training.command(training.make_parser(prog="prdp-petsc", description=_usage()),
                            [name, *argv])  # fmt: skip


def _scene(name: str, argv: list[str]) -> int:
    return scene_commands.command(argv)


_REPORTS = "prdp_petsc.lab.reports"

#: Every sub-command of ``prdp-petsc``, in the order ``--help`` lists them.
COMMANDS = {
    "run": Command("train a scene once", own=_training),
    "compare": Command("PRDP against full fidelity, over seeds and routes", own=_training),
    "scene": Command("a scene file's own commands (its COMMANDS)", own=_scene),
    "bench": Command("benchmarks: bridge, mpi, elasticity, jax, gpu", f"{_REPORTS}.bench"),
    "work-precision": Command("error against time per KSP/PC and K", f"{_REPORTS}.workprecision"),
    "stability": Command("stiff and extreme cases", f"{_REPORTS}.stability"),
    "pages": Command("the results pages, or record a run for them", f"{_REPORTS}.pages"),
    "rollouts": Command("held-out rollouts of several runs", f"{_REPORTS}.rollouts"),
    "horizon": Command("m-step training against m: time and memory", f"{_REPORTS}.horizon"),
    "ablation": Command("compare --seeds once per lever", f"{_REPORTS}.ablation"),
    "unseen": Command("six problems PRDP was never tuned on", f"{_REPORTS}.unseen"),
    "defaults": Command("tuned PRDP against the default construction", f"{_REPORTS}.defaults"),
}


def missing_lab_packages() -> list[str]:
    """The packages of the ``lab`` extra that are not installed."""
    import importlib.util

    names = ("matplotlib", "tqdm", "jinja2")
    return [name for name in names if importlib.util.find_spec(name) is None]


def _usage() -> str:
    from . import __doc__ as usage

    return usage


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``prdp-petsc`` console script."""
    apply_warning_options()
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if argv[:1] == ["--version"]:
        from prdp_petsc import __version__

        print(f"prdp-petsc {__version__}")
        return 0
    missing = missing_lab_packages()
    if missing and argv and argv[0] not in ("-h", "--help"):
        print(
            f"prdp-petsc: the lab needs {', '.join(missing)}, which the library does not "
            "install: pip install 'prdp-petsc[lab]'",
            file=sys.stderr,
        )
        return 2
    if argv and argv[0] in COMMANDS:
        return COMMANDS[argv[0]](argv[0], argv[1:])
    if not argv or argv[0] in ("-h", "--help"):
        training.make_parser(prog="prdp-petsc", description=_usage()).print_help()
        width = max(map(len, COMMANDS))
        print("\ncommands:")
        for name, entry in COMMANDS.items():
            print(f"  {name:<{width}}  {entry.summary}")
        return 0
    usage = argparse.ArgumentParser(prog="prdp-petsc", usage="%(prog)s COMMAND [ARGS ...]")
    usage.error(f"unknown command {argv[0]!r}; the commands: {', '.join(COMMANDS)}")


def scene_main(scene_file: str, argv: list[str] | None = None) -> int:
    """Entry point of ``python demos/<scene>.py [run|compare|NAME] ...`` (default:
    compare); NAME is one of the scene's ``COMMANDS``, listed by ``-h``."""
    apply_warning_options()
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    prog = Path(scene_file).name
    parser = training.make_parser(prog=prog, scene_arg=False, description=_usage())
    if argv[:1] in (["-h"], ["--help"]):
        parser.print_help()
        print()
        return scene_commands.scene_command(scene_file, [], prog)
    if argv and not argv[0].startswith("-") and argv[0] not in training.COMMANDS:
        return scene_commands.scene_command(scene_file, argv, prog, also=training.COMMANDS)
    if not argv or argv[0] not in training.COMMANDS:
        argv.insert(0, "compare")
    return training.command(parser, argv, scene_file)
