"""Vector and mixed problems: elasticity with its rigid-body modes, Stokes with fields.

The guide page `docs/guide/vector.md` shows the sections of this file, and
`tests/lab/test_docs.py` runs each function and checks its numbers.

* `elasticity(dim, n)`: linear elasticity on the unit square or cube (P1 triangles,
  Q1 hexahedra), clamped at x = 0 and loaded by its weight; CG + GAMG to 1e-8 with and
  without the rigid-body modes as near-null space (block size = dimension).
* `free_body()`: the same body with nothing clamped is singular; undeclared it raises
  `SingularOperatorError`, with the modes as null space it gives the minimum-norm
  least-squares displacement.
* `stokes(n)`: Taylor–Hood (P2/P1) Stokes in a channel, the viscosity per element
  the parameter, a Schur-complement fieldsplit declared by ``fields=``; returns the
  solution error against a direct solve and the gradient of the outflow flux.
* `simp_contrast()`: GAMG on a SIMP-like stiffness with contrast 1e-9 : 1; the
  default smoothers fail (``DIVERGED_INDEFINITE_PC``), Richardson + SOR smoothers solve.
"""

import numpy as np
import scipy.sparse.linalg as spla
import skfem
import torch
from skfem import BilinearForm, LinearForm
from skfem.helpers import ddot, div, grad

import prdp_petsc as pp
from prdp_petsc.errors import SingularOperatorError

# --8<-- [start:elasticity]
GAMG = {"ksp_type": "cg", "pc_type": "gamg"}


def elasticity(dim: int = 3, n: int = 8) -> dict:
    """GAMG iterations to rtol 1e-8 with and without the rigid-body modes."""
    t = np.linspace(0.0, 1.0, n + 1)
    if dim == 2:
        mesh, element = skfem.MeshTri.init_tensor(t, t), skfem.ElementTriP1()
    else:
        mesh, element = skfem.MeshHex.init_tensor(t, t, t), skfem.ElementHex1()
    basis = skfem.Basis(mesh, skfem.ElementVector(element))  # dofs node by node
    A = pp.elasticity_operator(basis)  # E = θ per element
    clamp = basis.get_dofs(lambda x: np.isclose(x[0], 0.0)).all()  # every component
    bc = pp.Dirichlet(A, clamp)

    @LinearForm
    def weight(v, w):
        return -v[1]

    f = torch.from_numpy(weight.assemble(basis))
    g = torch.zeros(len(bc.boundary), dtype=torch.float64)
    theta = torch.ones(A.n_params, dtype=torch.float64)

    structure = pp.Structure(  # declared once: every Mat the solver builds gets it
        near_nullspace=pp.rigid_body_modes(basis, bc.interior),  # the kept dofs
        block_size=dim,
    )
    iterations = {}
    for name, declared in (("scalar", None), ("modes", structure)):
        with pp.KSPSolver(GAMG, max_it=500, rtol=1e-8, structure=declared) as solver:
            sol = bc.solve(f, g, solver, theta=theta, return_solution=True)
            iterations[name] = sol.iterations
    return iterations


# --8<-- [end:elasticity]


# --8<-- [start:free]
def free_body() -> dict:
    """Nothing clamped: undeclared, the kernel is named; declared, A⁺b comes back."""
    basis = skfem.Basis(skfem.MeshTri().refined(3), skfem.ElementVector(skfem.ElementTriP1()))
    K = pp.elasticity_operator(basis).matrix(np.ones(basis.mesh.nelements))
    b = np.random.default_rng(0).standard_normal(basis.N)
    try:
        with pp.KSPSolver(GAMG, max_it=500, rtol=1e-8) as solver:
            solver.set_operator(K)
            solver.solve(b)
        undeclared = "returned"
    except SingularOperatorError as err:
        undeclared = err.reason  # "SINGULAR": its message says to declare nullspace=
    modes = pp.rigid_body_modes(basis)
    with pp.KSPSolver(
        GAMG, max_it=500, rtol=1e-10, structure=pp.Structure(nullspace=modes, block_size=2)
    ) as solver:
        solver.set_operator(K)
        x = solver.solve(b).value  # the minimum-norm least-squares solution A⁺b
    return {"undeclared": undeclared, "x": x, "K": K, "b": b}


# --8<-- [end:free]


# --8<-- [start:stokes]
SCHUR = {
    "ksp_type": "fgmres",
    "pc_type": "fieldsplit",
    "pc_fieldsplit_type": "schur",
    "pc_fieldsplit_schur_fact_type": "full",
    "pc_fieldsplit_schur_precondition": "selfp",  # S ≈ −B diag(A)⁻¹ Bᵀ
    "fieldsplit_u_ksp_type": "preonly",  # the split named "u" in fields=
    "fieldsplit_u_pc_type": "gamg",
    "fieldsplit_p_ksp_type": "cg",
    "fieldsplit_p_pc_type": "jacobi",
    "fieldsplit_p_ksp_rtol": 1e-10,
}


