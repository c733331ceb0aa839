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

__all__ = ["gradient_check"]


def gradient_check(
    loss: Callable[[], torch.Tensor],
    parameters: Iterable[torch.Tensor],
    solvers: KSPSolver | Sequence[KSPSolver],
) -> Callable[[int], np.ndarray]:
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
    callable ``k -> ndarray``
        ``check(k)``: the gradient of ``loss()`` with respect to `parameters`,
        flattened and concatenated (float64), with every solver's ``max_it`` set to
        k for the call and restored after it (the adjoint follows ``max_it`` unless
        set apart).  It runs with gradients enabled (also when called under
        ``torch.no_grad()``), never accumulates into ``.grad`` and never steps an
        optimiser; parameters `loss` does not reach contribute zeros.

    Notes
    -----
    A check costs one forward and one adjoint solve of the validation batch at k;
    the controller calls it at K and at K_full.  ``PRDP.savings`` counts that cost.

    Examples
    --------
    >>> check = pp.gradient_check(lambda: val_loss(net), net.parameters(), solver)
    >>> prdp = pp.PRDP.for_problem(k_full, check=check)
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

    def check(k: int) -> np.ndarray:
        saved = [s.max_it for s in group]
        try:
            for s in group:
                s.max_it = k
            with torch.enable_grad():
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

    return check
