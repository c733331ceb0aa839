"""A capped CG solve on an L-shaped mesh, differentiated by one transpose solve."""

import numpy as np
import torch
from skfem import Basis, ElementTriP1

import prdp_petsc as pp

mesh = pp.load_mesh("lshape")  # a shipped gmsh mesh
basis = Basis(mesh, ElementTriP1())  # scikit-fem stays scikit-fem
A = pp.diffusion_operator(basis, coefficient="P0")  # A(θ) = a0 + G θ, θ = κ per element
bc = pp.Dirichlet(A, basis.get_dofs())  # u = g on the boundary, by elimination

# CG + GAMG, capped at K = 20 iterations (rtol = atol = 0: exactly 20)
solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "gamg"}, prefix="fwd_", max_it=20)

theta = torch.ones(A.n_params, dtype=torch.float64, requires_grad=True)
f = torch.from_numpy(pp.mass_matrix(basis) @ np.ones(basis.N))  # load vector of f = 1
g = torch.zeros(len(bc.boundary), dtype=torch.float64, requires_grad=True)

sol = bc.solve(f, g, solver, theta=theta, return_solution=True)  # KSPSolve
u = sol.value  # the full vector, u = g on the boundary
loss = u.square().sum()
loss.backward()  # one KSPSolveTranspose: ∂L/∂θ and ∂L/∂g

print(sol.iterations, sol.reason, sol.residual_norm)  # this call's outcome, kept with u
print(sol.adjoint.iterations)  # and its transpose solve's, once backward has run
print(solver.stats)  # solves, iterations and seconds, forward and adjoint
print(f"|dL/dθ| = {theta.grad.norm():.3e}, |dL/dg| = {g.grad.norm():.3e}")

solver.max_it = 40  # the next solve: another cap, the same preconditioner
solver.destroy()
