"""Work–precision report: error against wall time for KSP/PC pairs on a standard problem.

``prdp-petsc work-precision PROBLEM --out DIR`` (a problem of
`prdp_petsc.lab.reports.problems`) sweeps, for every applicable KSP/PC pair, the
iteration cap K over K = 1, 2, 4, … in fixed mode (``rtol = atol = 0``) and records
the forward error against a sparse direct solve, the error and cosine of the capped
implicit gradient ``∂L/∂θ`` against the converged one, and the wall time of PC set-up
(paid whenever θ changes), forward solve, and adjoint solve + ``Gᵀ(λ ⊙ x)``.  It writes
``work_precision_<problem>.json``, ``.png`` and ``.md`` in DIR.

Notes
-----
``gamg-plain`` is GAMG with plain aggregation (``-pc_gamg_agg_nsmooths 0``).
Richardson is damped by ``1/ρ`` (ρ the estimated spectral radius of the preconditioned
operator) with no PC or Jacobi.  PETSc's SOR has no transpose: on a non-symmetric
operator its adjoint runs with ``ksp_use_explicittranspose`` (timed with it).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from ..cli.arguments import add_debug, add_out, add_size_preset, positive
from ..provenance import load_average, write_result
from ..training.routes import parse_routes, route_settings
from .benchmarking import stopwatch
from .kinds import DataSet, ReportKind, markdown_table
from .problems import PROBLEMS, build_problem, direct_gradient

__all__ = ["KIND", "main", "pairs_for", "summarize", "sweep", "to_markdown"]

logger = logging.getLogger(__name__)

SYMMETRIC_KSPS = ("cg", "gmres", "bcgs", "richardson")
NONSYMMETRIC_KSPS = ("gmres", "bcgs", "richardson")
SYMMETRIC_PCS = ("none", "jacobi", "sor", "icc", "gamg")
NONSYMMETRIC_PCS = ("none", "jacobi", "sor", "ilu", "gamg", "gamg-plain")
#: gradient-error levels at which the summary reports the cheapest pair
LEVELS = (1e-2, 1e-4, 1e-8)
#: errors below this count as converged: the sweep of a pair stops there
FLOOR = 1e-11


def pairs_for(symmetric: bool) -> list[tuple[str, str]]:
    """KSP/PC pairs that apply: CG and ICC only for symmetric operators."""
    ksps = SYMMETRIC_KSPS if symmetric else NONSYMMETRIC_KSPS
    pcs = SYMMETRIC_PCS if symmetric else NONSYMMETRIC_PCS
    return [(k, p) for k in ksps for p in pcs]


def _spectral_radius(A, pc: str, symmetric: bool) -> float:
    """Estimated spectral radius of ``A`` (``pc="none"``) or ``D⁻¹A`` (Jacobi)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import eigs, eigsh

    if pc == "jacobi":
        d = 1.0 / np.sqrt(A.diagonal())
        A = sp.diags(d) @ A @ sp.diags(d)  # similar to D⁻¹A
    if symmetric:
        lam = eigsh(A, k=1, which="LA", tol=1e-3, return_eigenvectors=False)
    else:
        lam = eigs(A, k=1, which="LM", tol=1e-3, return_eigenvectors=False)
    return float(np.abs(lam).max())


def _options(ksp: str, pc: str, A, symmetric: bool) -> tuple[dict, dict | None]:
    opts: dict = {"ksp_type": ksp, "pc_type": pc}
    if pc == "gamg-plain":  # plain (unsmoothed) aggregation, for non-symmetric operators
        opts.update(pc_type="gamg", pc_gamg_agg_nsmooths=0)
    adjoint = None
    if ksp == "richardson" and pc in ("none", "jacobi"):
        opts["ksp_richardson_scale"] = 1.0 / (1.05 * _spectral_radius(A, pc, symmetric))
    if pc == "sor" and abs(A - A.T).max() > 1e-14 * abs(A).max():  # SOR has no transpose,
        adjoint = {"options": {"ksp_use_explicittranspose": True}}  # use an explicit Aᵀ
    return opts, adjoint


def _timed(fn, min_time: float = 0.3, max_repeat: int = 3):
    """(result, best wall time) of fn(), repeated while the total stays under min_time."""
    best, total = np.inf, 0.0
    for _ in range(max_repeat):
        out, dt = stopwatch(fn)
        best, total = min(best, dt), total + dt
        if total > min_time:
            break
    return out, best


def _setup(opts: dict, adjoint, A):
    """A KSPSolver on A with its PC(s) set up."""
    from prdp_petsc import KSPSolver

    solver = KSPSolver(opts, max_it=1, adjoint=adjoint, prefix="wp_")
    solver.set_operator(A)
    solver.ksp.setUp()
    if solver.adjoint_ksp.getPC() is not solver.ksp.getPC():
        solver.adjoint_ksp.setUp()
    return solver


