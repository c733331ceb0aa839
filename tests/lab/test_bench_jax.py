"""`prdp-petsc bench jax`: `bench gpu` on the CPU at the JAX comparison's sizes, where
prdp_petsc, jax, lineax and raw petsc4py compute the same gradient with exactly K
iterations; the former record's page (timings are never compared here)."""

import json
from pathlib import Path

import pytest

from prdp_petsc.lab.reports import bench_jax, gpu_contenders, pages
from prdp_petsc.lab.reports.bench import main
from prdp_petsc.lab.reports.kinds import DataSet

RECORD = Path(__file__).parents[2] / "docs" / "data" / "bench_jax" / "bench_jax.json"


def _run(tmp_path, *args) -> dict:
    assert main(["jax", "--preset", "quick", "--out", str(tmp_path), *args]) == 0
    return json.loads((tmp_path / "bench_gpu.json").read_text())


def test_bench_jax_quick(tmp_path):
    pytest.importorskip("jax")
    pytest.importorskip("lineax")
    d = _run(tmp_path)
    assert d["device"]["kind"] == "cpu" and d["time_to_tolerance"] == {}
    assert d["problems"]["five_point20"]["n"] == 400
    (cell,) = d["cells"]
    assert cell["k"] == 10 and cell["notes"] == {}
    assert {"prdp_petsc", "jax_cg", "lineax_cg", "raw_petsc"} <= set(cell["median_s"])
    assert {"prdp_petsc/jax_cg", "lineax_cg/jax_cg", "prdp_petsc/raw_petsc"} <= set(cell["ratios"])
    # the same K iterations forward and adjoint everywhere: the same gradient
    for name, diff in cell["agreement"].items():
        assert diff["grad"] < 1e-10, name
    info = cell["info"]["prdp_petsc"]
    assert info["forward_iterations_per_solve"] == info["adjoint_iterations_per_solve"] == 10
    assert cell["info"]["raw_petsc"]["iterations_per_solve"] == [10]
    assert cell["info"]["jax_cg"]["matvec"] == "BCOO @ x"
    assert all(len(t) == d["settings"]["rounds"] == 3 for t in cell["timings_s"].values())


def test_bench_gpu_options_override_the_preset(tmp_path):
    pytest.importorskip("jax")
    pytest.importorskip("lineax")
    d = _run(tmp_path, "--k", "4", "--rounds", "1", "--skip", "torch_pcg,prdp_petsc_sr")
    (cell,) = d["cells"]
    assert (cell["problem"], cell["k"]) == ("five_point20", 4)
    assert "torch_pcg" not in cell["median_s"]
    assert cell["info"]["prdp_petsc"]["adjoint_iterations_per_solve"] == 4


def test_bench_jax_without_jax_says_how_to_install(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(bench_jax, "jax_missing", lambda: bench_jax.INSTALL_HINT)
    assert main(["jax", "--preset", "quick", "--out", str(tmp_path)]) == 2
    assert "jaxbench" in capsys.readouterr().err
    assert not (tmp_path / "bench_gpu.json").exists()


def test_five_point_is_a_problem():
    label, matrix = gpu_contenders.problem("five_point20")
    A = matrix()
    assert label == "5-point -Δ" and A.shape == (400, 400) and A.nnz == 5 * 400 - 4 * 20


def test_the_former_record_becomes_its_page():
    """The recorded bench_jax.json is of kind bench-jax: its ratios in the headline, the
    target judged from them."""
    record = json.loads(RECORD.read_text())
    kind = pages.kind_of(["bench_jax.json"])
    assert kind is bench_jax.KIND
    ds = DataSet("bench_jax", kind, {}, {"bench_jax.json": record}, [])
    ratios = {name: r["median"] for name, r in record["ratios"].items()}
    figure = kind.headline(ds)[0][1]
    assert figure.startswith(f"{ratios['jax_cg/prdp_petsc']:.2f}× / ")
    met = min(ratios["jax_cg/prdp_petsc"], ratios["lineax_cg/prdp_petsc"]) >= 1.5
    assert kind.after(ds)[0].startswith(f"**Target (≥ 1.5× faster than each): "
                                        f"{'met' if met else 'not met'}.**")  # fmt: skip
    assert f"{ratios['prdp_petsc/raw_petsc']:.3f}" in kind.output(ds)
