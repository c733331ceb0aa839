"""`prdp-petsc bench gpu` on the CPU at tiny sizes: the JSON's figures are there, the
contenders agree (fixed-mode CG is the same arithmetic everywhere), an absent peer is
skipped with a note, the budget stops a run.  Times are never compared here."""

import json

import numpy as np
import pytest

from prdp_petsc.lab.reports import bench_gpu, gpu_contenders
from prdp_petsc.lab.reports.bench import main

PEERS = ("jax_cg", "lineax_cg")


def _has_row(markdown: str, *cells: str) -> bool:
    """Whether a row of a Markdown table in `markdown` starts with `cells` (padding aside)."""
    rows = (line.strip("|").split("|") for line in markdown.splitlines() if line.startswith("|"))
    return any([c.strip() for c in row[: len(cells)]] == list(cells) for row in rows)


def _run(tmp_path, *args):
    assert main(["gpu", "--out", str(tmp_path), "--device", "cpu", *args]) == 0
    return json.loads((tmp_path / "bench_gpu.json").read_text())


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """One tiny L-shape, K = 2 and 5, and the time to a 1e-6 gradient on it."""
    out = tmp_path_factory.mktemp("bench_gpu")
    args = ["--problems", "lshape3", "--k", "2,5", "--rounds", "2", "--calls", "2"]
    return _run(out, *args, "--warmup", "1", "--tol-problems", "lshape3", "--tol-calls", "1")


def test_cells_time_every_contender_and_agree(quick):
    have_jax = all(quick["contenders"][p]["available"] for p in PEERS)
    assert quick["problems"]["lshape3"]["n"] == 161
    assert [(c["problem"], c["k"]) for c in quick["cells"]] == [("lshape3", 2), ("lshape3", 5)]
    expected = {c.name for c in gpu_contenders.CONTENDERS if have_jax or c.name not in PEERS}
    for cell in quick["cells"]:
        assert set(cell["median_s"]) == expected, cell["notes"]
        assert all(t > 0 for t in cell["median_s"].values())
        assert all(len(t) == 2 for t in cell["timings_s"].values())  # rounds
        assert cell["reference"] == "prdp_petsc"
        assert set(cell["agreement"]) == expected - {"prdp_petsc"}
        # K iterations of the same CG forward and adjoint: x and the gradient to rounding
        for name, diff in cell["agreement"].items():
            assert diff["x"] < 1e-12 and diff["grad"] < 1e-12, name
        info = cell["info"]["prdp_petsc"]
        assert info["forward_iterations_per_solve"] == cell["k"]
        assert info["adjoint_iterations_per_solve"] == cell["k"]
        assert info["ksp"] == ["cg", "jacobi"]
        assert cell["info"]["raw_petsc"]["iterations_per_solve"] == [cell["k"]]
        assert "prdp_petsc/raw_petsc" in cell["ratios"]
        assert "prdp_petsc_sr/raw_petsc_sr" in cell["ratios"]
        assert ("prdp_petsc/jax_cg" in cell["ratios"]) == have_jax
    assert quick["cpu_gpu_agreement"] == {
        "note": "no CUDA device: the whole run is on the CPU path"
    }
    assert quick["device"]["kind"] == "cpu" and quick["skipped"] == []
    assert quick["provenance"]["versions"]["petsc4py"]


def test_time_to_tolerance(quick):
    t = quick["time_to_tolerance"]["lshape3"]
    assert t["tol"] == 1e-6
    assert t["reference"]["method"].startswith("scipy")
    assert max(t["reference"]["relative_residuals"]) < 1e-12
    k = t["jacobi"]["k"]
    assert t["jacobi"]["searched_with"] == "torch_pcg"
    # the search's trace brackets K: K itself passes, and (up to 1 %) one fewer fails
    trace = dict(map(tuple, t["jacobi"]["search"]))
    assert trace[k] <= 1e-6
    assert any(kk < k and e > 1e-6 and kk >= 0.99 * k - 1 for kk, e in trace.items())
    for name, r in t["contenders"].items():
        assert r["k"] == k and r["grad_error"] <= 1e-6 and r["median_s"] > 0, name
    gamg = t["gamg"]
    assert gamg["grad_error"] <= 1e-6 and gamg["k"] < k  # a multigrid PC needs fewer
    assert gamg["info"]["ksp"] == ["cg", "gamg"] and gamg["setup_s"] >= 0


def test_report_prints_the_table(quick):
    text = bench_gpu.format_report(quick)
    assert _has_row(text, "L-shape P1 (161)", "2 / 5")
    assert "prdp_petsc + GAMG" in text and "targets:" in text


