"""`prdp-petsc bench bridge`: the JSON holds every figure, and the relations between them hold.

Timings are never compared with targets or with each other here (they describe a
machine, not the code).  What is asserted: the bridge and the raw petsc4py baseline
run the same K iterations forward and backward and compute the same numbers (so the
timings compare like with like), the hand-written CG is mode="unrolled"'s iteration,
and the peak-memory relation that motivates implicit gradients: unrolling keeps at
least one vector per iteration, the implicit gradient's peak does not grow with K.
"""

import json
import re

import numpy as np
import pytest
import torch

import prdp_petsc as pp
from prdp_petsc.lab.reports.bench import handwritten_unrolled_cg, main
from prdp_petsc.lab.reports.benchmarking import bench_solver, raw_ksp
from prdp_petsc.lab.reports.problems import five_point, plate_reaction

#: unrolled comparison: 100 × 100 grid, peak memory at K/3 = 15 and K = 45
UNROLLED_N, UNROLLED_K = 10_000, 45


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    argv = ["bridge", "--n", "4851", "--k", "10", "--repeats", "3", "--unrolled-n",
            str(UNROLLED_N), "--unrolled-k", str(UNROLLED_K), "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    return json.loads((out / "bench_bridge.json").read_text())


def test_bench_bridge_writes_every_figure(data):
    assert data["n"] == 4851 and data["k"] == 10 and data["unrolled_n"] == UNROLLED_N
    assert data["settings"]["rtol"] == data["settings"]["atol"] == 0.0  # fixed mode
    over = data["overhead_detail"]
    assert over["ksp"]["raw"] == over["ksp"]["bridge"] == ["cg", "jacobi"]
    for key, values in over["timings_s"].items():
        assert len(values) == data["settings"]["repeats"], key
    assert set(data["throughput_detail"]["batches"]) == {"1", "32"}
    for key in ("platform", "cpu_count", "versions"):
        assert data["machine"][key]


def test_unrolled_memory_grows_with_k_and_implicit_does_not(data):
    """Measured twice on this project's machine: unrolled 8.5 → 18.5-19.0 MiB from K = 15
    to 45 (0.34 MiB, 4.5 vectors of 10 000 doubles, per iteration), hand-written CG
    7.2-7.3 → 18.1-18.3 MiB, implicit 0.4-0.5 MiB at both K."""
    peak = data["unrolled_detail"]["peak_rss_increase_mb"]
    k_lo, k_hi = str(UNROLLED_K // 3), str(UNROLLED_K)
    vector_mb = 8 * data["unrolled_n"] / 2**20
    extra = UNROLLED_K - UNROLLED_K // 3
    growth = {mode: peak[mode][k_hi] - peak[mode][k_lo] for mode in peak}
    # the backward of an unrolled loop needs every iterate's p (at least one vector each)
    assert growth["unrolled"] >= extra * vector_mb
    assert growth["handwritten"] >= extra * vector_mb
    # the implicit gradient runs one adjoint solve: its peak is independent of K
    assert abs(growth["implicit"]) < 0.1 * growth["unrolled"]
    assert peak["unrolled"][k_hi] - peak["implicit"][k_hi] >= UNROLLED_K * vector_mb
    # the same iteration gives the same gradient
    assert data["unrolled_detail"]["handwritten_grad_rel_diff"] < 1e-10


def test_bridge_and_raw_ksp_run_the_same_iterations_and_numbers():
    """Backward runs as many iterations as the forward at equal K, and the raw KSP the
    bench times against returns the bridge's x and λ."""
    k = 10
    A, theta_np, b_np, g_np, _ = plate_reaction(4851)
    solver = bench_solver("cg", "jacobi", k)
    theta = torch.tensor(theta_np, requires_grad=True)
    b = torch.tensor(b_np, requires_grad=True)
    x = pp.solve(A, b, solver, theta=theta)
    x.backward(torch.tensor(g_np))
    stats = solver.stats
    assert stats.forward_solves == stats.adjoint_solves == 1
    assert stats.forward_iterations == stats.adjoint_iterations == k
    raw = raw_ksp(solver.mat, "cg", "jacobi", k)
    out, rhs = solver.mat.createVecs()
    for given, expected in ((b_np, x.detach().numpy()), (g_np, b.grad.numpy())):
        rhs.array[:] = given
        out.set(0.0)
        raw.solve(rhs, out)
        assert raw.getIterationNumber() == k
        np.testing.assert_allclose(out.array, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    raw.destroy()
    solver.destroy()


def test_unrolled_modes_run_petsc_cg_iterates():
    """mode="implicit", mode="unrolled" and the hand-written CG reach the same x_K;
    unrolled and hand-written differentiate the same map, so their gradients agree, and
    differ from the implicit (capped-adjoint) one before convergence."""
    A, b_np, g_np = five_point(20)
    k = 12
    xs, grads = {}, {}
    for mode in ("implicit", "unrolled", "handwritten"):
        b = torch.tensor(b_np, requires_grad=True)
        if mode == "handwritten":
            x = handwritten_unrolled_cg(A, b, k)
        else:
            x = pp.solve(A, b, bench_solver("cg", "jacobi", k), mode=mode)
        x.backward(torch.tensor(g_np))
        xs[mode], grads[mode] = x.detach().numpy(), b.grad.numpy()
    scale = np.abs(xs["implicit"]).max()
    for mode in ("unrolled", "handwritten"):
        assert np.abs(xs[mode] - xs["implicit"]).max() < 1e-10 * scale
    g_scale = np.abs(grads["unrolled"]).max()
    assert np.abs(grads["handwritten"] - grads["unrolled"]).max() < 1e-10 * g_scale
    assert np.abs(grads["implicit"] - grads["unrolled"]).max() > 1e-3 * g_scale


@pytest.mark.parametrize("flag", ["--k", "--n", "--repeats", "--unrolled-k"])
def test_bench_rejects_non_positive_sizes(tmp_path, flag):
    with pytest.raises(SystemExit):
        main(["bridge", flag, "0", "--out", str(tmp_path)])
    assert not (tmp_path / "bench_bridge.json").exists()


def _owned_record():
    """An owned-layout ``bench mpi`` record at N = 1000 with memory = 200 MB + 0.1 MB
    × N/P on every rank but rank 0 (which also held the mesh) and halos ∝ (N/P)^(2/3)."""
    solve = {}
    for p in (1, 2, 4):
        share = 1000 / p
        peaks = [200 + 0.1 * share] * p
        peaks[0] += 30 if p > 1 else 0
        ghosts = [0] * p if p == 1 else [round(3 * share ** (2 / 3))] * p
        solve[str(p)] = {
            "layout": "owned", "unknowns": 1000, "k": 20, "forward_s": 1.0 / p,
            "backward_s": 2.0 / p, "speedup_forward": float(p), "speedup_backward": float(p),
            "rows_per_rank": [1000 // p] * p, "petsc_mat_mb_per_rank": [1.0] * p,
            "owned_arrays_mb_per_rank": [2.0] * p, "peak_rss_mb_per_rank": peaks,
            "ghost_vertices_per_rank": ghosts,
        }  # fmt: skip
    return {"layout": "owned", "mesh": "cube 10", "solve": solve, "epoch": {}}


def test_the_mpi_scaling_model_recovers_the_law_it_was_fitted_to():
    from prdp_petsc.lab.reports.bench_mpi import format_scaling_model, scaling_model

    model = scaling_model(_owned_record())
    assert model["base_mb"] == pytest.approx(200, abs=1e-6)
    assert model["mb_per_unknown"] == pytest.approx(0.1)
    assert model["halo_coefficient"] == pytest.approx(3, rel=1e-2)
    assert model["rank0_mb"] == pytest.approx(30)
    row = model["rows"]["1024"]
    assert row["peak_mb_per_rank"] == pytest.approx(200 + 0.1 * 1000 / 1024)
    assert row["halo_kb_per_iteration"] == pytest.approx(
        8 * 3 * (1000 / 1024) ** (2 / 3) / 1024, rel=1e-2
    )
    assert row["weak_unknowns"] == 1024 * 1000
    assert "Model (not measured)" in format_scaling_model(model)
    replicated = _owned_record()
    for r in replicated["solve"].values():
        r["layout"] = "replicated"
    assert scaling_model(replicated) is None


@pytest.mark.parametrize(
    ("argv", "scene", "preset"),
    [
        ([], "demos/heat.py", "paper3d"),
        (["--preset", "quick"], "demos/heat.py", "quick3d"),
        (["--preset", "paper"], "demos/heat.py", "paper3d"),
        (["--preset", "quick3d"], "demos/heat.py", "quick3d"),
        (["demos/heat.py", "--preset", "paper"], "demos/heat.py", "paper"),  # the L-shape
        (["demos/ns2d.py", "--preset", "quick"], "demos/ns2d.py", "quick"),
    ],
)
def test_bench_mpi_trains_the_cube_unless_told_another_scene(argv, scene, preset):
    """Its epoch benchmark is the cube's (demos/heat3d.py's, now demos/heat.py's quick3d
    and paper3d) for the report tools' --preset quick|paper, not heat.py's L-shape."""
    from prdp_petsc.lab.reports.bench_mpi import _parser, epoch_scene

    args = _parser().parse_args([*argv, "--out", "o"])
    assert epoch_scene(args.scene, args.preset) == (scene, preset)


def test_a_bench_mpi_record_gets_a_page_with_the_model(tmp_path):
    from prdp_petsc.lab.reports import pages

    folder = tmp_path / "data" / "bench_mpi_cube10"
    folder.mkdir(parents=True)
    (folder / "bench_mpi.json").write_text(json.dumps(_owned_record()))
    (folder / "provenance.json").write_text(json.dumps({"command": ["prdp-petsc"]}))
    (ds,) = pages.load_data(tmp_path / "data", tmp_path / "images")
    assert ds.kind.name == "bench-mpi"
    ((what, figure),) = ds.kind.headline(ds)
    assert "2 ranks against 1" in what and "backward 2.00×" in figure
    assert "0.93×" in figure  # the largest rank, rank 0: (200 + 50 + 30) / 300


def test_child_env_drops_the_mpi_runtime_of_this_process(monkeypatch):
    """After MPI_Init as a singleton, Open MPI's runtime variables are in os.environ; an
    mpiexec started with them fails (a recorded `bench mpi` did), so children lose them."""
    from prdp_petsc.lab.subprocesses import child_env

    for key in ("PMIX_RANK", "PMIX_SERVER_URI4", "OMPI_MCA_ess", "OMPI_MCA_orte_launch"):
        monkeypatch.setenv(key, "1")
    monkeypatch.setenv("OMPI_MCA_rmaps_base_oversubscribe", "1")
    env = child_env({"OMP_NUM_THREADS": "1"})
    assert not any(
        k.startswith("PMIX_") or k in ("OMPI_MCA_ess", "OMPI_MCA_orte_launch") for k in env
    )
    assert env["OMPI_MCA_rmaps_base_oversubscribe"] == "1" and env["OMP_NUM_THREADS"] == "1"


def test_bench_elasticity_records_every_declaration(tmp_path):
    """`prdp-petsc bench elasticity --preset quick`: three declarations per size, the modes'
    error at K against its own converged solution, and growth from the counts."""
    assert main(["elasticity", "--preset", "quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "bench_elasticity.json").read_text())
    rows = data["rows"]
    assert [(r["cells"], r["variant"]) for r in rows] == [
        (n, v) for n in (2, 4) for v in ("scalar", "block", "modes")
    ]
    for r in rows:
        assert r["reason"] == "CONVERGED_RTOL" and r["relative_residual"] <= 1e-6
        assert (r["block_size"], r["near_nullspace"]) == {
            "scalar": (1, 0), "block": (3, 0), "modes": (3, 6)
        }[r["variant"]]  # fmt: skip
    assert rows[3]["unknowns"] == 3 * 5 * 5 * 4  # 4³ cells, the face x = 0 clamped
    for v in ("scalar", "block", "modes"):
        counts = [r["iterations"] for r in rows if r["variant"] == v]
        assert data["growth"][v] == counts[-1] / counts[0]
    assert "machine" in data and data["settings"]["quick"] is True
    from prdp_petsc.lab.reports.bench_elasticity import format_report

    # the table's cells, whatever padding the markdown table gives them
    assert "| 4³ | 300 | block size 3, 6 modes |" in re.sub(r" +", " ", format_report(data))


def test_implicit_gradient_allocates_a_few_vectors(data):
    """tracemalloc, not a clock: the operator (a ParametricMatrix) is the library's own and
    is never copied; a θ gradient adds one entry per nonzero (dA) and the p-sized result."""
    traced = data["overhead_detail"]["traced_peak"]
    peak = traced["vectors"]
    assert peak["b"] < 4
    assert peak["b_theta"] < traced["nnz_over_n"] + traced["n_params_over_n"] + 4
    # a new θ: its values A(θ) are new (nnz) as well
    assert peak["b_theta_new_theta"] < 2 * traced["nnz_over_n"] + 2 * traced["n_params_over_n"] + 4
