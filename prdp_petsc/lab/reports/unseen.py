"""PRDP's default construction against full fidelity on problems it was never tuned on.

``prdp-petsc unseen`` trains each problem of `prdp_petsc.lab.reports.unseen_problems`,
per seed, at constant K_full and with ``PRDP.for_problem(find_k_full(...))`` and its
checks, and writes ``unseen.json``.  Costs are the inner iterations of every solve a run
makes, the checks' included.  ``--baselines`` adds the constant caps K_full/8, /4, /2
(the best one at equal accuracy is what stopping below K_full can save without a
schedule) and a schedule chosen by hand (`HAND`).
"""

from __future__ import annotations

import time

from prdp_petsc import PRDP, find_k_full

from ..provenance import write_result
from ..training.accuracy import (
    ACCURACY_RATIO,
    WORST_SEED_RATIO,
    constant_caps,
    equal_over_seeds,
    fraction_of,
    probe_errors,
    probed_at,
    worst_ratio,
)
from .kinds import DataSet, ReportKind, markdown_table, percent
from .unseen_problems import HELD_OUT, PROBLEMS, RTOL_FULL, Problem, build

__all__ = ["HAND", "KIND", "compare", "main", "table", "train"]

#: the hand schedule: `PRDP.paper` (the reference's test) started and stepped at this
#: fraction of K_full (rounded up), capped at K_full
HAND = 1 / 10


def train(problem: Problem, schedule: str, k_full: int) -> dict:
    """Run `problem` with ``"full"`` (constant K_full), ``"prdp"`` (the default
    construction, `PRDP.for_problem`, with checks), ``"hand"`` (`HAND`) or
    ``"fixed:K"``; return its record."""
    solver = problem.solver
    controller = None
    solver.reset_stats()
    if schedule == "prdp":
        controller = PRDP.for_problem(k_full, check=problem.check(), epochs=problem.epochs)
    elif schedule == "hand":
        step = fraction_of(k_full, HAND)
        controller = PRDP.paper(k_init=step, k_step=step, k_max=max(k_full, step))
    constant = k_full if schedule == "full" else None
    if schedule.startswith("fixed:"):
        constant = int(schedule.split(":", 1)[1])
    elif controller is None and schedule != "full":
        raise ValueError(f"schedule must be 'full', 'prdp', 'hand' or 'fixed:K', got {schedule!r}")
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
    if controller is not None and controller.check is not None:
        controller.certify()
        record["savings_k"] = controller.savings()
        record["checks"] = [
            {"epoch": c.epoch, "k": c.k, "against": c.against, "gap": c.gap,
             "descent": c.descent, "certified": c.certified}
            for c in controller.checks
        ]  # fmt: skip
        record["check_iterations"] = controller.check.spent()[0]
    stats = solver.stats
    record.update(
        wall_time=time.perf_counter() - t0,
        iterations=stats.forward_iterations + stats.adjoint_iterations,
        solver_time=stats.forward_time + stats.adjoint_time,
        final_error=float(problem.score()),
    )
    return record


def compare(names, seeds, *, quick: bool = False, baselines: bool = False) -> dict:
    """Full fidelity and the default PRDP on every problem and seed: the records and,
    per problem, the final-error ratios (PRDP / full) and the iterations saved; with
    `baselines`, the same for the hand schedule and each constant cap of
    `prdp_petsc.lab.training.accuracy.constant_caps` (``"baselines"``: schedule ->
    ratios and savings per seed)."""
    out = {"quick": quick, "seeds": list(seeds), "problems": {}}
    for name in names:
        runs = []
        for seed in seeds:
            problem = build(name, seed, quick)
            k_full = find_k_full(*problem.probe, problem.solver, rtol=RTOL_FULL)
            full = train(problem, "full", k_full)
            prdp = train(build(name, seed, quick), "prdp", k_full)
            run = {"seed": seed, "k_full": k_full, "full": full, "prdp": prdp,
                   "probe_errors": probe_errors(k_full),
                   **_against(full, prdp)}  # fmt: skip
            if baselines:
                schedules = ["hand", *(f"fixed:{k}" for k in constant_caps(k_full).values())]
                run["baselines"] = {
                    s: _against(full, train(build(name, seed, quick), s, k_full)) for s in schedules
                }
            runs.append(run)
        certified = [r["prdp"]["savings_k"]["certified"] for r in runs]
        out["problems"][name] = {**_summary(runs), "runs": runs, "certified": certified}
        if baselines:
            out["problems"][name]["baselines"] = _baselines(runs)
    return out


