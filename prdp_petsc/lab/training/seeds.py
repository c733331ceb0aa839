"""``compare`` over several seeds: is PRDP's error ratio more than training's noise?

One seed's PRDP / K_full error ratio is one draw; `compare`'s ``twin`` (full fidelity
with other initial weights and batch order) shows how far two equally valid runs end
apart.  `compare_seeds` runs `compare` with its twin for each seed and summarises the
ratios on a log scale, where "10 % worse" and "10 % better" weigh the same: geometric
means with 95 % Student-t intervals (`ratio_statistics`) of PRDP's and the twin's
ratios and of each seed's ``speedup_vs_best_full``, the savings on the seeds at equal
accuracy (`equal_accuracy_savings`), and what each schedule and route bought
(`lever_ratios`).  The per-seed test stays each `compare`'s verdict; an interval
entirely at or below `ACCURACY_RATIO` says PRDP is within 5 %, entirely above that it
is behind, across it that these seeds cannot decide.  A seed whose PRDP or K_full run
stopped has no ratio, and one without a speed-up none: each is named, counts against
its test and stays out of the statistics.
"""

from __future__ import annotations

import math
from pathlib import Path

from .accuracy import ACCURACY_RATIO
from .compare import compare
from .parallel import Parallel
from .records import write_json
from .summary import format_table, plain_table, stopped_runs

__all__ = [
    "SPEEDUP_GOAL",
    "compare_seeds",
    "equal_accuracy_savings",
    "format_ratio",
    "format_seeds",
    "lever_ratios",
    "optional_ratio_statistics",
    "plot_seeds",
    "ratio_statistics",
    "seeds_figure",
]

#: The speedup over the best full-fidelity route a reduced run should reach (2: twice as fast)
SPEEDUP_GOAL = 2.0


def ratio_statistics(ratios: list[float]) -> dict:
    """Geometric mean of ratios >= 0 and its 95 % Student-t interval (on their logs).

    ``interval`` is None for fewer than two ratios; a ratio that is not finite (a
    diverged run) makes ``geometric_mean`` inf, a zero one makes it 0.
    """
    import numpy as np
    from scipy import stats

    if not ratios:
        raise ValueError("ratio_statistics needs at least one ratio")
    values = np.asarray(ratios, dtype=float)
    n = len(values)
    if not np.all(np.isfinite(values) & (values >= 0)):  # a diverged run, NaN
        return {"geometric_mean": math.inf, "interval": None, "n": n}
    if np.any(values == 0):  # an error of exactly zero: no log scale
        return {"geometric_mean": 0.0, "interval": None, "n": n}
    logs = np.log(values)
    out = {"geometric_mean": math.exp(logs.mean()), "interval": None, "n": n}
    if n >= 2:
        half = stats.t.ppf(0.975, n - 1) * stats.sem(logs)
        out["interval"] = [math.exp(logs.mean() - half), math.exp(logs.mean() + half)]
        out["log_sd"] = float(logs.std(ddof=1))
    return out


def optional_ratio_statistics(ratios: list[float]) -> dict:
    """`ratio_statistics`, or ``geometric_mean`` and ``interval`` None with ``n`` 0
    where there is no ratio."""
    if not ratios:
        return {"geometric_mean": None, "interval": None, "n": 0}
    return ratio_statistics(ratios)


def format_ratio(
    stats: dict | None, spec: str = ".3f", unit: str = "", extra: str = "", ci_spec: str = ""
) -> str:
    """``1.234× (95 % interval 1.100–1.384, n = 3)``: the geometric mean of `stats`
    (`ratio_statistics`) in format `spec` with `unit`, then its interval (in `ci_spec`,
    `spec` by default) and `extra` where there are any; ``—`` for a missing mean."""
    mean = (stats or {}).get("geometric_mean")
    inside = []
    if (stats or {}).get("interval"):
        lo, hi = stats["interval"]
        inside.append(f"95 % interval {lo:{ci_spec or spec}}–{hi:{ci_spec or spec}}")
    if extra:
        inside.append(extra)
    text = "—" if mean is None else f"{mean:{spec}}{unit}"
    return text + (f" ({', '.join(inside)})" if inside else "")


