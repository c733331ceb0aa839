"""`prdp-petsc bench gpu --preset quick` on the GPU: the PETSc contenders run on CUDA
types, every contender agrees with prdp_petsc, and the GPU path with the CPU path, to
the bounds the results page judges (tests/lab/test_bench_gpu.py runs the same on the CPU).

Runs where torch sees a GPU and PETSc was built with CUDA (``.ci/device-run.sh``); skipped
everywhere else, with one reason.  Times are never compared.
"""

import json

import pytest
import torch
from petsc4py import PETSc

from prdp_petsc.lab.reports import bench_gpu

pytestmark = pytest.mark.skipif(
    not (torch.cuda.is_available() and PETSc.Sys.hasExternalPackage("cuda")),
    reason="needs a GPU that torch sees and a PETSc built with CUDA",
)


def test_quick_benchmark_runs_on_cuda_types_and_agrees(tmp_path):
    args = ["--out", str(tmp_path), "--preset", "quick", "--device", "cuda", "--budget-s", "0"]
    assert bench_gpu.main(args) == 0
    d = json.loads((tmp_path / "bench_gpu.json").read_text())
    assert d["device"]["kind"] == "cuda" and d["skipped"] == []
    for cell in d["cells"]:
        assert cell["reference"] == "prdp_petsc", cell["notes"]
        assert {"raw_petsc", "torch_pcg"} <= set(cell["median_s"]), cell["notes"]
        info = cell["info"]
        assert info["prdp_petsc"]["mat_type"] == "seqaijcusparse"
        assert info["prdp_petsc"]["forward_iterations_per_solve"] == cell["k"]
        assert (info["raw_petsc"]["mat_type"], info["raw_petsc"]["vec_type"]) == (
            "seqaijcusparse",
            "seqcuda",
        )
        # fixed-mode CG is the same arithmetic everywhere: x and the gradient to rounding
        for name, diff in cell["agreement"].items():
            assert max(diff["x"], diff["grad"]) < 1e-10, name
    for name, a in d["cpu_gpu_agreement"].items():
        assert max(a["x"], a["grad"]) <= a["target"], name
    gamg = d["time_to_tolerance"]["lshape3"]["gamg"]
    assert gamg["grad_error"] <= 1e-6 and gamg["info"]["mat_type"] == "seqaijcusparse"
