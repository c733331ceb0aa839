"""The summary of a comparison and its table: savings, accuracy, time to accuracy.

`summarize` turns the per-run logs of `prdp_petsc.lab.training.compare.compare` into
``summary.json``; `format_table` prints it.  Runs are named ``schedule[@route]``: full
fidelity is ``fixed:K_full`` of its route, ``twin:K`` full fidelity with torch seeded
differently (the run-to-run noise), anything else a reduced run.
"""

from __future__ import annotations

import math

from prdp_petsc.prdp import savings

from .accuracy import ACCURACY_RATIO, accuracy_target, equal_accuracy_k, time_to_accuracy

__all__ = [
    "TWIN",
    "fastest",
    "format_table",
    "is_full",
    "plain_table",
    "solver_bound",
    "speedup_vs_best_full",
    "split_run",
    "stopped_runs",
    "summarize",
]

TWIN = "twin"  # compare's schedule name for the full-fidelity twin
_TOTALS = ("final_val_error", "best_val_error", "wall_time", "solver_time", "fwd_iterations",
           "adj_iterations", "k_final")  # fmt: skip


def summarize(
    scene: str,
    k_full: int | dict,
    logs: dict,
    *,
    threads: int | None = None,
    skipped: dict | None = None,
) -> dict:
    """Summary of a comparison: runs, PRDP savings against K_full, error ratios, speed-up.

    `k_full` is an int, or ``{route: K_full}`` with ``""`` for the scene's own solver;
    routes add ``routes`` (their K_full and PRDP savings, or ``{"skipped": why}`` for
    those in `skipped`) and ``fastest``.  Every run gets ``time_to_full_accuracy``
    (`time_to_accuracy` against full fidelity's final validation error); a twin adds
    ``noise_ratio``, its final validation error over K_full's.  Also
    `speedup_vs_best_full`, the ``auto`` schedule's savings and certificate, and
    ``equal_accuracy_k`` over the constant-K runs.
    """
    k_fulls = k_full if isinstance(k_full, dict) else {"": k_full}
    k_full = k_fulls[""]
    full_name, twin_name = f"fixed:{k_full}", f"{TWIN}:{k_full}"
    target = accuracy_target(logs, full_name)
    runs = {}
    for name, log in logs.items():
        run = {key: log["totals"].get(key) for key in _TOTALS}
        run.update(epochs=log["totals"]["epochs"], stopped=log["stopped"])
        if log.get("rtol"):  # the rtol schedule: where its tolerance ended, what it cost
            run["rtol"] = _rtol_summary(log)
        for key in ("rollout", "uncorrected_rollout"):  # per-step errors, when recorded
            if log.get(key) is not None:
                run[key] = log[key]
        run["time_to_full_accuracy"] = None if target is None else time_to_accuracy(log, target)
        runs[name] = run
    summary = {"scene": scene, "k_full": k_full, "threads": threads, "runs": runs}
    summary.update(speedup_vs_best_full(logs, k_fulls))
    twin, full = logs.get(twin_name), logs.get(full_name)
    if twin and full and not (twin["stopped"] or full["stopped"]):
        summary["noise_ratio"] = _ratio(
            twin["totals"]["final_val_error"], full["totals"]["final_val_error"]
        )
    if len(k_fulls) > 1 or skipped:
        summary["routes"] = {
            route: {"k_full": k, **_savings(logs, f"prdp@{route}", f"fixed:{k}@{route}")}
            for route, k in k_fulls.items()
            if route
        }
        summary["routes"].update(
            {route: {"skipped": why} for route, why in (skipped or {}).items()}
        )
        summary["fastest"] = fastest({n: g for n, g in logs.items() if n != twin_name}, full_name)
    summary.update(_savings(logs, "prdp", full_name))
    if "auto" in logs:  # the default construction beside the scene's tuned settings
        certificate = logs["auto"].get("certificate") or {}
        summary["auto"] = {
            **_savings(logs, "auto", full_name),
            "certified": certificate.get("certified"),
        }
    constant = {
        split_run(name)[1]: log["totals"]["final_val_error"]
        for name, log in logs.items()
        if split_run(name)[::2] == ("fixed", "") and not log["stopped"]
    }
    if k_full in constant and len(constant) > 1:
        summary["equal_accuracy_k"] = equal_accuracy_k(constant, k_full, ACCURACY_RATIO - 1)
    return summary


