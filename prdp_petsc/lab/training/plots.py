"""Plots of a comparison: validation error against wall time and inner iterations, K,
and the per-step error of each trained model over a long rollout.

The figures follow a few written-down rules, so that one reads like the next.

Axis scale and limits (`scale_axis`)
    An axis of errors, costs or K is logarithmic when its finite data span more than a
    decade (largest / smallest > `LOG_SPAN`, 10) and linear otherwise: a curve
    between 0.45 and 0.8 fills the height instead of a fifth of a decade.  Data that
    are not all positive are drawn linear.  The limits are the smallest and largest
    finite value of the curves drawn, widened by `MARGIN` (5 %) of that span, of its
    logarithm on a log axis; no fixed factor.  A run that blows up therefore widens
    the axis (and usually turns it logarithmic) rather than leaving the plot: the
    figure shows what was measured.  Epochs and rollout steps are counts: linear, with
    integer ticks.
Tick labels
    Plain numbers (0.9, 1, 1.07, 2000), never "1.07×10⁰", on log axes too: ticks at
    1, 2, 5 of each decade over one to three decades, at the decades beyond, at 1, 1.5,
    2, 3, 5, 7 over half a decade to one, and at evenly spaced round numbers with alike
    decimals (0.95, 1.00, 1.05) over less (`seeds.png` draws its ratios on a log axis
    that is often that short).
Line styles (`run_styles`)
    Colour and marker name the schedule: PRDP red circles, full fidelity (K = K_full)
    blue squares, its twin (a second seed) grey diamonds, each coarser constant K its
    own colour and marker, in order of K.  Linestyle and marker fill name the solver
    route: the scene's own solid with filled markers, each other route hollow markers
    and dashed, dotted, dash-dot, ... in order of route name.  PRDP is drawn thicker
    and on top; where a curve has many points, about eight carry markers, staggered
    from run to run so that curves lying on each other still show each marker.  No
    two runs of one figure share a (colour, linestyle, marker); with more runs than
    the palettes hold, later ones take the next free combination.
Legend (`run_label`)
    In words: ``"PRDP"``, ``"K = 52 (full)"``, ``"K = 13"``, ``"PRDP, cg/icc"``,
    ``"K = 8 (full), cg/icc"``; with other routes in the figure the scene's own runs
    name their KSP/PC too.  A run that stopped early says so.  The legend stands beside
    the axes, never over a curve, grouped by route (PRDP, full, then coarser K).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import (
    FuncFormatter,
    LogLocator,
    MaxNLocator,
    NullFormatter,
    NullLocator,
    ScalarFormatter,
)

__all__ = [
    "LOG_SPAN",
    "MARGIN",
    "compare_figures",
    "plain_number",
    "plot_compare",
    "run_label",
    "run_styles",
    "scale_axis",
]

#: An axis is logarithmic when its data span more than this ratio (largest / smallest).
LOG_SPAN = 10.0
#: Fraction of the data's span (of its log10 on a log axis) added beyond each limit.
MARGIN = 0.05

_PRDP = ("C3", "o")
_FULL = ("C0", "s")
_TWIN = ("C7", "D")
_COLOURS = ["C1", "C2", "C4", "C5", "C6", "C8", "C9"]  # coarser K, in order of K
_MARKERS = ["^", "v", "P", "X", "<", ">", "h"]
_LINESTYLES = ["-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)), (0, (1, 3)), (0, (8, 3))]
_SIZE = (8.0, 4.2)  # inches; 960 x 504 pixels at `_DPI`
_DPI = 120


class _PositiveMaxN(MaxNLocator):
    """Evenly spaced round ticks, the positive ones only (for a log axis under a decade)."""

    def tick_values(self, vmin, vmax):
        ticks = super().tick_values(vmin, vmax)
        return ticks[ticks > 0]


def _split(name: str) -> tuple[str, int | None, str]:
    """``"fixed:8@cg/icc"`` → ``("fixed", 8, "cg/icc")``; ``"prdp"`` → ``("prdp", None, "")``."""
    schedule, _, route = name.partition("@")
    kind, _, k = schedule.partition(":")
    try:
        return kind, int(k), route
    except ValueError:
        return schedule, None, route


def _is_full(kind: str, k: int | None, route: str, k_fulls: dict) -> bool:
    return kind in ("fixed", "twin") and k is not None and k == k_fulls.get(route, k_fulls.get(""))


def run_label(
    name: str, k_fulls: dict | int | None = None, *, route_name: str | None = None
) -> str:
    """What a legend calls run `name` (``schedule[@route]``, as `compare` names runs).

    Parameters
    ----------
    name : str
        ``"prdp"``, ``"fixed:K"``, ``"twin:K"`` (full fidelity, a second torch seed),
        each optionally ``@ksp/pc``.
    k_fulls : dict or int, optional
        ``{route: K_full}`` with ``""`` for the scene's own solver (or one int): a K
        equal to its route's K_full reads "(full)".
    route_name : str, optional
        What to call the route: by default the one in `name`, nothing for the scene's
        own solver.

    Examples
    --------
    >>> run_label("fixed:8@cg/icc", {"": 52, "cg/icc": 8})
    'K = 8 (full), cg/icc'
    >>> run_label("prdp@cg/icc")
    'PRDP, cg/icc'
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    kind, k, route = _split(name)
    if kind == "prdp":
        label = "PRDP"
    elif kind in ("fixed", "twin") and k is not None:
        label = f"K = {k}" + (" (full)" if _is_full(kind, k, route, k_fulls) else "")
        if kind == "twin":
            label += ", second seed"
    else:
        label = kind
    route_name = route if route_name is None else route_name
    return f"{label}, {route_name}" if route_name else label


