"""from_form: A(θ) = a₀ + Gθ from a scikit-fem form, against scikit-fem's own direct assembly.

Every expected matrix is ``form.assemble(basis, kappa=cb.interpolate(θ))``: scikit-fem's
assembly of the field interpolated from θ, a code path from_form does not share.
"""

import logging

import numpy as np
import pytest
import scipy.sparse as sp
import skfem
from skfem import BilinearForm
from skfem.helpers import dot, grad
from skfem.models.poisson import mass

import prdp_petsc as pp
from prdp_petsc.errors import StructureError
from prdp_petsc.fem.forms import AFFINE_RTOL


@BilinearForm
def stiffness(u, v, w):
    return w.kappa * dot(grad(u), grad(v))


@BilinearForm
def nonsymmetric(u, v, w):
    """Linear in κ, reads κ's gradient and is not symmetric: a transposed scatter shows."""
    return w.kappa * dot(grad(u), grad(v)) + (w.kappa * u.grad[0] + dot(grad(w.kappa), grad(u))) * v


def direct(form, basis, cb, theta, **fields):
    """scikit-fem's assembly with the coefficient field interpolated from θ."""
    return form.assemble(basis, kappa=cb.interpolate(theta), **fields)


def relative_error(A, B) -> float:
    return abs(A - B).max() / abs(B).max()


def positive_theta(p: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.1, 10.0, p)


MESHES = {
    "tri": lambda: skfem.MeshTri().refined(2),
    "tet": lambda: skfem.MeshTet().refined(1),
    "quad": lambda: skfem.MeshQuad().refined(2),
    "hex": lambda: skfem.MeshHex().refined(1),
}

CASES = [  # (mesh, unknown element, coefficient element)
    ("tri", skfem.ElementTriP1, skfem.ElementTriP0),
    ("tri", skfem.ElementTriP1, skfem.ElementTriP1),
    ("tri", skfem.ElementTriP2, skfem.ElementTriP0),
    ("tri", skfem.ElementTriP2, skfem.ElementTriP1),
    ("tet", skfem.ElementTetP1, skfem.ElementTetP0),
    ("tet", skfem.ElementTetP1, skfem.ElementTetP1),
    ("tet", skfem.ElementTetP2, skfem.ElementTetP0),
    ("tet", skfem.ElementTetP2, skfem.ElementTetP1),
    ("quad", skfem.ElementQuad1, skfem.ElementQuad0),
    ("quad", skfem.ElementQuad1, skfem.ElementQuad1),
    ("quad", skfem.ElementQuad2, skfem.ElementQuad1),
    ("hex", skfem.ElementHex1, skfem.ElementHex0),
    ("hex", skfem.ElementHex1, skfem.ElementHex1),
]


def test_local_matrices_are_trial_index_first():
    """The convention from_form relies on: tolocal()[e, j, i] is row dofs[i, e], column dofs[j, e].

    Scattered here with scipy's COO summation, independently of from_form, the local
    matrices of a non-symmetric form reproduce scikit-fem's assembly to rounding, and
    the transposed reading does not.
    """
    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP2())
    cb = basis.with_element(skfem.ElementTriP1())
    field = cb.interpolate(positive_theta(cb.N, seed=0))
    local = nonsymmetric.elemental(basis, kappa=field).tolocal()
    assert local.shape == (basis.nelems, basis.Nbfun, basis.Nbfun)
    dofs = basis.element_dofs  # (Nbfun, nelems)
    e, j, i = np.meshgrid(*map(np.arange, local.shape), indexing="ij")
    expected = nonsymmetric.assemble(basis, kappa=field)
    scattered = sp.coo_matrix((local.ravel(), (dofs[i, e].ravel(), dofs[j, e].ravel())))
    assert relative_error(scattered.tocsr(), expected) < 1e-14
    transposed = sp.coo_matrix((local.ravel(), (dofs[j, e].ravel(), dofs[i, e].ravel())))
    assert relative_error(transposed.tocsr(), expected) > 1e-2


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("mesh", "element", "coefficient"), CASES)
def test_from_form_equals_direct_assembly(mesh, element, coefficient, seed):
    """a₀ + Gθ equals scikit-fem's assembly at random positive θ, on every cell shape."""
    basis = skfem.Basis(MESHES[mesh](), element())
    cb = basis.with_element(coefficient())
    A = pp.from_form(nonsymmetric, basis, cb, positive=True)
    assert A.n_params == cb.N and A.shape == (basis.N, basis.N) and A.positive
    assert not np.any(A.a0)  # nothing in the form is free of κ
    theta = positive_theta(cb.N, seed)
    expected = direct(nonsymmetric, basis, cb, theta)
    assert relative_error(A.matrix(theta), expected) < 1e-13
    # A(θ) is linear: a second θ, and the sum of two, need no new assembly
    other = positive_theta(cb.N, seed + 100)
    expected_sum = direct(nonsymmetric, basis, cb, theta + other)
    assert relative_error(A.matrix(theta + other), expected_sum) < 1e-13


