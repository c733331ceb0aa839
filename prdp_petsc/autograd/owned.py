"""The torch bridge in the owned layout: every rank's tensors hold its own rows only.

With a `prdp_petsc.fem.distributed.DistributedParametricMatrix` operator,
`prdp_petsc.solve`, `prdp_petsc.autograd.bridge.matvec` and `prdp_petsc.Dirichlet` take
and return this rank's rows (and its own θ) as torch tensors; they come here.  The maths is
the replicated bridge's, run by the same autograd functions
(`prdp_petsc.autograd.implicit`): forward ``KSPSolve``, backward one transpose solve
``Aᵀλ = g``, ``∂L/∂b = λ``, ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])``; only the ghost
values of x and the ghost elements' share of ∂L/∂θ cross between ranks (PETSc
ghost exchanges, `prdp_petsc.core.ghosts`).

A loss of owned tensors is a sum over the ranks: `sum_over_ranks` adds the ranks'
parts with one ``MPI_Allreduce``, and its backward hands the (rank-independent)
upstream gradient to every rank's part unchanged, which is the derivative of a
sum.  Every call here is collective: all ranks run the same solves, products and
backward passes in the same order.  Parameters that every rank holds alike (a
network whose output feeds owned rows) get only this rank's share of their
gradient from a backward pass; their gradients must then be summed over the
ranks (``MPI_Allreduce``) before the optimizer steps.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.parallel import as_petsc_comm
from ..core.solution import AdjointSlot, LinearSolution
from ..core.solver import KSPSolver
from ..errors import InputError
from ..fem.distributed import DistributedParametricMatrix
from .implicit import ImplicitSolve, MatVec, SolveOperator
from .once import once_differentiable
from .tensors import as_numpy

__all__ = ["owned_matvec", "owned_solve", "sum_over_ranks"]


def _agree_shape(P: DistributedParametricMatrix, tensor: torch.Tensor, n: int, name: str):
    """`InputError` on every rank unless `tensor` is ``(n,)`` or ``(B, n)`` on every rank."""
    bad = tensor.ndim not in (1, 2) or tensor.shape[-1] != n
    if _any_rank(P.comm, bad):
        raise InputError(
            f"{name} must hold each rank's own rows, shape ({n},) or (batch, {n}) here; "
            f"got {tuple(tensor.shape)} on this rank (some rank's shape is wrong)"
        )


def _any_rank(comm, flag: bool) -> bool:
    if comm.getSize() == 1:
        return bool(flag)
    from mpi4py import MPI

    return bool(comm.tompi4py().allreduce(bool(flag), op=MPI.LOR))


def owned_solve(
    A: DistributedParametricMatrix,
    b: torch.Tensor,
    solver: KSPSolver,
    theta: torch.Tensor | None,
    mode: str,
    outcome: AdjointSlot | None = None,
) -> LinearSolution:
    """`prdp_petsc.solve` for a `DistributedParametricMatrix` (collective).

    `b` holds this rank's rows, ``(m,)`` or ``(B, m)`` (a batch sharing θ), `theta`
    this rank's parameters ``(p,)``; x, the result's ``value``, holds this rank's rows
    of the solution.  Implicit mode only.  `outcome`: the result's `AdjointSlot`,
    which the backward fills (None: a new one).
    """
    if mode != "implicit":
        raise InputError("the owned layout runs implicit (adjoint) gradients only")
    if theta is None:
        raise InputError("A is a DistributedParametricMatrix: pass its parameters as theta=")
    _agree_shape(A, b, A.local_shape[0], "b")
    as_numpy(b, "b", finite=False)  # float64; NaN or Inf is refused by the solver on all ranks
    csr = A.owned_csr(as_numpy(theta, "theta", finite=False))  # validated on all ranks
    slot = AdjointSlot() if outcome is None else outcome
    operator = SolveOperator(A, csr)
    x = ImplicitSolve.apply(b, theta, operator, solver, slot)
    return LinearSolution(x, operator.forward, slot)


class _OwnedProduct:
    """The `Product` of a `DistributedParametricMatrix`'s values: this rank's entries of
    v (its column block) in, its rows out (collective)."""

    def __init__(self, P: DistributedParametricMatrix, values: np.ndarray) -> None:
        self.P, self.values = P, values

    def apply(self, v: np.ndarray) -> np.ndarray:
        return self.P.matvec(self.values, v)

    def apply_transpose(self, g: np.ndarray) -> np.ndarray:
        return self.P.rmatvec(self.values, g)

    def theta_vjp(self, g: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.P.vjp_matvec(g, v)


def owned_matvec(
    A: DistributedParametricMatrix, v: torch.Tensor, theta: torch.Tensor
) -> torch.Tensor:
    """`prdp_petsc.autograd.bridge.matvec` for a `DistributedParametricMatrix`: this
    rank's entries of v (its column block) in, its rows of ``A(θ) v`` out (collective)."""
    _agree_shape(A, v, A.local_shape[1], "v")
    as_numpy(v, "v")
    values = A.values(as_numpy(theta, "theta", finite=False))
    return MatVec.apply(v, theta, _OwnedProduct(A, values))


class _SumOverRanks(torch.autograd.Function):
    @staticmethod
    def forward(ctx, t, comm):
        total = t.detach().cpu().numpy().astype(np.float64, copy=True)
        if comm.getSize() > 1:
            from mpi4py import MPI

            comm.tompi4py().Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
        return torch.from_numpy(total).to(dtype=t.dtype, device=t.device)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        return grad, None


def sum_over_ranks(t: torch.Tensor, comm) -> torch.Tensor:
    """Differentiable sum of `t` (any shape, the same on every rank) over the ranks.

    Parameters
    ----------
    t : torch.Tensor
        This rank's part, e.g. ``(x - x_obs).square().sum()`` over its own rows.
    comm : PETSc.Comm or mpi4py communicator
        The ranks to sum over, e.g. the operator's (``A.comm``).  Required: a loss
        runs outside the ``use_comm`` block a scene is built in.

    Returns
    -------
    torch.Tensor
        The same total on every rank (one ``MPI_Allreduce``, float64 sum).  Its
        gradient reaches each rank's part unchanged: every rank back-propagates
        the same total, whose derivative by each part is one.

    Notes
    -----
    Collective, in the forward and nowhere in the backward (no message).  The
    sum's order of addition differs from a serial sum's: results agree to
    round-off, not bitwise.
    """
    return _SumOverRanks.apply(t, as_petsc_comm(comm))
