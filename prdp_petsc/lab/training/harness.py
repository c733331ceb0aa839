"""One training run: `run` sets a scene up under a schedule and trains it epoch by epoch.

`run` writes ``results.json`` after every epoch (a run that stops early keeps what it
measured), TensorBoard curves beside it (`prdp_petsc.lab.training.curves`) and
``checkpoint.pt`` (`prdp_petsc.lab.training.checkpoint`), from which
``run(resume=DIR)`` continues it exactly and `load_trained` loads the trained model.
A solver outcome (`SolverError`, `InputError`: a diverged solve, a non-finite loss)
stops the run with a ``stopped`` record; any other error propagates.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from prdp_petsc import PRDP, InputError, SolverError
from prdp_petsc.errors import NonFiniteError

from ..parsing import check_epochs, positive_int
from ..provenance import provenance
from .building import build_scene, release
from .checkpoint import (
    CHECKPOINT,
    check_resume,
    continue_result,
    load_checkpoint,
    load_trained,
    recorded_run,
    restore,
    save_checkpoint,
)
from .curves import Curves
from .parallel import Parallel
from .probe import find_k_full, k_cap, probe, rtol_plan
from .records import RESULTS, to_json, write_json
from .scene import load_scene, preset_config
from .schedules import Schedule, gradient_check, parse_schedule, rtol_from_level
from .threads import torch_threads

__all__ = [
    "RESULTS",
    "RunSettings",
    "build_scene",
    "find_k_full",
    "load_trained",
    "release",
    "run",
    "to_json",
    "torch_threads",
    "write_json",
]


logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunSettings:
    """How `run` trains (`run` documents each setting); ``run(scene, schedule,
    preset="paper")`` is short for ``run(scene, schedule, RunSettings(preset="paper"))``."""

    preset: str | None = None
    epochs: int | None = None
    seed: int | None = None
    torch_seed: int | None = None
    prdp: Mapping | None = None
    out: str | Path | None = None
    progress: bool = True
    threads: int = 1
    parallel: str | None = None
    checkpoint_every: int = 1

    def __post_init__(self):
        check_epochs(self.epochs)
        positive_int(self.threads, "threads")
        positive_int(self.checkpoint_every, "checkpoint_every")

    def replace(self, **changes) -> RunSettings:
        """These settings with `changes` (`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)


def run(
    scene_file=None,
    schedule: str | None = None,
    settings: RunSettings | None = None,
    *,
    module=None,
    resume=None,
    **changes,
) -> dict:
    """Train a scene once; return (and write to ``out/results.json``) the per-epoch log.

    Parameters
    ----------
    scene_file : str or Path
        Scene file (`prdp_petsc.lab.training.scene`); with `resume`, default: the
        recorded one.
    schedule : str
        ``"prdp"`` (the default), ``"auto"``, ``"fixed:K"`` or ``"rtol"``
        (`prdp_petsc.lab.training.schedules`).
    settings : RunSettings, optional
        The settings below; keyword arguments (``preset="paper"``) change single ones.
    module : module, optional
        The scene module, instead of importing `scene_file`.
    preset, epochs, seed, torch_seed
        Preset (default ``"quick"``), epochs (default: the scene's), the seed of the
        data (default 0) and of torch (default `seed`: initial weights, batch order).
    out : str or Path, optional
        Folder for ``results.json``, ``checkpoint.pt`` and the TensorBoard files.
    progress : bool
        Show a progress bar.
    threads : int
        torch threads for the run (restored afterwards).
    prdp : dict, optional
        Settings of `prdp_petsc.PRDP` that replace the scene's.  Unless they or the
        scene set ``k_max``, PRDP caps K at K_full (`find_k_full`); ``{"k_max": None}``
        lifts the cap.
    parallel : {None, "domain", "batch"}
        Use the ranks of ``MPI.COMM_WORLD`` (`prdp_petsc.lab.training.parallel`).
    checkpoint_every : int
        Save ``out/checkpoint.pt`` after every this many epochs and after the last.
    resume : str or Path, optional
        Folder of an earlier run: rebuild it with its recorded settings, load its
        checkpoint and train on to `epochs` (default: the recorded number), appending
        to its results; on one thread bitwise as if it had never stopped.

    Returns
    -------
    dict
        The ``results.json`` record: ``epochs`` (per epoch ``k``, ``train_loss``,
        ``val_metric``, ``wall_time``, ``fwd_iterations``, ``adj_iterations``, ...),
        ``totals``, ``config``, ``solvers``, ``provenance``, ``stopped`` (None, or the
        ``epoch``, ``reason`` and ``message`` of a solver outcome or Ctrl-C),
        ``finished``, ``checkpoint``, for the ``auto`` schedule ``certificate`` (the
        end's) and ``checks`` (every check of the run: `prdp_petsc.Certificate`'s
        fields and ``certified``) and, for scenes that define them, ``rollout`` and
        ``uncorrected_rollout``.

    Raises
    ------
    InputError
        `resume` with settings other than the recorded ones, or fewer `epochs` than
        its checkpoint holds.  Errors other than `SolverError` and `InputError`
        propagate: they are bugs, not solver outcomes.
    """
    settings = (settings or RunSettings()).replace(**changes)
    epochs, out, preset = settings.epochs, settings.out, settings.preset
    seed, torch_seed = settings.seed, settings.torch_seed
    prdp = None if settings.prdp is None else dict(settings.prdp)
    recorded = state = None
    if resume is not None:
        recorded = recorded_run(resume)
        given = {"schedule": schedule, "preset": preset, "seed": seed, "torch_seed": torch_seed}
        check_resume(resume, recorded, scene_file, given, prdp)
        state = load_checkpoint(Path(resume) / CHECKPOINT)
        scene_file = scene_file if scene_file is not None else recorded["scene_file"]
        schedule, preset = recorded["schedule"], recorded["preset"]
        seed, torch_seed = recorded["seed"], recorded["torch_seed"]
        epochs = epochs or recorded["requested_epochs"]
        if epochs < state["epoch"]:
            raise InputError(
                f"resume: {resume} holds {state['epoch']} trained epochs, more than "
                f"epochs={epochs}; give at least {state['epoch']}"
            )
        out = resume if out is None else out
    elif scene_file is None:
        raise ValueError("run needs a scene_file (or resume=DIR)")
    schedule = "prdp" if schedule is None else schedule
    preset = "quick" if preset is None else preset
    seed = 0 if seed is None else seed
    torch_seed = seed if torch_seed is None else torch_seed
    plan = parse_schedule(schedule)
    module = module or load_scene(scene_file)
    ranks = Parallel(settings.parallel)
    with torch_threads(settings.threads) as threads:
        with ranks.solvers():
            scene = build_scene(module, preset, seed, torch_seed)
        epochs = epochs or scene.epochs
        if recorded is not None and recorded["prdp"] is not None:
            scene.prdp = dict(recorded["prdp"])  # K_full is not searched again
        scene.prdp = {**scene.prdp, **(prdp or {})}
        result = {
            "scene": Path(scene_file).stem,
            "scene_file": str(Path(scene_file).resolve()),
            "schedule": schedule,
            "preset": preset,
            "config": preset_config(module, preset),  # every setting the scene read
            "seed": seed,
            "torch_seed": torch_seed,
            "threads": threads,
            "parallel": ranks.describe(),
            "provenance": provenance(threads, ranks.size),
            "info": scene.info,
            "solvers": [s.describe() for s in scene.solvers],
            "requested_epochs": epochs,
            "epochs": [],
            "stopped": None,
            "finished": False,
            "checkpoint": None,
        }
        if state is not None:
            if scene.owned_parameters and ranks.size > 1:
                raise InputError(
                    "this scene holds owned parameters (each rank its own part) and its "
                    "checkpoint holds rank 0's: it cannot be resumed on several ranks"
                )
            continue_result(result, state)
        out = Path(out) if out is not None and ranks.root else None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
        try:
            if plan.kind == "prdp" and "k_max" not in scene.prdp:  # past K_full buys nothing
                with ranks.solvers():
                    scene.prdp["k_max"] = k_cap(scene)
            if plan.kind == "auto":  # the default construction: the scene's settings unused
                if ranks.size > 1:
                    raise InputError(
                        "the 'auto' schedule's gradient check runs on one rank; use 'prdp' "
                        "with --parallel"
                    )
                before = (recorded or {}).get("prdp") or {}  # the resumed run's
                given = prdp or {}  # compare's or defaults' probe
                k_full = given.get("k_full") or before.get("k_full")
                start = given.get("k_init") or before.get("k_init")
                if k_full is None or start is None:  # the start comes from the probe's errors
                    measured = probe(scene)
                    k_full = k_full or int(measured)
                    start = start or PRDP.for_problem(measured).k_init
                scene.prdp = {"k_full": int(k_full), "k_init": int(start)}
            if plan.kind == "rtol":
                with ranks.solvers():
                    result["rtol"] = rtol_plan(scene, recorded)
                levels = result["rtol"]["levels"]  # the controller's K is the level + 1
                scene.prdp.update(k_init=1, k_step=1, k_min=1, k_max=levels + 1)
            ranks.check_solvers(scene)
            ranks.synchronize(scene)
            result["prdp"] = scene.prdp if plan.kind != "fixed" else None
            progress = settings.progress and ranks.root
            _train(
                scene, result, plan, epochs, torch_seed, out, progress, ranks,
                every=settings.checkpoint_every, state=state,
            )  # fmt: skip
            if not result["stopped"]:
                if scene.rollout is not None:
                    result["rollout"] = ranks.rollout(scene.rollout)
                if scene.uncorrected_rollout is not None:
                    result["uncorrected_rollout"] = ranks.rollout(scene.uncorrected_rollout)
                result["finished"] = True
        except KeyboardInterrupt:
            epoch = len(result["epochs"])
            logger.error("epoch %d: interrupted (Ctrl-C)", epoch)
            message = f"KeyboardInterrupt during epoch {epoch}; earlier epochs are complete"
            result["stopped"] = {"epoch": epoch, "reason": "interrupted", "message": message}
            raise
        finally:
            result["solvers"] = [s.describe() for s in scene.solvers]
            result["totals"] = totals(result["epochs"])
            if out is not None:
                write_json(out / RESULTS, result)
            release(scene)
    return result


def _train(
    scene,
    result: dict,
    plan: Schedule,
    epochs: int,
    torch_seed: int,
    out,
    progress: bool,
    ranks: Parallel,
    *,
    every: int = 1,
    state: dict | None = None,
) -> None:
    """Fill ``result["epochs"]`` (and ``stopped``) in place, from a checkpoint's `state`
    if given; into `out` a checkpoint every `every` epochs, ``results.json`` and the
    TensorBoard curves after every epoch."""
    from tqdm.auto import tqdm

    generator = torch.Generator().manual_seed(torch_seed)
    check = gradient_check(scene) if plan.kind == "auto" else None
    if plan.kind == "auto":  # `run` has set k_full and k_init
        controller = PRDP.for_problem(**scene.prdp, check=check, epochs=epochs)
    else:
        controller = PRDP(**scene.prdp) if plan.kind != "fixed" else None
    levels = result.get("rtol") if plan.kind == "rtol" else None
    start = 0
    if state is not None:
        restore(scene, state, controller=controller, generator=generator)
        start = state["epoch"]
    k = plan.k if plan.kind == "fixed" else levels["max_it"] if levels else controller.k
    level = controller.level if levels else None  # rtol: the controller's K counts levels
    bar = tqdm(
        range(start, epochs),
        desc=f"{result['scene']} {result['schedule']}",
        initial=start,
        total=epochs,
        disable=None if progress else True,  # None: tqdm hides itself when not a terminal
        leave=False,
    )
    curves = Curves(out, result, start) if out is not None else None
    try:
        for epoch in bar:
            rtol = None
            if levels:  # PRDP's level as PETSc's rtol (the adjoint follows unless set apart)
                rtol = rtol_from_level(level, levels["rtol_init"], levels["factor"],
                                       levels["rtol_min"])  # fmt: skip
            for s in scene.solvers:
                s.max_it = k
                if rtol is not None:
                    s.rtol = rtol
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
                if controller is not None:  # its checks' solves count in this epoch's costs
                    following = ranks.agree(controller.update(metric))
                if check is not None and epoch == epochs - 1:  # the certified end
                    cert = controller.certify()
                    result["certificate"] = {**asdict(cert), "certified": cert.certified}
                    result["checks"] = [
                        {**asdict(c), "certified": c.certified} for c in controller.checks
                    ]
                    logger.info("%s %s: %s", result["scene"], result["schedule"], cert.describe())
            except (SolverError, InputError) as err:  # outcomes, not bugs (prdp_petsc.errors)
                logger.error("epoch %d: %s", epoch, err)
                result["stopped"] = {"epoch": epoch, "reason": err.reason, "message": str(err)}
                return
            wall = time.perf_counter() - t0
            stats = [s.stats for s in scene.solvers]
            names = ["forward_iterations", "adjoint_iterations"]
            if any(s.pc_lag > 1 for s in scene.solvers):  # what reusing the PC saved
                names += ["pc_setups", "pc_quality_rebuilds"]
            if rtol is not None:  # what the tolerance bought: solves and real iterations
                names += ["forward_solves", "adjoint_solves"]
            counts, solver_time = ranks.totals(
                [sum(getattr(s, name) for s in stats) for name in names],
                sum(s.forward_time + s.adjoint_time for s in stats),
            )
            counts = dict(zip(names, counts, strict=True))
            record = {
                "epoch": epoch,
                "k": k,
                "train_loss": float(np.mean(losses)) if losses else math.nan,
                "val_metric": metric,
                "wall_time": wall,
                "fwd_iterations": counts.pop("forward_iterations"),
                "adj_iterations": counts.pop("adjoint_iterations"),
                "solver_time": solver_time,
            }
            if rtol is not None:
                record.update(rtol=rtol, rtol_level=level, fwd_solves=counts.pop("forward_solves"),
                              adj_solves=counts.pop("adjoint_solves"))  # fmt: skip
            record.update(counts)
            result["epochs"].append(record)
            bar.set_postfix(K=k, val=f"{metric:.3e}", **({"rtol": f"{rtol:.0e}"} if rtol else {}))
            if controller is not None:
                if levels:  # rtol: the level moves, the cap stays
                    level = following - controller.k_min
                else:
                    k = following
            result["totals"] = totals(result["epochs"])
            if out is not None:
                done = epoch + 1
                if done % every == 0 or done == epochs:
                    save_checkpoint(
                        out / CHECKPOINT, scene, epoch=done, k=k, controller=controller,
                        generator=generator, result=to_json(result),
                    )  # fmt: skip
                    result["checkpoint"] = {"file": CHECKPOINT, "epoch": done}
                write_json(out / RESULTS, result)
                curves.add(record, result["totals"], controller)
    finally:
        bar.close()
        if curves is not None:
            curves.close()


def _check_finite(value: float, what: str) -> None:
    """A NaN or Inf loss or metric stops the run (`NonFiniteError`), never trains on."""
    if not math.isfinite(value):
        raise NonFiniteError(
            f"{what} is {value}: training cannot continue (a diverged network, a too large "
            "learning rate, or a solve that lost accuracy); earlier epochs are complete"
        )


def totals(log: list[dict]) -> dict:
    """A run's totals over the epochs of `log` and its final and best validation error."""
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
        **({"rtol_final": log[-1]["rtol"]} if "rtol" in log[-1] else {}),
    }
