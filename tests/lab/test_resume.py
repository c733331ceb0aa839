"""Checkpoint and resume: a run stopped at epoch k and resumed equals one that never
stopped, bitwise on one thread; the checkpoint is the saved model; results carry
their provenance."""

import json
import re
from pathlib import Path

import pytest
import torch

from prdp_petsc.errors import InputError
from prdp_petsc.lab.cli import main
from prdp_petsc.lab.provenance import DISTRIBUTIONS, git_commit, provenance
from prdp_petsc.lab.training.checkpoint import CHECKPOINT, load_checkpoint, recorded_run
from prdp_petsc.lab.training.compare import compare
from prdp_petsc.lab.training.harness import load_trained, release, run, torch_threads

ROOT = Path(__file__).resolve().parents[2]
HEAT2D = ROOT / "demos" / "heat.py"
POISSON = ROOT / "demos" / "poisson_inverse.py"

# A network trained through a capped solve, with everything a resume must restore:
# Adam's moments, a StepLR schedule (its step depends on its own epoch count), PRDP's
# state (window 1: K moves often), the batch order's generator, and noise from
# torch's, numpy's and Python's global generators; leaving any one of them out of
# the checkpoint changes the resumed epochs.  RESUME_INTERRUPT_AT=k makes epoch k
# raise KeyboardInterrupt (Ctrl-C).
NOISY_SCENE = """
import os, random
import numpy as np, scipy.sparse as sp, scipy.sparse.linalg as spla, torch
import prdp_petsc as pp
from prdp_petsc.fem.fd import laplacian
from prdp_petsc import lab
from prdp_petsc.lab.training.scene import shuffled_batches

PRESETS = {"quick": {"epochs": 6, "lr": 2e-2}, "slow": {"epochs": 6, "lr": 1e-3}}

def build(config, seed):
    n = 12
    A = (sp.identity(n) - 0.2 * laplacian(n)).tocsr()
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(rng.standard_normal((16, n)))
    y = torch.from_numpy(spla.spsolve(A.tocsc(), x.numpy().T).T.copy())
    net = torch.nn.Sequential(torch.nn.Linear(n, 16), torch.nn.Tanh(), torch.nn.Linear(16, n))
    net = net.double()
    opt = torch.optim.Adam(net.parameters(), lr=config["lr"])
    solver = pp.KSPSolver({"ksp_type": "richardson", "pc_type": "jacobi"},
                          prefix="noisy_", max_it=1)
    order = shuffled_batches(16, 4)

    def batches(epoch, generator):
        if epoch == int(os.environ.get("RESUME_INTERRUPT_AT", "-1")):
            raise KeyboardInterrupt
        return order(epoch, generator)

    def loss(idx):
        noise = torch.randn(len(idx), n, dtype=torch.float64)
        noise = noise + np.random.standard_normal() + random.random()
        u = pp.solve(A, net(x[idx] + 1e-3 * noise), solver)
        return (u - y[idx]).square().mean()

    def validate():
        with torch.no_grad():
            return float((pp.solve(A, net(x), solver) - y).square().mean())

    return lab.Scene(
        solvers=[solver], optimizer=opt, batches=batches, loss=loss, validate=validate,
        probe=lambda: (A, np.ones(n), None), epochs=config["epochs"],
        prdp={"window": 1, "ema_window": 1, "k_step": 1},
        scheduler=torch.optim.lr_scheduler.StepLR(opt, step_size=2, gamma=0.5),
    )
"""

KEYS = ("k", "train_loss", "val_metric", "fwd_iterations", "adj_iterations")


@pytest.fixture
def noisy(tmp_path):
    path = tmp_path / "noisy.py"
    path.write_text(NOISY_SCENE)
    return path


def _epochs(result):
    return [{key: e[key] for key in KEYS} for e in result["epochs"]]


def _parameters(folder):
    return load_checkpoint(Path(folder) / CHECKPOINT)["parameters"]


