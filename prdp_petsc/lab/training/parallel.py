"""Training on more than one process: ``--parallel domain`` and ``--parallel batch``.

Start the command under MPI (``mpiexec -n P prdp-petsc run SCENE --parallel ...``).
``domain`` builds every solver on ``COMM_WORLD`` (each solve one distributed PETSc
solve; every rank sees the same tensors).  ``batch`` keeps serial solvers and trains
every rank on its share of each mini-batch (samples ``rank, rank + P, ...``), its loss
weighted by its share and the gradients summed across the ranks, so that the
parameters equal those of serial training to round-off; rank 0 validates and its PRDP
decision is broadcast.  Rank 0 writes results; iteration counts are totals over the
ranks (``batch``) or those of the collective solves (``domain``), solver time the mean.
"""

from __future__ import annotations

import contextlib
import copy

import numpy as np
import torch

from prdp_petsc import InputError, SolverError
from prdp_petsc.errors import MeshError, NonFiniteError, StructureError

from .checkpoint import parameters

__all__ = ["MEAN_RTOL", "MODES", "Parallel"]

MODES = ("domain", "batch")

#: Relative difference beyond which ``batch`` mode refuses a loss: the ranks' weighted
#: share losses against the whole batch's (float64; ``100 eps`` for coarser dtypes)
MEAN_RTOL = 1e-9


class Parallel:
    """How one training run uses the ranks of ``MPI.COMM_WORLD`` (`mode` None: alone).

    Notes
    -----
    ``batch`` is exact only for a loss that is the mean of per-sample losses.  The
    first step of a run checks it from the numbers: every rank also computes the whole
    batch's loss once under ``torch.no_grad()`` (its solves left out of the `stats`),
    and where the weighted share losses sum to something else (by more than
    `MEAN_RTOL`) every rank raises `InputError`, pointing to ``--parallel domain``; a
    NaN or Inf proves nothing and the next step checks again.  A loss that draws from
    torch's generator (noise, dropout) is refused too: the ranks' shares would draw
    other numbers than the serial run.
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
        self._mean_checked = False

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

        from prdp_petsc.core.parallel import use_comm

        return use_comm(PETSc.COMM_WORLD)

    # -- one optimisation step ---------------------------------------------------------
    def step(self, scene, batch) -> float:
        """Zero the gradients, back-propagate the loss of `batch`, step; return the loss
        (``batch``: of the whole batch, the gradients summed over the ranks)."""
        scene.optimizer.zero_grad()
        params = parameters(scene)
        if self.mode != "batch":
            loss = scene.loss(batch)
            loss.backward()
            if self.mode == "domain" and _owned(scene):  # each rank has its part of the rest
                owned = {id(p) for p in _owned(scene)}
                self._sum_gradients([p for p in params if id(p) not in owned], 0.0, None)
            scene.optimizer.step()
            return float(loss.detach())
        share, weight = self._share(batch)
        check = not self._mean_checked
        error = whole = None
        loss = 0.0
        try:
            if check:
                whole = _whole_batch_loss(scene, batch)
            if len(share):
                value = scene.loss(share) * weight
                value.backward()
                loss = float(value.detach())
        except Exception as err:  # every rank must learn of it, or they wait forever
            error = err
        loss = self._sum_gradients(params, loss, error)
        if check:
            self._check_mean(loss, whole)
        scene.optimizer.step()
        return loss

    def _check_mean(self, shares: float, whole: torch.Tensor) -> None:
        """Refuse, on every rank, a loss whose split `shares` (summed) is not `whole`."""
        from mpi4py import MPI

        value = float(whole)
        finite = bool(np.isfinite(value) and np.isfinite(shares))
        rtol = max(MEAN_RTOL, 100 * torch.finfo(whole.dtype).eps)
        scale = max(abs(value), abs(shares))
        differ = finite and abs(shares - value) > rtol * scale
        flags = np.array([not finite, differ], dtype=np.int8)  # any rank: every rank
        self.comm.Allreduce(MPI.IN_PLACE, flags, op=MPI.MAX)
        if flags[1]:
            raise InputError(
                "--parallel batch needs a loss that is the mean of per-sample losses over "
                f"the batch: the ranks' weighted share losses sum to {shares:.17g}, the "
                f"whole batch's loss is {value:.17g} (relative difference "
                f"{abs(shares - value) / scale:.1e}, more than {rtol:.0e}); a sum over the "
                "batch or a normalisation by a batch total changes with the split. Use "
                "--parallel domain instead."
            )
        self._mean_checked = not flags[0]  # NaN or Inf proves nothing: check the next step

    def _share(self, batch):
        if not isinstance(batch, torch.Tensor) or batch.ndim != 1:
            raise TypeError(
                "--parallel batch needs a scene whose batches are 1-D index tensors (e.g. "
                f"shuffled_batches), got {type(batch).__name__}; use --parallel domain"
            )
        share = batch[self.rank :: self.size]
        return share, len(share) / len(batch)

    def _sum_gradients(self, params: list, value: float, error) -> float:
        """Sum over the ranks, in place and in one ``MPI_Allreduce``, the gradients of the
        `params` some rank has (a rank without one adds zeros) and `value`; return the
        summed `value`.  An `error` on any rank is raised on every rank (none is left
        waiting in a collective call)."""
        from mpi4py import MPI

        has = np.array([p.grad is not None for p in params] + [error is not None], dtype=np.int8)
        self.comm.Allreduce(MPI.IN_PLACE, has, op=MPI.MAX)
        if has[-1]:
            failures = self.comm.allgather(_describe(error))
            rank, failure = next((r, f) for r, f in enumerate(failures) if f)
            raise error if error is not None else _remote_error(rank, failure)
        live = [p for p, h in zip(params, has[:-1], strict=True) if h]
        bounds = np.cumsum([0, *(p.numel() for p in live)])
        flat = np.zeros(bounds[-1] + 1)
        for p, lo, hi in zip(live, bounds[:-1], bounds[1:], strict=True):
            if p.grad is not None:
                flat[lo:hi] = p.grad.detach().reshape(-1).numpy()
        flat[-1] = value
        self.comm.Allreduce(MPI.IN_PLACE, flat, op=MPI.SUM)
        for p, lo, hi in zip(live, bounds[:-1], bounds[1:], strict=True):
            p.grad = torch.from_numpy(flat[lo:hi].copy()).reshape(p.shape).to(dtype=p.dtype)
        return float(flat[-1])

    # -- agreement across ranks ----------------------------------------------------------
    def validate(self, scene) -> float:
        """The validation metric: every rank (``domain``: collective solves) or rank 0."""
        return self._on_root(lambda: float(scene.validate()))

    def rollout(self, errors) -> list[float]:
        """The per-step errors `errors()` returns, computed on rank 0."""
        return self._on_root(lambda: [float(e) for e in errors()])

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
        """Start every rank from rank 0's parameters (replicas must not drift apart);
        the scene's ``owned_parameters`` are each rank's own and stay as they are."""
        if self.comm is None:
            return
        owned = {id(p) for p in _owned(scene)}
        for group in scene.optimizer.param_groups:
            for p in group["params"]:
                if id(p) in owned:
                    continue
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

    def totals(self, counts: list[int], solver_time: float) -> tuple[list[int], float]:
        """The epoch's `counts` (iterations, solves) over all ranks and the mean solver time."""
        if self.mode is None:
            return counts, solver_time
        from mpi4py import MPI

        total = np.array([*counts, solver_time], dtype=np.float64)
        self.comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
        if self.mode == "batch":  # domain: collective solves, every rank counted the same
            counts = [int(c) for c in total[:-1]]
        return counts, float(total[-1] / self.size)