def _gradient_step(problem, solver, x):
    """Adjoint solve and ``∂L/∂θ = −Gᵀ(λ ⊙ x)`` at the capped forward solution x:
    ``(gradient, the adjoint solve's LinearSolution)``."""
    adjoint = solver.solve_transpose(problem.loss_grad(x))
    return problem.A.theta_gradient(adjoint.value, x), adjoint


def _measure(problem, A, opts, adjoint, ks, refs, max_seconds) -> list[dict]:
    """First pass over K for one pair: errors and times."""
    from prdp_petsc import SolverError

    x_ref, g_ref = refs
    solver, t_setup = _timed(lambda: _setup(opts, adjoint, A), 0.0)
    rows = []
    for K in ks:
        solver.max_it = K
        row = {"K": K, "t_setup": t_setup}
        try:
            sol, row["t_forward"] = _timed(lambda: solver.solve(problem.b))
            x = sol.value
            row["iterations"], row["reason"] = sol.iterations, sol.reason
            step, row["t_adjoint"] = _timed(lambda x=x: _gradient_step(problem, solver, x))
            grad, row["adjoint_iterations"] = step[0], step[1].iterations
        except SolverError as err:
            row["error"] = err.reason
            rows.append(row)
            break
        row["t_total"] = t_setup + row["t_forward"] + row["t_adjoint"]
        row["forward_error"] = float(np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref))
        row["gradient_error"] = float(np.linalg.norm(grad - g_ref) / np.linalg.norm(g_ref))
        norms = np.linalg.norm(grad) * np.linalg.norm(g_ref)
        row["gradient_cosine"] = float(grad @ g_ref / norms) if norms > 0 else 0.0
        rows.append(row)
        if (
            max(row["forward_error"], row["gradient_error"]) < FLOOR
            or not np.isfinite(row["gradient_error"])
            or 2 * row["t_total"] > max_seconds  # the next K would cost more
        ):
            break
    return rows


def _retime(problem, A, opts, adjoint, rows, limit: float) -> None:
    """Time a pair's points once more (K-step solves are deterministic); keep the minimum."""
    solver, t_setup = _timed(lambda: _setup(opts, adjoint, A), 0.0, 1)
    for row in rows:
        row["t_setup"] = min(row["t_setup"], t_setup)
        if "t_total" not in row:
            continue
        if row["t_total"] <= limit:
            solver.max_it = row["K"]
            x, t_forward = _timed(lambda: solver.solve(problem.b).value, 0.0, 1)
            _, t_adjoint = _timed(lambda x=x: _gradient_step(problem, solver, x), 0.0, 1)
            row["t_forward"] = min(row["t_forward"], t_forward)
            row["t_adjoint"] = min(row["t_adjoint"], t_adjoint)
        row["t_total"] = row["t_setup"] + row["t_forward"] + row["t_adjoint"]


def sweep(
    problem,
    ks: list[int],
    pairs: list[tuple[str, str]] | None = None,
    *,
    max_seconds: float = 6.0,
    passes: int = 3,
    retime_limit: float = 3.0,
) -> dict:
    """Run the sweep; return a JSON-ready dict with the reference and one row per point.

    A pair's sweep stops once forward and gradient error are below `FLOOR`, at the
    first `SolverError`, or when the next K (double the cost) would take more than
    `max_seconds` per gradient.
    Timings are the minimum over `passes` passes through all pairs (points above
    `retime_limit` seconds are timed once): on a shared machine, interference hits
    different points in different passes.
    """
    from scipy.sparse.linalg import splu

    load_start = load_average()
    A = problem.matrix()
    (x_ref, _, g_ref), t_direct = _timed(lambda: direct_gradient(problem))
    _, t_factor = _timed(lambda: splu(A.tocsc()))
    configs, rows = {}, []
    for ksp, pc in pairs or pairs_for(problem.symmetric):
        label = f"{ksp}/{pc}"
        try:
            configs[label] = _options(ksp, pc, A, problem.symmetric)
        except Exception as err:  # e.g. the eigenvalue estimate failed: skip, say why
            rows.append({"pair": label, "ksp": ksp, "pc": pc, "K": None, "error": f"{err}"})
            continue
        pair_rows = _measure(problem, A, *configs[label], ks, (x_ref, g_ref), max_seconds)
        rows.extend({"pair": label, "ksp": ksp, "pc": pc, **r} for r in pair_rows)
        logger.info("pair %s: %d points", label, len(pair_rows))
    for _ in range(passes - 1):
        for label, (opts, adjoint) in configs.items():
            _retime(
                problem, A, opts, adjoint, [r for r in rows if r["pair"] == label], retime_limit
            )
        _, t = _timed(lambda: direct_gradient(problem), 0.0, 1)
        t_direct = min(t_direct, t)
    load = [v[0] for v in (load_start, load_average()) if v]
    return {
        "problem": problem.name,
        "description": problem.description,
        "info": problem.info,
        "K": list(ks),
        "max_seconds": max_seconds,
        "passes": passes,
        "load_average": load,
        "direct": {"t_factor": t_factor, "t_solve_and_gradient": t_direct},
        "rows": rows,
    }


