"""The ``prdp-petsc`` command line.

Sub-commands::

    prdp-petsc run SCENE_FILE --schedule prdp|fixed:K [--preset quick|paper]
                   [--epochs N] [--seed S] --out DIR [PETSc options]
    prdp-petsc compare SCENE_FILE [--preset ...] [--epochs N] [--seed S] --out DIR
    prdp-petsc bench bridge --out DIR
    prdp-petsc work-precision PROBLEM --out DIR
    prdp-petsc stability --out DIR

Arguments that start with ``-`` and are not ours are PETSc options
(``-fwd_ksp_type gmres -fwd_ksp_monitor``) and go into PETSc's options
database, where the scene's KSPs read them at ``KSPSetFromOptions``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

__all__ = ["main", "scene_main"]


def _scene_parser(prog: str | None = None, scene_arg: bool = True) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("run", "compare"):
        p = sub.add_parser(name, help=f"{name} a scene")
        if scene_arg:
            p.add_argument("scene", help="scene file, e.g. demos/heat1d.py")
        p.add_argument("--preset", default="quick", help="preset name (quick | paper)")
        p.add_argument("--epochs", type=int, default=None, help="override the preset's epochs")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--out", required=True, help="output folder")
        p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
        if name == "run":
            p.add_argument("--schedule", default="prdp", help="prdp | fixed:K")
    return parser


def split_petsc_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """Separate PETSc options (``-name [value]``, one dash) from ours (``--name``)."""
    from .core.options import is_number

    ours, petsc = [], []
    i = 0
    while i < len(argv):
        tok = argv[i]
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


def _insert_petsc_options(petsc: list[str]) -> None:
    if not petsc:
        return
    from petsc4py import PETSc

    PETSc.Options().insertString(" ".join(petsc))


def _run_scene_command(args, scene_file: str) -> int:
    from .training.compare import compare, format_table
    from .training.harness import run

    if args.command == "run":
        result = run(
            scene_file,
            args.schedule,
            preset=args.preset,
            epochs=args.epochs,
            seed=args.seed,
            out=args.out,
            progress=not args.no_progress,
        )
        print(json.dumps(result["totals"], indent=1))
        if result["stopped"]:
            print(f"stopped at epoch {result['stopped']['epoch']}: {result['stopped']['reason']}")
            return 1
        return 0
    summary = compare(
        scene_file,
        preset=args.preset,
        epochs=args.epochs,
        seed=args.seed,
        out=args.out,
        progress=not args.no_progress,
    )
    print(format_table(summary))
    print(
        f"results in {args.out}/ (summary.json, error_vs_time.png, error_vs_iterations.png, "
        "k_schedule.png)"
    )
    return 0


def scene_main(scene_file: str, argv: list[str] | None = None) -> int:
    """Entry point of ``python demos/<scene>.py [run|compare] ...`` (default: compare)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("run", "compare", "-h", "--help"):
        argv.insert(0, "compare")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    argv, petsc = split_petsc_options(argv)
    args = _scene_parser(scene_arg=False).parse_args(argv)
    _insert_petsc_options(petsc)
    return _run_scene_command(args, scene_file)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``prdp-petsc`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    tools = {
        "bench": "prdp_petsc.reports.bench",
        "work-precision": "prdp_petsc.reports.workprecision",
        "stability": "prdp_petsc.reports.stability",
    }
    if argv and argv[0] in tools:
        import importlib

        return importlib.import_module(tools[argv[0]]).main(argv[1:])
    parser = _scene_parser(prog="prdp-petsc")
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        print("\nother commands: " + ", ".join(tools))
        return 0
    argv, petsc = split_petsc_options(argv)
    args = parser.parse_args(argv)
    _insert_petsc_options(petsc)
    return _run_scene_command(args, args.scene)


if __name__ == "__main__":
    raise SystemExit(main())
