"""The device path on the CPU: a solver whose options name vec_type/mat_type solves in
torch's memory (DLPack), computes a ParametricMatrix's values and θ-gradient with torch,
and gives what the default (numpy) path gives.

The same code runs with CUDA types and CUDA tensors (tests/gpu/); here host types
(``vec_type standard``, ``mat_type aij``) drive every line of it except the CUDA
types themselves.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from _core import CONVERGED, interior_operator, randn, random_theta, unit_square
from petsc4py import PETSc

import prdp_petsc as pp
from prdp_petsc.core.device import DeviceTypes, wrap
from prdp_petsc.core.operator import DeviceCSR, DLPackCSR
from prdp_petsc.errors import InputError, NonFiniteError, SolverError, StructureError

HOST_TYPES = {"vec_type": "standard", "mat_type": "aij"}
METHODS = {
    "cg_jacobi": {"ksp_type": "cg", "pc_type": "jacobi"},
    "gmres_ilu": {"ksp_type": "gmres", "pc_type": "ilu"},
}
CAPS = {"capped": {"max_it": 5}, "converged": CONVERGED}
BATCH = 3


@pytest.fixture(scope="module")
def symmetric():
    return interior_operator(unit_square(3), "P0").A_II


@pytest.fixture(scope="module")
def advective():
    return interior_operator(unit_square(3), "P0", advect=True).A_II


def pair(options, **kw):
    """The default-path solver and its device-path twin (host types)."""
    return pp.KSPSolver(options, **kw), pp.KSPSolver({**options, **HOST_TYPES}, **kw)


def run(A, solver, b, theta):
    """x, ∂L/∂b, ∂L/∂θ of L = Σ w ⊙ x (a fixed random w)."""
    b = b.detach().clone().requires_grad_(True)
    theta = theta.detach().clone().requires_grad_(True)
    x = pp.solve(A, b, solver, theta=theta)
    w = randn(*x.shape, seed=99)
    (x * w).sum().backward()
    return x.detach(), b.grad, theta.grad


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("cap", CAPS)
@pytest.mark.parametrize("shape", ["single", "batched_b", "batched_theta"])
def test_device_path_equals_default_path(symmetric, advective, method, cap, shape):
    A = symmetric if method == "cg_jacobi" else advective
    default, device = pair(METHODS[method], **CAPS[cap])
    assert default.vec_type is None and device.vec_type == "standard"
    n, p = A.shape[0], A.n_params
    b = randn(n, seed=1) if shape == "single" else randn(BATCH, n, seed=1)
    if shape == "batched_theta":
        theta = torch.stack([random_theta(p, seed=2 + i) for i in range(BATCH)])
    else:
        theta = random_theta(p, seed=2)
    expected = run(A, default, b, theta)
    got = run(A, device, b, theta)
    for e, g in zip(expected, got, strict=True):
        assert g.shape == e.shape
        scale = e.abs().max().item()
        assert (g - e).abs().max().item() <= 1e-12 * scale
    assert device.stats.forward_iterations == default.stats.forward_iterations
    assert device.stats.adjoint_iterations == default.stats.adjoint_iterations
    assert type(device._op) is DeviceCSR and device.mat.getType() == "seqaij"


def test_scipy_operator_and_outcome(symmetric):
    """A constant scipy A on the device path: same x, the same outcome record."""
    M = symmetric.matrix(random_theta(symmetric.n_params, seed=3).numpy())
    default, device = pair(METHODS["cg_jacobi"], max_it=6)
    b = randn(BATCH, M.shape[0], seed=4, requires_grad=True)
    ref = pp.solve(M, b, default, return_solution=True)
    sol = pp.solve(M, b, device, return_solution=True)
    np.testing.assert_allclose(sol.value.detach().numpy(), ref.value.detach().numpy(), rtol=1e-13)
    assert list(sol.iterations) == list(ref.iterations) == [6] * BATCH
    assert sol.reason == ref.reason
    np.testing.assert_allclose(sol.residual_norm, ref.residual_norm, rtol=1e-12)
    sol.value.sum().backward()
    assert sol.adjoint is not None and list(sol.adjoint.iterations) == [6] * BATCH


def test_no_copy_of_b_or_x(symmetric, monkeypatch):
    """PETSc's Vec arrays are the tensors' memory: b is read and x written in place."""
    from prdp_petsc.core.step import SolveStep

    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=4)
    A = symmetric.matrix(random_theta(symmetric.n_params).numpy())
    solver.set_operator(A)
    b = randn(BATCH, A.shape[0], seed=5)
    x = torch.full_like(b, np.nan)
    seen = []
    original = SolveStep.solve_vecs

    def spy(step, bv, xv):
        seen.append((bv.getArray(readonly=True).ctypes.data, xv.getArray().ctypes.data))
        return original(step, bv, xv)

    monkeypatch.setattr(SolveStep, "solve_vecs", spy)
    sol = solver.solve(list(b.unbind(0)), out=list(x.unbind(0)))
    row = b.shape[1] * b.element_size()
    assert seen == [(b.data_ptr() + i * row, x.data_ptr() + i * row) for i in range(BATCH)]
    ref = pp.KSPSolver(METHODS["cg_jacobi"], max_it=4)
    ref.set_operator(A)
    np.testing.assert_array_equal(x.numpy(), ref.solve(b.numpy()).value)
    assert list(sol.iterations) == [4] * BATCH


def test_bridge_returns_torch_memory_handed_to_petsc(symmetric, monkeypatch):
    """pp.solve allocates x with torch and PETSc writes into it (the Vec's array is x's)."""
    from prdp_petsc.core import device

    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=3)
    wrapped = []
    real = device.wrap

    def spy(array, size, name, memory):
        vec = real(array, size, name, memory)
        wrapped.append((name, vec.getArray(readonly=True).ctypes.data))
        return vec

    monkeypatch.setattr(device, "wrap", spy)
    b = randn(symmetric.shape[0], seed=6)
    x = pp.solve(symmetric, b, solver, theta=random_theta(symmetric.n_params))
    pointers = dict(wrapped)
    assert pointers["the right-hand side (a batch is a sequence of rows)"] == b.data_ptr()
    assert pointers["out (right-hand side)"] == x.data_ptr()


def test_values_set_by_coo_equal_a0_plus_G_theta(symmetric):
    """MatSetValuesCOO from the values' own memory: the Mat is a0 + G θ, for each new θ."""
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=3)
    P = symmetric
    for seed in (0, 1):
        theta = random_theta(P.n_params, seed=seed)
        values = torch.as_tensor(P.values(theta.numpy()).copy())
        solver.set_operator(DLPackCSR(P.indptr, P.indices, values, P.shape))
        indptr, indices, data = solver.mat.getValuesCSR()
        np.testing.assert_array_equal(indptr, P.indptr)
        np.testing.assert_array_equal(indices, P.indices)
        np.testing.assert_allclose(data, P.a0 + P.G @ theta.numpy(), rtol=1e-15)
    version = solver.operator_version
    solver.set_operator(DLPackCSR(P.indptr, P.indices, values, P.shape))  # the same values
    assert solver.operator_version == version


