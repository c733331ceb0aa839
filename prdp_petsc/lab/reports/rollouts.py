"""Long rollouts side by side: trained correctors against each other and the solver alone.

``prdp-petsc rollouts --run NAME=DIR[,DIR...] ... [--ratio NAME/REFERENCE] --out OUT``
reads the ``results.json`` of finished runs (one folder per seed, the same seeds for
every NAME) and writes ``OUT/rollouts.json`` (`rollout_report`: per NAME the per-step
rollout error per seed and its geometric mean, wall time, inner iterations, on how many
seeds it stayed below the uncorrected solver at every step, and what made each run; per
``--ratio`` the ratios of error at ``--step``, iterations and wall time per seed with
their geometric mean and 95 % interval) and ``OUT/rollouts.png`` (the mean curves).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from scipy.stats import gmean

from ..cli.arguments import add_debug, add_out
from ..provenance import write_result
from ..training.seeds import format_ratio, ratio_statistics
from .kinds import DataSet, ReportKind, text_table

__all__ = ["KIND", "main", "rollout_report", "format_rollout_report"]


def _load(folder: Path) -> dict:
    result = json.loads((folder / "results.json").read_text())
    if not result.get("finished") or result.get("rollout") is None:
        raise ValueError(f"{folder}: not a finished run with a recorded rollout")
    return result


def _geomean(rows: list) -> list[float]:
    """The geometric mean over the seeds (rows) at every step."""
    return gmean(np.asarray(rows, dtype=float), axis=0).tolist()


def rollout_report(runs: dict[str, list[Path]], ratios: list[tuple[str, str]], step=None):
    """The report `main` writes (module notes) from ``{NAME: [folder per seed]}``."""
    seeds = {len(folders) for folders in runs.values()}
    if len(seeds) != 1:
        raise ValueError(f"every run needs the same number of seed folders, got {seeds}")
    loaded = {name: [_load(Path(f)) for f in folders] for name, folders in runs.items()}
    first = next(iter(loaded.values()))
    uncorrected = [r.get("uncorrected_rollout") for r in first]
    for name, results in loaded.items():
        for i, r in enumerate(results):
            u = r.get("uncorrected_rollout")
            if uncorrected[i] is not None and (u is None or not np.allclose(u, uncorrected[i])):
                raise ValueError(f"{name}, seed folder {i + 1}: another uncorrected rollout")
    steps = min(len(r["rollout"]) for results in loaded.values() for r in results)
    at = steps if step is None else step
    if not 1 <= at <= steps:
        raise ValueError(f"step must lie in [1, {steps}], got {step}")
    report = {"steps": steps, "step": at, "runs": {}, "ratios": {}}
    if all(u is not None for u in uncorrected):
        report["uncorrected"] = {
            "rollout": [u[:steps] for u in uncorrected],
            "geometric_mean": _geomean([u[:steps] for u in uncorrected]),
        }
    for name, results in loaded.items():
        curves = [r["rollout"][:steps] for r in results]
        entry = {
            "rollout": curves,
            "geometric_mean": _geomean(curves),
            "wall_time": [r["totals"]["wall_time"] for r in results],
            "iterations": [
                r["totals"]["fwd_iterations"] + r["totals"]["adj_iterations"] for r in results
            ],
            "k_final": [r["totals"]["k_final"] for r in results],
            # what made each run: its command line and commit (`provenance`)
            "made_by": [
                {key: r.get("provenance", {}).get(key) for key in ("command", "git")}
                for r in results
            ],
        }
        if "uncorrected" in report:
            below = [
                bool(np.all(np.asarray(c) < np.asarray(u)))
                for c, u in zip(curves, report["uncorrected"]["rollout"], strict=True)
            ]
            entry["below_uncorrected_every_step"] = sum(below)
        report["runs"][name] = entry
    for name, reference in ratios:
        if name not in loaded or reference not in loaded:
            raise ValueError(f"--ratio {name}/{reference}: both must be --run names")
        a, b = report["runs"][name], report["runs"][reference]
        pairs = zip(a["rollout"], b["rollout"], strict=True)
        per_seed = {
            "error": [x[at - 1] / y[at - 1] for x, y in pairs],
            "iterations": [x / y for x, y in zip(a["iterations"], b["iterations"], strict=True)],
            "wall_time": [x / y for x, y in zip(a["wall_time"], b["wall_time"], strict=True)],
        }
        report["ratios"][f"{name}/{reference}"] = {
            key: {"per_seed": values, **ratio_statistics(values)}
            for key, values in per_seed.items()
        }
    return report


def format_rollout_report(report: dict) -> str:
    """The report as the tables the command prints."""
    at = report["step"]
    marks = sorted({1, 5, 10, 20, 30, 40, at} & set(range(1, report["steps"] + 1)))
    runs = dict(report["runs"])
    if "uncorrected" in report:
        runs = {"uncorrected": report["uncorrected"], **runs}
    rows = [
        (name, *(f"{entry['geometric_mean'][s - 1]:.3f}" for s in marks),
         "—" if "below_uncorrected_every_step" not in entry
         else f"{entry['below_uncorrected_every_step']}/{len(entry['rollout'])}")
        for name, entry in runs.items()
    ]  # fmt: skip
    header = ["run", *(f"step {s}" for s in marks), "below uncorrected at every step"]
    lines = ["rollout error (geometric mean over seeds):", text_table(header, rows)]
    for pair, stats in report["ratios"].items():
        lines.append(f"{pair} (per seed; geometric mean):")
        for key, s in stats.items():
            label = f"error at step {at}" if key == "error" else key
            per = ", ".join(f"{v:.3f}" for v in s["per_seed"])
            lines.append(f"  {label:<18} {per}  ->  {format_ratio(s)}")
    return "\n".join(lines)


def rollouts_figure(report: dict):
    """Per-step error of every run (geometric mean over seeds) and of the solver alone."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 4.2), dpi=120, layout="constrained")
    ax = fig.add_subplot()
    steps = np.arange(1, report["steps"] + 1)
    if "uncorrected" in report:
        ax.plot(steps, report["uncorrected"]["geometric_mean"], "k--", label="uncorrected solver")
    for i, (name, entry) in enumerate(report["runs"].items()):
        # ten colours, then the same colours dotted; the first run (the one compared) bold
        style = {"linestyle": "-" if i < 10 else ":", "linewidth": 2.4 if i == 0 else 1.4}
        ax.plot(steps, entry["geometric_mean"], label=name, **style)
    seeds = len(next(iter(report["runs"].values()))["rollout"])
    ax.set_xlabel("rollout step")
    ax.set_ylabel(f"normalised velocity error (geometric mean, {seeds} seeds)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    fig.legend(loc="outside right upper", fontsize=8, frameon=False)
    return fig


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="prdp-petsc rollouts", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--run",
        action="append",
        required=True,
        metavar="NAME=DIR[,DIR...]",
        help="a run's result folders, one per seed (repeatable)",
    )
    parser.add_argument(
        "--ratio", action="append", default=[], metavar="NAME/REFERENCE", help="a ratio to report"
    )
    parser.add_argument("--step", type=int, help="the step of the error ratios (default: last)")
    add_out(parser)
    add_debug(parser)
    return parser