def equal_accuracy_savings(
    per_seed: list[dict], keys=("iterations_saved", "wall_time_saved")
) -> dict | None:
    """Savings over the seeds whose reduced run reached full-fidelity accuracy only.

    A seed whose run ended more than `ACCURACY_RATIO` times full fidelity's error (its
    row's ``equal_accuracy`` false) saved nothing at equal accuracy.  Returns
    ``{"seeds": n, key: spread, ...}`` for each of `keys` (mean, min, max over those n
    seeds), or None when no seed reached equal accuracy.
    """
    equal = [r for r in per_seed if r.get("equal_accuracy")]
    if not equal:
        return None
    out = {"seeds": len(equal)}
    for key in keys:
        values = [r[key] for r in equal]
        out[key] = {"mean": sum(values) / len(values), "min": min(values), "max": max(values)}
    return out


def compare_seeds(scene_file, seeds: list[int], *, out="results", **kwargs) -> dict:
    """`compare` (with ``twin=True`` unless `kwargs` say otherwise) for each seed into
    ``out/seed_S``; summarise into ``out/seeds.json``, written after every seed.

    Keyword arguments go to `compare`.  Returns ``scene``, ``seeds``, ``per_seed``
    (K_full, final errors, ratios, savings, per-seed verdict, the speed-up with its two
    runs or ``speedup_unavailable``, ``reach_seconds``: every run's
    ``time_to_full_accuracy``), the statistics over the seeds (``prdp_ratio``,
    ``twin_ratio``, ``savings``, ``equal_accuracy``, ``compared``, ``speedup``,
    ``levers``) and ``tables``, each seed's `format_table`.
    """
    if not seeds:
        raise ValueError("compare_seeds needs at least one seed")
    seeds = list(dict.fromkeys(seeds))  # a seed twice would count twice
    out = Path(out)
    root = Parallel(kwargs.get("parallel")).root  # rank 0 alone writes files
    per_seed, tables = [], []
    for seed in seeds:
        summary = compare(
            scene_file, seed=seed, out=out / f"seed_{seed}", **{"twin": True, **kwargs}
        )
        tables.append(f"seed {seed}\n{format_table(summary)}")
        per_seed.append(_seed_row(seed, summary))
        result = _aggregate(Path(scene_file).stem, seeds, per_seed)
        if root:
            write_json(out / "seeds.json", result)
    if kwargs.get("plots", True) and root:
        result["plot"] = plot_seeds(result, out)
        write_json(out / "seeds.json", result)
    result["tables"] = tables
    return result


def _seed_row(seed: int, summary: dict) -> dict:
    """One seed's row of ``per_seed`` from its comparison's summary."""
    runs, k = summary["runs"], summary["k_full"]
    detail = summary.get("speedup") or {}
    row = {
        "seed": seed,
        "k_full": k,
        "prdp_val_error": runs.get("prdp", {}).get("final_val_error"),
        "full_val_error": runs.get(f"fixed:{k}", {}).get("final_val_error"),
        "twin_val_error": runs.get(f"twin:{k}", {}).get("final_val_error"),
        "prdp_k_final": runs.get("prdp", {}).get("k_final"),
        "stopped": stopped_runs(summary),
        "speedup_vs_best_full": summary.get("speedup_vs_best_full"),
        "reach_seconds": {n: r.get("time_to_full_accuracy") for n, r in runs.items()},
        "runs": len(runs),
    }
    if summary.get("reused"):  # --resume: read from an earlier comparison, not trained
        row["reused"] = list(summary["reused"])
    if row["speedup_vs_best_full"] is None:
        row["speedup_unavailable"] = detail.get("unavailable", "compare gave no speedup")
    else:
        row["speedup_full"], row["speedup_reduced"] = detail["full"], detail["reduced"]
    row["full_seconds"] = detail.get("full_seconds")
    row["reduced_seconds"] = detail.get("reduced_seconds")
    if detail.get("solver_bound") is not None:
        row["solver_bound"] = detail["solver_bound"]
    if "savings" in summary:
        row.update(
            prdp_ratio=summary["val_error_ratio"],
            twin_ratio=summary.get("noise_ratio"),
            iterations_saved=summary["savings"]["iterations"],
            wall_time_saved=summary["savings"]["wall_time"],
            equal_accuracy=summary["equal_accuracy"],
        )
    else:
        row["savings_unavailable"] = summary["savings_unavailable"]
    return row