def test_unchanged_theta_sets_no_new_values(symmetric):
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=3)
    theta = random_theta(symmetric.n_params)
    b = randn(symmetric.shape[0], seed=7)
    pp.solve(symmetric, b, solver, theta=theta)
    version = solver.operator_version
    pp.solve(symmetric, b, solver, theta=theta.clone())
    assert solver.operator_version == version
    pp.solve(symmetric, b, solver, theta=theta * 1.5)
    assert solver.operator_version > version


def test_backward_uses_the_forward_operator(symmetric):
    """Another solve in between (another θ) does not change the first one's gradient."""
    default, device = pair(METHODS["cg_jacobi"], **CONVERGED)
    n, p = symmetric.shape[0], symmetric.n_params
    grads = []
    for solver in (default, device):
        t1 = random_theta(p, seed=8).requires_grad_(True)
        x1 = pp.solve(symmetric, randn(n, seed=9), solver, theta=t1)
        pp.solve(symmetric, randn(n, seed=10), solver, theta=random_theta(p, seed=11))
        x1.sum().backward()
        grads.append(t1.grad)
    assert (grads[0] - grads[1]).abs().max() <= 1e-12 * grads[0].abs().max()


def test_initial_guess_on_the_device_path(symmetric):
    default, device = pair(METHODS["cg_jacobi"], max_it=4)
    n, p = symmetric.shape[0], symmetric.n_params
    out = []
    for solver in (default, device):
        theta = random_theta(p, seed=12).requires_grad_(True)
        x0 = randn(n, seed=13, requires_grad=True)
        x = pp.solve(symmetric, randn(n, seed=14), solver, theta=theta, x0=x0)
        (x * randn(n, seed=15)).sum().backward()
        out.append((x.detach(), theta.grad, x0.grad))
    for e, g in zip(*out, strict=True):
        assert (g - e).abs().max() <= 1e-12 * e.abs().max()


