"""Plots of a comparison: validation error against wall time and inner iterations, K,
and the per-step error of each trained model over a long rollout."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_compare"]

_OTHERS = ["C0", "C1", "C2", "C4", "C5", "C6", "C7", "C8", "C9"]


def _styles(names: list[str], k_fulls: dict[str, int]) -> dict[str, dict]:
    """Line style per run name ``schedule[@route]``: PRDP bold, K_full solid, others dashed.

    A run on another solver route (``"prdp@cg/icc"``) is drawn dotted and labelled so.
    """
    colors = iter(_OTHERS * 4)
    styles = {}
    for name in names:
        schedule, _, route = name.partition("@")
        suffix = f" [{route}]" if route else ""
        if schedule == "prdp":
            style = {"color": "C3" if not route else "C6", "lw": 2.2, "label": "PRDP" + suffix}
            style["zorder"] = 3
        else:
            k = int(schedule.split(":")[1])
            full = k == k_fulls.get(route, k_fulls[""])
            label = f"K = {k}" + (" (K_full)" if full else "") + suffix
            style = {"color": next(colors), "lw": 1.4, "label": label}
            style["ls"] = "-" if full else "--"
        if route:
            style["ls"] = ":"
        styles[name] = style
    return styles


def _top(series) -> float | None:
    """Upper y-limit: 10 x the largest value of the curves that stay below 10, so that
    a diverging run (far too small K) does not squash the others; None if none do."""
    tame = [np.max(v) for v in series if np.all(np.isfinite(v)) and np.max(v) < 10]
    return 10 * max(tame) if tame else None


def plot_compare(logs: dict, k_full: int | dict, out: Path) -> list[str]:
    """Write ``error_vs_time.png``, ``error_vs_iterations.png``, ``k_schedule.png`` and,
    when the runs recorded one, ``rollout.png``.

    `k_full` is an int, or ``{route: K_full}`` with ``""`` for the scene's own solver.
    One curve per run; returns the file names.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    k_fulls = k_full if isinstance(k_full, dict) else {"": k_full}
    curves = {}
    for name, log in logs.items():
        ep = log["epochs"]
        if not ep:
            continue
        curves[name] = {
            "time": np.cumsum([e["wall_time"] for e in ep]),
            "iters": np.cumsum([e["fwd_iterations"] + e["adj_iterations"] for e in ep]),
            "val": np.array([e["val_metric"] for e in ep]),
            "k": np.array([e["k"] for e in ep]),
            "rollout": log.get("rollout"),
        }
    style = _styles(list(curves), k_fulls)

    def figure(fname: str, xlabel: str, ylabel: str, draw, *, log_y=True, top=None) -> str:
        fig, ax = plt.subplots(figsize=(6, 4))
        for name, c in curves.items():
            draw(ax, c, style[name])
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if log_y:
            ax.set_yscale("log")
        if top is not None:
            ax.set_ylim(top=top)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=120)
        plt.close(fig)
        return fname

    top = _top([c["val"] for c in curves.values()])
    files = [
        figure(
            "error_vs_time.png",
            "cumulative wall time [s]",
            "validation error",
            lambda ax, c, s: ax.plot(c["time"], c["val"], **s),
            top=top,
        ),
        figure(
            "error_vs_iterations.png",
            "cumulative inner iterations (forward + adjoint)",
            "validation error",
            lambda ax, c, s: ax.plot(c["iters"], c["val"], **s),
            top=top,
        ),
        figure(
            "k_schedule.png",
            "epoch",
            "K (max_it)",
            lambda ax, c, s: ax.step(np.arange(len(c["k"])), c["k"], where="post", **s),
            log_y=False,
        ),
    ]
    rollouts = [np.asarray(c["rollout"]) for c in curves.values() if c["rollout"]]
    if rollouts:
        top = _top(rollouts)

        def rollout(ax, c, s):
            if c["rollout"]:
                r = np.asarray(c["rollout"])
                label = s["label"] + (" (off scale)" if top and not r.max() <= top else "")
                steps = np.arange(1, len(r) + 1)
                ax.plot(steps, r, marker=".", **{**s, "label": label})

        files.append(
            figure(
                "rollout.png", "rollout step", "normalised error (trained model)", rollout, top=top
            )
        )
    return files
