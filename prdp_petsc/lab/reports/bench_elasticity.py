"""GAMG on 3D elasticity: iterations against the mesh, with and without the rigid-body modes.

``prdp-petsc bench elasticity --out DIR`` writes ``DIR/bench_elasticity.json``.  On
`clamped_cube` (n³ Q1 hexahedra) for each n of ``--sizes``, CG + GAMG runs to
``--rtol`` in three declarations of the same operator (`VARIANTS`):

``scalar``
    nothing declared: GAMG aggregates the unknowns as unrelated scalars;
``block``
    ``block_size=3`` (GAMG aggregates nodes; near-null space: the translations);
``modes``
    ``block_size=3`` and the six rigid-body modes as ``near_nullspace``
    (`prdp_petsc.fem.vector.rigid_body_modes`).

Each row has the iterations and reason, the set-up time (first solve minus a second),
the true relative residual, and the relative error of a capped solve at ``--k``
iterations against the converged ``modes`` solution, what a PRDP schedule meets at
small K.  ``growth`` is each declaration's iterations on the largest mesh over those
on the smallest; the target for ``modes`` is at most `TARGET_GROWTH`.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from ..cli.arguments import add_debug, add_k, add_out, add_size_preset
from ..provenance import load_average, machine_info, write_result
from ..training.threads import torch_threads
from .benchmarking import stopwatch
from .kinds import DataSet, ReportKind, markdown_table
from .problems import clamped_cube

__all__ = ["KIND", "VARIANTS", "format_report", "main", "run"]

logger = logging.getLogger(__name__)

#: the declarations compared, in the order of the report
VARIANTS = ("scalar", "block", "modes")
#: iterations on the largest mesh over those on the smallest that count as flat
TARGET_GROWTH = 1.5


def _declaration(variant: str, basis, bc) -> dict:
    from prdp_petsc import rigid_body_modes
    from prdp_petsc.fem.vector import block_size

    if variant == "scalar":
        return {}
    declared = {"block_size": block_size(basis, bc.interior)}
    if variant == "modes":
        declared["near_nullspace"] = rigid_body_modes(basis, bc.interior)
    return declared


def run(sizes, *, rtol: float = 1e-8, max_it: int = 2000, k: int = 10) -> dict:
    """Solve every size in every declaration; return the JSON-ready record."""
    from prdp_petsc import KSPSolver, Structure

    options = {"ksp_type": "cg", "pc_type": "gamg"}
    rows = []
    for n in sizes:
        basis, bc, b = clamped_cube(n)
        M = bc.A_II.matrix(np.ones(bc.A_II.n_params))
        reference, results = None, {}
        for variant in reversed(VARIANTS):  # modes first: its solution is the reference
            declared = _declaration(variant, basis, bc)
            structure = Structure(**declared)
            with KSPSolver(
                options, prefix="elas_", max_it=max_it, rtol=rtol, structure=structure
            ) as s:
                s.set_operator(M)
                info, first = stopwatch(s.solve, b)
                second = stopwatch(s.solve, b)[1]
                x = info.value
                reference = x if reference is None else reference
                s.rtol, s.max_it = 0.0, k
                capped = s.solve(b).value
            results[variant] = {
                "cells": n,
                "unknowns": int(M.shape[0]),
                "variant": variant,
                "block_size": declared.get("block_size", 1),
                "near_nullspace": len(declared.get("near_nullspace", ())),
                "iterations": info.iterations,
                "reason": info.reason,
                "first_solve_s": first,
                "solve_s": second,
                "setup_s": max(first - second, 0.0),
                "relative_residual": float(np.linalg.norm(b - M @ x) / np.linalg.norm(b)),
                "error_at_k": float(np.linalg.norm(capped - reference) / np.linalg.norm(reference)),
            }
            logger.info("n=%d %s: %d iterations", n, variant, info.iterations)
        rows += [results[v] for v in VARIANTS]
    counts = {v: [r["iterations"] for r in rows if r["variant"] == v] for v in VARIANTS}
    return {
        "benchmark": "elasticity",
        "problem": "3D linear elasticity, E = 1, nu = 0.3, unit cube of n^3 Q1 hexahedra, "
        "clamped at x = 0, weight along -z",
        "settings": {**options, "rtol": rtol, "max_it": max_it, "k": k},
        "sizes": list(sizes),
        "rows": rows,
        "growth": {v: c[-1] / c[0] for v, c in counts.items()},
        "target": {"growth.modes": f"<= {TARGET_GROWTH}"},
    }


def format_report(d: dict) -> str:
    """The table `main` prints (and the results page shows)."""
    s = d["settings"]
    header = ["cells", "unknowns", "declared", "iterations", "set-up s", "solve s"]
    header += ["true residual", f"error at K = {s['k']}"]
    rows = []
    for r in d["rows"]:
        declared = {
            "scalar": "nothing",
            "block": f"block size {r['block_size']}",
            "modes": f"block size {r['block_size']}, {r['near_nullspace']} modes",
        }[r["variant"]]
        rows.append((f"{r['cells']}³", r["unknowns"], declared, r["iterations"],
                     f"{r['setup_s']:.2f}", f"{r['solve_s']:.2f}",
                     f"{r['relative_residual']:.1e}", f"{r['error_at_k']:.1e}"))  # fmt: skip
    sizes = d["sizes"]
    growth = ", ".join(f"{v} {g:.2f}×" for v, g in d["growth"].items())
    return (
        f"{d['problem']}; {s['ksp_type'].upper()} + {s['pc_type'].upper()} to rtol "
        f"{s['rtol']:g}\n\n{markdown_table(header, rows)}\n\n"
        f"Iterations on {sizes[-1]}³ over {sizes[0]}³ cells: {growth} "
        f"(target for the modes: ≤ {TARGET_GROWTH}×).\n"
    )


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="prdp-petsc bench elasticity", description=__doc__.split("\n")[0]
    )
    add_out(p, "folder for bench_elasticity.json")
    p.add_argument("--sizes", default="8,16,32", help="cells per axis, comma-separated (8,16,32)")
    p.add_argument("--rtol", type=float, default=1e-8, help="relative tolerance (1e-8)")
    add_k(p, 10, "K of the capped solve")
    add_size_preset(p, "tiny sizes (2,4): a smoke test")
    add_debug(p)
    return p


def main(argv: list[str]) -> int:
    """Run ``bench elasticity``; write ``<out>/bench_elasticity.json``; return 0."""
    args = _parser().parse_args(argv)

    quick = args.preset == "quick"
    sizes = [2, 4] if quick else [int(v) for v in args.sizes.split(",")]
    if len(sizes) < 2 or sorted(sizes) != sizes or min(sizes) < 1:
        raise SystemExit("--sizes needs two or more increasing cell counts, e.g. 8,16,32")
    machine = machine_info()
    with torch_threads(1):
        result, wall = stopwatch(run, sizes, rtol=args.rtol, k=args.k)
    result["wall_s"] = wall
    result["machine"] = {**machine, "load_average_end": load_average()}
    result["settings"]["quick"] = quick
    write_result(args.out, "bench_elasticity.json", result)
    print(format_report(result), end="")
    return 0


# -- the page of a recorded ``bench elasticity`` --------------------------------------------------
def _headline(ds: DataSet) -> list[tuple[str, str]]:
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


KIND = ReportKind(
    name="bench-elasticity",
    reads="bench_elasticity.json",
    title=lambda ds: (
        "GAMG on 3D elasticity: iterations against the mesh, with the rigid-body modes"
    ),
    headline=_headline,
    intro="What `prdp-petsc bench elasticity` printed: CG + GAMG on the same operator with "
    "nothing declared, with `block_size=3`, and with the block size and the six "
    "rigid-body modes as `near_nullspace`; the set-up time is the first solve's time "
    "minus a second solve's, the error at K is a capped solve's against the converged "
    "solution with the modes. What each declaration does is in the docstring of "
    "`prdp_petsc.lab.reports.bench_elasticity` and in the guide "
    "[Vector and mixed problems](../guide/vector.md).",
    output=lambda ds: format_report(ds.main).rstrip("\n"),
    printed=False,
)