def test_nan_in_b_and_cotangent_refused(symmetric):
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=3)
    theta = random_theta(symmetric.n_params)
    b = randn(BATCH, symmetric.shape[0], seed=16)
    b[1, 4] = float("nan")
    with pytest.raises(NonFiniteError, match=r"right-hand side contains NaN or Inf \(rows \[1\]"):
        pp.solve(symmetric, b, solver, theta=theta)
    b = randn(symmetric.shape[0], seed=16, requires_grad=True)
    x = pp.solve(symmetric, b, solver, theta=theta)
    with pytest.raises(NonFiniteError, match="cotangent"):
        (x * float("inf")).sum().backward()
    bad = theta.clone()
    bad[0] = float("nan")
    with pytest.raises(NonFiniteError, match="theta"):
        pp.solve(symmetric, b, solver, theta=bad)
    with pytest.raises(InputError, match="> 0"):
        pp.solve(symmetric, b, solver, theta=-theta)


def test_huge_right_hand_side_is_scaled_not_overflowed(symmetric):
    """Entries beyond 2^100: scaled in a work Vec (b itself untouched), x scaled back."""
    default, device = pair(METHODS["cg_jacobi"], max_it=5)
    theta = random_theta(symmetric.n_params)
    b = randn(symmetric.shape[0], seed=17) * 1e300
    kept = b.clone()
    x = pp.solve(symmetric, b, device, theta=theta)
    assert torch.equal(b, kept)
    ref = pp.solve(symmetric, b, default, theta=theta)
    assert torch.isfinite(x).all()
    assert ((x - ref).abs().max() / ref.abs().max()).item() <= 1e-13


def test_divergence_is_named(symmetric):
    """An indefinite operator under CG: the same named SolverError as the default path."""
    M = -symmetric.matrix(random_theta(symmetric.n_params).numpy())
    M = M + sp.diags(np.where(np.arange(M.shape[0]) % 2, 3.0, 0.0) * 2 * abs(M).max())
    b = randn(M.shape[0], seed=18)
    reasons = []
    for solver in pair(
        METHODS["cg_jacobi"], max_it=200, rtol=1e-10, structure=pp.Structure(symmetric=True)
    ):
        with pytest.raises(SolverError) as err:
            pp.solve(M.tocsr(), b, solver)
        reasons.append(err.value.reason)
    assert reasons[0] == reasons[1]


def test_cg_on_a_non_symmetric_operator_is_refused(advective):
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=5)
    theta = random_theta(advective.n_params)
    with pytest.raises(StructureError):
        pp.solve(advective, randn(advective.shape[0], seed=19), solver, theta=theta)


