"""PETSc option specifications: dicts or option strings, as PETSc's database wants them."""

from __future__ import annotations

import shlex

__all__ = ["is_number", "option_value", "parse_options"]


def parse_options(options: dict | str | None) -> dict:
    """Turn ``{"ksp_type": "cg"}`` or ``"-ksp_type cg -ksp_monitor"`` into a dict."""
    if options is None:
        return {}
    if isinstance(options, dict):
        return {str(k).lstrip("-"): v for k, v in options.items()}
    if not isinstance(options, str):
        raise TypeError(f"options must be a dict or a PETSc option string, got {type(options)}")
    out: dict = {}
    tokens = shlex.split(options)
    i = 0
    while i < len(tokens):
        tok = tokens[i]
        if not tok.startswith("-") or is_number(tok):
            raise ValueError(f"options: expected '-name', got {tok!r} in {options!r}")
        value = None
        if i + 1 < len(tokens) and (not tokens[i + 1].startswith("-") or is_number(tokens[i + 1])):
            value = tokens[i + 1]
            i += 1
        out[tok.lstrip("-")] = value
        i += 1
    return out


def is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def option_value(value) -> str | None:
    if value is None or value is True:
        return None
    if value is False:
        return "false"
    return str(value)
