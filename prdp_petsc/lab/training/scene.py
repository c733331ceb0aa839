"""Scenes: one learning problem each, described in a Python file.

A scene file (the shipped ones live in ``demos/``) defines

``PRESETS``
    ``{"quick": {...}, "paper": {...}}``: plain dicts of settings (sizes, epochs,
    learning rate, ...).  ``quick`` is for tests and CI, ``paper`` for the
    reference settings.  Every preset names the same keys, those of the first one
    (`check_presets`, run by `load_scene` and `preset_config`): so ``--set
    key=value`` reaches a setting on any preset, and the results record it.
``build(config: dict, seed: int) -> Scene``
    builds the physics, data, network, loss and validation metric for one preset,
    and nothing the scene does not need.  ``config`` is the preset's dict
    (`preset_config`); reading a key it lacks raises a ``KeyError`` that names the
    key and the preset.
``COMMANDS`` (optional)
    ``{"adjoint": adjoint_command, ...}``: the scene's own commands besides ``run``
    and ``compare`` (a report, a plot), run by ``prdp-petsc scene SCENE_FILE NAME
    [args]`` and ``python SCENE_FILE NAME [args]`` (`prdp_petsc.lab.cli`).  Each function
    is called with an ``argparse.ArgumentParser`` whose ``prog`` names the command
    and which has ``--debug``; it adds its arguments and returns the function that
    runs the parsed ``argparse.Namespace`` and returns the exit status.  The first
    line of its docstring is the command's summary.  The command line does the rest
    as for ``run``: PETSc options start PETSc, an error prints one line, a usage
    error exits 2, and an argument ``--preset`` is checked against ``PRESETS`` (the
    command reads it with `preset_config`).

A preset name may carry changed settings, ``"paper modes=32 k_step=10"``
(`preset_config`; the command line's ``--set modes=32``): each value takes the type
the presets give its key (``false`` for a switch, ``net=mlp`` a string).  A key
that names a setting of `prdp_petsc.PRDP` (``k_init``, ``k_step``, ``tau_stop``,
...) also goes into ``Scene.prdp`` (`with_prdp_settings`), so it changes the
controller in every scene.

The harness (`prdp_petsc.lab.training.harness`) does the rest: training loop, K schedule
(PRDP or fixed), finding K_full, cost accounting, results, plots, command line.
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
    "PRDP_SETTINGS",
    "Scene",
    "Settings",
    "check_presets",
    "load_scene",
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
        The capped solvers whose ``max_it`` the schedule controls (forward and
        adjoint together).
    optimizer : torch.optim.Optimizer
        Optimises whatever the scene trains (network weights, or θ itself).
    batches : callable ``(epoch, generator) -> iterable``
        Training batches of one epoch; `generator` is a seeded ``torch.Generator``.
    loss : callable ``batch -> torch.Tensor``
        Scalar training loss of one batch (through the solvers); the harness
        back-propagates it and steps the optimizer.  A scene may take optimizer steps
        of its own inside it and return the last step's loss (``poisson_field``,
        ``poisson3d``: several steps per batch); the ``auto`` schedule's check calls it
        too and restores the parameters and the optimizer's state afterwards.
    validate : callable ``() -> float``
        Validation metric, lower is better; this is what PRDP watches.
    probe : callable ``() -> (A, b, x0)``
        A representative operator and right-hand side(s) (numpy); the harness
        solves it to tolerance `rtol_full` to find K_full.  ``x0`` is None where the
        scene's solves start from zero; a scene whose solves start from a guess
        (``solve(..., x0=)``) returns that guess: K_full then counts the iterations
        from x0 to PETSc's default test, ``‖r‖ ≤ rtol_full ‖b‖``.  A 2-tuple
        ``(A, b)`` is refused (TypeError from `~.harness.find_k_full`).
    rtol_full : float
        Relative tolerance that defines a "converged" solve for this scene.
    epochs : int
        Default number of epochs.
    prdp : dict
        Keyword arguments of `prdp_petsc.PRDP` for this scene.
    scheduler : torch.optim.lr_scheduler.LRScheduler, optional
        Stepped once per epoch.
    compare_ks : list of int, optional
        Constant coarse Ks for ``compare`` (default: 1, K_full/4, K_full/2; an empty
        list: none).
    info : dict
        Free-form description written into results (sizes, settings).
    rollout : callable ``() -> sequence of float``, optional
        Per-step error of the trained model over a long autoregressive rollout
        (`prdp_petsc.lab.training.rollout.rollout_errors`); recorded after training
        and plotted by ``compare``.  Emulator scenes validate on its mean.
    owned_parameters : list of torch.Tensor, optional
        Parameters of the owned MPI layout (`prdp_petsc.fem.distributed`): each rank
        holds its own part (θ of its own elements), so their shapes and values differ
        between ranks.  The harness does not start them from rank 0's values, and
        under ``--parallel domain`` it sums the gradients of every *other* parameter
        over the ranks before the optimizer step: the loss is then a sum over the
        ranks of local parts (`prdp_petsc.sum_over_ranks`), so each rank's backward
        pass gives only its part of a replicated parameter's gradient.  Such a run
        cannot be resumed on several ranks (its checkpoint holds rank 0's part).
    uncorrected_rollout : callable ``() -> sequence of float``, optional
        For scenes whose network corrects a solver: the same rollout with the
        solver alone (what the corrector has to beat at every step); recorded
        after training next to ``rollout``.
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
    """Refuse a scene whose presets do not all name the same settings.

    The first preset of ``module.PRESETS`` (in the dict's order; ``quick`` in the
    shipped scenes) names the scene's settings.  Every other preset must name exactly
    those keys: a key it lacks (which ``build`` would read as ``config["key"]`` and
    not find) or a key the first preset does not name (which ``--set`` could not
    reach on the first preset) is refused here, when the scene is loaded, with the
    preset and the key named, instead of as a ``KeyError`` in the middle of a run.

    Raises
    ------
    TypeError
        ``PRESETS`` is not a non-empty dict of dicts with string keys.
    ValueError
        A preset lacks a key of the first preset, or names one it does not.
    """
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

    def __reduce__(self):  # pickles (and copies) as the dict it holds, with its names
        return (_settings, (dict(self), self.scene, self.preset))


def _settings(settings: dict, scene: str, preset: str) -> Settings:
    return Settings(settings, scene=scene, preset=preset)


def preset_config(module: ModuleType, preset: str) -> dict:
    """The settings of ``"name [key=value ...]"``: the scene's preset ``name``, changed.

    A value takes the type the scene's presets give that key (``true``/``false`` for
    a bool, an integer for an int, a number for a float; anything else refused), so
    that ``solver_grad=false`` means False, not the string ``"false"``.  A key that
    no preset names is still set, as a Python literal or else a string, with a
    warning (once per key): a scene reads only the keys of its presets, so such a
    key is most likely misspelt and would otherwise change nothing silently.

    The presets are checked first (`check_presets`), and the result is a `Settings`:
    a dict whose ``KeyError`` names the preset.
    """
    name, pairs = _parse(preset)
    check_presets(module)
    if name not in module.PRESETS:
        raise ValueError(f"preset must be one of {sorted(module.PRESETS)}, got {name!r}")
    config = Settings(module.PRESETS[name], scene=_scene_name(module), preset=str(preset))
    known = {}
    for settings in module.PRESETS.values():
        for key, value in settings.items():
            known.setdefault(key, value)
    for key, text in pairs:
        if key in known:
            config[key] = _typed(key, text, config.get(key, known[key]))
            continue
        if key in PRDP_SETTINGS:  # a setting of the controller: `with_prdp_settings`
            config[key] = _typed(key, text, PRDP_SETTINGS[key])
            continue
        if (_scene_name(module), key) not in _WARNED:
            _WARNED.add((_scene_name(module), key))
            logger.warning("setting %r is in no preset of this scene; it may be ignored", key)
        config[key] = _typed(key, text, None)
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
