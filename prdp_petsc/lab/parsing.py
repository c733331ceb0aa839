"""Values the lab reads from its users, checked one way: counts >= 1 and seed lists
(the command line turns the same checks into usage errors)."""

from __future__ import annotations

import operator

__all__ = ["check_epochs", "parse_seeds", "positive_int"]


def positive_int(value, name: str) -> int:
    """``value`` as an int, or ValueError naming `name` unless it is an integer >= 1."""
    try:
        value = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}") from None
    if value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value}")
    return value


def check_epochs(epochs) -> int | None:
    """Return ``epochs`` (None: the scene's default) or raise if it is not an integer >= 1."""
    return None if epochs is None else positive_int(epochs, "epochs")


def parse_seeds(text: str) -> list[int]:
    """``"0,1,2"``, ``"0-3"`` or a mix (``"0-2,7"``) as a list of distinct seeds."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        first, dash, last = part.partition("-")
        try:
            lo, hi = int(first), int(last) if dash else int(first)
        except ValueError:
            raise ValueError(f"seeds: expected e.g. 0,1,2 or 0-3, got {text!r}") from None
        if hi < lo:
            raise ValueError(f"seeds: empty range {part!r}")
        seeds += [s for s in range(lo, hi + 1) if s not in seeds]
    if not seeds:
        raise ValueError(f"seeds: none given in {text!r}")
    return seeds
