"""Solver routes for ``compare``: the same scene with another KSP/PC, and the fastest route.

A PETSc user would precondition, so a comparison of PRDP against full fidelity
with the scene's own (often unpreconditioned) solver is only half the answer.
A *route* ``"ksp/pc"`` (e.g. ``"cg/icc"``, ``"cg/gamg"``) runs the scene again with
``-<prefix>ksp_type ksp -<prefix>pc_type pc`` for every solver prefix of the
scene, in PETSc's options database exactly as if given on the command line (the
adjoints inherit them).  `fastest` then says which run reaches the full-fidelity
validation error in the least wall time, by `time_to_accuracy`: the one definition of
"reaching full-fidelity accuracy" that ``compare``'s ``time_to_full_accuracy`` and
``speedup_vs_best_full`` use too.

A scene declares the routes that fit its operator as the preset key ``routes``, a
comma-separated string (`parse_routes`); ``compare`` runs them unless told otherwise.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator

__all__ = [
    "REACH_FACTOR",
    "accuracy_target",
    "fastest",
    "parse_route",
    "parse_routes",
    "route_options",
    "time_to_accuracy",
]

#: a run "reaches" the full-fidelity error when within this factor of it
REACH_FACTOR = 1.05


def parse_route(route: str) -> tuple[str, str]:
    """``"cg/icc"`` → ``("cg", "icc")``; ValueError for anything else."""
    ksp, sep, pc = route.partition("/")
    if not sep or not ksp or not pc or "/" in pc or any(c.isspace() for c in route):
        raise ValueError(f"a route is 'ksp_type/pc_type', e.g. 'cg/icc', got {route!r}")
    return ksp, pc


def parse_routes(text: str) -> tuple[str, ...]:
    """``"cg/icc,cg/gamg"`` → ``("cg/icc", "cg/gamg")`` (each checked by `parse_route`).

    The form of a scene's ``routes`` preset key and of ``compare --routes``; the
    empty string is no route.  Spaces around a comma are allowed, a route named
    twice runs once.
    """
    if not isinstance(text, str):
        raise ValueError(f"routes are a comma-separated string like 'cg/icc,cg/gamg', got {text!r}")
    routes = tuple(dict.fromkeys(r.strip() for r in text.split(",") if r.strip()))
    for route in routes:
        parse_route(route)
    return routes


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


def accuracy_target(logs: dict, full_name: str) -> float | None:
    """`REACH_FACTOR` × the final validation error of run `full_name` (the scene's own
    solver at K_full), or None where that run is missing or recorded no epoch."""
    full = logs.get(full_name)
    if not full or not full["epochs"]:
        return None
    return REACH_FACTOR * full["epochs"][-1]["val_metric"]


def time_to_accuracy(log: dict, target: float) -> float | None:
    """Wall time a run needed to reach `target` and stay there; None if it never did.

    The run reaches it at the first epoch from which on its validation error stays
    at or below the target to the end of the run (a run that dips below and drifts
    back, as a biased small K does, has not reached it); its time is the cumulative
    wall time up to and including that epoch.  A run that stopped early (a diverged
    solve, Ctrl-C) did not train to the end, so it never reaches it; neither does
    any run against a NaN target.
    """
    epochs = log["epochs"]
    if log.get("stopped"):
        return None
    first = len(epochs)  # the first epoch from which on the run stays at the target
    while first > 0 and epochs[first - 1]["val_metric"] <= target:
        first -= 1
    if first == len(epochs):
        return None
    return sum(e["wall_time"] for e in epochs[: first + 1])


def fastest(logs: dict, full_name: str) -> dict | None:
    """Wall time each run needed to reach the full-fidelity validation error.

    The target is `accuracy_target` (the final validation error of `full_name`, the
    scene's own solver at K_full, times `REACH_FACTOR`), each run's time is
    `time_to_accuracy`.  Returns None without the full-fidelity run.
    """
    target = accuracy_target(logs, full_name)
    if target is None:
        return None
    times = {name: time_to_accuracy(log, target) for name, log in logs.items()}
    reached = {name: t for name, t in times.items() if t is not None}
    winner = min(reached, key=reached.get) if reached else None
    return {
        "target_val_error": target,
        "reference": full_name,
        "seconds_to_target": times,
        "winner": winner,
        "winner_seconds": reached.get(winner, math.nan) if winner else None,
    }
