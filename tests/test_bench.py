"""Smoke test of `prdp-petsc bench bridge --quick`: the JSON holds every figure.

Timings are never compared with targets here (they describe a machine, not the
code); the test checks that each figure was measured and is a finite number of
the right sign, and that the hand-written CG matches mode="unrolled".
"""

import json
import math

import pytest

from prdp_petsc.reports.bench import main


def test_bench_bridge_quick_writes_json(tmp_path):
    assert main(["bridge", "--quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "bench_bridge.json").read_text())

    assert data["n"] == 4851 and data["k"] == 10
    # ratios of two positive times; overhead = ratio - 1 may have either sign
    assert math.isfinite(data["overhead"]) and data["overhead"] > -1.0
    assert math.isfinite(data["overhead_vs_raw_solve_transpose"])
    for key in (
        "backward_over_forward_symmetric",
        "unrolled_speedup",
        "handwritten_unrolled_speedup",
    ):
        assert math.isfinite(data[key]) and data[key] > 0, key
    # peak RSS growth: finite and not negative (a solve may fit in pages already mapped)
    for key in ("unrolled_peak_rss_mb", "implicit_peak_rss_mb", "handwritten_peak_rss_mb"):
        assert math.isfinite(data[key]) and data[key] >= 0, key

    small = data["throughput"]
    assert small["n"] == 4851 and small["k"] == 10
    for key in ("overhead_1_rhs", "overhead_32_rhs", "extra_per_call_s", "extra_per_rhs_s"):
        assert math.isfinite(small[key]), key
    for batch in data["throughput_detail"]["batches"].values():
        assert all(v > 0 for v in batch["timings_s"]["raw"] + batch["timings_s"]["bridge"])
    over = data["overhead_detail"]
    assert over["ksp"]["raw"] == over["ksp"]["bridge"] == ["cg", "jacobi"]
    for key, values in over["timings_s"].items():
        assert len(values) == data["settings"]["repeats"], key
        assert all(math.isfinite(v) and v > 0 for v in values), key
    unr = data["unrolled_detail"]
    assert set(unr["peak_rss_increase_mb"]) == {"implicit", "unrolled", "handwritten"}
    assert unr["handwritten_grad_rel_diff"] < 1e-10  # same iteration, same gradient
    for key in ("platform", "cpu_count", "versions"):
        assert data["machine"][key]
    assert data["settings"]["rtol"] == data["settings"]["atol"] == 0.0


@pytest.mark.parametrize("flag", ["--k", "--n", "--repeats", "--unrolled-k"])
def test_bench_rejects_non_positive_sizes(tmp_path, flag):
    with pytest.raises(SystemExit):
        main(["bridge", flag, "0", "--out", str(tmp_path)])
    assert not (tmp_path / "bench_bridge.json").exists()
