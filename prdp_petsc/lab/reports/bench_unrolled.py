"""Implicit PETSc gradients against torch-unrolled CG: time and peak memory at K.

Part of ``prdp-petsc bench bridge`` (see `prdp_petsc.lab.reports.bench`).  Three ways to get
``∂L/∂b`` through K steps of Jacobi-preconditioned CG on the five-point ``−Δ``:

``implicit``
    ``solve(..., mode="implicit")``: PETSc ``KSPSolve`` + ``KSPSolveTranspose``.
``unrolled``
    ``solve(..., mode="unrolled")``: the iteration in torch under autograd.
``handwritten``
    The same CG loop written by hand in torch, with a matrix product whose
    backward uses a transpose stored once (a fair baseline for ``unrolled``).

Only b carries a gradient (the project's target: implicit ≥ 20× faster than
unrolled at K = 300, peak memory independent of K); ``mode="unrolled"`` also
differentiates θ, through `prdp_petsc.autograd.unrolled.UnrolledOperator`.  Peak memory is
the growth of the resident set over one forward + backward in a fresh subprocess,
so nothing the parent process allocated before can hide it.
"""

from __future__ import annotations

import gc
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

from .memory import peak_rss_mb, reset_peak, rss_mb

__all__ = ["bench_unrolled", "handwritten_unrolled_cg", "unrolled_problem"]

PREFIX = "bench_"


def bench_solver(ksp_type: str, pc_type: str, k: int):
    """The benchmarks' `KSPSolver`: fixed mode (rtol = atol = 0), prefix ``bench_``."""
    from prdp_petsc import KSPSolver

    return KSPSolver({"ksp_type": ksp_type, "pc_type": pc_type}, prefix=PREFIX, max_it=k)


def ksp_types(solver) -> list[str]:
    """``[ksp_type, pc_type]`` as PETSc reports them for the forward KSP."""
    return [solver.ksp.getType(), solver.ksp.getPC().getType()]


def unrolled_problem(n: int, seed: int = 1):
    """(A, b, g, side): the SPD five-point ``−Δ`` on a side × side grid, side ≈ √n."""
    from prdp_petsc.fem.fd import laplacian

    side = max(2, round(float(np.sqrt(n))))
    A = (-laplacian((side, side))).tocsr()
    rng = np.random.default_rng(seed)
    return A, rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0]), side