def main(argv: list[str]) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    runs = {}
    for spec in args.run:
        name, sep, folders = spec.partition("=")
        if not sep or not name or not folders:
            parser.error(f"--run expects NAME=DIR[,DIR...], got {spec!r}")
        runs[name] = [Path(f) for f in folders.split(",")]
    ratios = []
    for spec in args.ratio:
        name, sep, reference = spec.partition("/")
        if not sep:
            parser.error(f"--ratio expects NAME/REFERENCE, got {spec!r}")
        ratios.append((name, reference))
    report = rollout_report(runs, ratios, args.step)
    out = write_result(args.out, "rollouts.json", report).parent
    rollouts_figure(report).savefig(out / "rollouts.png")
    print(format_rollout_report(report))
    return 0 if all(math.isfinite(e["geometric_mean"][-1]) for e in report["runs"].values()) else 1


# -- the page of a recorded ``rollouts`` run ------------------------------------------------------
def _headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    out = []
    for name, entry in list(d["runs"].items())[:1]:  # the first run: the one compared
        below = entry.get("below_uncorrected_every_step")
        if below is not None:
            out.append(
                (
                    f"{ds.name}: `{name}` below the uncorrected solver at every one of "
                    f"{d['steps']} rollout steps",
                    f"on {below} of {len(entry['rollout'])} seeds",
                )
            )
    for pair, stats in d["ratios"].items():
        e = stats["error"]
        out.append(
            (
                f"{ds.name}: error ratio {pair} at rollout step {d['step']}",
                f"{format_ratio(e, ci_spec='.2f')}, {e['n']} seeds",
            )
        )
    return out


KIND = ReportKind(
    name="rollouts",
    reads="rollouts.json",
    title=lambda ds: f"Long rollouts against the uncorrected solver: {ds.name}",
    headline=_headline,
    intro="What `prdp-petsc rollouts` printed: the per-step error of each run's held-out "
    "rollout (geometric mean over the seeds) and of the uncorrected solver, on how "
    "many seeds each run stayed below the uncorrected solver at every step, and the "
    "ratios of error, inner iterations and wall time per seed with their geometric "
    "mean and 95 % interval:",
    output=lambda ds: format_rollout_report(ds.main).rstrip("\n"),
)
