"""prdp_petsc on one GPU (or the CPU) against jax, lineax and a torch CG, fwd + bwd.

``prdp-petsc bench gpu --out DIR`` (or ``python -m prdp_petsc.lab.reports.bench_gpu``,
PETSc options then through ``PETSC_OPTIONS``) writes ``DIR/bench_gpu.json``: every
contender in one process on one device (without CUDA, the CPU with PETSc's default
types), on the same problems, b and x_ref.  One call is K Jacobi-CG iterations from
x = 0 without a tolerance, the cotangent ``x − x_ref`` of ``½‖x_K(b) − x_ref‖²`` and K
iterations on the adjoint (the gradient in b), float64, ending with a device
synchronisation.  The contenders (`prdp_petsc.lab.reports.gpu_contenders`; one that
cannot run is skipped with a note): ``prdp_petsc``, ``pp.solve`` with ``vec_type cuda,
mat_type aijcusparse`` and ``backward()`` (A a ``DLPackCSR`` with its values on the GPU,
the device path's constant operator; on the CPU the scipy matrix); ``raw_petsc``,
petsc4py alone on Vecs wrapping torch tensors by DLPack (the adjoint by ``KSPSolve``, or
``KSPSolveTranspose``); each ``_sr`` with ``ksp_cg_single_reduction``; ``jax_cg`` and
``lineax_cg``, ``jax.jit(jax.grad)`` of their CG; ``torch_pcg``, `pcg` twice.  PETSc
options reach each one's KSP by its prefix (``-prdp_petsc_ksp_view``).  On the CPU
with ``--threads 1``, XLA runs on one thread too.  ``prdp-petsc bench jax``
(`prdp_petsc.lab.reports.bench_jax`) is this on the CPU at the sizes of the JAX
comparison.

Per (problem, K): medians over ``--rounds`` paired rounds (`interleaved`), ratios
within each round (median, IQR/median as ``noise``), x and the gradient against
prdp_petsc's; prdp_petsc's GPU path against its CPU path at K = 10; on
``--tol-problems`` the smallest K whose gradient is within ``--tol`` of the reference
(`reference_gradient`) for Jacobi CG and for prdp_petsc with GAMG.  A step that would
start after ``--budget-s`` is listed in ``skipped``.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import statistics
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from ..cli.arguments import add_debug, add_size_preset, positive
from ..provenance import cpu, machine, provenance, versions, write_result
from .benchmarking import interleaved, stopwatch, summary
from .gpu_contenders import CONTENDERS, GAMG, PAIRS, Case, Contender, Run, pcg, problem
from .kinds import DataSet, ReportKind, markdown_table

__all__ = ["KIND", "format_report", "main", "verdicts"]

logger = logging.getLogger(__name__)


# -- measuring -----------------------------------------------------------------------------
class Budget:
    """The run's time budget: `allows` says whether a step may still start."""

    def __init__(self, seconds: float | None) -> None:
        self.seconds, self.start, self.skipped = seconds, time.perf_counter(), []

    def allows(self, what: str) -> bool:
        if self.seconds is None or time.perf_counter() - self.start < self.seconds:
            return True
        self.skipped.append({"what": what, "why": f"budget of {self.seconds:g} s spent"})
        logger.warning("skipped %s: budget spent", what)
        return False


def _time_calls(run: Run, calls: int) -> list[float]:
    return [stopwatch(run.call)[1] for _ in range(calls)]


def _rel(a: np.ndarray, ref: np.ndarray) -> float:
    """max |a − ref| / max |ref|."""
    scale = float(np.abs(ref).max())
    return float(np.abs(a - ref).max() / scale) if scale > 0 else float(np.abs(a).max())


def _start(contender: Contender, case: Case, k: int, notes: dict, **kwargs) -> Run | None:
    """`Contender.start`, or None with a note in `notes` if that fails."""
    try:
        return contender.start(case, k, **kwargs)
    except Exception as err:  # one contender failing must not stop the others
        notes[contender.name] = f"failed: {type(err).__name__}: {err}"
        logger.warning("%s on %s, K = %d: %s", contender.name, case.name, k, err)
        return None


