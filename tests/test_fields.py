"""Saddle points: fields declared once, for PCFIELDSPLIT in the forward and adjoint solves.

Taylor–Hood Stokes with a Schur-complement fieldsplit declared through
``KSPSolver(fields={"u": ..., "p": ...})``: the split solvers read
``fieldsplit_u_*``/``fieldsplit_p_*``, a PC shared by both solves gets the fields once
(PETSc would add them twice, and then crash), an adjoint PC of its own gets its
own, new values and new Mats keep them, and gradients agree with finite
differences of a dense solve.  Misspelt split options are named, also when the
solve fails because of them.
"""

import warnings

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import skfem
import torch
from _vector import SCHUR, stokes, taylor_hood

import prdp_petsc as pp
from prdp_petsc.errors import InputError, SolverError, UnusedOptionWarning

CONVERGED = {"max_it": 500, "rtol": 1e-12}


@pytest.fixture(scope="module")
def problem():
    return stokes(n=4)


def _splits(ksp) -> list[str]:
    return [sub.getOptionsPrefix() for sub in ksp.getPC().getFieldSplitSubKSP()]


def _loss(bc, solver, theta, g):
    """L = Σ w ⊙ x over the whole state, a fixed weight w; and the solve's result."""
    f = torch.zeros(bc.n, dtype=torch.float64)
    sol = bc.solve(f, g, solver, theta=theta, return_solution=True)
    w = torch.from_numpy(np.random.default_rng(5).standard_normal(bc.n))
    return (w * sol.value).sum(), sol


def _dense_loss(A, bc, theta: np.ndarray, g: np.ndarray) -> float:
    """The same loss from a direct solve of the eliminated system."""
    full = A.matrix(theta).tocsr()
    interior = spla.spsolve(
        full[bc.interior][:, bc.interior].tocsc(),
        -full[bc.interior][:, bc.boundary] @ g,
    )
    x = np.zeros(bc.n)
    x[bc.interior], x[bc.boundary] = interior, g
    return float(np.random.default_rng(5).standard_normal(bc.n) @ x)


@pytest.mark.parametrize("adjoint", ["shared", "own"])
def test_schur_fieldsplit_solves_stokes_and_its_gradient(problem, adjoint):
    basis, A, bc, fields, g_np = problem
    settings = None
    if adjoint == "own":  # a PC of its own: it needs the fields as well
        settings = pp.AdjointSettings(options={"pc_type": "fieldsplit", "ksp_type": "gmres"})
    theta = torch.from_numpy(1.0 + np.random.default_rng(1).random(A.n_params))
    theta.requires_grad_(True)
    g = torch.from_numpy(g_np).requires_grad_(True)
    with pp.KSPSolver(
        SCHUR, structure=pp.Structure(fields=fields), adjoint=settings, **CONVERGED
    ) as solver:
        loss, sol = _loss(bc, solver, theta, g)
        loss.backward()
        assert _splits(solver.ksp) == ["fieldsplit_u_", "fieldsplit_p_"]
        assert solver.ksp.getPC().getFieldSplitSubKSP()[0].getPC().getType() == "gamg"
        assert len(_splits(solver.adjoint_ksp)) == 2
        assert sol.converged and sol.adjoint.converged
    t, gg = theta.detach().numpy(), g_np
    assert float(loss.detach()) == pytest.approx(_dense_loss(A, bc, t, gg), rel=1e-9)
    rng = np.random.default_rng(2)
    for gradient, direction, which in (
        (theta.grad.numpy(), rng.standard_normal(A.n_params), "theta"),
        (g.grad.numpy(), rng.standard_normal(len(gg)), "g"),
    ):
        h = 1e-6
        shift = {"theta": (h * direction, 0), "g": (0, h * direction)}[which]
        plus = _dense_loss(A, bc, t + shift[0], gg + shift[1])
        minus = _dense_loss(A, bc, t - shift[0], gg - shift[1])
        assert gradient @ direction == pytest.approx((plus - minus) / (2 * h), rel=1e-6), which


def test_fields_are_set_once_per_pc(problem):
    """New values keep the Mat, a new Mat of the same size keeps the PC: two splits
    each time (a second PCFieldSplitSetIS would make four)."""
    _, A, bc, fields, _ = problem
    rng = np.random.default_rng(3)
    with pp.KSPSolver(SCHUR, structure=pp.Structure(fields=fields), **CONVERGED) as solver:
        for theta in (np.ones(A.n_params), 2.0 + rng.random(A.n_params)):
            M = bc.A_II.matrix(theta)
            solver.set_operator(M)
            b = rng.standard_normal(M.shape[0])
            x = solver.solve(b).value
            assert np.linalg.norm(x - spla.spsolve(M.tocsc(), b)) <= 1e-8 * np.linalg.norm(x)
            assert len(_splits(solver.ksp)) == 2
        bigger = M.tolil()
        bigger[0, 1] += 1e-3  # another pattern, the same size: a new Mat
        bigger[1, 0] += 1e-3
        solver.set_operator(bigger.tocsr())
        solver.solve(b)
        assert len(_splits(solver.ksp)) == 2 and len(_splits(solver.adjoint_ksp)) == 2
        copy = solver.clone()
        assert list(copy.structure.fields) == ["u", "p"]
        copy.destroy()


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"u": [0, 1]}, "at least two"),
        ({"u": [0, 0], "p": [1]}, "more than once"),
        ({"u-x": [0], "p": [1]}, "must be a word"),
        ({"u": [0.5], "p": [1]}, "integer"),
        ([0, 1], "must map split names"),
    ],
)
def test_bad_fields_are_refused_at_construction(fields, message):
    with pytest.raises(InputError, match=message):
        pp.KSPSolver(max_it=5, structure=pp.Structure(fields=fields))


