"""The solver grid on vector and mixed operators: elasticity and a Stokes saddle point.

`tests/test_grid.py` runs every KSP × PC on scalar operators; this grid adds the
structure a vector problem declares.  Axes:

* KSP × PC: those of the scalar grid (`KSPS`, `PCS`) on elasticity; for Stokes the
  Krylov methods that take an indefinite operator and a non-symmetric PC
  (``gmres``, ``fgmres``, ``bcgs``) with Schur-complement fieldsplits declared
  through ``fields=`` (`SCHUR_TYPES`);
* operator (`VECTOR_OPERATORS`): plane-strain elasticity on a 6 × 3 mesh, E per
  element, clamped on one side (``clamped``, SPD), the same with the rigid-body
  modes as near-null space and block size 2 (``clamped_modes``), the free body with
  the modes declared as null space (``free_modes``: the minimum-norm least-squares
  solution is the answer), the free body with nothing declared (``free``), and
  Taylor–Hood Stokes (``stokes``);
* layout: one operator, or a batch of operators (θ of shape (B, p)).

A cell that solves must give the dense answer and gradients (x, ∂L/∂b, ∂L/∂θ of
``L = gᵀx``) to `tolerance`; the free body without a null space must never come
back converged: it raises a `SolverError` (`SingularOperatorError` with GAMG, whose
coarse solve blows the iterate up along the kernel) or returns a capped,
unconverged iterate.  Every outcome was measured with PETSc 3.26.
"""

import itertools
from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest
import torch
from _vector import SCHUR, clamped, elasticity, stokes
from test_grid import (
    KSPS,
    NOT_CONVERGENT,
    PCS,
    SOLVES,
    UNCERTIFIED,
    Outcome,
    Raises,
    relative_error,
)

import prdp_petsc as pp
from prdp_petsc.errors import InputError, SolverError

#: samples of a batch of operators; converged settings
B, MAX_IT, RTOL = 2, 2000, 1e-12
LAYOUTS = ("one", "operator_batch")
ELASTICITY = ("clamped", "clamped_modes", "free_modes", "free")
STOKES_KSPS = ("gmres", "fgmres", "bcgs")
SCHUR_TYPES = ("full", "upper", "lower", "diag")


@dataclass(frozen=True, eq=False)
class VectorOperator:
    """A(θ) (a `ParametricMatrix`), the solver's declared structure and θ's range."""

    name: str
    A: pp.ParametricMatrix
    structure: pp.Structure | None
    singular: bool

    @property
    def thetas(self) -> np.ndarray:
        return 1.0 + np.random.default_rng(1).random((B, self.A.n_params))

    def matrix(self, theta) -> np.ndarray:
        return self.A.matrix(theta).toarray()


@cache
def operators() -> dict[str, VectorOperator]:
    basis, A = elasticity(n=3)
    bc = clamped(basis, A)
    modes = pp.rigid_body_modes(basis)
    near = pp.Structure(near_nullspace=pp.rigid_body_modes(basis, bc.interior), block_size=2)
    declared = pp.Structure(nullspace=modes, near_nullspace=modes, block_size=2)
    _, S, sbc, fields, _ = stokes(n=2)
    return {
        "clamped": VectorOperator("clamped", bc.A_II, None, False),
        "clamped_modes": VectorOperator("clamped_modes", bc.A_II, near, False),
        "free_modes": VectorOperator("free_modes", A, declared, True),
        "free": VectorOperator("free", A, None, True),
        "stokes": VectorOperator("stokes", sbc.A_II, pp.Structure(fields=fields), False),
    }


def reference(op: VectorOperator, theta, b, g):
    """Dense x = A⁺b, λ = A⁺ᵀg and ∂L/∂θ_k = −λᵀ (∂A/∂θ_k) x (A⁺ = A⁻¹ if regular)."""
    A = op.matrix(theta)
    inverse = np.linalg.pinv(A) if op.singular else np.linalg.inv(A)
    x, lam = inverse @ b, inverse.T @ g
    P = op.A
    rows = np.repeat(np.arange(P.shape[0]), np.diff(P.indptr))
    # (λ[rows] ⊙ x[cols]) summed with G: ∂L/∂θ = −Gᵀ(λ[rows] ⊙ x[cols])
    return x, lam, -(P.G.T @ (lam[rows] * x[P.indices]))


def options(ksp: str, pc: str) -> dict:
    """The cell's options: the scalar grid's for elasticity, a Schur split for Stokes."""
    if pc in SCHUR_TYPES:
        return {**SCHUR, "ksp_type": ksp, "pc_fieldsplit_schur_fact_type": pc}
    out = {"ksp_type": ksp, "pc_type": pc}
    if ksp == "richardson":
        out["ksp_richardson_scale"] = RICHARDSON_SCALE_ELASTICITY.get(pc, 1.0)
    return out


#: Richardson damping on elasticity: λ_max(A) ≈ 14.5 and λ_max(D⁻¹A) ≈ 3.1 at E ∈ [1, 2)
#: (measured), so 0.13 without a PC (as in the scalar grid) and 0.6 with Jacobi
RICHARDSON_SCALE_ELASTICITY = {"none": 0.13, "jacobi": 0.6}


def expected(ksp: str, pc: str, operator: str):
    """What the cell does: `SOLVES`, `NOT_CONVERGENT`, `UNCERTIFIED`, or ``"never
    converged"`` for the free body without a null space (`check_never_converged`)."""
    if operator == "free":
        return "never converged"
    if ksp == "richardson" and operator.startswith("clamped"):
        if pc in ("none", "jacobi"):
            # damped Richardson contracts the smallest eigenmodes of the clamped body by
            # 1 − ωλ_min per step: 2000 steps leave an error of 0.2 (none) and 0.09 (jacobi);
            # with the free body's null space declared those modes are projected out
            return NOT_CONVERGENT
        if pc == "sor" or (pc == "gamg" and operator == "clamped"):
            # PCApplyRichardson runs 2000 sweeps (SSOR) or V-cycles (scalar GAMG) and
            # computes no residual: CONVERGED_ITS; GAMG with the modes converges by rtol
            return UNCERTIFIED
    return SOLVES