@pytest.mark.parametrize(
    ("mesh", "element", "coefficient", "kind"),
    [
        ("quad", skfem.ElementQuad1, skfem.ElementQuad0, "P0"),
        ("quad", skfem.ElementQuad2, skfem.ElementQuad1, "P1"),
        ("hex", skfem.ElementHex1, skfem.ElementHex0, "P0"),
        ("hex", skfem.ElementHex1, skfem.ElementHex1, "P1"),
    ],
)
def test_diffusion_operator_on_quads_and_hexes(mesh, element, coefficient, kind):
    basis = skfem.Basis(MESHES[mesh](), element())
    A = pp.diffusion_operator(basis, kind, reaction=0.5)
    cb = basis.with_element(coefficient())
    assert A.n_params == cb.N and A.positive
    assert A.n_params == (basis.mesh.nelements if kind == "P0" else basis.mesh.nvertices)
    theta = positive_theta(cb.N, seed=3)
    expected = direct(stiffness, basis, cb, theta) + 0.5 * mass.assemble(basis)
    assert relative_error(A.matrix(theta), expected) < 1e-13


def test_diffusion_operator_rejects_other_meshes():
    basis = skfem.Basis(skfem.MeshTri2.init_circle(), skfem.ElementTriP2())
    with pytest.raises(ValueError, match="MeshTri2"):
        pp.diffusion_operator(basis)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_affine_form_keeps_the_constant_part_in_a0(seed):
    """κ∇u·∇v + uv: a₀ is the mass matrix (counted once, not once per θ_j), G the rest."""

    @BilinearForm
    def diffusion_reaction(u, v, w):
        return w.kappa * dot(grad(u), grad(v)) + u * v

    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP1())
    A = pp.from_form(diffusion_reaction, basis, cb, positive=True)
    M = mass.assemble(basis)
    a0 = sp.csr_matrix((A.a0, A.indices, A.indptr), shape=A.shape)
    assert relative_error(a0, M) < 1e-14
    theta = positive_theta(cb.N, seed)
    assert relative_error(A.matrix(theta), direct(diffusion_reaction, basis, cb, theta)) < 1e-13
    assert relative_error(A.matrix(theta) - M, direct(stiffness, basis, cb, theta)) < 1e-13


@pytest.mark.parametrize(
    ("coefficient", "body"),
    [
        (skfem.ElementTriP0, lambda u, v, k: k**2 * dot(grad(u), grad(v))),
        (skfem.ElementTriP1, lambda u, v, k: k**2 * dot(grad(u), grad(v))),
        (skfem.ElementTriP1, lambda u, v, k: np.exp(k) * u * v),
        (skfem.ElementTriP0, lambda u, v, k: k * dot(grad(u), grad(v)) + k * k * u * v),
        (skfem.ElementTriP1, lambda u, v, k: k * dot(grad(k), grad(k)) * u * v),
        (skfem.ElementTriP1, lambda u, v, k: dot(grad(k), grad(k)) * u * v),
    ],
)
def test_nonaffine_forms_are_refused(coefficient, body):
    form = BilinearForm(lambda u, v, w: body(u, v, w.kappa))
    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    cb = basis.with_element(coefficient())
    with pytest.raises(StructureError, match="not affine in w.kappa") as error:
        pp.from_form(form, basis, cb, positive=True)
    assert isinstance(error.value, ValueError)
    mismatch = float(error.value.args[0].split(" by ")[1].split(" of the")[0])
    assert mismatch > 1e3 * AFFINE_RTOL  # the measured mismatch is named


