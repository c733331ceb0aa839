"""Training harness: K schedules, cost accounting, K_full, one training run.

``run`` trains a scene once under a schedule (`parse_schedule`: ``"prdp"``,
``"fixed:K"`` or ``"rtol"``) and writes ``results.json`` after every epoch, so a run
that stops early (a diverged solve, Ctrl-C) keeps everything measured so far, and
``checkpoint.pt`` (`prdp_petsc.lab.training.checkpoint`), from which ``run(resume=DIR)``
continues it exactly and `load_trained` loads the trained model.
`prdp_petsc.lab.training.compare` builds the PRDP-against-K_full comparison on top of it.
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
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from prdp_petsc import PRDP, InputError, NonFiniteError, SolverError, rtol_from_level
from prdp_petsc import find_k_full as probe_k_full

from .checkpoint import CHECKPOINT, load_checkpoint, restore, save_checkpoint
from .parallel import Parallel
from .provenance import provenance
from .scene import load_scene, preset_config, with_prdp_settings
from .schedules import (
    RTOL_FACTOR,
    RTOL_INIT,
    RTOL_MAX_IT_FACTOR,
    Schedule,
    gradient_check,
    parse_schedule,
    rtol_levels,
)

__all__ = [
    "RESULTS",
    "build_scene",
    "check_epochs",
    "find_k_full",
    "load_trained",
    "release",
    "run",
    "to_json",
    "torch_threads",
    "write_json",
]

logger = logging.getLogger(__name__)

#: File name of a run's results in its output folder.
RESULTS = "results.json"


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
    """Seed Python's, numpy's and torch's global generators (the shipped scenes draw
    their data from a numpy Generator of their own; one that draws from numpy's
    global state is then reproducible too, and resumes exactly)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 - the legacy global state, for such scenes
    torch.manual_seed(seed)


def build_scene(module, preset: str, seed: int, torch_seed: int | None = None):
    """``module.build(config, seed)``, Python and torch seeded with `torch_seed` (default
    `seed`): initial weights from torch, data from the scene's numpy Generator."""
    config = preset_config(module, preset)  # "paper modes=32": a preset, changed
    _seed_everything(seed if torch_seed is None else torch_seed)
    return with_prdp_settings(module.build(config, seed), preset, config)


