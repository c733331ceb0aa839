"""One rank against several: a distributed 3D solve and a training epoch.

``prdp-petsc bench mpi [SCENE_FILE] --out DIR`` starts ``mpiexec -n P`` for every P in
``--ranks`` (default 1 and 2) and writes ``DIR/bench_mpi.json`` with

``solve``
    A capped CG + Jacobi solve of one implicit heat step ``(M + Δt K(κ)) u¹ = M u⁰``
    (κ per element) on the refined tetrahedral ``box3d`` mesh, or with ``--cube N`` the
    unit cube of N³ points, forward and backward (adjoint and ∂L/∂κ) through
    `prdp_petsc.solve` on ``COMM_WORLD``: median times, speed-up over one rank, and per
    rank the peak resident memory, the PETSc Mat's share and the arrays it holds.
    ``--layout replicated`` assembles the whole operator on every rank; ``owned`` has
    rank 0 split the mesh (`prdp_petsc.fem.partition`) and every rank assemble and
    hold its own piece (`prdp_petsc.fem.distributed`).
``epoch``
    Training epochs of SCENE_FILE (default ``demos/heat.py`` on the cube: ``--preset
    quick|paper`` are its ``quick3d|paper3d``, `epoch_scene`) serial, under ``--parallel
    domain`` and ``--parallel batch``: the median epoch time after the first, and the
    speed-up.  ``--epochs 0`` leaves it out.

The page of an owned record adds `scaling_model`, a model of memory and halo traffic
beyond the ranks measured.  A quick preset (``quick3d``) runs tiny sizes (a smoke test); timings
mean something only on an idle machine (one torch thread per rank; the record has the
load average).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..cli.arguments import add_debug, add_k, add_out, add_preset, positive
from ..provenance import machine_info, write_result
from ..subprocesses import child_env
from ..training.scene import merged_scene
from .benchmarking import interleaved, stopwatch
from .kinds import DataSet, ReportKind, markdown_table
from .memory import peak_rss_mb
from .problems import mean_edge_length, warm_spot

__all__ = [
    "KIND",
    "MODEL_RANKS",
    "epoch_scene",
    "format_report",
    "format_scaling_model",
    "main",
    "scaling_model",
]

logger = logging.getLogger(__name__)

MPI_ENV = {
    "OMPI_ALLOW_RUN_AS_ROOT": "1",  # Open MPI refuses root without these two
    "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1",
    "OMPI_MCA_rmaps_base_oversubscribe": "1",
    "OMP_NUM_THREADS": "1",
}
#: rank counts the scaling model extrapolates to
MODEL_RANKS = (64, 256, 1024)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="prdp-petsc bench mpi", description=__doc__.split("\n")[0])
    add_out(p, "folder for bench_mpi.json", required=False)  # the --worker writes --json
    p.add_argument("--ranks", default="1,2", help="rank counts to compare (1,2)")
    p.add_argument("--refine", type=int, default=2, help="refinements of box3d (2: 58 575 nodes)")
    p.add_argument(
        "--cube", type=int, default=0, help="tetrahedral unit cube, N points per axis (N³ nodes)"
    )
    p.add_argument(
        "--layout", choices=["replicated", "owned"], default="replicated",
        help="data layout of the solve benchmark (replicated)",
    )  # fmt: skip
    add_k(p, 200, "K of the capped 3D solve")
    p.add_argument("--repeats", type=positive, default=5, help="timed solves after one warm-up (5)")
    p.add_argument(
        "scene", nargs="?",
        help="scene file of the epoch benchmark (default demos/heat.py on the cube, whose "
        "--preset quick and paper are quick3d and paper3d)",
    )  # fmt: skip
    add_preset(p, "paper", "the scene's preset (paper); quick, quick3d: also tiny sizes")
    p.add_argument("--schedule", default="fixed:96", help="K schedule of the epochs (K_full)")
    p.add_argument(
        "--epochs", type=int, default=3, help="epochs per run, the first warm-up (0: no epochs)"
    )
    p.add_argument("--mpiexec", default=os.environ.get("MPIEXEC", "mpiexec"))
    p.add_argument("--timeout", type=float, default=3600, help="seconds per mpiexec (3600)")
    add_debug(p)
    p.add_argument("--worker", choices=["solve", "epoch"], help=argparse.SUPPRESS)
    p.add_argument("--mode", help=argparse.SUPPRESS)
    p.add_argument("--json", type=Path, help=argparse.SUPPRESS)
    return p


def _mat_mb(mat) -> float:
    """This rank's share of an AIJ Mat in MB: its stored entries (value and column
    index) and row pointers (PETSc's own ``MatInfo.memory`` is not filled in)."""
    from petsc4py import PETSc

    index = np.dtype(PETSc.IntType).itemsize
    nonzeros = mat.getInfo(PETSc.Mat.InfoType.LOCAL)["nz_allocated"]
    return (nonzeros * (8 + index) + (mat.getLocalSize()[0] + 1) * index) / 2**20


def _distinct_mb(arrays) -> float:
    """MB of `arrays`, each memory block counted once."""
    counted = []
    for a in arrays:
        if a is not None and not any(np.shares_memory(a, c) for c in counted):
            counted.append(a)
    return sum(a.nbytes for a in counted) / 2**20


def _mesh(args):
    """The benchmark's mesh: refined box3d, or the unit cube with ``--cube`` points per axis."""
    if args.cube:
        from skfem import MeshTet

        axis = np.linspace(0.0, 1.0, args.cube)
        return MeshTet.init_tensor(axis, axis, axis)
    from prdp_petsc import load_mesh

    return load_mesh("box3d", args.refine)


def _solve_worker(args) -> dict:
    """Time the heat step's solve on this rank's share, in ``args.layout``; measure memory."""
    import torch
    from petsc4py import PETSc
    from skfem import Basis, ElementTetP1

    import prdp_petsc as pp

    torch.set_num_threads(1)
    comm = PETSc.COMM_WORLD
    owned = args.layout == "owned"
    t0 = time.perf_counter()
    record = {"layout": args.layout}
    if owned:  # rank 0 builds and splits the mesh; every rank keeps its own piece
        from prdp_petsc.autograd.owned import sum_over_ranks
        from prdp_petsc.fem.distributed import DistributedParametricMatrix
        from prdp_petsc.fem.partition import PartitionedMesh

        world = comm.tompi4py()
        mesh = _mesh(args) if comm.getRank() == 0 else None
        dt = world.bcast(10.0 * mean_edge_length(mesh) ** 2 if mesh is not None else None, root=0)
        part = PartitionedMesh.distribute(mesh, comm)
        mesh, rows = part.mesh, part.owned_vertices  # owned rows are complete: M u0 is exact
        record["partition_s"] = time.perf_counter() - t0
    else:
        mesh = _mesh(args)
        dt, rows = 10.0 * mean_edge_length(mesh) ** 2, None  # Δt κ / h² = 10
    basis = Basis(mesh, ElementTetP1())
    M = pp.mass_matrix(basis)
    A = dt * pp.diffusion_operator(basis) + M
    u0 = warm_spot(mesh.p)
    b, target = torch.from_numpy((M @ u0)[:rows]), torch.from_numpy(u0[:rows])
    del M
    if owned:
        A = DistributedParametricMatrix.from_local(A, part)
    P = A.local if owned else A  # the operator this rank holds
    held = [P.indptr, P.indices, P.a0, P.G.data, P.G.indices, P.G.indptr]
    held += [P.rows] if owned else []
    record["assembly_s"] = time.perf_counter() - t0
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=args.k, comm=comm)

    def step() -> dict:
        comm.barrier()
        u, forward = stopwatch(pp.solve, A, b, solver, theta=theta)
        comm.barrier()
        loss = 0.5 * ((u - target) ** 2).sum()
        _, backward = stopwatch((sum_over_ranks(loss, comm) if owned else loss).backward)
        comm.barrier()
        theta.grad = None
        return {"forward": forward, "backward": backward}

    times = interleaved({"solve": step}, args.repeats, 1)  # the warm-up: Mat, PC set-up
    sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
    held += [A.values(theta.detach().numpy()), *solver.host_arrays(), b.numpy()]
    held += [sol.value.detach().numpy()] + ([target.numpy()] if owned else [])
    record.update(
        unknowns=int(A.shape[0]),
        nnz=comm.tompi4py().allreduce(int(P.nnz)) if owned else int(P.nnz),
        parameters=int(A.params.size if owned else A.n_params),
        k=args.k,
        iterations=sol.iterations,
        forward_s=float(np.median(times["forward"])),
        backward_s=float(np.median(times["backward"])),
        rows_per_rank=solver.mat.getLocalSize()[0],
        petsc_mat_mb_per_rank=_mat_mb(solver.mat),
        peak_rss_mb_per_rank=peak_rss_mb(),
    )
    record[f"{args.layout}_arrays_mb_per_rank"] = _distinct_mb(held)
    if owned:  # the halo: what one ghost exchange moves into this rank
        record["owned_elements_per_rank"] = int(part.owned_elements)
        record["ghost_vertices_per_rank"] = int(len(part.vertices.ghosts))
        record["ghost_elements_per_rank"] = int(len(part.elements.ghosts))
    return record


