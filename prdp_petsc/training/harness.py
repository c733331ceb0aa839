"""Training harness: K schedules, cost accounting, K_full, one training run.

``run`` trains a scene once under a schedule (``"prdp"`` or ``"fixed:K"``) and
writes ``results.json`` after every epoch, so a run that stops early (a diverged
solve, Ctrl-C) keeps everything measured so far.  `prdp_petsc.training.compare` builds
the PRDP-against-K_full comparison on top of it.
"""

from __future__ import annotations

import json
import logging
import math
import random
import time
from pathlib import Path

import numpy as np
import torch

from ..prdp import PRDP
from .scene import load_scene
from ..core.solver import KSPSolver, SolverError

__all__ = ["build_scene", "find_k_full", "parse_schedule", "run"]

logger = logging.getLogger(__name__)


def parse_schedule(schedule: str) -> int | None:
    """``"prdp"`` → None, ``"fixed:K"`` → K."""
    if schedule == "prdp":
        return None
    if schedule.startswith("fixed:"):
        try:
            k = int(schedule.split(":", 1)[1])
        except ValueError:
            k = 0
        if k >= 1:
            return k
    raise ValueError(f"schedule must be 'prdp' or 'fixed:K' with K >= 1, got {schedule!r}")


def _seed_everything(seed: int) -> None:
    """Seed Python's and torch's global generators (scenes get their own numpy Generator)."""
    random.seed(seed)
    torch.manual_seed(seed)


def build_scene(module, preset: str, seed: int):
    if preset not in module.PRESETS:
        raise ValueError(f"preset must be one of {sorted(module.PRESETS)}, got {preset!r}")
    _seed_everything(seed)
    return module.build(dict(module.PRESETS[preset]), seed)


def find_k_full(scene, max_it: int = 100_000) -> int:
    """Iterations the scene's solver needs to reach ``scene.rtol_full`` on its probe.

    Uses a clone of the first solver (options, prefix, null spaces), so
    command-line options apply here too.
    """
    ref: KSPSolver = scene.solvers[0]
    A, b = scene.probe()
    b = np.atleast_2d(b)
    probe = ref.clone(max_it=max_it, rtol=scene.rtol_full)
    probe.set_operator(A)
    iterations = []
    for row in b:
        probe.solve(row)
        if not probe.last.converged:
            raise SolverError(
                f"the scene's solver did not reach rtol={scene.rtol_full} in {max_it} "
                f"iterations ({probe.last.reason}); K_full is undefined",
                reason=probe.last.reason,
            )
        iterations.append(probe.last.iterations)
    return max(iterations)


def write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=float))
    tmp.replace(path)


def run(
    scene_file,
    schedule: str = "prdp",
    *,
    preset: str = "quick",
    epochs: int | None = None,
    seed: int = 0,
    out=None,
    progress: bool = True,
    module=None,
) -> dict:
    """Train a scene once; return (and write to ``out/results.json``) the per-epoch log.

    Parameters
    ----------
    scene_file : str or Path
        Scene file (see `prdp_petsc.training.scene`).
    schedule : str
        ``"prdp"`` or ``"fixed:K"``.
    preset, epochs, seed
        Preset name; number of epochs (default: the scene's); random seed.
    out : str or Path, optional
        Output folder for ``results.json``.
    progress : bool
        Show a progress bar (epoch, K, validation metric).

    Returns
    -------
    dict
        ``epochs`` (per epoch: ``k``, ``train_loss``, ``val_metric``, ``wall_time``,
        ``fwd_iterations``, ``adj_iterations``), ``totals`` and ``stopped`` (None, or
        the epoch and PETSc reason of a diverged solve).
    """
    module = module or load_scene(scene_file)
    fixed_k = parse_schedule(schedule)
    scene = build_scene(module, preset, seed)
    epochs = epochs or scene.epochs
    generator = torch.Generator().manual_seed(seed)
    controller = PRDP(**scene.prdp) if fixed_k is None else None
    k = fixed_k if fixed_k is not None else controller.k
    out = Path(out) if out is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    result = {
        "scene": Path(scene_file).stem,
        "schedule": schedule,
        "preset": preset,
        "seed": seed,
        "info": scene.info,
        "solver": repr(scene.solvers[0]),
        "epochs": [],
        "stopped": None,
    }
    from tqdm.auto import tqdm

    bar = tqdm(
        range(epochs),
        desc=f"{result['scene']} {schedule}",
        disable=None if progress else True,  # None: tqdm hides itself when not a terminal
        leave=False,
    )
    for epoch in bar:
        for s in scene.solvers:
            s.max_it = k
            s.reset_stats()
        t0 = time.perf_counter()
        try:
            losses = []
            for batch in scene.batches(epoch, generator):
                scene.optimizer.zero_grad()
                loss = scene.loss(batch)
                loss.backward()
                scene.optimizer.step()
                losses.append(float(loss.detach()))
            if scene.scheduler is not None:
                scene.scheduler.step()
            metric = float(scene.validate())
        except SolverError as err:
            logger.error("epoch %d: %s", epoch, err)
            result["stopped"] = {"epoch": epoch, "reason": err.reason, "message": str(err)}
            break
        except ValueError as err:  # the bridge's input checks: e.g. the network produced NaN
            logger.error("epoch %d: %s", epoch, err)
            result["stopped"] = {"epoch": epoch, "reason": "INVALID_INPUT", "message": str(err)}
            break
        wall = time.perf_counter() - t0
        stats = [s.stats for s in scene.solvers]
        result["epochs"].append(
            {
                "epoch": epoch,
                "k": k,
                "train_loss": float(np.mean(losses)) if losses else math.nan,
                "val_metric": metric,
                "wall_time": wall,
                "fwd_iterations": sum(s.forward_iterations for s in stats),
                "adj_iterations": sum(s.adjoint_iterations for s in stats),
                "solver_time": sum(s.forward_time + s.adjoint_time for s in stats),
            }
        )
        bar.set_postfix(K=k, val=f"{metric:.3e}")
        if controller is not None:
            k = controller.update(metric)
        result["totals"] = _totals(result["epochs"])
        if out is not None:
            write_json(out / "results.json", result)
    bar.close()
    solver = scene.solvers[0]
    if solver._ksp is not None:  # configured by at least one solve
        fwd, adj = solver.ksp, solver.adjoint_ksp
        result["ksp"] = {
            "ksp_type": fwd.getType(),
            "pc_type": fwd.getPC().getType(),
            "adjoint_ksp_type": adj.getType(),
            "adjoint_pc_type": adj.getPC().getType(),
        }
    result["totals"] = _totals(result["epochs"])
    if out is not None:
        write_json(out / "results.json", result)
    return result


def _totals(log: list[dict]) -> dict:
    if not log:
        return {"epochs": 0}
    return {
        "epochs": len(log),
        "wall_time": sum(e["wall_time"] for e in log),
        "solver_time": sum(e["solver_time"] for e in log),
        "fwd_iterations": sum(e["fwd_iterations"] for e in log),
        "adj_iterations": sum(e["adj_iterations"] for e in log),
        "final_val_error": log[-1]["val_metric"],
        "best_val_error": min(e["val_metric"] for e in log),
        "k_final": log[-1]["k"],
    }
