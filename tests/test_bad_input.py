"""Every bad input is refused with a clear error before PETSc sees it.

"Before PETSc" is checked on a fresh solver: after the error it has still created
no KSP (``solver.ksp`` raises) and counted no solve.  Real divergence, by contrast,
happens inside PETSc and must come back as `SolverError` naming PETSc's reason.
"""

import math
import re

import numpy as np
import pytest
import torch
from _core import fd_poisson, interior_operator, randn, random_theta, unit_square

import prdp_petsc as pp
from prdp_petsc.core.results import SolverStats
from prdp_petsc.fem.fd import laplacian


@pytest.fixture(scope="module")
def problem():
    D = interior_operator(unit_square(2))
    return D, D.A_II, random_theta(D.A_II.n_params)


def fresh_solver(**kw):
    return pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=kw.pop("max_it", 5), **kw)


def assert_untouched(solver):
    """No operator reached PETSc and nothing was solved."""
    with pytest.raises(RuntimeError, match="no operator"):
        solver.mat  # noqa: B018
    assert solver.stats == SolverStats()


def poisoned(t: torch.Tensor, value: float) -> torch.Tensor:
    t = t.clone()
    t.view(-1)[0] = value
    return t


# -- right-hand side, parameters, boundary values -------------------------------------------


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nonfinite_b(problem, value):
    _, A, theta = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="b contains NaN or Inf"):
        pp.solve(A, poisoned(randn(A.shape[0]), value), solver, theta=theta)
    assert_untouched(solver)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_nonfinite_theta(problem, value):
    _, A, theta = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="theta contains NaN or Inf"):
        pp.solve(A, randn(A.shape[0]), solver, theta=poisoned(theta, value))
    assert_untouched(solver)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_nonfinite_boundary_values(problem, value):
    D, _, theta = problem
    solver = fresh_solver()
    g = poisoned(randn(len(D.boundary)), value)
    with pytest.raises(ValueError, match="g contains NaN or Inf"):
        D.solve(randn(D.n), g, solver, theta=theta)
    assert_untouched(solver)


@pytest.mark.parametrize("value", [0.0, -1.0])
def test_nonpositive_diffusion_coefficient(problem, value):
    _, A, theta = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="diffusion coefficient and must be > 0"):
        pp.solve(A, randn(A.shape[0]), solver, theta=poisoned(theta, value))
    assert_untouched(solver)


@pytest.mark.parametrize(
    ("shape", "what"),
    [((7,), "b"), ((2, 3, 9), "b"), ((9, 2), "b")],
)
def test_wrong_shape_b(problem, shape, what):
    _, A, theta = problem
    assert A.shape[0] == 9
    solver = fresh_solver()
    with pytest.raises(ValueError, match=rf"{what} must have shape \(9,\) or \(batch, 9\)"):
        pp.solve(A, torch.ones(shape, dtype=torch.float64), solver, theta=theta)
    assert_untouched(solver)


def test_wrong_shape_theta_and_g(problem):
    D, A, theta = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="theta must have shape"):
        pp.solve(A, randn(9), solver, theta=theta[:-1])
    with pytest.raises(ValueError, match="theta must have shape"):
        pp.solve(A, randn(9), solver, theta=theta[None, :])
    with pytest.raises(ValueError, match="g must have shape"):
        D.solve(randn(D.n), randn(len(D.boundary) + 1), solver, theta=theta)
    with pytest.raises(ValueError, match="f must have shape"):
        D.solve(randn(D.n - 1), randn(len(D.boundary)), solver, theta=theta)
    assert_untouched(solver)


@pytest.mark.parametrize("name", ["b", "theta", "g", "f"])
def test_float32_is_a_type_error(problem, name):
    D, A, theta = problem
    args = {"b": randn(9), "theta": theta, "g": randn(len(D.boundary)), "f": randn(D.n)}
    args[name] = args[name].float()
    solver = fresh_solver()
    with pytest.raises(TypeError, match=rf"{name} must be float64"):
        if name in ("b", "theta"):
            pp.solve(A, args["b"], solver, theta=args["theta"])
        else:
            D.solve(args["f"], args["g"], solver, theta=args["theta"])
    assert_untouched(solver)


def test_numpy_b_is_a_type_error(problem):
    _, A, theta = problem
    with pytest.raises(TypeError, match="b must be a torch.Tensor"):
        pp.solve(A, np.ones(9), fresh_solver(), theta=theta)


# -- operator and theta pairing -------------------------------------------------------------


def test_parametric_matrix_without_theta(problem):
    _, A, _ = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="pass its parameters as theta="):
        pp.solve(A, randn(9), solver)
    assert_untouched(solver)