def run_styles(
    names, k_fulls: dict | int | None = None, *, route_names: dict | None = None
) -> dict[str, dict]:
    """Matplotlib line keywords for each run of one figure; no two runs share a style.

    Parameters
    ----------
    names : iterable of str
        Run names ``schedule[@route]`` (`run_label`).
    k_fulls : dict or int, optional
        ``{route: K_full}`` (``""``: the scene's own solver) or one int.
    route_names : dict, optional
        ``{route: words}`` for the legend, e.g. ``{"": "richardson/jacobi"}``.  When the
        figure holds more than one route, runs on the scene's own solver are labelled
        with ``route_names[""]``, or "scene's solver" without one.

    Returns
    -------
    dict
        ``{name: {"color", "linestyle", "marker", "markerfacecolor", "linewidth",
        "markersize", "zorder", "label"}}``, in the order a legend should list them:
        by route (the scene's own first, then by name), then PRDP, full fidelity, its
        twin, coarser K from the largest.  The same names give the same styles in any
        order.
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    names = list(dict.fromkeys(names))
    routes = list(dict.fromkeys(_split(n)[2] for n in names))
    routes.sort(key=lambda r: (r != "", r))  # the scene's own first, then by name
    multi = len(routes) > 1
    words = {"": "scene's solver", **(route_names or {})}

    def rank(name):
        kind, k, route = _split(name)
        full = _is_full(kind, k, route, k_fulls)
        group = 0 if kind == "prdp" else 1 if full and kind == "fixed" else 2 if full else 3
        return routes.index(route), group, -(k or 0), name

    coarse = sorted(
        {
            (k, kind)
            for kind, k, route in map(_split, names)
            if kind != "prdp" and not _is_full(kind, k, route, k_fulls)
        },
        key=lambda kk: (kk[0] is None, kk[0] or 0, kk[1]),
    )
    styles, used = {}, set()
    for name in sorted(names, key=rank):
        kind, k, route = _split(name)
        if kind == "prdp":
            colour, marker = _PRDP
        elif _is_full(kind, k, route, k_fulls):
            colour, marker = _FULL if kind == "fixed" else _TWIN
        else:
            i = coarse.index((k, kind))
            colour, marker = _COLOURS[i % len(_COLOURS)], _MARKERS[i % len(_MARKERS)]
        ls = _LINESTYLES[routes.index(route) % len(_LINESTYLES)]
        key = (colour, str(ls), marker)
        if key in used:  # more runs than the palettes hold: the next free combination
            for colour, ls, marker in itertools.product(_COLOURS, _LINESTYLES, _MARKERS):
                key = (colour, str(ls), marker)
                if key not in used:
                    break
        used.add(key)
        prdp = kind == "prdp"
        styles[name] = {
            "color": colour,
            "linestyle": ls,
            "marker": marker,
            "markerfacecolor": colour if route == "" else "none",
            "linewidth": 2.2 if prdp else 1.4,
            "markersize": 5.5 if prdp else 4.5,
            "zorder": 3 if prdp else 2,
            "label": run_label(
                name, k_fulls, route_name=(route or words[""]) if multi else route or None
            ),
        }
    return styles


def plain_number(value: float, pos=None) -> str:
    """A tick label without a power of ten: 0.5, 1, 1.07, 20000 (``1e-05`` beyond).

    Four significant digits at most, trailing zeros dropped; `pos` is matplotlib's
    tick position, unused.
    """
    if value == 0 or not math.isfinite(value):
        return "0" if value == 0 else str(value)
    if 1e-4 <= abs(value) < 1e7:
        return np.format_float_positional(value, precision=4, fractional=False, trim="-")
    return f"{value:.3g}"


def scale_axis(ax, which: str, values, *, log: bool | None = None, integer: bool = False) -> bool:
    """Scale, limit and label the ``"x"`` or ``"y"`` axis of `ax` to `values`.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    which : {"x", "y"}
    values : iterable of array_like
        Everything drawn along that axis (curves, reference lines); NaN and Inf are
        ignored.
    log : bool, optional
        Force a scale; by default logarithmic when the finite values are all positive
        and span more than `LOG_SPAN`.
    integer : bool
        Ticks at integers only (epochs, steps, K on a linear axis).

    Returns
    -------
    bool
        Whether the axis is logarithmic.  Without any finite value the axis is left
        as matplotlib made it.
    """
    arrays = [np.asarray(v, dtype=float).ravel() for v in values]
    data = np.concatenate(arrays) if arrays else np.empty(0)
    data = data[np.isfinite(data)]
    axis = ax.xaxis if which == "x" else ax.yaxis
    set_scale, set_lim = (
        (ax.set_xscale, ax.set_xlim) if which == "x" else (ax.set_yscale, ax.set_ylim)
    )
    if data.size == 0:
        return False
    lo, hi = float(data.min()), float(data.max())
    if log is None:
        log = lo > 0 and hi / lo > LOG_SPAN
    elif log and lo <= 0:
        raise ValueError(f"a log {which} axis needs positive values, got {lo}")
    if log:
        a, b = math.log10(lo), math.log10(hi)
        pad = MARGIN * (b - a) if b > a else 0.02  # one value: about ±5 % of it
        a, b = a - pad, b + pad
        set_scale("log")
        set_lim(10**a, 10**b)
        if b - a < 0.5:  # nearly linear: round numbers, evenly spaced, alike decimals
            axis.set_major_locator(_PositiveMaxN(nbins=6, steps=[1, 2, 2.5, 5, 10]))
            axis.set_major_formatter(_fixed())
            axis.set_minor_locator(NullLocator())
        else:  # 0.05, 0.1, 0.2: as few decimals as each needs
            subs = (1, 1.5, 2, 3, 5, 7) if b - a < 1 else (1, 2, 5) if b - a <= 3 else (1,)
            axis.set_major_locator(LogLocator(base=10, subs=subs, numticks=12))
            axis.set_major_formatter(FuncFormatter(plain_number))
            axis.set_minor_locator(LogLocator(base=10, subs=np.arange(2, 10), numticks=12))
        axis.set_minor_formatter(NullFormatter())
        return True
    pad = MARGIN * (hi - lo) if hi > lo else (0.05 * abs(hi) or 0.5)
    set_scale("linear")
    set_lim(lo - pad, hi + pad)
    axis.set_major_locator(MaxNLocator(nbins="auto", integer=integer, steps=[1, 2, 2.5, 5, 10]))
    axis.set_major_formatter(_fixed())
    return False


def _fixed() -> ScalarFormatter:
    """Plain numbers with the decimals the tick spacing needs (0.90, 0.95, 1.00)."""
    formatter = ScalarFormatter(useOffset=False)
    formatter.set_scientific(False)
    return formatter


def _route_names(logs: dict) -> dict:
    """``{"": "ksp/pc"}``: the KSP/PC the scene's own runs used, from their logs."""
    seen = []
    for name, log in logs.items():
        if "@" in name:
            continue
        for solver in log.get("solvers") or []:
            fwd = solver.get("forward") or {}
            if fwd.get("ksp_type") and fwd.get("pc_type"):
                seen.append(f"{fwd['ksp_type']}/{fwd['pc_type']}")
    seen = list(dict.fromkeys(seen))
    return {"": " + ".join(seen)} if seen else {}