def test_declared_structure_is_on_the_device_mat():
    """Null space and block size declared once reach the Mat made by COO assembly."""
    basis = unit_square(3)
    P = pp.diffusion_operator(basis, "P0")  # Neumann: singular, constants in the kernel
    theta = random_theta(P.n_params, seed=20)
    options = {**METHODS["cg_jacobi"], **HOST_TYPES}
    structure = pp.Structure(nullspace="constant", near_nullspace="constant")
    solver = pp.KSPSolver(options, max_it=500, rtol=1e-12, structure=structure)
    b = randn(P.shape[0], seed=21)
    b = b - b.mean()
    x = pp.solve(P, b, solver, theta=theta)
    assert type(solver._op) is DeviceCSR
    assert solver.mat.getNullSpace() is not None and solver.mat.getNearNullSpace() is not None
    assert abs(x.mean().item()) < 1e-12
    ref = pp.KSPSolver(METHODS["cg_jacobi"], max_it=500, rtol=1e-12, structure=structure)
    np.testing.assert_allclose(x.numpy(), pp.solve(P, b, ref, theta=theta).numpy(), atol=1e-12)
    blocked = pp.KSPSolver(options, max_it=3, structure=pp.Structure(block_size=2))
    M = sp.kron(sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(6, 6)), sp.eye(2)).tocsr()
    M.sort_indices()
    blocked.set_operator(DLPackCSR(M.indptr, M.indices, torch.as_tensor(M.data), M.shape))
    assert blocked.mat.getBlockSize() == 2 and blocked.mat.getType() == "seqaij"
    x = torch.empty(12, dtype=torch.float64)
    blocked.solve(torch.ones(12, dtype=torch.float64), out=x)
    reference = pp.KSPSolver(METHODS["cg_jacobi"], max_it=3)
    reference.set_operator(M)
    np.testing.assert_array_equal(x.numpy(), reference.solve(np.ones(12)).value)


def test_types_from_the_command_line(symmetric):
    """-<prefix>vec_type on the command line chooses the path, PETSc's way."""
    opts = PETSc.Options()
    opts.setValue("devcl_vec_type", "standard")
    try:
        solver = pp.KSPSolver(METHODS["cg_jacobi"], prefix="devcl_", max_it=3)
    finally:
        opts.delValue("devcl_vec_type")
    assert solver.vec_type == "standard"
    assert DeviceTypes.resolve("standard", None).mat_type == "aij"
    assert DeviceTypes.resolve(None, "aij").vec_type == "standard"


def test_wrong_memory_and_types_are_input_errors(symmetric):
    with pytest.raises(InputError, match="one memory"):
        DeviceTypes.resolve("standard", "aijcusparse")
    with pytest.raises(InputError, match="device path takes"):
        pp.KSPSolver({"vec_type": "kokkos"}, max_it=3)
    with pytest.raises(InputError, match="adjoint"):
        pp.KSPSolver(HOST_TYPES, max_it=3, adjoint=pp.AdjointSettings(options={"vec_type": "seq"}))
    if not PETSc.Sys.hasExternalPackage("cuda"):
        with pytest.raises(InputError, match="PETSc built with CUDA"):
            pp.KSPSolver({"vec_type": "cuda", "mat_type": "aijcusparse"}, max_it=3)
    with pytest.raises(InputError, match="move it to the GPU"):
        wrap(torch.zeros(3, dtype=torch.float64), 3, "b", "cuda")
    with pytest.raises(InputError, match="C-contiguous"):
        wrap(torch.zeros(4, 3, dtype=torch.float64)[:, 0], 4, "b", "cpu")
    solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=3)
    solver.set_operator(symmetric.matrix(random_theta(symmetric.n_params).numpy()))
    with pytest.raises(InputError, match="out="):
        solver.solve(torch.zeros(symmetric.shape[0], dtype=torch.float64))
    with pytest.raises(InputError, match="mode='unrolled'"):
        pp.solve(
            symmetric,
            randn(symmetric.shape[0]),
            solver,
            theta=random_theta(symmetric.n_params),
            mode="unrolled",
        )


