"""Checkpoints: a training run's whole state saved (`save_checkpoint`), and a run's
folder read back, to resume it (`recorded_run`, `check_resume`, `continue_result`)
or to load its trained model (`load_trained`).

`prdp_petsc.lab.training.harness.run` saves ``checkpoint.pt`` after every
``checkpoint_every``-th epoch and the last one.  It holds what the next epoch depends
on, so that a resumed run continues bitwise as if it had not stopped (same threads and
machine): the optimizer's parameters (the model), the optimizer's, scheduler's and
`prdp_petsc.PRDP`'s ``state_dict()``, the epochs completed and the next K, the random
states (batch order, torch, Python, numpy) and the results so far.  It holds tensors
and plain values only, read with ``torch.load(weights_only=True)``.  State a scene
keeps outside its optimizer (buffers, closures) is rebuilt as ``build`` makes it.
"""

from __future__ import annotations

import json
import logging
import random
from pathlib import Path

import numpy as np
import torch

from prdp_petsc import InputError

from .building import build_scene
from .records import RESULTS
from .scene import load_scene, merged_scene

__all__ = [
    "CHECKPOINT",
    "check_resume",
    "continue_result",
    "load_checkpoint",
    "load_trained",
    "parameters",
    "recorded_run",
    "restore",
    "save_checkpoint",
]

logger = logging.getLogger(__name__)

#: File name of a run's checkpoint in its output folder.
CHECKPOINT = "checkpoint.pt"

_FORMAT = 1  # raised when the layout below changes


def parameters(scene) -> list[torch.Tensor]:
    """The tensors `scene`'s optimizer trains, in the order of its parameter groups."""
    return [p for group in scene.optimizer.param_groups for p in group["params"]]


def save_checkpoint(
    path, scene, *, epoch: int, k: int, controller, generator: torch.Generator, result: dict
) -> None:
    """Save the state after `epoch` completed epochs, with the next epoch's `k`, the
    `controller` (None for a fixed K), the batch order's `generator` and the JSON
    `result` so far, to `path` (through a temporary file: a save is whole or absent)."""
    numpy_state = np.random.get_state(legacy=False)  # noqa: NPY002 - for scenes that use it
    numpy_state["state"] = {
        "key": numpy_state["state"]["key"].tolist(),
        "pos": int(numpy_state["state"]["pos"]),
    }
    scheduler = scene.scheduler
    state = {
        "format": _FORMAT,
        "epoch": epoch,
        "k": k,
        "parameters": [p.detach().clone() for p in parameters(scene)],
        "optimizer": scene.optimizer.state_dict(),
        "scheduler": None if scheduler is None else scheduler.state_dict(),
        "prdp": None if controller is None else controller.state_dict(),
        "rng": {
            "batch_order": generator.get_state(),
            "torch": torch.get_rng_state(),
            "python": random.getstate(),
            "numpy": numpy_state,
        },
        "result": result,
    }
    path = Path(path)
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_checkpoint(path) -> dict:
    """Read a checkpoint `save_checkpoint` wrote (FileNotFoundError without one,
    InputError for a file of another format)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"no checkpoint {path}: nothing to resume or load (the run stopped before "
            "its first checkpoint, or wrote no files); start it again without resume"
        )
    state = torch.load(path, weights_only=True)
    if not isinstance(state, dict) or state.get("format") != _FORMAT:
        raise InputError(f"{path} is not a prdp_petsc checkpoint of format {_FORMAT}")
    return state


def restore(
    scene, state: dict, *, controller=None, generator: torch.Generator | None = None
) -> None:
    """Load a checkpoint into a freshly built `scene` (parameters, optimizer, scheduler),
    its `controller` and, with a `generator` (a run that continues), the random states.

    InputError where the scene's parameters or scheduler differ from the checkpoint's
    (the scene file or its preset changed since)."""
    saved, params = state["parameters"], parameters(scene)
    shapes = [tuple(p.shape) for p in params]
    if [tuple(p.shape) for p in saved] != shapes:
        raise InputError(
            f"the checkpoint holds {len(saved)} parameter tensors of shapes "
            f"{[tuple(p.shape) for p in saved]}, the scene builds {len(params)} of shapes "
            f"{shapes}: the scene file or its preset changed since the run was saved"
        )
    if (state["scheduler"] is None) != (scene.scheduler is None):
        raise InputError(
            "the checkpoint and the scene disagree on a learning-rate scheduler: the "
            "scene file changed since the run was saved"
        )
    with torch.no_grad():
        for p, value in zip(params, saved, strict=True):
            p.copy_(value)
    scene.optimizer.load_state_dict(state["optimizer"])
    if scene.scheduler is not None:
        scene.scheduler.load_state_dict(state["scheduler"])
    if controller is not None:
        controller.load_state_dict(state["prdp"])
    if generator is not None:
        rng = state["rng"]
        generator.set_state(rng["batch_order"])
        torch.set_rng_state(rng["torch"])
        random.setstate(rng["python"])
        numpy_state = dict(rng["numpy"])
        numpy_state["state"] = {
            "key": np.array(numpy_state["state"]["key"], dtype=np.uint32),
            "pos": numpy_state["state"]["pos"],
        }
        np.random.set_state(numpy_state)  # noqa: NPY002


def recorded_run(folder) -> dict:
    """The ``results.json`` of a run to resume (FileNotFoundError without one); a run of
    a scene file since merged into another names the new one (`merged_scene`)."""
    path = Path(folder) / RESULTS
    if not path.is_file():
        raise FileNotFoundError(
            f"no {path}: nothing to resume there (give the --out folder of a run)"
        )
    recorded = json.loads(path.read_text())
    if "scene_file" not in recorded or "requested_epochs" not in recorded:
        raise InputError(f"{path} was written by an older prdp_petsc: it cannot be resumed")
    if not Path(recorded["scene_file"]).is_file():  # perhaps merged into another since
        scene_file, preset = merged_scene(recorded["scene_file"], recorded["preset"])
        recorded.update(scene_file=scene_file, scene=Path(scene_file).stem, preset=preset)
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
    if len(before["epochs"]) != state["epoch"]:  # a damaged file
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
    """The scene of a finished (or checkpointed) run in `folder`, its trained model loaded.

    The scene is rebuilt from ``folder/results.json`` (or from `module`), the
    checkpoint's parameters loaded and every solver's ``max_it`` (and, after the
    ``rtol`` schedule, ``rtol``) set to the last trained epoch's, so that
    ``scene.validate()`` gives its ``val_metric``.  Random states are left alone;
    `prdp_petsc.lab.training.building.release` frees the solvers.

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