def test_theta_with_a_scipy_matrix(problem):
    _, _, theta = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="only meaningful for a ParametricMatrix"):
        pp.solve(fd_poisson(3), randn(9), solver, theta=theta)
    assert_untouched(solver)


def test_bad_operators():
    solver = fresh_solver()
    with pytest.raises(TypeError, match="scipy sparse matrix"):
        pp.solve(np.eye(9), randn(9), solver)
    M = fd_poisson(3)
    M.data[0] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        pp.solve(M, randn(9), solver)
    with pytest.raises(ValueError, match="square"):
        solver.set_operator(fd_poisson(3)[:, :8])
    assert_untouched(solver)


def test_mode_and_solver_type(problem):
    _, A, theta = problem
    solver = fresh_solver()
    with pytest.raises(ValueError, match="mode must be 'implicit' or 'unrolled'"):
        pp.solve(A, randn(9), solver, theta=theta, mode="adjoint")
    with pytest.raises(TypeError, match="solver must be a KSPSolver"):
        pp.solve(A, randn(9), "cg", theta=theta)
    assert_untouched(solver)


# -- solver settings ------------------------------------------------------------------------


@pytest.mark.parametrize("max_it", [0, -3, 2.5, "10", True, None])
def test_bad_max_it(max_it):
    with pytest.raises(ValueError, match="max_it must be an integer >= 1"):
        pp.KSPSolver(max_it=max_it)
    solver = fresh_solver()
    with pytest.raises(ValueError, match="max_it must be an integer >= 1"):
        solver.max_it = max_it
    assert solver.max_it == 5


@pytest.mark.parametrize("max_it", [0, -1, 1.5])
def test_bad_adjoint_max_it(max_it):
    with pytest.raises(ValueError, match="adjoint max_it"):
        pp.KSPSolver(max_it=5, adjoint=pp.AdjointSettings(max_it=max_it))
    with pytest.raises(ValueError, match="adjoint max_it"):
        fresh_solver().adjoint_max_it = max_it


@pytest.mark.parametrize(
    "kw", [{"rtol": -1e-6}, {"atol": -1.0}, {"rtol": math.nan}, {"atol": math.inf}]
)
def test_bad_tolerances(kw):
    with pytest.raises(ValueError, match=f"{next(iter(kw))} must be finite and >= 0"):
        pp.KSPSolver(max_it=5, **kw)
    solver = fresh_solver()
    with pytest.raises(ValueError, match="must be finite and >= 0"):
        ((name, value),) = kw.items()
        setattr(solver, name, value)
    with pytest.raises(ValueError, match="adjoint"):
        pp.KSPSolver(max_it=5, adjoint=pp.AdjointSettings(**kw))


def test_bad_option_strings():
    with pytest.raises(ValueError, match="expected '-name'"):
        pp.KSPSolver("ksp_type cg", max_it=5)
    with pytest.raises(TypeError, match="options must be a dict"):
        pp.KSPSolver(["-ksp_type", "cg"], max_it=5)


def test_unrolled_with_unsupported_ksp(problem):
    _, A, theta = problem
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "jacobi"}, max_it=5)
    with pytest.raises(ValueError, match="use mode='implicit'"):
        pp.solve(A, randn(9), solver, theta=theta, mode="unrolled")
    assert solver.stats.forward_solves == 0


def test_dirichlet_indices_out_of_range(problem):
    D, _, _ = problem
    with pytest.raises(ValueError, match="boundary indices"):
        pp.Dirichlet(fd_poisson(3), [0, 9])


# -- real divergence inside PETSc ------------------------------------------------------------


def test_richardson_divergence_is_a_solver_error():
    """Damped Jacobi with scale 3 on an SPD matrix diverges: DIVERGED_DTOL, named."""
    solver = pp.KSPSolver(
        {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 3.0}, max_it=200
    )
    with pytest.raises(pp.SolverError, match="DIVERGED_DTOL") as err:
        pp.solve(fd_poisson(8), randn(64, seed=1), solver)
    assert err.value.reason == "DIVERGED_DTOL"
    iterations = int(re.search(r"after (\d+) iterations", str(err.value))[1])
    assert 0 < iterations < 200  # named in the message


def test_hitting_the_cap_is_not_an_error():
    solver = pp.KSPSolver(
        {"ksp_type": "richardson", "pc_type": "jacobi", "ksp_richardson_scale": 3.0}, max_it=3
    )
    # diverging, but capped first
    sol = pp.solve(fd_poisson(8), randn(64, seed=1), solver, return_solution=True)
    assert sol.reason == "DIVERGED_MAX_IT" and torch.isfinite(sol.value).all()


