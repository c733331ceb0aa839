"""The documentation: its example files run and give the right numbers, its results
pages and the README's generated fragments equal what `prdp-petsc pages` makes from
the recorded data (so no page can drift from its data), and the API reference covers
the whole public API.  The site itself is built by `make docs` (`mkdocs --strict`)."""

import json
import math
import re
import runpy
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import prdp_petsc
from prdp_petsc.lab import cli
from prdp_petsc.lab.reports import pages
from prdp_petsc.lab.training import harness
from prdp_petsc.lab.training.scene import load_scene

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = ROOT / "README.md"


# -- the examples ----------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_my_scene_recovers_the_conductivity(seed, tmp_path):
    """The guide's scene trains, and PRDP recovers κ = (3, 1) to 0.1 % for a fraction
    of full fidelity's iterations (the κ error starts near 0.6 on these seeds)."""
    scene = DOCS / "examples" / "my_scene.py"
    result = harness.run(scene, "prdp", preset="quick", seed=seed, progress=False, out=tmp_path)
    totals = result["totals"]
    assert result["stopped"] is None
    assert result["epochs"][0]["val_metric"] > 0.3
    assert totals["final_val_error"] < 1e-3
    config = load_scene(scene).PRESETS["quick"]
    k_full = result["prdp"]["k_max"]  # the cap a PRDP run gets: K_full of the probe
    assert 50 < k_full < 200  # CG + Jacobi to rtol 1e-8 on ~1 300 unknowns
    full_cost = config["epochs"] * config["steps"] * k_full
    assert totals["fwd_iterations"] < 0.6 * full_cost
    assert json.loads((tmp_path / "results.json").read_text())["totals"] == totals


def test_quickstart_solves_and_differentiates():
    """The README's and Getting started's example: 20 CG + GAMG iterations give the
    direct solution of the interior system; the gradients are finite and non-zero."""
    ns = runpy.run_path(str(DOCS / "examples" / "quickstart.py"))
    assert ns["sol"].iterations == 20 and ns["sol"].reason == "DIVERGED_MAX_IT"
    assert ns["solver"].stats.forward_iterations == 20  # one call
    assert ns["sol"].adjoint.iterations.tolist() == [20]
    bc, u, f = ns["bc"], ns["u"].detach().numpy(), ns["f"].numpy()
    A_ii = bc.A_II.matrix(np.ones(ns["A"].n_params))
    direct = spla.spsolve(A_ii.tocsc(), f[bc.interior])
    assert np.linalg.norm(u[bc.interior] - direct) <= 1e-10 * np.linalg.norm(direct)
    assert np.all(u[bc.boundary] == 0.0)
    for grad in (ns["theta"].grad, ns["g"].grad):
        assert np.isfinite(grad.numpy()).all() and grad.norm() > 0


@pytest.fixture(scope="module")
def vector_guide():
    """docs/examples/vector.py, the code of the guide's vector page, as a module."""
    return runpy.run_path(str(DOCS / "examples" / "vector.py"))


def test_vector_guide_elasticity_needs_the_modes(vector_guide):
    """GAMG with the rigid-body modes needs far fewer iterations, in 2D and 3D."""
    for dim in (2, 3):
        its = vector_guide["elasticity"](dim, 8)
        assert its["modes"] <= 15 and its["scalar"] >= 1.5 * its["modes"], (dim, its)


def test_vector_guide_free_body(vector_guide):
    out = vector_guide["free_body"]()
    assert out["undeclared"] == "SINGULAR"
    expected = np.linalg.pinv(out["K"].toarray()) @ out["b"]
    assert np.linalg.norm(out["x"] - expected) <= 1e-8 * np.linalg.norm(expected)


def test_vector_guide_stokes(vector_guide):
    out = vector_guide["stokes"](6)
    assert out["splits"] == ["fieldsplit_u_", "fieldsplit_p_"]
    assert out["error"] <= 1e-8 and max(out["iterations"]) <= 50
    assert np.isfinite(out["grad"].numpy()).all() and out["grad"].abs().max() > 0


def test_vector_guide_simp_contrast(vector_guide):
    """Default GAMG breaks down on contrast 1e-9 : 1; Richardson + SOR smoothers solve."""
    out = vector_guide["simp_contrast"]()
    assert out["default"][0] == "DIVERGED_INDEFINITE_PC"
    assert out["richardson_sor"][0] == "CONVERGED_RTOL" and out["richardson_sor"][1] <= 30


def test_readme_shows_the_quickstart_file():
    code = (DOCS / "examples" / "quickstart.py").read_text()
    assert f"```python\n{code}```" in README.read_text()


