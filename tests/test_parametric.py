"""ParametricMatrix: A(θ) = a₀ + Gθ built from scikit-fem forms, its blocks, sums and VJPs."""

import numpy as np
import pytest
import scipy.sparse as sp
import skfem
import torch
from _core import advection, randn, random_theta, unit_square
from skfem import BilinearForm
from skfem.helpers import dot, grad
from skfem.models.poisson import mass
from torch.autograd import gradcheck

import prdp_petsc as pp
from prdp_petsc.autograd.bridge import matvec


@BilinearForm
def weighted_stiffness(u, v, w):
    return w.k * dot(grad(u), grad(v))


COEFFICIENT_ELEMENTS = {
    ("P0", skfem.MeshTri1): skfem.ElementTriP0,
    ("P1", skfem.MeshTri1): skfem.ElementTriP1,
    ("P0", skfem.MeshTet1): skfem.ElementTetP0,
    ("P1", skfem.MeshTet1): skfem.ElementTetP1,
}


@pytest.mark.parametrize(
    ("mesh", "element", "coefficient"),
    [
        ("annulus", skfem.ElementTriP1, "P0"),
        ("annulus", skfem.ElementTriP1, "P1"),
        ("sliver", skfem.ElementTriP2, "P1"),
        ("box3d", skfem.ElementTetP1, "P0"),
    ],
)
def test_diffusion_operator_equals_direct_assembly(mesh, element, coefficient):
    """a₀ + Gθ equals scikit-fem's assembly with the coefficient field interpolated from θ."""
    basis = skfem.Basis(pp.load_mesh(mesh), element())
    A = pp.diffusion_operator(basis, coefficient)
    cb = basis.with_element(COEFFICIENT_ELEMENTS[(coefficient, type(basis.mesh))]())
    assert A.n_params == cb.N and A.positive
    theta = random_theta(A.n_params, seed=1).numpy()
    direct = weighted_stiffness.assemble(basis, k=cb.interpolate(theta))
    scale = abs(direct).max()
    assert abs(A.matrix(theta) - direct).max() <= 1e-12 * scale
    # the pattern is fixed and sorted CSR: values change, indices do not
    M = A.matrix(2.0 * theta)
    assert M.has_sorted_indices and np.array_equal(M.indices, A.indices)
    assert abs(M - 2.0 * direct).max() <= 1e-12 * scale


def test_reaction_adds_mass_matrix():
    basis = unit_square(3)
    theta = random_theta(basis.mesh.nelements).numpy()
    A = pp.diffusion_operator(basis, reaction=3.0)
    expected = pp.diffusion_operator(basis).matrix(theta) + 3.0 * mass.assemble(basis)
    assert abs(A.matrix(theta) - expected).max() < 1e-13
    assert A.positive


def test_from_form_with_extra_fields():
    """A user form with a fixed extra field (here a scalar weight) is kept linear in θ."""
    basis = unit_square(2)

    @BilinearForm
    def form(u, v, w):
        return w.kappa * w.c * u * v

    cb = basis.with_element(skfem.ElementTriP1())
    A = pp.from_form(form, basis, cb, c=2.5)
    theta = random_theta(cb.N, seed=2).numpy()
    direct = form.assemble(basis, kappa=cb.interpolate(theta), c=2.5)
    assert abs(A.matrix(theta) - direct).max() < 1e-14
    assert not A.positive


def test_theta_gradient_matches_finite_differences():
    """−Gᵀ Σ_batch(λ[rows] ⊙ x[cols]) = −∂/∂θ Σ_batch λᵀ A(θ) x, exactly (A is affine in θ)."""
    basis = unit_square(3)
    A = pp.diffusion_operator(basis, "P1")
    theta = random_theta(A.n_params, seed=3).numpy()
    lam = randn(3, basis.N, seed=4).numpy()
    x = randn(3, basis.N, seed=5).numpy()
    grad_theta = A.theta_gradient(lam, x)
    h = np.eye(A.n_params)[[0, 7, A.n_params - 1]]
    for e in h:
        fd = sum(lam[k] @ (A.matrix(theta + e) - A.matrix(theta)) @ x[k] for k in range(3))
        assert grad_theta @ e == pytest.approx(-fd, rel=1e-12)
    single = sum(A.theta_gradient(lam[k], x[k]) for k in range(3))
    np.testing.assert_allclose(grad_theta, single, rtol=1e-12)


