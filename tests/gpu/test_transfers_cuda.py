"""A batch of 16 operators trains with θ, x and the gradients on the GPU: in steady state
no copy between host and device moves a vector or a row of θ, only scalars (CG's dot
products and norms, which PETSc reads on the host).

PETSc's Jacobi checks the inverted diagonal for zeros on the host (a copy there and back
at every PC set-up, i.e. every new θ) unless the Mat is known SPD or
``pc_jacobi_fixdiagonal`` is off, as here.  The copies are those the CUDA profiler
(CUPTI, through ``torch.profiler``) records for the whole process, PETSc's own
included; a deliberate copy of one vector inside the profiled steps shows that it sees
them.  Runs where torch sees a GPU and PETSc was built with CUDA (``.ci/device-run.sh``);
skipped everywhere else, with one reason.
"""

import collections
import json
import sys
from pathlib import Path

import pytest
import torch
from petsc4py import PETSc
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared problems
from _core import interior_operator, randn, random_theta, unit_square  # noqa: E402

import prdp_petsc as pp  # noqa: E402

pytestmark = pytest.mark.skipif(
    not (torch.cuda.is_available() and PETSc.Sys.hasExternalPackage("cuda")),
    reason="needs a GPU that torch sees and a PETSc built with CUDA",
)

BATCH = 16


def copies(prof, folder: Path) -> list[tuple[str, int]]:
    """(direction, bytes) of every host-device copy `prof` recorded."""
    trace = folder / "trace.json"
    prof.export_chrome_trace(str(trace))
    events = json.loads(trace.read_text())["traceEvents"]
    return [
        (e["name"], int(e.get("args", {}).get("bytes", -1)))
        for e in events
        if e.get("cat") == "gpu_memcpy" and ("HtoD" in e["name"] or "DtoH" in e["name"])
    ]


def test_training_steps_move_no_vector_between_host_and_device(tmp_path):
    A = interior_operator(unit_square(4), "P0").A_II
    n, p = A.shape[0], A.n_params
    solver = pp.KSPSolver(
        {
            "ksp_type": "cg",
            "pc_type": "jacobi",
            "pc_jacobi_fixdiagonal": False,
            "vec_type": "cuda",
            "mat_type": "aijcusparse",
        },
        max_it=20,
    )
    target = torch.stack([random_theta(p, seed=10 + i) for i in range(BATCH)]).cuda()
    b = randn(BATCH, n, seed=6).cuda()
    with torch.no_grad():
        x_ref = pp.solve(A, b, solver, theta=target)
    theta = torch.full_like(target, 1.5).requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=0.05)

    def step():
        opt.zero_grad()
        loss = ((pp.solve(A, b, solver, theta=theta) - x_ref) ** 2).sum()
        loss.backward()
        opt.step()
        with torch.no_grad():
            theta.clamp_(min=0.1)

    for _ in range(2):  # set-up: the Mat, its pattern, the PC
        step()
    torch.cuda.synchronize()
    steps = 3
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            step()
        control = x_ref[0].cpu()  # one vector, copied on purpose
        torch.cuda.synchronize()
    seen = copies(prof, tmp_path)
    vector = control.numel() * control.element_size()
    by_size = collections.Counter(seen)
    print(f"n = {n}, p = {p}, {BATCH} operators, {steps} steps: copies (direction, bytes) -> count")
    for (name, size), count in sorted(by_size.items(), key=lambda kv: -kv[0][1]):
        print(f"  {name:40s} {size:8d} B  x {count}")
    control_seen = [(name, size) for name, size in seen if "DtoH" in name and size == vector]
    assert control_seen, f"the profiler did not see the control copy: {by_size}"
    moved = [(name, size) for name, size in seen if size >= 8 * min(n, p)]
    assert moved == control_seen[:1], f"vectors or rows of θ crossed: {sorted(set(moved))}"
