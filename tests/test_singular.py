"""Singular and indefinite systems never pass: an iterate is judged by its true residual.

Elasticity without a Dirichlet condition has the rigid-body modes as kernel.  Without
a declared null space, CG + GAMG reported ``CONVERGED_RTOL`` after one iteration
with |u| ≈ 1e14 and a true residual 50 times ‖b‖, and the capped solve's
``DIVERGED_INDEFINITE_MAT`` was accepted by the late-breakdown rescue (its backward
error is tiny *because* ‖x‖ exploded).  Each such solve must raise
`SingularOperatorError`, which says to declare ``nullspace=``; with the modes
declared, the solve returns the minimum-norm least-squares solution.

Curl-curl on Nédélec elements (ε = 0) has every gradient in its kernel.  CG fails on
it as ``DIVERGED_DTOL`` with an iterate that is a null vector only to 1e-7..1e-5 (the
kernel part grew, but not to rounding level): not provably singular, but it looks so,
and the error says how to declare the null space (the discrete gradient).  An
indefinite operator (Helmholtz) fails too, and its error does not say so.
"""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import skfem
import torch
from _curl_curl import curl_curl, interior, triangles
from _vector import body_load, elasticity
from skfem import BilinearForm
from skfem.helpers import dot, grad

import prdp_petsc as pp
from prdp_petsc.core import safeguards
from prdp_petsc.core.safeguards import Residual, judge
from prdp_petsc.errors import SingularOperatorError, SolverError


@pytest.fixture(scope="module")
def free_body():
    """2D elasticity with no Dirichlet condition (E = 1), its load and its modes."""
    basis, A = elasticity(n=4)
    M = A.matrix(np.ones(A.n_params))
    return basis, A, M, body_load(basis)


# (options, max_it, rtol): the paths by which a singular solve used to come back
SINGULAR_CASES = {
    "cg/gamg converged": ({"ksp_type": "cg", "pc_type": "gamg"}, 1000, 1e-8),
    "cg/gamg capped, indefinite": ({"ksp_type": "cg", "pc_type": "gamg"}, 20, 0.0),
    "gmres/gamg capped": ({"ksp_type": "gmres", "pc_type": "gamg"}, 20, 0.0),
    "minres/jacobi step length": ({"ksp_type": "minres", "pc_type": "jacobi"}, 2000, 1e-8),
    "bcgs/jacobi dtol": ({"ksp_type": "bcgs", "pc_type": "jacobi"}, 2000, 1e-8),
}


@pytest.mark.parametrize("case", SINGULAR_CASES)
def test_singular_operator_without_nullspace_raises(free_body, case):
    _, _, M, b = free_body
    options, max_it, rtol = SINGULAR_CASES[case]
    with pp.KSPSolver(options, max_it=max_it, rtol=rtol) as solver:
        solver.set_operator(M)
        with pytest.raises(SingularOperatorError, match="nullspace=") as info:
            solver.solve(b)
    assert isinstance(info.value, SolverError) and info.value.reason == "SINGULAR"
    assert "np." not in str(info.value)


def test_singular_error_reaches_the_torch_bridge(free_body):
    _, A, _, b = free_body
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "gamg"}, max_it=200, rtol=1e-8) as solver:
        with pytest.raises(SingularOperatorError):
            pp.solve(A, torch.from_numpy(b), solver, theta=theta)


@pytest.mark.parametrize("options", [{"ksp_type": "cg", "pc_type": "gamg"}, {"ksp_type": "cg"}])
def test_declared_rigid_body_modes_give_the_least_squares_solution(free_body, options):
    """With the modes as null space the solve returns A⁺b (b itself is not balanced)."""
    basis, _, M, b = free_body
    modes = pp.rigid_body_modes(basis)
    with pp.KSPSolver(
        options,
        max_it=2000,
        rtol=1e-12,
        structure=pp.Structure(nullspace=modes, near_nullspace=modes, block_size=2),
    ) as solver:
        solver.set_operator(M)
        sol = solver.solve(b)
        assert sol.converged
    x = sol.value
    expected = np.linalg.pinv(M.toarray()) @ b
    assert np.linalg.norm(x - expected) <= 1e-8 * np.linalg.norm(expected)


