"""The summary of a comparison and its table: savings, accuracy, time to accuracy.

`summarize` turns the per-run logs of `prdp_petsc.lab.training.compare.compare` into
``summary.json``: PRDP's savings against constant full fidelity (inner iterations
and wall time, split into progressive refinement and incomplete convergence), the
validation-error ratio that says whether they are at equal accuracy
(`ACCURACY_RATIO`), the smallest constant K that would have done
(`prdp_petsc.lab.training.accuracy.equal_accuracy_k`), every run's ``time_to_full_accuracy`` and
``speedup_vs_best_full`` (the fastest full-fidelity run's time over the fastest
reduced run's).  `format_table` prints it.
"""

from __future__ import annotations

import math

from prdp_petsc.prdp import ACCURACY_BAND, savings

from .accuracy import equal_accuracy_k
from .routes import REACH_FACTOR, accuracy_target, fastest, time_to_accuracy

__all__ = [
    "ACCURACY_RATIO",
    "TWIN",
    "format_table",
    "solver_bound",
    "speedup_vs_best_full",
    "stopped_runs",
    "summarize",
]

#: Largest PRDP / K_full ratio of final validation errors that still counts as equal accuracy.
ACCURACY_RATIO = 1.0 + ACCURACY_BAND
TWIN = "twin"  # compare's schedule name for the full-fidelity twin


def summarize(
    scene: str,
    k_full: int | dict,
    logs: dict,
    *,
    threads: int | None = None,
    skipped: dict | None = None,
) -> dict:
    """Summary of a comparison: runs, PRDP savings against K_full, error ratio.

    `k_full` is an int, or ``{route: K_full}`` with ``""`` for the scene's own
    solver; routes add ``routes`` (their K_full and PRDP savings) and ``fastest``.
    A run ``twin:K`` (full fidelity again, torch seeded differently) adds
    ``noise_ratio``, its final validation error over K_full's; it is not a
    candidate for ``fastest`` nor for the speedup.  `skipped` maps routes that do
    not fit the scene's solvers (a `StructureError`: CG on a non-symmetric
    operator) to the reason; they appear in ``routes`` as ``{"skipped": reason}``.
    A run whose results recorded ``rollout`` / ``uncorrected_rollout`` (per-step
    errors of the trained model, and of the solver alone) keeps them.  Every run
    gets ``time_to_full_accuracy``
    (`prdp_petsc.lab.training.routes.time_to_accuracy` against full fidelity's final
    validation error; None if it never reached it, or without full fidelity), and
    the summary ``speedup_vs_best_full`` and ``speedup`` (`speedup_vs_best_full`).
    """
    k_fulls = k_full if isinstance(k_full, dict) else {"": k_full}
    k_full = k_fulls[""]
    full_name = f"fixed:{k_full}"
    twin_name = f"twin:{k_full}"
    runs = {}
    for schedule, log in logs.items():
        t = log["totals"]
        runs[schedule] = {
            "final_val_error": t.get("final_val_error"),
            "best_val_error": t.get("best_val_error"),
            "wall_time": t.get("wall_time"),
            "solver_time": t.get("solver_time"),
            "fwd_iterations": t.get("fwd_iterations"),
            "adj_iterations": t.get("adj_iterations"),
            "k_final": t.get("k_final"),
            "epochs": t["epochs"],
            "stopped": log["stopped"],
        }
        if log.get("rtol"):  # the rtol schedule: where its tolerance ended, what it cost
            runs[schedule]["rtol"] = _rtol_summary(log)
        for key in ("rollout", "uncorrected_rollout"):  # per-step errors, when recorded
            if log.get(key) is not None:
                runs[schedule][key] = log[key]
    target = accuracy_target(logs, full_name)
    for name, r in runs.items():
        reached = None if target is None else time_to_accuracy(logs[name], target)
        r["time_to_full_accuracy"] = reached
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
        candidates = {name: log for name, log in logs.items() if name != twin_name}
        summary["fastest"] = fastest(candidates, full_name)
    summary.update(_savings(logs, "prdp", full_name))
    if "auto" in logs:  # the default construction beside the scene's tuned settings
        certificate = logs["auto"].get("certificate") or {}
        summary["auto"] = {
            **_savings(logs, "auto", full_name),
            "certified": certificate.get("certified"),
        }
    constant = {
        int(name[6:]): log["totals"]["final_val_error"]
        for name, log in logs.items()
        if name.startswith("fixed:") and name[6:].isdigit() and not log["stopped"]
    }
    if k_full in constant and len(constant) > 1:
        summary["equal_accuracy_k"] = equal_accuracy_k(constant, k_full, ACCURACY_RATIO - 1)
    return summary