def _epoch_worker(args) -> dict:
    from prdp_petsc.lab.training.harness import run

    mode = None if args.mode == "serial" else args.mode
    result = run(args.scene, args.schedule, preset=args.preset, epochs=args.epochs,
                 progress=False, threads=1, parallel=mode)  # fmt: skip
    if result["stopped"]:
        raise RuntimeError(f"the epoch run stopped: {result['stopped']}")
    after_first = result["epochs"][1:] or result["epochs"]
    return {
        "scene": Path(args.scene).stem,
        "preset": args.preset,
        "schedule": args.schedule,
        "epoch_s": float(np.median([e["wall_time"] for e in after_first])),
        "solver_s": float(np.median([e["solver_time"] for e in result["epochs"][1:]] or [0])),
        "val_metric": result["epochs"][-1]["val_metric"],
        "peak_rss_mb_per_rank": peak_rss_mb(),
    }


def _worker(args) -> int:
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    record = _solve_worker(args) if args.worker == "solve" else _epoch_worker(args)
    records = comm.gather(record, root=0)
    if comm.Get_rank() == 0:
        merged = dict(records[0])
        for key in [k for k in merged if k.endswith("_per_rank")]:
            merged[key] = [r[key] for r in records]
        args.json.write_text(json.dumps(merged))
    return 0


