"""Scenes: one learning problem each, described in a Python file.

A scene file (the shipped ones live in ``demos/``) defines

``PRESETS``
    ``{"quick": {...}, "paper": {...}}``: plain dicts of settings (sizes, epochs,
    learning rate, ...), ``quick`` for tests, ``paper`` for the reference settings.
    Every preset names the keys of the first one (`check_presets`).
``build(config: dict, seed: int) -> Scene``
    builds the physics, data, network, loss and validation metric of one preset's
    settings ``config`` (`preset_config`; a key it lacks raises a ``KeyError`` that
    names the preset).
``COMMANDS`` (optional)
    ``{"adjoint": adjoint_command, ...}``: the scene's own commands besides ``run`` and
    ``compare``, run by ``prdp-petsc scene SCENE_FILE NAME [ARGS]`` and ``python
    SCENE_FILE NAME [ARGS]``.  Each function receives an ``argparse.ArgumentParser``
    (with ``--debug``), adds its arguments and returns the function that runs the
    parsed arguments and returns the exit status; its docstring's first line is the
    command's summary.  An argument ``--preset`` is checked against ``PRESETS``.

A preset name may carry changed settings, ``"paper modes=32 k_step=10"``
(`preset_config`; the command line's ``--set modes=32``): each value takes the type
the presets give its key.  A key that names a setting of `prdp_petsc.PRDP` also goes
into ``Scene.prdp`` (`with_prdp_settings`).  The harness
(`prdp_petsc.lab.training.harness`) does the rest.
"""

from __future__ import annotations

import ast
import importlib.util
import inspect
import logging
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

import torch

from prdp_petsc import PRDP, KSPSolver

__all__ = [
    "MERGED_SCENES",
    "PRDP_SETTINGS",
    "Scene",
    "Settings",
    "check_presets",
    "load_scene",
    "merged_scene",
    "preset_config",
    "shuffled_batches",
    "with_prdp_settings",
]

logger = logging.getLogger(__name__)


@dataclass
class Scene:
    """What the harness needs from a learning problem.

    Parameters
    ----------
    solvers : list of KSPSolver
        The capped solvers whose ``max_it`` the schedule controls.
    optimizer : torch.optim.Optimizer
        Optimises whatever the scene trains (network weights, or θ itself).
    batches : callable ``(epoch, generator) -> iterable``
        Training batches of one epoch; `generator` is a seeded ``torch.Generator``.
    loss : callable ``batch -> torch.Tensor``
        Scalar training loss of one batch (through the solvers); the harness
        back-propagates it and steps the optimizer.  A scene may take optimizer steps
        of its own inside it and return the last step's loss.
    validate : callable ``() -> float``
        Validation metric, lower is better: what PRDP watches.
    probe : callable ``() -> (A, b, x0)``
        A representative operator and right-hand side (numpy) whose solve to
        `rtol_full` gives K_full; ``x0`` is the scene's initial guess, or None.
    rtol_full : float
        Relative tolerance that defines a "converged" solve for this scene.
    epochs : int
        Default number of epochs.
    prdp : dict
        Keyword arguments of `prdp_petsc.PRDP` for this scene.
    scheduler : torch.optim.lr_scheduler.LRScheduler, optional
        Stepped once per epoch.
    compare_ks : list of int, optional
        Constant coarse Ks for ``compare`` (default: 1, K_full/4, K_full/2).
    info : dict
        Free-form description written into results (sizes, settings).
    rollout : callable ``() -> sequence of float``, optional
        Per-step error of the trained model over a long rollout
        (`prdp_petsc.lab.training.rollout.rollout_errors`), recorded after training.
    uncorrected_rollout : callable ``() -> sequence of float``, optional
        The same rollout with the solver alone, for scenes whose network corrects it.
    owned_parameters : list of torch.Tensor, optional
        Parameters of the owned MPI layout (`prdp_petsc.fem.distributed`), each rank's
        own part: not synchronised from rank 0, and under ``--parallel domain`` every
        other parameter's gradient is summed over the ranks.  Such a run cannot be
        resumed on several ranks.
    check_loss : callable ``() -> torch.Tensor``, optional
        The loss the ``auto`` schedule's gradient check differentiates
        (`prdp_petsc.lab.training.schedules.gradient_check`): fixed data, no optimizer
        steps.  Default: `loss` on one fixed batch.  A scene whose epoch is one batch, or
        whose `loss` takes optimizer steps, gives a smaller one, so a check costs less
        than an epoch.
    """

    solvers: list[KSPSolver]
    optimizer: torch.optim.Optimizer
    batches: Callable[[int, torch.Generator], Iterable]
    loss: Callable[[object], torch.Tensor]
    validate: Callable[[], float]
    probe: Callable[[], tuple]
    rtol_full: float = 1e-6
    epochs: int = 50
    prdp: dict = field(default_factory=dict)
    scheduler: object | None = None
    compare_ks: list[int] | None = None
    info: dict = field(default_factory=dict)
    rollout: Callable[[], Sequence[float]] | None = None
    uncorrected_rollout: Callable[[], Sequence[float]] | None = None
    owned_parameters: list = field(default_factory=list)
    check_loss: Callable[[], torch.Tensor] | None = None

    def __post_init__(self):
        if not self.solvers or not all(isinstance(s, KSPSolver) for s in self.solvers):
            raise TypeError("Scene.solvers must be a non-empty list of KSPSolver")
        if not 0 < self.rtol_full < 1:
            raise ValueError(f"rtol_full must lie in (0, 1), got {self.rtol_full}")
        if self.epochs < 1:
            raise ValueError(f"epochs must be >= 1, got {self.epochs}")