def _against(full: dict, run: dict) -> dict:
    """A run's final error over full fidelity's, and the share of its iterations saved."""
    out = {"error_ratio": run["final_error"] / full["final_error"],
           "saved": 1.0 - run["iterations"] / full["iterations"]}  # fmt: skip
    if "ks" in run:
        out["k_final"] = run["ks"][-1]
    return out


def _summary(runs: list[dict]) -> dict:
    """Geometric-mean and worst error ratio and the savings of `runs` (dicts with
    ``error_ratio`` and ``saved``)."""
    from ..training.seeds import ratio_statistics

    ratios = [r["error_ratio"] for r in runs]
    return {
        "geomean_ratio": ratio_statistics(ratios)["geometric_mean"],
        "worst_ratio": worst_ratio(ratios),
        "saved": [r["saved"] for r in runs],
    }


def _baselines(runs: list[dict]) -> dict:
    """Per baseline (``hand``, ``K_full/8``, ``K_full/4``, ``K_full/2``): the summary
    over the seeds, whether it is at equal accuracy, and the best constant cap there."""
    out = {"hand": _summary([r["baselines"]["hand"] for r in runs])}
    for label in constant_caps(runs[0]["k_full"]):
        rows = [r["baselines"][f"fixed:{constant_caps(r['k_full'])[label]}"] for r in runs]
        out[label] = _summary(rows)
    for summary in out.values():
        summary["equal_accuracy"] = _equal(summary)
    constants = [lab for lab in out if lab != "hand" and out[lab]["equal_accuracy"]]
    out["best_constant"] = max(constants, key=lambda lab: min(out[lab]["saved"]), default=None)
    return out


def _equal(summary: dict) -> bool:
    """`equal_over_seeds` of a `_summary`."""
    return equal_over_seeds(summary["geomean_ratio"], summary["worst_ratio"])


def table(result: dict) -> str:
    """A markdown table of `compare`'s result (and of its baselines, where it has them)."""
    header = ["problem", "K_full", "error ratio (geo. mean)", "worst seed", "iterations saved",
              "checks' share", "certified", "wall time ratio"]  # fmt: skip
    rows = []
    for name, p in result["problems"].items():
        prdp = [r["prdp"] for r in p["runs"]]
        shares = [  # of the PRDP run's inner iterations; not recorded before check_iterations
            f"{100 * r['check_iterations'] / r['iterations']:.0f} %" if "check_iterations" in r
            else "–"
            for r in prdp
        ]  # fmt: skip
        walls = [r["prdp"]["wall_time"] / r["full"]["wall_time"] for r in p["runs"]]
        rows.append((f"`{name}`", ", ".join(map(str, sorted({r["k_full"] for r in p["runs"]}))),
                     f"{p['geomean_ratio']:.3f}", f"{p['worst_ratio']:.3f}",
                     ", ".join(f"{100 * s:.0f} %" for s in p["saved"]), ", ".join(shares),
                     f"{sum(map(bool, p['certified']))}/{len(p['certified'])}",
                     ", ".join(f"{w:.2f}" for w in walls)))  # fmt: skip
    text = markdown_table(header, rows)
    if all("baselines" in p for p in result["problems"].values()):
        text += "\n\n" + _baseline_table(result)
    return text


def _baseline_table(result: dict) -> str:
    """The default against the hand schedule and the best constant cap: error ratio
    (geometric mean, worst seed) and the iterations saved (mean over the seeds)."""

    def saved(s: dict) -> str:
        return f"{100 * sum(s['saved']) / len(s['saved']):.0f} %"

    def cell(s: dict) -> str:
        return f"{s['geomean_ratio']:.3f} ({s['worst_ratio']:.3f}), {saved(s)}"

    rows = []
    for name, p in result["problems"].items():
        b = p["baselines"]
        best = b["best_constant"]
        constants = [lab for lab in b if lab not in ("hand", "best_constant")]
        best_cell = "none" if best is None else f"{best}: {saved(b[best])}"
        every = "; ".join(f"{lab}: {cell(b[lab])}{_probed(p, lab)}" for lab in constants)
        rows.append((f"`{name}`", cell(p), cell(b["hand"]), best_cell, every))
    header = ["problem", "default: ratio, saved", "hand schedule: ratio, saved",
              "best constant K at equal accuracy: saved",
              "every constant K: ratio, saved [the probe's solve error there, per seed]",
              ]  # fmt: skip
    return markdown_table(header, rows)


def _probed(problem: dict, label: str) -> str:
    """`` [e0, e1, e2 %]``: per seed, the probe's error of the solve capped at the
    constant cap `label` (what the default's start reads); empty where not recorded."""
    errors = probed_at(problem["runs"], label)
    return "" if errors is None else f" [{', '.join(f'{100 * e:.1f}' for e in errors)} %]"


