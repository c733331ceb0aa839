"""K schedules of a training run: ``"prdp"``, ``"auto"``, ``"fixed:K"`` and ``"rtol"``.

``prdp`` lets `prdp_petsc.PRDP` raise the iteration cap K (``max_it``, ``rtol = atol
= 0``) with the scene's settings; ``auto`` with the default construction,
``PRDP.for_problem(K_full)``, certified by a gradient check (`gradient_check`);
``fixed:K`` keeps K; ``rtol`` moves PETSc's relative tolerance instead, a decade per
refinement level (`rtol_from_level`), under a cap of `RTOL_MAX_IT_FACTOR` × K_full.
"""

from __future__ import annotations

import copy
import operator
from typing import NamedTuple

import numpy as np
import torch

from prdp_petsc import gradient_check as library_gradient_check

__all__ = [
    "CHECK_SEED",
    "RTOL_FACTOR",
    "RTOL_INIT",
    "RTOL_MAX_IT_FACTOR",
    "Schedule",
    "gradient_check",
    "parse_schedule",
    "rtol_from_level",
    "rtol_levels",
]

#: The ``rtol`` schedule caps every solve at this many times K_full (PETSc's rtol test
#: stops it first; the cap only bounds a solve that would not converge)
RTOL_MAX_IT_FACTOR = 10
#: Seed of the generator that draws the ``auto`` schedule's fixed check batch
CHECK_SEED = 20_261_125

#: Relative tolerance of refinement level 0 when PRDP moves a Krylov rtol instead of K ...
RTOL_INIT = 1e-1
#: ... and its factor per refinement: a decade per level.
RTOL_FACTOR = 1e-1


def rtol_from_level(
    level: int, rtol_init: float = RTOL_INIT, factor: float = RTOL_FACTOR, rtol_min: float = 1e-10
) -> float:
    """Krylov rtol of refinement level ``level``: max(rtol_init * factor**level, rtol_min)."""
    if operator.index(level) < 0:
        raise ValueError(f"level must be >= 0, got {level}")
    if not 0 < rtol_min <= rtol_init:
        raise ValueError(f"need 0 < rtol_min <= rtol_init, got {rtol_min}, {rtol_init}")
    if not 0 < factor < 1:
        raise ValueError(f"factor must lie in (0, 1), got {factor}")
    return max(rtol_init * factor**level, rtol_min)


class Schedule(NamedTuple):
    """A parsed schedule: ``kind`` ``"prdp"``, ``"auto"``, ``"fixed"`` or ``"rtol"``; ``k``
    for fixed."""

    kind: str
    k: int | None = None


def parse_schedule(schedule: str) -> Schedule:
    """``"prdp"``, ``"auto"``, ``"rtol"`` or ``"fixed:K"`` (K >= 1) as a `Schedule`."""
    if schedule in ("prdp", "auto", "rtol"):
        return Schedule(schedule)
    if isinstance(schedule, str) and schedule.startswith("fixed:"):
        try:
            k = int(schedule.split(":", 1)[1])
        except ValueError:
            k = 0
        if k >= 1:
            return Schedule("fixed", k)
    raise ValueError(
        f"schedule must be 'prdp', 'auto', 'rtol' or 'fixed:K' with K >= 1, got {schedule!r}"
    )


def rtol_levels(rtol_full: float, rtol_init: float = RTOL_INIT, factor: float = RTOL_FACTOR):
    """Refinements from `rtol_init` until `rtol_from_level` reaches `rtol_full`: the
    ``rtol`` schedule stops there, as PRDP stops at K_full."""
    rtol_init = max(rtol_init, rtol_full)
    level = 0
    while rtol_from_level(level, rtol_init, factor, rtol_full) > rtol_full * (1 + 1e-9):
        level += 1
    return level


def gradient_check(scene):
    """The ``auto`` schedule's check: `prdp_petsc.gradient_check` of ``scene.check_loss``,
    or else of the training loss on one fixed batch (the first of ``scene.batches`` under
    `CHECK_SEED`), through every scene solver.  The parameters and the optimizer's state
    are restored after every check (a scene's loss may take optimizer steps), so a check
    never trains.
    """
    if scene.check_loss is not None:
        loss = scene.check_loss
    else:
        batch = next(iter(scene.batches(0, torch.Generator().manual_seed(CHECK_SEED))))
        loss = lambda: scene.loss(batch)  # noqa: E731
    params = [p for g in scene.optimizer.param_groups for p in g["params"] if p.requires_grad]
    gradient = library_gradient_check(loss, params, scene.solvers)

    def check(k: int) -> np.ndarray:
        values = [p.detach().clone() for p in params]
        state = copy.deepcopy(scene.optimizer.state_dict())
        try:
            return gradient(k)
        finally:
            with torch.no_grad():
                for p, value in zip(params, values, strict=True):
                    p.copy_(value)
            scene.optimizer.load_state_dict(state)
            scene.optimizer.zero_grad()

    check.spent = gradient.spent  # what the checks and the run cost: the controller's budget
    return check
