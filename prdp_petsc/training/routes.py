"""Solver routes for ``compare``: the same scene with another KSP/PC, and the fastest route.

A PETSc user would precondition, so a comparison of PRDP against full fidelity
with the scene's own (often unpreconditioned) solver is only half the answer.
A *route* ``"ksp/pc"`` (e.g. ``"cg/icc"``, ``"cg/gamg"``) runs the scene again with
``-<prefix>ksp_type ksp -<prefix>pc_type pc`` for every solver prefix of the
scene, in PETSc's options database exactly as if given on the command line (the
adjoints inherit them).  `fastest` then says which run reaches the full-fidelity
validation error in the least wall time.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator

__all__ = ["fastest", "parse_route", "route_options"]

#: a run "reaches" the full-fidelity error when within this factor of it
REACH_FACTOR = 1.05


def parse_route(route: str) -> tuple[str, str]:
    """``"cg/icc"`` → ``("cg", "icc")``; ValueError for anything else."""
    ksp, sep, pc = route.partition("/")
    if not sep or not ksp or not pc or "/" in pc or any(c.isspace() for c in route):
        raise ValueError(f"a route is 'ksp_type/pc_type', e.g. 'cg/icc', got {route!r}")
    return ksp, pc


@contextlib.contextmanager
def route_options(prefixes, route: str) -> Iterator[None]:
    """Put ``-<prefix>ksp_type``/``pc_type`` of `route` into PETSc's database meanwhile.

    Values already there (the user's command line) are restored afterwards.  The
    scene's own options that the route's KSP/PC does not read (a Richardson scale
    under CG) are expected, so `UnusedOptionWarning` is silenced meanwhile.
    """
    from petsc4py import PETSc  # here, not at import: the CLI starts PETSc first

    from ..core.solver import UnusedOptionWarning

    ksp, pc = parse_route(route)
    opts = PETSc.Options()
    saved = {}
    for prefix in dict.fromkeys(prefixes):
        for key, value in (("ksp_type", ksp), ("pc_type", pc)):
            name = prefix + key
            saved[name] = opts.getString(name) if opts.hasName(name) else None
            opts.setValue(name, value)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UnusedOptionWarning)
            yield
    finally:
        for name, value in saved.items():
            if value is None:
                opts.delValue(name)
            else:
                opts.setValue(name, value)


def fastest(logs: dict, full_name: str) -> dict | None:
    """Wall time each run needed to reach the full-fidelity validation error.

    The target is the final validation error of `full_name` (the scene's own solver
    at K_full) times `REACH_FACTOR`.  A run reaches it at the first epoch from which
    on its validation error stays at or below the target to the end of the run (a
    run that dips below and drifts back, as a biased small K does, has not reached
    it), and its time is the cumulative wall time up to that epoch.  Returns None
    without the full-fidelity run.
    """
    full = logs.get(full_name)
    if not full or not full["epochs"]:
        return None
    target = REACH_FACTOR * full["epochs"][-1]["val_metric"]
    times = {}
    for name, log in logs.items():
        epochs = log["epochs"]
        first = len(epochs)  # the first epoch from which on the run stays at the target
        while first > 0 and epochs[first - 1]["val_metric"] <= target:
            first -= 1
        reached = first < len(epochs)
        times[name] = sum(e["wall_time"] for e in epochs[: first + 1]) if reached else None
    reached = {name: t for name, t in times.items() if t is not None}
    winner = min(reached, key=reached.get) if reached else None
    return {
        "target_val_error": target,
        "reference": full_name,
        "seconds_to_target": times,
        "winner": winner,
        "winner_seconds": reached.get(winner, math.nan) if winner else None,
    }
