"""Training harness: run / compare on the heat1d scene (quick preset), CLI, divergence."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from petsc4py import PETSc

from prdp_petsc.lab.cli import main
from prdp_petsc.lab.training.compare import compare
from prdp_petsc.lab.training.harness import RunSettings, build_scene, find_k_full, run, to_json
from prdp_petsc.lab.training.scene import load_scene
from prdp_petsc.lab.training.schedules import parse_schedule
from prdp_petsc.lab.training.summary import format_table, summarize

HEAT1D = Path(__file__).resolve().parents[2] / "demos" / "heat1d.py"


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    return out, compare(HEAT1D, preset="quick", out=out, progress=False)


def test_compare_summary_is_complete(summary):
    out, s = summary
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["k_full"] == s["k_full"] > 1
    assert set(on_disk) >= {"scene", "k_full", "runs", "savings", "val_error_ratio", "plots"}
    assert on_disk["threads"] == 1
    assert on_disk["equal_accuracy"] == (on_disk["val_error_ratio"] <= 1.05)
    full = f"fixed:{s['k_full']}"
    assert "prdp" in s["runs"] and full in s["runs"] and "fixed:1" in s["runs"]
    for r in s["runs"].values():
        assert set(r) >= {
            "final_val_error",
            "wall_time",
            "fwd_iterations",
            "adj_iterations",
            "k_final",
        }
        assert np.isfinite(r["final_val_error"]) and r["wall_time"] > 0
    assert s["runs"][full]["k_final"] == s["k_full"]
    for name in on_disk["plots"]:
        assert (out / name).stat().st_size > 1000


def test_savings_match_logged_iterations(summary):
    out, s = summary
    prdp = json.loads((out / "prdp" / "results.json").read_text())
    full = json.loads((out / f"fixed_{s['k_full']}" / "results.json").read_text())
    inner = sum(e["fwd_iterations"] + e["adj_iterations"] for e in prdp["epochs"])
    inner_full = sum(e["fwd_iterations"] + e["adj_iterations"] for e in full["epochs"])
    assert s["savings"]["iterations"] == pytest.approx(1 - inner / inner_full, rel=1e-12)
    # fixed mode: every forward and adjoint solve runs exactly K iterations
    epoch = full["epochs"][0]
    assert epoch["fwd_iterations"] == epoch["adj_iterations"]
    assert epoch["fwd_iterations"] % s["k_full"] == 0
    n_solves = epoch["fwd_iterations"] // s["k_full"]
    for e in prdp["epochs"]:
        assert e["fwd_iterations"] == e["k"] * n_solves
    ic = 1 - prdp["epochs"][-1]["k"] / s["k_full"]
    assert s["savings"]["ic"] == pytest.approx(ic, rel=1e-12)
    assert s["savings"]["pr"] == pytest.approx(s["savings"]["iterations"] - ic, rel=1e-12)
    assert s["val_error_ratio"] == pytest.approx(
        s["runs"]["prdp"]["final_val_error"] / s["runs"][f"fixed:{s['k_full']}"]["final_val_error"]
    )


def test_run_is_deterministic(tmp_path):
    a = run(HEAT1D, "fixed:3", epochs=3, seed=1, out=tmp_path / "a", progress=False)
    b = run(HEAT1D, "fixed:3", epochs=3, seed=1, out=tmp_path / "b", progress=False)
    c = run(HEAT1D, "fixed:3", epochs=3, seed=2, progress=False)
    va = [e["val_metric"] for e in a["epochs"]]
    assert va == [e["val_metric"] for e in b["epochs"]]
    assert va != [e["val_metric"] for e in c["epochs"]]
    assert json.loads((tmp_path / "a" / "results.json").read_text())["totals"]["epochs"] == 3


def test_parse_schedule():
    assert parse_schedule("prdp") == ("prdp", None)
    assert parse_schedule("rtol") == ("rtol", None)
    assert parse_schedule("fixed:7") == ("fixed", 7) and parse_schedule("fixed:7").k == 7
    for bad in ("fixed:0", "fixed:x", "adaptive", "rtol:3"):
        with pytest.raises(ValueError):
            parse_schedule(bad)


def test_cli_run_passes_petsc_options(tmp_path):
    opts = PETSc.Options()
    try:
        rc = main(
            [
                "run",
                str(HEAT1D),
                "--schedule",
                "fixed:4",
                "--epochs",
                "2",
                "--out",
                str(tmp_path),
                "--no-progress",
                "-heat_pc_type",
                "none",
            ]
        )
    finally:
        opts.delValue("heat_pc_type")
    assert rc == 0
    result = json.loads((tmp_path / "results.json").read_text())
    # the adjoint inherits the command-line forward options
    (solver,) = result["solvers"]
    assert solver["prefix"] == "heat_"
    assert solver["forward"] == {"ksp_type": "richardson", "pc_type": "none"}
    assert solver["adjoint"] == {"ksp_type": "richardson", "pc_type": "none"}
    assert [e["k"] for e in result["epochs"]] == [4, 4]
    assert result["threads"] == 1


DIVERGING_SCENE = """
import numpy as np, scipy.sparse as sp, torch
import prdp_petsc as pp
from prdp_petsc.fem.fd import laplacian
from prdp_petsc import lab

