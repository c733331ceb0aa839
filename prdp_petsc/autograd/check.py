"""The check a `prdp_petsc.PRDP` controller certifies its K with.

``gradient_check(loss, parameters, solvers)`` is a function ``k -> ∂loss/∂parameters``
with every solver capped at k: what training would see through the solve at that cap,
on the current weights.  The controller compares it at K and at K_full.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import torch

from ..core.solver import KSPSolver
from ..errors import InputError

__all__ = ["GradientCheck", "gradient_check"]


def gradient_check(
    loss: Callable[[], torch.Tensor],
    parameters: Iterable[torch.Tensor],
    solvers: KSPSolver | Sequence[KSPSolver],
) -> GradientCheck:
    """The validation gradient through solves capped at k, as a `PRDP` check.

    Parameters
    ----------
    loss : callable ``() -> torch.Tensor``
        The validation loss (a scalar) computed through `solvers`, on a fixed batch:
        the same data at every call, so that two calls differ only by the cap.
    parameters : iterable of torch.Tensor
        What training updates (``model.parameters()``, or the design of an
        optimisation loop); each must require gradients.
    solvers : KSPSolver or sequence of KSPSolver
        Every solver `loss` runs through.

    Returns
    -------
    GradientCheck
        ``check(k)``: the gradient of ``loss()`` with respect to `parameters`,
        flattened and concatenated (float64), with every solver's ``max_it`` set to
        k for the call and restored after it (the adjoint follows ``max_it`` unless
        set apart).  It runs with gradients enabled (also when called under
        ``torch.no_grad()``), never accumulates into ``.grad`` and never steps an
        optimiser; parameters `loss` does not reach contribute zeros.  `loss` runs
        under ``torch.random.fork_rng``: a loss that draws random numbers draws the
        same ones at every cap of a check, and training's random stream is left as
        it was.

    Notes
    -----
    A check costs one forward and one adjoint solve of the validation batch at k;
    the controller calls it at K and at a higher cap.  The check counts what it costs
    (`GradientCheck.spent`), so the controller keeps its rechecks within
    `prdp_petsc.prdp.CHECK_BUDGET` of the run's inner iterations.

    Examples
    --------
    >>> check = pp.gradient_check(lambda: val_loss(net), net.parameters(), solver)
    >>> prdp = pp.PRDP.for_problem(k_full, check=check, epochs=epochs)
    """
    params = list(parameters)
    if not params:
        raise InputError("parameters is empty: the check needs what training updates")
    for i, p in enumerate(params):
        if not (isinstance(p, torch.Tensor) and p.requires_grad):
            raise InputError(f"parameters[{i}] must be a tensor that requires gradients")
    group = [solvers] if isinstance(solvers, KSPSolver) else list(solvers)
    if not group or not all(isinstance(s, KSPSolver) for s in group):
        raise InputError("solvers must be a KSPSolver or a non-empty sequence of them")
    if not callable(loss):
        raise InputError(f"loss must be a callable () -> tensor, got {loss!r}")

    return GradientCheck(loss, params, group)


class GradientCheck:
    """``check(k)``: the gradient of ``loss()`` with respect to `parameters` through
    `solvers` capped at k (`gradient_check` builds it); it counts its own cost.

    `spent` reads the solvers' `~prdp_petsc.core.results.SolverStats` (forward and
    adjoint inner iterations): what the checks ran, and what every solve through
    these solvers ran since the check was made (training, validation and checks), so
    a controller can hold the checks to a share of the run.  A solver whose stats are
    reset (`KSPSolver.reset_stats`) keeps counting from its new zero.
    """

    def __init__(self, loss, params: list[torch.Tensor], solvers: list[KSPSolver]) -> None:
        self.loss, self.params, self.solvers = loss, params, solvers
        self._counted = list({id(s): s for s in solvers}.values())  # each solver once
        self._seen = [(s.stats, _iterations(s)) for s in self._counted]
        self._total = 0
        self._checks = 0

    def spent(self) -> tuple[int, int]:
        """``(checks, total)``: inner iterations of the checks so far, and of every solve
        through the solvers since this check was made (the checks included)."""
        for i, solver in enumerate(self._counted):
            stats, seen = self._seen[i]
            now = _iterations(solver)
            # `reset_stats` gives the solver new stats: all of theirs is new
            self._total += now - seen if solver.stats is stats else now
            self._seen[i] = (solver.stats, now)
        return self._checks, self._total

    def __call__(self, k: int) -> np.ndarray:
        before = self.spent()[1]
        try:
            return self._gradient(k)
        finally:
            self._checks += self.spent()[1] - before

    def _gradient(self, k: int) -> np.ndarray:
        group, loss, params = self.solvers, self.loss, self.params
        saved = [s.max_it for s in group]
        try:
            for s in group:
                s.max_it = k
            # every call draws the same random numbers (dropout, noisy inputs) and leaves
            # the generators as training left them: calls differ only by the cap
            with torch.enable_grad(), torch.random.fork_rng():
                value = loss()
                if not (isinstance(value, torch.Tensor) and value.numel() == 1):
                    raise InputError("loss() must return a scalar tensor")
                if not value.requires_grad:
                    raise InputError(
                        "loss() does not depend on the parameters (computed under no_grad, "
                        "or from detached tensors?)"
                    )
                grads = torch.autograd.grad(value, params, allow_unused=True)
        finally:
            for s, k_saved in zip(group, saved, strict=True):
                s.max_it = k_saved
        return np.concatenate(
            [
                (torch.zeros_like(p) if g is None else g)
                .detach()
                .reshape(-1)
                .double()
                .cpu()
                .numpy()
                for p, g in zip(params, grads, strict=True)
            ]
        )


def _iterations(solver: KSPSolver) -> int:
    return solver.stats.forward_iterations + solver.stats.adjoint_iterations
