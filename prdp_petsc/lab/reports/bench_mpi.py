"""One rank against several: a distributed 3D solve and a training epoch.

``prdp-petsc bench mpi [SCENE_FILE] --out DIR`` starts ``mpiexec -n P`` for every P in
``--ranks`` (default 1 and 2) and writes ``DIR/bench_mpi.json`` with

``solve``
    A capped CG solve of one implicit heat step ``(M + Δt K(κ)) u¹ = M u⁰`` on the
    refined tetrahedral ``box3d`` mesh (κ per element, the operator a
    `ParametricMatrix`), forward and backward (adjoint solve and ∂L/∂κ) through
    `prdp_petsc.solve` on a solver living on ``COMM_WORLD``: the median time of
    each, the speed-up over one rank, and the memory per rank: peak resident
    memory, the PETSc Mat's share (this rank's rows) and the replicated arrays
    every rank holds (the assembly map G, the CSR operator and the solver's copy
    of its values, the full vectors).
``epoch``
    Training epochs of the scene SCENE_FILE (default ``demos/heat3d.py``, ``--preset``
    ``paper``, at its K_full = 96) under ``--parallel domain`` and ``--parallel batch``; the median
    epoch wall time after the first (warm-up) epoch, and the speed-up.  ``--epochs 0``
    leaves it out.

``--layout`` picks how the solve benchmark holds its data (`prdp_petsc.core.parallel`):
``replicated`` (default) assembles the whole operator on every rank; ``owned`` has rank
0 build and split the mesh (METIS, `prdp_petsc.fem.partition`), every rank assemble its
own piece (`prdp_petsc.fem.distributed`) and hold its own rows, with the misfit summed
over the ranks.  ``--cube N`` replaces ``box3d`` by the tetrahedral unit cube with N
points per axis (``skfem.MeshTet.init_tensor``: N³ unknowns; N = 101 gives 1 030 301).

``--preset quick`` runs tiny sizes with the scene's quick preset (a smoke test).
Timings are only meaningful on an otherwise idle machine, with one torch thread
per rank (set here); the record includes the load average.
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

from ..cli.arguments import DeprecatedAlias, DeprecatedFlag, add_debug, positive
from ..provenance import machine_info
from .kinds import DataSet, ReportKind, markdown_table
from .memory import peak_rss_mb
from .scaling import format_scaling_model, scaling_model

__all__ = ["KIND", "format_report", "main", "parse_arguments"]

logger = logging.getLogger(__name__)

MPI_ENV = {
    "OMPI_ALLOW_RUN_AS_ROOT": "1",  # Open MPI refuses root without these two
    "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1",
    "OMPI_MCA_rmaps_base_oversubscribe": "1",
    "OMP_NUM_THREADS": "1",
}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="prdp-petsc bench mpi", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, help="folder for bench_mpi.json")
    p.add_argument("--ranks", default="1,2", help="rank counts to compare (1,2)")
    p.add_argument("--refine", type=int, default=2, help="refinements of box3d (2: 58 575 nodes)")
    p.add_argument(
        "--cube", type=int, default=0, help="tetrahedral unit cube, N points per axis (N³ nodes)"
    )
    p.add_argument(
        "--layout", choices=["replicated", "owned"], default="replicated",
        help="data layout of the solve benchmark (replicated)",
    )  # fmt: skip
    p.add_argument("--k", type=positive, default=200, help="K of the capped 3D solve (200)")
    p.add_argument("--repeats", type=positive, default=5, help="timed solves after one warm-up (5)")
    p.add_argument(
        "scene", nargs="?", default="demos/heat3d.py",
        help="scene file of the epoch benchmark (demos/heat3d.py)",
    )  # fmt: skip
    p.add_argument(
        "--scene", dest="scene_option", action=DeprecatedAlias, new="the positional SCENE_FILE",
        help=argparse.SUPPRESS,
    )  # fmt: skip
    p.add_argument(
        "--preset", default="paper",
        help="the scene's preset (paper); quick also runs tiny sizes (a smoke test)",
    )  # fmt: skip
    p.add_argument("--schedule", default="fixed:96", help="K schedule of the epochs (K_full)")
    p.add_argument(
        "--epochs", type=int, default=3, help="epochs per run, the first warm-up (0: no epochs)"
    )
    p.add_argument("--mpiexec", default=os.environ.get("MPIEXEC", "mpiexec"))
    p.add_argument("--timeout", type=float, default=3600, help="seconds per mpiexec (3600)")
    p.add_argument(
        "--quick", action=DeprecatedFlag, dest="preset", const="quick", new="--preset quick",
        help=argparse.SUPPRESS,
    )  # fmt: skip
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


def _distinct_nbytes(arrays) -> int:
    """Bytes of `arrays`, each memory block counted once."""
    counted, total = [], 0
    for a in arrays:
        if a is not None and not any(np.shares_memory(a, c) for c in counted):
            counted.append(a)
            total += a.nbytes
    return total


def _mesh(args):
    """The benchmark's mesh: refined box3d, or the unit cube with ``--cube`` points per axis."""
    if args.cube:
        from skfem import MeshTet

        axis = np.linspace(0.0, 1.0, args.cube)
        return MeshTet.init_tensor(axis, axis, axis)
    from prdp_petsc import load_mesh

    return load_mesh("box3d", args.refine)


