"""One training run: `run` trains a scene once under a schedule.

`run` writes ``results.json`` after every epoch, so a run that stops early (a
diverged solve, Ctrl-C) keeps everything measured so far, TensorBoard event files
beside it (`prdp_petsc.lab.training.curves`: ``tensorboard --logdir DIR`` draws the
run as it trains), and ``checkpoint.pt``
(`prdp_petsc.lab.training.checkpoint`), from which ``run(resume=DIR)`` continues it
exactly and `load_trained` loads the trained model.
`prdp_petsc.lab.training.compare` builds the PRDP-against-K_full comparison on top of it.

The pieces live one idea a module, and this one re-exports the names a user of a run
needs:

* `prdp_petsc.lab.training.building`: `build_scene` (seeded), `release`;
* `prdp_petsc.lab.training.probe`: `find_k_full` and what the schedules take from it;
* `prdp_petsc.lab.training.loop`: the epoch loop and its records;
* `prdp_petsc.lab.training.curves`: the run's TensorBoard curves;
* `prdp_petsc.lab.training.resume`: a run folder read back, `load_trained`;
* `prdp_petsc.lab.training.records`: ``results.json``, `to_json`, `write_json`;
* `prdp_petsc.lab.training.threads`: `torch_threads`;
* `prdp_petsc.lab.training.schedules`: `parse_schedule` and the schedules' constants.
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
from .checkpoint import CHECKPOINT, load_checkpoint
from .loop import interrupted, totals, train
from .parallel import Parallel
from .probe import find_k_full, k_cap, probe, rtol_plan
from .records import RESULTS, to_json, write_json
from .resume import check_resume, continue_result, load_trained, recorded_run
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
    """How `run` trains: what it trains with, and where and how it runs.

    What is trained (recorded in ``results.json``; a resumed run keeps its own):
    ``preset`` (default ``"quick"``), ``epochs`` (>= 1; default: the scene's),
    ``seed`` (default 0), ``torch_seed`` (default ``seed``) and ``prdp`` (settings of
    `prdp_petsc.PRDP` that replace the scene's).  How and where it runs: ``out``,
    ``progress``, ``threads`` (>= 1), ``parallel`` and ``checkpoint_every`` (>= 1).
    `run` documents each.  ``run(scene, schedule, preset="paper")`` is short for
    ``run(scene, schedule, RunSettings(preset="paper"))``.
    """

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
        Scene file (see `prdp_petsc.lab.training.scene`); with `resume`, default: the
        recorded one.
    schedule : str
        ``"prdp"`` (the default), ``"fixed:K"`` or ``"rtol"`` (`parse_schedule`).
        ``"rtol"`` runs every scene solver with PETSc's rtol test (``‖r‖ ≤ rtol ‖b‖``,
        ``atol`` 0) under ``max_it`` = `RTOL_MAX_IT_FACTOR` × K_full, and rtol =
        ``rtol_from_level(level, RTOL_INIT, RTOL_FACTOR, rtol_min=scene.rtol_full)``
        (0.1, 0.01, ... down to the scene's own tolerance): a `prdp_petsc.PRDP` with
        the scene's plateau settings and ``k_init = k_step = k_min = 1`` raises the
        level (``controller.level``) by one where it would raise K, and stops at
        the level that reaches ``rtol_full``
        (`prdp_petsc.lab.training.schedules.rtol_levels`).
    settings : RunSettings, optional
        The settings below, grouped; keyword arguments (``preset="paper"``) change
        single ones.
    module : module, optional
        The scene module, instead of importing `scene_file`.
    preset, epochs, seed, torch_seed
        Preset name (default ``"quick"``); number of epochs (>= 1; default: the
        scene's); random seed (default 0; of the data and, unless `torch_seed` is
        given, of torch: initial weights, batch order, training noise; `compare`'s
        ``twin`` changes only `torch_seed`).
    out : str or Path, optional
        Output folder for ``results.json``, ``checkpoint.pt`` and the TensorBoard
        event files (`prdp_petsc.lab.training.curves.Curves`); with `resume`,
        default: the `resume` folder.
    progress : bool
        Show a progress bar (epoch, K, validation metric).
    threads : int
        torch threads for the run (``torch.set_num_threads``; restored afterwards).
        The default 1 keeps wall times honest on a shared machine.
    prdp : dict, optional
        Settings of `prdp_petsc.PRDP` that replace the scene's; recorded in results.
        For ``"rtol"`` its ``k_init``, ``k_step``, ``k_min`` and ``k_max`` count
        rtol levels and are set by the schedule.
        Unless they (or the scene) set ``k_max``, a PRDP run caps K at K_full
        (`find_k_full`, one converged solve of the scene's probe): refining past
        full fidelity buys nothing, and a validation error that rises for another
        reason (overfitting, drift) would otherwise ratchet K up without bound.
        ``{"k_max": None}`` lifts the cap; so does a probe that does not converge
        (with a warning).
    parallel : {None, "domain", "batch"}
        Use the ranks of ``MPI.COMM_WORLD`` (start under ``mpiexec``): distributed
        solves, or a split of every mini-batch (`prdp_petsc.lab.training.parallel`).
        Rank 0 writes ``results.json`` and ``checkpoint.pt``; every rank returns
        the same result.
    checkpoint_every : int
        Save ``out/checkpoint.pt`` (`prdp_petsc.lab.training.checkpoint`) after every
        this many epochs (>= 1) and after the last one.  A save (``torch.save`` of
        the parameters, optimizer and random states and the results so far) is not
        counted in an epoch's ``wall_time``; it matters only where epochs take
        milliseconds, as on the quick presets: raise it there.
    resume : str or Path, optional
        Folder of an earlier run (its ``results.json`` and ``checkpoint.pt``):
        rebuild its scene with the recorded preset, seeds, schedule and PRDP
        settings, load the checkpoint and train on to `epochs` (default: the
        recorded number; a finished run given more continues), appending to its
        results.  On one thread the epochs equal those of a run that never
        stopped, bitwise; epochs after the checkpoint that ``results.json`` already
        held (with ``checkpoint_every > 1``) are trained again.  Every rank of a
        ``parallel`` run reads the same files.

    Returns
    -------
    dict
        ``epochs`` (per epoch: ``k``, ``train_loss``, ``val_metric``, ``wall_time``,
        ``fwd_iterations``, ``adj_iterations``, the iterations PETSc ran; under
        ``"rtol"`` also ``rtol``, ``rtol_level``, ``fwd_solves`` and ``adj_solves``,
        with ``k`` the cap; where a scene solver reuses its PC (``pc_lag`` > 1) also
        ``pc_setups`` and ``pc_quality_rebuilds``), ``totals``; under ``"rtol"``,
        ``rtol`` (``rtol_init``, ``factor``, ``rtol_min``, ``levels``, ``k_full``,
        ``max_it_factor``, ``max_it``); ``threads``, ``config``
        (the preset's settings, as changed by the preset string), ``provenance``,
        ``solvers`` (`KSPSolver.describe` of every scene solver: prefixes, options,
        and the KSP/PC types PETSc used) and ``stopped``: None, or ``epoch`` (the
        first epoch not completed), ``reason`` (a PETSc reason; ``NON_FINITE`` for a
        NaN or Inf input, loss or metric; ``STRUCTURE``, ``INVALID_INPUT`` for the
        other `prdp_petsc.errors.InputError` kinds; or ``interrupted``) and
        ``message``; ``rollout``, the per-step error of the trained model, and
        ``uncorrected_rollout``, that of the solver alone, for scenes that define
        them; ``requested_epochs``; ``finished`` (True once all
        of them trained and the rollout is recorded); ``checkpoint`` (``file`` and
        ``epoch`` of the last save, or None); ``scene_file``; ``provenance``
        (`prdp_petsc.lab.provenance.provenance` of the process that started
        the run) and, after a resume, ``resumed``: per resume the ``epoch`` it
        started from and its ``provenance``.

    Raises
    ------
    Exception
        Anything but a `SolverError` or an `InputError` raised while training (a
        bug in the scene, a plain ``ValueError`` from numpy) propagates: it is not
        a solver outcome, and recording it as one would hide it.
    KeyboardInterrupt
        Re-raised after ``results.json`` records ``stopped: {"reason": "interrupted"}``.
    FileNotFoundError
        `resume` names a folder without ``results.json`` or ``checkpoint.pt``.
    InputError
        `resume` with a `scene_file`, `schedule`, `preset`, `seed`, `torch_seed` or
        `prdp` setting other than the recorded one, or with `epochs` fewer than
        the checkpoint's.
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
