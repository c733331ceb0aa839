"""The ``prdp-petsc`` command line.

Sub-commands::

    prdp-petsc run SCENE_FILE [--schedule prdp|fixed:K] [--preset quick|paper]
                   [--set KEY=VALUE ...] [--k-max full|none|K] [--epochs N] [--seed S]
                   [--threads T] [--parallel domain|batch] [--checkpoint-every N]
                   --out DIR [PETSc options]
    prdp-petsc run --resume DIR [--epochs N] [--threads T] [PETSc options]
    prdp-petsc compare SCENE_FILE [--preset ...] [--set KEY=VALUE ...] [--epochs N]
                   [--seed S | --seeds 0-3] [--threads T] [--routes cg/icc,cg/gamg]
                   [--schedules prdp,rtol] [--parallel domain|batch]
                   [--checkpoint-every N] [--resume]
                   --out DIR [PETSc options]
    prdp-petsc scene SCENE_FILE [NAME [ARGS ...]] [--debug] [PETSc options]
    prdp-petsc bench bridge|mpi|elasticity --out DIR
    prdp-petsc work-precision PROBLEM --out DIR [--k-max K] [--routes cg/gamg,...]
    prdp-petsc stability --out DIR
    prdp-petsc pages --out docs/results
    prdp-petsc rollouts --run NAME=DIR[,DIR...] ... [--ratio NAME/REF] --out DIR
    prdp-petsc horizon SCENE_FILE [--preset P] [--m 2 4 8 16] [--k K] --out DIR
    prdp-petsc ablation SCENE_FILE [--preset P] [--seeds 0-2] --lever NAME KEY=VALUE ...
                   [--schedules prdp,rtol] [--routes R] [--no-twin] --out DIR
    prdp-petsc --version

Every sub-command follows the same conventions: PETSc options (below) start PETSc,
``--debug`` shows the traceback of an error (otherwise one line, exit status 1), a
usage error exits 2, and a concept has one spelling (``--routes a,b``, ``--k-max``).

Arguments that start with a single ``-`` and are not ours are PETSc options
(``-heat_ksp_type cg -heat_ksp_monitor -log_view``): PETSc starts with them
(``petsc4py.init``), so the scene's KSPs read them at ``KSPSetFromOptions`` and
start-up options such as ``-log_view`` work as in any PETSc program.

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

``scene SCENE_FILE NAME [ARGS ...]`` runs a command the scene file declares in
``COMMANDS`` (`prdp_petsc.lab.training.scene`), such as ``prdp-petsc scene demos/ns2d.py
adjoint --preset quick --k 8 64``; ``python demos/ns2d.py adjoint ...`` is the same
command.  Without NAME it lists them (``python demos/ns2d.py -h`` too).  Each command
parses its own arguments (``prdp-petsc scene demos/ns2d.py adjoint -h``); an argument
``--preset`` is checked against the scene's presets like ``run``'s.

Exit status: 0 on success; 1 if a run stopped early (diverged solve, invalid
input) or on an error, which prints one line (``--debug`` shows the traceback);
2 for a usage error; 130 after Ctrl-C (the results written so far stay).

Warning filters that name a category of this package, such as
``python -W error::prdp_petsc.errors.UnusedOptionWarning -m prdp_petsc.lab.cli ...`` or
``PYTHONWARNINGS=error::prdp_petsc.errors.UnusedOptionWarning prdp-petsc ...`` (a
misspelt PETSc option then stops the run), are applied when the command starts
(`apply_warning_options`): Python reads them before its site-packages are
importable, drops them and says ``Invalid -W option ignored``.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import logging
import re
import sys
import warnings
from pathlib import Path

# Nothing here imports PETSc (or torch) at module level: `init_petsc` must run first.

__all__ = ["apply_warning_options", "init_petsc", "main", "scene_main", "split_petsc_options"]

_TOOLS = {
    "bench": "prdp_petsc.lab.reports.bench",
    "work-precision": "prdp_petsc.lab.reports.workprecision",
    "stability": "prdp_petsc.lab.reports.stability",
    "pages": "prdp_petsc.lab.reports.pages",
    "rollouts": "prdp_petsc.lab.reports.rollouts",
    "horizon": "prdp_petsc.lab.reports.horizon",
    "ablation": "prdp_petsc.lab.reports.ablation",
    "unseen": "prdp_petsc.lab.reports.unseen",
    "defaults": "prdp_petsc.lab.reports.defaults",
}


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def _scene_parser(prog: str | None = None, scene_arg: bool = True) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("run", "compare"):
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
        p.add_argument(
            "--epochs", type=_positive_int, default=None, help="override the preset's epochs"
        )
        seed = p.add_mutually_exclusive_group()
        seed.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
        if name == "compare":
            seed.add_argument(
                "--seeds",
                type=_seeds,
                default=None,
                help="compare on each of these seeds (e.g. 0-3 or 0,2,5), each with a "
                "second full-fidelity run from other initial weights (the run-to-run "
                "noise), and summarise the error ratios over the seeds",
            )
        p.add_argument(
            "--threads",
            type=_positive_int,
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
            type=_positive_int,
            default=1,
            metavar="N",
            help="save checkpoint.pt every N epochs and at the end (default 1)",
        )
        p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
        p.add_argument("--debug", action="store_true", help="show tracebacks of errors")
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
                type=_routes,
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
    if text in ("full", "none"):
        return None if text == "none" else text
    try:
        value = int(text)
    except ValueError:
        message = f"--k-max: full, none or an integer, got {text!r}"
        raise argparse.ArgumentTypeError(message) from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"--k-max must be >= 1, got {value}")
    return value


def _setting(text: str) -> str:
    key, eq, value = text.partition("=")
    if not (eq and key.isidentifier() and value) or any(c.isspace() for c in text):
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE without spaces, got {text!r}")
    return text


def _seeds(text: str) -> list[int]:
    from .parsing import parse_seeds

    try:
        return parse_seeds(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _routes(text: str) -> tuple[str, ...]:
    """The routes of ``--routes``, split; `_check_arguments` checks them once the
    scene, whose ``ROUTES`` may name some of them, is loaded."""
    return tuple(r.strip() for r in text.split(",") if r.strip())


def _schedules(text: str) -> tuple[str, ...]:
    """The names of ``--schedules``; `compare` checks them (importing it here would
    start PETSc before `init_petsc`)."""
    schedules = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    if not schedules:
        raise argparse.ArgumentTypeError(f"expected e.g. prdp,rtol, got {text!r}")
    return schedules


def split_petsc_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """Separate PETSc options (``-name [value]``, one dash) from ours (``--name``).

    Everything after a bare ``--`` is ours, untouched: the command that
    ``prdp-petsc pages record NAME -- COMMAND`` runs keeps its own PETSc options.
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


