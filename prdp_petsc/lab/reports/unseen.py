"""PRDP's default construction against full fidelity on the problems it was never tuned on.

``prdp-petsc unseen`` trains each problem of `prdp_petsc.lab.reports.unseen_problems`, per
seed, at constant K_full and with ``PRDP.for_problem(find_k_full(...))`` and its
checks, in the problem's own loop, and writes ``unseen.json`` for the results page.
Costs are the inner iterations (forward and adjoint) of every solve a run makes:
training, validation and the controller's checks.
"""

from __future__ import annotations

import math
import time

from prdp_petsc import PRDP, find_k_full

from .unseen_problems import PROBLEMS, RTOL_FULL, Problem, build

__all__ = ["compare", "main", "parse_arguments", "table", "train"]


def train(problem: Problem, schedule: str, k_full: int) -> dict:
    """Run `problem` with ``"full"`` (constant K_full), ``"prdp"`` (the default
    construction, `PRDP.for_problem`, with checks) or ``"fixed:K"``; return its record."""
    solver = problem.solver
    controller = PRDP.for_problem(k_full, check=problem.check) if schedule == "prdp" else None
    constant = k_full if schedule == "full" else None
    if schedule.startswith("fixed:"):
        constant = int(schedule.split(":", 1)[1])
    elif controller is None and schedule != "full":
        raise ValueError(f"schedule must be 'full', 'prdp' or 'fixed:K', got {schedule!r}")
    solver.reset_stats()
    ks, metrics = [], []
    t0 = time.perf_counter()
    for epoch in range(problem.epochs):
        k = controller.k if controller is not None else constant
        solver.max_it = k
        problem.train_epoch(epoch)
        metric = problem.metric()
        if controller is not None:
            controller.update(metric)
        ks.append(k)
        metrics.append(metric)
    record = {"schedule": schedule, "k_full": k_full, "ks": ks, "metrics": metrics}
    if controller is not None:
        controller.certify()
        record["savings_k"] = controller.savings()
        record["checks"] = [
            {"epoch": c.epoch, "k": c.k, "gap": c.gap, "certified": c.certified}
            for c in controller.checks
        ]
    stats = solver.stats
    record.update(
        wall_time=time.perf_counter() - t0,
        iterations=stats.forward_iterations + stats.adjoint_iterations,
        solver_time=stats.forward_time + stats.adjoint_time,
        final_error=float(problem.score()),
    )
    return record


def compare(names, seeds, *, quick: bool = False) -> dict:
    """Full fidelity and the default PRDP on every problem and seed: the records and,
    per problem, the final-error ratios (PRDP / full) and the iterations saved."""
    out = {"quick": quick, "seeds": list(seeds), "problems": {}}
    for name in names:
        runs = []
        for seed in seeds:
            problem = build(name, seed, quick)
            k_full = find_k_full(*problem.probe, problem.solver, rtol=RTOL_FULL)
            full = train(problem, "full", k_full)
            prdp = train(build(name, seed, quick), "prdp", k_full)
            runs.append({"seed": seed, "k_full": k_full, "full": full, "prdp": prdp,
                         "error_ratio": prdp["final_error"] / full["final_error"],
                         "saved": 1.0 - prdp["iterations"] / full["iterations"]})  # fmt: skip
        ratios = [r["error_ratio"] for r in runs]
        out["problems"][name] = {
            "runs": runs,
            "geomean_ratio": math.exp(sum(math.log(r) for r in ratios) / len(ratios)),
            "worst_ratio": max(ratios),
            "saved": [r["saved"] for r in runs],
            "certified": [r["prdp"]["savings_k"]["certified"] for r in runs],
        }
    return out


def table(result: dict) -> str:
    """A markdown table of `compare`'s result."""
    rows = [
        "| problem | K_full | error ratio (geo. mean) | worst seed | iterations saved | "
        "certified | wall time ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, p in result["problems"].items():
        walls = [r["prdp"]["wall_time"] / r["full"]["wall_time"] for r in p["runs"]]
        k_full = sorted({r["k_full"] for r in p["runs"]})
        rows.append(
            f"| `{name}` | {', '.join(map(str, k_full))} | {p['geomean_ratio']:.3f} | "
            f"{p['worst_ratio']:.3f} | "
            + ", ".join(f"{100 * s:.0f} %" for s in p["saved"])
            + f" | {sum(bool(c) for c in p['certified'])}/{len(p['certified'])} | "
            + ", ".join(f"{w:.2f}" for w in walls)
            + " |"
        )
    return "\n".join(rows)


def parse_arguments(argv=None):
    """The arguments of ``unseen``; ``--seeds`` as one list (the deprecated ``--seeds 0 1
    2`` too)."""
    import argparse
    from pathlib import Path

    from ..cli.arguments import add_debug, add_size_preset, deprecated, seeds

    parser = argparse.ArgumentParser(prog="prdp-petsc unseen")
    parser.add_argument("--out", required=True, type=Path, help="folder for unseen.json")
    add_debug(parser)
    parser.add_argument(
        "--seeds", type=seeds, nargs="+", default=[[0, 1, 2]],
        help="seeds, e.g. 0-2 or 0,3,5 (default 0-2)",
    )  # fmt: skip
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=list(PROBLEMS))
    add_size_preset(parser, "small sizes and few epochs")
    args = parser.parse_args(argv)
    groups, args.seeds = args.seeds, list(dict.fromkeys(s for group in args.seeds for s in group))
    if len(groups) > 1:  # one release more: --seeds 0 1 2
        deprecated("--seeds with several values", "--seeds " + ",".join(map(str, args.seeds)))
    return args


def main(argv=None) -> int:
    """``prdp-petsc unseen --out DIR [--seeds 0-2] [--problems ...] [--preset quick]``.

    Writes ``DIR/unseen.json`` (every run's record) and prints the table; record it
    for the results pages with ``prdp-petsc pages record unseen -- unseen --out DIR``.
    """
    import json

    import torch

    args = parse_arguments(argv)
    torch.set_num_threads(1)
    result = compare(args.problems, args.seeds, quick=args.preset == "quick")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "unseen.json").write_text(json.dumps(result, indent=1))
    print(table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