PRESETS = {"quick": {}}

def build(config, seed):
    A = (sp.identity(10) - 1e-2 * laplacian(10)).tocsr()
    if config.get("advection"):  # a non-symmetric operator: CG does not fit it
        A = (A + config["advection"] * sp.diags([np.ones(9), -np.ones(9)], [1, -1])).tocsr()
    solver = pp.KSPSolver({"ksp_type": "richardson", "pc_type": "jacobi",
                           "ksp_richardson_scale": 3.0}, prefix="div_", max_it=1)
    theta = torch.ones(10, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([theta], lr=0.1)
    metric = iter(range(1, 100))  # gets worse every epoch: PRDP refines every epoch
    return lab.Scene(
        solvers=[solver], optimizer=opt, batches=lambda e, g: [None],
        loss=lambda _: pp.solve(A, theta, solver).square().sum(),
        validate=lambda: float(next(metric)), probe=lambda: (A, np.ones(10), None), epochs=20,
        prdp={"window": 1, "ema_window": 1, "k_step": 4},
    )
"""


def test_diverged_solve_stops_cleanly(tmp_path):
    scene = tmp_path / "diverging.py"
    scene.write_text(DIVERGING_SCENE)
    # K grows by 4 per epoch; Richardson with scale 3 amplifies the error ~2x per
    # iteration, so PETSc's DTOL (1e5) stops it after ~17 iterations
    result = run(scene, "prdp", out=tmp_path / "out", progress=False)
    stopped = result["stopped"]
    assert stopped is not None and stopped["reason"] == "DIVERGED_DTOL"
    on_disk = json.loads((tmp_path / "out" / "results.json").read_text())
    assert on_disk["stopped"]["epoch"] == stopped["epoch"] == len(on_disk["epochs"]) > 0


# A tiny scene whose presets switch on the situations the harness must survive.
TINY_SCENE = """
from pathlib import Path
import numpy as np, scipy.sparse as sp, torch
import prdp_petsc as pp
from prdp_petsc.fem.fd import laplacian
from prdp_petsc.errors import NonFiniteError
from prdp_petsc import lab

NEVER = 10**9
BASE = {"two_solvers": False, "interrupt_at": NEVER, "invalid_at": NEVER, "bug_at": NEVER,
        "advection": 0.0, "nan_at": NEVER, "odd_info": False, "rising": False}
PRESETS = {
    "quick": BASE,
    "two_solvers": {**BASE, "two_solvers": True},
    "interrupt": {**BASE, "interrupt_at": 1},
    "invalid": {**BASE, "invalid_at": 2},
    "bug": {**BASE, "bug_at": 1},
    "advection": {**BASE, "advection": 0.3},
    "nan_loss": {**BASE, "nan_at": 2},
    "odd_info": {**BASE, "odd_info": True},
    "rising": {**BASE, "rising": True},
}

def build(config, seed):
    A = (sp.identity(10) - 1e-2 * laplacian(10)).tocsr()
    if config["advection"]:  # a non-symmetric operator: CG does not fit it
        A = (A + config["advection"] * sp.diags([np.ones(9), -np.ones(9)], [1, -1])).tocsr()
    solvers = [pp.KSPSolver({"ksp_type": "richardson", "pc_type": "jacobi"},
                            prefix="tiny_", max_it=1)]
    if config["two_solvers"]:
        solvers.append(pp.KSPSolver({"ksp_type": "cg", "pc_type": "none"},
                                    prefix="tiny2_", max_it=1))
    theta = torch.ones(10, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([theta], lr=0.1)

    def batches(epoch, generator):
        if epoch == config["interrupt_at"]:
            raise KeyboardInterrupt
        if epoch >= config["invalid_at"]:
            raise NonFiniteError("b contains NaN or Inf")
        if epoch >= config["bug_at"]:  # a bug in the scene, not a solver outcome
            np.ones(3) + np.ones(4)
        return [epoch]

    calls = []

    def validate():
        calls.append(None)
        if config["rising"]:  # a metric that only gets worse: PRDP refines every epoch
            return float(len(calls))
        return float(theta.detach().square().sum())

    info = {"threads_seen": torch.get_num_threads()}
    if config["odd_info"]:
        info.update(mesh=Path("meshes") / "lshape.msh", h=np.float64(0.5), n=np.int64(3),
                    field=np.arange(3), flag=np.bool_(True), pair=(1, 2))
        info[np.int64(7)] = "seven"
    return lab.Scene(
        solvers=solvers, optimizer=opt, batches=batches,
        loss=lambda epoch: sum(pp.solve(A, theta, s).square().sum() for s in solvers)
        * (float("nan") if epoch >= config["nan_at"] else 1.0),
        validate=validate,
        probe=lambda: (A, np.ones(10), None), epochs=4,
        prdp={"window": 1, "ema_window": 1, "k_step": 2}, info=info,
    )
"""


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.py"
    path.write_text(TINY_SCENE)
    return path


def test_run_sets_and_restores_torch_threads(tiny, tmp_path):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        result = run(tiny, "fixed:2", epochs=1, out=tmp_path / "out", progress=False)
        assert torch.get_num_threads() == 2  # restored
        assert result["info"]["threads_seen"] == 1  # the default: one thread while running
        assert result["threads"] == 1
        assert json.loads((tmp_path / "out" / "results.json").read_text())["threads"] == 1
        again = run(tiny, "fixed:2", epochs=1, threads=2, progress=False)
        assert again["info"]["threads_seen"] == 2 and again["threads"] == 2
    finally:
        torch.set_num_threads(before)
    with pytest.raises(ValueError, match="threads"):
        run(tiny, "fixed:2", epochs=1, threads=0, progress=False)


def test_run_takes_its_settings_grouped_or_as_keywords(tiny):
    grouped = RunSettings(preset="quick", epochs=1, seed=3, progress=False)
    a = run(tiny, "fixed:2", grouped)
    b = run(tiny, "fixed:2", epochs=1, seed=3, progress=False)
    c = run(tiny, "fixed:2", grouped.replace(epochs=2), seed=4)  # a keyword changes one
    assert [e["val_metric"] for e in a["epochs"]] == [e["val_metric"] for e in b["epochs"]]
    assert (a["seed"], len(a["epochs"])) == (3, 1) and (c["seed"], len(c["epochs"])) == (4, 2)
    with pytest.raises(TypeError, match="epoch"):
        run(tiny, "fixed:2", epoch=1)  # a misspelt setting is refused
    with pytest.raises(ValueError, match="checkpoint_every"):
        RunSettings(checkpoint_every=0)


def test_epochs_must_be_positive(tiny):
    for bad in (0, -3):
        with pytest.raises(ValueError, match="epochs"):
            run(tiny, "fixed:2", epochs=bad, progress=False)
    with pytest.raises(ValueError, match="epochs"):
        compare(tiny, epochs=0, progress=False, plots=False)


def test_cli_refuses_nonpositive_epochs(tiny, tmp_path, capsys):
    for bad in ("0", "-2"):
        with pytest.raises(SystemExit) as exit_info:
            main(["run", str(tiny), "--epochs", bad, "--out", str(tmp_path)])
        assert exit_info.value.code == 2
        assert "--epochs" in capsys.readouterr().err


def test_interrupt_is_recorded_then_reraised(tiny, tmp_path):
    with pytest.raises(KeyboardInterrupt):
        run(tiny, "fixed:2", preset="interrupt", out=tmp_path, progress=False)
    result = json.loads((tmp_path / "results.json").read_text())
    assert result["stopped"]["reason"] == "interrupted"
    assert result["stopped"]["epoch"] == 1 == len(result["epochs"])
    assert result["totals"]["epochs"] == 1
    assert result["solvers"][0]["forward"]["ksp_type"] == "richardson"


def test_cli_interrupt_exits_130_and_keeps_results(tiny, tmp_path, capsys):
    rc = main(["run", str(tiny), "--preset", "interrupt", "--out", str(tmp_path), "--no-progress"])
    assert rc == 130
    assert "interrupted" in capsys.readouterr().err
    assert json.loads((tmp_path / "results.json").read_text())["stopped"]["epoch"] == 1


def test_compare_interrupt_writes_summary(tiny, tmp_path):
    with pytest.raises(KeyboardInterrupt):
        compare(tiny, preset="interrupt", out=tmp_path, progress=False, plots=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["runs"]["prdp"]["stopped"]["reason"] == "interrupted"
    assert summary["runs"]["prdp"]["epochs"] == 1
    assert "prdp stopped at epoch 1 (interrupted)" in summary["savings_unavailable"]


def test_info_with_paths_and_numpy_is_written(tiny, tmp_path):
    run(tiny, "fixed:2", preset="odd_info", epochs=1, out=tmp_path, progress=False)
    info = json.loads((tmp_path / "results.json").read_text())["info"]
    assert info["mesh"] == str(Path("meshes") / "lshape.msh")
    assert info["h"] == 0.5 and info["n"] == 3 and info["field"] == [0, 1, 2]
    assert info["flag"] is True and info["pair"] == [1, 2] and info["7"] == "seven"


def test_to_json():
    data = {"t": torch.tensor([1.5, 2.0]), "s": {3, 3}, "o": object, np.float32(0.5): 1}
    out = json.loads(json.dumps(to_json(data)))
    assert out["t"] == [1.5, 2.0] and out["s"] == [3] and out["0.5"] == 1
    assert out["o"] == str(object)


def test_results_describe_every_solver(tiny, tmp_path):
    result = run(tiny, "fixed:3", preset="two_solvers", epochs=2, out=tmp_path, progress=False)
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert on_disk["solvers"] == result["solvers"]
    first, second = on_disk["solvers"]
    assert (first["prefix"], second["prefix"]) == ("tiny_", "tiny2_")
    assert first["forward"] == {"ksp_type": "richardson", "pc_type": "jacobi"}
    assert second["forward"] == {"ksp_type": "cg", "pc_type": "none"}
    assert first["max_it"] == second["max_it"] == 3
    # both solvers' iterations are counted: 3 per forward solve, two solvers
    assert result["epochs"][0]["fwd_iterations"] == 2 * 3


def test_cli_errors_print_one_line(tmp_path, capsys):
    missing = str(tmp_path / "no_such_scene.py")
    rc = main(["run", missing, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 1
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "FileNotFoundError" in err and "no_such_scene.py" in err and "--debug" in err
    with pytest.raises(FileNotFoundError):
        main(["run", missing, "--out", str(tmp_path / "out"), "--debug"])
    # usage errors exit 2, before anything trains, like argparse's own
    for bad in (["--schedule", "fixed:x"], ["--preset", "nope"], ["--set", "lr=abc"]):
        with pytest.raises(SystemExit) as exit_info:
            main(["run", str(HEAT1D), *bad, "--out", str(tmp_path / "o")])
        assert exit_info.value.code == 2
        assert bad[0] in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_version_and_tools_share_the_conventions(tmp_path, capsys):
    import prdp_petsc

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"prdp-petsc {prdp_petsc.__version__}"
    with pytest.raises(SystemExit) as exit_info:  # a tool's usage error: 2
        main(["stability", "--cases", "nope", "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    # a tool's error: one line and 1, the traceback with --debug
    quick = ["work-precision", "poisson", "--preset", "quick", "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as exit_info:  # --k-max 0 was silently 256
        main([*quick, "--k-max", "0"])
    assert exit_info.value.code == 2
    capsys.readouterr()
    argv = [*quick, "--k-max", "2"]
    argv += ["--routes", "cg/no_such_pc"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--debug" in err
    with pytest.raises(ValueError):
        main([*argv, "--debug"])


def test_cli_compare_with_stopped_runs_exits_nonzero(tiny, tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(["compare", str(tiny), "--preset", "invalid", "--epochs", "3", "--out", str(out),
               "--no-progress"])  # fmt: skip
    printed = capsys.readouterr().out
    assert rc == 1
    summary = json.loads((out / "summary.json").read_text())
    full = f"fixed:{summary['k_full']}"
    assert summary["runs"]["prdp"]["stopped"]["reason"] == "NON_FINITE"
    assert summary["runs"]["prdp"]["epochs"] == 2
    assert "savings" not in summary
    # the table has a stopped column and says why there is no savings line
    assert "stopped" in printed.splitlines()[1]
    assert "NON_FINITE at epoch 2" in printed
    assert f"no savings: prdp stopped at epoch 2 (NON_FINITE); {full} stopped" in printed
    assert "runs that stopped early: prdp" in printed


def fake_log(ks, errors, stopped=None):
    """A run's log as `run` returns it, with 10 forward and adjoint iterations per K."""
    epochs = [
        {"epoch": i, "k": k, "val_metric": e, "wall_time": 0.1 * k, "solver_time": 0.05 * k,
         "fwd_iterations": 10 * k, "adj_iterations": 10 * k, "train_loss": 0.0}
        for i, (k, e) in enumerate(zip(ks, errors))
    ]  # fmt: skip
    totals = {"epochs": len(epochs)}
    if epochs:
        totals.update(
            final_val_error=errors[-1],
            best_val_error=min(errors),
            wall_time=sum(e["wall_time"] for e in epochs),
            fwd_iterations=sum(e["fwd_iterations"] for e in epochs),
            adj_iterations=sum(e["adj_iterations"] for e in epochs),
            k_final=ks[-1],
        )
    return {"epochs": epochs, "totals": totals, "stopped": stopped}


def test_summary_flags_prdp_less_accurate_than_k_full():
    full = fake_log([10, 10, 10], [0.3, 0.2, 0.1])
    worse = summarize("s", 10, {"prdp": fake_log([1, 2, 4], [0.5, 0.3, 0.112]), "fixed:10": full})
    assert worse["val_error_ratio"] == pytest.approx(1.12)
    assert worse["equal_accuracy"] is False
    assert worse["savings"]["iterations"] == pytest.approx(1 - 7 / 30)
    warning = "val error ratio 1.12 > 1.05: PRDP did not reach full-fidelity accuracy"
    assert warning in worse["accuracy_warning"]
    lines = format_table(worse).splitlines()
    savings_line = next(i for i, line in enumerate(lines) if line.startswith("PRDP vs K_full"))
    assert warning in lines[savings_line + 1]
    assert "not at equal accuracy" in lines[savings_line + 1]

    equal = summarize("s", 10, {"prdp": fake_log([1, 2, 4], [0.5, 0.3, 0.104]), "fixed:10": full})
    assert equal["equal_accuracy"] is True and "accuracy_warning" not in equal
    assert "equal accuracy" not in format_table(equal)


def test_table_shows_stopped_runs_and_why_savings_are_missing():
    logs = {
        "prdp": fake_log([1, 2], [0.5, 0.4], {"epoch": 2, "reason": "DIVERGED_DTOL"}),
        "fixed:10": fake_log([10, 10, 10], [0.3, 0.2, 0.1]),
        "fixed:1": fake_log([], [], {"epoch": 0, "reason": "DIVERGED_NANORINF"}),
    }
    summary = summarize("s", 10, logs)
    assert "savings" not in summary
    table = format_table(summary)
    rows = {line.split()[0]: line for line in table.splitlines()[2:5]}
    assert rows["prdp"].endswith("DIVERGED_DTOL at epoch 2")
    assert rows["fixed:10"].endswith("no")
    assert rows["fixed:1"].split()[1:5] == ["—", "—", "0", "—"]
    lines = table.splitlines()
    assert lines[-3] == (
        "PRDP vs K_full: no savings: prdp stopped at epoch 2 (DIVERGED_DTOL); "
        "savings need prdp and fixed:10 over the same epochs"
    )
    # neither stopped run reaches full-fidelity accuracy: no speedup, and why
    assert lines[-2].startswith(
        "speedup vs best full fidelity: none, no reduced run (prdp, fixed:1) reached"
    )
    # fixed:10 spends half of each epoch in the solver: a cheaper one gains at most 2x
    assert lines[-1].startswith("  solver-only bound: 2.00x (fixed:10's wall time")


def test_prdp_run_caps_k_at_k_full(tiny, tmp_path):
    """A rising metric refines every epoch; `run` stops K at K_full unless told not to."""
    k_full = find_k_full(build_scene(load_scene(tiny), "rising", 0))
    capped = run(tiny, "prdp", preset="rising", epochs=30, progress=False)
    ks = [e["k"] for e in capped["epochs"]]
    assert capped["prdp"]["k_max"] == k_full and max(ks) == k_full and ks[-1] == k_full
    free = run(tiny, "prdp", preset="rising", epochs=30, progress=False, prdp={"k_max": None})
    assert free["prdp"]["k_max"] is None and free["epochs"][-1]["k"] > k_full
    own = run(tiny, "prdp", preset="rising", epochs=30, progress=False, prdp={"k_max": 5})
    assert max(e["k"] for e in own["epochs"]) == 5


@pytest.mark.parametrize(("flag", "expected"), [("none", None), ("7", 7)])
def test_cli_k_max(tiny, tmp_path, flag, expected):
    args = ["run", str(tiny), "--preset", "rising", "--epochs", "30", "--no-progress"]
    assert main([*args, "--k-max", flag, "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "results.json").read_text())
    assert result["prdp"]["k_max"] == expected
    ks = [e["k"] for e in result["epochs"]]
    assert max(ks) == 7 if expected == 7 else max(ks) > 7  # the cap held, or none was set


@pytest.mark.parametrize("bad", ["0", "-1", "many"])
def test_cli_refuses_a_bad_k_max(tiny, tmp_path, capsys, bad):
    with pytest.raises(SystemExit) as exit_info:
        main(["run", str(tiny), "--k-max", bad, "--out", str(tmp_path)])
    assert exit_info.value.code == 2 and "--k-max" in capsys.readouterr().err


def test_summary_bounds_incomplete_convergence_from_the_constant_runs():
    """e(K) = e_full (1 + 0.5^(K - 4)): fixed:4 and fixed:8 fit rho = 0.5, K_5% = 9."""
    errors = {k: 0.1 * (1 + 0.5 ** (k - 4)) for k in (1, 4, 8)}
    logs = {f"fixed:{k}": fake_log([k] * 3, [1.0, 0.5, e]) for k, e in errors.items()}
    logs["fixed:16"] = fake_log([16] * 3, [1.0, 0.5, 0.1])
    summary = summarize("s", 16, logs)
    bound = summary["equal_accuracy_k"]
    assert bound["pair"] == (4, 8) and bound["rho"] == pytest.approx(0.5)
    assert bound["fitted"] == 9 and bound["measured"] == 16
    assert bound["ic_bound"] == pytest.approx(1 - 9 / 16)
    line = next(x for x in format_table(summary).splitlines() if x.startswith("smallest"))
    assert "16 of the runs, ≈ 9 fitting" in line and "at most 44 %" in line
    # a twin 20 % away says the constant runs cannot resolve 5 %
    logs["twin:16"] = fake_log([16] * 3, [1.0, 0.5, 0.12])
    assert "do not resolve a 5 % difference" in format_table(summarize("s", 16, logs))


def test_a_bug_in_a_scene_propagates_and_the_cli_exits_1(tiny, tmp_path, capsys):
    # a numpy broadcast error is a ValueError, but not a solver outcome: never "stopped"
    with pytest.raises(ValueError, match="broadcast"):
        run(tiny, "fixed:2", preset="bug", epochs=3, out=tmp_path, progress=False)
    rc = main(["run", str(tiny), "--preset", "bug", "--epochs", "3", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 1 and "broadcast" in err and err.count("\n") == 1


def test_a_nan_loss_stops_the_run_with_a_named_reason(tiny, tmp_path):
    result = run(tiny, "fixed:2", preset="nan_loss", epochs=5, out=tmp_path, progress=False)
    stopped = result["stopped"]
    assert stopped["reason"] == "NON_FINITE" and stopped["epoch"] == 2
    assert len(result["epochs"]) == 2  # epochs 0 and 1 complete; none trained on NaN
    assert json.loads((tmp_path / "results.json").read_text())["stopped"] == stopped
    assert (
        main(["run", str(tiny), "--preset", "nan_loss", "--epochs", "4", "--out", str(tmp_path)])
        == 1
    )


def test_compare_skips_a_route_that_does_not_fit_and_says_so(tiny, tmp_path, capsys):
    rc = main(["compare", str(tiny), "--preset", "advection", "--epochs", "2", "--out",
               str(tmp_path), "--no-progress", "--routes", "cg/jacobi,gmres/jacobi"])  # fmt: skip
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert "StructureError" not in printed and rc == 0
    assert "ksp_type cg" in summary["routes"]["cg/jacobi"]["skipped"]
    assert "cg/jacobi: skipped, it does not fit the scene's solver" in printed
    assert not any(name.endswith("@cg/jacobi") for name in summary["runs"])  # never trained
    assert "savings" in summary["routes"]["gmres/jacobi"]  # the fitting route ran


def test_results_record_the_settings_the_scene_read(tmp_path):
    result = run(HEAT1D, "fixed:2", preset="quick lr=0.002", epochs=1, out=tmp_path,
                 progress=False)  # fmt: skip
    recorded = json.loads((tmp_path / "results.json").read_text())["config"]
    assert recorded == result["config"] and recorded["lr"] == 0.002
    assert set(recorded) == set(load_scene(HEAT1D).PRESETS["quick"])