def _u0(points: np.ndarray) -> np.ndarray:
    x, y, z = points
    return np.exp(-20 * ((x - 0.3) ** 2 + (y - 0.6) ** 2 + (z - 0.5) ** 2))


def _timed(comm, repeats: int, forward, backward) -> tuple[list, list]:
    """Times of `forward` and `backward` (its output in), each between barriers."""
    fwd, bwd = [], []
    for _ in range(repeats + 1):  # the first: warm-up (Mat creation, PC set-up)
        comm.barrier()
        t0 = time.perf_counter()
        out = forward()
        comm.barrier()
        t1 = time.perf_counter()
        backward(out)
        comm.barrier()
        fwd.append(t1 - t0)
        bwd.append(time.perf_counter() - t1)
    return fwd, bwd


def _solve_worker(args) -> dict:
    return _owned_solve_worker(args) if args.layout == "owned" else _replicated_solve_worker(args)


def _replicated_solve_worker(args) -> dict:
    import torch
    from petsc4py import PETSc
    from skfem import Basis, ElementTetP1

    import prdp_petsc as pp
    from prdp_petsc.lab.reports.problems import mean_edge_length

    torch.set_num_threads(1)
    comm = PETSc.COMM_WORLD
    t0 = time.perf_counter()
    mesh = _mesh(args)
    basis = Basis(mesh, ElementTetP1())
    dt = 10.0 * mean_edge_length(mesh) ** 2  # Δt κ / h² = 10
    A = dt * pp.diffusion_operator(basis) + pp.mass_matrix(basis)
    u0 = _u0(mesh.p)
    b = torch.from_numpy(pp.mass_matrix(basis) @ u0)
    assembly = time.perf_counter() - t0
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    target = torch.from_numpy(u0)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=args.k, comm=comm)

    def backward(u):
        (0.5 * ((u - target) ** 2).sum()).backward()
        theta.grad = None

    forward, backward = _timed(comm, args.repeats, lambda: pp.solve(A, b, solver, theta=theta),
                               backward)  # fmt: skip
    sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
    u = sol.value
    mat = solver.mat
    replicated = _distinct_nbytes(
        [A.indptr, A.indices, A.a0, A.G.data, A.G.indices, A.G.indptr]
        + [A.values(theta.detach().numpy()), *solver.host_arrays()]
        + [b.numpy(), u.detach().numpy()]
    )
    return {
        "layout": "replicated",
        "unknowns": int(A.shape[0]),
        "nnz": int(A.nnz),
        "parameters": int(A.n_params),
        "k": args.k,
        "iterations": sol.iterations,
        "assembly_s": assembly,
        "forward_s": float(np.median(forward[1:])),
        "backward_s": float(np.median(backward[1:])),
        "rows_per_rank": mat.getLocalSize()[0],
        "petsc_mat_mb_per_rank": _mat_mb(mat),
        "replicated_arrays_mb_per_rank": replicated / 2**20,
        "peak_rss_mb_per_rank": peak_rss_mb(),
    }


