"""A model of memory and halo traffic per rank beyond the ranks `bench mpi` measured.

Fitted to an owned-layout ``bench_mpi.json`` (`prdp_petsc.lab.reports.bench_mpi`) with at
least two rank counts, and labelled as a model wherever it is shown (the record's
results page).
"""

from __future__ import annotations

import numpy as np

from .kinds import markdown_table

__all__ = ["MODEL_RANKS", "format_scaling_model", "scaling_model"]


#: rank counts the scaling model extrapolates to
MODEL_RANKS = (64, 256, 1024)


def scaling_model(result: dict, ranks=MODEL_RANKS) -> dict | None:
    """A model of memory and halo traffic per rank beyond the measured rank counts.

    Fitted to an owned-layout record with at least two rank counts; None otherwise.
    It is a model, not a measurement:

    memory
        ``peak(P) = base + per_unknown · N / P``: least squares over the measured
        ranks of the largest rank's peak resident size (rank 0 also held the whole
        mesh at start-up and is left out where P > 1; ``rank0_mb`` below keeps it).
        ``base`` is what every process holds whatever its share (Python, torch,
        PETSc, MPI buffers).  ``rank0_mb`` is how far rank 0's peak was above the
        other ranks' at the largest P (rank 0 also read and partitioned the mesh).
    halo
        Ghost vertices per rank ``g(P) = c · (N / P)^(2/3)`` (the surface of a
        compact 3D part), c fitted on P ≥ 2.  One CG iteration moves 8·g bytes into
        each rank (the halo of the Krylov vector), the backward pass's ∂L/∂θ the
        ghost values of x and λ (16·g bytes) and the element halo back.

    Returns
    -------
    dict
        ``base_mb``, ``mb_per_unknown``, ``halo_coefficient``, ``rank0_mb`` (rank 0's
        measured extra at the largest P), and ``rows``: per P in `ranks`, the
        predicted ``peak_mb_per_rank``, ``ghost_vertices_per_rank`` and
        ``halo_kb_per_iteration`` at the measured size N (strong scaling) and at N·P
        (the measured one-rank share kept, weak scaling: ``weak_…``).
    """
    solve = result.get("solve", {})
    measured = {int(p): r for p, r in solve.items() if r.get("layout") == "owned"}
    if len(measured) < 2 or not all("ghost_vertices_per_rank" in r for r in measured.values()):
        return None
    n = next(iter(measured.values()))["unknowns"]
    ps = sorted(measured)
    peaks = [max(measured[p]["peak_rss_mb_per_rank"][1:] or measured[p]["peak_rss_mb_per_rank"])
             for p in ps]  # fmt: skip
    share = np.array([n / p for p in ps], dtype=float)
    slope, base = np.polyfit(share, np.array(peaks), 1)
    halos = [(p, max(measured[p]["ghost_vertices_per_rank"])) for p in ps if p > 1]
    c = float(np.mean([g / (n / p) ** (2 / 3) for p, g in halos]))
    top = measured[ps[-1]]["peak_rss_mb_per_rank"]
    rows = {}
    for p in ranks:
        g = c * (n / p) ** (2 / 3)
        weak_g = c * n ** (2 / 3)
        rows[str(p)] = {
            "peak_mb_per_rank": float(base + slope * n / p),
            "ghost_vertices_per_rank": g,
            "halo_kb_per_iteration": 8 * g / 1024,
            "weak_unknowns": n * p,
            "weak_peak_mb_per_rank": float(base + slope * n),
            "weak_halo_kb_per_iteration": 8 * weak_g / 1024,
        }
    return {
        "unknowns": n,
        "measured_ranks": ps,
        "base_mb": float(base),
        "mb_per_unknown": float(slope),
        "halo_coefficient": c,
        "rank0_mb": float(top[0] - max(top[1:] or top)) if len(top) > 1 else 0.0,
        "rows": rows,
    }


def format_scaling_model(model: dict) -> str:
    """The scaling model as a Markdown table, labelled as a model."""
    lines = [
        f"Model (not measured), fitted to P = {', '.join(map(str, model['measured_ranks']))} "
        f"at N = {model['unknowns']} unknowns: peak per rank = {model['base_mb']:.0f} MB + "
        f"{1e3 * model['mb_per_unknown']:.2f} kB × N/P; ghost vertices per rank = "
        f"{model['halo_coefficient']:.2f} × (N/P)^(2/3); rank 0's peak was "
        f"{model['rank0_mb']:.0f} MB above the other ranks' (it also read and partitioned "
        "the whole mesh).",
        "",
    ]
    header = ["ranks P", "N", "peak MB per rank", "ghost vertices per rank"]
    header += ["halo kB per CG iteration", "weak scaling: N", "peak MB per rank"]
    rows = [
        (p, model["unknowns"], f"{r['peak_mb_per_rank']:.0f}",
         f"{r['ghost_vertices_per_rank']:.0f}", f"{r['halo_kb_per_iteration']:.1f}",
         f"{r['weak_unknowns']:.3g}", f"{r['weak_peak_mb_per_rank']:.0f}",
         f"{r['weak_halo_kb_per_iteration']:.1f}")
        for p, r in model["rows"].items()
    ]  # fmt: skip
    return "\n".join([*lines, markdown_table([*header, "halo kB per iteration"], rows)])