def test_default_path_unchanged_types(symmetric):
    """No types named: numpy in, numpy out, the Mat PETSc's default AIJ."""
    solver = pp.KSPSolver(METHODS["cg_jacobi"], max_it=3)
    solver.set_operator(symmetric.matrix(random_theta(symmetric.n_params).numpy()))
    assert isinstance(solver.solve(np.ones(symmetric.shape[0])).value, np.ndarray)
    with pytest.raises(InputError, match="out="):
        solver.solve(np.ones(symmetric.shape[0]), out=np.empty(symmetric.shape[0]))


def test_numpy_on_host_types_and_the_k_full_probe(symmetric):
    """numpy rows on host types return a new array, so find_k_full probes such a solver."""
    M = symmetric.matrix(random_theta(symmetric.n_params).numpy())
    default, device = pair(METHODS["cg_jacobi"], max_it=30)
    b = randn(BATCH, M.shape[0], seed=22).numpy()
    for solver in (default, device):
        solver.set_operator(M)
    np.testing.assert_array_equal(device.solve(b).value, default.solve(b).value)
    np.testing.assert_array_equal(device.solve(b[0]).value, default.solve(b[0]).value)
    k = [pp.find_k_full(M, b[:1], solver, rtol=1e-8) for solver in (default, device)]
    assert k[0] == k[1] > 0


def test_wrapped_vec_norms_are_computed_not_cached_zeros():
    """PETSc's norm cache on a Vec of state 0 would answer ‖v‖_∞ = 0 after ‖v‖₂."""
    v = wrap(torch.tensor([1.0, -5.0, 2.0], dtype=torch.float64), 3, "v", "cpu")
    assert v.norm() == pytest.approx(30**0.5)
    assert v.norm(PETSc.NormType.INFINITY) == 5.0
    assert v.norm(PETSc.NormType.NORM_1) == 8.0


def test_dirichlet_solve_on_the_device_path():
    """Lifting (A_IB g, by the bridge's matvec) then the interior solve on the device path."""
    D = interior_operator(unit_square(3), "P1")
    default, device = pair(METHODS["cg_jacobi"], max_it=8)
    results = []
    for solver in (default, device):
        f = randn(D.n, seed=23, requires_grad=True)
        g = randn(len(D.boundary), seed=24, requires_grad=True)
        theta = random_theta(D.A_II.n_params, seed=25).requires_grad_(True)
        u = D.solve(f, g, solver, theta=theta)
        (u * randn(D.n, seed=26)).sum().backward()
        results.append((u.detach(), f.grad, g.grad, theta.grad))
    for e, got in zip(*results, strict=True):
        assert (got - e).abs().max() <= 1e-12 * e.abs().max()


def test_device_matvec_equals_the_host_product():
    """A(θ) v by torch (what a GPU θ uses, here on the CPU) equals the bridge's matvec, and
    so do its gradients in v and θ, single and per-sample θ."""
    from prdp_petsc.autograd.bridge import matvec
    from prdp_petsc.autograd.device import device_matvec

    A = interior_operator(unit_square(2), "P1").A_IB  # rectangular
    for theta in (
        random_theta(A.n_params, seed=27),
        torch.stack([random_theta(A.n_params, seed=28 + i) for i in range(BATCH)]),
    ):
        results = []
        for product in (matvec, lambda A, v, theta: device_matvec(A, v, theta)):
            t = theta.clone().requires_grad_(True)
            v = randn(BATCH, A.shape[1], seed=31, requires_grad=True)
            y = product(A, v, theta=t)
            (y * randn(BATCH, A.shape[0], seed=32)).sum().backward()
            results.append((y.detach(), v.grad, t.grad))
        for e, got in zip(*results, strict=True):
            assert (got - e).abs().max() <= 1e-13 * e.abs().max()