@pytest.mark.parametrize(
    ("body", "positive"),
    [
        (lambda u, v, k: u * v / k, True),  # Inf for the zero field, in a₀
        (lambda u, v, k: np.sqrt(k) * u * v, False),  # NaN in the direct assembly only
    ],
)
def test_forms_that_turn_into_inf_or_nan_are_refused(body, positive):
    """Refused with the mismatch reported as nan, never accepted as a matrix of Inf or NaN."""
    form = BilinearForm(lambda u, v, w: body(u, v, w.kappa))
    basis = skfem.Basis(skfem.MeshTri().refined(1), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP0())
    with np.errstate(divide="ignore", invalid="ignore"):
        with pytest.raises(StructureError, match="by nan of the largest entry"):
            pp.from_form(form, basis, cb, positive=positive)


def test_sign_of_the_check_follows_positive():
    """|κ| is linear on positive P1 fields (the nodal basis functions are ≥ 0), not on all."""
    form = BilinearForm(lambda u, v, w: abs(w.kappa) * u * v)
    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP1())
    A = pp.from_form(form, basis, cb, positive=True)
    theta = positive_theta(cb.N, seed=4)
    assert relative_error(A.matrix(theta), direct(form, basis, cb, theta)) < 1e-13
    with pytest.raises(StructureError, match="not affine"):
        pp.from_form(form, basis, cb, positive=False)


def test_form_without_the_coefficient_is_constant(caplog):
    """Accepted (it is affine): G is empty, a₀ the form's matrix, and a warning is logged."""
    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP0())
    with caplog.at_level(logging.WARNING, logger="prdp_petsc.fem.forms"):
        A = pp.from_form(mass, basis, cb)
    assert "does not read w.kappa" in caplog.text
    assert A.n_params == cb.N and A.G.nnz == 0
    M = mass.assemble(basis)
    assert relative_error(sp.csr_matrix((A.a0, A.indices, A.indptr), shape=A.shape), M) < 1e-14
    theta = np.random.default_rng(5).standard_normal(cb.N)
    assert relative_error(A.matrix(theta), M) < 1e-14
    lam, x = np.random.default_rng(6).standard_normal((2, basis.N))
    assert not np.any(A.theta_gradient(lam, x))


def test_fixed_fields_and_their_names():
    """Fixed fields reach the form; one named like the coefficient is refused."""

    @BilinearForm
    def weighted(u, v, w):
        return w.kappa * w.c * dot(grad(u), grad(v)) + w.d * u * v

    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP1())
    d = basis.interpolate(1.0 + basis.doflocs[0])
    A = pp.from_form(weighted, basis, cb, c=2.5, d=d)
    theta = np.random.default_rng(7).uniform(-2, 2, cb.N)
    expected = direct(weighted, basis, cb, theta, c=2.5, d=d)
    assert relative_error(A.matrix(theta), expected) < 1e-13
    with pytest.raises(ValueError, match="'c' is the coefficient's name"):
        pp.from_form(weighted, basis, cb, name="c", kappa=1.0, c=2.5, d=d)


def test_coefficient_under_another_name_and_quadrature_mismatch():
    @BilinearForm
    def form(u, v, w):
        return w.k * dot(grad(u), grad(v))

    basis = skfem.Basis(skfem.MeshTri().refined(2), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP0())
    A = pp.from_form(form, basis, cb, name="k")
    theta = positive_theta(cb.N, seed=8)
    expected = form.assemble(basis, k=cb.interpolate(theta))
    assert relative_error(A.matrix(theta), expected) < 1e-13
    finer = skfem.Basis(basis.mesh, skfem.ElementTriP0(), intorder=4)
    assert finer.X.shape != basis.X.shape
    with pytest.raises(ValueError, match="same quadrature"):
        pp.from_form(form, basis, finer, name="k")
