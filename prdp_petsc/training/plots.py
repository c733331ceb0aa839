"""Plots of a comparison: validation error against wall time and inner iterations, K."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_compare"]


def plot_compare(logs: dict, k_full: int, out: Path) -> list[str]:
    """Write ``error_vs_time.png``, ``error_vs_iterations.png`` and ``k_schedule.png``.

    One curve per schedule; returns the file names.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
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
        }

    others = iter(["C0", "C1", "C2", "C4", "C5", "C6", "C7", "C8", "C9"] * 3)
    colors = {name: "C3" if name == "prdp" else next(others) for name in curves}

    def style(name):
        if name == "prdp":
            return {"color": "C3", "lw": 2.2, "label": "PRDP", "zorder": 3}
        k = int(name.split(":")[1])
        label = f"K = {k}" + (" (K_full)" if k == k_full else "")
        return {
            "color": colors[name],
            "lw": 1.4,
            "label": label,
            "ls": "-" if k == k_full else "--",
        }

    files = []
    for key, xlabel, fname in (
        ("time", "cumulative wall time [s]", "error_vs_time.png"),
        ("iters", "cumulative inner iterations (forward + adjoint)", "error_vs_iterations.png"),
    ):
        fig, ax = plt.subplots(figsize=(6, 4))
        for name, c in curves.items():
            ax.plot(c[key], c["val"], **style(name))
        ax.set_xlabel(xlabel)
        ax.set_ylabel("validation error")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / fname, dpi=120)
        plt.close(fig)
        files.append(fname)

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, c in curves.items():
        ax.step(np.arange(len(c["k"])), c["k"], where="post", **style(name))
    ax.set_xlabel("epoch")
    ax.set_ylabel("K (max_it)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "k_schedule.png", dpi=120)
    plt.close(fig)
    files.append("k_schedule.png")
    return files
