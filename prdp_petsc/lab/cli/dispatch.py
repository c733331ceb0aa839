"""Which code runs a sub-command (`COMMANDS`), under the command line's conventions
(`guarded`): an error prints one line (``--debug``: the traceback) and exits 1, Ctrl-C
exits 130, and an error on one rank of a ``--parallel`` run stops all of them.

A command is either one of the command line's own (``run``, ``compare``: `training`;
``scene``: a scene file's ``COMMANDS``) or a report tool, a module with ``main(argv)``
imported once PETSc started.  `main` is the ``prdp-petsc`` console script,
`scene_main` the ``__main__`` of every scene file.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import inspect
import logging
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from . import training
from .arguments import add_debug
from .petsc import apply_warning_options, init_petsc, split_petsc_options

__all__ = ["COMMANDS", "Command", "guarded", "main", "missing_lab_packages", "scene_main"]


def guarded(command, debug: bool, out: str | None = None, args=None) -> int:
    """Run ``command()``; an error prints one line (unless ``debug``) and returns 1."""
    parallel = getattr(args, "parallel", None) is not None
    try:
        return command()
    except KeyboardInterrupt:
        if debug:
            raise
        where = f"; results so far in {out}/" if out else ""
        print(f"prdp-petsc: interrupted (Ctrl-C){where}", file=sys.stderr)
        return 130
    except Exception as err:
        if debug and parallel:
            import traceback

            traceback.print_exc()
        if not debug:
            message = " ".join(str(err).split()) or "(no message)"
            print(
                f"prdp-petsc: error: {type(err).__name__}: {message} (--debug shows the traceback)",
                file=sys.stderr,
            )
        if parallel:  # the other ranks may be waiting in a collective call
            from mpi4py import MPI

            if MPI.COMM_WORLD.Get_size() > 1:
                sys.stderr.flush()
                MPI.COMM_WORLD.Abort(1)
        if debug:
            raise
        return 1


def debug_flag(argv: list[str]) -> bool:
    """Whether `argv` asks for tracebacks (``--debug``), before its own parser reads it."""
    debug = argparse.ArgumentParser(add_help=False)
    add_debug(debug)
    return debug.parse_known_args(argv)[0].debug


@dataclass(frozen=True)
class Command:
    """One sub-command: its summary, and the report tool (`module`, whose ``main(argv)``
    runs it) or the command line's own function (`own`, ``own(name, argv)``)."""

    summary: str
    module: str | None = None
    own: object = None

    def __call__(self, name: str, argv: list[str]) -> int:
        if self.own is not None:
            return self.own(name, argv)
        ours, petsc = split_petsc_options(argv)
        init_petsc(petsc)
        tool = importlib.import_module(self.module)
        return guarded(lambda: tool.main(ours), debug_flag(ours))


def _training(name: str, argv: list[str], scene_file: str | None = None, prog="prdp-petsc") -> int:
    parser = training.make_parser(prog=prog, scene_arg=scene_file is None, description=_usage())
    args, scene = training.parse(parser, [name, *argv], scene_file)
    out = args.out or getattr(args, "resume", None)
    return guarded(lambda: training.execute(args, scene), args.debug, out, args)


def _scene(name: str, argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="prdp-petsc scene",
        usage="%(prog)s SCENE_FILE [NAME [ARGS ...]] [--debug] [PETSc options]",
        description="Run the command NAME that SCENE_FILE declares in COMMANDS "
        "(prdp_petsc.lab.training.scene); without NAME, list them.",
    )
    if argv[:1] in (["-h"], ["--help"]):
        parser.print_help()
        return 0
    if not argv or argv[0].startswith("-"):
        parser.error("give a SCENE_FILE, e.g. demos/ns2d.py")
    return scene_command(argv[0], argv[1:], f"prdp-petsc scene {argv[0]}")


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
    names = ("matplotlib", "tqdm", "tensorboard", "jinja2", "pandas", "tabulate")
    return [name for name in names if importlib.util.find_spec(name) is None]


def _usage() -> str:
    from . import __doc__ as usage

    return usage