def is_number(tok: str) -> bool:
    """``-10`` or ``-1e-3`` is a value, not an option name."""
    try:
        float(tok)
    except ValueError:
        return False
    return True


_ACTIONS = ("default", "always", "ignore", "module", "once", "error")


def apply_warning_options(options: list[str] | None = None) -> None:
    """Apply the warning filters of `options` whose category is one of prdp_petsc's.

    Python reads ``-W`` and ``PYTHONWARNINGS`` (both end up in ``sys.warnoptions``,
    the default of `options`) before its site-packages are on ``sys.path``, so it
    cannot import ``prdp_petsc.errors`` for
    ``-W error::prdp_petsc.errors.UnusedOptionWarning``: it prints ``Invalid -W
    option ignored: invalid module name`` and drops the filter.  The command line
    calls this first thing, so those filters apply after all.

    Parameters
    ----------
    options : list of str, optional
        Filters in Python's syntax, ``action:message:category:module:lineno``,
        with Python's meaning (an abbreviated action, a message matched from its
        start, a module matched whole, later filters first).  Filters whose
        category is not in ``prdp_petsc`` are left to Python, which applied them.
        They go before the filters Python set at start-up.
    """
    for option in sys.warnoptions if options is None else options:
        fields = [field.strip() for field in option.split(":")]
        fields += [""] * (5 - len(fields))
        if len(fields) != 5 or not fields[2].startswith("prdp_petsc."):
            continue
        action, message, category, module, lineno = fields
        try:
            action = _warning_action(action)
            owner, _, name = category.rpartition(".")
            cls = getattr(importlib.import_module(owner), name, None)
            if not (isinstance(cls, type) and issubclass(cls, Warning)):
                raise ValueError(f"{category} is not a warning category")
            line = int(lineno or 0)
            if line < 0:
                raise ValueError(f"invalid line number {lineno!r}")
        except (ImportError, ValueError) as err:
            print(f"prdp-petsc: invalid warning filter {option!r} ignored: {err}", file=sys.stderr)
            continue
        module = re.escape(module) + r"\Z" if module else ""
        warnings.filterwarnings(action, re.escape(message), cls, module, line)


