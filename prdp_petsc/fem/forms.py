"""Parametric operators from scikit-fem forms: ``from_form``, diffusion, mass.

`from_form` builds the assembly map G of a `ParametricMatrix` without a Python
loop over elements: the form is assembled once per *local* basis function of the
coefficient (3 for P1 triangles), and the element-wise COO data are scattered
into the pattern.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .parametric import ParametricMatrix, csr_pattern

__all__ = ["diffusion_operator", "from_form", "mass_matrix"]


def from_form(
    form, basis, coefficient_basis, *, name: str = "kappa", positive: bool = False, **kwargs
) -> ParametricMatrix:
    """Build A(θ) from a scikit-fem `BilinearForm` linear in the coefficient ``w[name]``.

    Parameters
    ----------
    form : skfem.BilinearForm
        A form using ``w[name]`` (e.g. ``w.kappa * dot(grad(u), grad(v))``) linearly.
    basis : skfem.CellBasis
        Trial/test basis of the unknown.
    coefficient_basis : skfem.CellBasis
        Basis of the coefficient field on the same mesh and quadrature, e.g.
        ``basis.with_element(ElementTriP0())`` (θ per element) or
        ``basis.with_element(ElementTriP1())`` (θ per node).  θ has
        ``coefficient_basis.N`` entries.
    name : str
        Keyword under which the form reads the coefficient.
    positive : bool
        Mark θ as a coefficient that must be positive.
    **kwargs
        Further fixed fields passed to the form.

    Notes
    -----
    The form is assembled once per local basis function of the coefficient, with
    that basis function's quadrature values as the field; the loop is over local
    degrees of freedom, never over elements.
    """
    if coefficient_basis.X.shape != basis.X.shape:
        raise ValueError("coefficient_basis must use the same quadrature as basis")
    nt = basis.nelems
    entries, cols_theta, vals = None, [], []
    for m in range(coefficient_basis.Nbfun):
        field = coefficient_basis.basis[m][0]
        indices, data, shape, _ = form._assemble(basis, **{name: field}, **kwargs)
        if entries is None:
            entries = indices
        element = np.arange(len(data)) % nt
        cols_theta.append(coefficient_basis.element_dofs[m][element])
        vals.append(data)
    indptr, indices, position = csr_pattern(entries[0], entries[1], shape)
    nnz = len(indices)
    G = sp.csr_matrix(
        (np.concatenate(vals), (np.tile(position, len(vals)), np.concatenate(cols_theta))),
        shape=(nnz, coefficient_basis.N),
    )
    G.eliminate_zeros()
    return ParametricMatrix(indptr, indices, shape, np.zeros(nnz), G, positive)


def mass_matrix(basis) -> sp.csr_matrix:
    """The scikit-fem mass matrix ``∫ u v`` of `basis`."""
    from skfem.models.poisson import mass

    return mass.assemble(basis).tocsr()


def diffusion_operator(
    basis, coefficient: str = "P0", *, reaction: float = 0.0
) -> ParametricMatrix:
    """``−∇·(κ∇u) + r u`` with κ per element (``"P0"``) or per node (``"P1"``).

    Parameters
    ----------
    basis : skfem.CellBasis
        Basis of the unknown (any Lagrange element on triangles or tetrahedra).
    coefficient : {"P0", "P1"}
        Where κ lives: θ has one entry per element or per mesh vertex.
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


def _coefficient_element(mesh, coefficient: str):
    import skfem

    kinds = {
        ("P0", "tri"): skfem.ElementTriP0,
        ("P1", "tri"): skfem.ElementTriP1,
        ("P0", "tet"): skfem.ElementTetP0,
        ("P1", "tet"): skfem.ElementTetP1,
        ("P0", "quad"): skfem.ElementQuad0,
        ("P1", "quad"): skfem.ElementQuad1,
    }
    shape = {skfem.MeshTri1: "tri", skfem.MeshTet1: "tet", skfem.MeshQuad1: "quad"}.get(type(mesh))
    if (coefficient, shape) not in kinds:
        raise ValueError(
            f"coefficient must be 'P0' or 'P1' on tri/tet/quad meshes, "
            f"got {coefficient!r} on {type(mesh).__name__}"
        )
    return kinds[(coefficient, shape)]()
