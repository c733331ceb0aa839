"""Long unrolls: m steps of (capped solve ↔ network) under autograd, memory bounded.

Solver-in-the-loop training feeds a corrector its own output for m steps and
differentiates the whole chain.  Two hybrids of a solver step P and a network C
(`Hybrid`): ``"direct"``, s ← P(s) + C(P(s)) (Um et al. 2020), and ``"indirect"``,
s ← P(s; f = C(s)), the correction a forcing of the implicit step's right-hand side
(Wei et al. 2025), whose gradient reaches C through the solve's adjoint.

An implicit solve keeps one state per step for the backward pass; the network's
activations are what grows with m.  With ``checkpoint=True`` every network call runs
under ``torch.utils.checkpoint``: its forward is recomputed during the backward pass
(no solve runs twice, the gradient is unchanged to round-off).  All m solves of an
unroll share the solver's ``max_it``, which the schedule sets.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import contextmanager

import torch
from torch.utils.checkpoint import checkpoint as _checkpoint

__all__ = [
    "CORRECTIONS",
    "Hybrid",
    "SavedTensorMeter",
    "horizon",
    "unrolled_loss",
    "windows",
]

CORRECTIONS = ("direct", "indirect")

Physics = Callable[..., torch.Tensor]


class Hybrid:
    """One corrected solver step, direct or indirect.

    Parameters
    ----------
    physics : callable ``(state, forcing, keys) -> state``
        The solver step P; `forcing` is None (uncorrected, or direct correction)
        or a tensor the step adds to its right-hand side; `keys` (or None) is
        passed through, e.g. for warm starts per sample.
    network : torch.nn.Module or callable ``tensor -> tensor``
        The corrector C.  Direct: a correction of the state, same shape.  Indirect:
        the forcing handed to `physics`.
    correction : {"direct", "indirect"}
    checkpoint : bool
        Run `network` under activation checkpointing while gradients are recorded.
    """

    def __init__(
        self,
        physics: Physics,
        network: Callable[[torch.Tensor], torch.Tensor],
        *,
        correction: str = "direct",
        checkpoint: bool = False,
    ):
        if correction not in CORRECTIONS:
            raise ValueError(f"correction must be one of {CORRECTIONS}, got {correction!r}")
        self.physics, self.network = physics, network
        self.correction, self.checkpoint = correction, checkpoint

    def _net(self, x: torch.Tensor) -> torch.Tensor:
        if self.checkpoint and torch.is_grad_enabled():
            return _checkpoint(self.network, x, use_reentrant=False)
        return self.network(x)

    def __call__(self, state: torch.Tensor, keys=None) -> torch.Tensor:
        """The corrected step from `state` (B, n)."""
        if self.correction == "direct":
            coarse = self.physics(state, None, keys)
            return coarse + self._net(coarse)
        return self.physics(state, self._net(state), keys)


def unrolled_loss(
    step: Callable[..., torch.Tensor],
    targets: torch.Tensor,
    *,
    steps: int | None = None,
    solver_grad: bool = True,
    keys: Callable[[int], Sequence] | None = None,
) -> torch.Tensor:
    """Summed MSE of an m-step rollout from ``targets[0]`` against ``targets[1:]``.

    Parameters
    ----------
    step : callable ``(state, keys) -> state``
        One hybrid step (a `Hybrid`).
    targets : torch.Tensor, shape (≥ m + 1, B, n)
        A window of the reference trajectory; its first state starts the rollout.
    steps : int, optional
        m (default: all of `targets` after the first).
    solver_grad : bool
        False detaches each step's input: the network is still trained on the states
        its own rollout reaches, without gradients through earlier steps.
    keys : callable ``t -> keys``, optional
        The keys of step t (1-based) handed to `step` (warm starts).

    Returns
    -------
    torch.Tensor
        ``Σ_t mean((s_t − targets[t])²)``, t = 1 … m.
    """
    m = len(targets) - 1 if steps is None else steps
    if not 1 <= m < len(targets):
        raise ValueError(f"steps must lie in [1, {len(targets) - 1}], got {steps}")
    state, total = targets[0], targets.new_zeros(())
    for t in range(1, m + 1):
        if not solver_grad:
            state = state.detach()
        state = step(state, None if keys is None else keys(t))
        total = total + ((state - targets[t]) ** 2).mean()
    return total


def windows(trajectories: torch.Tensor, length: int, stride: int = 1) -> torch.Tensor:
    """Windows of `length` consecutive states of trajectories (T + 1, N, n), starting
    at every `stride`-th step: shape (length, N · S, n), ordered by start, then
    trajectory."""
    if not 1 <= length <= len(trajectories) or stride < 1:
        raise ValueError(
            f"need 1 <= length <= {len(trajectories)} and stride >= 1, got {length}, {stride}"
        )
    w = trajectories.unfold(0, length, stride)  # (starts, N, n, length)
    return w.permute(3, 0, 1, 2).reshape(length, -1, trajectories.shape[-1])


def horizon(epoch: int, steps: int, *, start: int = 1, every: int = 0) -> int:
    """The unroll length m of `epoch`: `steps` (``every = 0``), or `start` doubled every
    `every` epochs up to `steps`."""
    if every < 0 or start < 1:
        raise ValueError(f"need every >= 0 and start >= 1, got {every}, {start}")
    if every == 0:
        return steps
    return min(steps, start * 2 ** (epoch // every))


class SavedTensorMeter:
    """Bytes of the tensors autograd saves for the backward pass, at their peak
    (``peak``): storages counted once, while a graph is alive (enter before the forward
    pass, leave after the backward pass); what checkpointing recomputes is not counted.
    """

    def __init__(self):
        self.peak = 0
        self._live: dict[int, int] = {}

    def _pack(self, t: torch.Tensor):
        if t.is_sparse:  # its index and value storages
            parts = [t._indices(), t._values()] if t.is_coalesced() else [t.coalesce()]
            for part in parts:
                self._pack(part)
            return t
        storage = t.untyped_storage()
        key = storage.data_ptr()
        self._live[key] = max(self._live.get(key, 0), storage.nbytes())
        self.peak = max(self.peak, sum(self._live.values()))
        return t

    @contextmanager
    def __call__(self):
        with torch.autograd.graph.saved_tensors_hooks(self._pack, lambda t: t):
            yield self
        self._live.clear()
