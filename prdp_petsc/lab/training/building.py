"""A scene built for training, seeded (`build_scene`), and its PETSc objects freed
(`release`)."""

from __future__ import annotations

import random

import numpy as np
import torch

from .scene import preset_config, with_prdp_settings

__all__ = ["build_scene", "release", "seed_everything"]


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 - the legacy global state, for such scenes
    torch.manual_seed(seed)


def build_scene(module, preset: str, seed: int, torch_seed: int | None = None):
    """``module.build(config, seed)``, Python and torch seeded with `torch_seed` (default
    `seed`): initial weights from torch, data from the scene's numpy Generator."""
    config = preset_config(module, preset)  # "paper modes=32": a preset, changed
    seed_everything(seed if torch_seed is None else torch_seed)
    return with_prdp_settings(module.build(config, seed), preset, config)


def release(scene) -> None:
    """Free the PETSc objects of a scene's solvers now (distributed ones would wait for
    a collective clean-up at exit)."""
    for solver in scene.solvers:
        solver.destroy()
    from petsc4py import PETSc

    if PETSc.COMM_WORLD.getSize() > 1:
        PETSc.garbage_cleanup(PETSc.COMM_WORLD)