def _launch(args, ranks: int, worker: str, mode: str | None = None) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        record = Path(tmp) / "record.json"
        cmd = [args.mpiexec, "-n", str(ranks), sys.executable, "-m", __name__]
        cmd += ["--worker", worker, "--json", str(record), "--refine", str(args.refine)]
        cmd += ["--cube", str(args.cube), "--layout", args.layout]
        cmd += ["--k", str(args.k), "--repeats", str(args.repeats), args.scene]
        cmd += ["--preset", args.preset, "--schedule", args.schedule, "--epochs", str(args.epochs)]
        cmd += ["--mode", mode] if mode else []
        logger.info("running %s", " ".join(cmd))
        # without this process's own MPI runtime variables; a timeout: a rank that
        # failed alone could leave the others waiting
        subprocess.run(cmd, check=True, env=child_env(MPI_ENV), stdout=subprocess.DEVNULL,
                       timeout=args.timeout)  # fmt: skip
        return json.loads(record.read_text())


def epoch_scene(scene: str | None, preset: str) -> tuple[str, str]:
    """The epoch benchmark's scene file and preset: without a scene file, the cube of
    ``demos/heat.py`` that ``demos/heat3d.py`` was (``quick``, ``paper``: ``quick3d``,
    ``paper3d``)."""
    if scene is not None:
        return scene, preset
    return merged_scene("demos/heat3d.py", preset)


