"""``compare`` over several seeds: is PRDP's error ratio more than training's noise?

One seed's PRDP / K_full error ratio is one draw: two full-fidelity runs on the same
data that differ only in the network's initial weights and mini-batch order
(`compare`'s ``twin``) can end far apart.  `compare_seeds` runs `compare` (with its twin) for
each seed and summarises the ratios on a log scale, where "PRDP is 10 % worse" and
"10 % better" weigh the same:

* the geometric mean of PRDP's ratios and a 95 % Student-t interval for it
  (treating the seeds as independent draws);
* the same for the twin's ratios: the spread two equally valid runs show;
* the mean, smallest and largest saving in inner iterations and wall time, and on
  how many seeds PRDP met the per-seed test (`ACCURACY_RATIO`);
* the geometric mean and 95 % interval of each seed's ``speedup_vs_best_full``
  (`prdp_petsc.lab.training.summary.speedup_vs_best_full`: the fastest full-fidelity
  route's time to full-fidelity accuracy over the fastest reduced run's), and on
  how many seeds it reached `SPEEDUP_GOAL`.

Decisions, written down: the per-seed test stays the verdict of each `compare`; this
summary adds the evidence a single seed cannot give.  Its reading of the interval:
entirely at or below 1.05, PRDP is within 5 %; entirely above, it is behind; across
1.05, these seeds cannot decide.  PRDP and K_full share initial weights and batch
order, so their ratio is a paired comparison; the twin changes both and so bounds
the noise from above.  A seed whose PRDP or K_full run stopped (diverged, invalid
input) has no ratio: it counts as a seed that did not meet the test and stays out of
the statistics, which say how many seeds they rest on.  With ``routes``, each seed's
table reports them; the error ratios cover the scene's own solver only, the speedup
every route and schedule.  A seed without a speedup (no reduced run reached
full-fidelity accuracy) is a failure: it is named with its reason, stays out of the
speedup's statistics (a ratio that does not exist has no logarithm) and counts as
short of `SPEEDUP_GOAL`.
"""

from __future__ import annotations

import math
from pathlib import Path

from .compare import compare
from .parallel import Parallel
from .records import write_json
from .summary import ACCURACY_RATIO, format_table, stopped_runs