def tolerance(ksp: str, pc: str, operator: str) -> float:
    """Relative max-norm tolerance of x and the gradients: converged cells ≤ 1e-10
    measured; 2000 SSOR sweeps on the clamped body leave 4e-6."""
    if ksp == "richardson" and pc == "sor":
        return 1e-5
    return 1e-8


def run_cell(ksp: str, pc: str, operator: str, layout: str):
    op = operators()[operator]
    n = op.A.shape[0]
    rng = np.random.default_rng(7)
    shape = (n,) if layout == "one" else (B, n)
    b, g = rng.standard_normal(shape), rng.standard_normal(shape)
    thetas = op.thetas if layout == "operator_batch" else op.thetas[:1]
    theta = thetas if layout == "operator_batch" else thetas[0]
    out = Outcome()
    b_t = torch.tensor(b, requires_grad=True)
    theta_t = torch.tensor(theta, requires_grad=True)
    prefix = f"vgrid_{ksp}_{pc}_{operator}_{layout}_"
    with pp.KSPSolver(
        options(ksp, pc), prefix=prefix, max_it=MAX_IT, rtol=RTOL, structure=op.structure
    ) as solver:
        try:
            sol = pp.solve(op.A, b_t, solver, theta=theta_t, return_solution=True)
            x, out.forward = sol.value, sol.info
            out.stage = "backward"
            (x * torch.from_numpy(g)).sum().backward()
            out.adjoint = sol.adjoint
        except (SolverError, InputError) as err:
            out.error = err
            return out, (b, g, thetas)
    out.x, out.grad_b, out.grad_theta = x.detach().numpy(), b_t.grad.numpy(), theta_t.grad.numpy()
    return out, (b, g, thetas)


def answer_errors(out: Outcome, operator: str, layout: str, b, g, thetas) -> dict:
    op = operators()[operator]
    b, g = np.atleast_2d(b, g)
    refs = [reference(op, thetas[i], b[i], g[i]) for i in range(len(b))]
    x, lam, dtheta = (np.array(r) for r in zip(*refs))
    return {
        "x": relative_error(np.atleast_2d(out.x), x),
        "dL/db": relative_error(np.atleast_2d(out.grad_b), lam),
        "dL/dtheta": relative_error(np.atleast_2d(out.grad_theta), dtheta),
    }


CELLS = [
    *itertools.product(KSPS, PCS, ELASTICITY, LAYOUTS),
    *itertools.product(STOKES_KSPS, SCHUR_TYPES, ("stokes",), LAYOUTS),
]


@pytest.mark.parametrize(
    ("ksp", "pc", "operator", "layout"), [pytest.param(*c, id="-".join(c)) for c in CELLS]
)
def test_cell(ksp, pc, operator, layout):
    want = expected(ksp, pc, operator)
    out, (b, g, thetas) = run_cell(ksp, pc, operator, layout)
    if want == "never converged":
        check_never_converged(out, ksp, pc)
        return
    if isinstance(want, Raises):
        assert isinstance(out.error, want.error), f"expected {want}, got {out.error!r}"
        assert (out.stage, out.error.reason) == (want.stage, want.reason), repr(out.error)
        return
    assert out.error is None, f"expected {want}, got {out.error!r}"
    errors = answer_errors(out, operator, layout, b, g, thetas)
    if want == NOT_CONVERGENT:  # capped without an error, never converged, not the answer
        forward = out.forward
        assert forward.reasons == ["DIVERGED_MAX_IT"] * len(forward) and not forward.converged
        assert errors["x"] > 1e3 * tolerance(ksp, pc, operator), errors
        return
    assert max(errors.values()) <= tolerance(ksp, pc, operator), errors
    if want == SOLVES:
        for call in (out.forward, out.adjoint):
            assert call.converged and len(call) == len(np.atleast_2d(b)), call
    else:
        assert want == UNCERTIFIED and not out.forward.converged


def check_never_converged(out: Outcome, ksp: str, pc: str) -> None:
    """The free body without a null space: an error, or an iterate that says it is not
    converged.  GAMG's blow-up along the kernel is named (`SingularOperatorError`), but
    for MINRES, which stops at x = 0 ("step length") and leaves nothing to diagnose:
    ``FALSE_CONVERGENCE``."""
    if out.error is not None:
        assert isinstance(out.error, SolverError), repr(out.error)
        if pc == "gamg":
            named = "FALSE_CONVERGENCE" if ksp == "minres" else "SINGULAR"
            assert out.error.reason == named, repr(out.error)
        return
    assert pc != "gamg"
    assert not any(call.converged for call in (out.forward, out.adjoint))


def test_table_tally():
    """The table in numbers, so that a changed entry is a visible change of this test."""
    counts: dict = {}
    for ksp, pc, operator, _ in CELLS:
        want = expected(ksp, pc, operator)
        counts[want] = counts.get(want, 0) + 1
    assert counts == {
        SOLVES: 2 * (5 * 7 * 3 - 7) + 24,  # 3 declared elasticity operators, 12 Stokes pairs
        NOT_CONVERGENT: 2 * 4,  # richardson with none or jacobi, clamped (with or without modes)
        UNCERTIFIED: 2 * 3,  # richardson with sor (clamped, clamped_modes) or gamg (clamped)
        "never converged": 2 * 5 * 7,  # the free body with nothing declared
    }
