"""A scene trained once, kept: what the scenes' report commands score and draw."""

from __future__ import annotations

import types
from types import ModuleType

from ..training.harness import run
from ..training.scene import Scene

__all__ = ["train_and_keep"]


def train_and_keep(
    scene: ModuleType, schedule: str, *, preset: str = "quick", seed: int = 0
) -> tuple[dict, Scene]:
    """One `prdp_petsc.lab.training.harness.run` of the loaded scene module `scene`, without
    progress bars or output folder: its record, and the scene it built and trained."""
    scenes = []

    def build_and_keep(config, seed):
        scenes.append(scene.build(config, seed))
        return scenes[-1]

    wrapper = types.SimpleNamespace(
        __name__=scene.__name__,
        __file__=scene.__file__,
        PRESETS=scene.PRESETS,
        build=build_and_keep,
    )
    record = run(scene.__file__, schedule, preset=preset, seed=seed, progress=False, module=wrapper)
    return record, scenes[-1]
