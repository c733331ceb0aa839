"""Warm starts across epochs: each sample's last solution as its next initial guess.

A training loop solves the same samples' systems epoch after epoch, and between
two visits only the network (θ, the right-hand side) has moved a little, so the
solution of the last visit is a far better initial guess than zero.  `WarmStarts`
keeps it, per call site (one instance each) and per sample key (the index of the
sample in the training set):

    starts = WarmStarts()
    ...
    x = prdp_petsc.solve(A, b, solver, theta=θ, x0=starts.guess(idx))
    starts.store(idx, x)

(torch-fem's ``CachedSolve`` does the same for its direct solves.)  A capped solve
from the stored guess continues where the last one stopped, so over the epochs its
iterates approach the converged solution; a converged solve returns the same x and
the same gradients as from zero.

The guesses are stored detached: `prdp_petsc.solve` is differentiable in `x0`
(``∂L/∂x0 = g − Aᵀλ``), and a guess that kept its graph would link this epoch's
backward to the last epoch's (a second backward through a freed graph, or
gradients leaking into old parameters).  A guess is a constant.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable

import numpy as np
import torch

from ..errors import InputError, NonFiniteError

__all__ = ["WarmStarts"]


class WarmStarts:
    """The last solution of every sample of one call site, as its next initial guess.

    Keys are sample indices (ints, a 1-D integer tensor or array) or any hashable
    values (``(step, index)`` for a call site inside an unroll).  One key gives and
    takes a vector ``(n,)``, several keys a batch ``(B, n)`` in their order.

    Attributes
    ----------
    hits, misses : int
        Keys `guess` found and did not find, since construction or `clear`.

    Notes
    -----
    What the guess changes: a capped solve from it is not a capped solve from
    zero (that is the point).  A solve converged to ``rtol`` stops at
    ``‖r‖ ≤ rtol ‖b − A x0‖`` (`prdp_petsc.solve`'s correction form), so it is
    more accurate than from zero but takes as many iterations; an absolute
    tolerance (``atol``) turns the better guess into fewer iterations.  The
    store lives in memory and is not part of a training checkpoint unless the
    caller saves `state_dict` (a resumed run otherwise starts its guesses anew).
    """

    def __init__(self) -> None:
        self._solutions: dict[Hashable, torch.Tensor] = {}
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._solutions)

    def __contains__(self, key: Hashable) -> bool:
        return _key(key) in self._solutions

    def clear(self) -> None:
        """Forget every stored solution and zero the counters."""
        self._solutions.clear()
        self.hits = self.misses = 0

    def guess(self, keys, fill: torch.Tensor | None = None) -> torch.Tensor | None:
        """The stored solutions of `keys` (detached), for ``solve(..., x0=)``.

        Parameters
        ----------
        keys : int, hashable, sequence of them, or 1-D integer tensor/array
        fill : torch.Tensor, optional
            The guesses of keys with nothing stored yet (shape of the result);
            default zeros (a solve from zero).

        Returns
        -------
        torch.Tensor or None
            ``(n,)`` for one key, ``(B, n)`` for several; None when no key has a
            stored solution and no `fill` is given (``x0=None``: the solve starts
            from zero without the correction form's extra product).
        """
        keys, single = _keys(keys)
        rows = [self._solutions.get(k) for k in keys]
        found = sum(r is not None for r in rows)
        self.hits += found
        self.misses += len(rows) - found
        if fill is not None:
            fill = fill.detach()
            if fill.shape[:1] != (len(keys),) and not single:
                raise InputError(
                    f"fill must have one row per key ({len(keys)}), got shape {tuple(fill.shape)}"
                )
            fill = fill.unsqueeze(0) if single else fill
            rows = [fill[i] if r is None else r for i, r in enumerate(rows)]
        elif found == 0:
            return None
        else:
            like = next(r for r in rows if r is not None)
            rows = [torch.zeros_like(like) if r is None else r for r in rows]
        shapes = {tuple(r.shape) for r in rows}
        if len(shapes) > 1:
            raise InputError(f"stored solutions and fill differ in shape: {sorted(shapes)}")
        out = torch.stack(rows)
        return out[0] if single else out

    def store(self, keys, x: torch.Tensor) -> None:
        """Keep `x` (detached copies) as the next guesses of `keys`.

        `x` is ``(n,)`` for one key, ``(B, n)`` with one row per key otherwise.
        A non-finite row raises `NonFiniteError` (it would poison every later solve
        of that sample).
        """
        keys, single = _keys(keys)
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"x must be a torch.Tensor, got {type(x).__name__}")
        x = x.detach()
        if single:
            x = x.unsqueeze(0)
        if x.ndim != 2 or x.shape[0] != len(keys):
            raise InputError(
                f"x must have one row per key ({len(keys)} keys), got shape {tuple(x.shape)}"
            )
        finite = torch.isfinite(x).all(dim=1)
        if not bool(finite.all()):
            bad = [keys[i] for i in torch.nonzero(~finite).flatten().tolist()]
            raise NonFiniteError(f"solutions of keys {bad[:5]} contain NaN or Inf; not stored")
        for k, row in zip(keys, x.clone(), strict=True):  # a copy: later edits of x stay out
            self._solutions[k] = row

    def state_dict(self) -> dict:
        """The stored solutions, ``{"keys": [...], "solutions": [...]}``, for a checkpoint."""
        return {"keys": list(self._solutions), "solutions": list(self._solutions.values())}

    def load_state_dict(self, state: dict) -> None:
        """Replace the stored solutions with those of `state_dict`."""
        self._solutions = {
            _key(k): v.detach().clone()
            for k, v in zip(state["keys"], state["solutions"], strict=True)
        }


def _key(key: Hashable) -> Hashable:
    """An int for any integer (Python, numpy, 0-d tensor), else the key itself."""
    if isinstance(key, torch.Tensor):
        key = key.item()
    if isinstance(key, np.integer):
        return int(key)
    if isinstance(key, list):
        return tuple(_key(k) for k in key)
    return key


def _keys(keys) -> tuple[list, bool]:
    """(list of keys, whether one key was given)."""
    if isinstance(keys, torch.Tensor | np.ndarray):
        if keys.ndim > 1:
            raise InputError(f"keys must be 1-D, got shape {tuple(keys.shape)}")
        if keys.ndim == 0:
            return [_key(keys)], True
        return [_key(k) for k in keys.tolist()], False
    if isinstance(keys, Iterable) and not isinstance(keys, str | tuple):
        return [_key(k) for k in keys], False
    return [_key(keys)], True