def test_an_absent_peer_is_skipped_with_a_note(monkeypatch, tmp_path):
    real = bench_gpu.environment

    def without_jax(device):
        device, notes = real(device)
        notes.update(jax="jax is not installed", lineax="jax is not installed")
        return device, notes

    monkeypatch.setattr(bench_gpu, "environment", without_jax)
    d = _run(tmp_path, "--problems", "lshape2", "--k", "3", "--rounds", "1", "--calls", "1",
             "--tol-problems", "", "--skip", "raw_petsc_transpose,prdp_petsc_sr")  # fmt: skip
    described = {c.name: c.describe for c in gpu_contenders.CONTENDERS}
    for name in PEERS:
        assert d["contenders"][name] == {
            "describe": described[name],
            "available": False,
            "note": "jax is not installed",
        }
    for name in ("raw_petsc_transpose", "prdp_petsc_sr"):
        assert d["contenders"][name]["note"] == "left out by --skip"
    (cell,) = d["cells"]
    assert set(cell["median_s"]) == {"prdp_petsc", "raw_petsc", "raw_petsc_sr", "torch_pcg"}
    assert "prdp_petsc/jax_cg" not in cell["ratios"]
    assert "skipped jax_cg: jax is not installed" in bench_gpu.format_report(d)
    assert d["time_to_tolerance"] == {}


def test_a_contender_that_fails_is_noted_and_the_others_run(monkeypatch, tmp_path):
    def broken(name, case, k):
        raise RuntimeError("no device here")

    contenders = [c._replace(build=broken) if c.name == "torch_pcg" else c
                  for c in gpu_contenders.CONTENDERS]  # fmt: skip
    monkeypatch.setattr(bench_gpu, "CONTENDERS", tuple(contenders))
    d = _run(tmp_path, "--problems", "lshape2", "--k", "3", "--rounds", "1", "--calls", "1",
             "--tol-problems", "", "--skip", "jax_cg,lineax_cg")  # fmt: skip
    (cell,) = d["cells"]
    assert cell["notes"] == {"torch_pcg": "failed: RuntimeError: no device here"}
    assert "torch_pcg" not in cell["median_s"] and "prdp_petsc" in cell["median_s"]


def test_the_budget_skips_what_would_start_after_it(tmp_path):
    d = _run(tmp_path, "--problems", "lshape2,heat3d4", "--budget-s", "1e-9")
    assert d["cells"] == [] and d["problems"] == {}
    assert [s["what"] for s in d["skipped"]] == ["problem lshape2", "problem heat3d4"]
    assert all("budget" in s["why"] for s in d["skipped"])


def test_problems_are_the_issues(tmp_path):
    # the sizes the issue names: 12 033 unknowns at refined(6), 59 319 on 41³ points
    label, matrix = gpu_contenders.problem("lshape6")
    A = matrix()
    assert label == "L-shape P1" and A.shape == (12033, 12033)
    heat = gpu_contenders.problem("heat3d5")[1]()
    assert heat.shape == (27, 27)
    for M in (A, heat):  # SPD: symmetric to rounding, positive diagonal, Cholesky works
        assert abs(M - M.T).max() <= 1e-14 * abs(M).max()
        assert (M.diagonal() > 0).all()
    assert np.linalg.eigvalsh(heat.toarray()).min() > 0
    # the jitter moves the interior vertices: the matrix is not the unjittered one's
    still = gpu_contenders.lshape(3, jitter=0.0)
    moved = gpu_contenders.problem("lshape3")[1]()
    assert still.shape == moved.shape and abs(still - moved).max() > 1e-3
    for name in ("square7", "heat3d2"):
        with pytest.raises(Exception, match="unknown problem"):
            gpu_contenders.problem(name)


def test_tight_cg_matches_the_direct_reference():
    A = gpu_contenders.lshape(4)
    rng = np.random.default_rng(1)
    case = gpu_contenders.Case("lshape4", A, rng.standard_normal(A.shape[0]),
                          rng.standard_normal(A.shape[0]))  # fmt: skip
    direct = bench_gpu.reference_gradient(case, direct_max_n=10**6)
    tight = bench_gpu.reference_gradient(case, direct_max_n=1)
    assert direct["method"].startswith("scipy") and tight["method"].startswith("torch")
    assert max(tight["last_corrections"]) <= 1e-11
    assert max(tight["relative_residuals"]) < 1e-12
    rel = np.linalg.norm(tight["grad"] - direct["grad"]) / np.linalg.norm(direct["grad"])
    assert rel < 1e-9


def test_smallest_k_brackets_to_one_percent():
    k, trace = bench_gpu._smallest_k(lambda k: 1.0 / k, 1e-3, 16, 10**6)
    assert 1000 <= k <= 1010 and trace[-1][0] <= 1010
    assert bench_gpu._smallest_k(lambda k: 1.0, 1e-3, 16, 64) == (
        None,
        [[16, 1.0], [32, 1.0], [64, 1.0]],
    )