def assert_same_training(straight, resumed, folders):
    """Every epoch's numbers and the final parameters bitwise equal."""
    assert _epochs(resumed) == _epochs(straight)
    a, b = (_parameters(f) for f in folders)
    assert len(a) == len(b) > 0
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_interrupted_run_resumes_bitwise(noisy, tmp_path, monkeypatch):
    straight = run(noisy, "prdp", out=tmp_path / "straight", progress=False)
    ks = [e["k"] for e in straight["epochs"]]
    assert len(set(ks)) > 1  # PRDP moved K: its state matters after the resume
    monkeypatch.setenv("RESUME_INTERRUPT_AT", "3")
    with pytest.raises(KeyboardInterrupt):
        run(noisy, "prdp", out=tmp_path / "cut", progress=False)
    cut = json.loads((tmp_path / "cut" / "results.json").read_text())
    assert cut["stopped"]["reason"] == "interrupted" and cut["finished"] is False
    assert cut["checkpoint"] == {"file": CHECKPOINT, "epoch": 3}
    monkeypatch.delenv("RESUME_INTERRUPT_AT")
    resumed = run(resume=tmp_path / "cut", progress=False)
    assert_same_training(straight, resumed, [tmp_path / "straight", tmp_path / "cut"])
    assert resumed["stopped"] is None and resumed["finished"] is True
    assert [r["epoch"] for r in resumed["resumed"]] == [3]
    on_disk = json.loads((tmp_path / "cut" / "results.json").read_text())
    assert _epochs(on_disk) == _epochs(straight)
    assert on_disk["provenance"] == cut["provenance"]  # of the process that started it
    assert on_disk["totals"]["epochs"] == 6 and on_disk["checkpoint"]["epoch"] == 6


def test_resume_after_sparse_checkpoints_trains_the_lost_epochs_again(noisy, tmp_path):
    straight = run(noisy, "fixed:3", out=tmp_path / "straight", progress=False)
    part = run(noisy, "fixed:3", epochs=5, checkpoint_every=2, out=tmp_path / "part",
               progress=False)  # fmt: skip
    assert part["checkpoint"]["epoch"] == 5  # every second epoch, and the last
    state = load_checkpoint(tmp_path / "part" / CHECKPOINT)
    assert state["epoch"] == 5 and len(state["result"]["epochs"]) == 5
    resumed = run(resume=tmp_path / "part", epochs=6, progress=False)
    assert_same_training(straight, resumed, [tmp_path / "straight", tmp_path / "part"])


def test_resume_refuses_a_checkpoint_whose_epochs_disagree_with_its_count(noisy, tmp_path):
    run(noisy, "fixed:3", epochs=3, out=tmp_path, progress=False)
    state = load_checkpoint(tmp_path / CHECKPOINT)
    state["result"]["epochs"].pop()  # a damaged file: 3 epochs trained, 2 recorded
    torch.save(state, tmp_path / CHECKPOINT)
    with pytest.raises(InputError, match="the checkpoint records 2 epochs, not 3"):
        run(resume=tmp_path, epochs=4, progress=False)


@pytest.mark.parametrize(("scene", "cut"), [(HEAT2D, 3), (POISSON, 17)])
def test_real_scenes_resume_bitwise(scene, cut, tmp_path):
    """A finished run of `cut` epochs, resumed to the preset's count, equals a straight
    run: heat2d (ModalNet, Adam, LR schedule, rollout) and poisson_inverse (θ, SGD)."""
    straight = run(scene, "prdp", out=tmp_path / "straight", progress=False)
    n = len(straight["epochs"])
    assert straight["finished"] and n > cut
    short = run(scene, "prdp", epochs=cut, out=tmp_path / "short", progress=False)
    assert short["finished"] and short["requested_epochs"] == cut
    resumed = run(resume=tmp_path / "short", epochs=n, progress=False)
    assert_same_training(straight, resumed, [tmp_path / "straight", tmp_path / "short"])
    ks = [e["k"] for e in resumed["epochs"]]
    assert ks == [e["k"] for e in straight["epochs"]] and len(set(ks)) > 1
    assert resumed.get("rollout") == straight.get("rollout")
    assert resumed["requested_epochs"] == n and resumed["finished"]


