"""The plots of `compare` and `compare --seeds`: scaled to their data, one style per
run, plain tick labels, and PNGs of the promised size."""

import itertools

import numpy as np
import pytest

pytest.importorskip("matplotlib")
from matplotlib.image import imread  # noqa: E402

from prdp_petsc.lab.training.plots import (  # noqa: E402
    LOG_SPAN,
    compare_figures,
    plain_number,
    plot_compare,
    run_label,
    run_styles,
    scale_axis,
)
from prdp_petsc.lab.training.seeds import plot_seeds, seeds_figure  # noqa: E402

K_FULLS = {"": 52, "cg/icc": 8}


def _log(k, val, *, its=10, rollout=None, stopped=None, route=("richardson", "jacobi")):
    """A `run` result as `compare` hands it to `plot_compare`: what the plots read."""
    k = [k] * len(val) if np.isscalar(k) else k
    epochs = [
        {"epoch": i, "k": kk, "val_metric": v, "wall_time": 0.01 * kk,
         "fwd_iterations": its * kk, "adj_iterations": its * kk}
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
    curve = lambda: list(np.sort(rng.uniform(low, high, 6))[::-1])  # noqa: E731
    steps = np.arange(1, 21)
    roll = (lambda s: list(0.05 * s * (1 + s % 3))) if rollout else (lambda s: None)
    cg = ("cg", "icc")
    return {
        "prdp": _log([2, 2, 4, 4, 8, 8], curve(), rollout=roll(steps)),
        "fixed:52": _log(52, curve(), rollout=roll(steps)),
        "fixed:1": _log(1, curve(), rollout=roll(steps)),
        "fixed:13": _log(13, curve(), rollout=roll(steps)),
        "fixed:26": _log(26, curve(), rollout=roll(steps)),
        "prdp@cg/icc": _log([1, 1, 2, 2, 2, 2], curve(), rollout=roll(steps), route=cg),
        "fixed:8@cg/icc": _log(8, curve(), rollout=roll(steps), route=cg),
    }


def _tick_labels(fig) -> list[str]:
    fig.draw_without_rendering()
    return [
        t.get_text()
        for ax in fig.axes
        for axis in (ax.xaxis, ax.yaxis)
        for t in axis.get_ticklabels(which="both")
        if t.get_text()
    ]


def _assert_plain(labels):
    assert labels
    for text in labels:
        assert not any(s in text for s in ("×10", "10^", "\\times", "$", "e+")), text


def _data_lines(ax):
    return [line for line in ax.get_lines() if not line.get_label().startswith("_")]


def _axes_fraction(ax, ys):
    """Where `ys` lie in `ax`'s height, 0 at the bottom, 1 at the top."""
    x = ax.get_xlim()[0]
    return ax.transAxes.inverted().transform(ax.transData.transform([[x, y] for y in ys]))[:, 1]


def test_plot_compare_writes_each_png_at_its_size(tmp_path):
    files = plot_compare(_logs(), K_FULLS, tmp_path)
    assert files == ["error_vs_time.png", "error_vs_iterations.png", "k_schedule.png",
                     "rollout.png"]  # fmt: skip
    for name in files:
        image = imread(tmp_path / name)
        assert image.shape[:2] == (504, 960), name  # 8 x 4.2 inches at 120 dpi
        assert image[..., :3].std() > 0.05, name  # something is drawn


def test_rollout_png_only_when_a_run_recorded_one(tmp_path):
    assert "rollout.png" not in plot_compare(_logs(rollout=False), K_FULLS, tmp_path)


@pytest.mark.parametrize("fname", ["error_vs_time.png", "error_vs_iterations.png"])
def test_errors_between_045_and_08_fill_the_height(fname):
    ax = compare_figures(_logs(0.45, 0.8), K_FULLS)[fname].axes[0]
    assert ax.get_yscale() == "linear"  # 0.8 / 0.45 is less than a decade
    lo, hi = _axes_fraction(ax, [0.45, 0.8])
    assert 0 < lo < hi < 1  # the limits enclose the data ...
    assert hi - lo >= 0.5  # ... and the data cover most of the height
    assert hi - lo == pytest.approx(1 / 1.1, abs=0.03)  # the 5 % margins, no more
    for line in _data_lines(ax):  # and the x limits enclose every point
        x0, x1 = ax.get_xlim()
        assert x0 < line.get_xdata().min() and line.get_xdata().max() < x1


def test_errors_over_decades_get_a_log_axis_that_encloses_them():
    logs = _logs()
    logs["fixed:1"] = _log(1, [3e2, 40.0, 5.0, 1.0, 0.2, 1e-3])  # one run far off
    for fname in ("error_vs_time.png", "error_vs_iterations.png"):
        ax = compare_figures(logs, K_FULLS)[fname].axes[0]
        assert ax.get_yscale() == "log"
        lo, hi = ax.get_ylim()
        assert lo < 1e-3 and 3e2 < hi < 3e2 * 10**0.5  # from the data, not 10 x the top
        _assert_plain(_tick_labels(ax.figure))
    # cumulative iterations span 10 to 3120 per epoch: a log x axis
    its = compare_figures(logs, K_FULLS)["error_vs_iterations.png"].axes[0]
    assert its.get_xscale() == "log"


def test_k_schedule_and_rollout_axes():
    figs = compare_figures(_logs(), K_FULLS)
    k = figs["k_schedule.png"].axes[0]
    assert k.get_yscale() == "log"  # K from 1 to 52
    assert k.get_ylim()[0] < 1 and 52 < k.get_ylim()[1]
    assert set(_tick_labels(k.figure)) >= {"1", "2", "5", "10", "20", "50"}
    assert [t for t in k.get_xticks() if 1 <= t <= 6] == [1, 2, 3, 4, 5, 6]  # epochs
    roll = figs["rollout.png"].axes[0]
    assert all(float(t).is_integer() for t in roll.get_xticks())  # steps, not 2.5
    assert roll.get_xlim()[0] < 1 and 20 < roll.get_xlim()[1]


def test_each_run_in_a_figure_has_its_own_style_and_a_label_in_words():
    logs = _logs()
    logs["fixed:40"] = _log(40, [0.5] * 3, stopped={"epoch": 3, "reason": "NON_FINITE"})
    logs["fixed:2"] = {"epochs": []}  # nothing to draw
    for fname, fig in compare_figures(logs, K_FULLS).items():
        lines = _data_lines(fig.axes[0])
        styles = {(ln.get_color(), str(ln.get_linestyle()), ln.get_marker()) for ln in lines}
        labels = [ln.get_label() for ln in lines]
        stopped = "K = 40, richardson/jacobi (stopped: NaN or Inf)"
        assert labels == [
            "PRDP, richardson/jacobi",
            "K = 52 (full), richardson/jacobi",
            *([stopped] if fname != "rollout.png" else []),  # a stopped run has no rollout
            "K = 26, richardson/jacobi",
            "K = 13, richardson/jacobi",
            "K = 1, richardson/jacobi",
            "PRDP, cg/icc",
            "K = 8 (full), cg/icc",
        ], fname
        assert len(styles) == len(lines), fname
        assert fig.legends and [t.get_text() for t in fig.legends[0].get_texts()] == labels
        _assert_plain(_tick_labels(fig))


def test_run_styles_are_distinct_and_deterministic_over_many_names():
    routes = ["", "cg/icc", "gmres/ilu", "bcgs/jacobi", "richardson/sor"]
    schedules = ["prdp", "twin:52"] + [f"fixed:{k}" for k in range(1, 60)]
    names = [s + (f"@{r}" if r else "") for r, s in itertools.product(routes, schedules)]
    k_fulls = {"": 52, "cg/icc": 8, "gmres/ilu": 20}
    styles = run_styles(names, k_fulls)
    keys = {(s["color"], str(s["linestyle"]), s["marker"]) for s in styles.values()}
    assert len(keys) == len(names) == len(styles)
    assert run_styles(names[::-1], k_fulls) == styles  # order does not matter
    # the rules of the module docstring
    assert styles["prdp"]["color"] == styles["prdp@cg/icc"]["color"] == "C3"
    assert styles["fixed:52"]["color"] == styles["fixed:8@cg/icc"]["color"] == "C0"
    assert styles["fixed:52"]["marker"] == "s" and styles["twin:52"]["color"] == "C7"
    assert styles["prdp"]["linestyle"] == "-" != styles["prdp@cg/icc"]["linestyle"]
    assert styles["prdp"]["markerfacecolor"] == "C3"
    assert styles["prdp@cg/icc"]["markerfacecolor"] == "none"
    assert styles["prdp"]["linewidth"] > styles["fixed:52"]["linewidth"]
    # a small figure: the coarser K each get a colour of their own
    small = run_styles(["prdp", "fixed:52", "fixed:1", "fixed:13", "fixed:26"], 52)
    assert len({s["color"] for s in small.values()}) == 5
    assert list(small) == ["prdp", "fixed:52", "fixed:26", "fixed:13", "fixed:1"]


def test_run_label():
    assert run_label("prdp") == "PRDP"
    assert run_label("prdp@cg/icc", K_FULLS) == "PRDP, cg/icc"
    assert run_label("fixed:52", K_FULLS) == "K = 52 (full)"
    assert run_label("fixed:13", 52) == "K = 13"
    assert run_label("fixed:8@cg/icc", K_FULLS) == "K = 8 (full), cg/icc"
    assert run_label("fixed:52@cg/icc", K_FULLS) == "K = 52, cg/icc"
    assert run_label("twin:52", K_FULLS) == "K = 52 (full), second seed"
    assert run_label("fixed:52", K_FULLS, route_name="gmres/ilu") == "K = 52 (full), gmres/ilu"
    # one route in the figure: no route in the labels
    assert {s["label"] for s in run_styles(["prdp", "fixed:52"], 52).values()} == {
        "PRDP",
        "K = 52 (full)",
    }
    # several, without word for the scene's own solver
    assert run_styles(["prdp", "prdp@cg/icc"], K_FULLS)["prdp"]["label"] == "PRDP, scene's solver"


@pytest.mark.parametrize(
    ("value", "text"),
    [(1.07, "1.07"), (1.0, "1"), (0.30000000000000004, "0.3"), (0.05, "0.05"),
     (20000.0, "20000"), (1e-5, "1e-05"), (0.0, "0")],
)  # fmt: skip
def test_plain_number(value, text):
    assert plain_number(value) == text


@pytest.mark.parametrize(
    ("values", "log"),
    [([0.45, 0.8], False), ([1.0, 1.0 * LOG_SPAN], False), ([1.0, 1.01 * LOG_SPAN], True),
     ([-1.0, 100.0], False), ([0.9, 1.2], False), ([np.nan, 0.5, np.inf, 0.7], False)],
)  # fmt: skip
def test_scale_axis_decade_rule_and_margins(values, log):
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    ax.plot([0, 1], [1, 2])  # autoscaled limits that must not survive
    assert scale_axis(ax, "y", [values]) is log
    finite = [v for v in values if np.isfinite(v)]
    lo, hi = _axes_fraction(ax, [min(finite), max(finite)])
    assert hi - lo == pytest.approx(1 / 1.1, abs=1e-9)  # 5 % of the span each side
    _assert_plain(_tick_labels(ax.figure))


def test_scale_axis_forced_log_under_a_decade_has_plain_labels():
    from matplotlib.figure import Figure

    for values in ([0.95, 1.07, 1.2], [0.4, 2.5]):
        ax = Figure().add_subplot()
        assert scale_axis(ax, "y", [values], log=True)
        labels = _tick_labels(ax.figure)
        _assert_plain(labels)
        assert len(labels) >= 3  # a short log axis still gets numbers to read
    with pytest.raises(ValueError, match="positive"):
        scale_axis(Figure().add_subplot(), "y", [[0.0, 1.0]], log=True)


def _seeds_result(ratios, twins, saved):
    rows = [
        {"seed": s, "prdp_ratio": r, "twin_ratio": t, "wall_time_saved": w}
        for s, (r, t, w) in enumerate(zip(ratios, twins, saved, strict=True))
    ]
    return {"scene": "toy", "per_seed": rows, "accuracy": 1.05}


def test_seeds_png_size_styles_limits_and_plain_ticks(tmp_path):
    result = _seeds_result([1.07, 0.95, 1.2], [0.98, 1.12, 1.03], [0.42, -0.08, 0.51])
    assert plot_seeds(result, tmp_path) == "seeds.png"
    assert imread(tmp_path / "seeds.png").shape[:2] == (504, 1200)
    fig = seeds_figure(result)
    left, right = fig.axes
    assert left.get_yscale() == "log"  # ratios: 10 % worse and better weigh the same
    lo, hi = _axes_fraction(left, [0.95, 1.2])
    assert 0 < lo and hi < 1 and hi - lo >= 0.8  # the points fill the panel
    labels = _tick_labels(fig)
    _assert_plain(labels)
    ylabels = [t.get_text() for t in left.get_yticklabels() if t.get_text()]
    assert len(ylabels) >= 3 and "1.00" in ylabels
    bottom, top = right.get_ylim()
    assert bottom < -8 and 51 < top < 60  # a negative saving stays on the panel
    markers = {ln.get_marker() for ln in _data_lines(left) if ln.get_marker() != "None"}
    assert markers == {"o", "D"}  # PRDP and its twin, marked as in compare's plots


def test_seeds_without_a_ratio_draw_nothing(tmp_path):
    result = {"scene": "toy", "per_seed": [{"seed": 0}], "accuracy": 1.05}
    assert seeds_figure(result) is None and plot_seeds(result, tmp_path) is None
    assert not (tmp_path / "seeds.png").exists()