def bench_cell(case: Case, k: int, contenders, rounds: int, calls: int, warmup: int) -> dict:
    """Time every contender at K on `case` (paired rounds); agreement with prdp_petsc."""
    notes, runs, setup = {}, {}, {}
    for c in contenders:
        run, seconds = stopwatch(_start, c, case, k, notes)
        if run is not None:
            setup[c.name] = seconds
            _time_calls(run, warmup)
            runs[c.name] = run
    names = list(runs)
    steps = {name: partial(_time_calls, run, calls) for name, run in runs.items()}
    timings = interleaved(steps, rounds, 0)
    med = {name: np.median(timings[name], axis=1) for name in names}
    pairs = [pair for pair in PAIRS if set(pair) <= set(names)]
    if "jax_cg" in names:
        pairs += [(name, "jax_cg") for name in names if name != "jax_cg"]
    results = {name: run.result() for name, run in runs.items()}
    reference = "prdp_petsc" if "prdp_petsc" in names else next(iter(names), None)
    x0, g0 = results.get(reference, (None, None))
    agreement = {n: {"x": _rel(x, x0), "grad": _rel(g, g0)} for n, (x, g) in results.items()}
    agreement.pop(reference, None)
    return {
        "problem": case.name,
        "n": case.n,
        "k": k,
        "median_s": {name: float(np.median(m)) for name, m in med.items()},
        "ratios": {f"{a}/{b}": summary(med[a] / med[b]) for a, b in pairs},
        "reference": reference,
        "agreement": agreement,
        "setup_s": setup,
        "info": {name: run.info() for name, run in runs.items()},
        "notes": notes,
        "round_medians_s": {name: m.tolist() for name, m in med.items()},
        "timings_s": timings,
    }


def cpu_gpu_agreement(case: Case, k: int, devices=("cuda", "cpu")) -> dict:
    """prdp_petsc on the GPU (CUDA types) against prdp_petsc on the CPU (default types):
    the max relative difference of x and of the gradient (`devices`: the two runs)."""
    notes = {}
    runs = [_start(CONTENDERS[0], case, k, notes, on=device) for device in devices]
    if None in runs:
        return {"k": k, "note": "; ".join(notes.values())}
    (x1, g1), (x2, g2) = (run.result() for run in runs)
    return {"k": k, "x": _rel(x1, x2), "grad": _rel(g1, g2), "target": 1e-10}


# -- time to a gradient within tol of the reference ---------------------------------------
def reference_gradient(case: Case, direct_max_n: int) -> dict:
    """x* = A⁻¹b and ∇* = A⁻¹(x* − x_ref): SuperLU up to `direct_max_n` unknowns, above
    that `tight_cg`; with the relative residuals of both."""
    t = time.perf_counter()
    if case.n <= direct_max_n:
        from scipy.sparse.linalg import splu

        lu = splu(case.A.tocsc())
        x = lu.solve(case.b)
        grad = lu.solve(x - case.x_ref)
        found = {"method": "scipy.sparse.linalg.splu (SuperLU, COLAMD)"}
    else:
        _, _, b, x_ref = case.on_device
        x, change_x = tight_cg(case, b)
        grad, change_grad = tight_cg(case, x - x_ref)
        x, grad = x.cpu().numpy(), grad.cpu().numpy()
        found = {
            "method": "torch Jacobi CG, iteratively refined until a correction is below 1e-11",
            "last_corrections": [change_x, change_grad],
        }
    residuals = [
        np.linalg.norm(case.A @ x - case.b) / np.linalg.norm(case.b),
        np.linalg.norm(case.A @ grad - (x - case.x_ref)) / np.linalg.norm(x - case.x_ref),
    ]
    found["relative_residuals"] = [float(r) for r in residuals]
    return {"grad": grad, **found, "seconds": time.perf_counter() - t}


def tight_cg(case: Case, rhs, inner_rtol: float = 1e-12, settled: float = 1e-11, rounds: int = 10):
    """Solve A x = rhs by iterative refinement: Jacobi CG on the true residual, each to
    `inner_rtol` of its own right-hand side, until a correction changes x by at most
    `settled` (relative), so the recursive residual's drift cannot fake convergence.
    Returns x and the relative size of the last correction."""
    A, inv_diag, _, _ = case.on_device
    x = torch.zeros_like(rhs)
    for _ in range(rounds):
        d = pcg(A, inv_diag, rhs - A @ x, 100 * case.n, rtol=inner_rtol)
        x += d
        change = float(torch.linalg.vector_norm(d) / torch.linalg.vector_norm(x))
        if change <= settled:
            return x, change
    raise RuntimeError(f"{case.name}: the reference CG did not settle (last change {change:.1e})")


