"""One training run: `run` trains a scene once under a schedule.

`run` writes ``results.json`` after every epoch (a run that stops early keeps what it
measured), TensorBoard curves beside it (`prdp_petsc.lab.training.curves`) and
``checkpoint.pt`` (`prdp_petsc.lab.training.checkpoint`), from which
``run(resume=DIR)`` continues it exactly and `load_trained` loads the trained model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from prdp_petsc import PRDP, InputError

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
)
from .loop import interrupted, totals, train
from .parallel import Parallel
from .probe import find_k_full, k_cap, probe, rtol_plan
from .records import RESULTS, to_json, write_json
from .scene import load_scene, preset_config
from .schedules import parse_schedule
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
        ``finished``, ``checkpoint`` and, for scenes that define them, ``rollout`` and
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
            train(
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
            interrupted(result)
            raise
        finally:
            result["solvers"] = [s.describe() for s in scene.solvers]
            result["totals"] = totals(result["epochs"])
            if out is not None:
                write_json(out / RESULTS, result)
            release(scene)
    return result