def summarize(result: dict, levels=LEVELS) -> list[dict]:
    """Per pair: cheapest point (time, K) reaching each gradient-error level."""
    out = []
    labels = list(dict.fromkeys(r["pair"] for r in result["rows"]))
    for label in labels:
        pts = [r for r in result["rows"] if r["pair"] == label and "t_total" in r]
        failed = [r["error"] for r in result["rows"] if r["pair"] == label and "error" in r]
        entry = {"pair": label, "error": failed[0] if failed else None, "levels": {}}
        if pts:
            entry["best_gradient_error"] = min(r["gradient_error"] for r in pts)
            entry["best_forward_error"] = min(r["forward_error"] for r in pts)
            entry["t_setup"] = pts[0]["t_setup"]
        for level in levels:
            hit = [r for r in pts if r["gradient_error"] <= level]
            if hit:
                r = min(hit, key=lambda r: r["t_total"])
                entry["levels"][str(level)] = {"t": r["t_total"], "K": r["K"]}
        out.append(entry)
    return out


def to_markdown(result: dict) -> str:
    """Summary table of one problem plus the winner at each gradient-error level."""
    summary = summarize(result)
    info = result["info"]
    head = [
        f"**{result['problem']}** — {result['description']}; {info['unknowns']} unknowns, "
        f"{info['parameters']} parameters. Direct reference (SuperLU): factorisation "
        f"{result['direct']['t_factor'] * 1e3:.0f} ms, forward + adjoint + gradient "
        f"{result['direct']['t_solve_and_gradient'] * 1e3:.0f} ms.",
        "",
        "Time (ms, PC setup + forward + adjoint) and K of the cheapest point reaching a "
        "relative gradient error ≤ level; — never reached within the K range "
        f"(K = 1 … {result['K'][-1]}, doubling). Wall times are the minimum over "
        f"{result.get('passes', 1)} passes; load average at start/end "
        + "/".join(f"{v:.1f}" for v in result.get("load_average", []))
        + " on this machine.",
        "",
    ]
    header = ["KSP/PC", "setup ms", *(f"≤ {lv:.0e}" for lv in LEVELS)]
    header += ["best grad. err", "best fwd err", "note"]
    rows = []
    for e in summary:
        cells = []
        for lv in LEVELS:
            hit = e["levels"].get(str(lv))
            cells.append(f"{hit['t'] * 1e3:.1f} (K={hit['K']})" if hit else "—")
        setup = f"{e['t_setup'] * 1e3:.1f}" if "t_setup" in e else "—"
        best_g = f"{e['best_gradient_error']:.1e}" if "best_gradient_error" in e else "—"
        best_f = f"{e['best_forward_error']:.1e}" if "best_forward_error" in e else "—"
        note = f"stopped: {e['error']}" if e["error"] else ""
        rows.append((e["pair"], setup, *cells, best_g, best_f, note))
    head += [markdown_table(header, rows, "l" + "r" * (len(LEVELS) + 3)), ""]
    for lv in LEVELS:
        ranked = sorted(
            (e["levels"][str(lv)]["t"], e["pair"]) for e in summary if str(lv) in e["levels"]
        )
        if ranked:
            podium = ", ".join(f"{p} {t * 1e3:.1f} ms" for t, p in ranked[:3])
            head.append(f"- gradient error ≤ {lv:.0e}: {podium}")
    return "\n".join(head) + "\n"


