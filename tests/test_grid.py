"""The solver grid: every KSP × PC × operator × layout × mode cell solves or names its error.

Hand-picked cases test what their author thought of; a grid (lineax's
``tests/helpers.py`` is the model) tests every combination, so a cell that
silently returns a wrong answer fails.  The axes:

* KSP: ``cg``, ``minres``, ``gmres``, ``bcgs``, ``richardson``;
* PC: ``none``, ``jacobi``, ``sor``, ``icc``, ``ilu`` (both, on every operator:
  ICC is refused on the non-symmetric one), ``gamg``, ``bjacobi``;
* operator: SPD, symmetric indefinite, non-symmetric, singular (pure Neumann,
  ``nullspace="constant"``, compatible right-hand side), all on an 8 × 8 grid
  (n = 64) and affine in three parameters θ (`OPERATORS`);
* layout: one right-hand side (a scipy matrix, ∂L/∂b), a batch of right-hand
  sides ``(B, n)`` with one θ (∂L/∂b and the summed ∂L/∂θ), a batch of operators
  (θ of shape ``(B, p)``, one ∂L/∂θ_i per sample);
* mode: ``implicit`` and ``unrolled``.

`expected` is the table: a cell either solves (forward equal to a dense direct
solve, ∂L/∂b = A⁻ᵀg and ∂L/∂θ_k = −λᵀ M_k x from dense numpy solves, to `tolerance`,
with converged solves: rtol 1e-12, max_it 2000), or raises a named error at a
named stage, or is one of two measured exceptions that must not pass as
converged (`NOT_CONVERGENT`, `UNCERTIFIED`).  Every outcome was measured with
PETSc 3.26 and is explained next to its entry.

A cell that solves must also report it: one record per sample in its result's
``info`` and, after the backward, ``adjoint``, each converged (`RecordError`
otherwise).  Richardson with GAMG is one to watch: PETSc tests its tolerance inside
the PC and leaves the KSP's residual history empty (the record's residual is None,
and it is converged).

Every cell runs by default (849 tests, about 4 s on two cores); the cells outside
a fixed sample (`in_default_sample`: every cell with one right-hand side in implicit
mode, every unrolled cell of a supported KSP/PC pair, and every fourth of the
others) are marked ``slow``, so ``pytest -m "not slow"`` runs the sample alone.
"""

import itertools
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

import prdp_petsc as pp
from prdp_petsc.errors import InputError, SolverError, StructureError

KSPS = ("cg", "minres", "gmres", "bcgs", "richardson")
PCS = ("none", "jacobi", "sor", "icc", "ilu", "gamg", "bjacobi")
OPERATOR_NAMES = ("spd", "indefinite", "nonsymmetric", "singular")
LAYOUTS = ("one", "rhs_batch", "operator_batch")
MODES = ("implicit", "unrolled")

#: grid points per axis (n = N²), parameters per operator, samples per batch
N, P, B = 8, 3, 3
n = N * N
#: converged solves: the implicit gradient is then the true derivative
MAX_IT, RTOL = 2000, 1e-12
#: Richardson damping that converges on the SPD operator: 2 / (λ_min + λ_max) ≈ 0.135
#: without a PC (λ_max ≈ 14.4); 1 with every PC (the eigenvalues of M⁻¹A lie in (0, 2))
RICHARDSON_SCALE = {"none": 0.13}
#: KSP/PC pairs that mode="unrolled" supports (`prdp_petsc.autograd.unrolled`)
UNROLLED = {("richardson", "none"), ("richardson", "jacobi"), ("cg", "none"), ("cg", "jacobi")}


# -- operators: A(θ) = C + Σ_k θ_k M_k on an N × N grid ----------------------------------------


