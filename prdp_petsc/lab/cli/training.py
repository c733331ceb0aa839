"""``prdp-petsc run`` and ``prdp-petsc compare``: train a scene (`parse`, `execute`).

``run`` saves ``DIR/checkpoint.pt`` every ``--checkpoint-every N`` epochs and at the
end; ``run --resume DIR`` continues that run with its recorded settings, and
``compare --resume`` reads the finished runs of ``--out`` and resumes the others.
``--parallel domain|batch`` uses the ranks of ``mpiexec -n P``
(`prdp_petsc.lab.training.parallel`).
"""

from __future__ import annotations

import argparse
import json

from . import arguments
from .petsc import init_petsc, split_petsc_options

__all__ = ["COMMANDS", "execute", "make_parser", "parse"]

#: The training commands, which every scene file's ``__main__`` takes too
COMMANDS = ("run", "compare")


def _k_max(text: str) -> str | int | None:
    """``--k-max``: ``full``, ``none`` or an integer >= 1."""
    if text in ("full", "none"):
        return None if text == "none" else text
    try:
        return arguments.positive(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"full, none or an integer >= 1, got {text!r}") from None


def _setting(text: str) -> str:
    key, eq, value = text.partition("=")
    if not (eq and key.isidentifier() and value) or any(c.isspace() for c in text):
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE without spaces, got {text!r}")
    return text