def stokes(n: int = 8) -> dict:
    """Channel flow, parabolic inflow, do-nothing outflow; viscosity θ per element."""
    x, y = np.linspace(0.0, 2.0, 2 * n + 1), np.linspace(0.0, 1.0, n + 1)
    mesh = skfem.MeshTri.init_tensor(x, y).with_defaults()  # boundaries left, right, ...
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTriP2()) * skfem.ElementTriP1())

    @BilinearForm
    def form(u, p, v, q, w):
        return w.kappa * ddot(grad(u), grad(v)) - div(v) * p - div(u) * q

    A = pp.from_form(form, basis, basis.with_element(skfem.ElementTriP0()), positive=True)
    u_dofs, p_dofs = basis.split_indices()
    walls = basis.get_dofs({"left", "top", "bottom"}).all()
    bc = pp.Dirichlet(A, np.intersect1d(walls, u_dofs))  # velocity only
    fields = {  # positions among the unknowns bc.interior
        "u": np.flatnonzero(np.isin(bc.interior, u_dofs)),
        "p": np.flatnonzero(np.isin(bc.interior, p_dofs)),
    }
    u_x = u_dofs[basis.split_bases()[0].split_indices()[0]]
    where = basis.doflocs[:, bc.boundary]
    inflow = np.isclose(where[0], 0.0) & np.isin(bc.boundary, u_x)
    g = torch.from_numpy(np.where(inflow, where[1] * (1.0 - where[1]), 0.0))
    f = torch.zeros(basis.N, dtype=torch.float64)
    theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)

    with pp.KSPSolver(
        SCHUR, max_it=200, rtol=1e-10, structure=pp.Structure(fields=fields)
    ) as solver:
        sol = bc.solve(f, g, solver, theta=theta, return_solution=True)
        state = sol.value
        outflow = np.isclose(basis.doflocs[0], 2.0) & np.isin(np.arange(basis.N), u_x)
        flux = state[torch.from_numpy(np.flatnonzero(outflow))].sum()
        flux.backward()  # the adjoint solve shares the forward PC and its fields
        splits = [k.getOptionsPrefix() for k in solver.ksp.getPC().getFieldSplitSubKSP()]
        iterations = (sol.iterations, sol.adjoint[0].iterations)
    M = bc.A_II.matrix(np.ones(A.n_params))
    direct = spla.spsolve(M.tocsc(), bc.rhs(f, g, theta.detach()).numpy())
    error = np.abs(state.detach().numpy()[bc.interior] - direct).max() / np.abs(direct).max()
    return {"splits": splits, "iterations": iterations, "error": error, "grad": theta.grad}


# --8<-- [end:stokes]


# --8<-- [start:simp]
ROBUST_GAMG = {
    "ksp_type": "cg",
    "pc_type": "gamg",
    "mg_levels_ksp_type": "richardson",  # smoothers that need no eigenvalue estimate
    "mg_levels_pc_type": "sor",
}


def simp_contrast(n: int = 30, e_min: float = 1e-9) -> dict:
    """A clamped 2:1 plate (E = 1) with four void holes (E = 1e-9), SIMP penalty 3."""
    x, y = np.linspace(0.0, 2.0, 2 * n + 1), np.linspace(0.0, 1.0, n + 1)
    basis = skfem.Basis(skfem.MeshTri.init_tensor(x, y), skfem.ElementVector(skfem.ElementTriP1()))
    A = pp.elasticity_operator(basis)
    bc = pp.Dirichlet(A, basis.get_dofs(lambda x: np.isclose(x[0], 0.0)).all())
    cx, cy = basis.mesh.p[:, basis.mesh.t].mean(axis=1)  # element centroids
    density = np.ones(basis.mesh.nelements)
    for hx, hy, r in ((0.4, 0.5, 0.2), (0.9, 0.3, 0.15), (1.3, 0.7, 0.18), (1.7, 0.4, 0.15)):
        density[(cx - hx) ** 2 + (cy - hy) ** 2 < r**2] = 0.0
    theta = e_min + (1.0 - e_min) * density**3  # SIMP
    M = bc.A_II.matrix(theta)
    f = np.ones(M.shape[0])
    structure = pp.Structure(near_nullspace=pp.rigid_body_modes(basis, bc.interior), block_size=2)
    outcome = {}
    for name, options in (("default", GAMG), ("richardson_sor", ROBUST_GAMG)):
        with pp.KSPSolver(options, max_it=500, rtol=1e-8, structure=structure) as solver:
            solver.set_operator(M)
            try:
                sol = solver.solve(f)
                outcome[name] = (sol.reason, sol.iterations)
            except pp.SolverError as err:  # its message says after how many iterations
                outcome[name] = (err.reason, None)
    return outcome


# --8<-- [end:simp]

if __name__ == "__main__":
    for dim in (2, 3):
        print(f"{dim}D elasticity, GAMG iterations:", elasticity(dim))
    print("free body, undeclared:", free_body()["undeclared"])
    print("Stokes:", {k: v for k, v in stokes().items() if k != "grad"})
    print("SIMP contrast 1e-9:", simp_contrast())
