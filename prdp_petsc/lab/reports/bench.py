"""Benchmark of the torch bridge: overhead over raw PETSc, throughput, unrolled CG.

``prdp-petsc bench bridge --out DIR`` writes ``DIR/bench_bridge.json``, all from
one run on one machine:

``overhead`` (the headline)
    Bridge forward + backward (``solve(A, b, solver, theta=θ)``, then
    ``x.backward(g)`` with gradients for b and θ) over what the bridge runs in
    PETSc for this symmetric operator and symmetric PC, raw petsc4py ``KSPSolve``
    + ``KSPSolve`` on the same Mat with the same KSP/PC and K, minus 1: a
    like-for-like figure.  Problem: ``plate_holes`` refined twice, P1,
    ``−∇·(κ∇u) + u``, κ per element.  ``overhead_detail`` adds the ratio against
    ``KSPSolve`` + ``KSPSolveTranspose`` (what a non-symmetric operator runs;
    PETSc's transposed products are slower), for b only (θ constant), of the
    minima, and the time the bridge spends outside KSPSolve.
``implicit_traced_peak_vectors``
    Peak memory of one forward + backward on that problem's `ParametricMatrix`,
    traced (tracemalloc), in vectors of n doubles: gradient in b only (target: a
    few vectors; the operator is the library's own and is not copied), in b and θ
    (plus ``dA = λ[rows] ⊙ x[cols]``, one entry per nonzero, and the p-sized
    gradient), and in b and θ with a new θ every call (plus the new values A(θ)).
``throughput``
    Small systems (n ≈ 5 000, K = 10), one and 32 right-hand sides: bridge over
    raw ``KSPSolve`` + ``KSPSolve`` loops, and the bridge's fixed cost per call and
    per right-hand side (see `prdp_petsc.lab.reports.bench_throughput`).
``backward_over_forward_symmetric``
    Bridge backward time over bridge forward time at equal K, for this symmetric
    case (the adjoint runs as a forward solve).
``unrolled_speedup``
    ``mode="unrolled"`` over ``mode="implicit"``, forward + backward at K = 300 on
    the five-point ``−Δ`` (175 × 175), gradient in b, with the peak memory of
    each; ``handwritten_unrolled_speedup`` is the same against a hand-written
    torch CG (see `prdp_petsc.lab.reports.bench_unrolled`).

Every ratio is the median over repeats (after warm-up, ``time.perf_counter``) of
the ratio within one repeat: the variants run interleaved, in alternating order,
so that a neighbour's load on a shared machine hits both sides of each ratio.
``timing_noise`` (interquartile range / median of the raw forward time) says how
busy the machine was; every single timing is in the JSON.  torch runs on
``--threads`` threads (default 1: PETSc's AIJ kernels are serial, and OpenMP
spin-waiting on an oversubscribed machine makes threaded torch sparse kernels
erratic).  Never assert these numbers in tests; they describe one machine.
Targets: overhead ≤ 5 % at about 1e5 unknowns; small systems ≤ 25 % for one
right-hand side and ≤ 10 % for 32; backward / forward ≤ 1.1.

Notes
-----
The KSPs have options prefix ``bench_``: options such as ``-bench_ksp_view`` given
through ``PETSC_OPTIONS`` reach the bridge's KSP (the raw KSP is set up from
``--routes KSP/PC`` only, and the run stops if the two types differ).  ``--preset
quick`` runs tiny sizes (a smoke test); the default is ``paper``.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from ..cli.arguments import DeprecatedAlias, add_debug, add_size_preset, positive, routes
from ..provenance import load_average, machine_info, write_result
from . import bench_elasticity, bench_gpu, bench_jax, bench_mpi
from .bench_throughput import bench_throughput, overhead_problem, raw_ksp
from .bench_unrolled import bench_solver, bench_unrolled, ksp_types
from .kinds import DataSet, ReportKind, markdown_table

__all__ = ["KIND", "main"]

logger = logging.getLogger(__name__)

RAW_KEYS = ("raw_forward", "raw_transpose", "raw_adjoint_as_solve")


def _median(values) -> float:
    return float(statistics.median(values))


def timing_noise(values) -> float:
    """Interquartile range over median of a timing series: above ~0.05 the machine was
    busy during the run, and the paired ratios are the figures to trust."""
    q1, q2, q3 = statistics.quantiles(values, n=4) if len(values) > 1 else (values[0],) * 3
    return float((q3 - q1) / q2)


def bench_overhead(n: int, k: int, repeats: int, warmup: int, ksp_type: str, pc_type: str):
    """Time the bridge against raw petsc4py on the same Mat; return a JSON-ready dict."""
    import torch

    from prdp_petsc import solve

    A, theta_np, b_np, g_np, refine = overhead_problem(n)
    solver = bench_solver(ksp_type, pc_type, k)
    theta = torch.tensor(theta_np, requires_grad=True)
    b = torch.tensor(b_np, requires_grad=True)
    g = torch.tensor(g_np)
    solve(A, b, solver, theta=theta).backward(g)  # creates the Mat and both KSPs

    raw = raw_ksp(solver.mat, ksp_type, pc_type, k)
    x_vec, b_vec = solver.mat.createVecs()
    lam_vec, g_vec = x_vec.duplicate(), b_vec.duplicate()
    b_vec.array[:] = b_np
    g_vec.array[:] = g_np

    t = {
        key: []
        for key in (
            *RAW_KEYS,
            "bridge_forward",
            "bridge_backward",
            "bridge_forward_ksp",
            "bridge_backward_ksp",
            "bridge_b_only_forward",
            "bridge_b_only_backward",
        )
    }

    def raw_step(record: bool) -> None:
        times = []
        for op, rhs, sol in (
            (raw.solve, b_vec, x_vec),
            (raw.solveTranspose, g_vec, lam_vec),
            (raw.solve, g_vec, lam_vec),
        ):
            sol.set(0.0)
            t0 = time.perf_counter()
            op(rhs, sol)
            times.append(time.perf_counter() - t0)
            if raw.getIterationNumber() != k:
                raise RuntimeError(f"raw KSP ran {raw.getIterationNumber()} iterations, not {k}")
        if record:
            for key, dt in zip(RAW_KEYS, times, strict=True):
                t[key].append(dt)

    def bridge_step(record: bool, key: str = "bridge", th=theta) -> None:
        theta.grad = b.grad = None
        stats = solver.stats
        f0, a0 = stats.forward_time, stats.adjoint_time
        t0 = time.perf_counter()
        x = solve(A, b, solver, theta=th)
        t1 = time.perf_counter()
        x.backward(g)
        t2 = time.perf_counter()
        if record:
            t[f"{key}_forward"].append(t1 - t0)
            t[f"{key}_backward"].append(t2 - t1)
            if key == "bridge":
                t["bridge_forward_ksp"].append(stats.forward_time - f0)
                t["bridge_backward_ksp"].append(stats.adjoint_time - a0)

    def b_only_step(record: bool) -> None:
        bridge_step(record, "bridge_b_only", theta.detach())

    for i in range(warmup + repeats):
        steps = (raw_step, bridge_step, b_only_step)
        for step in steps if i % 2 == 0 else steps[::-1]:
            step(i >= warmup)
    stats = solver.stats  # every bridge solve, forward and adjoint, ran exactly k
    for side in ("forward", "adjoint"):
        solves, its = getattr(stats, f"{side}_solves"), getattr(stats, f"{side}_iterations")
        if its != k * solves:
            raise RuntimeError(f"bridge {side} KSP: {its} iterations in {solves} solves, not {k}")

    if ksp_types(solver) != [raw.getType(), raw.getPC().getType()]:
        raise RuntimeError(f"bridge KSP is {ksp_types(solver)}, raw is {raw.getType()}")
    traced = traced_peaks(A, b, theta, g, solver)
    med = {key: _median(v) for key, v in t.items()}
    low = {key: min(v) for key, v in t.items()}
    r = {key: np.asarray(v) for key, v in t.items()}  # one entry per repeat
    bridge = r["bridge_forward"] + r["bridge_backward"]
    raw_fb = r["raw_forward"] + r["raw_transpose"]
    return {
        "problem": f"plate_holes refine={refine}, P1, -div(kappa grad u) + u, kappa P0",
        "n": int(A.shape[0]),
        "nnz": int(A.nnz),
        "n_params": int(A.n_params),
        "k": k,
        "statistic": "median over repeats of the ratio within each repeat (paired)",
        "overhead": _median(bridge / (r["raw_forward"] + r["raw_adjoint_as_solve"]) - 1.0),
        "backward_over_forward_symmetric": _median(r["bridge_backward"] / r["bridge_forward"]),
        "overhead_vs_raw_solve_transpose": _median(bridge / raw_fb - 1.0),
        "overhead_b_only": _median(
            (r["bridge_b_only_forward"] + r["bridge_b_only_backward"])
            / (r["raw_forward"] + r["raw_adjoint_as_solve"])
            - 1.0
        ),
        "overhead_of_medians": (med["bridge_forward"] + med["bridge_backward"])
        / (med["raw_forward"] + med["raw_adjoint_as_solve"])
        - 1.0,
        "overhead_of_minima": (low["bridge_forward"] + low["bridge_backward"])
        / (low["raw_forward"] + low["raw_adjoint_as_solve"])
        - 1.0,
        "raw_transpose_over_forward": _median(r["raw_transpose"] / r["raw_forward"]),
        "bridge_outside_ksp_s": {
            "forward": _median(r["bridge_forward"] - r["bridge_forward_ksp"]),
            "backward": _median(r["bridge_backward"] - r["bridge_backward_ksp"]),
        },
        "timing_noise": timing_noise(t["raw_forward"]),
        "median_s": med,
        "min_s": low,
        "timings_s": t,
        "ksp": {"raw": [raw.getType(), raw.getPC().getType()], "bridge": ksp_types(solver)},
        "traced_peak": traced,
    }


TRACED_METHOD = (
    "tracemalloc (numpy and torch-from-numpy allocations are traced; PETSc's own are "
    "not, and the PETSc work vectors are made once per operator), in-process, after "
    "a warm-up call of the same kind: peak over one forward + backward minus the traced "
    "memory before it, in vectors of n doubles"
)


def traced_peaks(A, b, theta, g, solver) -> dict:
    """Peak traced memory of one forward + backward on the library's own operator (a
    `ParametricMatrix`), in vectors of n doubles: gradient in b only, in b and θ, and
    in b and θ with a new θ every call (whose values A(θ), nnz of them, are new too)."""
    import gc
    import tracemalloc

    import torch

    from prdp_petsc import solve

    vector = 8.0 * A.shape[0]
    fresh = [theta.detach() * (1.0 + 1e-3 * i) for i in range(4)]

    def call(th):
        b.grad = None
        if th.requires_grad:
            th.grad = None
        solve(A, b, solver, theta=th).backward(g)

    cases = {
        "b": lambda i: call(theta.detach()),
        "b_theta": lambda i: call(theta),
        "b_theta_new_theta": lambda i: call(fresh[i].requires_grad_(True)),
    }
    out = {}
    for name, run in cases.items():
        run(0)  # warm-up: the same kind of call
        gc.collect()
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            run(1)
            peak = tracemalloc.get_traced_memory()[1] - base
        finally:
            tracemalloc.stop()
        out[name] = peak / vector
    with torch.no_grad():
        solve(A, b, solver, theta=theta)  # leave the solver on the benchmark's θ
    return {
        "vectors": out,
        "n": int(A.shape[0]),
        "nnz_over_n": A.nnz / A.shape[0],
        "n_params_over_n": A.n_params / A.shape[0],
        "method": TRACED_METHOD,
    }


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="prdp-petsc bench", description=__doc__.split("\n")[0])
    p.add_argument(
        "which",
        choices=["bridge", "mpi", "elasticity", "jax", "gpu"],
        help="benchmark to run (mpi: bench_mpi, elasticity: bench_elasticity, jax: bench_jax, "
        "gpu: bench_gpu)",
    )
    p.add_argument("--out", type=Path, required=True, help="folder for bench_<which>.json")
    add_size_preset(p, "tiny sizes (a smoke test)")
    p.add_argument(
        "--n", type=positive, help="overhead problem size, rounded to a plate_holes refinement"
    )
    p.add_argument("--k", type=positive, help="K of the overhead problem (default 100)")
    p.add_argument("--unrolled-n", type=positive, help="unrolled comparison: about n unknowns")
    p.add_argument("--unrolled-k", type=positive, help="K of the unrolled comparison (300)")
    p.add_argument("--repeats", type=positive, help="timed repeats after warm-up (21)")
    p.add_argument(
        "--routes",
        type=_route,
        default=("cg", "jacobi"),
        metavar="KSP/PC",
        help="the KSP and PC type of every solve (default cg/jacobi; one route)",
    )
    for old in ("--ksp-type", "--pc-type"):  # one release more: --routes KSP/PC
        p.add_argument(old, action=DeprecatedAlias, new="--routes KSP/PC", help=argparse.SUPPRESS)
    p.add_argument("--threads", type=positive, default=1, help="torch threads (default 1)")
    add_debug(p)
    return p


def _route(text: str) -> tuple[str, str]:
    """``--routes KSP/PC``: one plain pair (this benchmark compares with a raw KSP of
    the same types)."""
    pairs = routes(text)
    if len(pairs) != 1 or pairs[0].count("/") != 1 or ":" in pairs[0]:
        message = f"expected one KSP/PC pair such as cg/jacobi, got {text!r}"
        raise argparse.ArgumentTypeError(message)
    ksp_type, pc_type = pairs[0].split("/")
    return ksp_type, pc_type


def main(argv: list[str]) -> int:
    """Run ``bench bridge``; write ``<out>/bench_bridge.json``; return an exit code."""
    others = {
        "mpi": bench_mpi,
        "elasticity": bench_elasticity,
        "jax": bench_jax,
        "gpu": bench_gpu,
    }
    if argv and argv[0] in others:
        return others[argv[0]].main(argv[1:])
    args = _parser().parse_args(argv)
    ksp_type = args.ksp_type or args.routes[0]  # the deprecated --ksp-type/--pc-type first
    pc_type = args.pc_type or args.routes[1]
    import torch

    quick = args.preset == "quick"
    n = args.n or (4851 if quick else 75018)
    k = args.k or (10 if quick else 100)
    un = args.unrolled_n or (400 if quick else 30625)
    uk = args.unrolled_k or (20 if quick else 300)
    repeats = args.repeats or (3 if quick else 21)
    unrolled_repeats = max(3, repeats // 4)
    memory_ks = (uk,) if quick else (max(1, uk // 3), uk)
    default_threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        machine = {**machine_info(), "torch_default_threads": default_threads}
        t0 = time.perf_counter()
        over = bench_overhead(n, k, repeats, 2, ksp_type, pc_type)
        logger.info("overhead %.4f", over["overhead"])
        small = bench_throughput(4851, 10, (1, 32), max(3, repeats), 2, ksp_type, pc_type)
        unr = bench_unrolled(un, uk, unrolled_repeats, 1, ksp_type, pc_type, memory_ks)
        wall = time.perf_counter() - t0
    finally:
        torch.set_num_threads(default_threads)
    peak = unr["peak_rss_increase_mb"]
    result = {
        "benchmark": "bridge",
        "n": over["n"],
        "k": k,
        "overhead": over["overhead"],
        "overhead_vs_raw_solve_transpose": over["overhead_vs_raw_solve_transpose"],
        "backward_over_forward_symmetric": over["backward_over_forward_symmetric"],
        "throughput": {
            "n": small["n"],
            "k": small["k"],
            "overhead_1_rhs": small["batches"]["1"]["overhead"],
            "overhead_32_rhs": small["batches"]["32"]["overhead"],
            "floor_1_rhs": small["batches"]["1"]["floor"],
            "floor_32_rhs": small["batches"]["32"]["floor"],
            "extra_per_call_s": small["extra_per_call_s"],
            "extra_per_rhs_s": small["extra_per_rhs_s"],
        },
        "unrolled_n": unr["n"],
        "unrolled_k": uk,
        "unrolled_speedup": unr["unrolled_speedup"],
        "handwritten_unrolled_speedup": unr.get("handwritten_speedup"),
        "implicit_peak_rss_mb": peak["implicit"][str(uk)],
        "unrolled_peak_rss_mb": peak["unrolled"][str(uk)],
        "handwritten_peak_rss_mb": peak.get("handwritten", {}).get(str(uk)),
        "peak_memory_method": unr["peak_memory_method"],
        "implicit_traced_peak_vectors": over["traced_peak"]["vectors"],
        "timing_noise": over["timing_noise"],
        "targets": {
            "overhead": "<= 0.05 (like-for-like: raw KSPSolve + KSPSolve)",
            "throughput.overhead_1_rhs": "<= 0.25",
            "throughput.overhead_32_rhs": "<= 0.10",
            "backward_over_forward_symmetric": "<= 1.1",
            "unrolled_speedup": ">= 20",
        },
        "settings": {
            "ksp_type": ksp_type,
            "pc_type": pc_type,
            "rtol": 0.0,
            "atol": 0.0,
            "mode": "fixed (rtol = atol = 0: exactly K iterations)",
            "gradients": {"overhead": ["b", "theta"], "unrolled": ["b"]},
            "repeats": repeats,
            "warmup": 2,
            "unrolled_repeats": unrolled_repeats,
            "unrolled_warmup": 1,
            "statistic": "median over repeats of the ratio within each repeat; variants "
            "interleaved, order alternating per repeat",
            "clock": "time.perf_counter",
            "torch_threads": args.threads,
            "quick": quick,
        },
        "overhead_detail": over,
        "throughput_detail": small,
        "unrolled_detail": unr,
        "machine": machine,
        "wall_s": wall,
    }
    result["machine"]["load_average_end"] = load_average()
    write_result(args.out, "bench_bridge.json", result)
    return 0


# -- the page of a recorded ``bench bridge`` -----------------------------------------------------
def _signed(value: float) -> str:
    return f"{value:+.3f}"


def _rows(d: dict) -> list[tuple[str, str, str]]:
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


def _settings(ds: DataSet) -> str:
    d = ds.main
    s = d["settings"]
    return (
        f"`{s['ksp_type']}` + `{s['pc_type']}`, {s['mode']}; torch threads "
        f"{s['torch_threads']}; every ratio is the {s['statistic']} ({s['repeats']} "
        f"repeats after {s['warmup']} warm-up); timing noise (interquartile range over "
        f"median of the raw forward time) {d['timing_noise']:.3f}."
    )


def _headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
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


KIND = ReportKind(
    name="bench",
    reads="bench_bridge.json",
    title=lambda ds: "Bridge benchmark",
    headline=_headline,
    intro=_settings,
    output=lambda ds: markdown_table(["figure", "measured", "target"], _rows(ds.main), "lrl"),
    printed=False,
    after=lambda ds: [
        "What the rows mean is in the docstring of `prdp_petsc.lab.reports.bench`; every "
        "single timing is in the JSON."
    ],
)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    sys.exit(main(sys.argv[1:]))
