"""Vector and mixed problems shared by the vector test files: elasticity and Stokes.

Small enough that a converged solve takes milliseconds and a dense reference
(`numpy.linalg`) is exact.
"""

import numpy as np
import skfem
from skfem import BilinearForm, LinearForm
from skfem.helpers import ddot, div, grad

import prdp_petsc as pp


def elasticity(n: int = 4, dim: int = 2, length: float = 2.0):
    """(basis, A(E)) of plane-strain (2D) or 3D elasticity on a box, E per element."""
    if dim == 2:
        x, y = np.linspace(0, length, 2 * n + 1), np.linspace(0, 1, n + 1)
        mesh = skfem.MeshTri.init_tensor(x, y)
        basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTriP1()))
    else:
        t = np.linspace(0, 1, n + 1)
        mesh = skfem.MeshHex.init_tensor(t * length, t, t)
        basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementHex1()))
    return basis, pp.elasticity_operator(basis)


def body_load(basis) -> np.ndarray:
    """A downward load growing along x: not balanced (net force and moment)."""

    @LinearForm
    def load(v, w):
        return -v[1] * (1.0 + w.x[0])

    return load.assemble(basis)


def clamped(basis, A):
    """`Dirichlet` of A with the face x = 0 clamped (every component of its nodes)."""
    return pp.Dirichlet(A, basis.get_dofs(lambda x: np.isclose(x[0], 0.0)).all())


def taylor_hood(mesh):
    """(basis, A(θ)) of Stokes on Taylor–Hood (P2/P1) elements, viscosity θ per element."""
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTriP2()) * skfem.ElementTriP1())

    @BilinearForm
    def form(u, p, v, q, w):
        return w.kappa * ddot(grad(u), grad(v)) - div(v) * p - div(u) * q

    return basis, pp.from_form(form, basis, basis.with_element(skfem.ElementTriP0()), positive=True)


def stokes(n: int = 4):
    """Taylor–Hood Stokes on [0, 2] × [0, 1], viscosity θ per element.

    Returns (basis, A(θ), bc, fields, g): the velocity is fixed on the left (inflow),
    top and bottom walls, the right side is a do-nothing outflow (so the pressure
    has no null space); ``fields`` numbers velocity and pressure among the unknowns
    ``bc.interior``, and ``g`` is a parabolic inflow on ``bc.boundary``.
    """
    x, y = np.linspace(0, 2, 2 * n + 1), np.linspace(0, 1, n + 1)
    basis, A = taylor_hood(skfem.MeshTri.init_tensor(x, y).with_defaults())
    u_dofs, p_dofs = basis.split_indices()
    walls = basis.get_dofs({"left", "top", "bottom"}).all()
    bc = pp.Dirichlet(A, np.intersect1d(walls, u_dofs))
    fields = {
        "u": np.flatnonzero(np.isin(bc.interior, u_dofs)),
        "p": np.flatnonzero(np.isin(bc.interior, p_dofs)),
    }
    x_component = u_dofs[basis.split_bases()[0].split_indices()[0]]
    where = basis.doflocs[:, bc.boundary]
    inflow = np.isclose(where[0], 0.0) & np.isin(bc.boundary, x_component)
    g = np.where(inflow, where[1] * (1.0 - where[1]), 0.0)
    return basis, A, bc, fields, g


#: a Schur-complement fieldsplit for Taylor–Hood Stokes (split names of `stokes`)
SCHUR = {
    "ksp_type": "fgmres",
    "pc_type": "fieldsplit",
    "pc_fieldsplit_type": "schur",
    "pc_fieldsplit_schur_fact_type": "full",
    "pc_fieldsplit_schur_precondition": "selfp",
    "fieldsplit_u_ksp_type": "preonly",
    "fieldsplit_u_pc_type": "gamg",
    "fieldsplit_p_ksp_type": "cg",
    "fieldsplit_p_pc_type": "jacobi",
    "fieldsplit_p_ksp_rtol": 1e-10,
}
