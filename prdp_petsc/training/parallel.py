"""Training on more than one process: ``--parallel domain`` and ``--parallel batch``.

Start the command under MPI (``mpiexec -n P prdp-petsc run SCENE --parallel ...``);
scenes need no change.

``domain``
    Every solver the scene builds lives on ``COMM_WORLD``: each solve is one
    distributed PETSc solve (MPIAIJ, rows split across the ranks), and every rank
    sees the same tensors (the replicated layout of `prdp_petsc.core.parallel`).
    The network and the loss run on every rank alike.  Pays off when the solve
    dominates and is large.
``batch``
    Every rank keeps serial solvers and trains on its share of each mini-batch
    (samples ``rank, rank + P, ...``).  Its loss is weighted by its share of the
    batch, the gradients are summed across ranks (one ``MPI_Allreduce``), and
    every rank takes the same optimizer step: the parameters equal those of serial
    training with the same global batch, to round-off.  Rank 0 validates, and its
    PRDP decision (the next K) is broadcast.  This needs a scene whose batches are
    index tensors and whose loss is the mean of a per-sample loss over the batch
    (as `shuffled_batches` scenes have).

Rank 0 writes results and shows progress; iteration counts are totals over the
ranks (``batch``) or those of the collective solves (``domain``); solver time is
the mean over the ranks.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from ..core.results import SolverError

__all__ = ["MODES", "Parallel"]

MODES = ("domain", "batch")


class Parallel:
    """How a training run uses the ranks of ``MPI.COMM_WORLD``.

    Parameters
    ----------
    mode : {None, "domain", "batch"}
        None: every rank trains alone (one process: the serial run).
    """

    def __init__(self, mode: str | None = None):
        if mode not in (None, *MODES):
            raise ValueError(f"parallel must be one of {MODES} or None, got {mode!r}")
        self.mode = mode
        self.comm = None
        self.rank, self.size = 0, 1
        if mode is not None:
            from mpi4py import MPI

            self.comm = MPI.COMM_WORLD
            self.rank, self.size = self.comm.Get_rank(), self.comm.Get_size()

    @property
    def root(self) -> bool:
        """True on the rank that validates, writes results and shows progress."""
        return self.rank == 0

    def describe(self) -> dict:
        return {"mode": self.mode, "ranks": self.size}

    def solvers(self):
        """Context in which the scene is built: its solvers on ``COMM_WORLD`` for ``domain``."""
        if self.mode != "domain":
            return contextlib.nullcontext()
        from petsc4py import PETSc

        from ..core.parallel import use_comm

        return use_comm(PETSc.COMM_WORLD)

    # -- one optimisation step ---------------------------------------------------------
    def step(self, scene, batch) -> float:
        """Zero the gradients, back-propagate the loss of `batch`, step; return the loss.

        ``batch`` mode splits `batch` and sums the weighted gradients across ranks.
        """
        scene.optimizer.zero_grad()
        if self.mode != "batch":
            loss = scene.loss(batch)
            loss.backward()
            scene.optimizer.step()
            return float(loss.detach())
        share, weight = self._share(batch)
        error = None
        loss = 0.0
        if len(share):
            try:
                value = scene.loss(share) * weight
                value.backward()
                loss = float(value.detach())
            except Exception as err:  # every rank must learn of it, or they wait forever
                error = err
        loss = self._sum_gradients(scene.optimizer, loss, error)
        scene.optimizer.step()
        return loss

    def _share(self, batch):
        if not isinstance(batch, torch.Tensor) or batch.ndim != 1:
            raise TypeError(
                "--parallel batch needs a scene whose batches are 1-D index tensors (e.g. "
                f"shuffled_batches), got {type(batch).__name__}; use --parallel domain"
            )
        share = batch[self.rank :: self.size]
        return share, len(share) / len(batch)

    def _sum_gradients(self, optimizer, loss: float, error) -> float:
        """Sum the gradients (and the weighted losses) of all ranks in place.

        A failed solve on any rank stops every rank with the same error (no rank
        is left waiting in a collective call).
        """
        from mpi4py import MPI

        params = [p for group in optimizer.param_groups for p in group["params"]]
        has = np.array([p.grad is not None for p in params] + [error is not None], dtype=np.int8)
        self.comm.Allreduce(MPI.IN_PLACE, has, op=MPI.MAX)
        if has[-1]:
            failures = self.comm.allgather(_describe(error))
            rank, failure = next((r, f) for r, f in enumerate(failures) if f)
            raise error if error is not None else _remote_error(rank, failure)
        live = [p for p, h in zip(params, has[:-1], strict=True) if h]
        flat = np.empty(sum(p.numel() for p in live) + 1)
        offset = 0
        for p in live:
            size = p.numel()
            flat[offset : offset + size] = (
                p.grad.detach().reshape(-1).numpy() if p.grad is not None else 0.0
            )
            offset += size
        flat[-1] = loss
        self.comm.Allreduce(MPI.IN_PLACE, flat, op=MPI.SUM)
        offset = 0
        for p in live:
            size = p.numel()
            grad = torch.from_numpy(flat[offset : offset + size].copy()).reshape(p.shape)
            p.grad = grad.to(dtype=p.dtype)
            offset += size
        return float(flat[-1])

    # -- agreement across ranks ----------------------------------------------------------
    def validate(self, scene) -> float:
        """The validation metric: every rank (``domain``: collective solves) or rank 0."""
        return self._on_root(lambda: float(scene.validate()))

    def rollout(self, scene) -> list[float]:
        return self._on_root(lambda: [float(e) for e in scene.rollout()])

    def _on_root(self, compute):
        """``compute()`` on rank 0 in ``batch`` mode (on every rank otherwise), its value
        broadcast; an error there is raised on every rank."""
        if self.mode != "batch":
            return compute()
        value = error = None
        if self.root:
            try:
                value = compute()
            except Exception as err:
                error = err
        outcome = self.comm.bcast((value, _describe(error)), root=0)
        if error is not None:
            raise error
        if outcome[1] is not None:
            raise _remote_error(0, outcome[1])
        return outcome[0]

    def synchronize(self, scene) -> None:
        """Start every rank from rank 0's parameters (replicas must not drift apart)."""
        if self.comm is None:
            return
        for group in scene.optimizer.param_groups:
            for p in group["params"]:
                with torch.no_grad():
                    p.copy_(torch.from_numpy(self.comm.bcast(p.detach().numpy(), root=0)))

    def check_solvers(self, scene) -> None:
        """``batch`` mode needs serial solvers: rank 0 validates alone."""
        if self.mode == "batch":
            shared = [s.prefix for s in scene.solvers if s.comm.getSize() > 1]
            if shared:
                raise ValueError(
                    f"--parallel batch needs serial solvers, but {shared} live on a larger "
                    "communicator; build them without comm= (or use --parallel domain)"
                )

    def agree(self, value):
        """Rank 0's `value` on every rank (PRDP's next K)."""
        return value if self.comm is None else self.comm.bcast(value, root=0)

    def totals(self, fwd: int, adj: int, solver_time: float) -> tuple[int, int, float]:
        """Forward and adjoint iterations of the epoch over all ranks, mean solver time."""
        if self.mode is None:
            return fwd, adj, solver_time
        from mpi4py import MPI

        total = np.array([fwd, adj, solver_time], dtype=np.float64)
        self.comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
        if self.mode == "batch":  # domain: collective solves, every rank counted the same
            fwd, adj = int(total[0]), int(total[1])
        return fwd, adj, float(total[2] / self.size)


def _describe(error) -> tuple | None:
    """What other ranks need to raise `error` again: (type name, message, reason)."""
    if error is None:
        return None
    return type(error).__name__, str(error), getattr(error, "reason", None)


def _remote_error(rank: int, failure: tuple) -> Exception:
    """The error a rank raises when another rank failed: the same kind where it is
    one the harness records (`SolverError`, ``ValueError``), else ``RuntimeError``."""
    kind, message, reason = failure
    message = f"rank {rank}: {message}"
    if reason is not None:
        return SolverError(message, reason=reason)
    if kind == "ValueError":
        return ValueError(message)
    return RuntimeError(f"{kind} on {message}")