def seeds_figure(result: dict):
    """The figure of `plot_seeds`, unsaved (a matplotlib Figure); None without any ratio.

    Left, per seed, the PRDP / full and twin / full error ratios, with
    the lines at 1 and at the per-seed test; right, the wall time PRDP saved.
    """
    rows = [r for r in result["per_seed"] if "prdp_ratio" in r]
    if not rows:
        return None
    from matplotlib.figure import Figure

    from .plots import run_styles

    style = run_styles(["prdp", "twin:1"], 1)
    seeds = [str(r["seed"]) for r in rows]
    fig = Figure(figsize=(10, 4.2), layout="constrained")
    left, right = fig.subplots(1, 2)
    left.axhline(1.0, color="0.45", lw=0.9, label="equal error (ratio 1)")
    accuracy = result["accuracy"]
    left.axhline(accuracy, color="C3", ls="--", lw=0.9, label=f"per-seed test (ratio {accuracy})")
    left.plot(seeds, [r["prdp_ratio"] for r in rows], ls="none", color=style["prdp"]["color"],
              marker=style["prdp"]["marker"], label="PRDP / full")  # fmt: skip
    twins = [(str(r["seed"]), r["twin_ratio"]) for r in rows if r.get("twin_ratio")]
    if twins:
        left.plot(*zip(*twins, strict=True), ls="none", color=style["twin:1"]["color"], mfc="none",
                  marker=style["twin:1"]["marker"], label="twin / full (second seed)")  # fmt: skip
    left.set_ylabel("final validation error ratio to full fidelity")
    right.bar(seeds, [100 * r["wall_time_saved"] for r in rows], color="C2", width=0.6)
    right.axhline(0.0, color="0.45", lw=0.9)
    right.set_ylabel("wall time saved by PRDP [%]")
    for ax in (left, right):
        ax.set_xlabel("seed")
        ax.grid(alpha=0.3)
    fig.legend(loc="outside lower center", ncols=4, fontsize=8, frameon=False)
    fig.suptitle(f"{result['scene']}: PRDP against full fidelity, seed by seed")
    return fig


def plot_seeds(result: dict, out) -> str | None:
    """Write ``seeds.png`` (`seeds_figure`) into `out`; its name, or None without any ratio."""
    fig = seeds_figure(result)
    if fig is None:
        return None
    fig.savefig(Path(out) / "seeds.png", dpi=120)
    return "seeds.png"


def _aggregate(scene: str, seeds: list[int], per_seed: list[dict]) -> dict:
    """``seeds.json`` over the rows so far: the statistics of the module docstring."""
    done = [r for r in per_seed if "prdp_ratio" in r]
    result = {"scene": scene, "seeds": seeds, "per_seed": per_seed, "accuracy": ACCURACY_RATIO}
    if any("speedup_vs_best_full" in r for r in per_seed):  # not in rows of older comparisons
        result["speedup"] = _speedups(per_seed)
    levers = lever_ratios(per_seed)
    if levers:
        result["levers"] = levers
    if not done:
        return result
    result["prdp_ratio"] = ratio_statistics([r["prdp_ratio"] for r in done])
    twins = [r["twin_ratio"] for r in done if r.get("twin_ratio") is not None]
    if twins:
        result["twin_ratio"] = ratio_statistics(twins)
    result["savings"] = equal_accuracy_savings(done)
    result["equal_accuracy"] = sum(r["equal_accuracy"] for r in done)
    result["compared"] = len(done)
    return result