def test_cpu_gpu_agreement_compares_two_runs():
    A = gpu_contenders.lshape(2)
    rng = np.random.default_rng(2)
    case = gpu_contenders.Case("lshape2", A, rng.standard_normal(A.shape[0]),
                          rng.standard_normal(A.shape[0]))  # fmt: skip
    same = bench_gpu.cpu_gpu_agreement(case, 10, devices=("cpu", "cpu"))
    assert same["x"] == 0.0 and same["grad"] == 0.0 and same["target"] == 1e-10


def _ratio(r):
    return {"median": r, "q1": r, "q3": r, "noise": 0.0}


def _gpu_result() -> dict:
    """The issue's bounds, on a made-up GPU result: 3.5x at 12 k, 2x from 59 k up, 1.3x
    at 784 k, the bridge within 15 % of raw petsc4py, GAMG before every GPU peer."""
    cells = [
        {"problem": "lshape6", "n": 12033, "k": 10,
         "ratios": {"prdp_petsc/raw_petsc": _ratio(1.10), "prdp_petsc/jax_cg": _ratio(3.0)}},
        {"problem": "lshape9", "n": 784385, "k": 300,
         "ratios": {"prdp_petsc/raw_petsc": _ratio(1.20), "prdp_petsc/jax_cg": _ratio(1.4)}},
    ]  # fmt: skip
    tol = {"tol": 1e-6, "contenders": {"jax_cg": {"median_s": 0.5}, "torch_pcg": {"median_s": 0.9}},
           "gamg": {"k": 20, "median_s": 0.1, "setup_s": 0.6}}  # fmt: skip
    return {
        "device": {"kind": "cuda", "name": "a GPU"},
        "cells": cells,
        "cpu_gpu_agreement": {"lshape6": {"k": 10, "x": 1e-14, "grad": 3e-12}},
        "time_to_tolerance": {"lshape9": tol},
    }


def test_verdicts_judge_each_target_from_the_json():
    d = _gpu_result()
    got = {target: (measured, met) for target, measured, met in bench_gpu.verdicts(d)}
    assert got["bridge over raw petsc4py <= 1.15"] == ("worst 1.20 (lshape9, K = 300)", False)
    assert got["prdp_petsc / jax_cg <= 3.5 at 12 k"][1] is True
    assert got["prdp_petsc / jax_cg <= 2.0 at >= 59 k"][1] is True
    assert got["prdp_petsc / jax_cg <= 1.3 at 784 k"][1] is False
    assert got["prdp_petsc_sr / jax_cg <= 2.0 at >= 59 k"] == ("not measured", None)
    assert got["CPU and GPU paths agree to 1e-10 at K = 10"] == ("worst 3.0e-12", True)
    assert got["GAMG first to 1e-06 on lshape9"][1] is True  # 0.1 s against jax's 0.5 s
    assert got["GAMG first to 1e-06 on lshape9, its setup counted"] == ("700.0 ms", False)
    cpu = {**d, "device": {"kind": "cpu", "name": "AMD EPYC"}}
    assert bench_gpu.verdicts(cpu) == [
        ("the GPU targets", "not judged: measured on AMD EPYC", None)
    ]


def test_a_recorded_run_becomes_a_results_page(quick):
    """The kind is found by its file, and its page carries the table and the verdicts."""
    from prdp_petsc.lab.reports import pages
    from prdp_petsc.lab.reports.kinds import DataSet

    kind = pages.kind_of(["bench_gpu.json"])
    assert kind is bench_gpu.KIND and pages.report_kinds()["bench-gpu"] is kind
    ds = DataSet("bench_gpu", kind, {}, {"bench_gpu.json": quick}, [])
    assert "GPU" in kind.title(ds)
    assert kind.headline(ds) == [
        ("prdp_petsc against jax, lineax and torch CG on one GPU", "not judged: measured on "
         + quick["device"]["name"])
    ]  # fmt: skip
    parts = kind.parts(ds)
    assert _has_row(parts["output"], "L-shape P1 (161)", "2 / 5")
    measured = "not judged: measured on " + quick["device"]["name"]
    assert _has_row("\n".join(parts["after"]), "the GPU targets", measured)
    gpu = DataSet("bench_gpu", kind, {}, {"bench_gpu.json": _gpu_result()}, [])
    assert kind.headline(gpu) == [
        ("GPU, fwd + bwd of capped Jacobi CG: bridge over raw petsc4py <= 1.15",
         "worst 1.20 (lshape9, K = 300)"),
        ("GPU, fwd + bwd of capped Jacobi CG: prdp_petsc / jax_cg <= 2.0 at >= 59 k",
         "worst 1.40 (lshape9, K = 300)"),
    ]  # fmt: skip
    assert _has_row("\n".join(kind.after(gpu)), "bridge over raw petsc4py <= 1.15",
                    "worst 1.20 (lshape9, K = 300)", "**not met**")  # fmt: skip
