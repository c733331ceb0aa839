"""``prdp-petsc run`` and ``prdp-petsc compare``: train a scene (`command`).

``run`` saves ``DIR/checkpoint.pt`` (the model, optimizer, PRDP controller and
random states; every ``--checkpoint-every N`` epochs, default 1, and at the end).
``run --resume DIR`` continues the run in DIR with its recorded scene, preset, seeds
and schedule (changing one is refused) to ``--epochs N`` (default: the recorded
number), appending to its ``results.json``; ``compare --resume`` reads the runs of
``--out`` that finished and resumes the others.  Load a trained model with
`prdp_petsc.lab.training.harness.load_trained`.

``--parallel domain|batch`` uses the ranks of ``mpiexec -n P``: distributed solves,
or a split of every mini-batch (see `prdp_petsc.lab.training.parallel`).  An error on
one rank then aborts all of them (``MPI_Abort``) instead of leaving them waiting.
"""

from __future__ import annotations

import argparse
import json

from .arguments import add_debug, positive, routes, seeds
from .guard import guarded, is_root
from .petsc import init_petsc, split_petsc_options

__all__ = ["COMMANDS", "command", "make_parser"]

#: The training commands, which every scene file's ``__main__`` takes too
COMMANDS = ("run", "compare")


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
                "scene",
                nargs="?" if name == "run" else None,
                help="scene file, e.g. demos/heat1d.py"
                + (" (with --resume: the recorded one)" if name == "run" else ""),
            )
        p.add_argument("--preset", default=None, help="preset name (quick | paper; default quick)")
        p.add_argument(
            "--set",
            action="append",
            default=[],
            type=_setting,
            metavar="KEY=VALUE",
            help="change one of the preset's settings (repeatable), e.g. --set modes=32",
        )
        p.add_argument("--epochs", type=positive, default=None, help="override the preset's epochs")
        seed = p.add_mutually_exclusive_group()
        seed.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
        if name == "compare":
            seed.add_argument(
                "--seeds",
                type=seeds,
                default=None,
                help="compare on each of these seeds (e.g. 0-3 or 0,2,5), each with a "
                "second full-fidelity run from other initial weights (the run-to-run "
                "noise), and summarise the error ratios over the seeds",
            )
        p.add_argument(
            "--threads",
            type=positive,
            default=1,
            help="torch threads (default 1: honest wall times on a shared machine)",
        )
        p.add_argument(
            "--parallel",
            choices=("domain", "batch"),
            default=None,
            help="under mpiexec: distribute every solve (domain) or split every "
            "mini-batch across the ranks (batch)",
        )
        p.add_argument(
            "--out",
            required=name == "compare",
            help="output folder"
            + (" (default with --resume: that folder)" if name == "run" else ""),
        )
        p.add_argument(
            "--checkpoint-every",
            type=positive,
            default=1,
            metavar="N",
            help="save checkpoint.pt every N epochs and at the end (default 1)",
        )
        p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
        add_debug(p)
        if name == "run":
            p.add_argument(
                "--resume",
                metavar="DIR",
                default=None,
                help="continue the run in DIR from its checkpoint.pt, with its recorded "
                "scene, preset, seeds and schedule, to --epochs (default: the recorded)",
            )
            p.add_argument("--schedule", default=None, help="prdp | fixed:K | rtol (default prdp)")
            p.add_argument(
                "--k-max",
                type=_k_max,
                default="full",
                help="PRDP's cap on K: full (the default: the scene's own k_max, else "
                "K_full of its probe), none, or a number >= the scene's k_init",
            )
        else:
            p.add_argument(
                "--resume",
                action="store_true",
                help="continue the comparison in --out: finished runs are read, "
                "interrupted ones resume from their checkpoint",
            )
            p.add_argument(
                "--routes",
                type=routes,
                default=None,
                help="other solvers to run PRDP and full fidelity with, comma-separated "
                "ksp_type/pc_type (e.g. cg/icc,cg/gamg), each optionally with sub-options "
                "as :option=value (gmres/fieldsplit:pc_fieldsplit_type=schur), or a route "
                "the scene names in ROUTES; the summary names the fastest (default: the "
                "routes the scene's preset declares; --routes '' runs none; --routes auto: "
                "a short pilot at full fidelity picks one of the declared routes)",
            )
            p.add_argument(
                "--schedules",
                type=_schedules,
                default=("prdp",),
                help="reduced-fidelity schedules to run on every route, comma-separated: "
                "prdp (PRDP on the iteration cap K; the default) and rtol (PRDP on PETSc's "
                "rtol under a generous cap)",
            )
    return parser


def _k_max(text: str) -> str | int | None:
    """``--k-max``: ``full``, ``none`` or an integer >= 1."""
    if text in ("full", "none"):
        return None if text == "none" else text
    try:
        return positive(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"full, none or an integer >= 1, got {text!r}") from None


def _setting(text: str) -> str:
    key, eq, value = text.partition("=")
    if not (eq and key.isidentifier() and value) or any(c.isspace() for c in text):
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE without spaces, got {text!r}")
    return text


