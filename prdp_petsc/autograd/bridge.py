"""torch autograd bridge: differentiable capped PETSc solves and parametric matvecs.

``x = solve(A, b, solver, theta=θ)`` runs ``KSPSolve`` forward.  Its backward runs
``KSPSolveTranspose`` with the solver's adjoint settings on the upstream gradient
g (a forward ``KSPSolve`` when A and the PC are symmetric): ``Aᵀ λ = g``, then
``∂L/∂b = λ`` and ``∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])``.  The forward solution is
kept, never recomputed, and nothing is computed for an input that does not need
a gradient.

θ of shape (B, p) with b of shape (B, n) is a batch of operators (a network
predicting one coefficient field per input): sample i solves ``A(θ_i) x_i = b_i``
with its own operator and PC setup, all in one call, and gets its own
``∂L/∂θ_i``.  The backward functions are once-differentiable: a second
derivative raises rather than silently missing the solve's second-order term.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp
import torch

from ..core.operator import as_csr, frozen_csr
from ..core.solution import AdjointSlot, LinearSolution
from ..core.solver import KSPSolver
from ..errors import InputError
from ..fem.distributed import DistributedParametricMatrix
from ..fem.parametric import ParametricMatrix
from .device import device_matvec, device_solve
from .implicit import ImplicitSolve, MatVec, SolveOperator
from .once import once_differentiable
from .owned import owned_matvec, owned_solve
from .tensors import as_numpy, check_tensor, check_vector

__all__ = ["matvec", "solve"]


def _operator(A, theta: torch.Tensor | None):
    """Return (ParametricMatrix or None, CSR tuple ``(indptr, indices, data, shape)``).

    ``data`` is (nnz,), or (B, nnz) for θ of shape (B, p): one operator per sample.
    For a `ParametricMatrix` the tuple is the library's own (its read-only pattern
    and the read-only values computed for θ); for a scipy matrix it is the
    caller's arrays, validated, not copied: the solver keeps what the forward
    used (see `solve`, Notes).
    """
    if isinstance(A, ParametricMatrix):
        if theta is None:
            raise InputError("A is a ParametricMatrix: pass its parameters as theta=")
        values = A.values(as_numpy(theta, "theta", finite=False))  # validates θ
        return A, (A.indptr, A.indices, values, A.shape)
    if theta is not None:
        raise InputError("theta= is only meaningful for a ParametricMatrix A")
    if not sp.issparse(A):
        raise TypeError(f"A must be a scipy sparse matrix or ParametricMatrix, got {type(A)}")
    return None, as_csr(A, finite=False)  # the solver tests values it has not seen


def _check_pairing(P: ParametricMatrix, values: np.ndarray, shape, name: str) -> None:
    """A batch of operators (θ of shape (B, p)) needs `name` of shape (B, n), same B."""
    if values.ndim == 2 and (len(shape) != 2 or shape[0] != len(values)):
        batch, p = len(values), P.n_params
        raise InputError(
            f"theta must have shape ({p},) for {name} of shape {tuple(shape)}: theta of shape "
            f"({batch}, {p}) is a batch of operators and needs {name} of shape ({batch}, "
            f"{shape[-1]}); for a shared {name} pass {name}.expand({batch}, -1)"
        )


def solve(
    A: sp.spmatrix | ParametricMatrix | DistributedParametricMatrix,
    b: torch.Tensor,
    solver: KSPSolver,
    *,
    theta: torch.Tensor | None = None,
    mode: str = "implicit",
    x0: torch.Tensor | None = None,
    return_solution: bool = False,
) -> torch.Tensor | LinearSolution:
    """Differentiable capped solve ``x = A(θ)⁻¹ b`` with a PETSc KSP.

    Parameters
    ----------
    A : scipy.sparse matrix, ParametricMatrix or DistributedParametricMatrix
        The operator; a `ParametricMatrix` is evaluated at `theta`.  A
        `~prdp_petsc.fem.distributed.DistributedParametricMatrix` selects the
        *owned* layout: `b`, `theta`, `x0` and x hold this rank's rows and
        parameters only, and the call is collective (`prdp_petsc.autograd.owned`).
        On the device path a constant operator may also be a
        `~prdp_petsc.core.operator.DLPackCSR` with its values in the solver's memory.
    b : torch.Tensor, float64, shape (n,) or (B, n)
        Right-hand side(s).  With one θ (or a scipy A) the batch shares one
        operator and one PC setup.
    solver : KSPSolver
        Carries the KSP/PC options, ``max_it`` (K) and the adjoint settings.
    theta : torch.Tensor, float64, shape (p,) or (B, p), optional
        Parameters of a ParametricMatrix.  Shape (B, p) is a batch of operators:
        sample i solves ``A(θ_i) x_i = b_i``, so `b` must be (B, n) with the same B
        (a shared right-hand side is ``b.expand(B, -1)``; it is not broadcast).
    mode : {"implicit", "unrolled"}
        ``"implicit"``: PETSc forward solve, PETSc transpose solve in backward.
        ``"unrolled"``: the same K-step iteration in torch under autograd (exact
        derivative of the truncated solver); see `prdp_petsc.autograd.unrolled`.
    x0 : torch.Tensor, shape of `b`, optional
        Initial guess (PETSc's ``KSPSetInitialGuessNonzero``), e.g. the previous
        time step's state.  Solved in correction form, ``x = x0 + P_K(b − A(θ) x0)``:
        Richardson/Jacobi and Krylov iterates from x0 are x0 plus those of the
        correction from zero, so the K iterations are PETSc's from x0; a converged
        solve's tolerance is then relative to the initial residual, not to ``‖b‖``.
        Differentiable in x0 too: ``∂L/∂x0 = g − Aᵀλ``, zero for an exact adjoint
        λ, and for a capped stationary iteration the exact derivative of its K steps.

    return_solution : bool
        Return a `LinearSolution` instead of the tensor: x as ``.value`` with this
        call's outcome (``.iterations``, ``.reason``, ``.residual_norm``,
        ``.converged``, ``.info``: every sample's `SolveInfo`; ``.adjoint`` once a
        backward ran through ``.value``).  The outcome is read there, nowhere else:
        the solver keeps only running totals (``solver.stats``).

    Returns
    -------
    torch.Tensor or LinearSolution
        x, float64, on the device of `b` (in a `LinearSolution` with
        ``return_solution=True``, the type `KSPSolver.solve` returns with an
        ndarray value).

    Raises
    ------
    SolverError
        When a solve diverges (PETSc's reason in ``.reason``); in a batch of
        operators the message names the sample.
    NonFiniteError
        NaN or Inf in b, θ, x0, or in the cotangent reaching the backward.
    StructureError
        A symmetric-only KSP or PC on a non-symmetric operator (see `KSPSolver`).

    Notes
    -----
    The operator contract: the backward uses exactly the operator the forward
    used, so editing a scipy `A` in place after the forward (``A.data *= 3``)
    changes neither this solve's gradient nor any other.  Nothing is copied per
    call for it: the backward holds the operator as the solver keeps it
    (`KSPSolver.operator_csr`: read-only arrays that new values replace, never
    edit), and while the solver still holds that operator (its
    `~KSPSolver.operator_version` unchanged) it solves on the solver's Mat as it
    is.  Only if another solve set another operator in between is the kept one
    set again (no copy, no comparison).  What the solver keeps: a
    `ParametricMatrix`'s values for θ as they are (read-only, computed by the
    library: the immutable matrix's own), and of a scipy matrix the caller can
    still change a copy of its values made when they change (one comparison per
    call finds an unchanged matrix unchanged) and of its pattern once per new
    pattern.
    With `x0` and a scipy `A`, the product ``A x0`` keeps a read-only snapshot.

    A batch of operators runs one ``KSPSolve`` per sample, each after
    ``set_operator`` with that sample's values, hence B PC setups forward.  The
    backward visits the samples in reverse order, so the last forward operator is
    still set: B − 1 more PC setups (B when another solve changed the operator in
    between; an adjoint with its own PC, e.g. ``AdjointSettings(options={"pc_type":
    ...})``, is set up once per sample).  ``∂L/∂θ_i = −Gᵀ(λ_i[rows] ⊙ x_i[cols])``
    is one (B, nnz) product and one sparse product with Gᵀ.  The backward is
    marked once-differentiable: a double backward raises instead of dropping
    the solve's second-order term.  Dirichlet values enter through the
    right-hand side; see `prdp_petsc.autograd.dirichlet`.

    A solver whose options name ``vec_type``/``mat_type`` (its `KSPSolver.vec_type`
    is not None) runs the device path, `prdp_petsc.autograd.device`: b, x and the
    gradients stay in the memory of its types (the GPU for ``cuda`` /
    ``aijcusparse``), shared with PETSc by DLPack, and a tensor in other memory
    raises `InputError`.  Without such options CUDA tensors are solved on the host,
    one copy each way per call (a documented copy, not the device path).
    """
    if mode not in ("implicit", "unrolled"):
        raise InputError(f"mode must be 'implicit' or 'unrolled', got {mode!r}")
    if not isinstance(solver, KSPSolver):
        raise TypeError(f"solver must be a KSPSolver, got {type(solver).__name__}")
    # the backward fills the slot: the graph holds it, not the result
    sol = _solve(A, b, solver, theta, mode, x0, AdjointSlot())
    return sol if return_solution else sol.value


def _solve(A, b, solver, theta, mode, x0, outcome: AdjointSlot) -> LinearSolution:
    """`solve` after its argument checks: x with the forward's `CallInfo`; `outcome`,
    the result's slot, gets the adjoint's."""
    if isinstance(A, DistributedParametricMatrix):
        if x0 is None:
            return owned_solve(A, b, solver, theta, mode, outcome)
        if x0.shape != b.shape:
            raise InputError(f"x0 must have the shape of b {tuple(b.shape)}, got {tuple(x0.shape)}")
        sol = _solve(A, b - matvec(A, x0, theta=theta), solver, theta, mode, None, outcome)
        return replace(sol, value=x0 + sol.value)
    if solver.vec_type is not None:  # the device path: torch memory shared with PETSc
        return _device_solve(A, b, solver, theta, mode, x0, outcome)
    P, csr = _operator(A, theta)
    check_vector(as_numpy(b, "b"), csr[3][0], "b")
    if P is not None:
        _check_pairing(P, csr[2], b.shape, "b")
    if x0 is not None:
        if x0.shape != b.shape:
            raise InputError(f"x0 must have the shape of b {tuple(b.shape)}, got {tuple(x0.shape)}")
        as_numpy(x0, "x0")  # finite
        if P is not None:
            residual = b - matvec(A, x0, theta=theta)
        else:
            residual = b - ConstMatVec.apply(x0, _frozen_matrix(frozen_csr(A)))
        sol = _solve(A, residual, solver, theta, mode, None, outcome)
        return replace(sol, value=x0 + sol.value)
    if mode == "unrolled":
        from .unrolled import unrolled_solve

        return unrolled_solve(A, b, solver, theta=theta)
    known_symmetric = P.is_symmetric if P is not None else None  # None: the solver tests
    operator = SolveOperator(P, csr, known_symmetric)
    x = ImplicitSolve.apply(b, theta, operator, solver, outcome)
    return LinearSolution(x, operator.forward, outcome)


def _device_solve(A, b, solver, theta, mode, x0, outcome) -> LinearSolution:
    """`_solve` on a solver's device path (`prdp_petsc.autograd.device`)."""
    if mode == "unrolled":
        raise InputError(
            "mode='unrolled' runs the iteration in torch, not in the solver: give it a "
            "solver without vec_type/mat_type options"
        )
    if x0 is not None:
        if not isinstance(A, ParametricMatrix):
            raise InputError(
                "x0 on the device path (vec_type/mat_type options) needs a ParametricMatrix "
                "A, whose product A(θ) x0 torch computes on the device; for a constant "
                "matrix pass ParametricMatrix with no parameters, or solve for b - A x0 "
                "yourself"
            )
        if not isinstance(x0, torch.Tensor) or x0.shape != b.shape:
            shape = tuple(x0.shape) if isinstance(x0, torch.Tensor) else type(x0).__name__
            raise InputError(f"x0 must have the shape of b {tuple(b.shape)}, got {shape}")
        if theta is None:
            raise InputError("A is a ParametricMatrix: pass its parameters as theta=")
        residual = b - device_matvec(A, x0, theta)
        sol = device_solve(A, residual, solver, theta, outcome)
        return replace(sol, value=x0 + sol.value)
    return device_solve(A, b, solver, theta, outcome)


def _frozen_matrix(csr: tuple) -> sp.csr_matrix:
    """A scipy matrix on the frozen arrays of `csr` (read-only: nobody can edit it)."""
    indptr, indices, data, shape = csr
    return sp.csr_matrix((data, indices, indptr), shape=shape, copy=False)


class ConstMatVec(torch.autograd.Function):
    """``M v`` for a constant scipy matrix M, rows of v (B, n) as samples; backward ``Mᵀ g``."""

    @staticmethod
    def forward(ctx, v, M):
        ctx.M = M
        return torch.from_numpy(np.asarray((M @ v.detach().cpu().numpy().T).T)).to(v.device)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        g = np.asarray((ctx.M.T @ grad.detach().cpu().numpy().T).T)
        return torch.from_numpy(g).to(grad.device), None


class _CSRProduct:
    """The `Product` of a `ParametricMatrix`'s values: one operator, or (B, nnz) values
    one per sample."""

    def __init__(self, P: ParametricMatrix, values: np.ndarray) -> None:
        self.P, self.values = P, values

    def _product(self, v: np.ndarray, transpose: bool) -> np.ndarray:
        if self.values.ndim == 2:
            return self.P.matvecs(self.values, v, transpose=transpose)
        P = self.P
        A = sp.csr_matrix((self.values, P.indices, P.indptr), shape=P.shape)
        return np.asarray(((A.T if transpose else A) @ v.T).T)

    def apply(self, v: np.ndarray) -> np.ndarray:
        return self._product(v, transpose=False)

    def apply_transpose(self, g: np.ndarray) -> np.ndarray:
        return self._product(g, transpose=True)

    def theta_vjp(self, g: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.P.vjp_matvec(g, v, per_sample=self.values.ndim == 2)


def matvec(
    A: ParametricMatrix | DistributedParametricMatrix, v: torch.Tensor, *, theta: torch.Tensor
) -> torch.Tensor:
    """Differentiable ``A(θ) v`` (used for Dirichlet lifting).

    v is (m,) or (B, m) with one θ (p,); with θ of shape (B, p) (one operator per
    sample) v must be (B, m) and sample i gives ``A(θ_i) v_i``.  For a
    `~prdp_petsc.fem.distributed.DistributedParametricMatrix` v holds this rank's
    entries of the column space and the result its rows (collective).  With θ on a
    GPU the product is computed by torch there (`prdp_petsc.autograd.device.device_matvec`,
    differentiable by torch's own autograd), without a host copy.
    """
    if isinstance(A, DistributedParametricMatrix):
        return owned_matvec(A, v, theta)
    if not isinstance(A, ParametricMatrix):
        raise TypeError("matvec expects a ParametricMatrix; for a constant matrix use torch")
    if isinstance(theta, torch.Tensor) and theta.device.type != "cpu":
        # θ on a GPU: torch computes A(θ) v there (`device_matvec`), nothing crosses
        check_tensor(v, A.shape[1], "v")
        if v.device != theta.device:
            raise InputError(f"v is on {v.device} and theta on {theta.device}: use one device")
        if theta.ndim == 2 and (v.ndim != 2 or len(v) != len(theta)):
            raise InputError(
                f"theta of shape {tuple(theta.shape)} is a batch of operators and needs v of "
                f"shape ({len(theta)}, {A.shape[1]}), got {tuple(v.shape)}"
            )
        return device_matvec(A, v, theta)
    values = A.values(as_numpy(theta, "theta"))  # validates θ
    check_vector(as_numpy(v, "v"), A.shape[1], "v")
    _check_pairing(A, values, v.shape, "v")
    return MatVec.apply(v, theta, _CSRProduct(A, values))
