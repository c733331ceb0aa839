"""The problems PRDP was never tuned on (`prdp_petsc.lab.reports.unseen_problems`), quick
variants, run by `prdp_petsc.lab.reports.unseen`.

Each runs full fidelity and the default construction (`PRDP.for_problem` with a
gradient check) in a plain loop.  The full-size runs over three seeds are on the
results page (docs/results/unseen.md); here the fast problems run on two seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

import prdp_petsc as pp
from prdp_petsc.lab.reports import unseen, unseen_problems
from prdp_petsc.lab.training.accuracy import constant_caps


@pytest.mark.parametrize("name", ["heat_sink", "annulus_inverse", "box3d_regions"])
@pytest.mark.parametrize("seed", [1, 2])
def test_default_prdp_matches_full_fidelity_for_fewer_iterations(name, seed):
    problem = unseen_problems.build(name, seed, quick=True)
    k_full = pp.find_k_full(*problem.probe, problem.solver, rtol=unseen_problems.RTOL_FULL)
    full = unseen.train(problem, "full", k_full)
    prdp = unseen.train(unseen_problems.build(name, seed, quick=True), "prdp", k_full)
    assert prdp["final_error"] <= 1.10 * full["final_error"]
    assert prdp["iterations"] <= 0.8 * full["iterations"]  # checks included
    # the end's check against K_full was made at the final K: certified or not, the run
    # says which (a quick run is too short to afford rechecks within the checks' budget)
    assert prdp["savings_k"]["certified"] is not None
    assert prdp["checks"][-1]["k"] == prdp["ks"][-1] and prdp["checks"][-1]["against"] == k_full
    assert prdp["ks"][0] == max(1, -(-k_full // 8))


def test_the_check_is_the_validation_gradient_through_the_capped_solve():
    problem = unseen_problems.build("lshape_mlp", 0, quick=True)
    k_full = pp.find_k_full(*problem.probe, problem.solver)
    check = problem.check()
    g_full, g_coarse = check(k_full), check(max(1, k_full // 8))
    n_weights = sum(p.numel() for p in problem.net.parameters())
    assert g_full.shape == (n_weights,) and np.all(np.isfinite(g_full))
    assert pp.prdp.fidelity_gap(check(k_full), g_full) == pytest.approx(0.0, abs=1e-12)
    assert pp.prdp.fidelity_gap(g_coarse, g_full) > 0.05  # K_full / 8 is far off here
    assert all(p.grad is None for p in problem.net.parameters())  # no training step


def test_table_of_a_comparison():
    result = unseen.compare(["heat_sink"], [0], quick=True)
    p = result["problems"]["heat_sink"]
    assert len(p["runs"]) == 1 and p["geomean_ratio"] == pytest.approx(p["worst_ratio"])
    assert "`heat_sink`" in unseen.table(result)


def test_cli_writes_the_json_the_results_page_reads(tmp_path, capsys):
    from prdp_petsc.lab.cli import main

    rc = main(["unseen", "--problems", "heat_sink", "--seeds", "0", "--preset", "quick", "--out",
               str(tmp_path)])  # fmt: skip
    assert rc == 0
    import json

    result = json.loads((tmp_path / "unseen.json").read_text())
    run = result["problems"]["heat_sink"]["runs"][0]
    assert run["error_ratio"] == pytest.approx(
        run["prdp"]["final_error"] / run["full"]["final_error"]
    )
    assert "`heat_sink`" in capsys.readouterr().out


def test_baselines_put_the_default_beside_the_hand_schedule_and_constant_caps():
    """``unseen --baselines``: per problem, the hand schedule and each constant cap of
    K_full/8, /4, /2, judged at equal accuracy as the default is, and the best of them."""
    result = unseen.compare(["box3d_regions"], [0], quick=True, baselines=True)
    p = result["problems"]["box3d_regions"]
    run, b = p["runs"][0], p["baselines"]
    caps = constant_caps(run["k_full"]).values()
    assert set(run["baselines"]) == {"hand", *(f"fixed:{k}" for k in caps)}
    assert set(b) == {"hand", "K_full/8", "K_full/4", "K_full/2", "best_constant"}
    for label in ("K_full/8", "K_full/4", "K_full/2"):
        s = b[label]
        assert s["equal_accuracy"] == (s["geomean_ratio"] <= 1.05 and s["worst_ratio"] <= 1.10)
    k_half = max(1, -(-run["k_full"] // 2))
    assert b["K_full/2"]["saved"][0] == pytest.approx(run["baselines"][f"fixed:{k_half}"]["saved"])
    fits = [lab for lab in ("K_full/8", "K_full/4", "K_full/2") if b[lab]["equal_accuracy"]]
    if fits:  # the best constant cap saves the most of those at equal accuracy
        assert b["best_constant"] in fits
        assert all(b[b["best_constant"]]["saved"][0] >= b[lab]["saved"][0] for lab in fits)
    assert "hand schedule" in unseen.table(result)
    # beside each constant cap, the probe's error of the solve capped there
    for label, k in constant_caps(run["k_full"]).items():
        error = run["probe_errors"][str(k)]
        assert f"{label}: " in unseen.table(result)
        assert f"[{100 * error:.1f} %]" in unseen.table(result)
    assert all("descent" in c for c in run["prdp"]["checks"])
