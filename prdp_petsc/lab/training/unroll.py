"""Long unrolls: m steps of (capped solve ↔ network) under autograd, memory bounded.

Solver-in-the-loop training feeds a corrector its own output for m steps and
differentiates the whole chain, so the network sees the states its rollouts reach
and gets gradients about how its errors grow.  Two hybrids of a solver step P
(`physics`) and a network C (`network`) are supported (`Hybrid`):

``"direct"``
    s ← P(s) + C(P(s)): the correction is added to the solver's output state
    (Um et al. 2020, "Solver-in-the-Loop").
``"indirect"``
    s ← P(s; f = C(s)): the correction enters the implicit step as a forcing of
    its right-hand side and the solve carries it (the Indirect Neural Corrector,
    Wei et al. 2025).  The solve then damps what the network adds instead of
    passing it on unchanged; the gradient reaches C through the right-hand side
    of the solve (its adjoint).

Memory.  An implicit solve (`prdp_petsc.solve`) keeps only its solution and
parameters for the backward pass, one state per step; the network's activations
are what grows with m.  With ``checkpoint=True`` every network call runs under
``torch.utils.checkpoint`` (non-reentrant): only its input is kept and its forward
is recomputed during the backward pass, so an unroll stores the step boundaries and
the solves' states and recomputes one network at a time.  No solve runs twice: the
recomputation covers the network only, and the gradient is the same as without
checkpointing (to round-off).

The K of every solve in the unroll is the solver's ``max_it``, which the training
schedule (PRDP) sets: all m solves of an unroll share it.
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
    """One corrected solver step, direct or indirect (module notes).

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

    def uncorrected(self, state: torch.Tensor) -> torch.Tensor:
        """The solver step alone, P(s)."""
        return self.physics(state, None, None)


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
        its own rollout reaches (the unrolled distribution), without gradients
        through earlier steps (List et al. 2024's "no solver gradient" variant).
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
    at every `stride`-th step (0, stride, 2·stride, … while the window fits).

    Returns
    -------
    torch.Tensor, shape (length, N · S, n)
        Windows ordered by start step, then by trajectory; S = ⌊(T + 1 − length) /
        stride⌋ + 1 starts per trajectory.
    """
    if not 1 <= length <= len(trajectories) or stride < 1:
        raise ValueError(
            f"need 1 <= length <= {len(trajectories)} and stride >= 1, got {length}, {stride}"
        )
    w = trajectories.unfold(0, length, stride)  # (starts, N, n, length)
    return w.permute(3, 0, 1, 2).reshape(length, -1, trajectories.shape[-1])


def horizon(epoch: int, steps: int, *, start: int = 1, every: int = 0) -> int:
    """The unroll length m of `epoch` under a doubling curriculum.

    ``every = 0``: always `steps`.  Else m starts at `start` and doubles every
    `every` epochs up to `steps` (1, 2, 4, … with ``start=1``).
    """
    if every < 0 or start < 1:
        raise ValueError(f"need every >= 0 and start >= 1, got {every}, {start}")
    if every == 0:
        return steps
    return min(steps, start * 2 ** (epoch // every))


class SavedTensorMeter:
    """Bytes of the tensors autograd keeps for the backward pass, at their peak.

    A CPU process has no allocator statistics like CUDA's; what an unroll adds with
    m is what autograd saves, and this counts it exactly: storages are counted once
    however many tensors view them, while a graph is alive (enter before the
    forward pass, leave after the backward pass).  Inside a checkpointed region
    torch keeps its own hooks: the activations it recomputes during the backward
    pass (one network call at a time) are not counted.

    Attributes
    ----------
    peak : int
        The largest number of saved bytes alive at once.
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