def _smallest_k(error, tol: float, k0: int, k_max: int) -> tuple[int | None, list]:
    """The smallest K (to 1 %) with ``error(K) <= tol``, by doubling from `k0` and then
    bisection, and the [K, error] pairs tried; None if `k_max` misses `tol`."""
    trace, lo, k = [], 0, k0
    while (e := error(k)) > tol:
        trace.append([k, e])
        if k >= k_max:
            return None, trace
        lo, k = k, min(2 * k, k_max)
    trace.append([k, e])
    hi = k
    while hi - lo > max(1, hi // 100):
        mid = (lo + hi) // 2
        e = error(mid)
        trace.append([mid, e])
        lo, hi = (lo, mid) if e <= tol else (mid, hi)
    return hi, trace


def time_to_tolerance(case: Case, contenders, gamg: bool, args, budget: Budget) -> dict:
    """For each contender the smallest K whose gradient is within ``args.tol`` of the
    reference and its fwd + bwd time there; the same for prdp_petsc with GAMG if `gamg`."""
    tol = args.tol
    ref = reference_gradient(case, args.direct_max_n)
    grad_ref = ref.pop("grad")
    out = {"tol": tol, "reference": ref, "contenders": {}, "notes": {}}

    def error(run: Run) -> float:
        return float(np.linalg.norm(run.result()[1] - grad_ref) / np.linalg.norm(grad_ref))

    by_name = {c.name: c for c in contenders}  # torch_pcg searches fastest: no set-up
    if (searcher := by_name.get("torch_pcg", by_name.get("prdp_petsc"))) is None:
        out["notes"]["jacobi"] = "neither torch_pcg nor prdp_petsc runs here: no K search"
    else:
        k, trace = _smallest_k(lambda k: error(searcher.start(case, k)), tol, 16, args.k_max)
        out["jacobi"] = {"k": k, "searched_with": searcher.name, "search": trace}
        for c in contenders if k is not None else ():
            if budget.allows(f"time to {tol:g}: {c.name} on {case.name}"):
                out["contenders"][c.name] = _at_k(c, case, k, error, args, out["notes"])
    if gamg and budget.allows(f"time to {tol:g}: GAMG on {case.name}"):
        out["gamg"] = _gamg(case, error, args, out["notes"])
    return out


def _at_k(c: Contender, case: Case, k: int, error, args, notes: dict) -> dict | None:
    """`c` at K, raised by 5 % (at most twice) while its own gradient misses the tolerance."""
    for _ in range(3):
        if (run := _start(c, case, k, notes)) is None:
            return None
        if (err := error(run)) <= args.tol:
            break
        k = int(np.ceil(1.05 * k))
    times = _time_calls(run, args.tol_calls)
    return {"k": k, "grad_error": err, "median_s": statistics.median(times), "times_s": times}


def _gamg(case: Case, error, args, notes: dict) -> dict | None:
    """prdp_petsc with CG + GAMG: the PC set up once, K moved on the same solver."""
    run, first = stopwatch(_start, GAMG, case, 1, notes)  # the first call sets the PC up
    if run is None:
        return None
    again = _time_calls(run, 1)[0]  # the same call with the PC kept

    def error_at(k):
        run.set_k(k)
        run.call()
        return error(run)

    k, trace = _smallest_k(error_at, args.tol, 1, args.k_max)
    if k is None:
        return {"k": None, "search": trace, "note": f"no K <= {args.k_max} reached {args.tol:g}"}
    err = error_at(k)
    times = _time_calls(run, args.tol_calls)
    return {
        "k": k,
        "grad_error": err,
        "median_s": statistics.median(times),
        "setup_s": max(first - again, 0.0),
        "first_call_s": first,
        "times_s": times,
        "search": trace,
        "info": run.info(),
    }


# -- the run -------------------------------------------------------------------------------
def environment(device: str) -> tuple[str, dict]:
    """The torch device (``auto``: CUDA where torch sees a GPU) and why each need of the
    contenders (`Contender.needs`) cannot be met there (None where it can)."""
    from petsc4py import PETSc

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda: torch sees no CUDA device")
    notes = {"petsc": None, "jax": None}
    if device == "cuda" and not PETSc.Sys.hasExternalPackage("cuda"):
        notes["petsc"] = "PETSc is built without CUDA (PETSc.Sys.hasExternalPackage('cuda') False)"
    try:
        import jax

        backends = {d.platform for d in jax.devices()}
        if device == "cuda" and not backends & {"gpu", "cuda"}:
            notes["jax"] = f"jax has no GPU backend here (devices: {sorted(backends)})"
    except ImportError:
        notes["jax"] = "jax is not installed"
    notes["lineax"] = notes["jax"]
    if notes["jax"] is None and importlib.util.find_spec("lineax") is None:
        notes["lineax"] = "lineax is not installed"
    return device, notes


def device_info(device: str, jax: bool) -> dict:
    """The device's name and memory, and the CUDA and PETSc versions of the run."""
    from petsc4py import PETSc

    cuda = device == "cuda"
    info = {
        "kind": device,
        "petsc_cuda": bool(PETSc.Sys.hasExternalPackage("cuda")),
        "torch_cuda": torch.version.cuda,
        "name": torch.cuda.get_device_name() if cuda else cpu(),
        "petsc_version": PETSc.Sys.getVersionInfo(),
    }
    if cuda:
        info["memory_gib"] = round(torch.cuda.get_device_properties(0).total_memory / 2**30, 1)
    if jax:
        import jax

        info["jax_devices"] = [str(d) for d in jax.devices()]
    return info


def bench_gpu(args, device: str, notes: dict, budget: Budget, save=None) -> dict:
    """Every problem, cell and time to tolerance of `args` on `device`, with the contenders
    that `notes` (`environment`) lets run there; a JSON-ready dict.  `save`, if given, is
    called with the dict so far after each problem (a run cut short keeps what it did)."""
    availability = {}
    for c in (*CONTENDERS, GAMG):
        why = "left out by --skip" if c.name in args.skip else notes.get(c.needs)
        availability[c.name] = {"describe": c.describe, "available": why is None, "note": why}
    contenders = [c for c in CONTENDERS if availability[c.name]["available"]]
    problems, cells, agreement, tolerance = {}, [], {}, {}

    def result() -> dict:
        return {
            "device": device_info(device, notes["jax"] is None),
            "problems": problems,
            "contenders": availability,
            "cells": cells,
            "cpu_gpu_agreement": agreement
            if device == "cuda"
            else {"note": "no CUDA device: the whole run is on the CPU path"},
            "time_to_tolerance": tolerance,
            "skipped": budget.skipped,
        }

    for name in args.problems:
        if not budget.allows(f"problem {name}"):
            continue
        t = time.perf_counter()
        label, matrix = problem(name)
        A = matrix()
        b, x_ref = np.random.default_rng(args.seed).standard_normal((2, A.shape[0]))
        case = Case(name, A, b, x_ref, device, args.jax_matrix)
        build_s = time.perf_counter() - t
        problems[name] = {"label": label, "n": case.n, "nnz": A.nnz, "build_s": build_s}
        logger.info("%s: n = %d, nnz = %d", name, case.n, A.nnz)
        for k in args.k:
            if budget.allows(f"{name}, K = {k}"):
                cells.append(bench_cell(case, k, contenders, args.rounds, args.calls, args.warmup))
        if device == "cuda" and budget.allows(f"CPU/GPU agreement on {name}"):
            agreement[name] = cpu_gpu_agreement(case, 10)
        if name in args.tol_problems and budget.allows(f"time to {args.tol:g} on {name}"):
            gamg = availability[GAMG.name]["available"]
            tolerance[name] = time_to_tolerance(case, contenders, gamg, args, budget)
        case.release()
        if save is not None:
            save(result())
    return result()


# -- the report ----------------------------------------------------------------------------
def format_report(d: dict) -> str:
    """The printed summary of a `bench_gpu` result: the issue's table and the ratios."""
    dev = d["device"]
    lines = [f"device: {dev['name']} ({dev['kind']}; PETSc with CUDA: {dev['petsc_cuda']})"]
    if d.get("partial"):
        missing = [p for p in d["settings"]["problems"] if p not in d["problems"]]
        lines.append(f"  cut short: the run was stopped before {', '.join(missing) or 'its end'}")
    lines += [
        f"  skipped {n}: {c['note']}" for n, c in d["contenders"].items() if not c["available"]
    ]
    names = [n for n in d["contenders"] if any(n in cell["median_s"] for cell in d["cells"])]
    rows = []
    for pname, p in d["problems"].items():
        if cells := [c for c in d["cells"] if c["problem"] == pname]:
            ms = [" / ".join(_ms(c["median_s"].get(n)) for c in cells) + " ms" for n in names]
            problem = f"{p['label']} ({p['n']:,})".replace(",", " ")
            rows.append([problem, " / ".join(str(c["k"]) for c in cells), *ms])
    lines += ["", markdown_table(("problem (unknowns)", "K", *names), rows), ""]
    lines.append("ratios (median over rounds; noise = IQR/median) and agreement with prdp_petsc:")
    for c in d["cells"]:
        ratios = ", ".join(f"{k} {r['median']:.2f}" for k, r in c["ratios"].items()) or "-"
        worst = max((max(a.values()) for a in c["agreement"].values()), default=float("nan"))
        lines.append(f"  {c['problem']} K={c['k']}: {ratios}; max rel. diff {worst:.1e}")
        lines += [f"    {name}: {note}" for name, note in c["notes"].items()]
    for pname, a in d["cpu_gpu_agreement"].items():
        if pname == "note":
            lines.append(f"CPU vs GPU path: {a}")
        elif "grad" in a:
            lines.append(
                f"CPU vs GPU path, {pname} K={a['k']}: x {a['x']:.1e}, grad {a['grad']:.1e}"
            )
    for pname, t in d["time_to_tolerance"].items():
        ref = t["reference"]
        residuals = ", ".join(f"{r:.1e}" for r in ref["relative_residuals"])
        lines.append(
            f"time to a {t['tol']:g} gradient on {pname} (reference: {ref['method']}, "
            f"{ref['seconds']:.1f} s; residuals {residuals}):"
        )
        reached = {name: r for name, r in t["contenders"].items() if r is not None}
        gamg = t.get("gamg") or {}
        if gamg.get("k") is not None:
            reached["prdp_petsc + GAMG"] = gamg
        for name, r in reached.items():
            setup = f"; PC setup {r['setup_s'] * 1e3:.1f} ms once" if "setup_s" in r else ""
            lines.append(
                f"  {name:<20} K = {r['k']:>6}  {r['median_s'] * 1e3:9.2f} ms  "
                f"(error {r['grad_error']:.1e}{setup})"
            )
        if "note" in gamg:
            lines.append(f"  prdp_petsc + GAMG: {gamg['note']}")
        lines += [f"  {name}: {note}" for name, note in t["notes"].items()]
    lines += [f"skipped {s['what']}: {s['why']}" for s in d["skipped"]]
    lines.append("targets:")
    for target, measured, met in verdicts(d):
        lines.append(
            f"  {target}: {measured} [{ {True: 'met', False: 'NOT met', None: '-'}[met] }]"
        )
    return "\n".join(lines) + "\n"


def _ms(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    ms = seconds * 1e3
    return f"{ms:.3g}" if ms < 100 else f"{ms:.0f}"


def verdicts(d: dict) -> list[tuple[str, str, bool | None]]:
    """Each target of issue 36 against a `bench_gpu` result: (target, what was measured,
    met: True/False, or None where the run measured nothing to judge it by)."""
    if d["device"]["kind"] != "cuda":
        return [("the GPU targets", f"not judged: measured on {d['device']['name']}", None)]

    def worst(target: str, pair: str, bound: float, sizes=(0, np.inf)) -> tuple:
        found = [(c["ratios"][pair]["median"], c) for c in d["cells"]
                 if pair in c["ratios"] and sizes[0] <= c["n"] < sizes[1]]  # fmt: skip
        if not found:
            return target, "not measured", None
        r, c = max(found, key=lambda rc: rc[0])
        return target, f"worst {r:.2f} ({c['problem']}, K = {c['k']})", r <= bound

    out = [worst("bridge over raw petsc4py <= 1.15", "prdp_petsc/raw_petsc", 1.15)]
    # PETSc's own CG without the bridge, against jax: how far the jax targets are reachable
    own = [c["ratios"][pair]["median"] for c in d["cells"] for pair in
           ("raw_petsc/jax_cg", "raw_petsc_sr/jax_cg") if pair in c["ratios"]]  # fmt: skip
    if own:
        text = f"{min(own):.2f} to {max(own):.2f} over the cells (raw_petsc, raw_petsc_sr)"
        out.append(("for reference: raw petsc4py / jax_cg, no bridge", text, None))
    for name in ("prdp_petsc", "prdp_petsc_sr"):
        for bound, label, sizes in ((3.5, "12 k", (0, 59_000)), (2.0, ">= 59 k", (59_000, np.inf)),
                                    (1.3, "784 k", (700_000, np.inf))):  # fmt: skip
            out.append(
                worst(f"{name} / jax_cg <= {bound} at {label}", f"{name}/jax_cg", bound, sizes)
            )
    diffs = [max(a["x"], a["grad"]) for a in d["cpu_gpu_agreement"].values()
             if isinstance(a, dict) and "grad" in a]  # fmt: skip
    measured = f"worst {max(diffs):.1e}" if diffs else "not measured"
    out.append(
        (
            "CPU and GPU paths agree to 1e-10 at K = 10",
            measured,
            max(diffs) <= 1e-10 if diffs else None,
        )
    )
    for pname, t in d["time_to_tolerance"].items():
        target = f"GAMG first to {t['tol']:g} on {pname}"
        gamg = t.get("gamg") or {}
        peers = {n: r["median_s"] for n, r in t["contenders"].items()
                 if r and n in ("jax_cg", "lineax_cg", "torch_pcg")}  # fmt: skip
        if gamg.get("k") is None or not peers:
            out.append((target, "not measured", None))
            continue
        fastest = min(peers, key=peers.get)
        total = gamg["median_s"] + gamg["setup_s"]
        text = (f"GAMG {gamg['median_s'] * 1e3:.1f} ms per call (+ {gamg['setup_s'] * 1e3:.0f} "
                f"ms setup once) against {fastest} {peers[fastest] * 1e3:.1f} ms")  # fmt: skip
        out.append((target, text, gamg["median_s"] < peers[fastest]))
        out.append(
            (f"{target}, its setup counted", f"{total * 1e3:.1f} ms", total < peers[fastest])
        )
    return out


# -- the command ---------------------------------------------------------------------------
_XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def _names(text: str) -> tuple[str, ...]:
    return tuple(name for name in text.split(",") if name)


def _problems(text: str) -> tuple[str, ...]:
    for name in _names(text):
        problem(name)  # raises ArgumentTypeError for an unknown name
    return _names(text)


def _contenders(text: str) -> tuple[str, ...]:
    known = [c.name for c in CONTENDERS]
    if unknown := [n for n in _names(text) if n not in known]:
        raise argparse.ArgumentTypeError(f"unknown contender(s) {unknown}; known: {known}")
    return _names(text)


def _ks(text: str) -> tuple[int, ...]:
    return tuple(positive(k) for k in _names(text))


#: option -> (type, default, help) of ``bench gpu``, besides those with fixed choices
# fmt: off
OPTIONS = {
    "--problems": (_problems, ("lshape6", "heat3d41", "lshape8", "lshape9"),
                   "lshape<r>,heat3d<m>,five_point<side>,..."),
    "--k": (_ks, (10, 100, 300), "CG iterations K"),
    "--rounds": (positive, 5, "paired rounds per cell"),
    "--calls": (positive, 5, "timed calls per round"),
    "--warmup": (int, 2, "untimed calls after set-up"),
    "--tol": (float, 1e-6, "gradient tolerance"),
    "--tol-problems": (_names, ("lshape8", "lshape9"), "problems timed to --tol ('' for none)"),
    "--tol-calls": (positive, 2, "timed calls at that K"),
    "--direct-max-n": (positive, 60_000, "largest n whose reference is spsolve, else a tight CG"),
    "--k-max": (positive, 20_000, "largest K searched"),
    "--skip": (_contenders, (), "contenders to leave out"),
    "--seed": (int, 0, "seed of b and x_ref"),
    "--threads": (positive, 1, "torch CPU threads"),
    "--budget-s": (float, 420.0, "start no step after this many seconds (0: no limit)"),
}
# fmt: on
#: the settings of ``--preset quick`` (a smoke test)
QUICK = {
    "problems": ("lshape3", "heat3d5"),
    "k": (2, 5),
    "tol_problems": ("lshape3",),
    "rounds": 2,
    "calls": 2,
    "warmup": 1,
    "tol_calls": 2,
}


def _shown(value) -> str:
    """An option's value as it is typed: ``lshape3,heat3d5``, ``1e-06``, ``5``."""
    if isinstance(value, tuple):
        return ",".join(map(str, value)) or "none"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _parser(prog: str, defaults: dict, quick: dict) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for bench_gpu.json")
    device = defaults.get("device", "auto")
    p.add_argument("--device", choices=("auto", "cuda", "cpu"), default=device)
    p.add_argument("--jax-matrix", choices=("bcoo", "bcsr"), default="bcoo",
                   help="jax's sparse format of A (bcoo)")  # fmt: skip
    for option, (kind, default, text) in OPTIONS.items():
        default = defaults.get(option[2:].replace("-", "_"), default)
        text = f"{text} (default {_shown(default)})"
        p.add_argument(option, type=kind, default=default, help=text)
    sizes = ", ".join(f"--{name.replace('_', '-')} {_shown(v)}" for name, v in quick.items())
    add_size_preset(p, f"{sizes} (a smoke test)")
    add_debug(p)
    return p


def main(
    argv: list[str],
    prog: str = "prdp-petsc bench gpu",
    defaults: dict | None = None,
    quick: dict = QUICK,
) -> int:
    """Run ``bench gpu``; write ``<out>/bench_gpu.json``; return an exit code.
    `defaults` replaces defaults of the options, `quick` the settings of ``--preset quick``
    (``bench jax`` gives its own, under its `prog` name)."""
    args = _parser(prog, defaults or {}, quick).parse_args(argv)
    if args.preset == "quick":
        vars(args).update(quick)
    # jax takes 75 % of the GPU's memory at its first array unless told not to
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if args.device == "cpu" and args.threads == 1:  # before jax starts its CPU client
        os.environ.setdefault("XLA_FLAGS", _XLA_ONE_THREAD)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()

    def framed(measured: dict, **more) -> dict:
        return {
            "benchmark": "gpu",
            **measured,
            "settings": {k: v for k, v in vars(args).items() if k not in ("out", "debug")},
            "provenance": provenance(torch.get_num_threads(), 1),
            "machine": machine(),
            "versions": versions("jax", "jaxlib", "lineax", "equinox", "cupy", "jax-cuda13-plugin"),
            "wall_s": time.perf_counter() - t0,
            **more,
        }

    def save(partial: dict) -> None:  # the problems so far, in case the run is cut short
        write_result(args.out, "bench_gpu.json", framed(partial, partial=True))

    measured = bench_gpu(args, *environment(args.device), Budget(args.budget_s or None), save)
    result = framed(measured)
    write_result(args.out, "bench_gpu.json", result)
    print(format_report(result), end="")
    return 0


def _headline(ds: DataSet) -> list[tuple[str, str]]:
    """The index's rows: the bridge over raw petsc4py, prdp_petsc over jax's CG."""
    judged = {target: measured for target, measured, _ in verdicts(ds.main)}
    if "the GPU targets" in judged:
        return [
            ("prdp_petsc against jax, lineax and torch CG on one GPU", judged["the GPU targets"])
        ]
    rows = ("bridge over raw petsc4py <= 1.15", "prdp_petsc / jax_cg <= 2.0 at >= 59 k")
    return [(f"GPU, fwd + bwd of capped Jacobi CG: {row}", judged[row]) for row in rows]


def _verdict_table(ds: DataSet) -> list[str]:
    word = {True: "met", False: "**not met**", None: "not judged"}
    rows = [(target, measured, word[met]) for target, measured, met in verdicts(ds.main)]
    table = markdown_table(("target", "measured", "verdict"), rows)
    return ["Each target of issue 36, read from this run:", table]


KIND = ReportKind(
    name="bench-gpu",
    reads="bench_gpu.json",
    title=lambda ds: "Capped CG gradients on one GPU: prdp_petsc against jax, lineax and torch",
    headline=_headline,
    intro="What `prdp-petsc bench gpu` printed: the gradient in b of ½‖x_K(b) − x_ref‖², K "
    "capped Jacobi-CG iterations forward and K on the adjoint, every contender in one process "
    "on one device, paired rounds; the time to a gradient within 1e-6 of the direct one with "
    "Jacobi CG and with GAMG. Exactly what each contender runs is in the docstrings of "
    "`prdp_petsc.lab.reports.bench_gpu` and `prdp_petsc.lab.reports.gpu_contenders`.",
    output=lambda ds: format_report(ds.main).rstrip("\n"),
    after=_verdict_table,
)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    sys.exit(main(sys.argv[1:]))
