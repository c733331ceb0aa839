"""PRDP in your own training loop: the default construction and a certified end.

A network maps observations of u to the log-conductivity κ of −∇·(κ∇u) = 1 on the
L-shaped mesh (one operator per sample), trained through CG + Jacobi capped at K.
The controller takes its start, step and cap from K_full and certifies every stop
with the validation gradient at K against the one at K_full.
"""

import numpy as np
import torch
from skfem import Basis, ElementTriP1, LinearForm

import prdp_petsc as pp

torch.manual_seed(0)
rng = np.random.default_rng(0)
mesh = pp.load_mesh("lshape")
basis = Basis(mesh, ElementTriP1())
bc = pp.Dirichlet(pp.diffusion_operator(basis, "P0"), basis.get_dofs().all())
b = torch.from_numpy(LinearForm(lambda v, w: v).assemble(basis)[bc.interior])
centres = mesh.p[:, mesh.t].mean(axis=1)
modes = torch.from_numpy(np.stack([np.cos(np.pi * centres[0]), np.cos(np.pi * centres[1])], 1))

solver = pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, prefix="loop_", max_it=1)


def physics(coef):  # (B, 2) -> u (B, n) through the capped solve
    theta = torch.exp(coef @ modes.T)
    return pp.solve(bc.A_II, b.expand(len(coef), -1), solver, theta=theta)


coef = torch.from_numpy(rng.normal(0.0, 0.5, (40, 2)))
with torch.no_grad():
    solver.max_it = 1000
    solver.rtol = 1e-10
    obs = physics(coef)
    solver.rtol = 0.0
train_obs, val_obs = obs[10:], obs[:10]
net = torch.nn.Sequential(torch.nn.Linear(obs.shape[1], 32), torch.nn.Tanh(),
                          torch.nn.Linear(32, 2)).double()  # fmt: skip
opt = torch.optim.Adam(net.parameters(), lr=1e-2)


def loss_fn(pred_obs, target):
    return torch.mean((pred_obs - target) ** 2) / torch.mean(target**2)


def val_loss():
    """The validation loss through the capped solve: what the check differentiates."""
    return loss_fn(physics(net(val_obs)), val_obs)


# the check: the validation gradient through the solve capped at k (no training step)
check = pp.gradient_check(val_loss, net.parameters(), solver)
k_full = pp.find_k_full(bc.A_II, b, solver, theta=np.ones(mesh.t.shape[1]))
prdp = pp.PRDP.for_problem(k_full, check=check, epochs=40)  # the run's length
for _epoch in range(40):
    solver.max_it = prdp.k
    opt.zero_grad()
    loss_fn(physics(net(train_obs)), train_obs).backward()
    opt.step()
    with torch.no_grad():
        metric = float(torch.linalg.norm(net(val_obs) - coef[:10]) / torch.linalg.norm(coef[:10]))
    prdp.update(metric)
certificate = prdp.certify()
# iterations saved, the checks' included as they measured themselves (a check is one
# gradient on the 10 validation samples, a third of an epoch's 30 training samples)
savings = prdp.savings()
print(certificate.describe())
print({k: round(v, 3) if isinstance(v, float) else v for k, v in savings.items()})