def _schedules(text: str) -> tuple[str, ...]:
    """The names of ``--schedules``; `compare` checks them (importing it here would
    start PETSc before `init_petsc`)."""
    schedules = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    if not schedules:
        raise argparse.ArgumentTypeError(f"expected e.g. prdp,rtol, got {text!r}")
    return schedules


def command(parser: argparse.ArgumentParser, argv: list[str], scene_file=None) -> int:
    """``run`` or ``compare`` (``argv[0]``) with the rest of `argv`, parsed by `parser`;
    `scene_file` for a scene file's ``__main__``, whose `parser` has no scene argument."""
    ours, petsc = split_petsc_options(argv)
    args = parser.parse_args(ours)
    resume = args.resume if args.command == "run" else None
    if args.command == "run" and resume is None:
        if scene_file is None and args.scene is None:
            parser.error("run: give a SCENE_FILE, or --resume DIR")
        if args.out is None:
            parser.error("run: --out DIR is required (unless --resume DIR)")
    init_petsc(petsc)
    scene = scene_file if scene_file is not None else args.scene
    _check_arguments(parser, args, scene)
    out = args.out or resume
    return guarded(lambda: _run_scene_command(args, scene), args.debug, out, args)


def _check_arguments(parser: argparse.ArgumentParser, args, scene) -> None:
    """A malformed ``--schedule``, a preset the scene does not have or a ``--set`` it
    cannot take is a usage error (exit 2), found before anything trains.  Checked after
    PETSc started: the scene and the harness import it."""
    from ..training.schedules import parse_schedule

    if getattr(args, "schedule", None) is not None:
        try:
            parse_schedule(args.schedule)
        except ValueError as err:
            parser.error(f"--schedule: {err}")
    preset = _preset(args, None)
    if scene is None:
        return
    from ..training.routes import parse_routes
    from ..training.scene import load_scene, preset_config

    try:
        module = load_scene(scene)
    except (FileNotFoundError, AttributeError):
        return  # reported by the command itself, with the file's name
    if getattr(args, "routes", None) and args.routes != ("auto",):  # auto: compare's pilot
        try:
            parse_routes(",".join(args.routes), getattr(module, "ROUTES", None))
        except ValueError as err:
            parser.error(f"--routes: {err}")
    if preset is None:
        return
    try:
        preset_config(module, preset)
    except ValueError as err:
        parser.error(f"--preset/--set: {err}")


def _run_scene_command(args, scene_file: str) -> int:
    from ..training.compare import compare
    from ..training.harness import run
    from ..training.summary import format_table, stopped_runs

    if args.command == "run":
        result = run(
            scene_file,
            args.schedule,
            preset=_preset(args, None if args.resume else "quick"),
            epochs=args.epochs,
            seed=args.seed,
            out=args.out,
            progress=not args.no_progress,
            threads=args.threads,
            parallel=args.parallel,
            prdp=None if args.k_max == "full" else {"k_max": args.k_max},
            checkpoint_every=args.checkpoint_every,
            resume=args.resume,
        )
        if not is_root(args):
            return 1 if result["stopped"] else 0
        print(json.dumps(result["totals"], indent=1))
        if result["stopped"]:
            stop = result["stopped"]
            print(f"stopped at epoch {stop['epoch']}: {stop['reason']}: {stop['message']}")
            return 1
        return 0
    if args.seeds is not None:
        return _compare_seeds(args, scene_file)
    seed = 0 if args.seed is None else args.seed
    summary = compare(scene_file, seed=seed, **_compare_options(args))
    if not is_root(args):
        return 1 if stopped_runs(summary) else 0
    print(format_table(summary))
    print(f"results in {args.out}/ (summary.json, " + ", ".join(summary.get("plots", [])) + ")")
    stopped = stopped_runs(summary)
    if stopped:
        print(f"runs that stopped early: {', '.join(stopped)} (see their results.json)")
        return 1
    return 0


def _preset(args, default: str | None = "quick") -> str | None:
    """The preset with the ``--set`` changes: ``"paper modes=32"`` (`default` for
    neither: None lets a resumed run keep its recorded preset)."""
    if args.preset is None and not args.set:
        return default
    return " ".join([args.preset or "quick", *args.set])


def _compare_options(args) -> dict:
    """Keyword arguments of `compare` (and `compare_seeds`) from the command line."""
    return {
        "preset": _preset(args),
        "epochs": args.epochs,
        "out": args.out,
        "progress": not args.no_progress,
        "threads": args.threads,
        "routes": args.routes,
        "schedules": args.schedules,
        "parallel": args.parallel,
        "resume": args.resume,
        "checkpoint_every": args.checkpoint_every,
    }


def _compare_seeds(args, scene_file: str) -> int:
    from ..training.seeds import compare_seeds, format_seeds

    result = compare_seeds(scene_file, args.seeds, **_compare_options(args))
    stopped = [f"seed {r['seed']}: {name}" for r in result["per_seed"] for name in r["stopped"]]
    if not is_root(args):
        return 1 if stopped else 0
    print("\n\n".join(result["tables"]))
    print()
    print(format_seeds(result))
    print(f"results in {args.out}/ (seeds.json, seed_*/summary.json)")
    if stopped:
        print(f"runs that stopped early: {', '.join(stopped)} (see their results.json)")
    return 1 if stopped else 0
