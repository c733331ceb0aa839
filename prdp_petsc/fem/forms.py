"""Parametric operators from scikit-fem forms: ``from_form``, diffusion, elasticity, mass.

`from_form` builds ``A(θ) = a₀ + Gθ`` of a `ParametricMatrix` from a
`BilinearForm` affine in a coefficient field, on scikit-fem's public API only
(`Form.elemental`, `COOData.tolocal`, `Basis.element_dofs`, `Basis.interpolate`,
`CellBasis.basis`), without a Python loop over elements: the local matrices are
computed once with the coefficient field zero and once per *local* basis
function of the coefficient (3 for P1 triangles), and scattered into the CSR
pattern.  Two
direct assemblies at seeded random coefficients then confirm that the form
really is affine in the coefficient.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp

from ..errors import InputError, StructureError
from .parametric import ParametricMatrix, csr_pattern

if TYPE_CHECKING:
    import skfem

__all__ = ["AFFINE_RTOL", "diffusion_operator", "elasticity_operator", "from_form", "mass_matrix"]

logger = logging.getLogger(__name__)

#: Largest mismatch between ``a₀ + Gθ`` and a direct assembly, relative to the
#: matrix's largest entry, that `from_form` accepts as rounding.
AFFINE_RTOL = 1e-10


def from_form(
    form: skfem.BilinearForm,
    basis: skfem.CellBasis,
    coefficient_basis: skfem.CellBasis,
    *,
    name: str = "kappa",
    positive: bool = False,
    **kwargs: Any,
) -> ParametricMatrix:
    """Build A(θ) from a scikit-fem `BilinearForm` affine in the coefficient ``w[name]``.

    Parameters
    ----------
    form : skfem.BilinearForm
        A form affine in ``w[name]``: a part that does not read the coefficient
        plus a part linear in it, e.g. ``w.kappa * dot(grad(u), grad(v)) + u * v``.
        The coefficient's value and its gradient (``w.kappa.grad``) may be used.
    basis : skfem.CellBasis
        Trial/test basis of the unknown.
    coefficient_basis : skfem.CellBasis
        Basis of the coefficient field on the same mesh and quadrature, e.g.
        ``basis.with_element(ElementTriP0())`` (θ per element) or
        ``basis.with_element(ElementTriP1())`` (θ per node).  θ has
        ``coefficient_basis.N`` entries and the field is
        ``coefficient_basis.interpolate(θ)``.
    name : str
        Keyword under which the form reads the coefficient.
    positive : bool
        Mark θ as a coefficient that must be positive; the affinity check then
        draws positive coefficients only.
    **kwargs
        Further fixed fields passed to the form.

    Returns
    -------
    ParametricMatrix
        ``a0`` is the form assembled with the coefficient field zero; ``G`` holds
        the linear part only.  A form that does not read the coefficient is
        accepted: ``G`` is then empty, A(θ) constant and its θ-gradient zero
        (logged as a warning, since that is rarely what was meant).

    Raises
    ------
    StructureError
        If the form is not affine in the coefficient (``kappa**2 * ...``,
        ``exp(kappa) * ...``): ``a0 + Gθ`` would silently be a different matrix.

    Notes
    -----
    The local matrices come from ``form.elemental(basis, ...).tolocal()``, shape
    (nelems, Nbfun, Nbfun), trial index first: ``local[e, j, i]`` lands in row
    ``basis.element_dofs[i, e]`` and column ``basis.element_dofs[j, e]``.  The
    m-th local basis function of the coefficient at the quadrature points is
    ``coefficient_basis.basis[m][0]``, the field whose weighted sum over m is
    ``coefficient_basis.interpolate(θ)``; so with ``Z`` the local matrices for the
    zero field (scattered into ``a0``) and ``L_m`` those for basis function m minus
    ``Z`` (scattered into G), an affine form has the local matrices
    ``Z + Σ_m θ[coefficient_basis.element_dofs[m, e]] L_m``.  The loop
    is over local degrees of freedom, never over elements.

    The check assembles ``form.assemble(basis, **{name: coefficient_basis.interpolate(θ)})``
    directly at a seeded random θ (in [0.5, 2] if `positive`, else in [-2, 2])
    and at 2θ, and requires ``a0 + Gθ`` to match both to `AFFINE_RTOL` of the
    largest entry (matching at 2θ as well means A(2θ) − A(θ) = A(θ) − A(0)).
    The whole build costs ``coefficient_basis.Nbfun + 3`` assemblies.
    """
    if coefficient_basis.X.shape != basis.X.shape:
        raise InputError("coefficient_basis must use the same quadrature as basis")
    if name in kwargs:
        raise InputError(f"{name!r} is the coefficient's name; it cannot also be a fixed field")

    def local_matrices(field):
        return form.elemental(basis, **{name: field}, **kwargs).tolocal()

    zero = local_matrices(coefficient_basis.interpolate(np.zeros(coefficient_basis.N)))
    dofs = basis.element_dofs.T  # (nelems, Nbfun)
    rows = np.broadcast_to(dofs[:, None, :], zero.shape)  # local[e, j, i]: row dofs[e, i]
    cols = np.broadcast_to(dofs[:, :, None], zero.shape)  # ... and column dofs[e, j]
    shape = (basis.N, basis.N)
    indptr, indices, position = csr_pattern(rows.ravel(), cols.ravel(), shape)
    nnz = len(indices)
    a0 = np.bincount(position, weights=zero.ravel(), minlength=nnz)

    values, theta_cols = [], []
    for m in range(coefficient_basis.Nbfun):
        values.append((local_matrices(coefficient_basis.basis[m][0]) - zero).ravel())
        theta_dofs = coefficient_basis.element_dofs[m][:, None, None]
        theta_cols.append(np.broadcast_to(theta_dofs, zero.shape).ravel())
    G = sp.csr_matrix(
        (np.concatenate(values), (np.tile(position, len(values)), np.concatenate(theta_cols))),
        shape=(nnz, coefficient_basis.N),
    )
    G.eliminate_zeros()
    if G.nnz == 0:
        logger.warning("form does not read w.%s: A(θ) is constant, its θ-gradient zero", name)

    def affine(theta):
        return sp.csr_matrix((a0 + G @ theta, indices, indptr), shape=shape)

    def direct(theta):
        field = coefficient_basis.interpolate(theta)
        return form.assemble(basis, **{name: field}, **kwargs)

    _check_affine(affine, direct, coefficient_basis.N, positive, name)
    return ParametricMatrix(indptr, indices, shape, a0, G, positive)


def _check_affine(affine, direct, n_params: int, positive: bool, name: str) -> None:
    """Raise `StructureError` unless ``affine(θ)`` equals ``direct(θ)`` at a random θ and 2θ."""
    rng = np.random.default_rng(0)
    theta = rng.uniform(0.5, 2.0, n_params) if positive else rng.uniform(-2.0, 2.0, n_params)
    for where, t in [("a random θ", theta), ("2θ", 2.0 * theta)]:
        expected, model = direct(t), affine(t)
        difference = _largest(expected - model)
        scale = np.max([_largest(expected), _largest(model)])  # NaN if either has one
        mismatch = difference / scale if scale != 0 else difference
        if not mismatch <= AFFINE_RTOL:  # NaN fails too
            raise StructureError(
                f"the form is not affine in w.{name}: a0 + Gθ differs from direct assembly "
                f"at {where} by {mismatch:.3g} of the largest entry (tolerance "
                f"{AFFINE_RTOL:g}); from_form needs c(u, v) + b(u, v; {name}) with b linear "
                f"in {name} (e.g. {name} * dot(grad(u), grad(v)) + u * v), not {name}**2 "
                f"or exp({name})"
            )


def _largest(matrix: sp.spmatrix) -> float:
    """Largest absolute stored value of a sparse matrix (0 if none, NaN if any is NaN)."""
    return float(np.max(np.abs(matrix.data), initial=0.0))


def mass_matrix(basis: skfem.CellBasis) -> sp.csr_matrix:
    """The scikit-fem mass matrix ``∫ u v`` of `basis`."""
    from skfem.models.poisson import mass

    return mass.assemble(basis).tocsr()


def diffusion_operator(
    basis: skfem.CellBasis, coefficient: str = "P0", *, reaction: float = 0.0
) -> ParametricMatrix:
    """``−∇·(κ∇u) + r u`` with κ per element (``"P0"``) or per node (``"P1"``).

    Parameters
    ----------
    basis : skfem.CellBasis
        Basis of the unknown: any element on a mesh of triangles, tetrahedra,
        quadrilaterals or hexahedra (`skfem.MeshTri1`, `MeshTet1`, `MeshQuad1`,
        `MeshHex1`).
    coefficient : {"P0", "P1"}
        Where κ lives: θ has one entry per element (``ElementTriP0``,
        ``ElementTetP0``, ``ElementQuad0``, ``ElementHex0``) or per mesh vertex
        (``ElementTriP1``, ``ElementTetP1``, ``ElementQuad1``, ``ElementHex1``).
    reaction : float
        Constant reaction coefficient r ≥ 0 (adds ``r`` times the mass matrix).

    Returns
    -------
    ParametricMatrix
        Marked ``positive``: κ must be > 0.
    """
    from skfem import BilinearForm
    from skfem.helpers import dot, grad

    if reaction < 0 or not np.isfinite(reaction):
        raise ValueError(f"reaction must be finite and >= 0, got {reaction}")
    coefficient_basis = basis.with_element(_coefficient_element(basis.mesh, coefficient))

    @BilinearForm
    def stiffness(u, v, w):
        return w.kappa * dot(grad(u), grad(v))

    A = from_form(stiffness, basis, coefficient_basis, positive=True)
    return A + reaction * mass_matrix(basis) if reaction > 0 else A


def elasticity_operator(
    basis: skfem.CellBasis, coefficient: str = "P0", *, poisson_ratio: float = 0.3
) -> ParametricMatrix:
    """Linear elasticity ``−∇·σ(u)`` with Young's modulus E = θ per element or per node.

    ``σ = E (λ̂ tr ε(u) I + 2 μ̂ ε(u))`` with ``λ̂ = ν / ((1 + ν)(1 − 2ν))`` and
    ``μ̂ = 1 / (2 (1 + ν))``: plane strain in 2D, the isotropic solid in 3D; a SIMP
    stiffness is ``θ = E_min + ρ^p (E_0 − E_min)``.

    Parameters
    ----------
    basis : skfem.CellBasis
        A vector basis, ``Basis(mesh, ElementVector(ElementTriP1()))`` (any Lagrange
        element on triangles, tetrahedra, quadrilaterals or hexahedra).  Its dofs
        are numbered node by node, so ``Structure(block_size=mesh.dim())`` fits;
        `prdp_petsc.fem.vector.rigid_body_modes` gives the near-null space.
    coefficient : {"P0", "P1"}
        Where E lives: θ per element or per mesh vertex, as in `diffusion_operator`.
    poisson_ratio : float
        ν in [0, 0.5).

    Returns
    -------
    ParametricMatrix
        Marked ``positive`` (E > 0).  Without Dirichlet conditions it is singular,
        with the rigid-body modes as kernel.
    """
    from skfem import BilinearForm
    from skfem.helpers import ddot, sym_grad, trace

    if not 0.0 <= poisson_ratio < 0.5:
        raise InputError(f"poisson_ratio must lie in [0, 0.5), got {poisson_ratio}")
    nu = float(poisson_ratio)
    lam, mu = nu / ((1 + nu) * (1 - 2 * nu)), 1.0 / (2 * (1 + nu))
    coefficient_basis = basis.with_element(_coefficient_element(basis.mesh, coefficient))

    @BilinearForm
    def stiffness(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        return w.kappa * (lam * trace(eu) * trace(ev) + 2.0 * mu * ddot(eu, ev))

    return from_form(stiffness, basis, coefficient_basis, positive=True)


def _coefficient_element(mesh, coefficient: str):
    """The scikit-fem element of a κ per element (``"P0"``) or per vertex (``"P1"``)."""
    import skfem

    kinds = {
        ("P0", "tri"): skfem.ElementTriP0,
        ("P1", "tri"): skfem.ElementTriP1,
        ("P0", "tet"): skfem.ElementTetP0,
        ("P1", "tet"): skfem.ElementTetP1,
        ("P0", "quad"): skfem.ElementQuad0,
        ("P1", "quad"): skfem.ElementQuad1,
        ("P0", "hex"): skfem.ElementHex0,
        ("P1", "hex"): skfem.ElementHex1,
    }
    shapes = {
        skfem.MeshTri1: "tri",
        skfem.MeshTet1: "tet",
        skfem.MeshQuad1: "quad",
        skfem.MeshHex1: "hex",
    }
    shape = shapes.get(type(mesh))
    if (coefficient, shape) not in kinds:
        raise ValueError(
            f"coefficient must be 'P0' or 'P1' on tri/tet/quad/hex meshes, "
            f"got {coefficient!r} on {type(mesh).__name__}"
        )
    return kinds[(coefficient, shape)]()
