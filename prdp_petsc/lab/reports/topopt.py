"""The table and headline of a topology-optimisation comparison (``topopt.json``).

``demos/topopt3d.py results`` writes ``topopt.json``: per load case, each route
(converged solves, constant K, PRDP's default construction with its gradient check,
the ``rtol`` schedule) with the compliance of its final design scored by a converged
solve, its inner iterations (forward + adjoint, checks included), wall time and the
time at which its design first came within 1 % of the converged route's final
compliance.  This module formats it for the command's output and the results page.
"""

from __future__ import annotations

__all__ = ["TARGET_RATIO", "TARGET_SAVED", "format_results", "spread", "target_met"]

#: the issue's target: PRDP's design within 1 % of the converged design's compliance ...
TARGET_RATIO = 1.01
#: ... at this many fewer inner iterations
TARGET_SAVED = 0.5


def format_results(data: dict) -> str:
    """One line per load case and route."""
    lines = [
        f"{'case':>4} {'z_c':>4} {'route':<12} {'C final':>10} {'C/C_conv':>8} {'inner its':>9} "
        f"{'saved':>6} {'wall s':>7} {'t→1% s':>7} {'K final':>7}"
    ]
    for case in data["cases"]:
        for label, r in case["routes"].items():
            head = f"{case['seed']:>4} {case['load_height']:>4} {label:<12}"
            if "compliance" not in r:
                lines.append(f"{head} stopped at epoch {r['stopped']['epoch']}: "
                             f"{r['stopped']['reason']}")  # fmt: skip
                continue
            t = "—" if r["time_to_1pct"] is None else f"{r['time_to_1pct']:.2f}"
            k_final = "conv" if label == "converged" else str(r["ks"][-1])
            lines.append(
                f"{head} {r['compliance']:>10.5g} {r['ratio']:>8.4f} {r['iterations']:>9d} "
                f"{100 * r['saved']:>5.1f}% {r['wall_time']:>7.2f} {t:>7} {k_final:>7}"
            )
    return "\n".join(lines)


def target_met(data: dict, route: str = "PRDP (auto)") -> list[bool]:
    """Per load case: `route`'s design within `TARGET_RATIO` of the converged design's
    compliance at ≥ `TARGET_SAVED` fewer inner iterations."""
    met = []
    for case in data["cases"]:
        r = case["routes"].get(route, {})
        met.append("ratio" in r and r["ratio"] <= TARGET_RATIO and r["saved"] >= TARGET_SAVED)
    return met


def spread(data: dict) -> str | None:
    """A sentence on routes whose design beat the converged one by more than the target,
    read off the data (None where none did): SIMP is not convex, so a route's path
    decides which local optimum its design ends in."""
    better = [
        (case["seed"], label, r["ratio"])
        for case in data["cases"]
        for label, r in case["routes"].items()
        if label != "converged" and "ratio" in r and r["ratio"] < 2 - TARGET_RATIO
    ]
    if not better:
        return None
    worst = max(
        (r["ratio"], case["seed"], label)
        for case in data["cases"]
        for label, r in case["routes"].items()
        if label != "converged" and "ratio" in r
    )
    listed = ", ".join(f"{label} on case {seed} ({ratio:.3f})" for seed, label, ratio in better)
    return (
        f"Some routes ended *better* than the converged one by more than the target: "
        f"{listed}; the largest ratio is {worst[0]:.3f} ({worst[2]} on case {worst[1]}). "
        "Compliance minimisation under a volume constraint is not convex: routes that take "
        "other steps early (capped solves, another K) end in other local optima, so the "
        "1 % target compares designs whose spread is the problem's, not only the solver's."
    )