def _warning_action(text: str) -> str:
    """Python's reading of a ``-W`` action: empty is ``default``, a prefix names one."""
    if not text:
        return "default"
    if text == "all":
        return "always"
    for action in _ACTIONS:
        if action.startswith(text):
            return action
    raise ValueError(f"invalid action {text!r}")


def init_petsc(options: list[str]) -> None:
    """Start PETSc with the command line's PETSc options, as petsc4py's demos do.

    ``petsc4py.init`` must come before the first ``from petsc4py import PETSc``:
    options read only at ``PetscInitialize`` (``-log_view``, ``-malloc_debug``)
    work only then.  If PETSc is already running (the CLI called in-process, as in
    tests), the options go into its options database instead.
    """
    if "petsc4py.PETSc" in sys.modules:
        if options:
            from petsc4py import PETSc

            PETSc.Options().insertString(" ".join(options))
        return
    import petsc4py

    petsc4py.init([sys.argv[0] or "prdp-petsc", *options])


def _run_scene_command(args, scene_file: str) -> int:
    from .training.compare import compare
    from .training.harness import run
    from .training.summary import format_table, stopped_runs

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
        if not _is_root(args):
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
    if not _is_root(args):
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
    from .training.seeds import compare_seeds, format_seeds

    result = compare_seeds(scene_file, args.seeds, **_compare_options(args))
    stopped = [f"seed {r['seed']}: {name}" for r in result["per_seed"] for name in r["stopped"]]
    if not _is_root(args):
        return 1 if stopped else 0
    print("\n\n".join(result["tables"]))
    print()
    print(format_seeds(result))
    print(f"results in {args.out}/ (seeds.json, seed_*/summary.json)")
    if stopped:
        print(f"runs that stopped early: {', '.join(stopped)} (see their results.json)")
    return 1 if stopped else 0


def _is_root(args) -> bool:
    """False on the ranks other than 0 of a ``--parallel`` run (they print nothing)."""
    if getattr(args, "parallel", None) is None:
        return True
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_rank() == 0


def _abort_others(args) -> None:
    """After an error in a ``--parallel`` run, stop every rank (none waits forever)."""
    if getattr(args, "parallel", None) is not None:
        from mpi4py import MPI

        if MPI.COMM_WORLD.Get_size() > 1:
            sys.stderr.flush()
            MPI.COMM_WORLD.Abort(1)


def _guarded(command, debug: bool, out: str | None = None, args=None) -> int:
    """Run ``command()``; an error prints one line (unless ``debug``) and returns 1."""
    try:
        return command()
    except KeyboardInterrupt:
        if debug:
            raise
        where = f"; results so far in {out}/" if out else ""
        print(f"prdp-petsc: interrupted (Ctrl-C){where}", file=sys.stderr)
        return 130
    except Exception as err:
        if debug:
            if getattr(args, "parallel", None) is not None:
                import traceback

                traceback.print_exc()
                _abort_others(args)  # the other ranks may be waiting in a collective call
            raise
        message = " ".join(str(err).split()) or "(no message)"
        print(
            f"prdp-petsc: error: {type(err).__name__}: {message} (--debug shows the traceback)",
            file=sys.stderr,
        )
        _abort_others(args)
        return 1


def _scene_command(parser: argparse.ArgumentParser, argv: list[str], scene_file=None) -> int:
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
    return _guarded(lambda: _run_scene_command(args, scene), args.debug, out, args)


