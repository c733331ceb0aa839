"""Checkpoints: the whole state of a training run, saved and restored.

`prdp_petsc.lab.training.harness.run` saves ``checkpoint.pt`` (``torch.save``) at the end
of every ``checkpoint_every``-th epoch and of the last one.  It holds what the next
epoch depends on, so that a run resumed from it continues exactly as if it had not
stopped (bitwise, on the same threads and machine):

``parameters``
    The tensors the optimizer trains (``scene.optimizer.param_groups``, in order):
    the model.
``optimizer``, ``scheduler``
    Their ``state_dict()`` (moments, step counts, the current learning rate).
``prdp``
    `prdp_petsc.PRDP.state_dict` (history, EMA, checkpoint, K, the stop flag), or
    None for a fixed schedule.
``epoch``, ``k``
    Epochs completed; the K of the next epoch.
``rng``
    The ``torch.Generator`` of the batch order, torch's global generator, Python's
    ``random`` and numpy's global state.
``result``
    The run's results up to ``epoch`` (what ``results.json`` held then).

A checkpoint is also the saved model: `prdp_petsc.lab.training.harness.load_trained`
rebuilds the scene and loads it.  It holds tensors and plain Python values only and
is read with ``torch.load(weights_only=True)``, which runs no code from the file.

Notes
-----
State a scene keeps outside its optimizer's parameters (buffers such as a batch
norm's running statistics, counters in its closures, a generator of its own) is not
saved: a resumed run rebuilds it as ``build`` makes it.  The shipped scenes keep none.
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch

from prdp_petsc import InputError

__all__ = ["CHECKPOINT", "load_checkpoint", "parameters", "restore", "save_checkpoint"]

#: File name of a run's checkpoint in its output folder.
CHECKPOINT = "checkpoint.pt"

_FORMAT = 1  # raised when the layout below changes


def parameters(scene) -> list[torch.Tensor]:
    """The tensors `scene`'s optimizer trains, in the order of its parameter groups."""
    return [p for group in scene.optimizer.param_groups for p in group["params"]]


def save_checkpoint(
    path, scene, *, epoch: int, k: int, controller, generator: torch.Generator, result: dict
) -> None:
    """Save the training state after `epoch` completed epochs to `path` (atomically).

    Parameters
    ----------
    path : str or Path
        File to write (``DIR/checkpoint.pt``); written through a temporary file, so
        an interrupted save leaves the previous checkpoint whole.
    scene : Scene
        Its optimizer's parameters and state, and its scheduler's, are saved.
    epoch, k : int
        Epochs completed; K of the next epoch.
    controller : PRDP or None
        The schedule's controller (None for a fixed K).
    generator : torch.Generator
        The generator of the batch order.
    result : dict
        The run's results so far, as plain JSON types.
    """
    # numpy's legacy global state, for scenes that draw from it (ours use Generators)
    numpy_state = np.random.get_state(legacy=False)  # noqa: NPY002
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
    """Read a checkpoint `save_checkpoint` wrote (``torch.load(weights_only=True)``).

    Raises
    ------
    FileNotFoundError
        No checkpoint at `path` (a run without an output folder, or one stopped
        before its first checkpoint).
    InputError
        A file of another format.
    """
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
    """Load a checkpoint into a freshly built `scene` (and `controller`, `generator`).

    Parameters, optimizer and scheduler are always restored.  With a `generator`,
    so are the random number generators (its state, torch's, Python's and numpy's),
    for a run that continues; without one they are left alone (a model loaded for
    inference).

    Raises
    ------
    InputError
        The scene's parameters differ in number or shape from the checkpoint's (the
        scene file or its preset changed since), or it has a scheduler where the
        checkpoint has none or the other way round.
    """
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