def lever_ratios(per_seed: list[dict]) -> dict:
    """What each schedule and route bought, from the seeds' ``reach_seconds``.

    Per comparison ``"A vs B"``: B's time to full-fidelity accuracy over A's, seed by
    seed where both reached it (above 1: A got there sooner), as
    `optional_ratio_statistics` plus ``seeds`` (the rows with times).  The pairs: each
    route's full fidelity against the scene solver's; ``prdp`` and ``rtol`` against
    full fidelity on the same solver; the best coarse constant K against the scene
    solver's full fidelity.  Empty for rows without ``reach_seconds``.
    """
    pairs: dict[str, list[float]] = {}

    def add(label: str, reference, lever) -> None:
        values = pairs.setdefault(label, [])
        if reference and lever:
            values.append(reference / lever)

    rows = [row for row in per_seed if row.get("reach_seconds")]
    for row in rows:
        reach = row["reach_seconds"]
        full = f"fixed:{row['k_full']}"
        fulls = {"": full}  # the full-fidelity run of each solver
        for name in reach:
            schedule, _, route = name.partition("@")
            if route and schedule.startswith("fixed:"):
                fulls.setdefault(route, name)
        coarse = [
            t for n, t in reach.items()
            if n.startswith("fixed:") and "@" not in n and n != full and t is not None
        ]  # fmt: skip
        for route, reference in sorted(fulls.items()):
            at = f"@{route}" if route else ""
            if route:
                add(f"full{at} vs full", reach.get(full), reach[reference])
            for schedule in ("prdp", "rtol"):
                if schedule + at in reach:
                    add(f"{schedule}{at} vs full{at}", reach.get(reference), reach[schedule + at])
            if not route:
                add("best coarse K vs full", reach.get(full), min(coarse) if coarse else None)
    return {
        label: {**optional_ratio_statistics(v), "seeds": len(rows)} for label, v in pairs.items()
    }


def _speedups(per_seed: list[dict]) -> dict:
    """Statistics of the seeds' speed-ups, the seeds without one named, and the goal."""
    values = [
        r["speedup_vs_best_full"] for r in per_seed if r.get("speedup_vs_best_full") is not None
    ]
    failures = [
        {"seed": r["seed"], "reason": r.get("speedup_unavailable", "no speedup")}
        for r in per_seed
        if r.get("speedup_vs_best_full") is None
    ]
    out = optional_ratio_statistics(values)
    out.update(n=len(values), seeds=len(per_seed), failures=failures, goal=SPEEDUP_GOAL,
               goal_met=sum(v >= SPEEDUP_GOAL for v in values))  # fmt: skip
    bounds = [r["solver_bound"] for r in per_seed if r.get("solver_bound") is not None]
    if bounds:  # the fastest full-fidelity run's solver-only bound (summary.solver_bound)
        out["solver_bound"] = ratio_statistics(bounds)
    return out


