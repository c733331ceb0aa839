"""Solver routes for ``compare``: the same scene with another KSP/PC.

A *route* ``"ksp/pc"`` (``"cg/icc"``) runs the scene again with ``-<prefix>ksp_type
ksp -<prefix>pc_type pc`` for every solver prefix of the scene, in PETSc's options
database as if given on the command line (the adjoints inherit them).  Sub-options
follow the pair as ``:option`` (a flag) or ``:option=value``, without the dash and
the prefix: ``"gmres/fieldsplit:pc_fieldsplit_type=schur"``; a value holds no ``:``,
``=``, ``,`` or space.  A scene's ``ROUTES`` dict names long ones (``"schur"``), and
its preset key ``routes`` (a comma-separated string, `parse_routes`) declares those
``compare`` runs.  ``auto`` is no route: ``compare --routes auto`` lets a pilot pick
one (`prdp_petsc.lab.training.compare.pilot_routes`).
"""

from __future__ import annotations

import contextlib
import re
import warnings
from collections.abc import Iterator, Mapping

__all__ = ["AUTO", "parse_route", "parse_routes", "route_options", "route_settings", "route_string"]

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
