"""Small problems shared by the core test files (solver, gradients, parametric, bad input).

Every problem is float64 and small enough that a converged solve takes well under a
millisecond, so gradcheck (one solve per input entry) stays fast.
"""

import numpy as np
import scipy.sparse as sp
import skfem
import torch
from petsc4py import PETSc
from skfem import BilinearForm

import prdp_petsc as pp
from prdp_petsc.fem.fd import laplacian

#: converged settings: the implicit gradient is then the true derivative
CONVERGED = {"max_it": 1000, "rtol": 1e-13, "atol": 1e-50}
#: advection velocity of the non-symmetric problem
BETA = (20.0, 10.0)


def unit_square(refine: int = 3):
    """P1 basis on the unit square (``refine`` uniform refinements of two triangles)."""
    return skfem.Basis(skfem.MeshTri().refined(refine), skfem.ElementTriP1())


def advection(basis) -> sp.csr_matrix:
    """Constant advection matrix ``∫ (β·∇u) v`` (non-symmetric)."""

    @BilinearForm
    def form(u, v, w):
        return (BETA[0] * u.grad[0] + BETA[1] * u.grad[1]) * v

    return form.assemble(basis).tocsr()


def interior_operator(basis, coefficient: str = "P0", *, advect: bool = False):
    """``A_II(θ)`` of ``−∇·(θ∇u) [+ β·∇u]`` with the boundary dofs eliminated."""
    A = pp.diffusion_operator(basis, coefficient)
    if advect:
        A = A + advection(basis)
    return pp.Dirichlet(A, basis.get_dofs())


def random_theta(p: int, seed: int = 0, requires_grad: bool = False) -> torch.Tensor:
    """Positive coefficients in [1, 2)."""
    theta = torch.from_numpy(1.0 + np.random.default_rng(seed).random(p))
    return theta.requires_grad_(requires_grad)


def randn(*shape, seed: int = 0, requires_grad: bool = False) -> torch.Tensor:
    x = torch.from_numpy(np.random.default_rng(seed).standard_normal(shape))
    return x.requires_grad_(requires_grad)


def fd_poisson(n: int = 8) -> sp.csr_matrix:
    """SPD five-point matrix ``−Δ_h`` on an ``n × n`` interior grid."""
    return (-laplacian((n, n))).tocsr()


def observed_rate(xs, ys) -> float:
    """Least-squares slope of log(ys) against log(xs)."""
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def taylor_rate(J, m, h, eps0=1e-2, halvings=6):
    """Fitted rate of |J(m+εh) − J(m) − ε dJ·h| as ε halves (2 for a consistent gradient)."""
    m = m.detach().clone().requires_grad_(True)
    j0 = J(m)
    (grad,) = torch.autograd.grad(j0, m)
    slope = float(grad @ h)
    eps = eps0 * 0.5 ** np.arange(halvings)
    with torch.no_grad():
        rem = [abs(float(J(m + e * h)) - float(j0) - e * slope) for e in eps]
    return observed_rate(eps, rem)


def raw_ksp(mat, options):
    """A plain petsc4py KSP on `mat` with `options` (through a private prefix)."""
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setOperators(mat)
    db = PETSc.Options("rawx0_")
    for key, value in options.items():
        db[key] = value
    ksp.setOptionsPrefix("rawx0_")
    ksp.setFromOptions()
    for key in options:
        db.delValue(key)
    return ksp


def reaction_problem(n: int = 6):
    """``R(u; f, c) = A u + c u³ − f`` on the n × n five-point Laplacian: a nonlinear
    problem built from numpy callables only, with its exact Jacobian and vjp."""
    import prdp_petsc as pp

    A = fd_poisson(n).tocsr()

    def residual(u, f, c):
        return A @ u + c * u**3 - f

    def jacobian(u, f, c):
        return (A + sp.diags(3 * c * u**2)).tocsr()

    def vjp(u, lam, f, c, needs):
        return (-lam if needs[0] else None, np.asarray(lam @ u**3) if needs[1] else None)

    return pp.NonlinearProblem(
        n=A.shape[0], residual=residual, jacobian=jacobian, vjp=vjp, jacobian_symmetric=True
    )
