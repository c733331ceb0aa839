"""The plots of `compare` and `compare --seeds` draw the recorded data, one style and
one label in words per run."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from prdp_petsc.lab.training.plots import (  # noqa: E402
    compare_figures,
    plot_compare,
    run_label,
    run_styles,
)
from prdp_petsc.lab.training.seeds import plot_seeds, seeds_figure  # noqa: E402

K_FULLS = {"": 52, "cg/icc": 8}


def _log(k, val, *, rollout=None, stopped=None, route=("richardson", "jacobi")):
    """A `run` result as `compare` hands it to `plot_compare`: what the plots read."""
    k = [k] * len(val) if np.isscalar(k) else k
    epochs = [
        {"epoch": i, "k": kk, "val_metric": v, "wall_time": 0.01 * kk + 0.001 * i,
         "fwd_iterations": 10 * kk, "adj_iterations": 9 * kk}
        for i, (kk, v) in enumerate(zip(k, val, strict=True))
    ]  # fmt: skip
    log = {"scene": "toy", "preset": "quick", "seed": 0, "epochs": epochs, "stopped": stopped}
    log["solvers"] = [{"forward": {"ksp_type": route[0], "pc_type": route[1]}}]
    if rollout is not None:
        log["rollout"] = list(rollout)
    return log


def _logs(low=0.45, high=0.8, *, rollout=True):
    """Seven runs on two routes whose validation errors lie in [low, high]."""
    rng = np.random.default_rng(0)
    roll = list(0.05 * np.arange(1, 21)) if rollout else None
    cg = ("cg", "icc")
    runs = {"prdp": [2, 2, 4, 4, 8, 8], "fixed:52": 52, "fixed:1": 1, "fixed:13": 13,
            "fixed:26": 26, "prdp@cg/icc": [1, 1, 2, 2, 2, 2], "fixed:8@cg/icc": 8}  # fmt: skip
    return {
        name: _log(k, list(np.sort(rng.uniform(low, high, 6))[::-1]), rollout=roll,
                   route=cg if "@" in name else ("richardson", "jacobi"))
        for name, k in runs.items()
    }  # fmt: skip


def _lines(fig):
    return {ln.get_label(): ln for ln in fig.axes[0].get_lines()}


def test_plot_compare_writes_its_files_and_rollout_only_when_recorded(tmp_path):
    files = plot_compare(_logs(), K_FULLS, tmp_path)
    assert files == ["error_vs_time.png", "error_vs_iterations.png", "k_schedule.png",
                     "rollout.png"]  # fmt: skip
    assert all((tmp_path / f).stat().st_size > 10_000 for f in files)
    assert "rollout.png" not in plot_compare(_logs(rollout=False), K_FULLS, tmp_path)


def test_every_curve_is_the_recorded_data():
    logs = _logs()
    figs = compare_figures(logs, K_FULLS)
    styles = run_styles(logs, K_FULLS, route_names={"": "richardson/jacobi"})
    for name, log in logs.items():
        ep = log["epochs"]
        time = np.cumsum([e["wall_time"] for e in ep])
        its = np.cumsum([e["fwd_iterations"] + e["adj_iterations"] for e in ep])
        val = [e["val_metric"] for e in ep]
        label = styles[name]["label"]
        for fname, x, y in (("error_vs_time.png", time, val),
                            ("error_vs_iterations.png", its, val),
                            ("k_schedule.png", np.arange(1, 7), [e["k"] for e in ep]),
                            ("rollout.png", np.arange(1, 21), log["rollout"])):  # fmt: skip
            line = _lines(figs[fname])[label]
            np.testing.assert_allclose(line.get_xdata(), x, err_msg=f"{fname} {name}")
            np.testing.assert_allclose(line.get_ydata(), y, err_msg=f"{fname} {name}")


def test_legend_names_each_run_in_words_and_in_order():
    logs = _logs()
    logs["fixed:40"] = _log(40, [0.5] * 3, stopped={"epoch": 3, "reason": "NON_FINITE"})
    logs["fixed:2"] = {"epochs": []}  # nothing to draw
    fig = compare_figures(logs, K_FULLS)["error_vs_time.png"]
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == [
        "PRDP, richardson/jacobi",
        "K = 52 (full), richardson/jacobi",
        "K = 40, richardson/jacobi (stopped: NaN or Inf)",
        "K = 26, richardson/jacobi",
        "K = 13, richardson/jacobi",
        "K = 1, richardson/jacobi",
        "PRDP, cg/icc",
        "K = 8 (full), cg/icc",
    ]
    lines = fig.axes[0].get_lines()
    assert len({(ln.get_color(), ln.get_linestyle(), ln.get_marker()) for ln in lines}) == 8


def test_an_axis_over_more_than_a_decade_is_logarithmic():
    figs = compare_figures(_logs(0.45, 0.8), K_FULLS)
    assert figs["error_vs_time.png"].axes[0].get_yscale() == "linear"  # 0.8 / 0.45 < 10
    assert figs["k_schedule.png"].axes[0].get_yscale() == "log"  # K from 1 to 52
    assert figs["k_schedule.png"].axes[0].get_xscale() == "linear"  # epochs are counts
    logs = _logs()
    logs["fixed:1"] = _log(1, [3e2, 40.0, 5.0, 1.0, 0.2, 1e-3])  # one run far off
    assert compare_figures(logs, K_FULLS)["error_vs_time.png"].axes[0].get_yscale() == "log"


def test_run_styles_follow_the_schedule_and_the_route_in_any_order():
    names = ["prdp", "fixed:52", "twin:52", "fixed:1", "fixed:13", "fixed:26", "rtol",
             "prdp@cg/icc", "fixed:8@cg/icc", "rtol@cg/icc"]  # fmt: skip
    styles = run_styles(names, K_FULLS)
    assert run_styles(names[::-1], K_FULLS) == styles
    keys = {(s["color"], s["linestyle"], s["marker"]) for s in styles.values()}
    assert len(keys) == len(names)
    assert styles["prdp"]["color"] == styles["prdp@cg/icc"]["color"]
    assert styles["fixed:52"]["color"] == styles["fixed:8@cg/icc"]["color"]  # full fidelity
    assert styles["prdp"]["linestyle"] != styles["prdp@cg/icc"]["linestyle"]
    assert list(styles)[:6] == ["prdp", "fixed:52", "twin:52", "fixed:26", "fixed:13", "fixed:1"]


def test_run_label():
    assert run_label("prdp") == "PRDP"
    assert run_label("prdp@cg/icc", K_FULLS) == "PRDP, cg/icc"
    assert run_label("fixed:52", K_FULLS) == "K = 52 (full)"
    assert run_label("fixed:13", 52) == "K = 13"
    assert run_label("fixed:8@cg/icc", K_FULLS) == "K = 8 (full), cg/icc"
    assert run_label("fixed:52@cg/icc", K_FULLS) == "K = 52, cg/icc"
    assert run_label("twin:52", K_FULLS) == "K = 52 (full), second seed"
    assert run_label("fixed:52", K_FULLS, route_name="gmres/ilu") == "K = 52 (full), gmres/ilu"
    one = run_styles(["prdp", "fixed:52"], 52)  # one route in the figure: no route named
    assert [s["label"] for s in one.values()] == ["PRDP", "K = 52 (full)"]
    assert run_styles(["prdp", "prdp@cg/icc"], K_FULLS)["prdp"]["label"] == "PRDP, scene's solver"


def test_seeds_figure_draws_each_seeds_ratios_and_saving(tmp_path):
    rows = [
        {"seed": s, "prdp_ratio": r, "twin_ratio": t, "wall_time_saved": w}
        for s, r, t, w in [(0, 1.07, 0.98, 0.42), (1, 0.95, None, -0.08), (3, 1.2, 1.03, 0.51)]
    ]
    result = {"scene": "toy", "per_seed": [*rows, {"seed": 4}], "accuracy": 1.05}
    assert plot_seeds(result, tmp_path) == "seeds.png" and (tmp_path / "seeds.png").is_file()
    left, right = seeds_figure(result).axes
    lines = {ln.get_label(): ln for ln in left.get_lines()}
    assert list(lines["PRDP / full"].get_ydata()) == [1.07, 0.95, 1.2]
    assert list(lines["twin / full (second seed)"].get_ydata()) == [0.98, 1.03]
    assert [t.get_text() for t in left.get_xticklabels()] == ["0", "1", "3"]  # seed 4: no ratio
    assert [p.get_height() for p in right.patches] == pytest.approx([42, -8, 51])
    empty = {"scene": "toy", "per_seed": [{"seed": 0}], "accuracy": 1.05}
    assert seeds_figure(empty) is None and plot_seeds(empty, tmp_path / "none") is None