def _rtol_summary(log: dict) -> dict:
    """The ``rtol`` schedule of run `log`: first and last rtol, level, cap, and the mean
    forward iterations per solve in its first and last epoch (None without epochs)."""
    plan, epochs = log["rtol"], log["epochs"]

    def per_solve(epoch):
        return epoch["fwd_iterations"] / epoch["fwd_solves"] if epoch["fwd_solves"] else None

    return {
        "init": plan["rtol_init"],
        "final": epochs[-1]["rtol"] if epochs else None,
        "level": epochs[-1]["rtol_level"] if epochs else None,
        "levels": plan["levels"],
        "max_it": plan["max_it"],
        "max_it_factor": plan["max_it_factor"],
        "k_full": plan["k_full"],
        "fwd_per_solve_first": per_solve(epochs[0]) if epochs else None,
        "fwd_per_solve_last": per_solve(epochs[-1]) if epochs else None,
    }


def _kind(name: str, k_fulls: dict) -> str:
    """``"full"`` (``fixed:K_full`` of its route), ``"twin"``, or ``"reduced"`` (PRDP,
    ``rtol``, a coarse constant K) for a run named ``schedule[@route]``."""
    schedule, _, route = name.partition("@")
    if schedule.startswith(f"{TWIN}:"):
        return TWIN
    fixed = schedule.startswith("fixed:") and schedule[6:].isdigit()
    if fixed and int(schedule[6:]) == k_fulls.get(route):
        return "full"
    return "reduced"