def test_load_trained_reproduces_the_recorded_validation(noisy, tmp_path):
    result = run(noisy, "prdp", out=tmp_path, progress=False)
    scene = load_trained(tmp_path)
    try:
        assert scene.solvers[0].max_it == result["epochs"][-1]["k"]
        with torch_threads(result["threads"]):
            assert scene.validate() == result["totals"]["final_val_error"]
    finally:
        release(scene)
    untrained = load_trained(tmp_path)  # the parameters are the checkpoint's, not build's
    assert all(
        torch.equal(p, q)
        for p, q in zip(
            (p for g in untrained.optimizer.param_groups for p in g["params"]),
            _parameters(tmp_path),
            strict=True,
        )
    )
    release(untrained)


def test_load_trained_heat2d(tmp_path):
    result = run(HEAT2D, "fixed:8", epochs=3, out=tmp_path, progress=False)
    scene = load_trained(tmp_path)
    with torch_threads(1):
        assert scene.validate() == result["epochs"][-1]["val_metric"]
    release(scene)


def _as_before_the_merge(folder: Path, scene: str, preset: str) -> None:
    """Make `folder`'s results.json read as a run of demos/<scene>.py, as runs of heat2d
    and heat3d were recorded before the two became demos/heat.py."""
    path = folder / "results.json"
    recorded = json.loads(path.read_text())
    recorded.update(scene=scene, scene_file=str(ROOT / "demos" / f"{scene}.py"), preset=preset)
    path.write_text(json.dumps(recorded))


def test_a_run_of_heat2d_from_before_the_merge_loads_and_resumes(tmp_path):
    result = run(HEAT2D, "fixed:8", epochs=2, out=tmp_path, progress=False)
    _as_before_the_merge(tmp_path, "heat2d", "quick")
    scene = load_trained(tmp_path)
    with torch_threads(1):
        assert scene.validate() == result["epochs"][-1]["val_metric"]
    release(scene)
    resumed = run(resume=tmp_path, epochs=3, progress=False)
    assert resumed["finished"] and len(resumed["epochs"]) == 3
    assert resumed["scene_file"] == str(HEAT2D) and resumed["preset"] == "quick"


def test_a_run_of_heat3d_from_before_the_merge_names_the_cube_presets(tmp_path):
    (tmp_path / "results.json").write_text(json.dumps({
        "scene": "heat3d", "scene_file": str(ROOT / "demos" / "heat3d.py"),
        "preset": "paper k_step=5", "requested_epochs": 3,
    }))  # fmt: skip
    recorded = recorded_run(tmp_path)
    assert recorded["scene_file"] == str(HEAT2D) and recorded["scene"] == "heat"
    assert recorded["preset"] == "paper3d k_step=5"


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"preset": "slow"}, "preset='slow'"),
        ({"seed": 1}, "seed=1"),
        ({"schedule": "fixed:2"}, "schedule='fixed:2'"),
        ({"torch_seed": 7}, "torch_seed=7"),
        ({"prdp": {"k_step": 5}}, "prdp k_step=5"),
        ({"epochs": 1}, "more than epochs=1"),
    ],
)
def test_resume_refuses_other_settings(noisy, tmp_path, change, words):
    run(noisy, "prdp", epochs=2, out=tmp_path, progress=False)
    with pytest.raises(InputError, match=re.escape(words)):
        run(resume=tmp_path, progress=False, **change)
    # the recorded settings, given explicitly, are fine
    again = run(noisy, "prdp", preset="quick", seed=0, resume=tmp_path, progress=False)
    assert len(again["epochs"]) == 2


