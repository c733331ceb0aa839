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

A route may carry the sub-options its PC needs after the pair, each as
``:option`` (a flag) or ``:option=value``, written without the leading dash and
without the solver prefix: ``"gmres/fieldsplit:pc_fieldsplit_type=schur:
fieldsplit_0_pc_type=bjacobi"`` (one string, no spaces) sets
``-<prefix>pc_fieldsplit_type schur`` and ``-<prefix>fieldsplit_0_pc_type bjacobi``
for every prefix too.  A value holds no ``:``, ``=``, ``,`` or space.  Long ones read
better by name: a scene module's ``ROUTES`` dict maps a name (``"schur"``) to such a
string, and its preset key ``routes`` and ``compare --routes`` may use the name;
the runs are named by it (``prdp@schur``).  ``auto`` is no route: ``compare --routes
auto`` lets a pilot pick one (`prdp_petsc.lab.training.compare.pilot_routes`).

A scene declares the routes that fit its operator as the preset key ``routes``, a
comma-separated string (`parse_routes`); ``compare`` runs them unless told otherwise.
"""

from __future__ import annotations

import contextlib
import math
import re
import warnings
from collections.abc import Iterator, Mapping

from prdp_petsc.prdp import ACCURACY_BAND

__all__ = [
    "AUTO",
    "REACH_FACTOR",
    "accuracy_target",
    "fastest",
    "parse_route",
    "parse_routes",
    "route_options",
    "route_settings",
    "time_to_accuracy",
]

#: a run "reaches" the full-fidelity error when within this factor of it
REACH_FACTOR = 1.0 + ACCURACY_BAND


#: ``compare --routes auto``: a pilot picks one of the scene's routes; no route's name
AUTO = "auto"

_OPTION = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.-]*")
_FORM = "'ksp_type/pc_type[:option[=value]...]', e.g. 'cg/icc'"


def route_settings(route: str, named: Mapping[str, str] | None = None) -> dict[str, str | None]:
    """The PETSc options of `route`, without prefix: ``{"ksp_type": ..., "pc_type": ...,
    option: value, ...}`` (None for a flag), in the order written.

    `route` is ``"ksp/pc"`` with optional ``:option`` / ``:option=value`` parts, or a
    name in `named` (a scene's ``ROUTES``) that stands for such a string.  ValueError
    for anything else, naming the form.
    """
    if not isinstance(route, str):
        raise ValueError(f"a route is {_FORM}, got {route!r}")
    _check_names(named)
    if route == AUTO:  # compare's pilot, only on its own: never one route among others
        raise ValueError(f"{AUTO!r} lets a pilot pick one of the scene's routes; give it alone")
    if named and route in named:
        text = named[route]
        if not isinstance(text, str) or text in named:
            raise ValueError(f"route {route!r} must name a {_FORM} string, got {text!r}")
        return route_settings(text)
    head, *parts = route.split(":")
    ksp, sep, pc = head.partition("/")
    if not sep or not ksp or not pc or "/" in pc or any(c.isspace() or c == "," for c in route):
        if _NAME.fullmatch(route):
            known = ", ".join(sorted(named)) if named else "none"
            raise ValueError(
                f"no route named {route!r} (the scene names: {known}); a route is {_FORM}"
            )
        raise ValueError(f"a route is {_FORM}, got {route!r}")
    settings: dict[str, str | None] = {"ksp_type": ksp, "pc_type": pc}
    for part in parts:
        option, eq, value = part.partition("=")
        if not _OPTION.fullmatch(option) or (eq and not value) or "=" in value:
            raise ValueError(
                f"route {route!r}: {part!r} is not 'option' or 'option=value' "
                "(a PETSc option without the dash and the solver prefix)"
            )
        if option in settings:
            raise ValueError(f"route {route!r} sets {option!r} twice")
        settings[option] = value if eq else None
    return settings


def route_string(options: Mapping[str, object]) -> str:
    """The route of a solver's option dict (``ksp_type`` and ``pc_type`` required, the
    rest as ``:option=value``, a None value as a flag): the inverse of `route_settings`,
    so that a scene can name its own solver settings as a route
    (``ROUTES = {"schur": route_string(SCHUR)}``)."""
    rest = {str(k).lstrip("-"): v for k, v in options.items()}
    try:
        head = f"{rest.pop('ksp_type')}/{rest.pop('pc_type')}"
    except KeyError as err:
        raise ValueError(f"a route needs ksp_type and pc_type, got {sorted(options)}") from err
    parts = [head, *(k if v is None else f"{k}={v}" for k, v in rest.items())]
    route = ":".join(parts)
    route_settings(route)  # a value a route cannot carry (a space, a colon) fails here
    return route


def _check_names(named: Mapping[str, str] | None) -> None:
    """A scene's route names: letters, digits, ``_ . -``, starting with a letter (so
    never a pair, never the pilot's ``auto``)."""
    for name in named or ():
        if not isinstance(name, str) or not _NAME.fullmatch(name) or name == AUTO:
            raise ValueError(
                f"a scene's ROUTES names a route with letters, digits, '_', '.' or '-', "
                f"starting with a letter, and not {AUTO!r}; got {name!r}"
            )


def parse_route(route: str, named: Mapping[str, str] | None = None) -> tuple[str, str]:
    """``"cg/icc"`` → ``("cg", "icc")``: the KSP and PC of `route` (any form
    `route_settings` takes, which checks it; ValueError for anything else)."""
    settings = route_settings(route, named)
    return settings["ksp_type"], settings["pc_type"]


def parse_routes(text: str, named: Mapping[str, str] | None = None) -> tuple[str, ...]:
    """``"cg/icc,cg/gamg"`` → ``("cg/icc", "cg/gamg")`` (each checked by `route_settings`,
    names against `named`).

    The form of a scene's ``routes`` preset key and of ``compare --routes``; the
    empty string is no route.  Spaces around a comma are allowed, a route named
    twice runs once.
    """
    if not isinstance(text, str):
        raise ValueError(f"routes are a comma-separated string like 'cg/icc,cg/gamg', got {text!r}")
    routes = tuple(dict.fromkeys(r.strip() for r in text.split(",") if r.strip()))
    for route in routes:
        route_settings(route, named)
    return routes


@contextlib.contextmanager
def route_options(prefixes, route: str, named: Mapping[str, str] | None = None) -> Iterator[None]:
    """Put `route`'s options (`route_settings`) into PETSc's database under every
    prefix of `prefixes` meanwhile.

    Values already there (the user's command line) are restored afterwards.  The
    scene's own options that the route's KSP/PC does not read (a Richardson scale
    under CG) are expected, so `UnusedOptionWarning` is silenced meanwhile.
    """
    from petsc4py import PETSc  # here, not at import: the CLI starts PETSc first

    from prdp_petsc.errors import UnusedOptionWarning

    settings = route_settings(route, named)
    opts = PETSc.Options()
    saved = {}
    for prefix in dict.fromkeys(prefixes):
        for key, value in settings.items():
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
