"""What each kind of recorded data set says: its page title, page body and headline rows.

`prdp_petsc.lab.reports.pages` reads the data sets under ``docs/data/`` and writes the
pages, the index and the README fragments; this module turns one data set of a
given kind into text.  A kind (`DataSet.kind`) is one of ``compare``, ``seeds``,
``bench``, ``stability``, ``work-precision``, ``rollouts``, ``horizon``, ``ablation``,
``bench-mpi``, ``unseen``, ``defaults``, ``bench-elasticity`` and ``topopt``; each has a body (the
table its command prints, with its plots) and headline rows (``(what, figure)`` pairs
for the README and the index).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .pages import DataSet

__all__ = ["body", "headline", "title"]


def _pct(value: float) -> str:
    return f"{100 * value:.1f} %"


# the title of each kind's page, from its main record and its data set
_TITLES = {
    "compare": lambda d, ds: f"PRDP against full fidelity: {d['scene']}",
    "seeds": lambda d, ds: f"PRDP against full fidelity over seeds: {d['scene']}",
    "bench": lambda d, ds: "Bridge benchmark",
    "stability": lambda d, ds: "Stability on stiff and extreme cases",
    "rollouts": lambda d, ds: f"Long rollouts against the uncorrected solver: {ds.name}",
    "horizon": lambda d, ds: (
        f"Memory and time against the unroll length: {d['scene']} {d['preset']}"
    ),
    "ablation": lambda d, ds: f"Which lever buys what: {d['scene']} {d['preset']}",
    "unseen": lambda d, ds: "PRDP's default construction on problems it was never tuned on",
    "defaults": lambda d, ds: (
        f"Default construction against tuned settings: {d['scene']} {d['preset']}"
    ),
    "bench-mpi": lambda d, ds: (
        f"One rank against several: {d['mesh']}, {d.get('layout', 'replicated')} layout"
    ),
    "topopt": lambda d, ds: f"Topology optimisation with capped solves: {d['scene']} {d['preset']}",
    "bench-elasticity": lambda d, ds: (
        "GAMG on 3D elasticity: iterations against the mesh, with the rigid-body modes"
    ),
    "bench-jax": lambda d, ds: "Capped CG gradients: prdp_petsc against JAX and lineax",
    "work-precision": lambda d, ds: f"Error against run time: {d['problem']}",
}


def title(ds: DataSet) -> str:
    return _TITLES[ds.kind](ds.main, ds)


def _images(ds: DataSet, depth: str = "../") -> list[str]:
    return [f"![{Path(img).stem}]({depth}images/{ds.name}/{img})" for img in ds.images]


# -- the page of each kind -----------------------------------------------------------------------
def _compare_body(ds: DataSet) -> list[str]:
    from ..training.summary import format_table

    return [
        "What `compare` printed (validation error at the last epoch, final K, inner "
        "iterations forward + adjoint, wall time, the solver's share of it):",
        "",
        "<!-- --8<-- [start:output] -->",
        "```text",
        format_table(ds.main).rstrip("\n"),
        "```",
        "<!-- --8<-- [end:output] -->",
        "",
        *(["## Plots", "", *_images(ds)] if ds.images else []),
    ]


def _signed(value: float) -> str:
    return f"{value:+.3f}"


def _bench_rows(d: dict) -> list[tuple[str, str, str]]:
    t = d["throughput"]
    targets = d.get("targets", {})
    rows = [
        (
            f"overhead: bridge forward + backward (gradients for b and θ) over raw "
            f"`KSPSolve` + `KSPSolve`, − 1; n = {d['n']}, K = {d['k']}",
            _signed(d["overhead"]),
            targets.get("overhead", ""),
        ),
        (
            "same, over raw `KSPSolve` + `KSPSolveTranspose`",
            _signed(d["overhead_vs_raw_solve_transpose"]),
            "",
        ),
        (
            "backward over forward (symmetric: the adjoint runs as a forward solve)",
            f"{d['backward_over_forward_symmetric']:.2f}",
            targets.get("backward_over_forward_symmetric", ""),
        ),
        (
            f"small systems (n = {t['n']}, K = {t['k']}), gradient in b: 1 right-hand side",
            _signed(t["overhead_1_rhs"]),
            targets.get("throughput.overhead_1_rhs", ""),
        ),
        (
            "same, a batch of 32 right-hand sides",
            _signed(t["overhead_32_rhs"]),
            targets.get("throughput.overhead_32_rhs", ""),
        ),
    ]
    if "floor_1_rhs" in t:  # recorded since the bare-wrapper variant exists
        rows.append(
            (
                "floor of any torch bridge: the raw loops in a bare `torch.autograd.Function` "
                "(no checks), 1 / 32 right-hand sides",
                f"{_signed(t['floor_1_rhs'])} / {_signed(t['floor_32_rhs'])}",
                "",
            )
        )
    rows += [
        (
            "bridge's extra cost per call / per right-hand side",
            f"{t['extra_per_call_s'] * 1e6:.0f} µs / {t['extra_per_rhs_s'] * 1e6:.0f} µs",
            "",
        ),
        (
            f'`mode="unrolled"` CG over PETSc implicit, n = {d["unrolled_n"]}, '
            f"K = {d['unrolled_k']}, forward + backward",
            f"{d['unrolled_speedup']:.1f}×",
            targets.get("unrolled_speedup", ""),
        ),
    ]
    if d.get("handwritten_unrolled_speedup") is not None:
        rows.append(
            (
                "same, against a hand-written torch CG",
                f"{d['handwritten_unrolled_speedup']:.1f}×",
                "",
            )
        )
    rows.append(
        (
            f"peak memory increase at K = {d['unrolled_k']}: implicit / unrolled",
            f"{d['implicit_peak_rss_mb']:.2f} MiB / {d['unrolled_peak_rss_mb']:.0f} MiB",
            "",
        )
    )
    traced = d.get("implicit_traced_peak_vectors")
    if traced:
        rows.append(
            (
                f"traced peak of one forward + backward on the `ParametricMatrix` (n = "
                f"{d['n']}), in vectors of n: gradient in b / in b and θ / new θ each call",
                f"{traced['b']:.1f} / {traced['b_theta']:.1f} / {traced['b_theta_new_theta']:.1f}",
                "b: a few vectors",
            )
        )
    return rows


def _bench_body(ds: DataSet) -> list[str]:
    d = ds.main
    s = d["settings"]
    lines = [
        f"`{s['ksp_type']}` + `{s['pc_type']}`, {s['mode']}; torch threads "
        f"{s['torch_threads']}; every ratio is the {s['statistic']} ({s['repeats']} "
        f"repeats after {s['warmup']} warm-up); timing noise (interquartile range over "
        f"median of the raw forward time) {d['timing_noise']:.3f}.",
        "",
        "| figure | measured | target |",
        "|---|---:|---|",
    ]
    lines += [f"| {what} | {value} | {target} |" for what, value, target in _bench_rows(d)]
    lines += [
        "",
        "What the rows mean is in the docstring of `prdp_petsc.lab.reports.bench`; every "
        "single timing is in the JSON.",
    ]
    return lines


def _stability_body(ds: DataSet) -> list[str]:
    from .stability import summary_counts, summary_line, to_markdown

    rows = ds.main["rows"]
    c = summary_counts(rows)
    summary = f"{c['rows']} rows in {c['cases']} cases: {summary_line(c)}."
    return [
        "Each row solves `A(θ) x = b` through the torch bridge and reports the forward "
        "residual, the iterations (forward/adjoint), the Taylor rate of the gradient of "
        "`J(θ) = ⟨w, x(θ)⟩` (2 when the gradient is right) with the ε range of the fit, "
        "whether anything became NaN/Inf, and the outcome; a case that must fail reports "
        "the error and the PETSc reason. The cases are described in the docstring of "
        "`prdp_petsc.lab.reports.stability`; `tests/lab/test_stability.py` runs them at "
        "small sizes.",
        "",
        summary,
        "",
        to_markdown(rows).rstrip("\n"),
    ]


def _work_precision_body(ds: DataSet) -> list[str]:
    from .workprecision import to_markdown

    return [
        "Every KSP/PC pair runs in fixed mode (`rtol = atol = 0`) for K = 1, 2, 4, …; "
        "each point has the forward error against a direct (SuperLU) solve and the "
        "gradient error against the converged adjoint gradient, against the wall time of "
        "one gradient (PC setup + forward + adjoint). The JSON holds every point.",
        "",
        to_markdown(ds.main).rstrip("\n"),
        "",
        *_images(ds),
    ]


def _seeds_body(ds: DataSet) -> list[str]:
    from ..training.seeds import format_seeds

    return [
        "What `compare --seeds` printed (per seed: validation errors of PRDP, full "
        "fidelity and its twin, their ratios, PRDP's savings, and the speed-up of the "
        "fastest reduced run over the fastest full-fidelity run; then geometric means "
        "with 95 % intervals over the seeds):",
        "",
        "```text",
        format_seeds(ds.main).rstrip("\n"),
        "```",
        "",
        *(["## Plots", "", *_images(ds)] if ds.images else []),
    ]


def _rollouts_body(ds: DataSet) -> list[str]:
    from .rollouts import format_rollout_report

    return [
        "What `prdp-petsc rollouts` printed: the per-step error of each run's held-out "
        "rollout (geometric mean over the seeds) and of the uncorrected solver, on how "
        "many seeds each run stayed below the uncorrected solver at every step, and the "
        "ratios of error, inner iterations and wall time per seed with their geometric "
        "mean and 95 % interval:",
        "",
        "```text",
        format_rollout_report(ds.main).rstrip("\n"),
        "```",
        "",
        *_images(ds),
    ]


def _horizon_body(ds: DataSet) -> list[str]:
    from .horizon import format_horizon_report

    return [
        "What `prdp-petsc horizon` printed: m-step training at a fixed K, each row in a "
        "fresh process with one torch thread; `growth` is the peak resident size while "
        "training minus the size when training started, `saved MB` what autograd kept "
        "for one batch's backward pass:",
        "",
        "```text",
        format_horizon_report(ds.main).rstrip("\n"),
        "```",
    ]


def _bench_mpi_body(ds: DataSet) -> list[str]:
    from .bench_mpi import format_report
    from .scaling import format_scaling_model, scaling_model

    model = scaling_model(ds.main)
    lines = [
        "What `prdp-petsc bench mpi` printed: one capped CG + Jacobi solve (forward) and its "
        "adjoint with ∂L/∂θ (backward), medians of the repeats; 4 ranks on this 2-core "
        "machine are oversubscribed, so their times say nothing, their memory does.",
        "",
        format_report(ds.main).rstrip("\n"),
    ]
    if model is not None:
        lines += ["", "## Beyond this machine: a model", "", format_scaling_model(model)]
    return lines


def _ablation_body(ds: DataSet) -> list[str]:
    from .ablation import format_ablation

    return [
        "What `prdp-petsc ablation` printed: `compare --seeds` for the preset as given "
        "(`baseline`) and once per lever, each lever's preset settings on their own; one "
        "torch thread, configurations one after another. Each configuration's seeds "
        "result (per seed: errors, times, the runs compared) is kept in `ablation.json`.",
        "",
        "```text",
        format_ablation(ds.main).rstrip("\n"),
        "```",
    ]


def _unseen_body(ds: DataSet) -> list[str]:
    from .unseen import table

    d = ds.main
    lines = [
        "Six problems written for this page, none of them a shipped scene, each in a "
        "plain torch loop with `PRDP.for_problem(find_k_full(...))` and a check (the "
        "validation gradient through the solve at K against the next level 2K, against "
        "K_full from K_full/2 on and at the end); see "
        "`prdp_petsc.lab.reports.unseen_problems` for the problems. Error ratio: PRDP's final "
        "error "
        "over full fidelity's (constant K_full), same seed, same data and initial weights. "
        "Iterations saved: forward and adjoint inner iterations of every solve, the "
        "checks included; checks' share: the checks' part of them. Certified: the last "
        "check, at the final K against K_full, within the 5 % band. "
        "Wall time ratio: PRDP over full, one torch thread, runs one after another.",
        *(
            [
                "",
                "The second table (`unseen --baselines`) puts the default beside a schedule "
                "chosen by hand (the reference's plateau test from K_full/10 in steps of "
                "K_full/10, no checks) and the constant caps K_full/8, /4 and /2: error ratio "
                "as geometric mean (worst seed), iterations saved as the mean over the seeds; "
                "the best constant K is the one that saves most at equal accuracy (geometric "
                "mean ≤ 1.05, no seed above 1.10), i.e. what stopping below K_full can save "
                "without any schedule.",
            ]
            if all("baselines" in p for p in d["problems"].values())
            else []
        ),
        "",
        table(d),
        "",
        "## Every run",
        "",
        "| problem | seed | K_full | final K | error full | error PRDP | ratio | saved | checks |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, p in d["problems"].items():
        for r in p["runs"]:
            lines.append(
                f"| `{name}` | {r['seed']} | {r['k_full']} | {r['prdp']['ks'][-1]} | "
                f"{r['full']['final_error']:.4g} | {r['prdp']['final_error']:.4g} | "
                f"{r['error_ratio']:.3f} | {_pct(r['saved'])} | {len(r['prdp']['checks'])} |"
            )
    return lines


def _defaults_body(ds: DataSet) -> list[str]:
    from .defaults import format_defaults, notes

    return [
        "What `prdp-petsc defaults` printed: per seed, full fidelity (constant K_full), the "
        "scene's tuned PRDP (its preset's settings) and the default construction "
        "(`PRDP.for_problem(K_full)` with a gradient check on a fixed training batch; the "
        "scene's PRDP settings unused). Ratios are final validation errors over full "
        "fidelity's; savings count forward and adjoint inner iterations, the checks included.",
        "",
        "```text",
        format_defaults(ds.main, with_notes=False),
        "```",
        *[line for note in notes(ds.main) for line in ("", note)],
    ]


def _bench_elasticity_body(ds: DataSet) -> list[str]:
    from .bench_elasticity import format_report

    return [
        "What `prdp-petsc bench elasticity` printed: CG + GAMG on the same operator with "
        "nothing declared, with `block_size=3`, and with the block size and the six "
        "rigid-body modes as `near_nullspace`; the set-up time is the first solve's time "
        "minus a second solve's, the error at K is a capped solve's against the converged "
        "solution with the modes. What each declaration does is in the docstring of "
        "`prdp_petsc.lab.reports.bench_elasticity` and in the guide "
        "[Vector and mixed problems](../guide/vector.md).",
        "",
        format_report(ds.main).rstrip("\n"),
    ]


def _bench_jax_body(ds: DataSet) -> list[str]:
    from .bench_jax import format_report

    return [
        "What `prdp-petsc bench jax` printed: the gradient in b of ⟨g, x_K(b)⟩, K capped "
        "Jacobi-CG iterations forward and K on the adjoint, each implementation in its own "
        "single-threaded process, paired rounds. Exactly what each implementation runs is "
        "in the docstring of `prdp_petsc.lab.reports.bench_jax`.",
        "",
        "```text",
        format_report(ds.main).rstrip("\n"),
        "```",
        "",
        *_bench_jax_verdict(ds.main),
    ]


def _bench_jax_verdict(d: dict) -> list[str]:
    """Whether the target was met, and what bounds it: raw PETSc against JAX."""
    t = d["median_s"]
    # a bridge that cost nothing over raw PETSc: their time over raw PETSc's
    free = {name: t[name] / t["raw_petsc"] for name in ("jax_cg", "lineax_cg")}
    met = all(d["ratios"][f"{n}/prdp_petsc"]["median"] >= 1.5 for n in free)
    lines = [f"**Target (≥ 1.5× faster than each): {'met' if met else 'not met'}.**"]
    if not met:
        lines.append(
            f"What bounds it: raw petsc4py alone (KSPSolve + KSPSolve, no torch) takes "
            f"{t['raw_petsc'] * 1e3:.3f} ms per call against {t['jax_cg'] * 1e3:.3f} ms for "
            f"`jax_cg` and {t['lineax_cg'] * 1e3:.3f} ms for `lineax_cg`, so a bridge that "
            f"cost nothing over raw PETSc would be {free['jax_cg']:.2f}× / "
            f"{free['lineax_cg']:.2f}× as fast as they are, not 1.5×: on this problem the "
            "target asks more of PETSc's CG itself than of any wrapper around it."
        )
    return lines


def _topopt_body(ds: DataSet) -> list[str]:
    from .topopt import TARGET_RATIO, TARGET_SAVED, format_results, spread, target_met

    met = target_met(ds.main)
    note = spread(ds.main)
    return [
        "What `demos/topopt3d.py results` printed: per load case (the seed; z_c is the "
        "height of the loaded band), the converged route (every solve to rtol 1e-8), "
        "constant K, PRDP's default construction (`PRDP.for_problem(K_full)`, refinements "
        "decided by a gradient check of the compliance at K against K_full) and the `rtol` "
        "schedule. C final is the compliance of the last design solved to rtol 1e-10; "
        "inner iterations count forward and adjoint solves and the checks; t→1 % is the "
        "wall time at which a route's design first came within 1 % of the converged "
        "route's final compliance (designs scored outside the clock). The controller "
        "watches the design change per iteration (the scene's docstring says why).",
        "",
        "```text",
        format_results(ds.main),
        "```",
        "",
        f"PRDP within {_pct(TARGET_RATIO - 1)} of the converged design's compliance at "
        f"≥ {_pct(TARGET_SAVED)} fewer inner iterations: {sum(met)} of {len(met)} load cases.",
        "",
        *([note, ""] if note else []),
        *(["## Designs", "", *_images(ds)] if ds.images else []),
    ]


_BODIES = {
    "topopt": _topopt_body,
    "defaults": _defaults_body,
    "unseen": _unseen_body,
    "ablation": _ablation_body,
    "bench-elasticity": _bench_elasticity_body,
    "bench-jax": _bench_jax_body,
    "bench-mpi": _bench_mpi_body,
    "rollouts": _rollouts_body,
    "horizon": _horizon_body,
    "seeds": _seeds_body,
    "compare": _compare_body,
    "bench": _bench_body,
    "stability": _stability_body,
    "work-precision": _work_precision_body,
}


# -- headline figures: the index and the README ----------------------------------------------
def headline(ds: DataSet) -> list[tuple[str, str]]:
    """(what, figure) pairs of one data set for the headline table; savings are said to
    be at equal accuracy only where PRDP reached it."""
    from ..training.summary import ACCURACY_RATIO

    d = ds.main
    if ds.kind == "defaults":
        from .defaults import fewer

        parts = []
        for name in ("default", "tuned"):
            s = d.get(name)
            if s is None:
                parts.append(f"{name}: no seed finished")
                continue
            saved = s["saved_at_equal_accuracy"]
            parts.append(
                f"{name} {s['ratio']['geometric_mean']:.3f} (equal accuracy on "
                f"{s['equal_accuracy']} of {s['compared']}"
                + (f", {fewer(saved)} there" if saved is not None else "")
                + ")"
            )
        what = (
            f"{d['scene']} --preset {d['preset']}, seeds {', '.join(map(str, d['seeds']))}: "
            "final error over full fidelity's, default construction (PRDP.for_problem) "
            "and tuned settings"
        )
        return [(what, "; ".join(parts))]
    if ds.kind == "topopt":
        from .topopt import target_met

        met = target_met(d)
        return [(
            f"{d['scene']} --preset {d['preset']}: PRDP (default construction) within 1 % "
            "of the converged design's compliance at ≥ 50 % fewer inner iterations",
            f"{sum(met)} of {len(met)} load cases",
        )]  # fmt: skip
    if ds.kind == "unseen":
        problems = d["problems"].values()
        within = sum(p["geomean_ratio"] <= 1.05 and p["worst_ratio"] <= 1.10 for p in problems)
        saving = sum(min(p["saved"]) >= 0.40 for p in problems)
        worst = max(p["geomean_ratio"] for p in problems)
        return [(
            f"PRDP.for_problem on {len(d['problems'])} problems it was never tuned on, "
            f"seeds {', '.join(map(str, d['seeds']))}",
            f"within 5 % of full fidelity (geometric mean, no seed above 10 %) on {within} of "
            f"{len(d['problems'])} (worst mean ratio {worst:.3f}); at least 40 % fewer inner "
            f"iterations on every seed on {saving}",
        )]  # fmt: skip
    if ds.kind == "compare":
        out = []
        if "savings" in d:
            s = d["savings"]
            cost = (
                f"{_pct(s['iterations'])} fewer inner iterations, {_pct(s['wall_time'])} "
                f"less wall time, validation error ratio {d['val_error_ratio']:.3f}"
            )
            if not d.get("equal_accuracy", d["val_error_ratio"] <= ACCURACY_RATIO):
                cost = f"not at equal accuracy: {cost}"
            out.append((f"{d['scene']}: PRDP against constant K_full = {d['k_full']}", cost))
        else:
            out.append((f"{d['scene']}: PRDP against constant K_full", d["savings_unavailable"]))
        best = d.get("fastest")
        if best and best["winner"]:
            out.append(
                (
                    f"{d['scene']}: fastest run to the full-fidelity validation error",
                    f"`{best['winner']}` in {best['winner_seconds']:.2f} s, against "
                    f"{best['seconds_to_target'][best['reference']]:.2f} s for "
                    f"`{best['reference']}`",
                )
            )
        return out
    if ds.kind == "seeds":
        speedup = d.get("speedup") or {}
        seeds = f"{_setting(ds)} over seeds {', '.join(map(str, d['seeds']))}"
        what = f"{seeds}: speed-up of the fastest reduced run over the fastest full-fidelity one"
        if speedup.get("geometric_mean") is None:
            rows = [(what, "no reduced run reached full-fidelity accuracy")]
        else:
            rows = [(what, _speedup_figure(speedup))]
        bound = (speedup.get("solver_bound") or {}).get("geometric_mean")
        if bound is not None:  # summary.solver_bound: no solver setting gets past it
            rows[0] = (what, rows[0][1] + f"; solver-only bound {bound:.2f}×")
        ratio = d.get("prdp_ratio") or {}
        if ratio.get("geometric_mean") is not None:
            interval = ratio.get("interval")
            ci = "" if not interval else f" (95 % interval {interval[0]:.3f}–{interval[1]:.3f})"
            from ..training.seeds import equal_accuracy_savings

            equal = equal_accuracy_savings(d["per_seed"])
            n = sum("prdp_ratio" in r for r in d["per_seed"])
            saved = (
                f"; {_pct(equal['iterations_saved']['mean'])} fewer inner iterations on the "
                f"{equal['seeds']} of {n} seeds at equal accuracy"
                if equal
                else f"; no seed of {n} at equal accuracy"
            )
            rows.append(
                (
                    f"{seeds}: PRDP's final validation error over full fidelity's",
                    f"{ratio['geometric_mean']:.3f}{ci}{saved}",
                )
            )
        return rows
    if ds.kind == "bench":
        t = d["throughput"]
        return [
            (
                f"bridge overhead over raw PETSc, n = {d['n']}, K = {d['k']} (target ≤ 0.05)",
                f"{_signed(d['overhead'])}; one small system {_signed(t['overhead_1_rhs'])}, "
                f"32 right-hand sides {_signed(t['overhead_32_rhs'])}",
            ),
            (
                f"implicit against unrolled gradients, K = {d['unrolled_k']}",
                f"implicit {d['unrolled_speedup']:.1f}× faster; peak memory "
                f"{d['implicit_peak_rss_mb']:.2f} MiB against {d['unrolled_peak_rss_mb']:.0f} MiB",
            ),
        ]
    if ds.kind == "stability":
        from .stability import summary_counts, summary_line

        c = summary_counts(d["rows"])
        return [(f"stability suite: {c['rows']} stiff and extreme solves", summary_line(c))]
    if ds.kind == "rollouts":
        return _rollouts_headline(ds)
    if ds.kind == "horizon":
        return _horizon_headline(ds)
    if ds.kind == "ablation":
        return _ablation_headline(ds)
    if ds.kind == "bench-mpi":
        return _bench_mpi_headline(ds)
    if ds.kind == "bench-elasticity":
        return _bench_elasticity_headline(ds)
    if ds.kind == "bench-jax":
        r = d["ratios"]
        return [
            (
                f"prdp_petsc against JAX's CG and lineax's CG, n = {d['n']}, K = {d['k']}, "
                "gradient in b (target ≥ 1.5× faster than each)",
                f"{r['jax_cg/prdp_petsc']['median']:.2f}× / "
                f"{r['lineax_cg/prdp_petsc']['median']:.2f}× (their time over prdp_petsc's)",
            )
        ]
    from .workprecision import LEVELS, summarize

    summary = summarize(d)
    level = min(LEVELS)
    hits = sorted(
        (e["levels"][str(level)]["t"], e["pair"], e["levels"][str(level)]["K"])
        for e in summary
        if str(level) in e["levels"]
    )
    direct = d["direct"]["t_solve_and_gradient"]
    if not hits:
        return [(f"{d['problem']}: gradient error ≤ {level:.0e}", "no pair reached it")]
    t, pair, k = hits[0]
    return [
        (
            f"{d['problem']} ({d['info']['unknowns']} unknowns): cheapest gradient "
            f"to a relative error ≤ {level:.0e}",
            f"{pair} at K = {k}: {t * 1e3:.1f} ms, against {direct * 1e3:.0f} ms "
            "for a direct solve",
        )
    ]


def _rollouts_headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    out = []
    for name, entry in list(d["runs"].items())[:1]:  # the first run: the one compared
        below = entry.get("below_uncorrected_every_step")
        if below is not None:
            out.append(
                (
                    f"{ds.name}: `{name}` below the uncorrected solver at every one of "
                    f"{d['steps']} rollout steps",
                    f"on {below} of {len(entry['rollout'])} seeds",
                )
            )
    for pair, stats in d["ratios"].items():
        e = stats["error"]
        interval = e["interval"]
        ci = "" if interval is None else f" (95 % interval {interval[0]:.2f}–{interval[1]:.2f})"
        out.append(
            (
                f"{ds.name}: error ratio {pair} at rollout step {d['step']}",
                f"{e['geometric_mean']:.3f}{ci}, {e['n']} seeds",
            )
        )
    return out


def _bench_mpi_headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    solve = d["solve"]
    if "1" not in solve or "2" not in solve:
        return []
    one, two = solve["1"], solve["2"]
    ratio = max(two["peak_rss_mb_per_rank"]) / max(one["peak_rss_mb_per_rank"])
    return [
        (
            f"{d['mesh']} ({one['unknowns']} unknowns), {d.get('layout', 'replicated')} "
            "layout: 2 ranks against 1",
            f"peak memory per rank {ratio:.2f}× the one-rank peak; forward "
            f"{two['speedup_forward']:.2f}×, backward {two['speedup_backward']:.2f}× faster",
        )
    ]


def _bench_elasticity_headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    lo, hi = d["sizes"][0], d["sizes"][-1]
    its = {(r["variant"], r["cells"]): r["iterations"] for r in d["rows"] if r["cells"] in (lo, hi)}
    unknowns = max(r["unknowns"] for r in d["rows"])
    return [
        (
            f"GAMG on 3D elasticity, {lo}³ to {hi}³ hexahedra ({unknowns} unknowns), rtol "
            f"{d['settings']['rtol']:g}: iterations with the rigid-body modes (target ≤ "
            f"{d['target']['growth.modes'].split()[-1]}×)",
            f"{its['modes', lo]} → {its['modes', hi]} ({d['growth']['modes']:.2f}×); nothing "
            f"declared {its['scalar', lo]} → {its['scalar', hi]} "
            f"({d['growth']['scalar']:.2f}×)",
        )
    ]


def _horizon_headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    rows = {(r["m"], r["checkpoint"]): r for r in d["rows"]}
    ms = sorted({m for m, _ in rows})
    lo, hi = ms[0], ms[-1]
    if (lo, True) not in rows or (hi, True) not in rows:
        return []
    a, b = rows[lo, True], rows[hi, True]
    growth = [r["peak_rss_mb"] - r["rss_at_start_mb"] for r in (a, b)]
    return [
        (
            f"{d['scene']} {d['preset']}: peak memory of m = {hi} training against m = {lo}, "
            "checkpointed",
            f"{b['peak_rss_mb']:.0f} MB against {a['peak_rss_mb']:.0f} MB "
            f"({b['peak_rss_mb'] / a['peak_rss_mb']:.2f}×; while training +{growth[1]:.0f} "
            f"against +{growth[0]:.0f} MB)",
        )
    ]


def _ablation_headline(ds: DataSet) -> list[tuple[str, str]]:
    """One row per lever: its speed-up against the best full run, the baseline's, and
    how fast its fastest reduced and full runs got there against the baseline's."""
    d = ds.main
    seeds = ", ".join(map(str, d["seeds"]))
    base = (d["configs"]["baseline"]["result"].get("speedup") or {}).get("geometric_mean")
    rows = []
    for name, effect in d["effects"].items():
        speed = (d["configs"][name]["result"].get("speedup") or {}).get("geometric_mean")
        figure = "—" if speed is None else f"{speed:.2f}×"
        figure += "" if base is None else f" (baseline {base:.2f}×)"
        pace = [
            f"fastest {kind} run {ratio:.2f}×"
            for kind in ("reduced", "full")
            if (ratio := effect[f"{kind}_vs_baseline"].get("geometric_mean")) is not None
        ]
        if pace:  # a speed-up can also rise because full fidelity got slower
            figure += f"; as fast as the baseline's: {', '.join(pace)}"
        rows.append(
            (
                f"{d['scene']} --preset {d['preset']} over seeds {seeds}, lever `{name}` "
                f"({d['levers'][name]}): speed-up over the fastest full-fidelity run",
                figure,
            )
        )
    return rows