def test_fields_must_cover_the_operator(problem):
    _, A, bc, fields, _ = problem
    M = bc.A_II.matrix(np.ones(A.n_params))
    short = {"u": fields["u"], "p": fields["p"][:-1]}
    outside = {"u": fields["u"], "p": np.append(fields["p"], M.shape[0])}
    for bad, message in ((short, "exactly once"), (outside, "outside")):
        with pp.KSPSolver(SCHUR, structure=pp.Structure(fields=bad), max_it=5) as solver:
            with pytest.raises(InputError, match=message):
                solver.set_operator(M)


def test_misspelt_split_options_are_named(problem):
    """A split name that is not a field's: warned after the first solve."""
    _, A, bc, fields, _ = problem
    M = bc.A_II.matrix(np.ones(A.n_params))
    options = {**SCHUR, "fieldsplit_pressure_pc_type": "none"}
    with pp.KSPSolver(options, structure=pp.Structure(fields=fields), **CONVERGED) as solver:
        solver.set_operator(M)
        with pytest.warns(UnusedOptionWarning, match="-fieldsplit_pressure_pc_type"):
            solver.solve(np.ones(M.shape[0]))


def test_a_misspelt_option_is_named_in_the_error_it_causes(problem):
    """``pc_fieldsplit_typ schur``: PETSc runs its default (multiplicative) split with ILU
    on the zero pressure block, claims CONVERGED_RTOL, and the iterate's true residual is
    7 times the right-hand side: the error says so and names the misspelt option."""
    _, A, bc, fields, _ = problem
    M = bc.A_II.matrix(np.ones(A.n_params))
    options = {"ksp_type": "gmres", "pc_type": "fieldsplit", "pc_fieldsplit_typ": "schur"}
    b = np.random.default_rng(0).standard_normal(M.shape[0])
    with pp.KSPSolver(options, structure=pp.Structure(fields=fields), **CONVERGED) as solver:
        solver.set_operator(M)
        with warnings.catch_warnings():
            warnings.simplefilter("error", UnusedOptionWarning)  # named in the error instead
            with pytest.raises(SolverError, match="-pc_fieldsplit_typ") as info:
                solver.solve(b)
    assert info.value.reason == "FALSE_CONVERGENCE"


@pytest.mark.parametrize("flag", [None, True])
def test_option_flags_in_a_dict(problem, flag):
    """A PETSc flag is the value None or True: ``-pc_fieldsplit_detect_saddle_point``
    finds the fields itself (zero diagonal), no ``fields=`` needed."""
    _, A, bc, _, _ = problem
    M = bc.A_II.matrix(np.ones(A.n_params))
    options = {
        "ksp_type": "gmres",
        "pc_type": "fieldsplit",
        "pc_fieldsplit_detect_saddle_point": flag,
        "pc_fieldsplit_type": "schur",
        "pc_fieldsplit_schur_precondition": "selfp",
    }
    b = np.random.default_rng(0).standard_normal(M.shape[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnusedOptionWarning)  # the flag was read
        with pp.KSPSolver(options, **CONVERGED) as solver:
            solver.set_operator(M)
            x = solver.solve(b).value
            assert len(_splits(solver.ksp)) == 2
    assert np.linalg.norm(M @ x - b) <= 1e-8 * np.linalg.norm(b)


def test_a_pressure_null_space_gives_the_minimum_norm_solution():
    """A cavity (velocity fixed on every wall): the pressure is determined up to a
    constant.  Declared as null space, FGMRES with the Schur split, whose right
    preconditioner puts a constant into the pressure, still returns A⁺b."""
    basis, A = taylor_hood(skfem.MeshTri().refined(2))
    u_dofs, p_dofs = basis.split_indices()
    bc = pp.Dirichlet(A, np.intersect1d(basis.get_dofs().all(), u_dofs))
    pressure = np.isin(bc.interior, p_dofs)
    fields = {"u": np.flatnonzero(~pressure), "p": np.flatnonzero(pressure)}
    M = bc.A_II.matrix(np.ones(A.n_params))
    b = np.random.default_rng(0).standard_normal(M.shape[0])  # not compatible
    options = {**SCHUR, "fieldsplit_p_ksp_type": "preonly"}
    del options["fieldsplit_p_ksp_rtol"]
    with pp.KSPSolver(
        options,
        structure=pp.Structure(fields=fields, nullspace=pressure.astype(float)),
        **CONVERGED,
    ) as s:
        s.set_operator(M)
        x = s.solve(b).value
    expected = np.linalg.pinv(M.toarray()) @ b
    assert np.abs(x - expected).max() <= 1e-8 * np.abs(expected).max()