# -- generated pages -------------------------------------------------------------------------
def test_results_pages_equal_what_the_data_gives():
    """Regenerate with `make pages` (`prdp-petsc pages --out docs/results`)."""
    expected = pages.pages(DOCS / "data", DOCS / "images")
    committed = {p.name: p.read_text() for p in (DOCS / "results").glob("*.md")}
    assert sorted(committed) == sorted(expected)
    for name, text in expected.items():
        assert committed[name] == text, f"docs/results/{name} is stale: run `make pages`"


def test_readme_fragments_equal_what_the_data_gives():
    """Every generated fragment is in the README, between its markers, as generated."""
    parts = pages.fragments(pages.load_data(DOCS / "data", DOCS / "images"))
    assert set(parts) == {"results", "demo-output"}
    text = README.read_text()
    for name, body in parts.items():
        block = f"<!-- {name}:start -->\n{body}\n<!-- {name}:end -->"
        assert block in text, f"README fragment {name!r} is stale: run `make pages`"
    assert pages.replace_fragments(text, parts) == text


def test_every_results_page_is_in_the_site_navigation():
    config = (ROOT / "mkdocs.yml").read_text()
    for page in (DOCS / "results").glob("*.md"):
        assert f"results/{page.name}" in config


def test_a_data_set_is_of_the_one_kind_whose_file_it_holds():
    """Each report kind is declared once, in its report's module, and a recorded folder
    is of the one kind whose result file it holds (a pattern for work-precision)."""
    kinds = pages.report_kinds()
    assert all(kind.name == name for name, kind in kinds.items())
    assert kinds["bench-jax"].title.__module__ == "prdp_petsc.lab.reports.bench_jax"
    assert pages.kind_of(["work_precision_heat3d.json"]) is kinds["work-precision"]
    assert pages.kind_of(["unseen.json", "notes.json"]) is kinds["unseen"]
    with pytest.raises(ValueError, match="compare, seeds among"):
        pages.kind_of(["seeds.json", "summary.json"])
    with pytest.raises(ValueError, match="no known result file"):
        pages.kind_of(["notes.json"])


def test_every_recorded_data_set_names_its_command_machine_and_versions():
    sets = pages.load_data(DOCS / "data", DOCS / "images")
    assert {ds.name: ds.kind.name for ds in sets} == {
        "bench_bridge": "bench",
        "bench_jax": "bench-jax",
        "bench_gpu": "bench-gpu",
        "heat2d": "compare",
        "stability": "stability",
        "work_precision_heat3d": "work-precision",
        "heat2d_speedup": "seeds",
        "heat3d_speedup": "seeds",
        "heat_nonlinear_speedup": "seeds",
        "ns2d_large_routes_speedup": "seeds",
        "ns2d_large_k192_speedup": "seeds",
        "ns2d_large_ablation": "ablation",
        "heat_nonlinear_ablation": "ablation",
        "heat1d_seeds": "seeds",
        "heat1d_m2_seeds": "seeds",
        "heat1d_k10_seeds": "seeds",
        "ns2d_long_rollouts": "rollouts",
        "ns2d_long_horizon": "horizon",
        "bench_mpi_owned_cube64": "bench-mpi",
        "bench_mpi_owned_cube101": "bench-mpi",
        "bench_mpi_replicated_cube101": "bench-mpi",
        "elasticity_gamg": "bench-elasticity",
        "unseen": "unseen",
        "unseen_held_out": "unseen",
        **{
            name: "defaults"
            for name in sorted(ds.name for ds in sets)
            if name.startswith("defaults_")
        },
        "topopt3d_paper": "topopt",
    }
    assert {"defaults_heat1d", "defaults_heat2d", "defaults_heat3d"} <= {ds.name for ds in sets}
    for ds in sets:
        p = ds.provenance
        assert p["command"].startswith("prdp-petsc ")
        # a run stopped at its time limit is recorded only with what it saved, marked so
        assert p["exit_status"] == 0 or (ds.main.get("partial") and p.get("note"))
        assert p["machine"]["cpu_count"] >= 1 and len(p["git"]["commit"]) == 40
        known = {name for name, version in p["versions"].items() if version}
        assert {"petsc", "petsc4py", "torch", "scikit-fem"} <= known
        assert sorted(p["json"]) == sorted(ds.files)
        assert sorted(p["images"]) == ds.images
    # `make demo` is the recorded demo, whose scene file was demos/heat2d.py before the 2D
    # and 3D heat scenes became demos/heat.py (the 2D presets kept their names)
    demo = next(ds for ds in sets if ds.name == "heat2d")
    make_demo = "compare demos/heat.py --preset paper --routes cg/icc --out $(OUT)/heat2d"
    assert make_demo in (ROOT / "Makefile").read_text()
    recorded = make_demo.replace("$(OUT)", "results").replace("heat.py", "heat2d.py")
    assert demo.provenance["command"] == "prdp-petsc " + recorded


