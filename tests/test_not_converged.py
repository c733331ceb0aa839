"""A solve with a tolerance that ends without meeting it is never silent.

GMRES + GAMG on a convection-dominated convection–diffusion operator (Galerkin, no
stabilisation) stagnates: after 300 iterations the true residual is larger than ‖b‖.
With ``rtol > 0`` that solve warns (`NotConvergedWarning`), naming its true residual
``‖b − A x‖/‖b‖`` and what to do, or raises with ``not_converged="raise"``; in fixed
mode (``rtol = atol = 0``, exactly K iterations, how PRDP trains) the same capped
solve is the normal outcome and says nothing.
"""

import re
import warnings

import numpy as np
import pytest
import skfem
import torch
from _curl_curl import triangles
from skfem import BilinearForm

import prdp_petsc as pp
from prdp_petsc.errors import InputError, NotConvergedWarning, SolverError

GMRES_GAMG = {"ksp_type": "gmres", "pc_type": "gamg"}
FIGURE = re.compile(r"true residual ‖b − A x‖/‖b‖ = (\S+)\.")


@pytest.fixture(scope="module")
def stall():
    """Convection–diffusion ``−0.01 Δu + (1, 0.5)·∇u`` on P1, u = 0 on the boundary."""
    basis = skfem.Basis(skfem.MeshTri().refined(4), skfem.ElementTriP1())

    @BilinearForm
    def form(u, v, w):
        diffusion = u.grad[0] * v.grad[0] + u.grad[1] * v.grad[1]
        return 1e-2 * diffusion + (u.grad[0] + 0.5 * u.grad[1]) * v

    kept = basis.complement_dofs(basis.get_dofs())
    A = form.assemble(basis).tocsr()[kept][:, kept].tocsr()
    return A, np.ones(A.shape[0])


def relative_residual(A, b, x) -> float:
    return float(np.linalg.norm(b - A @ x) / np.linalg.norm(b))


def test_a_stalled_tolerance_solve_warns_with_its_true_residual(stall):
    A, b = stall
    with pp.KSPSolver(GMRES_GAMG, max_it=300, rtol=1e-8) as solver:
        solver.set_operator(A)
        with pytest.warns(NotConvergedWarning) as record:
            sol = solver.solve(b)
        assert sol.reason == "DIVERGED_MAX_IT" and not sol.converged
    x = sol.value
    assert len(record) == 1
    message = str(record[0].message)
    assert "forward solve (gmres/gamg) did not converge" in message
    assert "after 300 iterations with rtol=1e-08, atol=0" in message
    assert "Raise max_it, loosen rtol, or choose another KSP/PC" in message
    assert "nullspace" not in message  # the operator is not singular: no such hint
    figure = float(FIGURE.search(message).group(1))
    true = relative_residual(A, b, x)
    assert true > 1  # the stall: worse than x = 0
    assert figure == pytest.approx(true, rel=5e-3)  # printed to 3 digits
    assert record[0].filename == __file__  # the caller's line


def test_a_scaled_right_hand_side_warns_alike(stall):
    """Entries below 2⁻¹⁰⁰ are scaled by a power of two before the solve: the same
    iterates, the same warning and figure."""
    A, b = stall
    with pp.KSPSolver(GMRES_GAMG, max_it=300, rtol=1e-8) as solver:
        solver.set_operator(A)
        with pytest.warns(NotConvergedWarning) as record:
            x = solver.solve(1e-40 * b).value
    figure = float(FIGURE.search(str(record[0].message)).group(1))
    assert figure == pytest.approx(relative_residual(A, 1e-40 * b, x), rel=5e-3)


def test_raise_mode(stall):
    A, b = stall
    with pp.KSPSolver(GMRES_GAMG, max_it=300, rtol=1e-8, not_converged="raise") as solver:
        solver.set_operator(A)
        with warnings.catch_warnings():
            warnings.simplefilter("error", NotConvergedWarning)
            with pytest.raises(SolverError, match="did not converge") as info:
                solver.solve(b)
    assert info.value.reason == "DIVERGED_MAX_IT"
    assert float(FIGURE.search(str(info.value)).group(1)) > 1


def test_fixed_mode_hitting_the_cap_says_nothing(stall):
    """rtol = atol = 0: exactly K iterations, the training outcome; also "ignore"."""
    A, b = stall
    with warnings.catch_warnings():
        warnings.simplefilter("error", NotConvergedWarning)
        for settings in ({}, {"rtol": 1e-8, "not_converged": "ignore"}):
            with pp.KSPSolver(GMRES_GAMG, max_it=300, **settings) as solver:
                solver.set_operator(A)
                assert solver.solve(b).reason == "DIVERGED_MAX_IT"


def test_a_converged_solve_says_nothing(stall):
    A, b = stall
    with warnings.catch_warnings():
        warnings.simplefilter("error", NotConvergedWarning)
        with pp.KSPSolver({"ksp_type": "gmres", "pc_type": "jacobi"}, max_it=500, rtol=1e-8) as s:
            s.set_operator(A)
            assert s.solve(b).converged


def test_one_warning_per_call_naming_the_worst_row(stall):
    A, b = stall
    batch = np.stack([b, np.arange(len(b)) % 3 - 1.0, 2 * b])
    with pp.KSPSolver(GMRES_GAMG, max_it=100, rtol=1e-8) as solver:
        solver.set_operator(A)
        with pytest.warns(NotConvergedWarning) as record:
            x = solver.solve(batch).value
    assert len(record) == 1
    worst = max(relative_residual(A, row, xi) for row, xi in zip(batch, x, strict=True))
    message = str(record[0].message)
    assert "the worst of 3 of 3" in message
    assert float(FIGURE.search(message).group(1)) == pytest.approx(worst, rel=5e-3)


def test_the_bridge_and_the_adjoint_warn_at_the_callers_line(stall):
    """Through `prdp_petsc.solve` (torch autograd in between), forward and adjoint."""
    A, b = stall
    rhs = torch.from_numpy(b).requires_grad_(True)
    with pp.KSPSolver(GMRES_GAMG, max_it=100, rtol=1e-8) as solver:
        with pytest.warns(NotConvergedWarning) as forward:
            x = pp.solve(A, rhs, solver)
        assert forward[0].filename == __file__
        with pytest.warns(NotConvergedWarning, match="adjoint solve") as adjoint:
            x.sum().backward()
    assert "AdjointSettings(max_it=...)" in str(adjoint[0].message)
    assert "‖g − Aᵀλ‖/‖g‖" in str(adjoint[0].message)


def test_a_singular_looking_iterate_gets_the_null_space_hint():
    """GMRES + GAMG on curl-curl (ε = 0, u × n = 0) runs to the cap along the kernel:
    the warning says how to declare it."""
    _, A, b, _ = triangles(4)
    with pp.KSPSolver(GMRES_GAMG, max_it=100, rtol=1e-8) as solver:
        solver.set_operator(A)
        with pytest.warns(NotConvergedWarning, match=r"Structure\(nullspace=") as record:
            solver.solve(b)
    assert "discrete_gradient(basis, dofs)" in str(record[0].message)


def test_the_setting_is_validated_and_copied():
    with pytest.raises(InputError, match="not_converged must be one of"):
        pp.KSPSolver(max_it=5, rtol=1e-8, not_converged="loud")
    with pp.KSPSolver(max_it=5, rtol=1e-8, not_converged="raise") as solver:
        with solver.clone(max_it=10) as copy:
            assert copy.not_converged == "raise"
            assert copy.describe()["not_converged"] == "raise"
        with solver.clone(not_converged="ignore") as copy:
            assert copy.not_converged == "ignore"
