"""Which lever buys what: ``compare --seeds`` once per lever, against the scene as it is.

``prdp-petsc ablation SCENE_FILE --preset P --seeds 0-2 --lever NAME KEY=VALUE ...
--out DIR`` runs `prdp_petsc.lab.training.seeds.compare_seeds` for the preset as given
(``baseline``) and once per ``--lever`` (the preset with that lever's settings alone),
into ``DIR/<name>/``, with the same seeds, schedules and routes.  ``DIR/ablation.json``
keeps each configuration's result and, per lever, the baseline's time to full-fidelity
accuracy over the lever's, for the fastest reduced and the fastest full-fidelity run
(`lever_effect`; above 1 the lever got there sooner).  One torch thread per process,
configurations one after another: compare them on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cli import arguments
from .kinds import DataSet, ReportKind, text_table

__all__ = ["KIND", "ablation", "format_ablation", "main"]

BASELINE = "baseline"


def ablation(scene_file, levers: dict[str, str], *, preset: str, seeds, out, **kwargs) -> dict:
    """`compare_seeds` of `preset` and of ``preset + " " + settings`` per lever.

    `levers` is ``{name: "key=value key=value"}``; each configuration writes
    ``out/<name>/`` and the study ``out/ablation.json``; `kwargs` go to every
    `compare_seeds` (``schedules``, ``routes``, ``twin``, ...).  Returns ``scene``,
    ``preset``, ``seeds``, ``levers``, ``configs`` (``{name: {"preset": ..., "result":
    ...}}``, the baseline first) and ``effects`` (`lever_effect` per lever).
    """
    from ..training.parallel import Parallel
    from ..training.records import write_json
    from ..training.seeds import compare_seeds

    root = Parallel(kwargs.get("parallel")).root  # rank 0 alone writes files

    if BASELINE in levers:
        raise ValueError(f"{BASELINE!r} names the preset as given; choose another lever name")
    out = Path(out)
    configs = {
        BASELINE: preset,
        **{name: f"{preset} {settings}" for name, settings in levers.items()},
    }
    report = {
        "scene": Path(scene_file).stem,
        "preset": preset,
        "seeds": list(seeds),
        "levers": dict(levers),
        "configs": {},
        "effects": {},
    }
    for name, config in configs.items():
        result = compare_seeds(scene_file, list(seeds), preset=config, out=out / name, **kwargs)
        result.pop("plot", None)  # a path inside the configuration's folder
        report["configs"][name] = {"preset": config, "result": result}
        if name != BASELINE:
            report["effects"][name] = lever_effect(report["configs"][BASELINE]["result"], result)
        if root:  # after each configuration: an interrupted study keeps what it measured
            write_json(out / "ablation.json", report)
    return report


def lever_effect(baseline: dict, lever: dict) -> dict:
    """Per-seed ratios baseline time / lever time of the fastest reduced and the fastest
    full-fidelity run to full-fidelity accuracy, as `optional_ratio_statistics` (``n``
    = 0 and no mean where no seed has both)."""
    from ..training.seeds import optional_ratio_statistics

    base = {r["seed"]: r for r in baseline["per_seed"]}
    effect = {}
    for kind in ("reduced", "full"):
        ratios = [
            base[r["seed"]][f"{kind}_seconds"] / r[f"{kind}_seconds"]
            for r in lever["per_seed"]
            if r.get(f"{kind}_seconds") and (base.get(r["seed"]) or {}).get(f"{kind}_seconds")
        ]
        effect[f"{kind}_vs_baseline"] = optional_ratio_statistics(ratios)
    return effect


def _mean_seconds(per_seed: list[dict], key: str) -> str:
    values = [r[key] for r in per_seed if r.get(key) is not None]
    return f"{sum(values) / len(values):.3g}" if values else "—"


def format_ablation(report: dict) -> str:
    """Plain-text table: one row per configuration, then what each lever changed."""
    from ..training.seeds import format_ratio

    header = ["config", "settings", "speedup", "≥ 2", "full s", "reduced s", "PRDP/full",
              "its saved", "bound"]  # fmt: skip
    rows = []
    for name, config in report["configs"].items():
        r = config["result"]
        speed = r.get("speedup") or {}
        ratio = r.get("prdp_ratio", {}).get("geometric_mean")
        saved = (r.get("savings") or {}).get("iterations_saved", {}).get("mean")
        bound = (speed.get("solver_bound") or {}).get("geometric_mean")
        rows.append((name, report["levers"].get(name, "—"), format_ratio(speed, ".2f", "×"),
                     f"{speed.get('goal_met', 0)}/{speed.get('seeds', 0)}",
                     _mean_seconds(r["per_seed"], "full_seconds"),
                     _mean_seconds(r["per_seed"], "reduced_seconds"),
                     "—" if ratio is None else f"{ratio:.3f}",
                     "—" if saved is None else f"{100 * saved:.1f}%",
                     "—" if bound is None else f"{bound:.2f}"))  # fmt: skip
    lines = [
        f"ablation of {report['scene']} --preset {report['preset']} over seeds "
        f"{', '.join(map(str, report['seeds']))}",
        "speedup: the fastest full-fidelity run's time to full-fidelity accuracy over the "
        "fastest reduced run's (geometric mean, 95 % interval); full s / reduced s: those "
        "times, mean over the seeds; its saved: PRDP's inner iterations saved against K_full "
        "(mean); bound: the fastest full run's wall time over its time outside the solver",
        "",
        text_table(header, rows),
    ]
    if report["effects"]:
        lines += ["", "each lever against the baseline, seed by seed (baseline time / lever time):"]
        for name, effect in report["effects"].items():
            reduced, full = (
                format_ratio(s, ".2f", "×", f"n = {s['n']}")
                for s in (effect["reduced_vs_baseline"], effect["full_vs_baseline"])
            )
            lines.append(f"  {name:<10} fastest reduced run {reduced}, fastest full run {full}")
    return "\n".join(lines) + "\n"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="prdp-petsc ablation",
        description="compare --seeds for the preset and once per lever (preset settings); "
        "writes DIR/ablation.json and prints the table.",
    )
    parser.add_argument("scene", help="scene file (demos/ns2d.py)")
    arguments.add_preset(parser, help="the baseline's preset (default quick)")
    arguments.add_seeds(parser)
    parser.add_argument(
        "--lever",
        nargs="+",
        action="append",
        default=[],
        metavar=("NAME", "KEY=VALUE"),
        help="a lever: its name and the preset settings it changes (repeatable)",
    )
    arguments.add_schedules(parser, "prdp,rtol")
    arguments.add_routes(parser)
    arguments.add_epochs(parser)
    parser.add_argument("--no-twin", action="store_true", help="skip the twin runs")
    arguments.add_out(parser)
    arguments.add_debug(parser)
    return parser


def main(argv: list[str]) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    levers = {}
    for lever in args.lever:
        name, *settings = lever
        if not settings or any("=" not in s for s in settings) or name in levers:
            parser.error(f"--lever NAME KEY=VALUE ...: got {' '.join(lever)!r}")
        levers[name] = " ".join(settings)
    try:
        report = ablation(
            args.scene, levers, preset=args.preset, seeds=args.seeds, out=args.out,
            schedules=args.schedules,
            routes=args.routes, epochs=args.epochs, twin=not args.no_twin,
            progress=False, plots=False, resume=True,
        )  # fmt: skip
    except ValueError as err:
        parser.error(str(err))
    print(format_ablation(report), end="")
    print(f"wrote {args.out / 'ablation.json'}")
    return 0


# -- the page of a recorded ``ablation`` ----------------------------------------------------------
def _headline(ds: DataSet) -> list[tuple[str, str]]:
    """One row per lever: its speed-up against the best full run, the baseline's, and
    how fast its fastest reduced and full runs got there against the baseline's."""
    d = ds.main
    seeds = ", ".join(map(str, d["seeds"]))
    base = (d["configs"]["baseline"]["result"].get("speedup") or {}).get("geometric_mean")
    rows = []
    for name, effect in d["effects"].items():
        speed = (d["configs"][name]["result"].get("speedup") or {}).get("geometric_mean")
        figure = "—" if speed is None else f"{speed:.2f}×"
        figure += "" if base is None else f" (baseline {base:.2f}×)"
        pace = [
            f"fastest {kind} run {ratio:.2f}×"
            for kind in ("reduced", "full")
            if (ratio := effect[f"{kind}_vs_baseline"].get("geometric_mean")) is not None
        ]
        if pace:  # a speed-up can also rise because full fidelity got slower
            figure += f"; as fast as the baseline's: {', '.join(pace)}"
        rows.append(
            (
                f"{d['scene']} --preset {d['preset']} over seeds {seeds}, lever `{name}` "
                f"({d['levers'][name]}): speed-up over the fastest full-fidelity run",
                figure,
            )
        )
    return rows


KIND = ReportKind(
    name="ablation",
    reads="ablation.json",
    title=lambda ds: f"Which lever buys what: {ds.main['scene']} {ds.main['preset']}",
    headline=_headline,
    intro="What `prdp-petsc ablation` printed: `compare --seeds` for the preset as given "
    "(`baseline`) and once per lever, each lever's preset settings on their own; one "
    "torch thread, configurations one after another. Each configuration's seeds "
    "result (per seed: errors, times, the runs compared) is kept in `ablation.json`.",
    output=lambda ds: format_ablation(ds.main).rstrip("\n"),
)