def shuffled_batches(n: int, size: int) -> Callable[[int, torch.Generator], list]:
    """`Scene.batches` for n training samples: a fresh permutation per epoch, cut into
    index tensors of `size` (the last one may be shorter)."""

    def batches(epoch: int, generator: torch.Generator) -> list:
        order = torch.randperm(n, generator=generator)
        return [order[i : i + size] for i in range(0, n, size)]

    return batches


def load_scene(path: str | Path) -> ModuleType:
    """Import a scene file and check that it defines ``PRESETS`` and ``build``."""
    path = Path(path).resolve()
    if not path.is_file():
        raise FileNotFoundError(f"scene file {path} not found")
    name = f"prdp_scene_{path.stem}"
    if name in sys.modules and getattr(sys.modules[name], "__file__", None) == str(path):
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    for attr in ("PRESETS", "build"):
        if not hasattr(module, attr):
            raise AttributeError(
                f"scene {path.name} must define {attr} (see prdp_petsc.lab.training.scene)"
            )
    check_presets(module)
    return module


def check_presets(module) -> None:
    """Refuse a scene whose presets do not all name the keys of the first one: a key
    another preset lacks would be a ``KeyError`` mid-run, a key the first one lacks
    out of ``--set``'s reach on it (TypeError for malformed ``PRESETS``, ValueError
    naming the preset and the key)."""
    where = _scene_name(module)
    presets = getattr(module, "PRESETS", None)
    if not isinstance(presets, dict) or not presets:
        raise TypeError(f"scene {where}: PRESETS must be a non-empty dict of dicts")
    for name, settings in presets.items():
        if not (isinstance(name, str) and isinstance(settings, dict)):
            raise TypeError(
                f"scene {where}: PRESETS[{name!r}] must be a dict of settings under a "
                f"string name, got {type(settings).__name__}"
            )
        bad = [key for key in settings if not (isinstance(key, str) and key.isidentifier())]
        if bad:
            raise TypeError(
                f"scene {where}: preset {name!r}: setting names must be identifiers, got {bad}"
            )
    first, *others = presets
    keys = set(presets[first])
    for name in others:
        missing = sorted(keys - set(presets[name]))
        unknown = sorted(set(presets[name]) - keys)
        if missing:
            raise ValueError(
                f"scene {where}: preset {name!r} lacks the setting{'s' * (len(missing) > 1)} "
                f"{', '.join(map(repr, missing))} that preset {first!r} names; every "
                "preset names the same settings"
            )
        if unknown:
            raise ValueError(
                f"scene {where}: preset {name!r} names the setting"
                f"{'s' * (len(unknown) > 1)} {', '.join(map(repr, unknown))}, which preset "
                f"{first!r} does not; every preset names the same settings (give "
                f"{first!r} the key, with the value that keeps it as it is)"
            )


#: Scene files merged into another: the old file's stem -> (the file beside it now, the
#: new names of its presets)
MERGED_SCENES = {
    "heat2d": ("heat.py", {}),
    "heat3d": ("heat.py", {"quick": "quick3d", "paper": "paper3d"}),
}


