"""Small-system throughput of the bridge: fixed cost per call and per right-hand side.

Part of ``prdp-petsc bench bridge`` (see `prdp_petsc.lab.reports.bench`).  The
paper's small scenes solve thousands of small systems per epoch, so what the
bridge adds around ``KSPSolve`` matters there.  For a batch of B right-hand
sides on one operator (plate_holes P1, ``−∇·(κ∇u) + u``, κ per element, CG +
Jacobi in fixed mode, K iterations) it times

``raw``
    B times ``KSPSolve`` + ``KSPSolve`` in a petsc4py loop on the solver's own
    Mat (what the bridge runs for a symmetric operator with a symmetric PC);
``bridge``
    ``solve(A, b, solver, theta=θ)`` with b of shape (B, n), then
    ``x.backward(g)``; the gradient is taken in b only (θ constant), the usual
    case of an emulator whose operator does not change;
``wrapper``
    the floor of any torch bridge: the raw loops inside a bare
    ``torch.autograd.Function`` (forward solves b, backward solves g; no input
    check, no outcome check, no record), called as the bridge is.

``overhead = bridge / raw − 1`` is the median over repeats of the paired ratio,
``floor = wrapper / raw − 1`` likewise: what is left of the overhead above the floor
is the bridge's own work (input and outcome checks, the per-call record).
From B = 1 and B = B_max the difference ``bridge − raw = c₀ + c₁ B`` gives the
fixed cost per call c₀ and the cost per right-hand side c₁ of the bridge.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

__all__ = ["bench_throughput", "overhead_problem", "raw_ksp"]

# P1 unknowns of plate_holes: 4851 at refine 0, about 4x per refinement.
_PLATE_HOLES_N0 = 4851


def overhead_problem(n: int, seed: int = 0):
    """(A, θ, b, g, refine): plate_holes P1, κ per element plus unit reaction (SPD)."""
    import skfem

    from prdp_petsc import diffusion_operator, load_mesh

    refine = max(0, round(float(np.log(n / _PLATE_HOLES_N0) / np.log(4.0))))
    basis = skfem.Basis(load_mesh("plate_holes", refine=refine), skfem.ElementTriP1())
    A = diffusion_operator(basis, "P0", reaction=1.0)
    rng = np.random.default_rng(seed)
    theta = 1.0 + 0.5 * rng.random(A.n_params)
    return A, theta, rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0]), refine


def raw_ksp(mat, ksp_type: str, pc_type: str, k: int):
    """A bare petsc4py KSP on `mat` in fixed mode (K iterations), set up: the baseline."""
    from petsc4py import PETSc

    raw = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    raw.setType(ksp_type)
    raw.getPC().setType(pc_type)
    raw.setOperators(mat)
    raw.setTolerances(rtol=0.0, atol=0.0, max_it=k)
    raw.setUp()
    return raw


def bench_throughput(
    n: int,
    k: int,
    batches: tuple[int, ...],
    repeats: int,
    warmup: int,
    ksp_type: str,
    pc_type: str,
) -> dict:
    """Time the bridge against raw petsc4py loops for each batch size; JSON-ready dict."""
    import torch

    import prdp_petsc as pp

    A, theta_np, _, _, refine = overhead_problem(n)
    rng = np.random.default_rng(2)
    rhs = rng.standard_normal((max(batches), A.shape[0]))
    cot = rng.standard_normal((max(batches), A.shape[0]))
    solver = pp.KSPSolver({"ksp_type": ksp_type, "pc_type": pc_type}, prefix="bench_", max_it=k)
    theta = torch.tensor(theta_np)
    pp.solve(A, torch.tensor(rhs[0], requires_grad=True), solver, theta=theta).sum().backward()

    raw = raw_ksp(solver.mat, ksp_type, pc_type, k)
    x_vec, b_vec = solver.mat.createVecs()

    def raw_step(B: int) -> float:
        t0 = time.perf_counter()
        for rows in (rhs, cot):
            for row in rows[:B]:
                b_vec.setArray(row)
                x_vec.set(0.0)
                raw.solve(b_vec, x_vec)
                x_vec.getArray(readonly=True).copy()
        return time.perf_counter() - t0

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

    def wrapper_step(B: int) -> float:
        b = torch.tensor(rhs[:B], requires_grad=True)
        g = torch.tensor(cot[:B])
        t0 = time.perf_counter()
        Bare.apply(b).backward(g)
        return time.perf_counter() - t0

    def bridge_step(B: int) -> float:
        b = torch.tensor(rhs[:B], requires_grad=True)
        g = torch.tensor(cot[:B])
        t0 = time.perf_counter()
        pp.solve(A, b, solver, theta=theta).backward(g)
        return time.perf_counter() - t0

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
        t = {"raw": [], "bridge": [], "wrapper": []}
        for i in range(warmup + repeats):
            steps = (("raw", raw_step), ("bridge", bridge_step), ("wrapper", wrapper_step))
            for name, step in steps if i % 2 == 0 else steps[::-1]:
                dt = step(B)
                if i >= warmup:
                    t[name].append(dt)
        ratio = np.asarray(t["bridge"]) / np.asarray(t["raw"])
        floor = np.asarray(t["wrapper"]) / np.asarray(t["raw"])
        out["batches"][str(B)] = {
            "overhead": float(np.median(ratio) - 1.0),
            "floor": float(np.median(floor) - 1.0),
            "raw_s": statistics.median(t["raw"]),
            "bridge_s": statistics.median(t["bridge"]),
            "timings_s": t,
        }
    stats = solver.stats  # every bridge solve, forward and adjoint
    exact = stats.forward_iterations == k * stats.forward_solves
    if not exact or stats.adjoint_iterations != k * stats.adjoint_solves:
        raise RuntimeError("fixed mode did not run exactly K iterations")
    if raw.getIterationNumber() != k:
        raise RuntimeError("fixed mode did not run exactly K iterations")
    lo, hi = str(min(batches)), str(max(batches))
    if lo != hi:
        d = {B: out["batches"][B]["bridge_s"] - out["batches"][B]["raw_s"] for B in (lo, hi)}
        per_rhs = (d[hi] - d[lo]) / (int(hi) - int(lo))
        out["extra_per_rhs_s"] = per_rhs
        out["extra_per_call_s"] = d[lo] - per_rhs * int(lo)
    raw.destroy()
    x_vec.destroy()
    b_vec.destroy()
    solver.destroy()
    return out
