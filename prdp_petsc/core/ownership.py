"""Arrays the library owns: made by it, read-only, never edited.

The operator contract (an autograd backward uses exactly the operator its forward
used) keeps such arrays without a copy; every other array is copied when its values
change.  Plain numpy: nothing here imports PETSc or torch.
"""

from __future__ import annotations

import weakref

import numpy as np

__all__ = ["immutable", "own"]

#: the arrays the library made and never edits (weakly held: gone with the array)
_OWNED: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def own(arr: np.ndarray) -> np.ndarray:
    """Mark `arr`, which the library just made, as its own: read-only and never edited,
    so a solver keeps it (and a backward holds it) without a copy."""
    arr.flags.writeable = False
    _OWNED[id(arr)] = arr
    return arr


def immutable(arr) -> bool:
    """True for an array the library made and owns (`own`): no one else holds a
    writeable view of it.

    A caller's array is never taken at its word, read-only or not: a view made before
    its flag was cleared stays writeable, so it is copied when its values change.
    """
    return isinstance(arr, np.ndarray) and _OWNED.get(id(arr)) is arr