def _stripe(doubled_column: int) -> int:
    """Parameter index (vertical stripe) of a point at column ``doubled_column / 2``."""
    return min(doubled_column * P // (2 * N), P - 1)


def edge_laplacians(dirichlet: bool) -> list[sp.csr_matrix]:
    """Graph Laplacians M_k of the grid edges in stripe k (five-point stencil, h = 1).

    With `dirichlet` a boundary point also gets the edges to its missing
    neighbours (zero boundary values), so ``Σ θ_k M_k`` is SPD for θ > 0;
    without, it is the pure-Neumann Laplacian, singular with the constants as
    null space for every θ > 0.
    """
    entries = [([], [], []) for _ in range(P)]

    def add(k, i, j, value):
        entries[k][0].append(i)
        entries[k][1].append(j)
        entries[k][2].append(value)

    for i, j in itertools.product(range(N), range(N)):
        a = i * N + j
        for di, dj in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            ii, jj = i + di, j + dj
            inside = 0 <= ii < N and 0 <= jj < N
            if inside and (ii, jj) > (i, j):
                k, c = _stripe(j + jj), ii * N + jj
                add(k, a, a, 1.0)
                add(k, c, c, 1.0)
                add(k, a, c, -1.0)
                add(k, c, a, -1.0)
            elif not inside and dirichlet:
                add(_stripe(2 * j), a, a, 1.0)
    return [sp.csr_matrix((v, (r, c)), shape=(n, n)) for r, c, v in entries]


def upwind(axis: int) -> sp.csr_matrix:
    """First-order upwind difference along `axis` (1: x, 0: y), positive velocity."""
    d = sp.diags([np.ones(N), -np.ones(N - 1)], [0, -1])
    eye = sp.identity(N)
    return sp.csr_matrix(sp.kron(eye, d) if axis == 1 else sp.kron(d, eye))


@dataclass(frozen=True, eq=False)
class Operator:
    """``A(θ) = const + Σ_k θ_k terms[k]`` with θ drawn from ``[low, high)``."""

    name: str
    const: sp.csr_matrix
    terms: tuple
    low: float
    high: float

    @property
    def singular(self) -> bool:
        return self.name == "singular"

    @cached_property
    def parametric(self) -> pp.ParametricMatrix:
        """The same operator as a `ParametricMatrix` (a₀ and G read off the CSR pattern)."""
        pattern = sp.csr_matrix(abs(self.const) + sum(abs(t) for t in self.terms) + sp.identity(n))
        pattern.sort_indices()
        rows = np.repeat(np.arange(n), np.diff(pattern.indptr))
        cols = pattern.indices

        def on_pattern(M):
            return np.asarray(sp.csr_matrix(M)[rows, cols]).ravel()

        G = sp.csr_matrix(np.column_stack([on_pattern(t) for t in self.terms]))
        return pp.ParametricMatrix(pattern.indptr, cols, (n, n), on_pattern(self.const), G)

    @cached_property
    def thetas(self) -> np.ndarray:
        """B fixed parameter vectors; the first is the θ of the single-operator layouts."""
        u = np.random.default_rng(1).random((B, P))
        return self.low + (self.high - self.low) * u

    def matrix(self, theta) -> sp.csr_matrix:
        return sp.csr_matrix(self.const + sum(t * M for t, M in zip(theta, self.terms)))


def _operators() -> dict[str, Operator]:
    dirichlet, neumann = edge_laplacians(True), edge_laplacians(False)
    zero = sp.csr_matrix((n, n))
    # eigenvalues of Σ M_k at θ = 1 are 4 − 2cos(iπ/9) − 2cos(jπ/9): σ in the middle of
    # the gap (1.121, 1.468) leaves 6 negative ones; θ ∈ [1, 1.03) keeps |λ| ≥ 0.15
    sigma = (1.1206147584 + 1.4679111138) / 2
    diffusion = sum(dirichlet)
    return {
        "spd": Operator("spd", zero, tuple(dirichlet), 1.0, 2.0),
        "indefinite": Operator(
            "indefinite", -sigma * sp.identity(n, format="csr"), tuple(dirichlet), 1.0, 1.03
        ),
        # advection–diffusion: θ scales the diffusion and the two upwind velocities, an
        # M-matrix for θ > 0 (ILU, Jacobi and GAMG all work on it)
        "nonsymmetric": Operator(
            "nonsymmetric", diffusion, (diffusion, 4 * upwind(1), 4 * upwind(0)), 0.5, 1.5
        ),
        "singular": Operator("singular", zero, tuple(neumann), 1.0, 2.0),
    }


OPERATORS = _operators()


def reference(op: Operator, theta, b, g):
    """Dense answer for ``L = gᵀx``: x, λ = ∂L/∂b and ∂L/∂θ, independent of the library.

    ``x = A⁻¹b`` (``A⁺b`` for the singular operator), ``λ = A⁻ᵀg`` (``A⁺ᵀg``) and
    ``∂L/∂θ_k = −λᵀ M_k x``; the last holds for the singular operator too, because
    its null space does not depend on θ (`test_reference_is_the_derivative`).
    """
    A = op.matrix(theta)
    if op.singular:
        pinv = np.linalg.pinv(A.toarray())
        x, lam = pinv @ b, pinv.T @ g
    else:
        x, lam = spla.spsolve(A.tocsc(), b), spla.spsolve(A.T.tocsc(), g)
    return x, lam, np.array([-lam @ (M @ x) for M in op.terms])


# -- the expectation table -------------------------------------------------------------------

#: converged, scipy's answer and gradient
SOLVES = "solves"
#: returns after max_it without an error (DIVERGED_MAX_IT is a capped solve's normal end):
#: every sample must report ``converged`` False, and the answer is not scipy's
NOT_CONVERGENT = "not convergent"
#: PETSc runs max_it sweeps and computes no residual (Richardson+SOR's PCApplyRichardson):
#: ``CONVERGED_ITS`` with residual None and ``converged`` False, though after 2000 SSOR
#: sweeps the answer is scipy's (checked)
UNCERTIFIED = "uncertified"


@dataclass(frozen=True)
class Raises:
    """The cell raises `error` with ``error.reason == reason`` in the forward or backward."""

    error: type
    reason: str
    stage: str = "forward"


def expected(ksp: str, pc: str, operator: str, mode: str = "implicit"):
    """What the cell does: `SOLVES`, `NOT_CONVERGENT`, `UNCERTIFIED` or a `Raises`.

    The layout never changes the outcome (measured: a batch of operators differs
    from one operator only in θ, within each operator's range).
    """
    if mode == "unrolled":
        if (ksp, pc) not in UNROLLED:
            return Raises(InputError, "INVALID_INPUT")  # no torch version of the iteration
        if operator == "singular":
            return Raises(InputError, "INVALID_INPUT")  # unrolled does not project null spaces
        # otherwise the iteration is PETSc's, step for step: the implicit outcome
    if operator == "nonsymmetric":
        if ksp in ("cg", "minres") or pc == "icc":
            return Raises(StructureError, "STRUCTURE")  # symmetric-only method, refused
        if pc == "sor":
            # the forward runs; PCApplyTranspose_SOR refuses (PETSC_ERR_SUP: "Can only
            # apply transpose of SOR if matrix is symmetric and sweep is symmetric")
            return Raises(SolverError, "NO_TRANSPOSE", "backward")
        if ksp == "richardson" and pc == "none":
            # the scale tuned on the SPD operator: |1 − 0.13 λ| > 1 for Re λ up to 31
            return Raises(SolverError, "DIVERGED_DTOL")
    if operator == "indefinite":
        if ksp == "cg":
            # pᵀAp changes sign; with ILU(0) (an indefinite factor of an indefinite A)
            # and GAMG (smoothers assuming SPD) zᵀr changes sign first
            reason = (
                "DIVERGED_INDEFINITE_PC" if pc in ("ilu", "gamg") else "DIVERGED_INDEFINITE_MAT"
            )
            return Raises(SolverError, reason)
        if ksp == "minres" and pc in ("ilu", "gamg"):
            # MINRES needs an SPD preconditioner; Jacobi and SSOR (positive diagonal) and
            # ICC and bjacobi (its blocks use ICC on a symmetric matrix; PETSc's ICC shifts
            # to positive definite by default) are SPD, ILU(0) and this GAMG are not
            return Raises(SolverError, "DIVERGED_INDEFINITE_PC")
        if ksp == "richardson":
            # a positive scale amplifies the negative eigen-directions: DTOL where PETSc
            # tests norms; SOR and GAMG run PCApplyRichardson, which tests no divergence,
            # so 2000 sweeps overflow and the solver's finiteness check raises
            reason = "DIVERGED_NANORINF" if pc in ("sor", "gamg") else "DIVERGED_DTOL"
            return Raises(SolverError, reason)
    if ksp == "richardson":
        if pc == "jacobi" and operator == "singular":
            # D⁻¹A of the Neumann Laplacian of a bipartite grid has the eigenvalue 2
            # exactly: with scale 1 that mode oscillates forever (DIVERGED_MAX_IT)
            return NOT_CONVERGENT
        if pc == "sor" and operator != "singular":
            # PCApplyRichardson (skipped when a null space is attached: then the
            # ordinary iteration runs and converges)
            return UNCERTIFIED
    return SOLVES


def tolerance(ksp: str, pc: str, operator: str, mode: str) -> float:
    """Relative max-norm tolerance of x, ∂L/∂b and ∂L/∂θ against `reference`.

    Measured errors of converged cells are ≤ 1e-11 (implicit) and ≤ 1e-10
    (unrolled ∂L/∂θ); a cell that stops early is off by 1e-3 or more.
    """
    if pc == "ilu" and operator == "indefinite":
        # left-preconditioned GMRES/BiCGStab test rtol on ‖M⁻¹r‖, and the unshifted ILU(0)
        # factor of the indefinite operator is ill-conditioned (cond M⁻¹ ≈ 6e4, measured):
        # a true error of 1.2e-8 at rtol 1e-12
        return 1e-6
    return 1e-8


# -- one cell ----------------------------------------------------------------------------------


class RecordError(AssertionError):
    """A call's record (its result's ``info`` or ``adjoint``) contradicting the solve."""


@dataclass
class Outcome:
    """What one cell returned: an error and its stage, or the answer and the records."""

    error: Exception | None = None
    stage: str = "forward"
    x: np.ndarray | None = None
    grad_b: np.ndarray | None = None
    grad_theta: np.ndarray | None = None
    forward: object = None
    adjoint: object = None


def run_cell(ksp: str, pc: str, operator: str, layout: str, mode: str):
    """Solve, then backpropagate ``L = gᵀx``; return the `Outcome` and (b, g, θs)."""
    op = OPERATORS[operator]
    rng = np.random.default_rng(7)
    shape = (n,) if layout == "one" else (B, n)
    b, g = rng.standard_normal(shape), rng.standard_normal(shape)
    if op.singular:
        b -= b.mean(axis=-1, keepdims=True)  # compatible: orthogonal to the constants
    thetas = op.thetas if layout == "operator_batch" else op.thetas[:1].repeat(B, axis=0)
    options = {"ksp_type": ksp, "pc_type": pc}
    if ksp == "richardson":
        options["ksp_richardson_scale"] = RICHARDSON_SCALE.get(pc, 1.0)
    out = Outcome()
    b_t = torch.tensor(b, requires_grad=True)
    with pp.KSPSolver(
        options,
        prefix=f"grid_{ksp}_{pc}_{operator}_{layout}_{mode}_",
        max_it=MAX_IT,
        rtol=RTOL,
        structure=pp.Structure(nullspace="constant" if op.singular else None),
    ) as solver:
        theta_t = None
        try:
            if layout == "one":
                sol = pp.solve(op.matrix(thetas[0]), b_t, solver, mode=mode, return_solution=True)
            else:
                theta = thetas if layout == "operator_batch" else thetas[0]
                theta_t = torch.tensor(theta, requires_grad=True)
                sol = pp.solve(
                    op.parametric, b_t, solver, theta=theta_t, mode=mode, return_solution=True
                )
            out.stage = "backward"
            (sol.value * torch.from_numpy(g)).sum().backward()
        except (SolverError, InputError) as err:
            out.error = err
            return out, (b, g, thetas)
        out.forward, out.adjoint = sol.info, sol.adjoint
    x = sol.value
    out.x = x.detach().numpy()
    out.grad_b = b_t.grad.numpy()
    out.grad_theta = None if theta_t is None else theta_t.grad.numpy()
    return out, (b, g, thetas)


def relative_error(value, ref) -> float:
    return float(np.abs(np.asarray(value) - ref).max() / np.abs(ref).max())


def answer_errors(out: Outcome, layout: str, operator: str, b, g, thetas) -> dict:
    """Relative errors of x, ∂L/∂b and ∂L/∂θ against the dense `reference`."""
    op = OPERATORS[operator]
    b, g = np.atleast_2d(b, g)
    refs = [reference(op, thetas[i], b[i], g[i]) for i in range(len(b))]
    x, lam, dtheta = (np.array(r) for r in zip(*refs))
    errors = {
        "x": relative_error(np.atleast_2d(out.x), x),
        "dL/db": relative_error(np.atleast_2d(out.grad_b), lam),
    }
    if layout == "rhs_batch":  # one θ shared by the batch: the samples' gradients add up
        errors["dL/dtheta"] = relative_error(out.grad_theta, dtheta.sum(axis=0))
    elif layout == "operator_batch":
        errors["dL/dtheta"] = relative_error(out.grad_theta, dtheta)
    return errors


def samples(layout: str) -> int:
    return 1 if layout == "one" else B


def check_converged_records(out: Outcome, layout: str, mode: str) -> None:
    """One record per sample, each converged (raises `RecordError` otherwise)."""
    for kind, call in (("forward", out.forward), ("adjoint", out.adjoint)):
        if kind == "adjoint" and mode == "unrolled":
            if call is not None:
                raise RecordError(f"an unrolled backward ran no adjoint solve, got {call}")
            continue  # the unrolled backward is torch's: no PETSc adjoint solve
        if call is None or len(call) != samples(layout):
            raise RecordError(f"{kind} should hold {samples(layout)} samples, got {call}")
        if call.kind != kind or not call.converged:
            raise RecordError(f"{kind}: {call.kind} {call.reasons} {call.residual_norms}")


# -- the grid ----------------------------------------------------------------------------------

CELLS = list(itertools.product(KSPS, PCS, OPERATOR_NAMES, LAYOUTS, MODES))


def in_default_sample(ksp: str, pc: str, operator: str, layout: str, mode: str) -> bool:
    """The fixed sample of the default run; the other cells are marked ``slow``."""
    if layout == "one" and mode == "implicit":
        return True
    if mode == "unrolled" and (ksp, pc) in UNROLLED:
        return True
    index = (
        KSPS.index(ksp)
        + PCS.index(pc)
        + OPERATOR_NAMES.index(operator)
        + LAYOUTS.index(layout)
        + MODES.index(mode)
    )
    return index % 4 == 0


def _param(cell):
    marks = []
    if not in_default_sample(*cell):
        marks.append(pytest.mark.slow)
    return pytest.param(*cell, marks=marks, id="-".join(cell))


@pytest.mark.parametrize(("ksp", "pc", "operator", "layout", "mode"), [_param(c) for c in CELLS])
def test_cell(ksp, pc, operator, layout, mode):
    want = expected(ksp, pc, operator, mode)
    out, (b, g, thetas) = run_cell(ksp, pc, operator, layout, mode)

    if isinstance(want, Raises):
        assert isinstance(out.error, want.error), f"expected {want}, got {out.error!r}"
        assert (out.stage, out.error.reason) == (want.stage, want.reason), repr(out.error)
        if want.error is SolverError and want.stage == "forward":
            if want.reason != "DIVERGED_NANORINF":  # found by the finiteness check, not PETSc
                assert want.reason in str(out.error)  # the message names PETSc's reason
        return
    assert out.error is None, f"expected {want}, got {out.error!r}"

    errors = answer_errors(out, layout, operator, b, g, thetas)
    tol = tolerance(ksp, pc, operator, mode)
    if want == NOT_CONVERGENT:
        # capped without an error: never converged, and never scipy's answer
        assert not out.forward.converged and not out.adjoint.converged
        assert out.forward.reasons == ["DIVERGED_MAX_IT"] * samples(layout)
        assert errors["x"] > 1e3 * tol
        return
    assert max(errors.values()) <= tol, errors
    if want == UNCERTIFIED:
        assert len(out.forward) == samples(layout)
        assert out.forward.reasons == ["CONVERGED_ITS"] * samples(layout)
        assert not out.forward.residual_computed.any()
        assert not any(s.converged for s in out.forward)
        assert out.forward.iterations.tolist() == [MAX_IT] * samples(layout)
        return
    assert want == SOLVES
    check_converged_records(out, layout, mode)


def test_table_tally():
    """The table in numbers (implicit mode, 140 KSP/PC/operator triples; unrolled adds
    128 InputErrors), so that a changed entry is a visible change of this test."""

    def tally(mode):
        counts = {}
        for ksp, pc, operator in itertools.product(KSPS, PCS, OPERATOR_NAMES):
            want = expected(ksp, pc, operator, mode)
            key = want if isinstance(want, str) else f"{want.error.__name__} {want.reason}"
            counts[key] = counts.get(key, 0) + 1
        return counts

    assert tally("implicit") == {
        SOLVES: 101,
        NOT_CONVERGENT: 1,  # richardson/jacobi, singular
        UNCERTIFIED: 1,  # richardson/sor, SPD
        "StructureError STRUCTURE": 17,  # cg, minres or icc on the non-symmetric operator
        "SolverError NO_TRANSPOSE": 3,  # sor's adjoint on the non-symmetric operator
        "SolverError DIVERGED_INDEFINITE_MAT": 5,  # cg on the indefinite operator
        "SolverError DIVERGED_INDEFINITE_PC": 4,  # cg or minres with ilu or gamg, indefinite
        "SolverError DIVERGED_DTOL": 6,  # richardson, indefinite (5) and non-symmetric (1)
        "SolverError DIVERGED_NANORINF": 2,  # richardson with sor or gamg, indefinite
    }
    assert tally("unrolled") == {
        SOLVES: 5,
        "InputError INVALID_INPUT": 128,  # 124 unsupported pairs, 4 null spaces
        "StructureError STRUCTURE": 2,
        "SolverError DIVERGED_INDEFINITE_MAT": 2,
        "SolverError DIVERGED_DTOL": 3,
    }


# -- the references and the operators ----------------------------------------------------------


@pytest.mark.parametrize("operator", OPERATOR_NAMES)
def test_reference_is_the_derivative(operator):
    """The dense ∂L/∂θ formula agrees with central differences of ``gᵀ x(θ)`` (A⁺ too)."""
    op = OPERATORS[operator]
    rng = np.random.default_rng(3)
    b, g = rng.standard_normal(n), rng.standard_normal(n)
    if op.singular:
        b -= b.mean()
    theta = op.thetas[0]
    _, _, dtheta = reference(op, theta, b, g)
    h = 1e-6
    fd = [
        (g @ reference(op, theta + h * e, b, g)[0] - g @ reference(op, theta - h * e, b, g)[0])
        / (2 * h)
        for e in np.eye(P)
    ]
    np.testing.assert_allclose(fd, dtheta, rtol=1e-6)


def test_operators_have_the_structure_they_are_named_for():
    """SPD, indefinite (6 negative eigenvalues, |λ| ≥ 0.15), non-symmetric, singular (rank n−1)."""
    symmetric = {name: op.parametric.is_symmetric for name, op in OPERATORS.items()}
    assert symmetric == {"spd": True, "indefinite": True, "nonsymmetric": False, "singular": True}
    for theta in OPERATORS["spd"].thetas:
        assert np.linalg.eigvalsh(OPERATORS["spd"].matrix(theta).toarray()).min() > 0.3
    for theta in OPERATORS["indefinite"].thetas:
        eig = np.linalg.eigvalsh(OPERATORS["indefinite"].matrix(theta).toarray())
        assert (eig < 0).sum() == 6 and np.abs(eig).min() > 0.15
    for theta in OPERATORS["singular"].thetas:
        A = OPERATORS["singular"].matrix(theta)
        assert np.abs(A @ np.ones(n)).max() < 1e-12
        assert np.linalg.matrix_rank(A.toarray()) == n - 1
    for theta in OPERATORS["nonsymmetric"].thetas:
        A = OPERATORS["nonsymmetric"].matrix(theta)
        assert abs(A - A.T).max() > 0.5


# -- outside the grid ----------------------------------------------------------------------------


@pytest.mark.parametrize(("pc", "outcome"), [("ilu", "DIVERGED_PCSETUP_FAILED"), ("icc", SOLVES)])
def test_zero_pivot(pc, outcome):
    """A zero diagonal: ILU(0) fails its set-up (a `SolverError`), PETSc's ICC shifts and solves."""
    swap = sp.csr_matrix([[0.0, 1.0], [1.0, 0.0]])
    A = sp.csr_matrix(
        sp.kron(sp.identity(n // 2), swap) + 0.1 * sp.diags([np.ones(n - 2)] * 2, [2, -2])
    )
    b = np.random.default_rng(0).standard_normal(n)
    options = {"ksp_type": "gmres", "pc_type": pc}
    with pp.KSPSolver(options, prefix=f"grid_zero_pivot_{pc}_", max_it=MAX_IT, rtol=RTOL) as s:
        if outcome == SOLVES:
            sol = pp.solve(A, torch.from_numpy(b), s, return_solution=True)
            x = sol.value.numpy()
            assert sol.converged
            assert relative_error(x, spla.spsolve(A.tocsc(), b)) < 1e-8
        else:
            with pytest.raises(SolverError) as info:
                pp.solve(A, torch.from_numpy(b), s)
            assert info.value.reason == outcome


def test_each_call_reports_its_own_samples():
    """An implicit call of 3 samples and an unrolled call of 2 on one solver: each result
    holds its own call's records, 3 and 2."""
    A = OPERATORS["spd"].matrix(OPERATORS["spd"].thetas[0])
    b = torch.from_numpy(np.random.default_rng(0).standard_normal((3, n)))
    options = {"ksp_type": "cg", "pc_type": "jacobi"}
    with pp.KSPSolver(options, prefix="grid_stale_", max_it=MAX_IT, rtol=RTOL) as solver:
        implicit = pp.solve(A, b, solver, return_solution=True)
        unrolled = pp.solve(A, b[:2], solver, mode="unrolled", return_solution=True)
    assert len(implicit.info) == 3 and implicit.converged
    if len(unrolled.info) != 2:
        raise RecordError(f"an unrolled call of 2 reported {unrolled.info}")
