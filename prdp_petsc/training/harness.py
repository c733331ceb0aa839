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
import operator
import os
import random
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from ..core.results import SolverError
from ..core.solver import KSPSolver
from ..errors import InputError, NonFiniteError, stop_reason
from ..prdp import PRDP
from .parallel import Parallel
from .scene import load_scene, preset_config, with_prdp_settings

__all__ = [
    "build_scene",
    "check_epochs",
    "find_k_full",
    "parse_schedule",
    "release",
    "run",
    "to_json",
    "torch_threads",
    "write_json",
]

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


def positive_int(value, name: str) -> int:
    """``value`` as an int, or ValueError naming `name` unless it is an integer >= 1."""
    try:
        value = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}") from None
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return value


def check_epochs(epochs) -> int | None:
    """Return ``epochs`` (None: the scene's default) or raise if it is not an integer >= 1."""
    return None if epochs is None else positive_int(epochs, "epochs")


@contextmanager
def torch_threads(threads: int) -> Iterator[int]:
    """Run the body with ``torch.set_num_threads(threads)``; restore the old count after.

    torch's default (one thread per core) oversubscribes a machine that other
    processes share, and OpenMP spin-waiting then makes wall times meaningless.
    """
    threads = positive_int(threads, "threads")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield threads
    finally:
        torch.set_num_threads(previous)


def _seed_everything(seed: int) -> None:
    """Seed Python's and torch's global generators (scenes get their own numpy Generator)."""
    random.seed(seed)
    torch.manual_seed(seed)


def build_scene(module, preset: str, seed: int, torch_seed: int | None = None):
    """``module.build(config, seed)``, Python and torch seeded with `torch_seed` (default
    `seed`): initial weights from torch, data from the scene's numpy Generator."""
    config = preset_config(module, preset)  # "paper modes=32": a preset, changed
    _seed_everything(seed if torch_seed is None else torch_seed)
    return with_prdp_settings(module.build(config, seed), preset, config)


def find_k_full(scene, max_it: int = 100_000) -> int:
    """Iterations the scene's solver needs to reach ``scene.rtol_full`` on its probe.

    Uses a clone of the first solver (options, prefix, null spaces), so
    command-line options apply here too.  With a guess x0 in the probe, the count
    is that of a solve from x0 stopped by PETSc's default test, ``‖r_k‖ ≤ rtol
    ‖b‖`` in the KSP's norm (not relative to the smaller initial residual), so a
    good guess also shortens the full-fidelity baseline.
    """
    ref: KSPSolver = scene.solvers[0]
    A, b, *guess = scene.probe()
    b = np.atleast_2d(b)
    x0 = np.atleast_2d(guess[0]) if guess else None
    iterations = []
    with ref.clone(max_it=max_it, rtol=scene.rtol_full) as probe:
        probe.set_operator(A)
        for i, row in enumerate(b):
            if x0 is not None:
                probe.ksp.setConvergenceHistory(max_it + 1, reset=True)
            count = _probe_solve(probe, row)
            if x0 is not None:  # ‖b‖ in the KSP's norm, then the history from x0
                target = scene.rtol_full * probe.ksp.getConvergenceHistory()[0]
                probe.rtol = scene.rtol_full * 1e-3
                _probe_solve(probe, row - A @ x0[i])
                history = probe.ksp.getConvergenceHistory()
                probe.rtol = scene.rtol_full
                reached = np.flatnonzero(history <= target)
                count = int(reached[0]) if len(reached) else count
            iterations.append(count)
    return max(iterations)


def _probe_solve(probe: KSPSolver, row: np.ndarray) -> int:
    probe.solve(row)
    if not probe.last.converged:
        raise SolverError(
            f"the scene's solver did not reach rtol={probe.rtol} in {probe.max_it} "
            f"iterations ({probe.last.reason}); K_full is undefined",
            reason=probe.last.reason,
        )
    return probe.last.iterations