def test_submatrix_blocks_match_scipy_slicing():
    basis = unit_square(3)
    A = pp.diffusion_operator(basis, "P0")
    boundary = basis.get_dofs().flatten()
    interior = np.setdiff1d(np.arange(basis.N), boundary)
    theta = random_theta(A.n_params, seed=6).numpy()
    full = A.matrix(theta)
    for rows, cols in [(interior, interior), (interior, boundary), (boundary, interior)]:
        block = A.submatrix(rows, cols)
        assert block.shape == (len(rows), len(cols))
        assert abs(block.matrix(theta) - full[rows][:, cols]).max() == 0.0


def test_sum_with_constant_and_parametric_matrices():
    basis = unit_square(2)
    K = pp.diffusion_operator(basis, "P0")
    M = pp.from_form(
        BilinearForm(lambda u, v, w: w.kappa * u * v),
        basis,
        basis.with_element(skfem.ElementTriP1()),
    )
    C = advection(basis)
    t1 = random_theta(K.n_params, seed=7).numpy()
    t2 = random_theta(M.n_params, seed=8).numpy()
    AC = K + C
    assert AC.n_params == K.n_params and AC.positive
    assert abs(AC.matrix(t1) - (K.matrix(t1) + C)).max() < 1e-13
    KM = K + M  # parameters stacked: [θ_K, θ_M]
    assert KM.n_params == K.n_params + M.n_params and not KM.positive
    both = np.concatenate([t1, t2])
    assert abs(KM.matrix(both) - (K.matrix(t1) + M.matrix(t2))).max() < 1e-13
    assert abs((2.5 * K).matrix(t1) - 2.5 * K.matrix(t1)).max() < 1e-13
    with pytest.raises(ValueError, match="shape"):
        K + sp.eye(basis.N + 1)


def test_check_theta_rejects_bad_coefficients():
    A = pp.diffusion_operator(unit_square(1))
    good = np.ones(A.n_params)
    assert A.check_theta(good) is not None
    for bad, match in [
        (np.ones(A.n_params + 1), "shape"),
        (np.r_[np.nan, good[1:]], "NaN"),
        (np.r_[0.0, good[1:]], "> 0"),
        (np.r_[-1.0, good[1:]], "> 0"),
    ]:
        with pytest.raises(ValueError, match=match):
            A.check_theta(bad)


def test_coefficient_kind_is_checked():
    with pytest.raises(ValueError, match="coefficient"):
        pp.diffusion_operator(unit_square(1), "P2")
    with pytest.raises(ValueError, match="reaction"):
        pp.diffusion_operator(unit_square(1), reaction=-1.0)


def test_gradcheck_matvec():
    basis = unit_square(2)
    A = pp.diffusion_operator(basis, "P1") + advection(basis)
    v = randn(2, basis.N, seed=9, requires_grad=True)
    theta = random_theta(A.n_params, seed=10, requires_grad=True)
    assert gradcheck(lambda v, t: matvec(A, v, theta=t), (v, theta))
    y = matvec(A, v[0], theta=theta).detach().numpy()
    np.testing.assert_allclose(y, A.matrix(theta.detach().numpy()) @ v[0].detach().numpy())


def test_dirichlet_split_of_scipy_and_parametric_agree():
    basis = unit_square(3)
    A = pp.diffusion_operator(basis, "P0")
    theta = random_theta(A.n_params, seed=11)
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "icc"}, max_it=500, rtol=1e-12)
    f = randn(basis.N, seed=12)
    Dp = pp.Dirichlet(A, basis.get_dofs())
    Ds = pp.Dirichlet(A.matrix(theta.numpy()), basis.get_dofs())
    g = randn(len(Dp.boundary), seed=13)
    u1 = Dp.solve(f, g, solver, theta=theta)
    u2 = Ds.solve(f, g, solver)
    torch.testing.assert_close(u1, u2, rtol=1e-10, atol=1e-12)
    assert torch.equal(u1[Dp.boundary], g)  # boundary values are imposed exactly
    full = A.matrix(theta.numpy())
    residual = (full @ u1.numpy() - f.numpy())[Dp.interior]
    assert np.abs(residual).max() < 1e-9 * np.abs(f.numpy()).max()


def test_is_symmetric_structural():
    from skfem import Basis, ElementTriP1, MeshTri

    basis = Basis(MeshTri().refined(2), ElementTriP1())
    A = pp.diffusion_operator(basis, "P1", reaction=0.5)
    assert A.is_symmetric
    theta = np.random.default_rng(0).uniform(0.5, 2.0, A.n_params)
    M = A.matrix(theta)
    assert abs(M - M.T).max() < 1e-14
    C = sp.random(A.shape[0], A.shape[0], density=0.05, random_state=1, format="csr")
    assert not (A + C).is_symmetric
