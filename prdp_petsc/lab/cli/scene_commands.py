"""A scene file's own commands: ``prdp-petsc scene SCENE_FILE [NAME [ARGS ...]]``
(`command`) and ``python SCENE_FILE NAME ...`` (`scene_command`).

``scene SCENE_FILE NAME [ARGS ...]`` runs a command the scene file declares in
``COMMANDS`` (`prdp_petsc.lab.training.scene`), such as ``prdp-petsc scene demos/ns2d.py
adjoint --preset quick --k 8 64``; ``python demos/ns2d.py adjoint ...`` is the same
command.  Without NAME it lists them (``python demos/ns2d.py -h`` too).  Each command
parses its own arguments (``prdp-petsc scene demos/ns2d.py adjoint -h``); an argument
``--preset`` is checked against the scene's presets like ``run``'s.
"""

from __future__ import annotations

import argparse
import inspect
import re
from pathlib import Path

from .arguments import add_debug
from .guard import debug_flag, guarded
from .petsc import init_petsc, split_petsc_options
from .training import COMMANDS as TRAINING

__all__ = ["command", "scene_command"]


def scene_command(scene_file: str, argv: list[str], prog: str, also: tuple = ()) -> int:
    """``prdp-petsc scene SCENE_FILE [NAME ...]`` and ``python SCENE_FILE NAME ...``: the
    scene's command NAME from its ``COMMANDS`` (without NAME, their list), with the
    conventions of ``run``: PETSc options start PETSc (before the scene is imported:
    it imports PETSc), an error prints one line unless ``--debug``, usage errors exit 2.
    `prog` is how the usage names the scene (``prdp-petsc scene demos/ns2d.py``); `also`
    names the other commands that reach the scene there (for the error of a wrong NAME)."""
    ours, petsc = split_petsc_options(argv)
    init_petsc(petsc)
    return guarded(lambda: _dispatch_extra(scene_file, ours, prog, also), debug_flag(ours))


def _dispatch_extra(scene_file: str, argv: list[str], prog: str, also: tuple) -> int:
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
        if key in TRAINING:
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


def command(argv: list[str]) -> int:
    """``prdp-petsc scene SCENE_FILE [NAME [ARGS ...]]``."""
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
