"""Rollout metrics: the error of an emulator over many autoregressive steps.

A neural emulator is judged by where it drifts, not by one step: starting from
held-out initial states it is applied to its own output T times, and the error of
each step against the reference trajectory is recorded (as APEBench reports
rollouts).  Scenes use the mean over the steps as the validation metric that PRDP
watches, and hand the per-step curve to the harness for the ``rollout`` plot.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

__all__ = ["rollout_errors"]


def rollout_errors(
    step: Callable[[torch.Tensor], torch.Tensor], u0: torch.Tensor, reference: torch.Tensor
) -> np.ndarray:
    """Normalised error of each rollout step, averaged over the samples.

    Parameters
    ----------
    step : callable ``(B, n) -> (B, n)``
        One emulator step (run under ``torch.no_grad``).
    u0 : torch.Tensor, shape (B, n)
        Initial states.
    reference : torch.Tensor, shape (T, B, n)
        The reference states after 1, …, T steps.

    Returns
    -------
    numpy.ndarray, shape (T,)
        ``mean_b ‖û_t − u_t‖ / ‖u_t‖`` for t = 1, …, T.
    """
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
