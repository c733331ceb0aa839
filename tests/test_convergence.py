"""P1 finite elements solved through prdp_petsc converge at rate 2 in L2 on shipped meshes.

Manufactured solutions with inhomogeneous Dirichlet values (imposed through
`prdp_petsc.Dirichlet`), solved with CG + GAMG to convergence; the L2 error is
integrated by scikit-fem at quadrature points and its slope against the mesh size h
over three uniform refinements is fitted as in scikit-fem's own convergence tests.
"""

import numpy as np
import pytest
import skfem
import torch
from _core import observed_rate
from skfem import Functional, LinearForm

import prdp_petsc as pp

PI = np.pi


def u_exact(x, y):
    return np.sin(PI * x) * np.sin(PI * y) + x * y


def grad_u(x, y):
    return (
        PI * np.cos(PI * x) * np.sin(PI * y) + y,
        PI * np.sin(PI * x) * np.cos(PI * y) + x,
    )


def laplace_u(x, y):
    return -2 * PI**2 * np.sin(PI * x) * np.sin(PI * y)


# κ(x, y) and ∇κ; "P0" uses κ = 1, "P1" a smooth field interpolated at the vertices
KAPPA = {
    "P0": (lambda x, y: np.ones_like(x), lambda x, y: (0 * x, 0 * y)),
    "P1": (lambda x, y: 1 + x**2 + 0.5 * y**2, lambda x, y: (2 * x, y)),
}


def l2_error(mesh_name: str, refine: int, coefficient: str):
    mesh = pp.load_mesh(mesh_name, refine=refine)
    basis = skfem.Basis(mesh, skfem.ElementTriP1())
    kappa, grad_kappa = KAPPA[coefficient]
    A = pp.diffusion_operator(basis, coefficient)

    @LinearForm
    def rhs(v, w):  # f = −∇·(κ∇u)
        x, y = w.x
        gx, gy = grad_u(x, y)
        kx, ky = grad_kappa(x, y)
        return -(kappa(x, y) * laplace_u(x, y) + kx * gx + ky * gy) * v

    if coefficient == "P0":
        theta = np.ones(A.n_params)
    else:
        theta = kappa(*mesh.p)
    D = pp.Dirichlet(A, basis.get_dofs())
    solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "gamg"}, max_it=200, rtol=1e-10)
    sol = D.solve(
        torch.from_numpy(rhs.assemble(basis)),
        torch.from_numpy(u_exact(*mesh.p[:, D.boundary])),
        solver,
        theta=torch.from_numpy(theta),
        return_solution=True,
    )
    assert sol.converged
    u = sol.value

    @Functional
    def err2(w):
        return (w.uh - u_exact(*w.x)) ** 2

    error = np.sqrt(err2.assemble(basis, uh=basis.interpolate(u.numpy())))
    return mesh.param(), error, sol.iterations


@pytest.mark.parametrize(("mesh_name", "coefficient"), [("lshape", "P0"), ("annulus", "P1")])
def test_p1_l2_convergence_rate(mesh_name, coefficient):
    hs, errors, its = zip(*(l2_error(mesh_name, r, coefficient) for r in range(3)), strict=True)
    rate = observed_rate(hs, errors)
    assert 1.8 <= rate <= 2.3, (rate, hs, errors)
    assert errors[-1] < 1e-3
    # CG + GAMG: iteration counts flat (± a few) across refinements
    assert max(its) <= min(its) + 5