def _rtol_summary(log: dict) -> dict:
    """The ``rtol`` schedule of run `log`: first and last rtol, level, cap, and the mean
    forward iterations per solve in its first and last epoch (None without epochs)."""
    plan, epochs = log["rtol"], log["epochs"]
    first, last = (epochs[0], epochs[-1]) if epochs else ({}, {})

    def per_solve(epoch):
        return epoch["fwd_iterations"] / epoch["fwd_solves"] if epoch.get("fwd_solves") else None

    return {
        "init": plan["rtol_init"],
        "final": last.get("rtol"),
        "level": last.get("rtol_level"),
        **{key: plan[key] for key in ("levels", "max_it", "max_it_factor", "k_full")},
        "fwd_per_solve_first": per_solve(first),
        "fwd_per_solve_last": per_solve(last),
    }


def fastest(logs: dict, full_name: str) -> dict | None:
    """Which run reached full fidelity's accuracy (`accuracy_target` of `full_name`) in
    the least wall time, and each run's `time_to_accuracy`; None without `full_name`."""
    target = accuracy_target(logs, full_name)
    if target is None:
        return None
    times = {name: time_to_accuracy(log, target) for name, log in logs.items()}
    winner = _least(times)
    return {
        "target_val_error": target,
        "reference": full_name,
        "seconds_to_target": times,
        "winner": winner,
        "winner_seconds": times[winner] if winner else None,
    }


def _least(times: dict) -> str | None:
    """The name of the least time that is not None, or None."""
    reached = {name: t for name, t in times.items() if t is not None}
    return min(reached, key=reached.get) if reached else None


def split_run(name: str) -> tuple[str, int | None, str]:
    """``"fixed:8@cg/icc"`` → ``("fixed", 8, "cg/icc")``; ``"prdp"`` → ``("prdp", None, "")``."""
    schedule, _, route = name.partition("@")
    kind, _, k = schedule.partition(":")
    return (kind, int(k), route) if k.isdigit() else (schedule, None, route)


def is_full(name: str, k_fulls: dict) -> bool:
    """Whether run `name` is full fidelity (or its twin): K is its route's K_full
    (``k_fulls[""]``, the scene solver's, for a route `k_fulls` does not name)."""
    kind, k, route = split_run(name)
    return kind in ("fixed", TWIN) and k is not None and k == k_fulls.get(route, k_fulls.get(""))


def _kind(name: str, k_fulls: dict) -> str:
    """``"full"``, ``"twin"`` or ``"reduced"`` (PRDP, ``rtol``, a coarse constant K)."""
    if split_run(name)[0] == TWIN:
        return TWIN
    return "full" if is_full(name, k_fulls) else "reduced"