def _owned_solve_worker(args) -> dict:
    """The solve of `_replicated_solve_worker` in the owned layout: rank 0 builds and
    splits the mesh, every rank assembles and holds its own piece only."""
    import torch
    from petsc4py import PETSc
    from skfem import Basis, ElementTetP1

    import prdp_petsc as pp
    from prdp_petsc.autograd.owned import sum_over_ranks
    from prdp_petsc.fem.distributed import DistributedParametricMatrix
    from prdp_petsc.fem.partition import PartitionedMesh
    from prdp_petsc.lab.reports.problems import mean_edge_length

    torch.set_num_threads(1)
    comm = PETSc.COMM_WORLD
    world = comm.tompi4py()
    t0 = time.perf_counter()
    mesh = _mesh(args) if comm.getRank() == 0 else None
    dt = world.bcast(10.0 * mean_edge_length(mesh) ** 2 if mesh is not None else None, root=0)
    part = PartitionedMesh.distribute(mesh, comm)
    del mesh
    partition = time.perf_counter() - t0
    basis = Basis(part.mesh, ElementTetP1())
    M = pp.mass_matrix(basis)
    A = DistributedParametricMatrix.from_local(dt * pp.diffusion_operator(basis) + M, part)
    u0 = _u0(part.mesh.p)
    rows = part.owned_vertices  # the owned rows are complete: M u0 on them is exact
    b = torch.from_numpy((M @ u0)[:rows])
    target = torch.from_numpy(u0[:rows])
    del M
    assembly = time.perf_counter() - t0
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=args.k, comm=comm)

    def backward(u):
        sum_over_ranks(0.5 * ((u - target) ** 2).sum(), comm).backward()
        theta.grad = None

    forward, backward = _timed(comm, args.repeats, lambda: pp.solve(A, b, solver, theta=theta),
                               backward)  # fmt: skip
    sol = pp.solve(A, b, solver, theta=theta, return_solution=True)
    u = sol.value
    mat = solver.mat
    P = A.local
    local = _distinct_nbytes(
        [P.indptr, P.indices, P.a0, P.G.data, P.G.indices, P.G.indptr, P.rows]
        + [A.values(theta.detach().numpy()), *solver.host_arrays()]
        + [b.numpy(), u.detach().numpy(), target.numpy()]
    )
    nnz = world.allreduce(int(P.nnz))
    return {
        "layout": "owned",
        "unknowns": int(A.shape[0]),
        "nnz": nnz,
        "parameters": int(A.params.size),
        "k": args.k,
        "iterations": sol.iterations,
        "partition_s": partition,
        "assembly_s": assembly,
        "forward_s": float(np.median(forward[1:])),
        "backward_s": float(np.median(backward[1:])),
        "rows_per_rank": mat.getLocalSize()[0],
        "owned_elements_per_rank": int(part.owned_elements),
        # the halo: what one ghost exchange moves into this rank (vertex values for x,
        # λ; element values for θ and, reversed, for ∂L/∂θ)
        "ghost_vertices_per_rank": int(len(part.vertices.ghosts)),
        "ghost_elements_per_rank": int(len(part.elements.ghosts)),
        "petsc_mat_mb_per_rank": _mat_mb(mat),
        "owned_arrays_mb_per_rank": local / 2**20,
        "peak_rss_mb_per_rank": peak_rss_mb(),
    }


def _epoch_worker(args) -> dict:
    from prdp_petsc.lab.training.harness import run

    mode = None if args.mode == "serial" else args.mode
    result = run(
        args.scene,
        args.schedule,
        preset=args.preset,
        epochs=args.epochs,
        progress=False,
        threads=1,
        parallel=mode,
    )
    walls = [e["wall_time"] for e in result["epochs"]]
    if result["stopped"]:
        raise RuntimeError(f"the epoch run stopped: {result['stopped']}")
    return {
        "scene": Path(args.scene).stem,
        "preset": args.preset,
        "schedule": args.schedule,
        "epoch_s": float(np.median(walls[1:] or walls)),
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
        if mode:
            cmd += ["--mode", mode]
        logger.info("running %s", " ".join(cmd))
        from prdp_petsc.lab.subprocesses import child_env

        env = child_env(MPI_ENV)  # without this process's own MPI runtime variables
        # a timeout: a rank that failed alone could leave the others waiting
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL, timeout=args.timeout)
        return json.loads(record.read_text())