def _start(argv: list[str] | None) -> list[str]:
    apply_warning_options()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return list(sys.argv[1:] if argv is None else argv)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``prdp-petsc`` console script."""
    argv = _start(argv)
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
    argv = _start(argv)
    prog = Path(scene_file).name
    if argv[:1] in (["-h"], ["--help"]):
        training.make_parser(prog=prog, scene_arg=False, description=_usage()).print_help()
        print()
        return scene_command(scene_file, [], prog)
    if argv and not argv[0].startswith("-") and argv[0] not in training.COMMANDS:
        return scene_command(scene_file, argv, prog, also=training.COMMANDS)
    if not argv or argv[0] not in training.COMMANDS:
        argv.insert(0, "compare")
    return _training(argv[0], argv[1:], scene_file, prog)


def scene_command(scene_file: str, argv: list[str], prog: str, also: tuple = ()) -> int:
    """The scene's command ``argv[0]`` from its ``COMMANDS`` (without one, their list),
    under ``run``'s conventions; `prog` names the scene in the usage, `also` the other
    commands that reach it there."""
    ours, petsc = split_petsc_options(argv)
    init_petsc(petsc)  # before the scene is imported: it imports PETSc
    return guarded(lambda: _run_scene_command(scene_file, ours, prog, also), debug_flag(ours))


def _run_scene_command(scene_file: str, argv: list[str], prog: str, also: tuple) -> int:
    from ..training.scene import load_scene, preset_config

    module = load_scene(scene_file)
    commands = _scene_commands(module)
    name = Path(scene_file).name
    if not argv or argv[0] in ("-h", "--help"):
        print(_format_commands(name, commands, prog))
        return 0
    usage = argparse.ArgumentParser(prog=prog, usage="%(prog)s NAME [ARGS ...]")
    if argv[0] not in commands:
        known = ", ".join([*also, *commands]) or "none (it defines no COMMANDS)"
        if argv[0].startswith("-"):
            usage.error(f"give the command NAME before its options; {name}'s commands: {known}")
        usage.error(f"unknown command {argv[0]!r}; {name}'s commands: {known}")
    configure = commands[argv[0]]
    parser = argparse.ArgumentParser(
        prog=f"{prog} {argv[0]}",
        description=inspect.getdoc(configure),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_debug(parser)
    command = configure(parser)
    if not callable(command):
        raise TypeError(
            f"{name}: COMMANDS[{argv[0]!r}] must return the function that runs the parsed "
            f"arguments, got {type(command).__name__}"
        )
    args = parser.parse_args(argv[1:])
    if isinstance(getattr(args, "preset", None), str):  # checked as run's --preset is
        try:
            preset_config(module, args.preset)
        except ValueError as err:
            parser.error(f"--preset: {err}")
    status = command(args)
    return 0 if status is None else status


def _scene_commands(module) -> dict:
    """The scene's ``COMMANDS``, checked: names that are words (not ``run`` or
    ``compare``) mapped to functions."""
    commands = getattr(module, "COMMANDS", {})
    where = Path(module.__file__).name
    if not isinstance(commands, dict):
        raise TypeError(f"{where}: COMMANDS must be a dict, got {type(commands).__name__}")
    for key, value in commands.items():
        if not (isinstance(key, str) and re.fullmatch(r"[a-z][a-z0-9_-]*", key)):
            raise ValueError(f"{where}: COMMANDS: {key!r} is not a command name (a-z, 0-9, _, -)")
        if key in training.COMMANDS:
            raise ValueError(f"{where}: COMMANDS: {key!r} is the harness's; name it otherwise")
        if not callable(value):
            raise TypeError(f"{where}: COMMANDS[{key!r}] must be a function, got {value!r}")
    return commands


def _format_commands(name: str, commands: dict, prog: str) -> str:
    if not commands:
        return f"{name} defines no commands of its own (COMMANDS); run and compare take any scene"
    lines = [f"commands of {name} ({prog} NAME -h for the arguments of one):"]
    width = max(map(len, commands))
    for key, configure in commands.items():
        summary = (inspect.getdoc(configure) or "").split("\n", 1)[0]
        lines.append(f"  {key:<{width}}  {summary}")
    return "\n".join(lines)