def _parser():
    import argparse

    from ..cli.arguments import add_debug, add_out, add_seeds, add_size_preset

    parser = argparse.ArgumentParser(prog="prdp-petsc unseen")
    add_out(parser, "folder for unseen.json")
    add_debug(parser)
    add_seeds(parser)
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS),
                        choices=[*PROBLEMS, *HELD_OUT])  # fmt: skip
    add_size_preset(parser, "small sizes and few epochs")
    parser.add_argument(
        "--baselines", action="store_true",
        help="also run the hand schedule and the constant caps K_full/8, /4, /2",
    )  # fmt: skip
    return parser


def main(argv=None) -> int:
    """``prdp-petsc unseen --out DIR [--seeds 0-2] [--problems ...] [--preset quick]``.

    Writes ``DIR/unseen.json`` (every run's record) and prints the table; record it
    for the results pages with ``prdp-petsc pages record unseen -- unseen --out DIR``.
    """
    import torch

    args = _parser().parse_args(argv)
    torch.set_num_threads(1)
    result = compare(
        args.problems, args.seeds, quick=args.preset == "quick", baselines=args.baselines
    )
    write_result(args.out, "unseen.json", result)
    print(table(result))
    return 0


# -- the page of a recorded ``unseen`` ------------------------------------------------------------
def _intro(ds: DataSet) -> str:
    baselines = all("baselines" in p for p in ds.main["problems"].values())
    names = list(ds.main["problems"])
    held = ""
    if all(name in HELD_OUT for name in names):
        held = " and held out of the choice of the controller's rules (`HELD_OUT`)"
    return (
        f"{len(names)} problems written for this page{held}, none of them a shipped scene, "
        "each in a "
        "plain torch loop with `PRDP.for_problem(find_k_full(...))` and a check (the "
        "validation gradient through the solve at K against the next level, K_full/4 from "
        "K_full/8 and so on, against K_full from K_full/2 on and at the end); see "
        "`prdp_petsc.lab.reports.unseen_problems` for the problems. Error ratio: PRDP's final "
        "error over full fidelity's (constant K_full), same seed, same data and initial "
        "weights. Iterations saved: forward and adjoint inner iterations of every solve, the "
        "checks included; checks' share: the checks' part of them. Certified: the last "
        "check, at the final K against K_full, within the 5 % band. "
        "Wall time ratio: PRDP over full, one torch thread, runs one after another."
    ) + (
        "\n\nThe second table (`unseen --baselines`) puts the default beside a schedule "
        "chosen by hand (the reference's plateau test from K_full/10 in steps of "
        "K_full/10, no checks) and the constant caps K_full/8, /4 and /2: error ratio "
        "as geometric mean (worst seed), iterations saved as the mean over the seeds; "
        "the best constant K is the one that saves most at equal accuracy (geometric "
        f"mean ≤ {ACCURACY_RATIO}, no seed above {WORST_SEED_RATIO:.2f}), i.e. what stopping "
        "below K_full can save "
        "without any schedule."
        if baselines
        else ""
    )


def _every_run(ds: DataSet) -> list[str]:
    header = ["problem", "seed", "K_full", "final K", "error full", "error PRDP", "ratio"]
    rows = [
        (f"`{name}`", r["seed"], r["k_full"], r["prdp"]["ks"][-1],
         f"{r['full']['final_error']:.4g}", f"{r['prdp']['final_error']:.4g}",
         f"{r['error_ratio']:.3f}", percent(r["saved"]), len(r["prdp"]["checks"]))
        for name, p in ds.main["problems"].items()
        for r in p["runs"]
    ]  # fmt: skip
    return ["## Every run", markdown_table([*header, "saved", "checks"], rows)]


def _headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    problems = d["problems"].values()
    within = sum(map(_equal, problems))
    saving = sum(min(p["saved"]) >= 0.40 for p in problems)
    worst = max(p["geomean_ratio"] for p in problems)
    return [(
        f"PRDP.for_problem on {len(d['problems'])} problems it was never tuned on, "
        f"seeds {', '.join(map(str, d['seeds']))}",
        f"within 5 % of full fidelity (geometric mean, no seed above 10 %) on {within} of "
        f"{len(d['problems'])} (worst mean ratio {worst:.3f}); at least 40 % fewer inner "
        f"iterations on every seed on {saving}",
    )]  # fmt: skip


KIND = ReportKind(
    name="unseen",
    reads="unseen.json",
    title=lambda ds: "PRDP's default construction on problems it was never tuned on",
    headline=_headline,
    intro=_intro,
    output=lambda ds: table(ds.main),
    printed=False,
    after=_every_run,
)
