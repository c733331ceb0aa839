"""Differentiable nonlinear solves ``R(u; p) = 0``: Newton or Picard, capped inner KSP.

``newton_solve(problem, u0, *params, solver=...)`` runs an outer Newton (or
Picard) loop whose every linear step ``J(u_k) δ = −R(u_k)`` is one capped
`KSPSolver` solve, so the inner cost K is ``solver.max_it`` and PRDP controls
it exactly as for a linear solve.  The outer loop stops at ``‖R‖ ≤ max(atol,
rtol ‖R(u0)‖)`` or after `max_newton` steps and returns the (possibly
truncated) iterate u*.

The backward is the implicit gradient at the returned iterate (docs/maths.md §8):
one transpose solve with the Newton Jacobian,

    J(u*)ᵀ λ = ∂L/∂u,        ∂L/∂p = −λᵀ ∂R/∂p(u*; p),

where the products ``λᵀ ∂R/∂p`` come from the problem's ``vjp``.  Nothing of the
outer loop is stored; the Jacobian is assembled once more at u* in backward.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..core.results import SolverError
from ..core.solver import KSPSolver
from ..core.structure import symmetric_only
from ..errors import InputError, StructureError
from .once import once_differentiable
from .tensors import as_numpy

__all__ = ["NonlinearProblem", "NonlinearSolution", "newton_solve"]

logger = logging.getLogger(__name__)

_METHODS = ("newton", "picard")


@dataclass(frozen=True)
class NonlinearProblem:
    """A residual ``R(u; p)`` with its Jacobian, built from plain numpy callables.

    Any object with these attributes works as well (e.g. ``NonlinearHeat`` in
    demos/heat_nonlinear.py).

    Parameters
    ----------
    n : int
        Number of unknowns (length of u and of R).
    residual : callable ``(u, *params) -> ndarray (n,)``
        The residual; `params` are numpy arrays in the order given to `newton_solve`.
    jacobian : callable ``(u, *params) -> operator``
        The exact Jacobian ``∂R/∂u``: a scipy sparse matrix or a CSR tuple
        ``(indptr, indices, data, shape)``.  Used for Newton steps and always for
        the adjoint.
    vjp : callable ``(u, lam, *params, needs) -> tuple``, optional
        ``λᵀ ∂R/∂p_i`` for every parameter, each shaped like ``p_i``, None where
        ``needs[i]`` is False.  Required only when a parameter needs a gradient.
    picard : callable ``(u, *params) -> operator``, optional
        The Picard (frozen-coefficient) operator P(u) of ``method="picard"``: the
        step solves ``P(u_k) δ = −R(u_k)``, i.e. ``A(u_k) u_{k+1} = b`` for
        ``R(u) = A(u) u − b``.
    jacobian_symmetric, picard_symmetric : bool, optional
        Declared symmetry of the operators (None: the solver tests the values).
    """

    n: int
    residual: Callable
    jacobian: Callable
    vjp: Callable | None = None
    picard: Callable | None = None
    jacobian_symmetric: bool | None = None
    picard_symmetric: bool | None = None

    def __post_init__(self):
        if isinstance(self.n, bool) or not isinstance(self.n, int | np.integer) or self.n < 1:
            raise InputError(f"n must be an integer >= 1, got {self.n!r}")
        for name in ("residual", "jacobian", "vjp", "picard"):
            value = getattr(self, name)
            if not (callable(value) or (value is None and name in ("vjp", "picard"))):
                raise TypeError(f"{name} must be callable, got {type(value).__name__}")


@dataclass(frozen=True)
class NonlinearSolution:
    """The iterate of a nonlinear solve with its outcome.

    Attributes
    ----------
    value : torch.Tensor
        u*, differentiable in the parameters (implicit gradient at u*).
    method : str
        ``"newton"`` or ``"picard"``.
    iterations : int
        Outer steps taken.
    inner_iterations : int
        KSP iterations summed over the outer steps (forward only; the solver's
        ``stats`` count these and, after backward, the adjoint's).
    reason : str
        ``"CONVERGED_FNORM_ABS"``, ``"CONVERGED_FNORM_RELATIVE"`` or
        ``"DIVERGED_MAX_IT"`` (max_newton reached: the normal outcome of a
        capped loop), as PETSc's SNES names them.
    residual_norms : tuple of float
        ``‖R(u_k)‖₂`` for k = 0 … iterations.
    """

    value: torch.Tensor
    method: str
    iterations: int
    inner_iterations: int
    reason: str
    residual_norms: tuple

    @property
    def residual_norm(self) -> float:
        """``‖R(u)‖₂`` of the returned iterate (the last of `residual_norms`), as a
        `~prdp_petsc.core.solution.LinearSolution` reports its residual."""
        return self.residual_norms[-1]

    @property
    def converged(self) -> bool:
        """Whether the outer loop met a tolerance (the cap ``max_newton`` is not one)."""
        return self.reason.startswith("CONVERGED")


@dataclass
class _Loop:
    """The outer iteration in numpy; one instance per `newton_solve` call."""

    problem: object
    solver: KSPSolver
    adjoint_solver: KSPSolver
    method: str
    max_newton: int
    rtol: float
    atol: float
    divtol: float | None
    require_convergence: bool
    info: dict | None = None

    def fail(self, message: str, name: str):
        raise SolverError(f"{self.method}: {message}", reason=f"{self.method.upper()}_{name}")

    def run(self, u: np.ndarray, params: list) -> np.ndarray:
        problem, solver = self.problem, self.solver
        name = "jacobian" if self.method == "newton" else "picard"
        operator, symmetric = getattr(problem, name), getattr(problem, f"{name}_symmetric", None)
        r = problem.residual(u, *params)
        norms = [float(np.linalg.norm(r))]
        inner, reason, k = 0, None, 0
        while True:
            if not np.isfinite(norms[-1]):
                self.fail(
                    f"residual norm is {norms[-1]} at step {k}; reduce the time step or "
                    "start closer to the solution",
                    "DIVERGED_FNORM_NAN",
                )
            if norms[-1] <= self.atol:
                reason = "CONVERGED_FNORM_ABS"
            elif k > 0 and norms[-1] <= self.rtol * norms[0]:
                reason = "CONVERGED_FNORM_RELATIVE"
            elif self.divtol is not None and norms[-1] > self.divtol * norms[0]:
                self.fail(
                    f"residual norm grew from {norms[0]:.3e} to {norms[-1]:.3e} (more than "
                    f"divtol={self.divtol:g} times) in {k} steps; damp the problem, start "
                    "closer to the solution or raise the inner max_it",
                    "DIVERGED_DTOL",
                )
            elif k == self.max_newton:
                reason = "DIVERGED_MAX_IT"
            if reason is not None:
                break
            solver.set_operator(operator(u, *params), known_symmetric=symmetric)
            try:
                step = solver.solve(-r)
            except SolverError as err:
                raise SolverError(f"{self.method} step {k}: {err}", reason=err.reason) from err
            inner += step.iterations
            u = u + step.value
            k += 1
            r = problem.residual(u, *params)
            norms.append(float(np.linalg.norm(r)))
            logger.debug("%s step %d: |R| = %.3e (%d KSP its)", self.method, k, norms[-1], inner)
        if reason == "DIVERGED_MAX_IT" and self.require_convergence:
            self.fail(
                f"|R| = {norms[-1]:.3e} after max_newton={self.max_newton} steps, above "
                f"max(atol={self.atol:g}, rtol={self.rtol:g} * {norms[0]:.3e}); raise "
                "max_newton or the inner max_it, or loosen rtol/atol",
                "DIVERGED_MAX_IT",
            )
        self.info = {
            "iterations": k,
            "inner_iterations": inner,
            "reason": reason,
            "residual_norms": tuple(norms),
        }
        return u


class _NonlinearSolve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, loop, u0, *params):
        arrays = [_array(p) for p in params]
        u = loop.run(u0.detach().cpu().numpy().copy(), arrays)
        u = torch.from_numpy(u).to(u0.device)
        ctx.loop = loop
        if any(ctx.needs_input_grad[2:]):
            tensors = [p for p in params if isinstance(p, torch.Tensor)]
            ctx.is_tensor = [isinstance(p, torch.Tensor) for p in params]
            ctx.constants = [None if t else a for a, t in zip(arrays, ctx.is_tensor, strict=True)]
            ctx.save_for_backward(u, *tensors)  # saved: in-place edits are caught
        return u

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_u):
        needs = tuple(ctx.needs_input_grad[2:])
        if not any(needs):
            return (None, None, *(None for _ in needs))
        u, *tensors = (t.detach().cpu().numpy() for t in ctx.saved_tensors)
        tensors = iter(tensors)
        params = [
            next(tensors) if t else c for t, c in zip(ctx.is_tensor, ctx.constants, strict=True)
        ]
        loop = ctx.loop
        problem, solver = loop.problem, loop.adjoint_solver
        symmetric = getattr(problem, "jacobian_symmetric", None)
        solver.set_operator(problem.jacobian(u, *params), known_symmetric=symmetric)
        lam = solver.solve_transpose(grad_u.detach().cpu().numpy()).value
        products = problem.vjp(u, lam, *params, needs=needs)
        grads = []
        for i, (need, product) in enumerate(zip(needs, products, strict=True)):
            if not need:
                grads.append(None)
                continue
            if product is None:
                raise ValueError(f"problem.vjp returned None for parameter {i}, which needs a grad")
            grads.append(-torch.as_tensor(np.asarray(product), dtype=torch.float64).to(grad_u))
        return (None, None, *grads)


def _array(p) -> np.ndarray:
    """numpy view of a tensor parameter; other parameters as float64 arrays."""
    if isinstance(p, torch.Tensor):
        return p.detach().cpu().numpy()
    return np.asarray(p, dtype=np.float64)


def _check_krylov(solver: KSPSolver, ksp, symmetric, what: str) -> None:
    """Refuse a symmetric-only method on an operator declared non-symmetric, before any
    step runs (the solver itself checks the operators it gets, declared or tested)."""
    if symmetric is False and solver.structure.symmetric:
        raise StructureError(
            f"the {what} is not symmetric, but its KSPSolver was built with "
            "Structure(symmetric=True) (that would give wrong gradients); build it without"
        )
    if symmetric is False and solver.check_structure and symmetric_only(ksp):
        raise StructureError(
            f"the {what} is not symmetric, but its KSP uses {symmetric_only(ksp)}: each needs a "
            "symmetric operator; use ksp_type gmres (or bcgs), e.g. AdjointSettings(options="
            "{'ksp_type': 'gmres'}) for the adjoint, or method='picard' with a symmetric "
            "Picard operator for the forward steps"
        )


def newton_solve(
    problem: NonlinearProblem,
    u0: torch.Tensor | None,
    *params: torch.Tensor | np.ndarray | float,
    solver: KSPSolver,
    adjoint_solver: KSPSolver | None = None,
    method: str = "newton",
    max_newton: int = 50,
    rtol: float = 1e-8,
    atol: float = 1e-50,
    divtol: float | None = 1e4,
    require_convergence: bool = False,
) -> NonlinearSolution:
    """Differentiable solve of ``R(u; params) = 0`` by Newton or Picard with a capped KSP.

    Parameters
    ----------
    problem : NonlinearProblem or an object with the same attributes
        ``n``, ``residual``, ``jacobian``, ``vjp``, ``picard`` (for Picard) and
        the symmetry declarations; see `NonlinearProblem`.
    u0 : torch.Tensor (n,) or None
        Initial guess (None: zeros).  It receives no gradient: the implicit
        gradient does not depend on where the iteration started.
    *params : torch.Tensor (float64) or numpy arrays / numbers
        Inputs of the residual, passed on to every callable as numpy arrays.
        Tensors that require grad get ``∂L/∂p = −λᵀ ∂R/∂p``.
    solver : KSPSolver
        Solves every linear step ``J(u_k) δ = −R(u_k)`` from zero with its
        ``max_it`` (K, which PRDP schedules) and tolerances.
    adjoint_solver : KSPSolver, optional
        Solves ``J(u*)ᵀ λ = ∂L/∂u`` (its adjoint KSP, `KSPSolver.solve_transpose`);
        default `solver`.  Give a separate one when the forward operator differs
        from J (Picard), so that neither PC is set up twice per step.
    method : {"newton", "picard"}
        Newton steps use ``problem.jacobian``, Picard steps ``problem.picard``;
        the adjoint uses the Jacobian either way.
    max_newton : int
        Most outer steps.  With ``rtol = atol = 0`` exactly `max_newton` run.
    rtol, atol : float
        Stop when ``‖R(u_k)‖₂ ≤ max(atol, rtol ‖R(u0)‖₂)``.
    divtol : float or None
        Raise `SolverError` when ``‖R(u_k)‖₂ > divtol ‖R(u0)‖₂`` (None: never).
    require_convergence : bool
        Raise `SolverError` when max_newton steps do not reach the tolerance
        (otherwise the truncated iterate is returned, as a capped KSP does).

    Returns
    -------
    NonlinearSolution
        ``.value`` is u* (a tensor in the autograd graph); ``.iterations``,
        ``.inner_iterations``, ``.reason``, ``.residual_norms`` describe the loop.

    Raises
    ------
    SolverError
        ``reason`` is ``"<METHOD>_DIVERGED_DTOL"``, ``"<METHOD>_DIVERGED_FNORM_NAN"``
        or ``"<METHOD>_DIVERGED_MAX_IT"`` (with `require_convergence`), METHOD being
        NEWTON or PICARD; an inner KSP failure keeps PETSc's reason and names the step.
    ValueError
        Bad settings, NaN input, or a symmetric-only KSP (CG, MINRES) on an
        operator declared non-symmetric.

    Notes
    -----
    The outer loop is not a PETSc SNES, because PRDP must own the inner KSP's
    ``max_it`` and the adjoint needs the Jacobian at the returned iterate; it is
    SNES ``newtonls`` with ``-snes_linesearch_type basic`` (full steps) or, for
    Picard, ``-snes_type picard`` in its defect-correction form.  `max_newton`,
    `rtol`, `atol`, `divtol` mean what ``-snes_max_it``, ``-snes_rtol``,
    ``-snes_atol``, ``-snes_divtol`` mean there; SNES options are not read.  The
    inner solves take every option under the solver's prefix
    (``-<prefix>ksp_type gmres -<prefix>pc_type jacobi -<prefix>ksp_monitor``),
    the adjoint ``-<prefix>adj_*``.  The Newton Jacobian is in general not
    symmetric: use GMRES (or BiCGStab) for it, or Picard with a symmetric P(u)
    and CG forward plus a GMRES adjoint.  With a truncated loop (capped K or
    max_newton) the gradient is the implicit gradient evaluated at u*, an
    approximation of the derivative of the converged solution map (§4–§5).
    The backward is once-differentiable.  One system per call: a batch is a
    loop over samples (each has its own Jacobian and PC setups anyway).
    """
    if method not in _METHODS:
        raise InputError(f"method must be 'newton' or 'picard', got {method!r}")
    if isinstance(max_newton, bool) or not isinstance(max_newton, int) or max_newton < 1:
        raise InputError(f"max_newton must be an integer >= 1, got {max_newton!r}")
    for name, value in (("rtol", rtol), ("atol", atol)):
        if isinstance(value, bool) or not np.isfinite(value) or value < 0:
            raise InputError(f"{name} must be finite and >= 0, got {value!r}")
    if divtol is not None and not (np.isfinite(divtol) and divtol > 1):
        raise InputError(f"divtol must be finite and > 1 (or None), got {divtol!r}")
    adjoint_solver = solver if adjoint_solver is None else adjoint_solver
    for name, s in (("solver", solver), ("adjoint_solver", adjoint_solver)):
        if not isinstance(s, KSPSolver):
            raise TypeError(f"{name} must be a KSPSolver, got {type(s).__name__}")
    if method == "picard" and getattr(problem, "picard", None) is None:
        raise InputError("method='picard' needs problem.picard (the Picard operator)")
    n = int(problem.n)
    if u0 is None:
        u0 = torch.zeros(n, dtype=torch.float64)
    if as_numpy(u0, "u0").shape != (n,):
        raise InputError(f"u0 must have shape ({n},), got {tuple(u0.shape)}")
    for i, p in enumerate(params):
        if isinstance(p, torch.Tensor):
            as_numpy(p, f"params[{i}]")  # float64, finite
    needs_grad = torch.is_grad_enabled() and any(
        isinstance(p, torch.Tensor) and p.requires_grad for p in params
    )
    operator = "jacobian" if method == "newton" else "picard"
    forward_symmetric = getattr(problem, f"{operator}_symmetric", None)
    _check_krylov(solver, solver.ksp, forward_symmetric, f"{method} operator")
    if needs_grad:
        if getattr(problem, "vjp", None) is None:
            raise InputError("a parameter requires grad: the problem needs a vjp callable")
        jacobian_symmetric = getattr(problem, "jacobian_symmetric", None)
        _check_krylov(adjoint_solver, adjoint_solver.adjoint_ksp, jacobian_symmetric, "Jacobian")
    loop = _Loop(
        problem=problem,
        solver=solver,
        adjoint_solver=adjoint_solver,
        method=method,
        max_newton=max_newton,
        rtol=float(rtol),
        atol=float(atol),
        divtol=None if divtol is None else float(divtol),
        require_convergence=bool(require_convergence),
    )
    u = _NonlinearSolve.apply(loop, u0, *params)
    info = loop.info
    return NonlinearSolution(
        u,
        method,
        info["iterations"],
        info["inner_iterations"],
        info["reason"],
        info["residual_norms"],
    )