def test_a_partial_null_space_is_named(free_body):
    """Translations declared, the rotation forgotten: still singular, and said so."""
    basis, _, M, b = free_body
    translations = pp.rigid_body_modes(basis)[:2]
    options = {"ksp_type": "gmres", "pc_type": "gamg"}
    with pp.KSPSolver(
        options, max_it=1000, rtol=1e-8, structure=pp.Structure(nullspace=translations)
    ) as solver:
        solver.set_operator(M)
        with pytest.raises(SingularOperatorError, match="does not cover"):
            solver.solve(b)


def test_clamped_body_solves(free_body):
    """The same operator with one face clamped: no error, the direct solution."""
    basis, A, _, b = free_body
    bc = pp.Dirichlet(A, basis.get_dofs(lambda x: np.isclose(x[0], 0.0)).all())
    M = bc.A_II.matrix(np.ones(A.n_params))
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "gamg"}, max_it=500, rtol=1e-10) as s:
        s.set_operator(M)
        x = s.solve(b[bc.interior]).value
    expected = spla.spsolve(M.tocsc(), b[bc.interior])
    assert np.linalg.norm(x - expected) <= 1e-8 * np.linalg.norm(expected)


@pytest.fixture(scope="module", params=["tri", "tet"])
def curl_curl_system(request):
    """Curl-curl, ε = 0, u × n = 0, on triangles or tetrahedra, with an incompatible load."""
    if request.param == "tri":
        _, A, b, _ = triangles(4)
    else:
        basis, A, b = curl_curl(skfem.MeshTet().refined(2), skfem.ElementTetN0)
        A, b, _ = interior(basis, A, b)
    return A, b


# the paths by which CG on curl-curl fails (DIVERGED_DTOL), with a tolerance and capped
CURL_CURL_CASES = {
    "cg/icc": ({"ksp_type": "cg", "pc_type": "icc"}, 2000, 1e-8),
    "cg/gamg": ({"ksp_type": "cg", "pc_type": "gamg"}, 2000, 1e-8),
    "cg/jacobi": ({"ksp_type": "cg", "pc_type": "jacobi"}, 2000, 1e-8),
    "cg/icc capped": ({"ksp_type": "cg", "pc_type": "icc"}, 60, 0.0),
    "cg/gamg capped": ({"ksp_type": "cg", "pc_type": "gamg"}, 60, 0.0),
}


@pytest.mark.parametrize("case", CURL_CURL_CASES)
def test_a_failure_on_curl_curl_names_the_null_space(curl_curl_system, case):
    A, b = curl_curl_system
    options, max_it, rtol = CURL_CURL_CASES[case]
    with pp.KSPSolver(options, max_it=max_it, rtol=rtol) as solver:
        solver.set_operator(A)
        with pytest.raises(SolverError) as info:
            solver.solve(b)
    message = str(info.value)
    assert "Structure(nullspace=...)" in message and "discrete_gradient(basis, dofs)" in message
    if not isinstance(info.value, SingularOperatorError):  # PETSc's reason stands
        assert info.value.reason == "DIVERGED_DTOL"
        assert "if the operator is singular" in message


