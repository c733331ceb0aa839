"""The device path with CUDA types and CUDA tensors: what tests/test_device.py checks with
host types, on the GPU.

Runs where torch sees a GPU and PETSc was built with CUDA (``.ci/device-run.sh``); skipped
everywhere else, with one reason.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from petsc4py import PETSc

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared problems
from _core import CONVERGED, interior_operator, randn, random_theta, unit_square  # noqa: E402

import prdp_petsc as pp  # noqa: E402
from prdp_petsc.errors import InputError, NonFiniteError, StructureError  # noqa: E402

pytestmark = pytest.mark.skipif(
    not (torch.cuda.is_available() and PETSc.Sys.hasExternalPackage("cuda")),
    reason="needs a GPU that torch sees and a PETSc built with CUDA",
)

CUDA_TYPES = {"vec_type": "cuda", "mat_type": "aijcusparse"}
METHODS = {
    "cg_jacobi": {"ksp_type": "cg", "pc_type": "jacobi"},
    "gmres_jacobi": {"ksp_type": "gmres", "pc_type": "jacobi"},
}
BATCH = 4


@pytest.fixture(scope="module")
def problems():
    square = unit_square(4)
    return {
        "cg_jacobi": interior_operator(square, "P0").A_II,
        "gmres_jacobi": interior_operator(square, "P0", advect=True).A_II,
    }


def run(A, solver, b, theta):
    b = b.detach().clone().requires_grad_(True)
    theta = theta.detach().clone().requires_grad_(True)
    x = pp.solve(A, b, solver, theta=theta)
    w = randn(*x.shape, seed=99).to(x.device)
    (x * w).sum().backward()
    return x.detach(), b.grad, theta.grad


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("cap", [{"max_it": 10}, CONVERGED])
@pytest.mark.parametrize("shape", ["single", "batched_b", "batched_theta"])
def test_cuda_path_equals_cpu_path(problems, method, cap, shape):
    A = problems[method]
    host = pp.KSPSolver(METHODS[method], **cap)
    device = pp.KSPSolver({**METHODS[method], **CUDA_TYPES}, **cap)
    assert device.vec_type == "cuda"
    n, p = A.shape[0], A.n_params
    b = randn(n, seed=1) if shape == "single" else randn(BATCH, n, seed=1)
    if shape == "batched_theta":
        theta = torch.stack([random_theta(p, seed=2 + i) for i in range(BATCH)])
    else:
        theta = random_theta(p, seed=2)
    expected = run(A, host, b, theta)
    got = run(A, device, b.cuda(), theta.cuda())
    assert device.mat.getType() == "seqaijcusparse"
    for e, g in zip(expected, got, strict=True):
        assert g.is_cuda and g.shape == e.shape
        assert (g.cpu() - e).abs().max().item() <= 1e-10 * e.abs().max().item()


def test_solution_is_written_into_torch_cuda_memory(problems):
    """The Vec PETSc solves into wraps x's CUDA memory (its device pointer is x's)."""
    A = problems["cg_jacobi"]
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **CUDA_TYPES}, max_it=5)
    solver.set_operator(A.matrix(random_theta(A.n_params).numpy()))
    b = randn(A.shape[0], seed=3).cuda()
    x = torch.empty_like(b)
    sol = solver.solve(b, out=x)
    assert sol.value is x and sol.iterations == 5
    vec = PETSc.Vec().createWithDLPack(x)
    handle = vec.getCUDAHandle("r")
    vec.restoreCUDAHandle(handle, "r")
    assert handle == x.data_ptr()
    vec.destroy()


def test_values_on_the_device_equal_a0_plus_G_theta(problems):
    A = problems["cg_jacobi"]
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **CUDA_TYPES}, max_it=3)
    theta = random_theta(A.n_params, seed=4)
    pp.solve(A, randn(A.shape[0], seed=5).cuda(), solver, theta=theta.cuda())
    _, _, data = solver.mat.getValuesCSR()  # a copy to the host, for the test only
    np.testing.assert_allclose(data, A.a0 + A.G @ theta.numpy(), rtol=1e-14)


def test_errors_on_the_device(problems):
    A = problems["cg_jacobi"]
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **CUDA_TYPES}, max_it=3)
    theta = random_theta(A.n_params).cuda()
    with pytest.raises(InputError, match="move it to the GPU"):
        pp.solve(A, randn(A.shape[0]), solver, theta=theta.cpu())
    b = randn(A.shape[0]).cuda()
    b[2] = float("nan")
    with pytest.raises(NonFiniteError):
        pp.solve(A, b, solver, theta=theta)
    host = pp.KSPSolver({**METHODS["cg_jacobi"], "vec_type": "standard"}, max_it=3)
    with pytest.raises(InputError, match="move it to the host"):
        pp.solve(A, randn(A.shape[0]).cuda(), host, theta=theta)
    B = problems["gmres_jacobi"]
    with pytest.raises(StructureError):
        pp.solve(B, randn(B.shape[0]).cuda(), solver, theta=random_theta(B.n_params).cuda())


def test_batch_of_sixteen_operators_trains_on_the_device(problems):
    """θ (16, p) on the GPU: a few Adam steps lower the loss, every tensor stays there."""
    A = problems["cg_jacobi"]
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **CUDA_TYPES}, max_it=20)
    target = torch.stack([random_theta(A.n_params, seed=10 + i) for i in range(16)]).cuda()
    b = randn(16, A.shape[0], seed=6).cuda()
    with torch.no_grad():
        x_ref = pp.solve(A, b, solver, theta=target)
    theta = torch.full_like(target, 1.5).requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=0.05)
    losses = []
    for _ in range(5):
        opt.zero_grad()
        loss = ((pp.solve(A, b, solver, theta=theta) - x_ref) ** 2).sum()
        loss.backward()
        assert theta.grad.is_cuda
        opt.step()
        with torch.no_grad():
            theta.clamp_(min=0.1)
        losses.append(loss.item())
    assert losses[-1] < losses[0]


def test_dirichlet_on_the_device():
    """Lifting by torch on the GPU (matvec with a CUDA θ) and the interior solve there."""
    D = interior_operator(unit_square(3), "P1")
    host = pp.KSPSolver(METHODS["cg_jacobi"], max_it=10)
    device = pp.KSPSolver({**METHODS["cg_jacobi"], **CUDA_TYPES}, max_it=10)
    results = []
    for solver, where in ((host, "cpu"), (device, "cuda")):
        f = randn(D.n, seed=23).to(where).requires_grad_(True)
        g = randn(len(D.boundary), seed=24).to(where).requires_grad_(True)
        theta = random_theta(D.A_II.n_params, seed=25).to(where).requires_grad_(True)
        u = D.solve(f, g, solver, theta=theta)
        (u * randn(D.n, seed=26).to(where)).sum().backward()
        results.append([t.detach().cpu() for t in (u, f.grad, g.grad, theta.grad)])
    for e, got in zip(*results, strict=True):
        assert (got - e).abs().max() <= 1e-10 * e.abs().max()