def _speedups(records: dict, key: str) -> dict:
    base = records["1"][key]
    return {p: base / r[key] for p, r in records.items()}


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    """The arguments of ``bench mpi``, the deprecated ``--scene FILE`` read as SCENE_FILE."""
    parser = _parser()
    args = parser.parse_args(argv)
    if args.scene_option is not None:
        if args.scene != parser.get_default("scene"):
            parser.error("give the scene file once (the positional SCENE_FILE)")
        args.scene = args.scene_option
    return args


def main(argv: list[str]) -> int:
    """Run ``bench mpi``; write ``<out>/bench_mpi.json``; return an exit code."""
    args = parse_arguments(argv)
    if args.worker:
        return _worker(args)
    if args.out is None:
        raise SystemExit("prdp-petsc bench mpi: --out is required")
    if args.preset == "quick":  # tiny sizes: a smoke test
        args.refine, args.k, args.repeats, args.epochs = 0, 20, 2, 2
    ranks = [int(r) for r in args.ranks.split(",")]
    if 1 not in ranks:
        ranks.insert(0, 1)
    solve = {str(p): _launch(args, p, "solve") for p in ranks}
    for key in ("forward_s", "backward_s"):
        for p, s in _speedups(solve, key).items():
            solve[p][f"speedup_{key[:-2]}"] = s
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
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "bench_mpi.json"
    path.write_text(json.dumps(result, indent=1))
    print(format_report(result))
    print(f"written {path}")
    return 0


def format_report(result: dict) -> str:
    """The two tables of ``bench mpi`` as Markdown."""
    solve = result["solve"]
    first = next(iter(solve.values()))
    layout = result.get("layout", "replicated")
    mesh = result.get("mesh", "box3d")
    lines = [
        f"3D solve: {mesh} P1, {first['unknowns']} unknowns, CG + Jacobi, K = {first['k']}, "
        f"{layout} layout",
        "",
    ]
    header = ["ranks", "forward s", "backward s", "speed-up fwd / bwd", "rows per rank"]
    header += ["PETSc Mat MB per rank", f"{layout} arrays MB per rank", "peak RSS MB per rank"]
    rows = []
    for p, r in solve.items():
        arrays = r.get("owned_arrays_mb_per_rank") or r["replicated_arrays_mb_per_rank"][:1]
        rows.append((p, f"{r['forward_s']:.3f}", f"{r['backward_s']:.3f}",
                     f"{r['speedup_forward']:.2f} / {r['speedup_backward']:.2f}",
                     ", ".join(map(str, r["rows_per_rank"])), _mb(r["petsc_mat_mb_per_rank"]),
                     _mb(arrays), _mb(r["peak_rss_mb_per_rank"])))  # fmt: skip
    lines.append(markdown_table(header, rows))
    epoch = result["epoch"]
    if not epoch:
        return "\n".join(lines)
    first = epoch["1"]
    lines += [
        "",
        f"Training epoch: {first['scene']} {first['preset']}, {first['schedule']}",
        "",
    ]
    header = ["run", "epoch s", "solver s", "speed-up", "val metric", "peak RSS MB per rank"]
    rows = [
        (name, f"{r['epoch_s']:.3f}", f"{r['solver_s']:.3f}", f"{r['speedup']:.2f}",
         f"{r['val_metric']:.6g}", _mb(r["peak_rss_mb_per_rank"]))
        for name, r in epoch.items()
    ]  # fmt: skip
    return "\n".join([*lines, markdown_table(header, rows)])


def _mb(values) -> str:
    """Megabytes per rank: ``"310, 295"``."""
    return ", ".join(f"{m:.0f}" for m in values)


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
