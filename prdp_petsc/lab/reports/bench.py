"""Benchmark of the torch bridge: overhead over raw PETSc, throughput, unrolled CG.

``prdp-petsc bench bridge --out DIR`` writes ``DIR/bench_bridge.json`` (``bench mpi``,
``elasticity`` and ``gpu`` run their own modules, ``jax`` is ``gpu`` on the CPU at
other sizes), all from one run:

``overhead`` (the headline)
    Bridge forward + backward (``solve(A, b, solver, theta=θ)``, then ``x.backward(g)``,
    gradients in b and θ) over what the bridge runs in PETSc for this symmetric operator
    and PC, raw petsc4py ``KSPSolve`` + ``KSPSolve`` on the same Mat, KSP/PC and K,
    minus 1; on `plate_reaction` at about ``--n`` unknowns.  ``overhead_detail`` adds
    the ratio against ``KSPSolve`` + ``KSPSolveTranspose`` (what a non-symmetric
    operator runs), the gradient in b only, the time outside KSPSolve, and the traced
    peak memory of one forward + backward in vectors of n (`traced_peaks`).
``throughput``
    Small systems (n ≈ 5 000, K = 10), gradient in b, 1 and 32 right-hand sides: the
    bridge over the raw loops, the floor of any torch bridge (the raw loops in a bare
    ``torch.autograd.Function``), and from ``bridge − raw = c₀ + c₁ B`` the bridge's
    fixed cost per call c₀ and per right-hand side c₁.
``backward_over_forward_symmetric``
    Bridge backward time over forward time at equal K (the adjoint is a forward solve).
``unrolled_speedup``
    ``mode="unrolled"`` and a hand-written torch CG over ``mode="implicit"``, forward +
    backward at K = 300 on `five_point` (175 × 175), gradient in b, with the peak
    resident-set growth of each in a fresh subprocess.

Every ratio is a paired median (`prdp_petsc.lab.reports.benchmarking.paired`); ``timing_noise``
says how busy the machine was, and every timing is in the JSON; they describe one
machine, never assert them.  torch runs on ``--threads`` (default 1: PETSc's AIJ kernels
are serial).  Targets: overhead ≤ 5 % at about 1e5 unknowns; small systems ≤ 25 % for
one right-hand side and ≤ 10 % for 32; backward / forward ≤ 1.1; unrolled ≥ 20×.

Notes
-----
The KSPs have options prefix ``bench_``: ``PETSC_OPTIONS=-bench_ksp_view`` reaches the
bridge's KSP (the raw KSP is set up from ``--routes KSP/PC`` only, and the run stops if
the two types differ).  ``--preset quick`` runs tiny sizes (a smoke test).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import subprocess
import sys
import tracemalloc

import numpy as np

from ..cli.arguments import (
    add_debug,
    add_k,
    add_out,
    add_size_preset,
    add_threads,
    positive,
    routes,
)
from ..components.emulators import torch_csr
from ..provenance import load_average, machine_info, write_result
from ..training.threads import torch_threads
from . import bench_elasticity, bench_gpu, bench_jax, bench_mpi
from . import benchmarking as bm
from .kinds import DataSet, ReportKind, markdown_table
from .memory import peak_rss_mb, reset_peak, rss_mb
from .problems import five_point, plate_reaction

__all__ = ["KIND", "main"]

RAW_KEYS = ("raw_forward", "raw_transpose", "raw_adjoint_as_solve")
MODES = ("implicit", "unrolled", "handwritten")
HEADLINE_KEYS = ("overhead", "overhead_vs_raw_solve_transpose", "backward_over_forward_symmetric")


def bench_overhead(n: int, k: int, repeats: int, warmup: int, ksp_type: str, pc_type: str):
    """Time the bridge against raw petsc4py on the same Mat; return a JSON-ready dict."""
    import torch

    from prdp_petsc import solve

    A, theta_np, b_np, g_np, refine = plate_reaction(n)
    solver = bm.bench_solver(ksp_type, pc_type, k)
    theta = torch.tensor(theta_np, requires_grad=True)
    b = torch.tensor(b_np, requires_grad=True)
    g = torch.tensor(g_np)
    solve(A, b, solver, theta=theta).backward(g)  # creates the Mat and both KSPs
    raw = bm.raw_ksp(solver.mat, ksp_type, pc_type, k)
    x_vec, b_vec = solver.mat.createVecs()
    lam_vec, g_vec = x_vec.duplicate(), b_vec.duplicate()
    b_vec.array[:] = b_np
    g_vec.array[:] = g_np
    raw_calls = ((raw.solve, b_vec, x_vec), (raw.solveTranspose, g_vec, lam_vec),
                 (raw.solve, g_vec, lam_vec))  # fmt: skip

    def raw_step() -> dict:
        times = {}
        for key, (op, rhs, sol) in zip(RAW_KEYS, raw_calls, strict=True):
            sol.set(0.0)
            _, times[key] = bm.stopwatch(op, rhs, sol)
            if raw.getIterationNumber() != k:
                raise RuntimeError(f"raw KSP ran {raw.getIterationNumber()} iterations, not {k}")
        return times

    def bridge_step(key: str, th):
        def step() -> dict:
            theta.grad = b.grad = None
            f0, a0 = solver.stats.forward_time, solver.stats.adjoint_time
            x, forward = bm.stopwatch(solve, A, b, solver, theta=th)
            _, backward = bm.stopwatch(x.backward, g)
            times = {f"{key}_forward": forward, f"{key}_backward": backward}
            if key == "bridge":
                times["bridge_forward_ksp"] = solver.stats.forward_time - f0
                times["bridge_backward_ksp"] = solver.stats.adjoint_time - a0
            return times

        return step

    steps = {"raw": raw_step, "bridge": bridge_step("bridge", theta),
             "b_only": bridge_step("bridge_b_only", theta.detach())}  # fmt: skip
    t = bm.interleaved(steps, repeats, warmup)
    bm.check_exactly_k(solver, k)
    if bm.ksp_types(solver) != [raw.getType(), raw.getPC().getType()]:
        raise RuntimeError(f"bridge KSP is {bm.ksp_types(solver)}, raw is {raw.getType()}")
    r = {key: np.asarray(v) for key, v in t.items()}  # one entry per repeat
    bridge = r["bridge_forward"] + r["bridge_backward"]
    raw_pair = r["raw_forward"] + r["raw_adjoint_as_solve"]
    raw_transpose = r["raw_forward"] + r["raw_transpose"]
    b_only = r["bridge_b_only_forward"] + r["bridge_b_only_backward"]
    return {
        "problem": f"plate_holes refine={refine}, P1, -div(kappa grad u) + u, kappa P0",
        "n": int(A.shape[0]),
        "nnz": int(A.nnz),
        "n_params": int(A.n_params),
        "k": k,
        "statistic": bm.STATISTIC,
        "overhead": bm.paired(bridge, raw_pair) - 1.0,
        "backward_over_forward_symmetric": bm.paired(r["bridge_backward"], r["bridge_forward"]),
        "overhead_vs_raw_solve_transpose": bm.paired(bridge, raw_transpose) - 1.0,
        "overhead_b_only": bm.paired(b_only, raw_pair) - 1.0,
        "raw_transpose_over_forward": bm.paired(r["raw_transpose"], r["raw_forward"]),
        "bridge_outside_ksp_s": {
            side: float(np.median(r[f"bridge_{side}"] - r[f"bridge_{side}_ksp"]))
            for side in ("forward", "backward")
        },
        "timing_noise": bm.summary(t["raw_forward"])["noise"],
        "median_s": {key: float(np.median(v)) for key, v in t.items()},
        "timings_s": t,
        "ksp": {"raw": [raw.getType(), raw.getPC().getType()], "bridge": bm.ksp_types(solver)},
        "traced_peak": traced_peaks(A, b, theta, g, solver),
    }


def traced_peaks(A, b, theta, g, solver) -> dict:
    """Peak traced memory of one forward + backward on the library's own operator (a
    `ParametricMatrix`), in vectors of n doubles: gradient in b only, in b and θ, and
    in b and θ with a new θ every call (whose values A(θ), nnz of them, are new too)."""
    import torch

    from prdp_petsc import solve

    fresh = [theta.detach() * (1.0 + 1e-3 * i) for i in range(4)]

    def call(th):
        b.grad = th.grad = None
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
            out[name] = (tracemalloc.get_traced_memory()[1] - base) / (8.0 * A.shape[0])
        finally:
            tracemalloc.stop()
    with torch.no_grad():
        solve(A, b, solver, theta=theta)  # leave the solver on the benchmark's θ
    return {
        "vectors": out,
        "n": int(A.shape[0]),
        "nnz_over_n": A.nnz / A.shape[0],
        "n_params_over_n": A.n_params / A.shape[0],
        "method": "tracemalloc (numpy and torch-from-numpy allocations; PETSc's own are "
        "not traced, its work vectors are made once per operator), after a warm-up call "
        "of the same kind: peak over one forward + backward minus the memory before it",
    }


def bench_throughput(n, k, batches, repeats, warmup, ksp_type, pc_type) -> dict:
    """Time the bridge, the raw petsc4py loops and a bare `torch.autograd.Function`
    around them, gradient in b, for each batch size; return a JSON-ready dict."""
    import torch

    import prdp_petsc as pp

    A, theta_np, _, _, refine = plate_reaction(n)
    rhs, cot = np.random.default_rng(2).standard_normal((2, max(batches), A.shape[0]))
    solver = bm.bench_solver(ksp_type, pc_type, k)
    theta = torch.tensor(theta_np)
    pp.solve(A, torch.tensor(rhs[0], requires_grad=True), solver, theta=theta).sum().backward()
    raw = bm.raw_ksp(solver.mat, ksp_type, pc_type, k)
    x_vec, b_vec = solver.mat.createVecs()

    def raw_rows(rows: np.ndarray) -> np.ndarray:
        out = np.empty_like(rows)
        for row, x in zip(rows, out, strict=True):
            b_vec.setArray(row)
            x_vec.set(0.0)
            raw.solve(b_vec, x_vec)
            x[:] = x_vec.getArray(readonly=True)
        return out

    class Bare(torch.autograd.Function):
        @staticmethod
        def forward(ctx, b):
            return torch.from_numpy(raw_rows(b.detach().numpy()))

        @staticmethod
        def backward(ctx, g):
            return torch.from_numpy(raw_rows(g.detach().numpy()))

    def steps(B: int) -> dict:
        def through_torch(fn):
            def step() -> float:
                b, g = torch.tensor(rhs[:B], requires_grad=True), torch.tensor(cot[:B])
                return bm.stopwatch(lambda: fn(b).backward(g))[1]

            return step

        return {
            "raw": lambda: bm.stopwatch(lambda: (raw_rows(rhs[:B]), raw_rows(cot[:B])))[1],
            "bridge": through_torch(lambda b: pp.solve(A, b, solver, theta=theta)),
            "wrapper": through_torch(Bare.apply),
        }

    out: dict = {
        "problem": f"plate_holes refine={refine}, P1, -div(kappa grad u) + u, kappa P0",
        "n": int(A.shape[0]),
        "k": k,
        "gradient": "b (theta constant)",
        "raw": "B x (KSPSolve + KSPSolve), petsc4py loop, same Mat, same KSP/PC",
        "wrapper": "the raw loops in a bare torch.autograd.Function (no checks)",
        "batches": {},
    }
    for B in batches:
        t = bm.interleaved(steps(B), repeats, warmup)
        out["batches"][str(B)] = {
            "overhead": bm.paired(t["bridge"], t["raw"]) - 1.0,
            "floor": bm.paired(t["wrapper"], t["raw"]) - 1.0,
            "raw_s": float(np.median(t["raw"])),
            "bridge_s": float(np.median(t["bridge"])),
            "timings_s": t,
        }
    bm.check_exactly_k(solver, k)
    if raw.getIterationNumber() != k:
        raise RuntimeError(f"raw KSP ran {raw.getIterationNumber()} iterations, not {k}")
    lo, hi = min(batches), max(batches)
    if lo != hi:  # bridge − raw = c₀ + c₁ B
        extra = {B: out["batches"][str(B)]["bridge_s"] - out["batches"][str(B)]["raw_s"]
                 for B in (lo, hi)}  # fmt: skip
        out["extra_per_rhs_s"] = (extra[hi] - extra[lo]) / (hi - lo)
        out["extra_per_call_s"] = extra[lo] - out["extra_per_rhs_s"] * lo
    for obj in (raw, x_vec, b_vec, solver):
        obj.destroy()
    return out


def bench_unrolled(n, k, repeats, warmup, ksp_type, pc_type, memory_ks) -> dict:
    """Time ``mode="unrolled"`` and `handwritten_unrolled_cg` against ``mode="implicit"``
    (gradient in b) on `five_point` of about n unknowns, and measure the peak memory
    of each at every K in `memory_ks`."""
    import torch

    A, b_np, g_np = five_point(max(2, round(float(np.sqrt(n)))), seed=1)
    solver = bm.bench_solver(ksp_type, pc_type, k)
    b, g = torch.tensor(b_np, requires_grad=True), torch.tensor(g_np)
    handwritten = ksp_type == "cg" and pc_type in ("jacobi", "none")
    modes = MODES if handwritten else MODES[:2]
    grads = {}

    def step(mode: str):
        def timed() -> dict:
            b.grad = None
            x, forward = bm.stopwatch(_mode_solve, mode, A, b, solver, pc_type)
            _, backward = bm.stopwatch(x.backward, g)
            grads[mode] = b.grad.numpy().copy()
            return {f"{mode}_fwd": forward, f"{mode}_bwd": backward}

        return timed

    t = bm.interleaved({mode: step(mode) for mode in modes}, repeats, warmup)
    total = {mode: np.add(t[f"{mode}_fwd"], t[f"{mode}_bwd"]) for mode in modes}
    spec = {"n": n, "ksp_type": ksp_type, "pc_type": pc_type, "threads": torch.get_num_threads()}
    ks = sorted(set(memory_ks) | {k})
    side = round(float(np.sqrt(A.shape[0])))
    out = {
        "problem": f"-laplacian({side}x{side}), 5-point FD, Dirichlet; gradient wrt b",
        "n": int(A.shape[0]),
        "nnz": int(A.nnz),
        "k": k,
        "unrolled_speedup": bm.paired(total["unrolled"], total["implicit"]),
        "statistic": bm.STATISTIC,
        "peak_rss_increase_mb": peak_rss_increase(
            [{**spec, "k": kk, "mode": mode} for mode in modes for kk in ks]
        ),
        "peak_memory_method": MEMORY_METHOD,
        "median_s": {key: float(np.median(v)) for key, v in t.items()},
        "timings_s": t,
        "ksp": bm.ksp_types(solver),
    }
    if handwritten:
        out["handwritten_speedup"] = bm.paired(total["handwritten"], total["implicit"])
        diff = np.abs(grads["handwritten"] - grads["unrolled"]).max()
        out["handwritten_grad_rel_diff"] = float(diff / np.abs(grads["unrolled"]).max())
    return out


def _mode_solve(mode: str, A, b, solver, pc_type: str):
    from prdp_petsc import solve

    if mode == "handwritten":
        return handwritten_unrolled_cg(A, b, solver.max_it, jacobi=pc_type == "jacobi")
    return solve(A, b, solver, mode=mode)


def handwritten_unrolled_cg(A, b, k: int, *, jacobi: bool = True):
    """K steps of (Jacobi-)preconditioned CG from x = 0 in torch, the iteration of
    ``mode="unrolled"``, through a matrix product whose backward multiplies by ``Aᵀ``
    stored once as CSR: a fair baseline for it."""
    import torch

    A = A.tocsr()
    A_t, At_t = torch_csr(A), torch_csr(A.T)

    class SpMV(torch.autograd.Function):
        @staticmethod
        def forward(ctx, p):
            return A_t @ p

        @staticmethod
        def backward(ctx, grad):
            return At_t @ grad

    inv_m = torch.from_numpy(1.0 / A.diagonal()) if jacobi else torch.ones(A.shape[0])
    x, r = torch.zeros_like(b), b
    p = z = inv_m * r
    rho = r @ z
    for _ in range(k):
        q = SpMV.apply(p)
        alpha = rho / (p @ q)
        x, r = x + alpha * p, r - alpha * q
        z = inv_m * r
        rho, rho_old = r @ z, rho
        p = z + (rho / rho_old) * p
    return x


MEMORY_METHOD = (
    "fresh subprocess per (mode, K) with glibc MALLOC_MMAP_THRESHOLD_=65536 (freed large "
    "buffers leave the resident set at once, so the figure is reproducible): build the "
    "problem, one warm-up forward+backward at K=1, gc + malloc_trim, reset the high-water "
    "mark (/proc/self/clear_refs = 5), then one forward+backward at K; value = VmHWM - "
    "VmRSS before it, in MiB (without /proc: ru_maxrss delta)"
)
_MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "65536", "MALLOC_TRIM_THRESHOLD_": "131072"}


def peak_rss_increase(specs: list[dict]) -> dict:
    """``{mode: {K: MiB}}``: peak resident-set growth of each spec, each in its own
    subprocess, all side by side (each measures only itself)."""
    code = f"import sys; from {__name__} import _peak_rss_child as f; f(sys.argv[1])"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code, json.dumps(spec)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "OMP_NUM_THREADS": str(spec["threads"]), **_MALLOC_ENV},
        )
        for spec in specs
    ]
    peak: dict = {}
    for spec, proc in zip(specs, procs, strict=True):
        stdout, stderr = proc.communicate()
        if proc.returncode:
            raise RuntimeError(f"peak-memory subprocess {spec} failed:\n{stderr}")
        mb = float(json.loads(stdout.strip().splitlines()[-1])["peak_mb"])
        peak.setdefault(spec["mode"], {})[str(spec["k"])] = mb
    return peak


def _peak_rss_child(spec_json: str) -> None:
    """Subprocess body: peak resident-set growth of one forward+backward, printed as JSON."""
    import torch

    spec = json.loads(spec_json)
    torch.set_num_threads(int(spec["threads"]))
    A, b_np, g_np = five_point(max(2, round(float(np.sqrt(int(spec["n"]))))), seed=1)
    solver = bm.bench_solver(spec["ksp_type"], spec["pc_type"], 1)
    b, g = torch.tensor(b_np, requires_grad=True), torch.tensor(g_np)
    mode, pc = spec["mode"], spec["pc_type"]
    _mode_solve(mode, A, b, solver, pc).backward(g)  # warm-up: set-ups, autograd
    solver.max_it = int(spec["k"])
    b.grad = None
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass
    base = rss_mb() if reset_peak() else peak_rss_mb()  # without /proc: the peak's growth
    _mode_solve(mode, A, b, solver, pc).backward(g)
    print(json.dumps({"peak_mb": peak_rss_mb() - base}))


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="prdp-petsc bench", description=__doc__.split("\n")[0])
    p.add_argument(
        "which",
        choices=["bridge", "mpi", "elasticity", "jax", "gpu"],
        help="benchmark to run (mpi: bench_mpi, elasticity: bench_elasticity, gpu: bench_gpu, "
        "jax: bench gpu on the CPU at the JAX comparison's sizes)",
    )
    add_out(p, "folder for bench_<which>.json")
    add_size_preset(p, "tiny sizes (a smoke test)")
    p.add_argument(
        "--n", type=positive, help="overhead problem size, rounded to a plate_holes refinement"
    )
    add_k(p, None, "K of the overhead problem (default 100)")
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
    add_threads(p)
    add_debug(p)
    return p


def _route(text: str) -> tuple[str, str]:
    """``--routes KSP/PC``: one plain pair (the raw KSP compared with has the same types)."""
    pairs = routes(text)
    if len(pairs) != 1 or pairs[0].count("/") != 1 or ":" in pairs[0]:
        message = f"expected one KSP/PC pair such as cg/jacobi, got {text!r}"
        raise argparse.ArgumentTypeError(message)
    ksp_type, pc_type = pairs[0].split("/")
    return ksp_type, pc_type


def main(argv: list[str]) -> int:
    """Run ``bench WHICH``; ``bench bridge`` writes ``<out>/bench_bridge.json``."""
    others = {"mpi": bench_mpi, "elasticity": bench_elasticity, "jax": bench_jax, "gpu": bench_gpu}
    if argv and argv[0] in others:
        return others[argv[0]].main(argv[1:])
    args = _parser().parse_args(argv)
    ksp_type, pc_type = args.routes
    import torch

    quick = args.preset == "quick"
    n = args.n or (4851 if quick else 75018)
    k = args.k or (10 if quick else 100)
    un = args.unrolled_n or (400 if quick else 30625)
    uk = args.unrolled_k or (20 if quick else 300)
    repeats = args.repeats or (3 if quick else 21)
    unrolled_repeats = max(3, repeats // 4)
    memory_ks = (uk,) if quick else (max(1, uk // 3), uk)
    machine = {**machine_info(), "torch_default_threads": torch.get_num_threads()}
    with torch_threads(args.threads):
        (over, small, unr), wall = bm.stopwatch(
            lambda: (
                bench_overhead(n, k, repeats, 2, ksp_type, pc_type),
                bench_throughput(4851, 10, (1, 32), max(3, repeats), 2, ksp_type, pc_type),
                bench_unrolled(un, uk, unrolled_repeats, 1, ksp_type, pc_type, memory_ks),
            )
        )
    peak = unr["peak_rss_increase_mb"]
    batches = small["batches"]
    result = {
        "benchmark": "bridge",
        "n": over["n"],
        "k": k,
        **{key: over[key] for key in HEADLINE_KEYS},
        "throughput": {
            "n": small["n"],
            "k": small["k"],
            **{f"{key}_{B}_rhs": batches[B][key] for key in ("overhead", "floor") for B in batches},
            "extra_per_call_s": small["extra_per_call_s"],
            "extra_per_rhs_s": small["extra_per_rhs_s"],
        },
        "unrolled_n": unr["n"],
        "unrolled_k": uk,
        "unrolled_speedup": unr["unrolled_speedup"],
        "handwritten_unrolled_speedup": unr.get("handwritten_speedup"),
        **{f"{mode}_peak_rss_mb": peak.get(mode, {}).get(str(uk)) for mode in MODES},
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
            "statistic": bm.STATISTIC,
            "clock": "time.perf_counter",
            "torch_threads": args.threads,
            "quick": quick,
        },
        "overhead_detail": over,
        "throughput_detail": small,
        "unrolled_detail": unr,
        "machine": {**machine, "load_average_end": load_average()},
        "wall_s": wall,
    }
    write_result(args.out, "bench_bridge.json", result)
    return 0


# -- the page of a recorded ``bench bridge`` -----------------------------------------------------
def _signed(value: float) -> str:
    return f"{value:+.3f}"


def _rows(d: dict) -> list[tuple[str, str, str]]:
    t, target = d["throughput"], d.get("targets", {})
    rows = [
        (f"overhead: bridge forward + backward (gradients for b and θ) over raw `KSPSolve` + "
         f"`KSPSolve`, − 1; n = {d['n']}, K = {d['k']}", _signed(d["overhead"]),
         target.get("overhead", "")),
        ("same, over raw `KSPSolve` + `KSPSolveTranspose`",
         _signed(d["overhead_vs_raw_solve_transpose"]), ""),
        ("backward over forward (symmetric: the adjoint runs as a forward solve)",
         f"{d['backward_over_forward_symmetric']:.2f}",
         target.get("backward_over_forward_symmetric", "")),
        (f"small systems (n = {t['n']}, K = {t['k']}), gradient in b: 1 right-hand side",
         _signed(t["overhead_1_rhs"]), target.get("throughput.overhead_1_rhs", "")),
        ("same, a batch of 32 right-hand sides", _signed(t["overhead_32_rhs"]),
         target.get("throughput.overhead_32_rhs", "")),
    ]  # fmt: skip
    if "floor_1_rhs" in t:  # recorded since the bare-wrapper variant exists
        rows.append(("floor of any torch bridge: the raw loops in a bare "
                     "`torch.autograd.Function` (no checks), 1 / 32 right-hand sides",
                     f"{_signed(t['floor_1_rhs'])} / {_signed(t['floor_32_rhs'])}",
                     ""))  # fmt: skip
    rows += [
        ("bridge's extra cost per call / per right-hand side",
         f"{t['extra_per_call_s'] * 1e6:.0f} µs / {t['extra_per_rhs_s'] * 1e6:.0f} µs", ""),
        (f'`mode="unrolled"` CG over PETSc implicit, n = {d["unrolled_n"]}, '
         f"K = {d['unrolled_k']}, forward + backward", f"{d['unrolled_speedup']:.1f}×",
         target.get("unrolled_speedup", "")),
    ]  # fmt: skip
    if d.get("handwritten_unrolled_speedup") is not None:
        rows.append(("same, against a hand-written torch CG",
                     f"{d['handwritten_unrolled_speedup']:.1f}×", ""))  # fmt: skip
    rows.append((f"peak memory increase at K = {d['unrolled_k']}: implicit / unrolled",
                 f"{d['implicit_peak_rss_mb']:.2f} MiB / {d['unrolled_peak_rss_mb']:.0f} MiB",
                 ""))  # fmt: skip
    if traced := d.get("implicit_traced_peak_vectors"):
        rows.append((f"traced peak of one forward + backward on the `ParametricMatrix` (n = "
                     f"{d['n']}), in vectors of n: gradient in b / in b and θ / new θ each call",
                     " / ".join(f"{traced[key]:.1f}" for key in ("b", "b_theta",
                                                                 "b_theta_new_theta")),
                     "b: a few vectors"))  # fmt: skip
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