def speedup_vs_best_full(logs: dict, k_fulls: dict | int) -> dict:
    """How much sooner the fastest reduced run reached full-fidelity accuracy.

    The target is `accuracy_target` of ``fixed:K_full`` on the scene's own solver; the
    best full-fidelity time the least `time_to_accuracy` over full fidelity on every
    route, the best reduced time the least over PRDP, ``rtol`` and coarse constant Ks on
    any route.  A twin is neither.

    Returns
    -------
    dict
        ``speedup_vs_best_full``: best full time / best reduced time (above 1: the
        reduced run was faster), or None; ``speedup``: ``target_val_error``,
        ``reference``, ``full`` / ``full_seconds`` and ``reduced`` / ``reduced_seconds``
        (the fastest run of each kind and its time, None where none reached),
        ``solver_bound`` (`solver_bound` of the fastest full run), and where the
        speed-up is None, ``unavailable``: why, in words.
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    reference = f"fixed:{k_fulls['']}"
    target = accuracy_target(logs, reference)
    detail = {"target_val_error": target, "reference": reference}
    times = {"full": {}, "reduced": {}, TWIN: {}}
    for name, log in logs.items():
        if target is not None:
            times[_kind(name, k_fulls)][name] = time_to_accuracy(log, target)
    for kind in ("full", "reduced"):
        best = _least(times[kind])
        detail[kind], detail[f"{kind}_seconds"] = best, times[kind].get(best)
    if detail["full"] is not None:
        detail["solver_bound"] = solver_bound(logs[detail["full"]])
    stop = (logs.get(reference) or {}).get("stopped")
    why = None
    if target is None:
        why = f"{reference} (full fidelity, the target) did not run"
    elif stop:
        why = (
            f"{reference} (full fidelity, the target) stopped at epoch {stop['epoch']} "
            f"({stop['reason']}): no full-fidelity accuracy to reach"
        )
    elif detail["full"] is None:
        why = f"no full-fidelity run reached its own final validation error ({target:.4e})"
    elif not times["reduced"]:
        why = "no reduced run (PRDP, rtol, coarse K) ran"
    elif detail["reduced"] is None:
        why = (
            f"no reduced run ({', '.join(times['reduced'])}) reached full-fidelity accuracy: "
            f"validation error <= {ACCURACY_RATIO} x {reference}'s final, {target:.4e}, "
            "from some epoch on to the end"
        )
    if why:
        detail["unavailable"] = why
        return {"speedup_vs_best_full": None, "speedup": detail}
    ratio = _ratio(detail["full_seconds"], detail["reduced_seconds"])
    return {"speedup_vs_best_full": ratio, "speedup": detail}


def solver_bound(log: dict) -> float | None:
    """The most a cheaper solver can speed run `log` up at equal epochs: its wall time
    over its wall time outside the solver.

    Another schedule or route trains the same network on the same data, so only the
    solver's share of an epoch can shrink.  None without epochs or recorded solver
    times, or where the solver took all of the time.
    """
    epochs = log.get("epochs", [])
    if not epochs or any(e.get("solver_time") is None for e in epochs):
        return None
    wall = sum(e["wall_time"] for e in epochs)
    solver = sum(e["solver_time"] for e in epochs)
    return wall / (wall - solver) if wall > solver else None


def _savings(logs: dict, prdp_name: str, full_name: str) -> dict:
    """``savings``, ``val_error_ratio``, ``equal_accuracy`` (or ``savings_unavailable``)."""
    prdp, full = logs.get(prdp_name), logs.get(full_name)
    unavailable = _why_no_savings(prdp, full, prdp_name, full_name)
    if unavailable:
        return {"savings_unavailable": unavailable}

    def inner(log):
        return [e["fwd_iterations"] + e["adj_iterations"] for e in log["epochs"]]

    def wall(log):
        return [e["wall_time"] for e in log["epochs"]]

    by_iter = savings(costs=inner(prdp), cost_full=inner(full))
    by_time = savings(costs=wall(prdp), cost_full=wall(full))
    ratio = _ratio(prdp["totals"]["final_val_error"], full["totals"]["final_val_error"])
    summary = {
        "savings": {"iterations": by_iter["total"], "wall_time": by_time["total"],
                    "pr": by_iter["pr"], "ic": by_iter["ic"]},
        "val_error_ratio": ratio,
        "equal_accuracy": ratio <= ACCURACY_RATIO,
    }  # fmt: skip
    if not summary["equal_accuracy"]:
        summary["accuracy_warning"] = (
            f"val error ratio {ratio:.3g} > {ACCURACY_RATIO}: PRDP did not reach "
            "full-fidelity accuracy; savings are not at equal accuracy"
        )
    return summary


def _ratio(num: float, den: float) -> float:
    """``num / den`` for errors >= 0; 0 / 0 is 1, x / 0 is inf, NaN stays NaN (unequal)."""
    if den > 0 or math.isnan(den):
        return num / den
    return math.inf if num > 0 else 1.0


def _why_no_savings(prdp: dict | None, full: dict | None, prdp_name: str, full_name: str):
    """None if PRDP and K_full ran over the same epochs, else the reason in words."""
    reasons = []
    for name, log in ((prdp_name, prdp), (full_name, full)):
        if log is None:
            reasons.append(f"{name} did not run")
        elif log["stopped"]:
            stop = log["stopped"]
            reasons.append(f"{name} stopped at epoch {stop['epoch']} ({stop['reason']})")
    if not reasons and len(prdp["epochs"]) != len(full["epochs"]):
        reasons.append(
            f"{prdp_name} ran {len(prdp['epochs'])} epochs, {full_name} {len(full['epochs'])}"
        )
    if not reasons and not prdp["epochs"]:
        reasons.append("no epochs ran")
    if not reasons:
        return None
    return (
        f"no savings: {'; '.join(reasons)}; savings need {prdp_name} and {full_name} "
        "over the same epochs"
    )


def stopped_runs(summary: dict) -> list[str]:
    """Schedules of the summary whose run stopped early (diverged, invalid input, Ctrl-C)."""
    return [name for name, r in summary["runs"].items() if r["stopped"]]


def format_table(summary: dict) -> str:
    """Plain-text table of a comparison summary, then its savings, bounds and speed-up.

    Column ``reach s``: the run's ``time_to_full_accuracy`` (— where it never reached
    full-fidelity accuracy; a summary from before that key takes ``fastest``'s times).
    """
    reach = (summary.get("fastest") or {}).get("seconds_to_target", {})
    rows = []
    for name, r in summary["runs"].items():
        wall, solver, stop = r["wall_time"], r["solver_time"], r["stopped"]
        rows.append({
            "schedule": name,
            "val error": r["final_val_error"],
            "K final": r["k_final"],
            "inner its": (r["fwd_iterations"] or 0) + (r["adj_iterations"] or 0),
            "wall s": wall,
            "solver %": 100 * solver / wall if wall and solver is not None else None,
            "reach s": r.get("time_to_full_accuracy", reach.get(name)),
            "stopped": f"{stop['reason']} at epoch {stop['epoch']}" if stop else "no",
        })  # fmt: skip
    table = plain_table(rows, ("", ".4e", "", "", ".2f", ".1f", ".2f", ""))
    lines = [f"scene {summary['scene']}   K_full = {summary['k_full']}", table]
    lines += [_rtol_line(name, r["rtol"]) for name, r in summary["runs"].items() if "rtol" in r]
    if "pilot" in summary:
        lines.append(_pilot_line(summary["pilot"]))
    lines.append(_savings_line("PRDP vs K_full", summary))
    if summary.get("accuracy_warning"):
        lines.append(f"  !! {summary['accuracy_warning']}")
    if summary.get("auto"):
        verdict = {True: "certified", False: "NOT certified", None: "not checked"}
        lines.append(
            _savings_line("PRDP.for_problem (auto) vs K_full", summary["auto"],
                          f", {verdict[summary['auto']['certified']]}")
        )  # fmt: skip
    noise = summary.get("noise_ratio")
    if noise is not None:
        lines.append(
            f"full fidelity twice (twin:{summary['k_full']}: other initial weights "
            f"and batch order): val error ratio {noise:.3f}, the run-to-run noise"
        )
    bound = summary.get("equal_accuracy_k")
    if bound:
        fit = bound["fitted"] and (
            f", ≈ {bound['fitted']} fitting e_full + C ρ^K to fixed:{bound['pair'][0]}, "
            f"fixed:{bound['pair'][1]} (ρ = {bound['rho']:.3f})"
        )
        lines.append(
            f"smallest constant K within 5 % of K_full: {bound['measured']} of the runs"
            f"{fit or ''}; incomplete convergence alone saves at most "
            f"{100 * bound['ic_bound']:.0f} %"
        )
        if noise is not None and not 1 / ACCURACY_RATIO <= noise <= ACCURACY_RATIO:
            lines.append(
                f"  (the twin ends {noise:.3f}x full fidelity: below that noise the "
                "constant-K errors do not resolve a 5 % difference)"
            )
    for route, r in summary.get("routes", {}).items():
        if "skipped" in r:
            lines.append(f"{route}: skipped, it does not fit the scene's solver: {r['skipped']}")
        else:
            lines.append(_savings_line(f"PRDP vs K_full on {route} (K_full = {r['k_full']})", r))
    best = summary.get("fastest")
    if best:
        winner = best["winner"] and f"{best['winner']} in {best['winner_seconds']:.2f} s"
        lines.append(
            f"fastest to the full-fidelity validation error ({best['target_val_error']:.4e}, "
            f"within 5 % of {best['reference']}): {winner or 'no run reached it'}"
        )
    if "speedup" in summary:
        lines.append(_speedup_line(summary["speedup_vs_best_full"], summary["speedup"]))
    return "\n".join(lines)


def plain_table(rows: list[dict], floatfmt: tuple[str, ...]) -> str:
    """`rows` as a plain-text table (pandas' `DataFrame.to_markdown`): a column of numbers
    right-aligned in its `floatfmt` format, a missing value (None) as —."""
    import pandas as pd

    return pd.DataFrame(rows, dtype=object).to_markdown(
        index=False, tablefmt="plain", numalign="right", missingval="—", floatfmt=floatfmt
    )


def _savings_line(label: str, d: dict, note: str = "") -> str:
    """``label: x % fewer inner iterations ..., val error ratio r`` from `_savings`'s keys."""
    if "savings" not in d:
        return f"{label}: {d['savings_unavailable']}"
    s = d["savings"]
    cost = (
        f"{100 * s['iterations']:.1f} % fewer inner iterations "
        f"(PR {100 * s['pr']:.1f} %, IC {100 * s['ic']:.1f} %), "
        f"{100 * s['wall_time']:.1f} % less wall time"
    )
    ratio = f"val error ratio {d['val_error_ratio']:.3f}{note}"
    if d["equal_accuracy"]:
        return f"{label}: {cost}, {ratio}"
    return f"{label}: NOT at equal accuracy ({ratio}); it ran {cost}"


def _speedup_line(ratio: float | None, detail: dict) -> str:
    """The table's line for `speedup_vs_best_full`, and the solver-only bound."""
    if ratio is None:
        line = f"speedup vs best full fidelity: none, {detail['unavailable']}"
    else:
        line = (
            f"speedup vs best full fidelity: {ratio:.2f}x ({detail['full']} reached "
            f"full-fidelity accuracy, val error <= {detail['target_val_error']:.4e}, in "
            f"{detail['full_seconds']:.2f} s; {detail['reduced']} in "
            f"{detail['reduced_seconds']:.2f} s)"
        )
    bound = detail.get("solver_bound")
    if bound is not None:
        line += (
            f"\n  solver-only bound: {bound:.2f}x ({detail['full']}'s wall time over its time "
            "outside the solver: the most a cheaper solver gains in as many epochs)"
        )
    return line


def _pilot_line(pilot: dict) -> str:
    """The table's line for ``compare --routes auto``'s pilot: each candidate, the pick."""
    if not pilot["candidates"]:
        return "pilot: the preset declares no route to choose; the scene's solver ran alone"
    parts = [
        f"{name} skipped ({c['skipped']})"
        if "skipped" in c
        else f"{name} {c['epoch_seconds']:.2f} s (K_full {c['k_full']})"
        for name, c in pilot["candidates"].items()
    ]
    return (
        f"pilot ({pilot['epochs']} timed full-fidelity epoch each, after an untimed one): "
        f"{', '.join(parts)}; picked {pilot['picked']}"
    )


def _rtol_line(name: str, r: dict) -> str:
    """The table's line for an ``rtol`` run: tolerances, cap, iterations per solve."""
    first, last = r["fwd_per_solve_first"], r["fwd_per_solve_last"]
    its = "" if first is None else f"; forward iterations per solve {first:.1f} -> {last:.1f}"
    final = "—" if r["final"] is None else f"{r['final']:.0e} (level {r['level']} of {r['levels']})"
    return (
        f"{name}: PETSc's rtol test under max_it = {r['max_it']} "
        f"({r['max_it_factor']} x K_full {r['k_full']}), rtol {r['init']:.0e} -> {final}{its}"
    )