def _stopped(log: dict) -> str:
    stopped = log.get("stopped")
    if not stopped:
        return ""
    reason = str(stopped.get("reason", ""))
    reason = "NaN or Inf" if reason == "NON_FINITE" else reason.lower().replace("_", " ")
    return " (stopped" + (f": {reason}" if reason else "") + ")"


def compare_figures(logs: dict, k_full: int | dict) -> dict:
    """The figures of `plot_compare`, unsaved: ``{file name: matplotlib Figure}``.

    Runs without a completed epoch are left out; ``rollout.png`` only when a run
    recorded a rollout.
    """
    k_fulls = k_full if isinstance(k_full, dict) else {"": k_full}
    curves = {}
    for name, log in logs.items():
        ep = log["epochs"]
        if not ep:
            continue
        curves[name] = {
            "time": np.cumsum([e["wall_time"] for e in ep]),
            "iters": np.cumsum([e["fwd_iterations"] + e["adj_iterations"] for e in ep]),
            "val": np.array([e["val_metric"] for e in ep], dtype=float),
            "k": np.array([e["k"] for e in ep], dtype=float),
            "epoch": np.arange(1, len(ep) + 1),
            "rollout": np.asarray(log["rollout"], dtype=float) if log.get("rollout") else None,
            "stopped": _stopped(log),
        }
    style = run_styles(curves, k_fulls, route_names=_route_names(logs))
    title = _title(logs)

    def figure(x: str, y: str, xlabel: str, ylabel: str, *, x_counts=False, steps=False):
        drawn = [n for n in style if curves[n][y] is not None]
        fig = Figure(figsize=_SIZE, dpi=_DPI, layout="constrained")
        ax = fig.add_subplot()
        for i, name in enumerate(drawn):
            c = curves[name]
            xs = c[x] if x != "step" else np.arange(1, len(c[y]) + 1)
            s = {**style[name], "label": style[name]["label"] + c["stopped"]}
            if len(xs) > 15:  # a few markers, staggered: they name, not clutter
                every = max(3, round(len(xs) / 8))
                s["markevery"] = (i % every, every)
            ax.plot(xs, c[y], drawstyle="steps-mid" if steps else "default", **s)
        xs = [curves[n][x] if x != "step" else [1, len(curves[n][y])] for n in drawn]
        scale_axis(ax, "x", xs, log=False if x_counts else None, integer=x_counts)
        scale_axis(ax, "y", [curves[n][y] for n in drawn], integer=y == "k")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
        fig.legend(loc="outside right upper", fontsize=8, frameon=False)
        if title:
            ax.set_title(title, fontsize=10)
        return fig

    figures = {
        "error_vs_time.png": figure("time", "val", "cumulative wall time [s]", "validation error"),
        "error_vs_iterations.png": figure(
            "iters", "val", "cumulative inner iterations (forward + adjoint)", "validation error"
        ),
        "k_schedule.png": figure(
            "epoch", "k", "epoch", "K (KSP max_it per solve)", x_counts=True, steps=True
        ),
    }
    if any(c["rollout"] is not None for c in curves.values()):
        figures["rollout.png"] = figure(
            "step", "rollout", "rollout step", "normalised error (trained model)", x_counts=True
        )
    return figures


def _title(logs: dict) -> str:
    """``"heat2d, preset quick, seed 0"`` when every run agrees on them, else ``""``."""
    parts = []
    for key, fmt in (("scene", "{}"), ("preset", "preset {}"), ("seed", "seed {}")):
        values = {log.get(key) for log in logs.values()}
        if len(values) == 1 and None not in values:
            parts.append(fmt.format(values.pop()))
    return ", ".join(parts)


def plot_compare(logs: dict, k_full: int | dict, out: Path) -> list[str]:
    """Write ``error_vs_time.png``, ``error_vs_iterations.png``, ``k_schedule.png`` and,
    when the runs recorded one, ``rollout.png`` into `out`; return the file names.

    `logs` maps run names (``schedule[@route]``) to `run` results; `k_full` is an int,
    or ``{route: K_full}`` with ``""`` for the scene's own solver.  One curve per run,
    styled and scaled as the module docstring says (`compare_figures`).
    """
    out = Path(out)
    files = []
    for fname, fig in compare_figures(logs, k_full).items():
        fig.savefig(out / fname)
        files.append(fname)
    return files