def _owned(scene) -> list:
    """The scene's ``owned_parameters`` (none for a scene-like object without them)."""
    return list(getattr(scene, "owned_parameters", None) or [])


def _whole_batch_loss(scene, batch) -> torch.Tensor:
    """The loss of the whole `batch` under ``no_grad``, leaving no trace in the run:
    torch's generator and the solvers' `stats` are restored (a loss that drew from the
    generator is refused)."""
    solvers = getattr(scene, "solvers", None) or []
    stats = [copy.deepcopy(s.stats) for s in solvers]
    try:
        with torch.random.fork_rng(devices=[]):
            state = torch.random.get_rng_state()
            with torch.no_grad():
                whole = scene.loss(batch)
            random = not torch.equal(state, torch.random.get_rng_state())
    finally:
        for solver, saved in zip(solvers, stats, strict=True):
            solver.stats = saved
    if random:
        raise InputError(
            "--parallel batch cannot check or split a loss that draws from torch's random "
            "number generator (noise, dropout): the ranks' shares would draw other numbers "
            "than the serial run, every rank the same ones. Use --parallel domain instead."
        )
    return whole.detach()


# the kinds of `prdp_petsc.errors` a rank raises again as they are (most specific first)
_KINDS = (SolverError, NonFiniteError, StructureError, MeshError, InputError)


def _describe(error) -> tuple | None:
    """What other ranks need to raise `error` again: (type name, message, reason, kind),
    kind the name of the `prdp_petsc.errors` class `error` is an instance of, or None."""
    if error is None:
        return None
    kind = next((k.__name__ for k in _KINDS if isinstance(error, k)), None)
    return type(error).__name__, str(error), getattr(error, "reason", None), kind


def _remote_error(rank: int, failure: tuple) -> Exception:
    """The error a rank raises when another rank failed: the same kind where it is
    one of `prdp_petsc.errors` (`SolverError` with its reason, `InputError` and its
    kinds) or a ``ValueError``, else ``RuntimeError``."""
    name, message, reason, kind = failure
    message = f"rank {rank}: {message}"
    if kind == SolverError.__name__:
        return SolverError(message, reason=reason)
    if kind is not None:
        return next(k for k in _KINDS if k.__name__ == kind)(message)
    if name == "ValueError":
        return ValueError(message)
    return RuntimeError(f"{name} on {message}")