def merged_scene(scene_file: str, preset: str) -> tuple[str, str]:
    """`scene_file` and `preset` (``"paper k_step=5"``) as they are named now: those of
    a scene file merged into another (`MERGED_SCENES`), the others as they are."""
    merged = MERGED_SCENES.get(Path(scene_file).stem)
    if merged is None:
        return scene_file, preset
    file, presets = merged
    name, _, changes = preset.partition(" ")
    now = " ".join(filter(None, (presets.get(name, name), changes)))
    return str(Path(scene_file).with_name(file)), now


def _scene_name(module) -> str:
    file = getattr(module, "__file__", None)
    return Path(file).name if file else getattr(module, "__name__", "(scene)")


class Settings(dict):
    """A preset's settings (`preset_config`): a dict whose missing key names the
    scene and the preset in its ``KeyError``."""

    def __init__(self, settings: dict, *, scene: str = "", preset: str = ""):
        super().__init__(settings)
        self.scene, self.preset = scene, preset

    def __missing__(self, key):
        raise KeyError(
            f"setting {key!r} is not in preset {self.preset!r} of scene {self.scene} "
            f"(its settings: {', '.join(sorted(self))}); every setting a scene reads "
            "belongs in all its presets"
        )


def preset_config(module: ModuleType, preset: str) -> dict:
    """The settings of ``"name [key=value ...]"``: the scene's preset ``name``, changed.

    A value takes the type the presets give its key (``solver_grad=false`` is False);
    a key no preset names is set as a Python literal or else a string, with a warning
    (it most likely is misspelt).  The result is a `Settings`.
    """
    name, pairs = _parse(preset)
    check_presets(module)
    if name not in module.PRESETS:
        raise ValueError(f"preset must be one of {sorted(module.PRESETS)}, got {name!r}")
    config = Settings(module.PRESETS[name], scene=_scene_name(module), preset=str(preset))
    for key, text in pairs:  # every preset names the same keys (`check_presets`)
        if key in config:
            like = config[key]
        elif key in PRDP_SETTINGS:  # a setting of the controller: `with_prdp_settings`
            like = PRDP_SETTINGS[key]
        else:
            like = None
            if (_scene_name(module), key) not in _WARNED:
                _WARNED.add((_scene_name(module), key))
                logger.warning("setting %r is in no preset of this scene; it may be ignored", key)
        config[key] = _typed(key, text, like)
    return config


def _parse(preset: str) -> tuple[str, list[tuple[str, str]]]:
    """``"paper a=1 b=x"`` → ``("paper", [("a", "1"), ("b", "x")])``."""
    name, *pairs = str(preset).split() or [""]
    parsed = []
    for pair in pairs:
        key, eq, text = pair.partition("=")
        if not (eq and key.isidentifier() and text):
            raise ValueError(f"preset {preset!r}: expected key=value after the name, got {pair!r}")
        parsed.append((key, text))
    return name, parsed


_WARNED: set = set()

#: The keyword arguments of `prdp_petsc.PRDP` and their defaults.
PRDP_SETTINGS = {
    name: p.default
    for name, p in inspect.signature(PRDP.__init__).parameters.items()
    if name != "self"
}


def with_prdp_settings(scene: Scene, preset: str, config: dict) -> Scene:
    """`scene` with the PRDP settings that `preset` changes (``"paper k_step=4"``)
    put into ``scene.prdp``, whether or not the scene reads them from its config."""
    for key, _ in _parse(preset)[1]:
        if key in PRDP_SETTINGS:
            scene.prdp = {**scene.prdp, key: config[key]}
    return scene


def _typed(key: str, text: str, like):
    """`text` as a value of the type of `like` (any literal, else a string, for None)."""
    if isinstance(like, bool) or text in ("true", "false"):
        words = {"true": True, "True": True, "1": True, "false": False, "False": False, "0": False}
        if text in words:
            return words[text]
        raise ValueError(f"setting {key}: expected true or false, got {text!r}")
    if isinstance(like, str):
        return text
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        if like is None:
            return text
        raise ValueError(f"setting {key}: cannot read {text!r}") from None
    if isinstance(like, int) and not (isinstance(value, int) and not isinstance(value, bool)):
        raise ValueError(f"setting {key}: expected an integer, got {text!r}")
    if isinstance(like, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"setting {key}: expected a number, got {text!r}")
        return float(value)
    return value
