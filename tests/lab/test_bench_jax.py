"""`prdp-petsc bench jax`: every implementation computes the same gradient, the JSON
holds the figures (timings are never compared here: they describe a machine)."""

import json

import pytest

from prdp_petsc.lab.reports.bench import main


def test_bench_jax_quick(tmp_path):
    pytest.importorskip("jax")
    pytest.importorskip("lineax")
    assert main(["jax", "--preset", "quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "bench_jax.json").read_text())
    assert data["k"] == 10 and data["n"] == 400
    assert set(data["ratios"]) == {
        "jax_cg/prdp_petsc",
        "lineax_cg/prdp_petsc",
        "prdp_petsc/raw_petsc",
    }
    # the same K iterations forward and adjoint everywhere: the same gradient
    for impl, diff in data["gradient_rel_diff"].items():
        assert diff < 1e-10, impl
    for times in data["timings_s"].values():
        assert len(times) == data["settings"]["rounds"]


def test_bench_jax_without_jax_says_how_to_install(monkeypatch, tmp_path, capsys):
    import prdp_petsc.lab.reports.bench_jax as bench_jax

    monkeypatch.setattr(bench_jax, "jax_missing", lambda: bench_jax.INSTALL_HINT)
    assert main(["jax", "--preset", "quick", "--out", str(tmp_path)]) == 2
    assert "jaxbench" in capsys.readouterr().err
    assert not (tmp_path / "bench_jax.json").exists()


def test_bench_jax_page(tmp_path):
    """A recorded bench_jax.json becomes a results page (title, headline, body)."""
    pytest.importorskip("jax")
    pytest.importorskip("lineax")
    from prdp_petsc.lab.reports.kinds import DataSet
    from prdp_petsc.lab.reports.pages import kind_of

    assert main(["jax", "--preset", "quick", "--out", str(tmp_path)]) == 0
    files = {"bench_jax.json": json.loads((tmp_path / "bench_jax.json").read_text())}
    ds = DataSet("bench_jax", kind_of(files), {}, files, [])
    assert ds.kind.name == "bench-jax" and "JAX" in ds.kind.title(ds)
    assert "jax_cg/prdp_petsc" in ds.kind.output(ds)
    assert "lineax" in ds.kind.headline(ds)[0][0]