@pytest.mark.parametrize("k2", [50.0, 200.0])
@pytest.mark.parametrize("pc", ["icc", "gamg", "jacobi", "none"])
def test_an_indefinite_failure_claims_no_singularity(k2, pc):
    """Helmholtz ``−Δu − k² u`` (indefinite, not singular): CG fails
    (DIVERGED_INDEFINITE_MAT/PC), and the error says nothing of a null space."""
    basis = skfem.Basis(skfem.MeshTri().refined(5), skfem.ElementTriP1())

    @BilinearForm
    def helmholtz(u, v, w):
        return dot(grad(u), grad(v)) - k2 * u * v

    kept = basis.complement_dofs(basis.get_dofs())
    H = helmholtz.assemble(basis).tocsr()[kept][:, kept]
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": pc}, max_it=2000, rtol=1e-8) as solver:
        solver.set_operator(H)
        with pytest.raises(SolverError) as info:
            solver.solve(np.ones(H.shape[0]))
    assert info.value.reason.startswith("DIVERGED_INDEFINITE")
    assert not isinstance(info.value, SingularOperatorError)
    assert "nullspace" not in str(info.value) and "singular" not in str(info.value)


def test_what_is_checked_when(monkeypatch):
    """A converged solve computes its true residual (one MatMult per right-hand side); a
    capped solve of a well-posed system does not (two vector norms decide)."""
    from _core import fd_poisson

    calls = []
    original = safeguards.true_residual
    monkeypatch.setattr(
        safeguards, "true_residual", lambda *a, **k: calls.append(1) or original(*a, **k)
    )
    M = fd_poisson(8)
    b = np.random.default_rng(0).standard_normal((3, M.shape[0]))
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=5) as capped:
        capped.set_operator(M)
        capped.solve(b)
    assert calls == []
    with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=500, rtol=1e-10) as s:
        s.set_operator(M)
        s.solve(b)
    assert len(calls) == 3


def _residual(relative, null_ratio):
    """A `Residual` with ‖b‖ = 1, ‖A‖‖x‖ = 1e6 and the given ratios."""
    return Residual(relative, 1.0, null_ratio * 1e6, 1e6, 1.0)


@pytest.mark.parametrize(
    ("relative", "null_ratio", "outcome", "verdict"),
    [
        (1e-12, 1e-15, "converged", None),  # high contrast, converged: fine
        (52.0, 2.5e-16, "converged", "singular"),  # GAMG on the free body
        (0.96, 4e-11, "converged", "singular"),  # MINRES at the least-squares floor
        (3.0, 1e-3, "converged", "not solved"),  # worse than x = 0, not a null vector
        (0.5, 1e-3, "converged", None),
        (0.3, 5e-8, "stopped", "not solved"),  # MINRES's step length, no residual tested
        (1e-9, 1e-3, "stopped", None),
        (40.0, 1.3e-16, "capped", "singular"),  # capped GMRES + GAMG on the free body
        (87.0, 6e-4, "capped", None),  # capped CG may leave a large residual
        (0.96, 4e-11, "capped", None),
        (2e4, 3.6e-6, "failed", None),  # CG + Jacobi diverging: PETSc's DTOL stands
        (2.6e4, 1.6e-12, "failed", "singular"),
        (113.0, 5.7e-9, "failed", None),  # GAMG breaking down on SIMP contrast 1e-9: no kernel
    ],
)
def test_judge(relative, null_ratio, outcome, verdict):
    assert judge(_residual(relative, null_ratio), outcome) == verdict


def test_a_stop_is_held_to_its_tolerance():
    """A stop that tested no residual must meet √rtol: MINRES on a singular Stokes
    system stopped (step length) at the least-squares floor, 9 % of ‖b‖."""
    stop = _residual(0.09, 1e-3)
    assert judge(stop, "stopped") is None
    assert judge(stop, "stopped", rtol=1e-10) == "not solved"
    assert judge(_residual(1e-6, 1e-3), "stopped", rtol=1e-10) is None


def test_judge_refuses_a_stop_at_zero():
    """MINRES + GAMG on the free body stopped (step length) at x = 0."""
    assert judge(Residual(1.0, 1.0, 0.0, 0.0, 1.0), "stopped") == "not solved"
    assert judge(Residual(1.0, 1.0, 0.0, 0.0, 1.0), "converged") is None  # atol met at x = 0