def main(argv: list[str]) -> int:
    """Run ``bench mpi``; write ``<out>/bench_mpi.json``; return an exit code."""
    args = _parser().parse_args(argv)
    if args.worker:
        return _worker(args)
    if args.out is None:
        raise SystemExit("prdp-petsc bench mpi: --out is required")
    args.scene, args.preset = epoch_scene(args.scene, args.preset)
    if args.preset.startswith("quick"):  # tiny sizes: a smoke test
        args.refine, args.k, args.repeats, args.epochs = 0, 20, 2, 2
    ranks = [int(r) for r in args.ranks.split(",")]
    if 1 not in ranks:
        ranks.insert(0, 1)
    solve = {str(p): _launch(args, p, "solve") for p in ranks}
    for r in solve.values():
        for side in ("forward", "backward"):
            r[f"speedup_{side}"] = solve["1"][f"{side}_s"] / r[f"{side}_s"]
    epoch = {}
    if args.epochs > 0:
        epoch = {"1": _launch(args, 1, "epoch", "serial")}
        for p in ranks[1:]:
            for mode in ("domain", "batch"):
                epoch[f"{p}-{mode}"] = _launch(args, p, "epoch", mode)
        for record in epoch.values():
            record["speedup"] = epoch["1"]["epoch_s"] / record["epoch_s"]
    result = {
        "benchmark": "mpi",
        "layout": args.layout,
        "mesh": f"cube {args.cube}" if args.cube else f"box3d refine {args.refine}",
        "command": ["prdp-petsc", "bench", "mpi", *argv],
        "machine": machine_info(),
        "solve": solve,
        "epoch": epoch,
    }
    path = write_result(args.out, "bench_mpi.json", result)
    print(format_report(result))
    print(f"written {path}")
    return 0


def format_report(result: dict) -> str:
    """The two tables of ``bench mpi`` as Markdown."""
    solve = result["solve"]
    first = next(iter(solve.values()))
    layout = result.get("layout", "replicated")
    header = ["ranks", "forward s", "backward s", "speed-up fwd / bwd", "rows per rank"]
    header += ["PETSc Mat MB per rank", f"{layout} arrays MB per rank", "peak RSS MB per rank"]
    rows = []
    for p, r in solve.items():
        arrays = r.get("owned_arrays_mb_per_rank") or r["replicated_arrays_mb_per_rank"][:1]
        rows.append((p, f"{r['forward_s']:.3f}", f"{r['backward_s']:.3f}",
                     f"{r['speedup_forward']:.2f} / {r['speedup_backward']:.2f}",
                     ", ".join(map(str, r["rows_per_rank"])), _mb(r["petsc_mat_mb_per_rank"]),
                     _mb(arrays), _mb(r["peak_rss_mb_per_rank"])))  # fmt: skip
    lines = [
        f"3D solve: {result.get('mesh', 'box3d')} P1, {first['unknowns']} unknowns, CG + "
        f"Jacobi, K = {first['k']}, {layout} layout",
        "",
        markdown_table(header, rows),
    ]
    if epoch := result["epoch"]:
        first = epoch["1"]
        header = ["run", "epoch s", "solver s", "speed-up", "val metric", "peak RSS MB per rank"]
        rows = [
            (name, f"{r['epoch_s']:.3f}", f"{r['solver_s']:.3f}", f"{r['speedup']:.2f}",
             f"{r['val_metric']:.6g}", _mb(r["peak_rss_mb_per_rank"]))
            for name, r in epoch.items()
        ]  # fmt: skip
        lines += ["", f"Training epoch: {first['scene']} {first['preset']}, {first['schedule']}"]
        lines += ["", markdown_table(header, rows)]
    return "\n".join(lines)


def _mb(values) -> str:
    """Megabytes per rank: ``"310, 295"``."""
    return ", ".join(f"{m:.0f}" for m in values)