def _setting(ds: DataSet) -> str:
    """``ns2d --preset large_k64 k_init=192, -ns2d_pc_type fieldsplit``: the scene, the
    preset, its ``--set`` changes and the PC a run set on the command line, from the
    recorded command."""
    argv = ds.provenance.get("argv", [])
    text = ds.main["scene"]
    if "--preset" in argv[:-1]:
        text += f" --preset {argv[argv.index('--preset') + 1]}"
    changes = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--set"]
    if changes:  # --set k_init=192: another setting, another row
        text += " " + " ".join(changes)
    pcs = [f"{a} {argv[i + 1]}" for i, a in enumerate(argv[:-1]) if a.endswith("_pc_type")]
    return text + (f", {pcs[0]}" if pcs else "")


def _speedup_figure(stats: dict) -> str:
    """``2.10× (95 % interval 1.62–2.71, 3 seeds; ≥ 2 on 2 of 3)``."""
    text = f"{stats['geometric_mean']:.2f}×"
    inside = []
    if stats.get("interval"):
        lo, hi = stats["interval"]
        inside.append(f"95 % interval {lo:.2f}–{hi:.2f}")
    goal = f"≥ {stats['goal']:g} on {stats['goal_met']} of {stats['seeds']}"
    inside.append(f"{stats['n']} seeds; {goal}")
    return f"{text} ({', '.join(inside)})"


def body(ds: DataSet) -> list[str]:
    """The lines of `ds`'s page after its provenance."""
    return _BODIES[ds.kind](ds)
