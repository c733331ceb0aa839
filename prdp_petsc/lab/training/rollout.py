"""Rollout metrics: the error of an emulator over many autoregressive steps from
held-out initial states (as APEBench reports rollouts)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

__all__ = ["rollout_errors"]


def rollout_errors(
    step: Callable[[torch.Tensor], torch.Tensor], u0: torch.Tensor, reference: torch.Tensor
) -> np.ndarray:
    """``mean_b ‖û_t − u_t‖ / ‖u_t‖`` for t = 1, …, T: the error of each of the T
    steps of the emulator `step` (B, n) -> (B, n) from `u0` (B, n), against the
    `reference` states (T, B, n)."""
    if reference.ndim != 3 or reference.shape[1:] != u0.shape:
        raise ValueError(
            f"reference must have shape (T, {', '.join(map(str, u0.shape))}), "
            f"got {tuple(reference.shape)}"
        )
    errors = np.empty(len(reference))
    u = u0
    with torch.no_grad():
        for t, ref in enumerate(reference):
            u = step(u)
            errors[t] = float(((u - ref).norm(dim=-1) / ref.norm(dim=-1)).mean())
    return errors
