"""K_full of a scene (`find_k_full`: one converged solve of its probe; `probe` also
has the errors that choose PRDP's start), PRDP's cap (`k_cap`) and the ``rtol``
schedule's plan (`rtol_plan`)."""

from __future__ import annotations

import logging

from prdp_petsc import SolverError
from prdp_petsc import find_k_full as probe_k_full
from prdp_petsc.core.probe import KFull

from .schedules import RTOL_FACTOR, RTOL_INIT, RTOL_MAX_IT_FACTOR, rtol_levels

__all__ = ["find_k_full", "k_cap", "probe", "rtol_plan"]

logger = logging.getLogger(__name__)


def probe(scene) -> KFull:
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
        return probe_k_full(A, b, scene.solvers[0], rtol=scene.rtol_full, x0=x0, max_it=100_000)
    except SolverError as err:
        raise SolverError(f"the scene's solver: {err}", reason=err.reason) from err


def find_k_full(scene) -> int:
    """K_full of the scene (`probe`) as a plain ``int``."""
    return int(probe(scene))


def k_cap(scene) -> int | None:
    """K_full (at least K₀) as PRDP's cap, or None where the probe does not converge."""
    try:
        return max(find_k_full(scene), scene.prdp.get("k_init", 1))
    except SolverError as err:
        logger.warning("PRDP runs without a cap on K: %s", err)
        return None


def rtol_plan(scene, recorded: dict | None) -> dict:
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