def bench_unrolled(
    n: int,
    k: int,
    repeats: int,
    warmup: int,
    ksp_type: str,
    pc_type: str,
    memory_ks: tuple[int, ...] | None = None,
):
    """Time mode="unrolled" and a hand-written unrolled CG against mode="implicit".

    Peak memory is measured at every K in `memory_ks` (default ``(K // 3, K)``).
    """
    import torch

    A, b_np, g_np, side = unrolled_problem(n)
    solver = bench_solver(ksp_type, pc_type, k)
    b = torch.tensor(b_np, requires_grad=True)
    g = torch.tensor(g_np)
    modes = ["implicit", "unrolled"] + (
        ["handwritten"] if _handwritten_ok(ksp_type, pc_type) else []
    )
    t = {f"{mode}_{part}": [] for mode in modes for part in ("fwd", "bwd")}
    grads = {}
    for i in range(warmup + repeats):
        for mode in modes if i % 2 == 0 else modes[::-1]:
            b.grad = None
            t0 = time.perf_counter()
            x = _unrolled_mode_solve(mode, A, b, solver, pc_type)
            t1 = time.perf_counter()
            x.backward(g)
            t2 = time.perf_counter()
            if i >= warmup:
                t[f"{mode}_fwd"].append(t1 - t0)
                t[f"{mode}_bwd"].append(t2 - t1)
            grads[mode] = b.grad.numpy().copy()
            del x
    med = {key: statistics.median(v) for key, v in t.items()}
    total = {mode: med[f"{mode}_fwd"] + med[f"{mode}_bwd"] for mode in modes}
    per_repeat = {mode: np.add(t[f"{mode}_fwd"], t[f"{mode}_bwd"]) for mode in modes}

    def speedup(mode: str) -> float:  # median over repeats of the paired ratio
        return float(np.median(per_repeat[mode] / per_repeat["implicit"]))

    spec = {"n": n, "ksp_type": ksp_type, "pc_type": pc_type, "threads": torch.get_num_threads()}
    ks = sorted(set(memory_ks or (max(1, k // 3), k)) | {k})
    peak = peak_rss_increase([{**spec, "k": kk, "mode": mode} for mode in modes for kk in ks])
    out = {
        "problem": f"-laplacian({side}x{side}), 5-point FD, Dirichlet; gradient wrt b",
        "n": int(A.shape[0]),
        "nnz": int(A.nnz),
        "k": k,
        "unrolled_speedup": speedup("unrolled"),
        "statistic": "median over repeats of the ratio within each repeat (paired)",
        "seconds": total,
        "peak_rss_increase_mb": peak,
        "peak_memory_method": _MEMORY_METHOD,
        "median_s": med,
        "timings_s": t,
        "ksp": ksp_types(solver),
    }
    if "handwritten" in modes:
        ref = np.abs(grads["unrolled"]).max()
        out["handwritten_speedup"] = speedup("handwritten")
        out["handwritten_grad_rel_diff"] = float(
            np.abs(grads["handwritten"] - grads["unrolled"]).max() / ref
        )
        out["handwritten_note"] = (
            "the same preconditioned CG loop written by hand in torch, with an autograd "
            "SpMV whose backward multiplies by a precomputed transpose CSR (mode='unrolled' "
            "does the same through UnrolledOperator, plus PETSc's convergence test)"
        )
    return out


def _handwritten_ok(ksp_type: str, pc_type: str) -> bool:
    return ksp_type == "cg" and pc_type in ("jacobi", "none")


def _unrolled_mode_solve(mode: str, A, b, solver, pc_type: str):
    from prdp_petsc import solve

    if mode == "handwritten":
        return handwritten_unrolled_cg(A, b, solver.max_it, jacobi=pc_type == "jacobi")
    return solve(A, b, solver, mode=mode)


def _torch_csr(M):
    import warnings

    import torch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(
            torch.from_numpy(M.indptr.astype(np.int64)),
            torch.from_numpy(M.indices.astype(np.int64)),
            torch.from_numpy(M.data.astype(np.float64)),
            size=M.shape,
            check_invariants=False,
        )


def handwritten_unrolled_cg(A, b, k: int, *, jacobi: bool = True):
    """K steps of (Jacobi-)preconditioned CG from x = 0 in torch, for a fair baseline.

    The iteration of ``mode="unrolled"``; the matrix product is an autograd
    function whose backward multiplies by ``Aᵀ`` stored once as CSR.
    """
    import torch

    class SpMV(torch.autograd.Function):
        @staticmethod
        def forward(ctx, p):
            return A_t @ p

        @staticmethod
        def backward(ctx, grad):
            return At_t @ grad

    A = A.tocsr()
    A_t, At_t = _torch_csr(A), _torch_csr(A.T.tocsr())
    inv_m = torch.from_numpy(1.0 / A.diagonal()) if jacobi else torch.ones(A.shape[0])
    x = torch.zeros_like(b)
    r = b
    z = inv_m * r
    p = z
    rho = r @ z
    for _ in range(k):
        q = SpMV.apply(p)
        alpha = rho / (p @ q)
        x = x + alpha * p
        r = r - alpha * q
        z = inv_m * r
        rho_new = r @ z
        p = z + (rho_new / rho) * p
        rho = rho_new
    return x


_MEMORY_METHOD = (
    "fresh subprocess per (mode, K) with glibc MALLOC_MMAP_THRESHOLD_=65536 (freed large "
    "buffers leave the resident set at once, so the figure is reproducible): build the "
    "problem, one warm-up forward+backward at K=1, gc + malloc_trim, reset the high-water "
    "mark (/proc/self/clear_refs = 5), then one forward+backward at K; value = VmHWM - "
    "VmRSS before it, in MiB (without /proc: ru_maxrss delta)"
)


# glibc: fixed mmap threshold, so that freed large buffers leave the resident set at
# once and the high-water mark is the peak of live memory, not of allocator history
_MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "65536", "MALLOC_TRIM_THRESHOLD_": "131072"}


def peak_rss_increase(specs: list[dict]) -> dict:
    """``{mode: {K: MiB}}``: peak RSS growth of each spec, each in its own subprocess.

    The subprocesses run side by side (each measures only itself) after the timings.
    """
    code = (
        "import sys; from prdp_petsc.lab.reports.bench_unrolled import _peak_rss_child as f; "
        "f(sys.argv[1])"
    )
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
    import ctypes

    import torch

    spec = json.loads(spec_json)
    torch.set_num_threads(int(spec["threads"]))
    A, b_np, g_np, _ = unrolled_problem(int(spec["n"]))
    solver = bench_solver(spec["ksp_type"], spec["pc_type"], 1)
    b = torch.tensor(b_np, requires_grad=True)
    g = torch.tensor(g_np)
    mode, pc = spec["mode"], spec["pc_type"]
    _unrolled_mode_solve(mode, A, b, solver, pc).backward(g)  # warm-up: setups, autograd
    solver.max_it = int(spec["k"])
    b.grad = None
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass
    base = rss_mb() if reset_peak() else None  # without /proc: the growth of the peak
    before = peak_rss_mb()
    _unrolled_mode_solve(mode, A, b, solver, pc).backward(g)
    peak_mb = peak_rss_mb() - (base if base is not None else before)
    print(json.dumps({"peak_mb": peak_mb}))