def test_operator_norm_from_the_values_equals_petscs(symmetric, advective):
    """`DeviceCSR.norm` (a product with a 0/1 summing matrix, where the values live) is
    PETSc's max(‖A‖₁, ‖A‖_∞) of the Mat, for each new set of values."""
    from prdp_petsc.core.safeguards import operator_norm

    for P in (symmetric, advective):  # an unsymmetric one: ‖A‖₁ ≠ ‖A‖_∞
        layout = DeviceCSR(types=DeviceTypes.resolve("standard", "aij"))
        for seed in (0, 1):
            theta = random_theta(P.n_params, seed=seed).numpy()
            values = torch.as_tensor(P.values(theta).copy())
            layout.update(DLPackCSR(P.indptr, P.indices, values, P.shape), None)
            A = abs(P.matrix(theta))
            expected = max(A.sum(axis=0).max(), A.sum(axis=1).max())
            assert layout.norm() == pytest.approx(expected, rel=1e-14)
            assert layout.norm() == pytest.approx(operator_norm(layout.mat), rel=1e-14)
        layout.destroy()


@pytest.mark.parametrize(
    "entries, expected",
    [([1.0, -2.0, 3.0], False), ([1.0, np.nan, 3.0], True), ([1.0, -np.inf, 3.0], True),
     ([1e308, 1e308, -1e308], False), ([1e308, np.nan, 1e308], True)],
)  # fmt: skip
def test_nonfinite_sees_nan_and_inf_not_overflow(entries, expected):
    from prdp_petsc.core.device import nonfinite

    vec = wrap(torch.tensor(entries, dtype=torch.float64), len(entries), "v", "cpu")
    assert nonfinite(vec) is expected
    vec.destroy()


def test_constant_operator_with_values_in_the_solvers_memory(symmetric):
    """A DLPackCSR A: the scipy route's x and gradient, and an unchanged values tensor
    sets nothing on later calls (no comparison of values)."""
    P = symmetric
    csr = P.matrix(random_theta(P.n_params, seed=3).numpy()).tocsr()
    values = torch.as_tensor(csr.data.copy())
    A = DLPackCSR(csr.indptr, csr.indices, values, csr.shape)
    b = randn(BATCH, csr.shape[0], seed=8)
    results = []
    for operator in (csr, A):
        solver = pp.KSPSolver({**METHODS["cg_jacobi"], **HOST_TYPES}, max_it=7)
        bb = b.clone().requires_grad_(True)
        x = pp.solve(operator, bb, solver)
        (x * randn(*x.shape, seed=9)).sum().backward()
        results.append((x.detach(), bb.grad))
    torch.testing.assert_close(results[1], results[0], rtol=1e-13, atol=0)
    version = solver.operator_version
    pp.solve(A, b, solver)
    assert solver.operator_version == version
    pp.solve(DLPackCSR(csr.indptr, csr.indices, 2 * values, csr.shape), b, solver)
    assert solver.operator_version > version
    with pytest.raises(InputError, match="theta"):
        pp.solve(A, b, solver, theta=random_theta(P.n_params))


def test_a_solution_that_overflows_unseen_by_petsc_is_refused(symmetric):
    """Richardson scaled past overflow without a norm: PETSc reports the cap, and only the
    finiteness test of the solution rows finds the Inf."""
    options = {"ksp_type": "richardson", "ksp_richardson_scale": 1e300, "pc_type": "none",
               "ksp_norm_type": "none", **HOST_TYPES}  # fmt: skip
    solver = pp.KSPSolver(options, max_it=4)
    theta = random_theta(symmetric.n_params)
    with pytest.raises(SolverError, match="NaN/Inf"):
        pp.solve(symmetric, randn(symmetric.shape[0], seed=21), solver, theta=theta)