def format_seeds(result: dict) -> str:
    """Plain-text table of `compare_seeds`: one row per seed, then the summary lines."""
    has_speedup = "speedup" in result
    rows = []
    for r in result["per_seed"]:
        row = {
            "seed": r["seed"], "K_full": r["k_full"], "PRDP err": r.get("prdp_val_error"),
            "full err": r.get("full_val_error"), "twin err": r.get("twin_val_error"),
            "PRDP/full": r.get("prdp_ratio"), "twin/full": r.get("twin_ratio"),
            "its saved %": _percent(r.get("iterations_saved")),
            "wall saved %": _percent(r.get("wall_time_saved")), "K final": r.get("prdp_k_final"),
        }  # fmt: skip
        if has_speedup:
            row["speedup"] = r.get("speedup_vs_best_full")
        rows.append(row)
    table = plain_table(rows, ("", "", ".4e", ".4e", ".4e", ".3f", ".3f", ".1f", ".1f", "", ".2f"))
    lines = [f"scene {result['scene']}   seeds {', '.join(map(str, result['seeds']))}", table]
    lines += [f"seed {r['seed']}: {r['savings_unavailable']}" for r in result["per_seed"]
              if "prdp_ratio" not in r]  # fmt: skip
    if "prdp_ratio" not in result:
        lines.append("no seed gave PRDP and K_full over the same epochs")
    else:
        lines += _comparison_lines(result)
    stats = result.get("speedup")
    if stats:
        if stats["n"]:
            lines.append(_ratio_line("speedup vs best full fidelity", stats))
        else:
            lines.append("speedup vs best full fidelity: on no seed did a reduced run reach it")
        lines.append(
            f"speedup >= {stats['goal']:g} on {stats['goal_met']} of {stats['seeds']} seeds"
            + (f" ({len(stats['failures'])} without a speedup)" if stats["failures"] else "")
        )
        lines += [f"  seed {f['seed']}: no speedup, {f['reason']}" for f in stats["failures"]]
        if stats.get("solver_bound"):
            lines.append(
                _ratio_line("solver-only bound (the fastest full run's wall time over its time "
                            "outside the solver)", stats["solver_bound"])
            )  # fmt: skip
    if result.get("levers"):
        lines.append("time to full-fidelity accuracy, B / A for 'A vs B' (above 1: A sooner):")
        for label, s in result["levers"].items():
            lines.append(
                "  " + _ratio_line(label, s, f" of {s['seeds']} seeds")
                if s["n"]
                else f"  {label}: never both reached (of {s['seeds']} seeds)"
            )
    return "\n".join(lines)


def _comparison_lines(result: dict) -> list[str]:
    """Savings at equal accuracy, the two error ratios and what their interval says."""
    accuracy, compared = result["accuracy"], result["compared"]
    s = equal_accuracy_savings(result["per_seed"])
    if s is None:
        lines = [
            f"savings: none at equal accuracy (PRDP ended more than {ACCURACY_RATIO}x full "
            f"fidelity's error on all {compared} seeds compared)"
        ]
    else:
        spread = {
            key: f"{100 * v['mean']:.1f} % mean ({100 * v['min']:.1f}–{100 * v['max']:.1f} %)"
            for key, v in s.items()
            if key != "seeds"
        }
        lines = [
            f"savings over the {s['seeds']} of {compared} seeds at equal accuracy: inner "
            f"iterations {spread['iterations_saved']}, wall time {spread['wall_time_saved']}"
        ]
    lines.append(_ratio_line("PRDP / full", result["prdp_ratio"]))
    if "twin_ratio" in result:
        lines.append(_ratio_line("twin / full", result["twin_ratio"]))
    missing = len(result["per_seed"]) - compared
    lines.append(
        f"per-seed test (ratio <= {accuracy}): met on {result['equal_accuracy']} of "
        f"{len(result['per_seed'])} seeds"
        + (f" ({missing} without a comparison: a run stopped)" if missing else "")
    )
    interval = result["prdp_ratio"].get("interval")
    if interval:
        lo, hi = interval
        where = (
            "lies at or below {}: within 5 % of full fidelity" if hi <= accuracy
            else "lies above {}: PRDP is behind full fidelity" if lo > accuracy
            else "reaches past {}: these seeds cannot decide a 5 % question"
        )  # fmt: skip
        lines.append("  the PRDP interval " + where.format(accuracy))
    reused = sum(len(r.get("reused", [])) for r in result["per_seed"])
    if reused:  # the wall times are the runs' own, from when they trained
        lines.append(
            f"{reused} of {sum(r.get('runs', 0) for r in result['per_seed'])} runs were read "
            "from an earlier comparison (--resume), with the wall times they recorded"
        )
    return lines


def _percent(value: float | None) -> float | None:
    return None if value is None else 100 * value


def _ratio_line(name: str, stats: dict, of: str = "") -> str:
    extra = f"n = {stats['n']}{of}"
    return f"{name}: geometric mean {format_ratio(stats, extra=extra)}"