def test_cli_resume(noisy, tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    base = ["run", str(noisy), "--schedule", "fixed:2", "--no-progress", "--out", str(out)]
    assert main([*base, "--epochs", "2", "--checkpoint-every", "2"]) == 0
    assert main(["run", "--resume", str(out), "--epochs", "4", "--no-progress"]) == 0
    result = json.loads((out / "results.json").read_text())
    assert result["totals"]["epochs"] == 4 and result["resumed"][0]["epoch"] == 2
    straight = run(noisy, "fixed:2", epochs=4, progress=False)
    assert _epochs(result) == _epochs(straight)
    capsys.readouterr()
    # no checkpoint: one line, exit 1 (a run interrupted in its first epoch has none)
    monkeypatch.setenv("RESUME_INTERRUPT_AT", "0")
    assert main([*base[:-1], str(tmp_path / "cut")]) == 130
    for folder in (tmp_path / "cut", tmp_path / "nothing"):
        capsys.readouterr()
        assert main(["run", "--resume", str(folder)]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "FileNotFoundError" in err and "resume" in err
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--out", str(tmp_path / "x")])  # neither a scene nor --resume
    assert exit_info.value.code == 2
    assert "SCENE_FILE, or --resume" in capsys.readouterr().err


def test_compare_resume_skips_finished_runs_and_resumes_interrupted(noisy, tmp_path, monkeypatch):
    kwargs = {"epochs": 4, "progress": False, "plots": False, "twin": True}
    straight = compare(noisy, out=tmp_path / "straight", **kwargs)
    out = tmp_path / "cut"
    monkeypatch.setenv("RESUME_INTERRUPT_AT", "2")  # the first run, prdp, stops at 2
    with pytest.raises(KeyboardInterrupt):
        compare(noisy, out=out, **kwargs)
    monkeypatch.delenv("RESUME_INTERRUPT_AT")
    resumed = compare(noisy, out=out, resume=True, **kwargs)
    k_full = resumed["k_full"]
    assert resumed["reused"] == []
    prdp = json.loads((out / "prdp" / "results.json").read_text())
    assert [r["epoch"] for r in prdp["resumed"]] == [2]
    for name in straight["runs"]:
        folder = name.replace(":", "_")
        a = json.loads((tmp_path / "straight" / folder / "results.json").read_text())
        b = json.loads((out / folder / "results.json").read_text())
        assert _epochs(a) == _epochs(b), name
    assert set(resumed["runs"]) == set(straight["runs"]) and f"twin:{k_full}" in resumed["runs"]
    # everything finished: a third call reads the runs, trains nothing
    before = {p: p.read_text() for p in out.glob("*/results.json")}
    again = compare(noisy, out=out, resume=True, **kwargs)
    assert sorted(again["reused"]) == sorted(straight["runs"])
    assert {p: p.read_text() for p in out.glob("*/results.json")} == before
    assert again["runs"] == resumed["runs"]
    # more epochs: every run continues from its checkpoint
    longer = compare(noisy, out=out, resume=True, **{**kwargs, "epochs": 5})
    assert longer["reused"] == []
    full = json.loads((out / f"fixed_{longer['k_full']}" / "results.json").read_text())
    assert [r["epoch"] for r in full["resumed"]] == [4] and full["totals"]["epochs"] == 5


def test_provenance_keys():
    record = provenance(threads=3, ranks=2)
    assert set(record) == {
        "versions", "command", "git", "timestamp", "host", "torch_threads", "mpi_ranks",
    }  # fmt: skip
    assert set(record["versions"]) == {*DISTRIBUTIONS, "petsc", "python"}
    assert re.fullmatch(r"3\.\d+\.\d+", record["versions"]["petsc"])
    assert record["versions"]["torch"] == torch.__version__
    assert record["torch_threads"] == 3 and record["mpi_ranks"] == 2
    assert record["host"]["cpus"] >= 1
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d[+-]\d\d:\d\d", record["timestamp"])
    if (ROOT / ".git").exists():  # a checkout: its commit; not one: null
        assert re.fullmatch(r"[0-9a-f]{40}", record["git"]["commit"])
        assert isinstance(record["git"]["dirty"], bool)
    else:
        assert record["git"] is None


def test_git_commit_is_null_outside_a_checkout(tmp_path):
    assert git_commit(tmp_path) is None
    assert git_commit(tmp_path / "no_such_folder") is None


def test_results_and_summary_carry_provenance(noisy, tmp_path):
    compare(noisy, epochs=1, out=tmp_path, progress=False, plots=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    results = json.loads((tmp_path / "prdp" / "results.json").read_text())
    for record in (summary["provenance"], results["provenance"]):
        assert record["torch_threads"] == 1 and record["mpi_ranks"] == 1
        assert record["versions"]["prdp-petsc"] is not None
    assert results["scene_file"] == str(noisy.resolve())