def make_parser(
    prog: str | None = None, scene_arg: bool = True, description: str | None = None
) -> argparse.ArgumentParser:
    """The parser of ``run`` and ``compare`` (`scene_arg`: with the positional scene file;
    a scene file's ``__main__`` names its own)."""
    parser = argparse.ArgumentParser(
        prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        p = sub.add_parser(name, help=f"{name} a scene")
        if scene_arg:
            p.add_argument(
                "scene", nargs="?" if name == "run" else None,
                help="scene file, e.g. demos/heat1d.py (run --resume: the recorded one)",
            )  # fmt: skip
        seed = p.add_mutually_exclusive_group()
        seed.add_argument("--seed", type=int, help="random seed (default 0)")
        arguments.add_preset(p, None, "preset name (quick | paper; default quick)")
        p.add_argument(
            "--set", action="append", default=[], type=_setting, metavar="KEY=VALUE",
            help="change one of the preset's settings (repeatable), e.g. --set modes=32",
        )  # fmt: skip
        arguments.add_epochs(p)
        arguments.add_threads(p)
        p.add_argument(
            "--parallel", choices=("domain", "batch"),
            help="under mpiexec: distribute every solve (domain) or split every mini-batch "
            "across the ranks (batch)",
        )  # fmt: skip
        p.add_argument(
            "--checkpoint-every", type=arguments.positive, default=1, metavar="N",
            help="save checkpoint.pt every N epochs and at the end (default 1)",
        )  # fmt: skip
        p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
        arguments.add_debug(p)
        if name == "run":
            arguments.add_out(p, "output folder (default with --resume: that folder)", False)
            p.add_argument(
                "--resume", metavar="DIR",
                help="continue the run in DIR from its checkpoint.pt, with its recorded scene, "
                "preset, seeds and schedule, to --epochs (default: the recorded)",
            )  # fmt: skip
            p.add_argument("--schedule", help="prdp | auto | fixed:K | rtol (default prdp)")
            p.add_argument(
                "--k-max", type=_k_max, default="full",
                help="PRDP's cap on K: full (the default: the scene's own k_max, else K_full "
                "of its probe), none, or a number >= the scene's k_init",
            )  # fmt: skip
        else:
            arguments.add_seeds(
                seed, None, "compare on each of these seeds, each with a second full-fidelity "
                "run from other initial weights, and summarise over the seeds",
            )  # fmt: skip
            arguments.add_out(p)
            p.add_argument(
                "--resume", action="store_true",
                help="continue the comparison in --out: finished runs are read, interrupted "
                "ones resume from their checkpoint",
            )  # fmt: skip
            arguments.add_routes(p)
            arguments.add_schedules(p)
    return parser


def parse(parser: argparse.ArgumentParser, argv: list[str], scene_file=None):
    """``(args, scene file)`` of ``run`` or ``compare`` (``argv[0]``), PETSc started with
    the PETSc options of `argv`; `scene_file` for a scene file's ``__main__``.

    A malformed ``--schedule``, ``--routes`` the scene does not name, a preset it lacks
    or a ``--set`` it cannot take is a usage error (exit 2) before anything trains."""
    ours, petsc = split_petsc_options(argv)
    args = parser.parse_args(ours)
    if args.command == "run" and args.resume is None:
        if scene_file is None and args.scene is None:
            parser.error("run: give a SCENE_FILE, or --resume DIR")
        if args.out is None:
            parser.error("run: --out DIR is required (unless --resume DIR)")
    init_petsc(petsc)  # the scene and the harness import PETSc
    scene = scene_file if scene_file is not None else args.scene
    from ..training.routes import parse_routes
    from ..training.scene import load_scene, preset_config
    from ..training.schedules import parse_schedule

    if getattr(args, "schedule", None) is not None:
        try:
            parse_schedule(args.schedule)
        except ValueError as err:
            parser.error(f"--schedule: {err}")
    if scene is None:
        return args, scene
    try:
        module = load_scene(scene)
    except (FileNotFoundError, AttributeError):
        return args, scene  # reported by the command itself, with the file's name
    if getattr(args, "routes", None) and args.routes != ("auto",):  # auto: compare's pilot
        try:
            parse_routes(",".join(args.routes), getattr(module, "ROUTES", None))
        except ValueError as err:
            parser.error(f"--routes: {err}")
    if _preset(args, None) is not None:
        try:
            preset_config(module, _preset(args, None))
        except ValueError as err:
            parser.error(f"--preset/--set: {err}")
    return args, scene


def _preset(args, default: str | None = "quick") -> str | None:
    """The preset with the ``--set`` changes: ``"paper modes=32"`` (`default` for
    neither: None lets a resumed run keep its recorded preset)."""
    if args.preset is None and not args.set:
        return default
    return " ".join([args.preset or "quick", *args.set])


def _is_root(args) -> bool:
    """False on the ranks other than 0 of a ``--parallel`` run (they print nothing)."""
    if args.parallel is None:
        return True
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_rank() == 0


def execute(args, scene_file: str) -> int:
    """Run the parsed ``run`` or ``compare``, print its summary, return the exit status
    (1 when a run stopped early)."""
    from ..training.compare import compare
    from ..training.harness import run
    from ..training.seeds import compare_seeds, format_seeds
    from ..training.summary import format_table, stopped_runs

    if args.command == "run":
        result = run(
            scene_file, args.schedule,
            preset=_preset(args, None if args.resume else "quick"), epochs=args.epochs,
            seed=args.seed, out=args.out, progress=not args.no_progress, threads=args.threads,
            parallel=args.parallel, prdp=None if args.k_max == "full" else {"k_max": args.k_max},
            checkpoint_every=args.checkpoint_every, resume=args.resume,
        )  # fmt: skip
        stop = result["stopped"]
        if _is_root(args):
            print(json.dumps(result["totals"], indent=1))
            if stop:
                print(f"stopped at epoch {stop['epoch']}: {stop['reason']}: {stop['message']}")
        return 1 if stop else 0
    options = dict(
        preset=_preset(args), epochs=args.epochs, out=args.out, progress=not args.no_progress,
        threads=args.threads, routes=args.routes, schedules=args.schedules,
        parallel=args.parallel, resume=args.resume, checkpoint_every=args.checkpoint_every,
    )  # fmt: skip
    if args.seeds is not None:
        result = compare_seeds(scene_file, args.seeds, **options)
        stopped = [f"seed {r['seed']}: {name}" for r in result["per_seed"] for name in r["stopped"]]
        report = ["\n\n".join(result["tables"]), "", format_seeds(result),
                  f"results in {args.out}/ (seeds.json, seed_*/summary.json)"]  # fmt: skip
    else:
        summary = compare(scene_file, seed=args.seed or 0, **options)
        stopped = stopped_runs(summary)
        plots = ", ".join(summary.get("plots", []))
        report = [format_table(summary), f"results in {args.out}/ (summary.json, {plots})"]
    if _is_root(args):
        print("\n".join(report))
        if stopped:
            print(f"runs that stopped early: {', '.join(stopped)} (see their results.json)")
    return 1 if stopped else 0