__all__ = [
    "SPEEDUP_GOAL",
    "compare_seeds",
    "equal_accuracy_savings",
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
    """Geometric mean of positive ratios and its 95 % Student-t interval.

    ``interval`` is None for fewer than two ratios; a ratio that is not finite (a
    diverged run) makes ``geometric_mean`` inf, a zero one makes it 0.
    """
    if not ratios:
        raise ValueError("ratio_statistics needs at least one ratio")
    if any(not (math.isfinite(r) and r >= 0) for r in ratios):  # a diverged run, NaN
        return {"geometric_mean": math.inf, "interval": None, "n": len(ratios)}
    finite = [r for r in ratios if r > 0]
    if len(finite) < len(ratios):  # an error of exactly zero: no log scale
        return {"geometric_mean": 0.0, "interval": None, "n": len(ratios)}
    logs = [math.log(r) for r in finite]
    n = len(logs)
    mean = sum(logs) / n
    out = {"geometric_mean": math.exp(mean), "interval": None, "n": n}
    if n >= 2:
        from scipy.stats import t

        sd = math.sqrt(sum((x - mean) ** 2 for x in logs) / (n - 1))
        half = t.ppf(0.975, n - 1) * sd / math.sqrt(n)
        out["interval"] = [math.exp(mean - half), math.exp(mean + half)]
        out["log_sd"] = sd
    return out


def optional_ratio_statistics(ratios: list[float]) -> dict:
    """`ratio_statistics`, or ``geometric_mean`` and ``interval`` None with ``n`` 0 where
    there is no ratio (no seed where both runs of a comparison reached the target)."""
    if not ratios:
        return {"geometric_mean": None, "interval": None, "n": 0}
    return ratio_statistics(ratios)


def _spread(values: list[float]) -> dict:
    return {"mean": sum(values) / len(values), "min": min(values), "max": max(values)}


def equal_accuracy_savings(per_seed: list[dict]) -> dict | None:
    """Savings over the seeds whose PRDP run reached full-fidelity accuracy only.

    A seed whose PRDP ended more than `ACCURACY_RATIO` times full fidelity's error
    saved nothing at equal accuracy, so its iterations do not count.  Returns
    ``{"seeds": n, "iterations_saved": spread, "wall_time_saved": spread}`` (mean,
    min, max over those n seeds), or None when no seed reached equal accuracy.
    """
    equal = [r for r in per_seed if r.get("equal_accuracy")]
    if not equal:
        return None
    keys = ("iterations_saved", "wall_time_saved")
    return {"seeds": len(equal), **{key: _spread([r[key] for r in equal]) for key in keys}}


def compare_seeds(scene_file, seeds: list[int], *, out="results", **kwargs) -> dict:
    """`compare` (with ``twin=True`` unless `kwargs` say otherwise) for each seed into
    ``out/seed_S``; summarise.

    Keyword arguments go to `compare`.  Writes ``out/seeds.json`` after every seed
    (so an interrupted study keeps what it measured) and returns it: ``scene``,
    ``seeds``, ``per_seed`` (K_full, final errors, PRDP ratio, twin ratio,
    savings, per-seed verdict, ``speedup_vs_best_full`` with the two runs it
    compares or ``speedup_unavailable``, ``reach_seconds``: every run's
    ``time_to_full_accuracy``) and, over the seeds whose PRDP and K_full
    runs both finished, ``prdp_ratio`` and ``twin_ratio`` (`ratio_statistics`),
    ``savings`` (`iterations`, `wall_time`: mean, min, max) and ``equal_accuracy``
    (count of seeds that met the per-seed test); ``speedup`` (`ratio_statistics`
    of the seeds' speedups, with ``failures``: the seeds without one, and
    ``goal_met``: how many seeds reached `SPEEDUP_GOAL`).
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
        runs = summary["runs"]
        k = summary["k_full"]
        row = {
            "seed": seed,
            "k_full": k,
            "prdp_val_error": runs.get("prdp", {}).get("final_val_error"),
            "full_val_error": runs.get(f"fixed:{k}", {}).get("final_val_error"),
            "twin_val_error": runs.get(f"twin:{k}", {}).get("final_val_error"),
            "prdp_k_final": runs.get("prdp", {}).get("k_final"),
            "stopped": stopped_runs(summary),
            "speedup_vs_best_full": summary.get("speedup_vs_best_full"),
            # every run's time to full-fidelity accuracy: what each schedule and route bought
            "reach_seconds": {n: r.get("time_to_full_accuracy") for n, r in runs.items()},
            "runs": len(runs),
        }
        if summary.get("reused"):  # --resume: read from an earlier comparison, not trained
            row["reused"] = list(summary["reused"])
        detail = summary.get("speedup") or {}
        if row["speedup_vs_best_full"] is None:
            row["speedup_unavailable"] = detail.get("unavailable", "compare gave no speedup")
        else:
            row["speedup_full"], row["speedup_reduced"] = detail["full"], detail["reduced"]
        # the fastest full and reduced times, each where it exists (a seed whose reduced
        # runs never reached still has its full-fidelity time)
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
        per_seed.append(row)
        result = _aggregate(Path(scene_file).stem, seeds, per_seed)
        if root:
            write_json(out / "seeds.json", result)
    if kwargs.get("plots", True) and root:
        result["plot"] = plot_seeds(result, out)
        write_json(out / "seeds.json", result)
    result["tables"] = tables
    return result


def seeds_figure(result: dict):
    """The figure of `plot_seeds`, unsaved (a matplotlib Figure); None without any ratio.

    Left, per seed, the PRDP / full and twin / full error ratios on a log scale (where
    "10 % worse" and "10 % better" lie equally far from 1), with the lines at 1 and
    at the per-seed test; right, the wall time PRDP saved.  Limits, ticks and styles
    follow `prdp_petsc.lab.training.plots`: limits from the points and lines drawn, plain
    tick labels, PRDP and the twin marked as in `compare`'s plots.
    """
    rows = [r for r in result["per_seed"] if "prdp_ratio" in r]
    if not rows:
        return None
    from matplotlib.figure import Figure

    from .plots import run_styles, scale_axis

    style = run_styles(["prdp", "twin:1"], 1)
    prdp, twin = style["prdp"], style["twin:1"]
    x = list(range(len(rows)))
    accuracy = result["accuracy"]
    fig = Figure(figsize=(10, 4.2), dpi=120, layout="constrained")
    left, right = fig.subplots(1, 2)
    left.axhline(1.0, color="0.45", lw=0.9, label="equal error (ratio 1)")
    left.axhline(accuracy, color="C3", lw=0.9, ls="--", label=f"per-seed test (ratio {accuracy})")
    ratios = [r["prdp_ratio"] for r in rows]
    left.plot(x, ratios, ls="none", marker=prdp["marker"], color=prdp["color"], ms=7,
              label="PRDP / full")  # fmt: skip
    twins = [i for i in x if rows[i].get("twin_ratio")]
    twin_ratios = [rows[i]["twin_ratio"] for i in twins]
    if twins:
        left.plot(twins, twin_ratios, ls="none", marker=twin["marker"], color=twin["color"],
                  mfc="none", mew=1.5, ms=7, label="twin / full (second seed)")  # fmt: skip
    drawn = [*ratios, *twin_ratios, 1.0, accuracy]
    scale_axis(left, "y", [drawn], log=min(drawn) > 0)
    left.set_ylabel("final validation error ratio to full fidelity")
    saved = [100 * r["wall_time_saved"] for r in rows]
    right.bar(x, saved, color="C2", width=0.6)
    right.axhline(0.0, color="0.45", lw=0.9)
    scale_axis(right, "y", [saved, [0.0]], log=False)
    if min(saved) >= 0:  # bars stand on the axis
        right.set_ylim(bottom=0)
    right.set_ylabel("wall time saved by PRDP [%]")
    for ax in (left, right):
        ax.set_xticks(x, [str(r["seed"]) for r in rows])
        ax.set_xlim(-0.6, len(rows) - 0.4)
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
    fig.savefig(Path(out) / "seeds.png")
    return "seeds.png"


def _aggregate(scene: str, seeds: list[int], per_seed: list[dict]) -> dict:
    done = [r for r in per_seed if "prdp_ratio" in r]
    result = {"scene": scene, "seeds": seeds, "per_seed": per_seed, "accuracy": ACCURACY_RATIO}
    result.update(_speedups(per_seed))
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
    seed where both reached it (above 1: A got there sooner), as `ratio_statistics`
    (its ``n``: the seeds where both reached) plus ``seeds`` (the seeds compared).
    The pairs: each route's full fidelity against the scene solver's
    (``"full@cg/icc vs full"``: the preconditioner's worth); ``prdp`` and ``rtol``
    against full fidelity on the same solver, scene's or route's
    (``"prdp@cg/icc vs full@cg/icc"``: the schedule's worth there); the best constant
    coarse K against the scene solver's full fidelity.  The twin is no lever.  Empty
    for rows without ``reach_seconds``.
    """
    pairs: dict[str, list[float]] = {}

    def add(label: str, reference, lever) -> None:
        values = pairs.setdefault(label, [])
        if reference and lever:
            values.append(reference / lever)

    for row in per_seed:
        reach = row.get("reach_seconds")
        if not reach:
            continue
        full = f"fixed:{row['k_full']}"
        routes = sorted({n.split("@", 1)[1] for n in reach if "@" in n})
        for schedule in ("prdp", "rtol"):
            if schedule in reach:
                add(f"{schedule} vs full", reach.get(full), reach[schedule])
        coarse = [
            t for n, t in reach.items()
            if n.startswith("fixed:") and "@" not in n and n != full and t is not None
        ]  # fmt: skip
        add("best coarse K vs full", reach.get(full), min(coarse) if coarse else None)
        for route in routes:
            fulls = [n for n in reach if n.startswith("fixed:") and n.endswith(f"@{route}")]
            if not fulls:
                continue
            add(f"full@{route} vs full", reach.get(full), reach[fulls[0]])
            for schedule in ("prdp", "rtol"):
                name = f"{schedule}@{route}"
                if name in reach:
                    add(f"{name} vs full@{route}", reach[fulls[0]], reach[name])
    rows = len([r for r in per_seed if r.get("reach_seconds")])
    return {label: {**optional_ratio_statistics(v), "seeds": rows} for label, v in pairs.items()}


def _speedups(per_seed: list[dict]) -> dict:
    """``speedup``: statistics of the seeds' speedups, failures named (see the module)."""
    if not any("speedup_vs_best_full" in r for r in per_seed):
        return {}  # rows of an older comparison
    values = [
        r["speedup_vs_best_full"] for r in per_seed if r.get("speedup_vs_best_full") is not None
    ]
    failures = [
        {"seed": r["seed"], "reason": r.get("speedup_unavailable", "no speedup")}
        for r in per_seed
        if r.get("speedup_vs_best_full") is None
    ]
    out = optional_ratio_statistics(values)
    out.update(
        n=len(values),
        seeds=len(per_seed),
        failures=failures,
        goal=SPEEDUP_GOAL,
        goal_met=sum(v >= SPEEDUP_GOAL for v in values),
    )
    bounds = [r["solver_bound"] for r in per_seed if r.get("solver_bound") is not None]
    if bounds:  # the fastest full-fidelity run's solver-only bound (summary.solver_bound)
        out["solver_bound"] = ratio_statistics(bounds)
    return {"speedup": out}


def _verdict(interval: list[float] | None, accuracy: float) -> str | None:
    """What a 95 % interval of the PRDP / full ratio says about ``ratio <= accuracy``."""
    if not interval:
        return None
    lo, hi = interval
    if hi <= accuracy:
        return f"  the PRDP interval lies at or below {accuracy}: within 5 % of full fidelity"
    if lo > accuracy:
        return f"  the PRDP interval lies above {accuracy}: PRDP is behind full fidelity"
    return f"  the PRDP interval reaches past {accuracy}: these seeds cannot decide a 5 % question"


def format_seeds(result: dict) -> str:
    """Plain-text table of `compare_seeds`: one row per seed, then the summary lines.

    Column ``speedup``: the seed's ``speedup_vs_best_full`` (— where there is none);
    results written before it existed keep their old table.
    """
    has_speedup = "speedup" in result
    lines = [
        f"scene {result['scene']}   seeds {', '.join(map(str, result['seeds']))}",
        f"{'seed':>4}{'K_full':>8}{'PRDP err':>12}{'full err':>12}{'twin err':>12}"
        f"{'PRDP/full':>11}{'twin/full':>11}{'its saved':>11}{'wall saved':>12}{'K final':>9}"
        + (f"{'speedup':>9}" if has_speedup else ""),
    ]
    for r in result["per_seed"]:
        speedup = _num(r.get("speedup_vs_best_full"), 9, ".2f") if has_speedup else ""
        if "prdp_ratio" not in r:
            why = r["savings_unavailable"] + (f"; speedup {speedup.strip()}" if speedup else "")
            lines.append(f"{r['seed']:>4}{r['k_full']:>8}  {why}")
            continue
        twin = r.get("twin_ratio")
        lines.append(
            f"{r['seed']:>4}{r['k_full']:>8}{r['prdp_val_error']:>12.4e}"
            f"{r['full_val_error']:>12.4e}{_num(r['twin_val_error'], 12, '.4e')}"
            f"{r['prdp_ratio']:>11.3f}{_num(twin, 11, '.3f')}"
            f"{100 * r['iterations_saved']:>10.1f}%{100 * r['wall_time_saved']:>11.1f}%"
            f"{_num(r['prdp_k_final'], 9, '')}{speedup}"
        )
    speedup = _speedup_lines(result.get("speedup"))
    if "prdp_ratio" not in result:
        return "\n".join([*lines, "no seed gave PRDP and K_full over the same epochs", *speedup])
    lines.append(_savings_line(result))
    lines.append(_ratio_line("PRDP / full", result["prdp_ratio"]))
    if "twin_ratio" in result:
        lines.append(_ratio_line("twin / full", result["twin_ratio"]))
    missing = len(result["per_seed"]) - result["compared"]
    lines.append(
        f"per-seed test (ratio <= {result['accuracy']}): met on "
        f"{result['equal_accuracy']} of {len(result['per_seed'])} seeds"
        + (f" ({missing} without a comparison: a run stopped)" if missing else "")
    )
    verdict = _verdict(result["prdp_ratio"].get("interval"), result["accuracy"])
    if verdict:
        lines.append(verdict)
    reused = sum(len(r.get("reused", [])) for r in result["per_seed"])
    if reused:  # the wall times are the runs' own, from when they trained
        lines.append(
            f"{reused} of {sum(r.get('runs', 0) for r in result['per_seed'])} runs were read "
            "from an earlier comparison (--resume), with the wall times they recorded"
        )
    return "\n".join(lines + speedup + _lever_lines(result.get("levers")))


def _lever_lines(levers: dict | None) -> list[str]:
    """Lines of `lever_ratios`: one per comparison, where it had a seed."""
    if not levers:
        return []
    lines = ["time to full-fidelity accuracy, B / A for 'A vs B' (above 1: A sooner):"]
    for label, stats in levers.items():
        if stats["n"]:
            lines.append("  " + _ratio_line(label, stats) + f" of {stats['seeds']} seeds")
        else:
            lines.append(f"  {label}: never both reached (of {stats['seeds']} seeds)")
    return lines


def _speedup_lines(stats: dict | None) -> list[str]:
    """Lines of the seeds' ``speedup_vs_best_full``: statistics, goal, failures."""
    if not stats:
        return []
    if stats["n"]:
        lines = [_ratio_line("speedup vs best full fidelity", stats)]
    else:
        lines = ["speedup vs best full fidelity: on no seed did a reduced run reach it"]
    lines.append(
        f"speedup >= {stats['goal']:g} on {stats['goal_met']} of {stats['seeds']} seeds"
        + (f" ({len(stats['failures'])} without a speedup)" if stats["failures"] else "")
    )
    lines += [f"  seed {f['seed']}: no speedup, {f['reason']}" for f in stats["failures"]]
    if stats.get("solver_bound"):
        lines.append(
            _ratio_line(
                "solver-only bound (the fastest full run's wall time over its time outside "
                "the solver)",
                stats["solver_bound"],
            )
        )
    return lines


def _num(value, width: int, spec: str) -> str:
    return ("—" if value is None else format(value, spec)).rjust(width)


def _pct(spread: dict) -> str:
    return (
        f"{100 * spread['mean']:.1f} % mean ({100 * spread['min']:.1f}–{100 * spread['max']:.1f} %)"
    )


def _ratio_line(name: str, stats: dict) -> str:
    line = f"{name}: geometric mean {stats['geometric_mean']:.3f}"
    if stats.get("interval"):
        lo, hi = stats["interval"]
        line += f", 95 % interval {lo:.3f}–{hi:.3f}"
    return line + f" (n = {stats['n']})"


def _savings_line(result: dict) -> str:
    """Savings over the seeds at equal accuracy only, saying how many of them there were."""
    s = equal_accuracy_savings(result["per_seed"])
    if s is None:
        return (
            f"savings: none at equal accuracy (PRDP ended more than {ACCURACY_RATIO}x full "
            f"fidelity's error on all {result['compared']} seeds compared)"
        )
    return (
        f"savings over the {s['seeds']} of {result['compared']} seeds at equal accuracy: "
        f"inner iterations {_pct(s['iterations_saved'])}, wall time {_pct(s['wall_time_saved'])}"
    )
