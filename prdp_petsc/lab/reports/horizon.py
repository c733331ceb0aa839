"""Memory and time of m-step training against m (`prdp_petsc.lab.training.unroll`).

``prdp-petsc horizon SCENE_FILE --preset P --m 2 4 8 16 --k K --out DIR`` trains the
scene with ``unroll = m`` for ``--epochs`` epochs at a fixed ``max_it = K``, with and
without activation checkpointing (preset key ``checkpoint``), each row in a fresh process
with one torch thread, and writes ``DIR/horizon.json``: per row the epoch times, the time
per unrolled step, the resident size when training starts, its peak while training
(``VmHWM``, reset at the start) and the most bytes autograd kept for one batch's backward
pass (`prdp_petsc.lab.training.unroll.SavedTensorMeter`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..cli.arguments import add_debug, add_epochs, add_k, add_out, add_preset, positive
from ..provenance import write_result
from .kinds import DataSet, ReportKind, text_table
from .memory import peak_rss_mb, reset_peak

__all__ = ["KIND", "format_horizon_report", "horizon_row", "main"]


def horizon_row(scene_file: str, preset: str, m: int, *, checkpoint: bool, k: int, epochs: int):
    """One row of the report, measured in this process (module notes)."""
    import torch

    from ..training.building import build_scene
    from ..training.scene import load_scene
    from ..training.unroll import SavedTensorMeter

    torch.set_num_threads(1)
    module = load_scene(scene_file)
    name = f"{preset} unroll={m} checkpoint={'true' if checkpoint else 'false'}"
    scene = build_scene(module, name, 0)
    for solver in scene.solvers:
        solver.max_it = k
    generator = torch.Generator().manual_seed(0)
    start = peak_rss_mb()
    reset_peak()  # building the data does not count
    times, saved, windows = [], 0, 0
    for epoch in range(epochs):
        tic = time.perf_counter()
        for batch in scene.batches(epoch, generator):
            scene.optimizer.zero_grad()
            meter = SavedTensorMeter()
            with meter():
                scene.loss(batch).backward()
            scene.optimizer.step()
            saved = max(saved, meter.peak)
            windows += len(batch) if epoch == 0 else 0
        times.append(time.perf_counter() - tic)
    return {
        "m": m,
        "checkpoint": checkpoint,
        "k": k,
        "windows": windows,
        "epoch_seconds": times,
        "seconds_per_step": float(np.median(times)) / (windows * m),
        "rss_at_start_mb": start,
        "peak_rss_mb": max(start, peak_rss_mb()),
        "saved_tensors_mb": saved / 2**20,
    }


def format_horizon_report(report: dict) -> str:
    """The report as the table the command prints."""
    header = ["m", "ckpt", "windows", "s/epoch", "ms/step", "RSS start", "peak RSS", "growth",
              "saved MB"]  # fmt: skip
    rows = [
        (r["m"], "yes" if r["checkpoint"] else "no", r["windows"],
         f"{float(np.median(r['epoch_seconds'])):.2f}", f"{1e3 * r['seconds_per_step']:.2f}",
         f"{r['rss_at_start_mb']:.0f}", f"{r['peak_rss_mb']:.0f}",
         f"{r['peak_rss_mb'] - r['rss_at_start_mb']:.0f}", f"{r['saved_tensors_mb']:.2f}")
        for r in report["rows"]
    ]  # fmt: skip
    title = f"{report['scene']} {report['preset']}, K = {report['k']}, one thread"
    return title + "\n" + text_table(header, rows)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="prdp-petsc horizon", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("scene", help="scene file with the preset keys unroll and checkpoint")
    add_preset(parser)
    parser.add_argument(
        "--m", type=positive, nargs="+", default=[2, 4, 8, 16], help="unroll lengths"
    )
    add_k(parser, 20, "fixed K of every solve")
    add_epochs(parser, 2, "epochs per row")
    add_out(parser, "folder for horizon.json", required=False)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--no-checkpoint", action="store_true", help=argparse.SUPPRESS)
    add_debug(parser)
    return parser


def main(argv: list[str]) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.worker:  # one row in this process: peak memory is per process
        row = horizon_row(
            args.scene, args.preset, args.m[0], checkpoint=not args.no_checkpoint, k=args.k,
            epochs=args.epochs,
        )  # fmt: skip
        print(json.dumps(row))
        return 0
    rows = []
    for m in args.m:
        for checkpoint in (True, False):
            command = [sys.executable, "-m", "prdp_petsc.lab.cli", "horizon", args.scene,
                       "--worker", "--preset", args.preset, "--m", str(m), "--k", str(args.k),
                       "--epochs", str(args.epochs), "--debug"]  # fmt: skip
            if not checkpoint:
                command.append("--no-checkpoint")
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode:
                raise RuntimeError(f"m = {m}: {done.stderr.strip().splitlines()[-1]}")
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    report = {"scene": Path(args.scene).name, "preset": args.preset, "k": args.k, "rows": rows}
    print(format_horizon_report(report))
    if args.out:
        write_result(args.out, "horizon.json", report)
    return 0


# -- the page of a recorded ``horizon`` run -------------------------------------------------------
def _headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    rows = {(r["m"], r["checkpoint"]): r for r in d["rows"]}
    ms = sorted({m for m, _ in rows})
    lo, hi = ms[0], ms[-1]
    if (lo, True) not in rows or (hi, True) not in rows:
        return []
    a, b = rows[lo, True], rows[hi, True]
    growth = [r["peak_rss_mb"] - r["rss_at_start_mb"] for r in (a, b)]
    return [
        (
            f"{d['scene']} {d['preset']}: peak memory of m = {hi} training against m = {lo}, "
            "checkpointed",
            f"{b['peak_rss_mb']:.0f} MB against {a['peak_rss_mb']:.0f} MB "
            f"({b['peak_rss_mb'] / a['peak_rss_mb']:.2f}×; while training +{growth[1]:.0f} "
            f"against +{growth[0]:.0f} MB)",
        )
    ]


KIND = ReportKind(
    name="horizon",
    reads="horizon.json",
    title=lambda ds: (
        f"Memory and time against the unroll length: {ds.main['scene']} {ds.main['preset']}"
    ),
    headline=_headline,
    intro="What `prdp-petsc horizon` printed: m-step training at a fixed K, each row in a "
    "fresh process with one torch thread; `growth` is the peak resident size while "
    "training minus the size when training started, `saved MB` what autograd kept "
    "for one batch's backward pass:",
    output=lambda ds: format_horizon_report(ds.main).rstrip("\n"),
)