def test_indefinite_preconditioner_is_a_solver_error():
    """CG with a preconditioner of mixed sign (Jacobi on an indefinite diagonal)."""
    import scipy.sparse as sp

    M = fd_poisson(6).tolil()
    M[0, 0] = -M[0, 0]
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=100, rtol=1e-10)
    with pytest.raises(pp.SolverError) as err:
        pp.solve(sp.csr_matrix(M), randn(36, seed=2), solver)
    assert err.value.reason.startswith("DIVERGED_INDEFINITE")


def test_adjoint_pc_without_transpose_is_a_solver_error():
    """SOR has no transpose in PETSc for a non-symmetric A: the adjoint fails with a hint."""
    import scipy.sparse as sp

    skew = sp.diags([np.full(8, 0.5), np.full(8, -0.5)], [1, -1])
    nonsym = (fd_poisson(3) + skew).tocsr()
    solver = pp.KSPSolver({"ksp_type": "gmres", "pc_type": "sor"}, max_it=5)
    b = randn(9, seed=3, requires_grad=True)
    x = pp.solve(nonsym, b, solver)
    with pytest.raises(pp.SolverError, match="(?i)choose another adjoint pc_type") as err:
        x.sum().backward()
    assert err.value.reason in ("NO_TRANSPOSE", "PETSC_ERROR")
    ok = pp.KSPSolver(
        {"ksp_type": "gmres", "pc_type": "sor"},
        max_it=5,
        adjoint=pp.AdjointSettings(options={"pc_type": "jacobi"}),
    )
    pp.solve(nonsym, b, ok).sum().backward()
    assert torch.isfinite(b.grad).all() and ok.stats.adjoint_solves == 1


def test_tolerances_in_adjoint_options_are_refused():
    with pytest.raises(ValueError, match="AdjointSettings"):
        pp.KSPSolver(max_it=5, adjoint=pp.AdjointSettings(options="-ksp_max_it 3"))


def test_unrolled_mode_refuses_a_null_space():
    solver = pp.KSPSolver(
        {"ksp_type": "cg"}, max_it=3, structure=pp.Structure(nullspace="constant")
    )
    with pytest.raises(ValueError, match="null space"):
        pp.solve(fd_poisson(3), randn(9, seed=1), solver, mode="unrolled")


# -- torch.func and the numbers in messages ------------------------------------------------------
@pytest.mark.parametrize("transform", ["vmap", "grad", "jacrev", "vmap_b"])
def test_torch_func_transforms_are_refused_by_name(problem, transform):
    """torch.func passes tensors without storage, which no PETSc solve can read: an
    `InputError` that points to the batch of operators, θ of shape (B, p)."""
    _, A, theta = problem
    b = torch.ones(A.shape[0], dtype=torch.float64)
    solver = fresh_solver(max_it=20)

    def loss(t):
        return pp.solve(A, b, solver, theta=t).sum()

    run = {
        "vmap": lambda: torch.func.vmap(loss)(theta.expand(3, -1).clone()),
        "grad": lambda: torch.func.grad(loss)(theta),
        "jacrev": lambda: torch.func.jacrev(lambda t: pp.solve(A, b, solver, theta=t))(theta),
        "vmap_b": lambda: torch.func.vmap(lambda v: pp.solve(A, v, solver, theta=theta))(
            b.expand(3, -1).clone()
        ),
    }[transform]
    with pytest.raises(pp.InputError, match=r"theta of shape \(B, p\)") as info:
        run()
    assert "torch.autograd" in str(info.value)
    assert_untouched(solver)


def test_messages_print_plain_numbers():
    """scikit-fem counts dofs in int32: a shape built from them printed
    ``(np.int32(81), np.int32(81))``."""
    import scipy.sparse as sp

    A = pp.diffusion_operator(unit_square(2))
    assert all(type(s) is int for s in A.shape)
    with pytest.raises(pp.InputError) as info:
        A + sp.identity(3)
    assert "np." not in str(info.value) and "(25, 25)" in str(info.value)


@pytest.mark.parametrize(
    "bad",
    [
        lambda: pp.KSPSolver(max_it=np.int32(0)),
        lambda: pp.KSPSolver(max_it=5, rtol=np.float64(-1.0)),
        lambda: pp.KSPSolver(max_it=5, structure=pp.Structure(block_size=np.int64(0))),
        lambda: pp.KSPSolver(max_it=5, pc_lag=np.int64(0)),
        lambda: laplacian((np.int32(0), 4)),
    ],
)
def test_validation_messages_print_numpy_values_as_numbers(bad):
    with pytest.raises(pp.InputError) as info:
        bad()
    assert "np." not in str(info.value), str(info.value)
