"""`prdp-petsc rollouts`: per-step rollouts of several runs over seeds, and their ratios."""

import json
import math

import pytest

from prdp_petsc.lab.cli import main as cli_main
from prdp_petsc.lab.reports.rollouts import format_rollout_report, rollout_report


def write_run(folder, rollout, uncorrected, wall=10.0, iterations=100, finished=True):
    folder.mkdir(parents=True)
    result = {
        "finished": finished,
        "rollout": rollout,
        "uncorrected_rollout": uncorrected,
        "totals": {"wall_time": wall, "fwd_iterations": iterations, "adj_iterations": 0,
                   "k_final": 4},
    }  # fmt: skip
    (folder / "results.json").write_text(json.dumps(result))
    return folder


@pytest.fixture
def runs(tmp_path):
    unc = [[0.2, 0.4, 0.5], [0.3, 0.5, 0.6]]
    sol = [write_run(tmp_path / f"sol{i}", [0.1, 0.2, 0.25], unc[i], wall=5, iterations=40)
           for i in range(2)]  # fmt: skip
    noise = [write_run(tmp_path / f"noise{i}", [0.1, 0.45, 1.0], unc[i]) for i in range(2)]
    return {"sol": sol, "noise": noise}


def test_report_counts_steps_below_the_solver_alone_and_takes_ratios(runs):
    report = rollout_report(runs, [("sol", "noise")])
    assert report["steps"] == report["step"] == 3
    assert report["runs"]["sol"]["below_uncorrected_every_step"] == 2
    assert report["runs"]["noise"]["below_uncorrected_every_step"] == 0  # 0.45 > 0.4 …
    ratio = report["ratios"]["sol/noise"]
    assert ratio["error"]["per_seed"] == [0.25, 0.25]
    assert ratio["error"]["geometric_mean"] == pytest.approx(0.25)
    assert ratio["iterations"]["geometric_mean"] == pytest.approx(0.4)
    assert ratio["wall_time"]["geometric_mean"] == pytest.approx(0.5)
    unc = report["uncorrected"]["geometric_mean"]
    assert unc[0] == pytest.approx(math.sqrt(0.2 * 0.3))
    early = rollout_report(runs, [("sol", "noise")], step=2)["ratios"]["sol/noise"]["error"]
    assert early["per_seed"] == pytest.approx([0.2 / 0.45] * 2)
    text = format_rollout_report(report)
    rows = {cells[0]: cells for cells in map(str.split, text.splitlines()[2:5])}
    assert rows["sol"][-1] == "2/2" and rows["noise"][-1] == "0/2" and "0.250" in text


def test_inconsistent_inputs_are_refused(runs, tmp_path):
    with pytest.raises(ValueError, match="same number of seed folders"):
        rollout_report({**runs, "one": runs["sol"][:1]}, [])
    other = write_run(tmp_path / "other", [0.1, 0.1, 0.1], [9.0, 9.0, 9.0])
    with pytest.raises(ValueError, match="another uncorrected rollout"):
        rollout_report({"sol": runs["sol"], "x": [runs["sol"][0], other]}, [])
    unfinished = write_run(tmp_path / "unfinished", [0.1] * 3, [0.2] * 3, finished=False)
    with pytest.raises(ValueError, match="not a finished run"):
        rollout_report({"x": [unfinished]}, [])
    with pytest.raises(ValueError, match="step must lie"):
        rollout_report(runs, [], step=4)


def test_command_writes_json_and_plot(runs, tmp_path, capsys):
    out = tmp_path / "report"
    sol = ",".join(map(str, runs["sol"]))
    noise = ",".join(map(str, runs["noise"]))
    code = cli_main(["rollouts", "--run", f"sol={sol}", "--run", f"noise={noise}",
                     "--ratio", "sol/noise", "--out", str(out)])  # fmt: skip
    assert code == 0
    assert json.loads((out / "rollouts.json").read_text())["runs"]["sol"]["k_final"] == [4, 4]
    assert (out / "rollouts.png").stat().st_size > 1000
    assert "sol/noise" in capsys.readouterr().out
    with pytest.raises(SystemExit) as usage:
        cli_main(["rollouts", "--run", "nonsense", "--out", str(out)])
    assert usage.value.code == 2
