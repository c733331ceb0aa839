"""A run's folder read back: the record of a run to resume (`recorded_run`,
`check_resume`, `continue_result`) and its trained model (`load_trained`).

`prdp_petsc.lab.training.harness.run` (``resume=DIR``) continues a run from
``DIR/results.json`` and ``DIR/checkpoint.pt`` (`prdp_petsc.lab.training.checkpoint`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from prdp_petsc import InputError

from .building import build_scene
from .checkpoint import CHECKPOINT, load_checkpoint, restore
from .records import RESULTS
from .scene import load_scene

__all__ = ["check_resume", "continue_result", "load_trained", "recorded_run"]

logger = logging.getLogger(__name__)


def recorded_run(folder) -> dict:
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


def check_resume(folder, recorded: dict, scene_file, given: dict, prdp: dict | None) -> None:
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


def continue_result(result: dict, state: dict) -> None:
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
        The ``out`` folder of `prdp_petsc.lab.training.harness.run` (a ``compare``
        run's ``out/<schedule>``).
    module : module, optional
        The scene module, instead of importing the recorded scene file.

    Returns
    -------
    Scene
        ``scene.validate()`` gives the run's last recorded ``val_metric`` (bitwise
        under the recorded ``threads``, see
        `prdp_petsc.lab.training.threads.torch_threads`), and the network or
        parameters in ``scene.optimizer.param_groups`` are the trained ones.  Call
        `prdp_petsc.lab.training.building.release` when done with its solvers.

    Examples
    --------
    >>> scene = load_trained("results/heat2d/prdp")  # doctest: +SKIP
    >>> scene.validate()  # doctest: +SKIP
    """
    recorded = recorded_run(folder)
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