def test_pages_command_writes_the_committed_pages(tmp_path):
    """`prdp-petsc pages --out DIR` through the command line's dispatch."""
    readme = tmp_path / "README.md"
    readme.write_text("head\n<!-- results:start -->\nold\n<!-- results:end -->\ntail\n")
    args = ["pages", "--out", str(tmp_path / "results"), "--data", str(DOCS / "data")]
    assert cli.main([*args, "--images", str(DOCS / "images"), "--readme", str(readme)]) == 0
    for page in (DOCS / "results").glob("*.md"):
        assert (tmp_path / "results" / page.name).read_text() == page.read_text()
    text = readme.read_text()
    assert "old" not in text and text.startswith("head\n") and text.endswith("tail\n")
    assert re.search(r"^\| result +\| measured +\| data +\|$", text, re.MULTILINE)


def test_replace_fragments_keeps_unknown_markers_and_text():
    text = "a\n<!-- x:start -->\n1\n<!-- x:end -->\nb\n<!-- y:start -->\n2\n<!-- y:end -->\n"
    out = pages.replace_fragments(text, {"x": "new\nlines", "z": "unused"})
    assert out == text.replace("\n1\n", "\nnew\nlines\n")
    empty = "<!-- x:start -->\n<!-- x:end -->\n"  # markers with nothing between them
    assert pages.replace_fragments(empty, {"x": "b"}) == "<!-- x:start -->\nb\n<!-- x:end -->\n"