def find_k_full(scene, max_it: int = 100_000) -> int:
    """`prdp_petsc.find_k_full` of the scene's first solver on its probe, at
    ``scene.rtol_full``."""
    system = scene.probe()
    if not (isinstance(system, tuple) and len(system) == 3):
        got = f"a {len(system)}-tuple" if isinstance(system, tuple) else type(system).__name__
        raise TypeError(
            "Scene.probe must return (A, b, x0), with x0=None where the scene's solves "
            f"start from zero; got {got}"
        )
    A, b, x0 = system
    try:
        return probe_k_full(scene.solvers[0], A, b, rtol=scene.rtol_full, x0=x0, max_it=max_it)
    except SolverError as err:
        raise SolverError(f"the scene's solver: {err}", reason=err.reason) from err


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
    scene_file=None,
    schedule: str | None = None,
    *,
    preset: str | None = None,
    epochs: int | None = None,
    seed: int | None = None,
    out=None,
    progress: bool = True,
    threads: int = 1,
    module=None,
    prdp: dict | None = None,
    parallel: str | None = None,
    torch_seed: int | None = None,
    checkpoint_every: int = 1,
    resume=None,
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
        the level that reaches ``rtol_full`` (`rtol_levels`).
    preset, epochs, seed, torch_seed
        Preset name (default ``"quick"``); number of epochs (>= 1; default: the
        scene's); random seed (default 0; of the data and, unless `torch_seed` is
        given, of torch: initial weights, batch order, training noise; `compare`'s
        ``twin`` changes only `torch_seed`).
    out : str or Path, optional
        Output folder for ``results.json`` and ``checkpoint.pt``; with `resume`,
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
        (`prdp_petsc.lab.training.provenance.provenance` of the process that started
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
    epochs = check_epochs(epochs)
    every = positive_int(checkpoint_every, "checkpoint_every")
    recorded = state = None
    if resume is not None:
        recorded = _recorded_run(resume)
        given = {"schedule": schedule, "preset": preset, "seed": seed, "torch_seed": torch_seed}
        _check_resume(resume, recorded, scene_file, given, prdp)
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
    ranks = Parallel(parallel)
    with torch_threads(threads):
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
            _continue_result(result, state)
        out = Path(out) if out is not None and ranks.root else None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
        try:
            if plan.kind == "prdp" and "k_max" not in scene.prdp:  # past K_full buys nothing
                with ranks.solvers():
                    scene.prdp["k_max"] = _k_cap(scene)
            if plan.kind == "auto":  # the default construction: the scene's settings unused
                if ranks.size > 1:
                    raise InputError(
                        "the 'auto' schedule's gradient check runs on one rank; use 'prdp' "
                        "with --parallel"
                    )
                known = (prdp or {}).get("k_full") or ((recorded or {}).get("prdp") or {}).get(
                    "k_full"
                )  # compare's probe, or the resumed run's
                scene.prdp = {"k_full": known or find_k_full(scene)}
            if plan.kind == "rtol":
                with ranks.solvers():
                    result["rtol"] = _rtol_plan(scene, recorded)
                levels = result["rtol"]["levels"]  # the controller's K is the level + 1
                scene.prdp.update(k_init=1, k_step=1, k_min=1, k_max=levels + 1)
            ranks.check_solvers(scene)
            ranks.synchronize(scene)
            result["prdp"] = scene.prdp if plan.kind != "fixed" else None
            _train(
                scene, result, plan, epochs, torch_seed, out, progress and ranks.root, ranks,
                every=every, state=state,
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
                write_json(out / RESULTS, result)
            release(scene)
    return result


def _recorded_run(folder) -> dict:
    """The ``results.json`` of a run to resume (FileNotFoundError without one)."""
    path = Path(folder) / RESULTS
    if not path.is_file():
        raise FileNotFoundError(
            f"no {path}: nothing to resume there (give the --out folder of a run)"
        )
    recorded = json.loads(path.read_text())
    if "scene_file" not in recorded or "requested_epochs" not in recorded:
        raise InputError(f"{path} was written by an older prdp_petsc: it cannot be resumed")
    return recorded


def _check_resume(folder, recorded: dict, scene_file, given: dict, prdp: dict | None) -> None:
    """Refuse to resume a run with settings other than its recorded ones."""
    changed = [
        f"{name}={value!r} (recorded: {recorded[name]!r})"
        for name, value in given.items()
        if value is not None and value != recorded[name]
    ]
    if scene_file is not None and Path(scene_file).stem != recorded["scene"]:
        changed.append(f"scene {Path(scene_file).stem!r} (recorded: {recorded['scene']!r})")
    settings = recorded["prdp"]  # None for a fixed schedule, which ignores `prdp`
    changed += [
        f"prdp {key}={value!r} (recorded: {settings.get(key)!r})"
        for key, value in (prdp or {}).items()
        if settings is not None and (key not in settings or settings[key] != value)
    ]
    if changed:
        raise InputError(
            f"resume: {folder} holds a run with other settings: {', '.join(changed)}; a "
            "resumed run keeps its scene, preset, seeds and schedule (leave them out, or "
            "start a new run in another folder)"
        )


def _continue_result(result: dict, state: dict) -> None:
    """Put the checkpoint's epochs and provenance into a resumed run's `result`."""
    before = state["result"]
    if len(before["epochs"]) != state["epoch"]:  # pragma: no cover - a damaged file
        raise InputError(
            f"the checkpoint records {len(before['epochs'])} epochs, not {state['epoch']}"
        )
    result["epochs"] = list(before["epochs"])
    result["resumed"] = [
        *before.get("resumed", []),
        {"epoch": state["epoch"], "provenance": result["provenance"]},
    ]
    result["provenance"] = before["provenance"]
    result["checkpoint"] = {"file": CHECKPOINT, "epoch": state["epoch"]}


def load_trained(folder, *, module=None):
    """The scene of a finished (or checkpointed) run, with its trained model loaded.

    Rebuilds the scene from ``folder/results.json`` (scene file, preset, seeds),
    loads ``folder/checkpoint.pt`` (`prdp_petsc.lab.training.checkpoint`: parameters,
    optimizer and scheduler state) and sets every solver's ``max_it`` to the K of
    the checkpoint's last epoch, the K its validation ran with (and, after the
    ``rtol`` schedule, ``rtol`` to that epoch's).  Random number
    generators are left alone.

    Parameters
    ----------
    folder : str or Path
        The ``out`` folder of `run` (a ``compare`` run's ``out/<schedule>``).
    module : module, optional
        The scene module, instead of importing the recorded scene file.

    Returns
    -------
    Scene
        ``scene.validate()`` gives the run's last recorded ``val_metric`` (bitwise
        under the recorded ``threads``, see `torch_threads`), and the network or
        parameters in ``scene.optimizer.param_groups`` are the trained ones.  Call
        `release` when done with its solvers.

    Examples
    --------
    >>> scene = load_trained("results/heat2d/prdp")  # doctest: +SKIP
    >>> scene.validate()  # doctest: +SKIP
    """
    recorded = _recorded_run(folder)
    state = load_checkpoint(Path(folder) / CHECKPOINT)
    module = module or load_scene(recorded["scene_file"])
    scene = build_scene(module, recorded["preset"], recorded["seed"], recorded["torch_seed"])
    restore(scene, state)
    trained = state["result"]["epochs"]
    if trained:
        for solver in scene.solvers:
            solver.max_it = trained[-1]["k"]
            if "rtol" in trained[-1]:  # the rtol schedule's last tolerance
                solver.rtol = trained[-1]["rtol"]
    if len(trained) < len(recorded["epochs"]):
        logger.warning(
            "%s: the checkpoint holds %d of the %d recorded epochs (checkpoint_every > 1)",
            folder, len(trained), len(recorded["epochs"]),
        )  # fmt: skip
    return scene


def _rtol_plan(scene, recorded: dict | None) -> dict:
    """The ``rtol`` schedule's levels and cap (a resumed run keeps its recorded ones)."""
    if recorded is not None and recorded.get("rtol"):
        return dict(recorded["rtol"])
    rtol_init = max(RTOL_INIT, scene.rtol_full)
    try:
        k_full = find_k_full(scene)
    except SolverError as err:
        raise SolverError(
            f"the rtol schedule caps its solves at {RTOL_MAX_IT_FACTOR} x K_full, but {err}",
            reason=err.reason,
        ) from err
    return {
        "rtol_init": rtol_init,
        "factor": RTOL_FACTOR,
        "rtol_min": scene.rtol_full,
        "levels": rtol_levels(scene.rtol_full, rtol_init, RTOL_FACTOR),
        "k_full": k_full,
        "max_it_factor": RTOL_MAX_IT_FACTOR,
        "max_it": RTOL_MAX_IT_FACTOR * k_full,
    }


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
    """The epoch loop of `run`: fills ``result["epochs"]`` (and ``stopped``) in place,
    from a checkpoint's `state` if given, saving one every `every` epochs into `out`."""
    from tqdm.auto import tqdm

    generator = torch.Generator().manual_seed(torch_seed)
    check = gradient_check(scene) if plan.kind == "auto" else None
    if plan.kind == "auto":
        controller = PRDP.for_problem(scene.prdp["k_full"])
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
                    following = ranks.agree(controller.update(metric, check=check))
                if check is not None and epoch == epochs - 1:  # the certified end
                    _certify(controller, check, result)
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
            record = {
                "epoch": epoch,
                "k": k,
                "train_loss": float(np.mean(losses)) if losses else math.nan,
                "val_metric": metric,
                "wall_time": wall,
                "fwd_iterations": fwd,
                "adj_iterations": adj,
                "solver_time": solver_time,
            }
            if any(s.pc_lag > 1 for s in scene.solvers):  # what reusing the PC saved
                setups, rebuilds, _ = ranks.totals(
                    sum(s.pc_setups for s in stats), sum(s.pc_quality_rebuilds for s in stats), 0.0
                )
                record.update(pc_setups=setups, pc_quality_rebuilds=rebuilds)
            if rtol is not None:  # what the tolerance bought: solves and real iterations
                fwd_solves, adj_solves, _ = ranks.totals(
                    sum(s.forward_solves for s in stats), sum(s.adjoint_solves for s in stats), 0.0
                )
                record.update(rtol=rtol, rtol_level=level, fwd_solves=fwd_solves,
                              adj_solves=adj_solves)  # fmt: skip
            result["epochs"].append(record)
            bar.set_postfix(K=k, val=f"{metric:.3e}", **({"rtol": f"{rtol:.0e}"} if rtol else {}))
            if controller is not None:
                if levels:  # rtol: the level moves, the cap stays
                    level = following - controller.k_min
                else:
                    k = following
            result["totals"] = _totals(result["epochs"])
            if out is not None:
                done = epoch + 1
                if done % every == 0 or done == epochs:
                    save_checkpoint(
                        out / CHECKPOINT, scene, epoch=done, k=k, controller=controller,
                        generator=generator, result=to_json(result),
                    )  # fmt: skip
                    result["checkpoint"] = {"file": CHECKPOINT, "epoch": done}
                write_json(out / RESULTS, result)
    finally:
        bar.close()


def _certify(controller: PRDP, check, result: dict) -> None:
    """The last epoch's certificate into ``result["certificate"]``."""
    cert = controller.certify(check)
    result["certificate"] = {**asdict(cert), "certified": cert.certified}
    logger.info("%s %s: %s", result["scene"], result["schedule"], cert.describe())


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
        **({"rtol_final": log[-1]["rtol"]} if "rtol" in log[-1] else {}),
    }


def stop_reason(error: BaseException) -> str | None:
    """The ``stopped.reason`` a training run records for `error`, or None to re-raise it.

    A `SolverError` gives PETSc's reason, an `InputError` its kind
    (``INVALID_INPUT``, ``NON_FINITE``, ``STRUCTURE``, ``MESH``); anything else is
    not a recorded outcome.
    """
    if isinstance(error, SolverError | InputError):
        return error.reason
    return None