def plot(result: dict, path: Path) -> None:
    """Forward error, gradient error and 1 − cosine against total time, one curve per pair."""
    from matplotlib.figure import Figure

    colors = {"none": "C7", "jacobi": "C0", "sor": "C2", "icc": "C1", "ilu": "C1", "gamg": "C3"}
    colors["gamg-plain"] = "C4"
    styles = {"cg": ("-", "o"), "gmres": ("--", "s"), "bcgs": ("-.", "^"), "richardson": (":", "x")}
    fig = Figure(figsize=(19, 5.6))
    axes = fig.subplots(1, 3, sharex=True)
    keys = (
        ("forward_error", "forward error ‖x_K − x*‖/‖x*‖"),
        ("gradient_error", "gradient error ‖g_K − g*‖/‖g*‖"),
        ("one_minus_cos", "1 − cos(g_K, g*)"),
    )
    labels = list(dict.fromkeys(r["pair"] for r in result["rows"]))
    for label in labels:
        pts = [r for r in result["rows"] if r["pair"] == label and "t_total" in r]
        if not pts:
            continue
        ksp, pc = label.split("/")
        t = np.array([r["t_total"] for r in pts]) * 1e3
        line, marker = styles[ksp]
        for ax, (key, _) in zip(axes, keys, strict=True):
            y = [1.0 - r["gradient_cosine"] if key == "one_minus_cos" else r[key] for r in pts]
            ax.loglog(t, np.maximum(y, 1e-17), line, color=colors[pc], marker=marker, ms=3.5,
                      lw=1.3, label=label)  # fmt: skip
    t_direct = (result["direct"]["t_solve_and_gradient"]) * 1e3
    for ax, (_, title) in zip(axes, keys, strict=True):
        ax.axvline(t_direct, color="k", lw=0.8, alpha=0.5)
        ax.set_xlabel("wall time per gradient: PC setup + forward + adjoint [ms]")
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].text(t_direct, 1e-16, " direct", fontsize=8, va="bottom")
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, fontsize=8, loc="center right", title="KSP/PC")
    info = result["info"]
    fig.suptitle(
        f"{result['problem']}: {result['description']} — {info['unknowns']} unknowns; "
        "K = " + ", ".join(map(str, result["K"])),
        fontsize=10,
    )
    fig.subplots_adjust(left=0.04, right=0.88, top=0.88, bottom=0.12, wspace=0.2)
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    """``prdp-petsc work-precision PROBLEM --out DIR [--preset quick] [--k-max K]
    [--routes R,...]``."""

    def routes(text: str) -> tuple[str, ...]:
        try:
            pairs = parse_routes(text)
            for route in pairs:
                if len(route_settings(route)) > 2:
                    raise ValueError(f"work-precision runs plain ksp/pc pairs, got {route!r}")
            return pairs
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    parser = argparse.ArgumentParser(
        prog="prdp-petsc work-precision",
        description="Forward and gradient error against wall time for KSP/PC pairs and "
        "K on a geometric range; writes work_precision_<problem>.{json,png,md} in DIR.",
    )
    parser.add_argument("problem", choices=sorted(PROBLEMS))
    add_out(parser)
    add_size_preset(parser, "small mesh and K range")
    parser.add_argument("--k-max", type=positive, default=None, help="largest K (power of two)")
    parser.add_argument(
        "--routes", type=routes, default=(), help="only these KSP/PC pairs, e.g. cg/gamg,cg/icc"
    )
    add_debug(parser)
    args = parser.parse_args(argv)
    quick = args.preset == "quick"
    kmax = args.k_max or (256 if quick else 2048)
    ks = [2**i for i in range(int(np.log2(kmax)) + 1)]
    t0 = time.perf_counter()
    problem = build_problem(args.problem, quick=quick)
    pairs = [tuple(r.split("/")) for r in args.routes] or None
    result = sweep(problem, ks, pairs, passes=2 if quick else 3)
    result["seconds"] = time.perf_counter() - t0
    result["quick"] = quick
    result["summary"] = summarize(result)
    stem = args.out / f"work_precision_{args.problem}"
    write_result(args.out, f"{stem.name}.json", result)
    stem.with_suffix(".md").write_text(to_markdown(result))
    plot(result, stem.with_suffix(".png"))
    print(
        f"work-precision {args.problem}: {len(result['rows'])} points in "
        f"{result['seconds']:.0f} s -> {stem}.{{json,png,md}}"
    )
    return 0


# -- the page of a recorded ``work-precision`` run ------------------------------------------------
def _headline(ds: DataSet) -> list[tuple[str, str]]:
    """The cheapest gradient to the loosest level, against a direct solve."""
    d = ds.main
    level = min(LEVELS)
    hits = sorted(
        (e["levels"][str(level)]["t"], e["pair"], e["levels"][str(level)]["K"])
        for e in summarize(d)
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


KIND = ReportKind(
    name="work-precision",
    reads="work_precision_*.json",
    title=lambda ds: f"Error against run time: {ds.main['problem']}",
    headline=_headline,
    intro="Every KSP/PC pair runs in fixed mode (`rtol = atol = 0`) for K = 1, 2, 4, …; "
    "each point has the forward error against a direct (SuperLU) solve and the "
    "gradient error against the converged adjoint gradient, against the wall time of "
    "one gradient (PC setup + forward + adjoint). The JSON holds every point.",
    output=lambda ds: to_markdown(ds.main).rstrip("\n"),
    printed=False,
)
