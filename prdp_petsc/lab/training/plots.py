"""Plots of a comparison: validation error against wall time and inner iterations, K,
and the per-step error of each trained model over a long rollout.

Colour and marker name the schedule (PRDP red circles, full fidelity blue squares, its
twin grey diamonds, each coarser constant K its own, in order of K); line style and
hollow markers name a solver route other than the scene's own.  An axis whose positive
data span more than a decade is logarithmic.  The legend says each run in words
(`run_label`) and stands beside the axes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .summary import is_full, split_run

__all__ = ["compare_figures", "plot_compare", "run_label", "run_styles"]

_PRDP, _FULL, _TWIN = ("C3", "o"), ("C0", "s"), ("C7", "D")
_COLOURS = ["C1", "C2", "C4", "C5", "C6", "C8", "C9"]  # coarser K, in order of K
_MARKERS = ["^", "v", "P", "X", "<", ">", "h"]
_LINESTYLES = ["-", "--", ":", "-."]


def run_label(
    name: str, k_fulls: dict | int | None = None, *, route_name: str | None = None
) -> str:
    """What a legend calls run `name` (``schedule[@route]``, as `compare` names runs).

    `k_fulls` is ``{route: K_full}`` with ``""`` for the scene's own solver (or one
    int): a K equal to its route's K_full reads "(full)".  `route_name` replaces the
    route in `name` (nothing for the scene's own solver).

    Examples
    --------
    >>> run_label("fixed:8@cg/icc", {"": 52, "cg/icc": 8})
    'K = 8 (full), cg/icc'
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    kind, k, route = split_run(name)
    if kind == "prdp":
        label = "PRDP"
    elif kind in ("fixed", "twin") and k is not None:
        label = f"K = {k}" + (" (full)" if is_full(name, k_fulls) else "")
        label += ", second seed" if kind == "twin" else ""
    else:
        label = kind
    route_name = route if route_name is None else route_name
    return f"{label}, {route_name}" if route_name else label


def run_styles(
    names, k_fulls: dict | int | None = None, *, route_names: dict | None = None
) -> dict[str, dict]:
    """Matplotlib line keywords and label for each run of one figure.

    `route_names` maps a route to words for the legend (``{"": "richardson/jacobi"}``):
    with several routes in the figure, the scene's own runs name theirs, or "scene's
    solver".  Returns ``{name: keywords}`` in legend order: by route (the scene's own
    first), then PRDP, full fidelity, its twin, coarser K from the largest.
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    names = list(dict.fromkeys(names))
    routes = sorted({split_run(n)[2] for n in names}, key=lambda r: (r != "", r))
    words = {"": "scene's solver", **(route_names or {})} if len(routes) > 1 else {}

    def role(name):  # PRDP, full fidelity, its twin, coarser K
        kind = split_run(name)[0]
        if kind == "prdp":
            return 0
        return (1 if kind == "fixed" else 2) if is_full(name, k_fulls) else 3

    coarse = sorted(
        {split_run(n)[:2] for n in names if role(n) == 3},
        key=lambda kk: (kk[1] is None, kk[1] or 0, kk[0]),
    )

    def rank(name):
        _, k, route = split_run(name)
        return routes.index(route), role(name), -(k or 0), name

    styles = {}
    for name in sorted(names, key=rank):
        kind, _, route = split_run(name)
        if role(name) < 3:
            colour, marker = (_PRDP, _FULL, _TWIN)[role(name)]
        else:
            i = coarse.index(split_run(name)[:2])
            colour, marker = _COLOURS[i % len(_COLOURS)], _MARKERS[i % len(_MARKERS)]
        styles[name] = {
            "color": colour,
            "marker": marker,
            "linestyle": _LINESTYLES[routes.index(route) % len(_LINESTYLES)],
            "markerfacecolor": colour if route == "" else "none",
            "linewidth": 2.2 if kind == "prdp" else 1.4,
            "zorder": 3 if kind == "prdp" else 2,
            "label": run_label(name, k_fulls, route_name=route or words.get("")),
        }
    return styles


def _log_scale(ax, which: str) -> None:
    """Make the ``"x"`` or ``"y"`` axis of `ax` logarithmic, with plain tick labels
    (0.02, 0.3, never 2×10⁻²)."""
    from matplotlib.ticker import LogFormatter

    (ax.set_xscale if which == "x" else ax.set_yscale)("log")
    axis = ax.xaxis if which == "x" else ax.yaxis
    axis.set_major_formatter(LogFormatter())
    axis.set_minor_formatter(LogFormatter())


def _route_names(logs: dict) -> dict:
    """``{"": "ksp/pc"}``: the KSP/PC the scene's own runs used, from their logs."""
    seen = [
        f"{fwd['ksp_type']}/{fwd['pc_type']}"
        for name, log in logs.items()
        if "@" not in name
        for fwd in ((s.get("forward") or {}) for s in log.get("solvers") or [])
        if fwd.get("ksp_type") and fwd.get("pc_type")
    ]
    return {"": " + ".join(dict.fromkeys(seen))} if seen else {}


def _stopped(log: dict) -> str:
    """`` (stopped: NaN or Inf)`` for a run that stopped early, else ``""``."""
    stopped = log.get("stopped")
    if not stopped:
        return ""
    reason = str(stopped.get("reason", ""))
    reason = "NaN or Inf" if reason == "NON_FINITE" else reason.lower().replace("_", " ")
    return " (stopped" + (f": {reason}" if reason else "") + ")"


def _title(logs: dict) -> str:
    """``"heat2d, preset quick, seed 0"`` as far as every run agrees on them."""
    parts = []
    for key, fmt in (("scene", "{}"), ("preset", "preset {}"), ("seed", "seed {}")):
        values = {log.get(key) for log in logs.values()}
        if len(values) == 1 and None not in values:
            parts.append(fmt.format(values.pop()))
    return ", ".join(parts)


def compare_figures(logs: dict, k_full: int | dict) -> dict:
    """The figures of `plot_compare`, unsaved: ``{file name: matplotlib Figure}``.

    Runs without a completed epoch are left out; ``rollout.png`` only when a run
    recorded a rollout.
    """
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    curves = {}
    for name, log in logs.items():
        ep = log["epochs"]
        if ep:
            rollout = log.get("rollout")
            curves[name] = {
                "time": np.cumsum([e["wall_time"] for e in ep]),
                "iters": np.cumsum([e["fwd_iterations"] + e["adj_iterations"] for e in ep]),
                "val": np.array([e["val_metric"] for e in ep], dtype=float),
                "k": np.array([e["k"] for e in ep], dtype=float),
                "epoch": np.arange(1, len(ep) + 1),
                "rollout": np.asarray(rollout, dtype=float) if rollout else None,
                "step": np.arange(1, len(rollout) + 1) if rollout else None,
            }
    k_fulls = k_full if isinstance(k_full, dict) else {"": k_full}
    style = run_styles(curves, k_fulls, route_names=_route_names(logs))

    def figure(x: str, y: str, xlabel: str, ylabel: str, *, counts=False, steps=False):
        drawn = [n for n in style if curves[n][y] is not None]
        fig = Figure(figsize=(8.0, 4.2), layout="constrained")
        ax = fig.add_subplot()
        for name in drawn:
            c = curves[name]
            label = style[name]["label"] + _stopped(logs[name])
            ax.plot(c[x], c[y], **{**style[name], "label": label},
                    markevery=max(1, len(c[x]) // 8),
                    drawstyle="steps-mid" if steps else "default")  # fmt: skip
        for axis, key in (("x", x), ("y", y)):
            values = np.concatenate([curves[n][key] for n in drawn] or [np.empty(0)])
            values = values[np.isfinite(values)]
            if not (counts and axis == "x") and values.size and values.min() > 0:
                if values.max() / values.min() > 10:  # more than a decade
                    _log_scale(ax, axis)
        if counts:  # epochs and rollout steps
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set(xlabel=xlabel, ylabel=ylabel, title=_title(logs))
        ax.grid(True, alpha=0.35)
        fig.legend(loc="outside right upper", fontsize=8, frameon=False)
        return fig

    figures = {
        "error_vs_time.png": figure("time", "val", "cumulative wall time [s]", "validation error"),
        "error_vs_iterations.png": figure(
            "iters", "val", "cumulative inner iterations (forward + adjoint)", "validation error"
        ),
        "k_schedule.png": figure(
            "epoch", "k", "epoch", "K (KSP max_it per solve)", counts=True, steps=True
        ),
    }
    if any(c["rollout"] is not None for c in curves.values()):
        figures["rollout.png"] = figure(
            "step", "rollout", "rollout step", "normalised error (trained model)", counts=True
        )
    return figures


def plot_compare(logs: dict, k_full: int | dict, out: Path) -> list[str]:
    """Write ``error_vs_time.png``, ``error_vs_iterations.png``, ``k_schedule.png`` and,
    when the runs recorded one, ``rollout.png`` into `out`; return the file names.

    `logs` maps run names (``schedule[@route]``) to `run` results; `k_full` is an int,
    or ``{route: K_full}`` with ``""`` for the scene's own solver.
    """
    files = []
    for fname, fig in compare_figures(logs, k_full).items():
        fig.savefig(Path(out) / fname, dpi=120)
        files.append(fname)
    return files