# -- beyond the ranks measured: a model ---------------------------------------------------------
def scaling_model(result: dict, ranks=MODEL_RANKS) -> dict | None:
    """A model (not a measurement) of memory and halo traffic per rank at `ranks`,
    fitted to an owned-layout record with two or more rank counts; None otherwise.

    memory
        ``peak(P) = base + per_unknown · N / P``, least squares over the measured
        ranks of the largest peak but rank 0's (it also read and partitioned the
        mesh; ``rank0_mb`` is how far above the others it was at the largest P).
    halo
        Ghost vertices per rank ``g(P) = c · (N / P)^(2/3)`` (the surface of a
        compact 3D part), c fitted on P ≥ 2; one CG iteration moves 8·g bytes into
        each rank.

    ``rows`` holds, per P, the predicted peak, ghost vertices and halo per iteration at
    the measured N (strong scaling) and at N·P (weak scaling: ``weak_…``).
    """
    measured = {int(p): r for p, r in result.get("solve", {}).items() if r.get("layout") == "owned"}
    if len(measured) < 2 or not all("ghost_vertices_per_rank" in r for r in measured.values()):
        return None
    n = next(iter(measured.values()))["unknowns"]
    ps = sorted(measured)
    peaks = [max(measured[p]["peak_rss_mb_per_rank"][1:] or measured[p]["peak_rss_mb_per_rank"])
             for p in ps]  # fmt: skip
    slope, base = np.polyfit([n / p for p in ps], peaks, 1)
    c = float(np.mean([max(measured[p]["ghost_vertices_per_rank"]) / (n / p) ** (2 / 3)
                       for p in ps if p > 1]))  # fmt: skip
    top = measured[ps[-1]]["peak_rss_mb_per_rank"]
    rows = {
        str(p): {
            "peak_mb_per_rank": float(base + slope * n / p),
            "ghost_vertices_per_rank": c * (n / p) ** (2 / 3),
            "halo_kb_per_iteration": 8 * c * (n / p) ** (2 / 3) / 1024,
            "weak_unknowns": n * p,
            "weak_peak_mb_per_rank": float(base + slope * n),
            "weak_halo_kb_per_iteration": 8 * c * n ** (2 / 3) / 1024,
        }
        for p in ranks
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
    header = ["ranks P", "N", "peak MB per rank", "ghost vertices per rank"]
    header += ["halo kB per CG iteration", "weak scaling: N", "peak MB per rank"]
    header += ["halo kB per iteration"]
    rows = [
        (p, model["unknowns"], f"{r['peak_mb_per_rank']:.0f}",
         f"{r['ghost_vertices_per_rank']:.0f}", f"{r['halo_kb_per_iteration']:.1f}",
         f"{r['weak_unknowns']:.3g}", f"{r['weak_peak_mb_per_rank']:.0f}",
         f"{r['weak_halo_kb_per_iteration']:.1f}")
        for p, r in model["rows"].items()
    ]  # fmt: skip
    return (
        f"Model (not measured), fitted to P = {', '.join(map(str, model['measured_ranks']))} "
        f"at N = {model['unknowns']} unknowns: peak per rank = {model['base_mb']:.0f} MB + "
        f"{1e3 * model['mb_per_unknown']:.2f} kB × N/P; ghost vertices per rank = "
        f"{model['halo_coefficient']:.2f} × (N/P)^(2/3); rank 0's peak was "
        f"{model['rank0_mb']:.0f} MB above the other ranks' (it also read and partitioned "
        f"the whole mesh).\n\n{markdown_table(header, rows)}"
    )


# -- the page of a recorded ``bench mpi`` ---------------------------------------------------------
def _model(ds: DataSet) -> list[str]:
    model = scaling_model(ds.main)
    return [] if model is None else ["## Beyond this machine: a model", format_scaling_model(model)]


def _headline(ds: DataSet) -> list[tuple[str, str]]:
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


KIND = ReportKind(
    name="bench-mpi",
    reads="bench_mpi.json",
    title=lambda ds: (
        f"One rank against several: {ds.main['mesh']}, {ds.main.get('layout', 'replicated')} layout"
    ),
    headline=_headline,
    intro="What `prdp-petsc bench mpi` printed: one capped CG + Jacobi solve (forward) and its "
    "adjoint with ∂L/∂θ (backward), medians of the repeats; 4 ranks on this 2-core "
    "machine are oversubscribed, so their times say nothing, their memory does.",
    output=lambda ds: format_report(ds.main).rstrip("\n"),
    printed=False,
    after=_model,
)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