def speedup_vs_best_full(logs: dict, k_fulls: dict | int) -> dict:
    """How much sooner the fastest reduced run reached full-fidelity accuracy.

    The target is `accuracy_target` of the scene's own solver at K_full
    (``fixed:K_full``), each run's time `time_to_accuracy`.  The best full-fidelity
    time is the least over ``fixed:K_full`` and every route's ``fixed:K@route`` at
    its own K_full; the best reduced time the least over PRDP, the ``rtol`` schedule
    and coarse constant Ks on any route.  A twin is neither.

    Parameters
    ----------
    logs : dict
        ``{run name: log}`` as `run` returns them, named as `compare` names runs.
    k_fulls : dict or int
        ``{route: K_full}`` with ``""`` for the scene's own solver (or that one int).

    Returns
    -------
    dict
        ``speedup_vs_best_full``: best full time / best reduced time (above 1: the
        reduced run was faster), or None; ``speedup``: ``target_val_error``,
        ``reference`` (the full-fidelity run that sets the target), ``full`` and
        ``full_seconds`` (the fastest full-fidelity run and its time), ``reduced`` and
        ``reduced_seconds`` (likewise, None where none reached), ``solver_bound``
        (`solver_bound` of the fastest full-fidelity run), and, where the speedup is
        None, ``unavailable``: why, in words.
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    reference = f"fixed:{k_fulls['']}"
    target = accuracy_target(logs, reference)
    detail = {"target_val_error": target, "reference": reference}
    best = {}
    for kind in ("full", "reduced"):
        times = {
            name: time_to_accuracy(log, target)
            for name, log in logs.items()
            if _kind(name, k_fulls) == kind and target is not None
        }
        reached = {name: t for name, t in times.items() if t is not None}
        name = min(reached, key=reached.get) if reached else None
        detail[kind], detail[f"{kind}_seconds"] = name, reached.get(name)
        best[kind] = times
    if detail["full"] is not None:
        detail["solver_bound"] = solver_bound(logs[detail["full"]])
    why = None
    stop = (logs.get(reference) or {}).get("stopped")
    if target is None:
        why = f"{reference} (full fidelity, the target) did not run"
    elif stop:
        why = (
            f"{reference} (full fidelity, the target) stopped at epoch {stop['epoch']} "
            f"({stop['reason']}): no full-fidelity accuracy to reach"
        )
    elif detail["full"] is None:
        why = f"no full-fidelity run reached its own final validation error ({target:.4e})"
    elif not best["reduced"]:
        why = "no reduced run (PRDP, rtol, coarse K) ran"
    elif detail["reduced"] is None:
        why = (
            f"no reduced run ({', '.join(best['reduced'])}) reached full-fidelity accuracy: "
            f"validation error <= {REACH_FACTOR} x {reference}'s final, {target:.4e}, "
            "from some epoch on to the end"
        )
    if why:
        detail["unavailable"] = why
        return {"speedup_vs_best_full": None, "speedup": detail}
    ratio = _ratio(detail["full_seconds"], detail["reduced_seconds"])
    return {"speedup_vs_best_full": ratio, "speedup": detail}


def solver_bound(log: dict) -> float | None:
    """The most a cheaper solver can speed run `log` up at equal epochs: its wall time
    over its wall time outside the solver (forward and adjoint KSP solves).

    Another schedule or route trains the same network on the same data, so only the
    solver share of an epoch can shrink; a reduced run that reaches full-fidelity
    accuracy in as many epochs as the fastest full-fidelity run is at most this much
    faster (fewer epochs to the target is the only way past it).  None without
    epochs, without recorded solver times, or where the solver took all of the time.
    """
    epochs = log.get("epochs", [])
    if not epochs or any(e.get("solver_time") is None for e in epochs):
        return None  # a log from before solver times were recorded
    wall = sum(e["wall_time"] for e in epochs)
    solver = sum(e["solver_time"] for e in epochs)
    return wall / (wall - solver) if wall > solver else None


def _savings(logs: dict, prdp_name: str, full_name: str) -> dict:
    """``savings``, ``val_error_ratio``, ``equal_accuracy`` (or ``savings_unavailable``)."""
    prdp, full = logs.get(prdp_name), logs.get(full_name)
    unavailable = _why_no_savings(prdp, full, prdp_name, full_name)
    if unavailable:
        return {"savings_unavailable": unavailable}
    summary = {}
    inner = [e["fwd_iterations"] + e["adj_iterations"] for e in prdp["epochs"]]
    inner_full = [e["fwd_iterations"] + e["adj_iterations"] for e in full["epochs"]]
    by_iter = savings(costs=inner, cost_full=inner_full)
    by_time = savings(
        costs=[e["wall_time"] for e in prdp["epochs"]],
        cost_full=[e["wall_time"] for e in full["epochs"]],
    )
    summary["savings"] = {
        "iterations": by_iter["total"],
        "wall_time": by_time["total"],
        "pr": by_iter["pr"],
        "ic": by_iter["ic"],
    }
    ratio = _ratio(prdp["totals"]["final_val_error"], full["totals"]["final_val_error"])
    summary["val_error_ratio"] = ratio
    summary["equal_accuracy"] = ratio <= ACCURACY_RATIO
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
    if reasons:
        detail = "; ".join(reasons)
        return (
            f"no savings: {detail}; savings need {prdp_name} and {full_name} over the same epochs"
        )
    return None


def stopped_runs(summary: dict) -> list[str]:
    """Schedules of the summary whose run stopped early (diverged, invalid input, Ctrl-C)."""
    return [name for name, r in summary["runs"].items() if r["stopped"]]


def format_table(summary: dict) -> str:
    """Plain-text table of a comparison summary, with its savings line and warnings.

    Column ``reach s``: the run's ``time_to_full_accuracy`` (— where it never
    reached full-fidelity accuracy); the line ``speedup vs best full fidelity`` gives
    ``speedup_vs_best_full`` with the two runs it compares, or why there is none.
    """

    def cell(value, width: int, spec: str = "") -> str:
        return ("—" if value is None else format(value, spec)).rjust(width)

    width = max([12, *(len(name) + 2 for name in summary["runs"])])
    # summaries written before time_to_full_accuracy existed keep their old table
    reach = any("time_to_full_accuracy" in r for r in summary["runs"].values())
    lines = [
        f"scene {summary['scene']}   K_full = {summary['k_full']}",
        f"{'schedule':<{width}}{'val error':>12}{'K final':>9}{'inner its':>12}{'wall s':>9}"
        f"{'solver %':>10}" + (f"{'reach s':>9}" if reach else "") + "  stopped",
    ]
    for name, r in summary["runs"].items():
        its = (r["fwd_iterations"] or 0) + (r["adj_iterations"] or 0)
        stop = r["stopped"]
        share = (
            100 * r["solver_time"] / r["wall_time"]
            if r["wall_time"] and r["solver_time"] is not None
            else None
        )
        lines.append(
            f"{name:<{width}}{cell(r['final_val_error'], 12, '.4e')}{cell(r['k_final'], 9)}"
            f"{its:>12}{cell(r['wall_time'], 9, '.2f')}{cell(share, 10, '.1f')}"
            + (cell(r.get("time_to_full_accuracy"), 9, ".2f") if reach else "")
            + "  "
            + (f"{stop['reason']} at epoch {stop['epoch']}" if stop else "no")
        )
    for name, r in summary["runs"].items():
        if "rtol" in r:
            lines.append(_rtol_line(name, r["rtol"]))
    if "pilot" in summary:
        lines.append(_pilot_line(summary["pilot"]))
    if "savings" in summary:
        s = summary["savings"]
        cost = (
            f"{100 * s['iterations']:.1f} % fewer inner iterations "
            f"(PR {100 * s['pr']:.1f} %, IC {100 * s['ic']:.1f} %), "
            f"{100 * s['wall_time']:.1f} % less wall time"
        )
        ratio = f"val error ratio {summary['val_error_ratio']:.3f}"
        if summary["equal_accuracy"]:
            lines.append(f"PRDP vs K_full: {cost}, {ratio}")
        else:  # not a saving: PRDP did not reach full fidelity's accuracy
            lines.append(f"PRDP vs K_full: NOT at equal accuracy ({ratio}); it ran {cost}")
            lines.append(f"  !! {summary['accuracy_warning']}")
    else:
        lines.append(f"PRDP vs K_full: {summary['savings_unavailable']}")
    auto = summary.get("auto")
    if auto:
        lines.append(_auto_line(auto))
    if "noise_ratio" in summary:
        lines.append(
            f"full fidelity twice (twin:{summary['k_full']}: other initial weights "
            f"and batch order): val error ratio {summary['noise_ratio']:.3f}, the run-to-run noise"
        )
    bound = summary.get("equal_accuracy_k")
    if bound:
        fit = bound["fitted"]
        lines.append(
            f"smallest constant K within 5 % of K_full: {bound['measured']} of the runs"
            + (
                f", ≈ {fit} fitting e_full + C ρ^K to fixed:{bound['pair'][0]}, "
                f"fixed:{bound['pair'][1]} (ρ = {bound['rho']:.3f})"
                if fit
                else ""
            )
            + f"; incomplete convergence alone saves at most {100 * bound['ic_bound']:.0f} %"
        )
        noise = summary.get("noise_ratio")
        if noise is not None and not 1 / ACCURACY_RATIO <= noise <= ACCURACY_RATIO:
            lines.append(
                f"  (the twin ends {noise:.3f}x full fidelity: below that noise the "
                "constant-K errors do not resolve a 5 % difference)"
            )
    for route, r in summary.get("routes", {}).items():
        if "skipped" in r:
            lines.append(f"{route}: skipped, it does not fit the scene's solver: {r['skipped']}")
        elif "savings" in r:
            lines.append(
                f"PRDP vs K_full on {route} (K_full = {r['k_full']}): "
                + ("" if r["equal_accuracy"] else "NOT at equal accuracy: ")
                + f"{100 * r['savings']['iterations']:.1f} % fewer inner iterations, "
                f"{100 * r['savings']['wall_time']:.1f} % less wall time, "
                f"val error ratio {r['val_error_ratio']:.3f}"
            )
        else:
            lines.append(f"PRDP vs K_full on {route}: {r['savings_unavailable']}")
    best = summary.get("fastest")
    if best:
        lines.append(
            f"fastest to the full-fidelity validation error ({best['target_val_error']:.4e}, "
            f"within 5 % of {best['reference']}): "
            + (
                f"{best['winner']} in {best['winner_seconds']:.2f} s"
                if best["winner"]
                else "no run reached it"
            )
        )
        if not reach:  # an older summary: the times per run, as the column would give them
            main = ["prdp", f"fixed:{summary['k_full']}"] + [
                name
                for route, r in summary.get("routes", {}).items()
                if "skipped" not in r
                for name in (f"prdp@{route}", f"fixed:{r['k_full']}@{route}")
            ]
            for name in main:
                if name in best["seconds_to_target"]:
                    t = best["seconds_to_target"][name]
                    lines.append(f"  {name}: " + ("not reached" if t is None else f"{t:.2f} s"))
    if "speedup" in summary:
        lines.append(_speedup_line(summary["speedup_vs_best_full"], summary["speedup"]))
    return "\n".join(lines)


def _speedup_line(ratio: float | None, detail: dict) -> str:
    """The table's line for `speedup_vs_best_full`."""
    bound = detail.get("solver_bound")
    tail = (
        f"\n  solver-only bound: {bound:.2f}x ({detail['full']}'s wall time over its time "
        "outside the solver: the most a cheaper solver gains in as many epochs)"
        if bound is not None
        else ""
    )
    if ratio is None:
        return f"speedup vs best full fidelity: none, {detail['unavailable']}" + tail
    return (
        f"speedup vs best full fidelity: {ratio:.2f}x ({detail['full']} reached full-fidelity "
        f"accuracy, val error <= {detail['target_val_error']:.4e}, in "
        f"{detail['full_seconds']:.2f} s; {detail['reduced']} in {detail['reduced_seconds']:.2f} s)"
        + tail
    )


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


def _auto_line(auto: dict) -> str:
    """The ``auto`` schedule (`PRDP.for_problem`) against K_full, with its certificate."""
    if "savings" not in auto:
        return f"PRDP.for_problem (auto) vs K_full: {auto['savings_unavailable']}"
    s = auto["savings"]
    cost = (
        f"{100 * s['iterations']:.1f} % fewer inner iterations, "
        f"{100 * s['wall_time']:.1f} % less wall time"
    )
    verdict = {True: "certified", False: "NOT certified", None: "not checked"}[auto["certified"]]
    ratio = f"val error ratio {auto['val_error_ratio']:.3f}, {verdict}"
    if auto["equal_accuracy"]:
        return f"PRDP.for_problem (auto) vs K_full: {cost}, {ratio}"
    return f"PRDP.for_problem (auto) vs K_full: NOT at equal accuracy ({ratio}); it ran {cost}"