def _check_arguments(parser: argparse.ArgumentParser, args, scene) -> None:
    """A malformed ``--schedule``, a preset the scene does not have or a ``--set`` it
    cannot take is a usage error (exit 2), found before anything trains.  Checked after
    PETSc started: the scene and the harness import it."""
    from .training.schedules import parse_schedule

    if getattr(args, "schedule", None) is not None:
        try:
            parse_schedule(args.schedule)
        except ValueError as err:
            parser.error(f"--schedule: {err}")
    preset = _preset(args, None)
    if scene is None:
        return
    from .training.routes import parse_routes
    from .training.scene import load_scene, preset_config

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


def scene_main(scene_file: str, argv: list[str] | None = None) -> int:
    """Entry point of ``python demos/<scene>.py [run|compare|NAME] ...`` (default:
    compare); NAME is one of the scene's ``COMMANDS``, listed by ``-h``."""
    apply_warning_options()
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    prog = Path(scene_file).name
    if argv[:1] in (["-h"], ["--help"]):
        _scene_parser(prog=prog, scene_arg=False).print_help()
        print()
        return _extra_command(scene_file, [], prog)
    if argv and not argv[0].startswith("-") and argv[0] not in _SCENE_FILE_COMMANDS:
        return _extra_command(scene_file, argv, prog, also=_SCENE_FILE_COMMANDS)
    if not argv or argv[0] not in _SCENE_FILE_COMMANDS:
        argv.insert(0, "compare")
    return _scene_command(_scene_parser(scene_arg=False), argv, scene_file)


def _tool_command(name: str, argv: list[str]) -> int:
    """``prdp-petsc bench|work-precision|stability|pages|rollouts|horizon ...``: the
    same conventions as ``run``: PETSc options start PETSc, the tool's own parser reads
    the rest (``--debug`` included: an error prints one line unless it is given), usage
    errors exit 2."""
    ours, petsc = split_petsc_options(argv)
    init_petsc(petsc)
    tool = importlib.import_module(_TOOLS[name])
    return _guarded(lambda: tool.main(ours), _debug_flag(ours))


def _debug_flag(argv: list[str]) -> bool:
    """Whether `argv` asks for tracebacks (``--debug``), before its own parser reads it."""
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument("--debug", action="store_true")
    return debug.parse_known_args(argv)[0].debug


_SCENE_FILE_COMMANDS = ("run", "compare")  # what every scene file's __main__ takes


def _extra_command(scene_file: str, argv: list[str], prog: str, also: tuple = ()) -> int:
    """``prdp-petsc scene SCENE_FILE [NAME ...]`` and ``python SCENE_FILE NAME ...``: the
    scene's command NAME from its ``COMMANDS`` (without NAME, their list), with the
    conventions of ``run``: PETSc options start PETSc (before the scene is imported:
    it imports PETSc), an error prints one line unless ``--debug``, usage errors exit 2.
    `prog` is how the usage names the scene (``prdp-petsc scene demos/ns2d.py``); `also`
    names the other commands that reach the scene there (for the error of a wrong NAME)."""
    ours, petsc = split_petsc_options(argv)
    init_petsc(petsc)
    return _guarded(lambda: _dispatch_extra(scene_file, ours, prog, also), _debug_flag(ours))


def _dispatch_extra(scene_file: str, argv: list[str], prog: str, also: tuple) -> int:
    from .training.scene import load_scene, preset_config

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
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
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
        if key in _SCENE_FILE_COMMANDS:
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


def _scene_file_command(argv: list[str]) -> int:
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
    return _extra_command(argv[0], argv[1:], f"prdp-petsc scene {argv[0]}")


def missing_lab_packages() -> list[str]:
    """The packages of the ``lab`` extra that are not installed."""
    import importlib.util

    return [name for name in ("matplotlib", "tqdm") if importlib.util.find_spec(name) is None]


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
    if argv and argv[0] in _TOOLS:
        return _tool_command(argv[0], argv[1:])
    if argv and argv[0] == "scene":
        return _scene_file_command(argv[1:])
    parser = _scene_parser(prog="prdp-petsc")
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        print("\nother commands: scene, " + ", ".join(_TOOLS))
        return 0
    return _scene_command(parser, argv)


if __name__ == "__main__":
    raise SystemExit(main())