def test_record_keeps_json_plots_and_provenance(tmp_path):
    """`pages record` runs the command and keeps only what it wrote, with provenance."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "stale.json").write_text("{}")  # left by an earlier run: not recorded
    data, images = tmp_path / "data", tmp_path / "images"
    command = ["stability", "--preset", "quick", "--cases", "magnitude", "--out", str(out)]
    assert pages.record("quick_stability", command, data=data, images=images) == 0
    folder = data / "quick_stability"
    assert sorted(p.name for p in folder.iterdir()) == ["provenance.json", "stability.json"]
    p = json.loads((folder / "provenance.json").read_text())
    assert p["command"] == "prdp-petsc " + " ".join(command)
    assert p["exit_status"] == 0 and p["json"] == ["stability.json"] and p["images"] == []
    assert p["versions"]["prdp-petsc"] == prdp_petsc.__version__
    (ds,) = pages.load_data(data, images)
    assert ds.kind.name == "stability" and len(ds.main["rows"]) == 9  # 3 sizes × 3 KSP/PC
    assert "| rhs magnitude |" in pages.page(ds)


def test_record_refuses_a_command_without_out(tmp_path):
    with pytest.raises(ValueError, match="--out"):
        pages.record("x", ["stability", "--preset", "quick"], data=tmp_path)
    with pytest.raises(ValueError, match="data set name"):
        pages.record("../x", ["stability", "--out", str(tmp_path)], data=tmp_path)


# -- API reference and packaging -------------------------------------------------------------
def test_api_reference_covers_the_public_api():
    """Every name of `prdp_petsc.__all__` has its `::: module.name` entry, by its real
    module (the package imports its names lazily, which static analysis cannot see)."""
    text = "\n".join(p.read_text() for p in (DOCS / "api").glob("*.md"))
    for name, module in prdp_petsc._EXPORTS.items():
        assert f"::: prdp_petsc{module}.{name}\n" in text, name
    assert set(prdp_petsc.__all__) == {*prdp_petsc._EXPORTS, "__version__"}


def test_py_typed_is_shipped():
    assert (ROOT / "prdp_petsc" / "py.typed").is_file()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in pyproject["tool"]["setuptools"]["package-data"]["prdp_petsc"]
    assert "mkdocstrings[python]" in " ".join(pyproject["project"]["optional-dependencies"]["docs"])


def test_a_seeds_data_set_headlines_its_error_ratio_and_savings():
    """The README row of a `compare --seeds` record gives PRDP's error ratio over full
    fidelity with its interval and the iterations saved, from seeds.json."""
    ds = next(d for d in pages.load_data(DOCS / "data", DOCS / "images") if d.kind.name == "seeds")
    rows = dict(ds.kind.headline(ds))
    ((what, figure),) = [(w, f) for w, f in rows.items() if "error over full" in w]
    ratio = ds.main["prdp_ratio"]
    assert figure.startswith(f"{ratio['geometric_mean']:.3f} (95 % interval")
    saved = ds.main["savings"]["iterations_saved"]["mean"]
    assert f"{100 * saved:.1f} % fewer inner iterations" in figure


def test_every_seeds_headline_recomputes_from_its_per_seed_records():
    """Each `compare --seeds` headline by hand from seeds.json's per-seed errors: each
    seed's ratio is PRDP's validation error over full fidelity's; the headline gives
    their geometric mean and 95 % t-interval on the logs, and the inner iterations
    saved averaged over the seeds at equal accuracy (ratio ≤ the recorded accuracy)."""
    from scipy import stats

    sets = [d for d in pages.load_data(DOCS / "data", DOCS / "images") if d.kind.name == "seeds"]
    assert len(sets) >= 5
    for ds in sets:
        runs = ds.main["per_seed"]
        ratios = np.array([r["prdp_val_error"] / r["full_val_error"] for r in runs])
        logs = np.log(ratios)
        half = stats.t.ppf(0.975, len(logs) - 1) * np.std(logs, ddof=1) / np.sqrt(len(logs))
        mean = logs.mean()
        equal = [r for r, ratio in zip(runs, ratios) if ratio <= ds.main["accuracy"]]
        figures = [f"{math.exp(m):.3f}" for m in (mean, mean - half, mean + half)]
        if equal:
            saved = np.mean([r["iterations_saved"] for r in equal])
            figures += [f"{100 * saved:.1f} %", f"{len(equal)} of {len(runs)}"]
        (figure,) = [f for w, f in ds.kind.headline(ds) if "error over full" in w]
        assert all(f in figure for f in figures), (ds.name, figures, figure)


def test_the_elasticity_page_supports_the_guide():
    """The guide says GAMG with the rigid-body modes stays flat on 3D elasticity: the
    recorded run goes from 8³ to 32³ cells, its counts are within 1.5× with the modes,
    and nothing declared grows beyond that."""
    sets = pages.load_data(DOCS / "data", DOCS / "images")
    ds = next(d for d in sets if d.name == "elasticity_gamg")
    d = ds.main
    assert d["sizes"][0] == 8 and d["sizes"][-1] == 32 and 16 in d["sizes"]
    assert d["growth"]["modes"] <= 1.5 < d["growth"]["scalar"]
    assert all(r["reason"] == "CONVERGED_RTOL" for r in d["rows"])


def test_prdp_loop_example_certifies_its_stop():
    """docs/examples/prdp_loop.py: the default construction in a user's loop ends
    certified below K_full, with the savings saying so."""
    ns = runpy.run_path(str(DOCS / "examples" / "prdp_loop.py"))
    prdp, savings = ns["prdp"], ns["savings"]
    assert prdp.k_init == -(-ns["k_full"] // 8) and prdp.k_max == ns["k_full"]
    assert ns["certificate"].certified and savings["certified"] is True
    assert prdp.k < ns["k_full"] and savings["total"] > 0.4


def test_the_unseen_page_and_headline_recompute_from_the_per_seed_records():
    """The unseen page's first table and the README's row, recomputed by hand from the
    per-seed records of docs/data/unseen: each seed's error ratio is PRDP's final error
    over full fidelity's, their geometric mean and worst seed per problem; iterations
    saved 1 − PRDP's over full fidelity's (checks included); certified, the runs whose
    last check is, or that end at K_full.  Equal accuracy: geometric mean ≤ 1.05, no
    seed above 1.10."""
    data = json.loads((DOCS / "data" / "unseen" / "unseen.json").read_text())
    page = (DOCS / "results" / "unseen.md").read_text().splitlines()
    means, accurate, saving = [], 0, 0
    for name, problem in data["problems"].items():
        runs = problem["runs"]
        ratios = [r["prdp"]["final_error"] / r["full"]["final_error"] for r in runs]
        saved = [1 - r["prdp"]["iterations"] / r["full"]["iterations"] for r in runs]
        # a run that ends at K_full is certified trivially (nothing to compare with)
        certified = sum(
            r["prdp"]["checks"][-1]["certified"] or r["prdp"]["ks"][-1] >= r["k_full"] for r in runs
        )
        mean = math.exp(sum(map(math.log, ratios)) / len(ratios))
        means.append(mean)
        accurate += mean <= 1.05 and max(ratios) <= 1.10
        saving += min(saved) >= 0.40
        figures = [f"{mean:.3f}", f"{max(ratios):.3f}", f"{certified}/{len(runs)}",
                   ", ".join(f"{100 * s:.0f} %" for s in saved)]  # fmt: skip
        rows = [line for line in page if line.startswith(f"| `{name}`")]
        assert any(all(f in row for f in figures) for row in rows), (name, figures)
    (row,) = [line for line in README.read_text().splitlines() if "results/unseen.md" in line]
    count = len(data["problems"])
    assert f"{accurate} of {count}" in row and f"{max(means):.3f}" in row
    assert f"every seed on {saving}" in row