def to_json(value):
    """``value`` as plain JSON types: paths become strings, numpy/torch scalars and
    arrays numbers and lists, other keys and objects their ``str``."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, dict):
        return {_json_key(k): to_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_json(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if hasattr(value, "tolist"):  # numpy scalars and arrays, torch tensors
        return to_json(value.tolist())
    return str(value)


def _json_key(key):
    plain = key is None or isinstance(key, bool | int | float | str)
    return key if plain else str(to_json(key))


def write_json(path: Path, data: dict) -> None:
    """Write ``to_json(data)`` to ``path`` atomically (through a temporary file)."""
    path = Path(path)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(to_json(data), indent=1))
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
    threads: int = 1,
    module=None,
    prdp: dict | None = None,
    parallel: str | None = None,
    torch_seed: int | None = None,
) -> dict:
    """Train a scene once; return (and write to ``out/results.json``) the per-epoch log.

    Parameters
    ----------
    scene_file : str or Path
        Scene file (see `prdp_petsc.training.scene`).
    schedule : str
        ``"prdp"`` or ``"fixed:K"``.
    preset, epochs, seed, torch_seed
        Preset name; number of epochs (>= 1; default: the scene's); random seed (of
        the data and, unless `torch_seed` is given, of torch: initial weights, batch
        order, training noise; `compare`'s ``twin`` changes only `torch_seed`).
    out : str or Path, optional
        Output folder for ``results.json``.
    progress : bool
        Show a progress bar (epoch, K, validation metric).
    threads : int
        torch threads for the run (``torch.set_num_threads``; restored afterwards).
        The default 1 keeps wall times honest on a shared machine.
    prdp : dict, optional
        Settings of `prdp_petsc.PRDP` that replace the scene's; recorded in results.
        Unless they (or the scene) set ``k_max``, a PRDP run caps K at K_full
        (`find_k_full`, one converged solve of the scene's probe): refining past
        full fidelity buys nothing, and a validation error that rises for another
        reason (overfitting, drift) would otherwise ratchet K up without bound.
        ``{"k_max": None}`` lifts the cap; so does a probe that does not converge
        (with a warning).
    parallel : {None, "domain", "batch"}
        Use the ranks of ``MPI.COMM_WORLD`` (start under ``mpiexec``): distributed
        solves, or a split of every mini-batch (`prdp_petsc.training.parallel`).
        Rank 0 writes ``results.json``; every rank returns the same result.

    Returns
    -------
    dict
        ``epochs`` (per epoch: ``k``, ``train_loss``, ``val_metric``, ``wall_time``,
        ``fwd_iterations``, ``adj_iterations``), ``totals``, ``threads``,
        ``solvers`` (`KSPSolver.describe` of every scene solver: prefixes, options,
        and the KSP/PC types PETSc used) and ``stopped``: None, or ``epoch`` (the
        first epoch not completed), ``reason`` (a PETSc reason; ``NON_FINITE`` for a
        NaN or Inf input, loss or metric; ``STRUCTURE``, ``INVALID_INPUT`` for the
        other `prdp_petsc.errors.InputError` kinds; or ``interrupted``) and
        ``message``; ``rollout``, the per-step error of the
        trained model, for scenes that define it.

    Raises
    ------
    Exception
        Anything but a `SolverError` or an `InputError` raised while training (a
        bug in the scene, a plain ``ValueError`` from numpy) propagates: it is not
        a solver outcome, and recording it as one would hide it.
    KeyboardInterrupt
        Re-raised after ``results.json`` records ``stopped: {"reason": "interrupted"}``.
    """
    epochs = check_epochs(epochs)
    fixed_k = parse_schedule(schedule)
    module = module or load_scene(scene_file)
    ranks = Parallel(parallel)
    with torch_threads(threads):
        with ranks.solvers():
            scene = build_scene(module, preset, seed, torch_seed)
        scene.prdp = {**scene.prdp, **(prdp or {})}
        result = {
            "scene": Path(scene_file).stem,
            "schedule": schedule,
            "preset": preset,
            "seed": seed,
            "torch_seed": seed if torch_seed is None else torch_seed,
            "threads": threads,
            "parallel": ranks.describe(),
            "info": scene.info,
            "solvers": [s.describe() for s in scene.solvers],
            "epochs": [],
            "stopped": None,
        }
        out = Path(out) if out is not None and ranks.root else None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
        try:
            if fixed_k is None and "k_max" not in scene.prdp:  # past K_full buys nothing
                with ranks.solvers():
                    scene.prdp["k_max"] = _k_cap(scene)
            ranks.check_solvers(scene)
            ranks.synchronize(scene)
            result["prdp"] = scene.prdp if fixed_k is None else None
            _train(
                scene, result, fixed_k, epochs or scene.epochs,
                seed if torch_seed is None else torch_seed, out, progress and ranks.root, ranks,
            )  # fmt: skip
            if scene.rollout is not None and not result["stopped"]:
                result["rollout"] = ranks.rollout(scene)
        except KeyboardInterrupt:
            epoch = len(result["epochs"])
            logger.error("epoch %d: interrupted (Ctrl-C)", epoch)
            result["stopped"] = {
                "epoch": epoch,
                "reason": "interrupted",
                "message": f"KeyboardInterrupt during epoch {epoch}; earlier epochs are complete",
            }
            raise
        finally:
            result["solvers"] = [s.describe() for s in scene.solvers]
            result["totals"] = _totals(result["epochs"])
            if out is not None:
                write_json(out / "results.json", result)
            release(scene)
    return result


def _k_cap(scene) -> int | None:
    """K_full (at least K₀) as PRDP's cap, or None where the probe does not converge."""
    try:
        return max(find_k_full(scene), scene.prdp.get("k_init", 1))
    except SolverError as err:
        logger.warning("PRDP runs without a cap on K: %s", err)
        return None


def release(scene) -> None:
    """Free the PETSc objects of a scene's solvers now.

    On one rank Python's garbage collector would; distributed PETSc objects are
    only queued for a collective clean-up, so a long ``compare`` would keep every
    run's matrices and KSPs until exit.
    """
    for solver in scene.solvers:
        solver.destroy()
    from petsc4py import PETSc

    if PETSc.COMM_WORLD.getSize() > 1:
        PETSc.garbage_cleanup(PETSc.COMM_WORLD)


def _train(
    scene, result: dict, fixed_k, epochs: int, torch_seed: int, out, progress: bool, ranks: Parallel
) -> None:
    """The epoch loop of `run`: fills ``result["epochs"]`` (and ``stopped``) in place."""
    from tqdm.auto import tqdm

    generator = torch.Generator().manual_seed(torch_seed)
    controller = PRDP(**scene.prdp) if fixed_k is None else None
    k = fixed_k if fixed_k is not None else controller.k
    bar = tqdm(
        range(epochs),
        desc=f"{result['scene']} {result['schedule']}",
        disable=None if progress else True,  # None: tqdm hides itself when not a terminal
        leave=False,
    )
    try:
        for epoch in bar:
            for s in scene.solvers:
                s.max_it = k
                s.reset_stats()
            t0 = time.perf_counter()
            try:
                losses = []
                for batch in scene.batches(epoch, generator):
                    losses.append(ranks.step(scene, batch))
                    _check_finite(losses[-1], f"the training loss of batch {len(losses) - 1}")
                if scene.scheduler is not None:
                    scene.scheduler.step()
                metric = ranks.validate(scene)
                _check_finite(metric, "the validation metric")
            except (SolverError, InputError) as err:  # outcomes, not bugs (prdp_petsc.errors)
                logger.error("epoch %d: %s", epoch, err)
                result["stopped"] = {
                    "epoch": epoch,
                    "reason": stop_reason(err),
                    "message": str(err),
                }
                return
            wall = time.perf_counter() - t0
            stats = [s.stats for s in scene.solvers]
            fwd, adj, solver_time = ranks.totals(
                sum(s.forward_iterations for s in stats),
                sum(s.adjoint_iterations for s in stats),
                sum(s.forward_time + s.adjoint_time for s in stats),
            )
            result["epochs"].append(
                {
                    "epoch": epoch,
                    "k": k,
                    "train_loss": float(np.mean(losses)) if losses else math.nan,
                    "val_metric": metric,
                    "wall_time": wall,
                    "fwd_iterations": fwd,
                    "adj_iterations": adj,
                    "solver_time": solver_time,
                }
            )
            bar.set_postfix(K=k, val=f"{metric:.3e}")
            if controller is not None:
                k = ranks.agree(controller.update(metric))
            result["totals"] = _totals(result["epochs"])
            if out is not None:
                write_json(out / "results.json", result)
    finally:
        bar.close()


def _check_finite(value: float, what: str) -> None:
    """A NaN or Inf loss or metric stops the run (`NonFiniteError`), never trains on."""
    if not math.isfinite(value):
        raise NonFiniteError(
            f"{what} is {value}: training cannot continue (a diverged network, a too large "
            "learning rate, or a solve that lost accuracy); earlier epochs are complete"
        )


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
