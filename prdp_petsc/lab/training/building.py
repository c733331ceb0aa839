"""A scene built for training, seeded (`build_scene`), and its PETSc objects freed
(`release`)."""

from __future__ import annotations

import random

import numpy as np
import torch

from .scene import preset_config, with_prdp_settings

__all__ = ["build_scene", "release"]


def build_scene(module, preset: str, seed: int, torch_seed: int | None = None):
    """``module.build(config, seed)``, Python and torch seeded with `torch_seed` (default
    `seed`): initial weights from torch, data from the scene's numpy Generator."""
    config = preset_config(module, preset)  # "paper modes=32": a preset, changed
    torch_seed = seed if torch_seed is None else torch_seed
    random.seed(torch_seed)  # the global generators, for scenes that draw from them
    np.random.seed(torch_seed % 2**32)  # noqa: NPY002
    torch.manual_seed(torch_seed)
    return with_prdp_settings(module.build(config, seed), preset, config)


def release(scene) -> None:
    """Free the PETSc objects of a scene's solvers now (distributed ones would wait for
    a collective clean-up at exit)."""
    for solver in scene.solvers:
        solver.destroy()
    from petsc4py import PETSc

    if PETSc.COMM_WORLD.getSize() > 1:
        PETSc.garbage_cleanup(PETSc.COMM_WORLD)
