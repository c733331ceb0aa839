"""What every benchmark shares: interleaved timing, paired statistics, fixed-mode KSPs.

Variants run once per round, in alternating order (forward, then reversed), after
warm-up rounds, so that a neighbour's load on a shared machine hits both sides of a
ratio taken within one round; a figure is the median of those paired ratios.  The
KSPs run in fixed mode (``rtol = atol = 0``: exactly K iterations), so that every
variant does the same work.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

__all__ = [
    "PREFIX",
    "STATISTIC",
    "bench_solver",
    "check_exactly_k",
    "interleaved",
    "ksp_types",
    "paired",
    "raw_ksp",
    "stopwatch",
    "summary",
]

STATISTIC = (
    "median over repeats of the ratio within each repeat; variants interleaved, "
    "order alternating per repeat"
)
#: options prefix of the benchmarks' KSPs: ``PETSC_OPTIONS=-bench_ksp_view`` reaches them
PREFIX = "bench_"


def stopwatch(fn: Callable, *args, **kwargs):
    """``(fn(*args, **kwargs), seconds)`` on ``time.perf_counter``."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def interleaved(steps: dict[str, Callable], repeats: int, warmup: int) -> dict[str, list]:
    """Run every step once per round, order alternating; keep the last `repeats` rounds.

    A step returns its time in seconds, or a dict of named times (parts of one call);
    the result maps each name to its times, one per repeat.
    """
    times: dict[str, list] = {}
    names = list(steps)
    for i in range(warmup + repeats):
        for name in names if i % 2 == 0 else names[::-1]:
            out = steps[name]()
            if i >= warmup:
                for key, value in out.items() if isinstance(out, dict) else [(name, out)]:
                    times.setdefault(key, []).append(value)
    return times


def paired(numerator, denominator) -> float:
    """Median over repeats of the ratio within each repeat."""
    return float(np.median(np.asarray(numerator) / np.asarray(denominator)))


def summary(values) -> dict:
    """``median``, quartiles ``q1`` and ``q3``, and ``noise``: the interquartile range
    over the median."""
    q1, q2, q3 = np.percentile(values, [25, 50, 75])
    return {"median": float(q2), "q1": float(q1), "q3": float(q3), "noise": float((q3 - q1) / q2)}


def bench_solver(ksp_type: str, pc_type: str, k: int):
    """The benchmarks' `KSPSolver`: fixed mode, K iterations, prefix `PREFIX`."""
    from prdp_petsc import KSPSolver

    return KSPSolver({"ksp_type": ksp_type, "pc_type": pc_type}, prefix=PREFIX, max_it=k)


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


def ksp_types(solver) -> list[str]:
    """``[ksp_type, pc_type]`` as PETSc reports them for the forward KSP."""
    return [solver.ksp.getType(), solver.ksp.getPC().getType()]


def check_exactly_k(solver, k: int) -> None:
    """Raise unless every solve of `solver`, forward and adjoint, ran exactly K iterations."""
    stats = solver.stats
    for side in ("forward", "adjoint"):
        solves, its = getattr(stats, f"{side}_solves"), getattr(stats, f"{side}_iterations")
        if its != k * solves:
            raise RuntimeError(f"{side} KSP: {its} iterations in {solves} solves, not {k} each")
