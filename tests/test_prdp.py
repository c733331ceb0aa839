"""Tests of the PRDP controller on synthetic metric histories.

Every expected K schedule below was worked out by hand from docs/maths.md §7 (EMA
values for the noisy cases are written next to the test), not by re-running the code.
Defaults: tau_step 0.98, tau_stop 0.9, ema_window 6 (alpha = 2/7), window 3, so the
plateau test at call t + 1 compares E_t with E_{t-2} and first runs at the 4th call.
"""

import json
import logging
import math

import pytest

from prdp_petsc.prdp import PRDP, PRDPStep, savings

ALPHA = 2 / 7


def run(ctrl, metrics):
    """Feed the metrics; return the K returned after each call."""
    return [ctrl.update(m) for m in metrics]


def test_constant_metric_refines_once_then_stops():
    # Call 4: r = 1 > 0.98 (plateau), r_c = 1/inf = 0 < 0.9 -> refine, checkpoint 1.
    # Call 5: r = 1, r_c = 1 in [0.9, 1] -> the refinement bought nothing: stop.
    ctrl = PRDP()
    assert run(ctrl, [1.0] * 8) == [1, 1, 1, 2, 2, 2, 2, 2]
    assert [s.k for s in ctrl.history] == [1, 1, 1, 1, 2, 2, 2, 2]
    assert [s.refined for s in ctrl.history] == [False] * 3 + [True] + [False] * 4
    assert ctrl.refining is False
    assert ctrl.k == 2


def test_constant_metric_with_restart_window_waits_before_stopping():
    # Refine at call 4; the next test needs window = 3 metrics with K = 2 (calls 5-7),
    # so the stop comes at call 7 instead of call 5.
    ctrl = PRDP(restart_window=True)
    refining = []
    for _ in range(8):
        ctrl.update(1.0)
        refining.append(ctrl.refining)
    assert [s.k_next for s in ctrl.history] == [1, 1, 1, 2, 2, 2, 2, 2]
    assert refining == [True] * 6 + [False] * 2


def test_geometric_decay_never_refines():
    # H_t = 0.9^t. E_1 = 1 - 0.1 alpha, E_2 = 0.81 alpha + (1 - alpha) E_1; each ratio
    # E_t / E_{t-1} <= E_1 / E_0 = 0.9714, so r = E_t / E_{t-2} < 0.9714^2 < 0.98 always.
    ctrl = PRDP()
    assert run(ctrl, [0.9**t for t in range(40)]) == [1] * 40
    e1 = 1 - 0.1 * ALPHA
    assert ctrl.history[1].ema == pytest.approx(e1, rel=1e-14)
    assert ctrl.history[2].ema == pytest.approx(0.81 * ALPHA + (1 - ALPHA) * e1, rel=1e-14)
    assert ctrl.refining is True


# H = 1.00, 1.05, 0.95, 1.05, ... ; E (6 d.p.) = 1, 1.014286, 0.995918, 1.011370, 0.993836,
# 1.009883, 0.992773, 1.009124, 0.992231. Every r = E_t/E_{t-2} is in (0.997, 1): plateau.
# Call 4 refines with checkpoint E_3 = 1.011370, a noise peak; later r_c = E_t / 1.011370
# lies in [0.981, 0.999]: stop, K stays 2.
NOISE_PEAK = [1.0, 1.05, 0.95, 1.05, 0.95, 1.05, 0.95, 1.05, 0.95]
# H = 1.00, 0.95, 1.05, 0.95, ... ; E = 1, 0.985714, 1.004082, 0.988630, 1.006164, 0.990117,
# 1.007227, 0.990876, 1.007769, 0.991263, 1.008045 (peaks creep up towards 1.00833).
# Call 4 refines with checkpoint at a trough (E_3 = 0.988630); each later peak exceeds the
# previous checkpoint: r_c = 1.0177 (call 5), 1.00106 (call 7), 1.00054 (9), 1.00027 (11)
# -> refine; troughs give r_c ~ 0.984 -> stop. The reference ratchets K up on noise.
NOISE_TROUGH = [1.0, 0.95, 1.05, 0.95, 1.05, 0.95, 1.05, 0.95, 1.05, 0.95, 1.05]


def test_noise_around_plateau_checkpoint_at_peak_stops():
    assert run(PRDP(), NOISE_PEAK) == [1, 1, 1, 2, 2, 2, 2, 2, 2]


def test_noise_around_plateau_checkpoint_at_trough_ratchets():
    ctrl = PRDP()
    assert run(ctrl, NOISE_TROUGH) == [1, 1, 1, 2, 3, 3, 4, 4, 5, 5, 6]
    assert ctrl.history[3].ema == pytest.approx(0.988630, abs=1e-6)
    assert ctrl.history[4].ema == pytest.approx(1.006164, abs=1e-6)


def test_noise_with_restart_window():
    # Each refinement restarts the EMA from the next metric and the window after it.
    # Call 4 refines (checkpoint E_3 = 0.988630). Calls 5-7 restart E at 1.05:
    # E = 1.05, 1.021429, 1.029592; call 7: r = 0.98056 (plateau), r_c = 1.0414 -> refine
    # (checkpoint 1.029592). Calls 8-11: E = 0.95, 0.978571, 0.970408, 0.993149; calls 10
    # and 11 are plateaus with r_c = 0.9425 and 0.9646: bought less than 10 % -> stop.
    ctrl = PRDP(restart_window=True)
    assert run(ctrl, NOISE_TROUGH) == [1, 1, 1, 2, 2, 2, 3, 3, 3, 3, 3]
    assert [s.ema for s in ctrl.history[4:8]] == pytest.approx([1.05, 1.021429, 1.029592, 0.95])
    assert ctrl.refining is False


def test_restart_window_forgets_a_blow_up_at_the_old_k():
    """An unstable rollout at K = 1 (1e4) must not read as "improving" at K = 2."""
    metrics = [1e4] * 4 + [2.0, 2.2, 2.4, 2.6]  # K = 2 trains, its metric rises
    assert run(PRDP(), metrics) == [1, 1, 1, 2, 2, 2, 2, 2]  # the EMA is still falling
    assert run(PRDP(restart_window=True), metrics) == [1, 1, 1, 2, 2, 2, 3, 3]


def test_noise_with_tau_worse_tolerance():
    # With tau_worse 1.05 the largest r_c after call 4 (1.008045 / 0.988630 = 1.0196) and
    # the smallest (0.990117 / 0.988630 = 1.0015) both mean "bought nothing": K stays 2.
    ctrl = PRDP(tau_worse=1.05)
    assert run(ctrl, NOISE_TROUGH) == [1, 1, 1] + [2] * 8
    assert ctrl.refining is False


def test_divergence_after_stop_resumes_refinement():
    # Calls 1-5 as in the constant test (refine at 4, stop at 5, checkpoint 1).
    # Call 6: E = 1 + alpha = 1.2857 (metric 2): plateau, r_c = 1.2857 > 1 -> refine,
    # checkpoint 1.2857. Call 7: E = 1 + alpha (2 - alpha) = 1.4898, r_c = 1.1587 -> refine.
    ctrl = PRDP()
    refining = []
    for m in [1.0] * 5 + [2.0, 2.0]:
        ctrl.update(m)
        refining.append(ctrl.refining)
    assert [s.k_next for s in ctrl.history] == [1, 1, 1, 2, 2, 3, 4]
    assert refining == [True] * 4 + [False] + [True] * 2
    assert ctrl.history[6].ema == pytest.approx(1 + ALPHA * (2 - ALPHA), rel=1e-14)


def test_divergence_with_restart_window():
    # Refine at call 4; calls 5, 6 are inside the restarted window; call 7: E_6 / E_4 =
    # 1.4898 plateau, r_c = 1.4898 / 1 > 1 -> refine.
    assert run(PRDP(restart_window=True), [1.0] * 5 + [2.0, 2.0]) == [1, 1, 1, 2, 2, 2, 3]


def test_use_ema_false_two_refinements_stop_and_resume():
    # Without EMA, r = H_t / H_{t-2} (0-based t):
    # t=3: r=1 -> refine (cp 1.0)   t=4,5: r=0.5 keep   t=6: r=1, r_c=0.5 -> refine (cp 0.5)
    # t=7: r=0.49/0.5=0.98 <= tau_step keep   t=8: 0.96 keep   t=9: 0.48/0.49 keep
    # t=10: r=1, r_c=0.96 -> stop   t=11: r=1.25, r_c=1.2 -> refine (cp 0.6)   t=12: r_c=1 stop
    metrics = [1.0] * 4 + [0.5] * 3 + [0.49, 0.48, 0.48, 0.48, 0.6, 0.6]
    ctrl = PRDP(use_ema=False)
    refining = []
    for m in metrics:
        ctrl.update(m)
        refining.append(ctrl.refining)
    assert [s.k_next for s in ctrl.history] == [1, 1, 1, 2, 2, 2, 3, 3, 3, 3, 3, 4, 4]
    assert [s.k for s in ctrl.history] == [1, 1, 1, 1, 2, 2, 2, 3, 3, 3, 3, 3, 4]
    assert refining == [True] * 10 + [False, True, False]
    assert [s.ema for s in ctrl.history] == metrics


def test_ema_window_one_equals_no_ema():
    metrics = [1.0] * 4 + [0.5] * 3 + [0.49, 0.48, 0.48, 0.48, 0.6, 0.6]
    assert run(PRDP(ema_window=1), metrics) == run(PRDP(use_ema=False), metrics)


def test_k_max_caps_refinement():
    # window 2, rising metric: every call from the 3rd is a plateau with r_c > 1 (the
    # first with r_c = 0): K 1 -> 3 -> 5 -> 6 (capped) -> 6 (no increase: not "refined").
    ctrl = PRDP(k_step=2, k_max=6, window=2, use_ema=False)
    assert run(ctrl, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) == [1, 1, 3, 5, 6, 6]
    assert [s.refined for s in ctrl.history] == [False, False, True, True, True, False]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_metric_raises_and_changes_nothing(bad):
    ctrl = PRDP()
    run(ctrl, [1.0, 1.0])
    before = ctrl.state_dict()
    with pytest.raises(ValueError, match="diverged"):
        ctrl.update(bad)
    assert ctrl.state_dict() == before


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"k_init": 0}, "k_init"),
        ({"k_step": 0}, "k_step"),
        ({"k_init": 3, "k_max": 2}, "k_max"),
        ({"tau_step": 0.0}, "tau_step"),
        ({"tau_step": math.nan}, "tau_step"),
        ({"tau_stop": 0.0}, "tau_stop"),
        ({"tau_stop": 1.01}, "tau_stop"),
        ({"ema_window": 0}, "ema_window"),
        ({"window": 0}, "window"),
        ({"k_min": 0}, "k_min"),
        ({"k_min": 2}, "k_min"),
        ({"tau_worse": 0.99}, "tau_worse"),
    ],
)
def test_invalid_arguments_are_rejected_by_name(kwargs, name):
    with pytest.raises(ValueError, match=name):
        PRDP(**kwargs)


def test_negative_metric_rejected():
    with pytest.raises(ValueError, match="metric"):
        PRDP().update(-1.0)


def test_savings_on_known_numbers():
    s = savings([1, 1, 2, 2, 3], 10)
    assert s["total"] == pytest.approx(1 - 9 / 50)
    assert s["ic"] == pytest.approx(0.7)
    assert s["pr"] == pytest.approx(0.12)


def test_savings_from_costs():
    # Seconds per epoch 2, 2, 4 vs 8 s per baseline epoch: total 1 - 8/24, IC 1 - 4/8.
    for cost_full in (8.0, [8.0, 8.0, 8.0], [6.0, 8.0, 10.0]):
        s = savings(costs=[2.0, 2.0, 4.0], cost_full=cost_full)
        assert s["total"] == pytest.approx(2 / 3)
        assert s["ic"] == pytest.approx(0.5)
        assert s["pr"] == pytest.approx(1 / 6)
    with pytest.raises(ValueError, match="cost_full"):
        savings(costs=[1.0])
    with pytest.raises(ValueError, match="empty"):
        savings([], 10)


def test_controller_savings_uses_k_per_epoch():
    # Constant metric: K used = 1, 1, 1, 1, 2, 2, 2, 2; against K_full = 4:
    # total = 1 - 12/32 = 0.625, IC = 1 - 2/4 = 0.5, PR = 0.125.
    ctrl = PRDP()
    run(ctrl, [1.0] * 8)
    got = ctrl.savings(4)
    assert {k: got[k] for k in ("total", "ic", "pr")} == pytest.approx(
        {"total": 0.625, "ic": 0.5, "pr": 0.125}
    )
    # no check ran: the savings say nothing about accuracy
    assert (got["certified"], got["gap"], got["checks"]) == (None, None, 0)
    assert got["check_share"] == 0.0
    iters = [10, 10, 10, 10, 20, 20, 20, 20]
    measured = ctrl.savings(costs=iters, cost_full=40)
    assert measured["check_share"] is None
    assert {k: measured[k] for k in ("total", "ic", "pr")} == pytest.approx(
        {k: got[k] for k in ("total", "ic", "pr")}
    )


@pytest.mark.parametrize("split", [2, 7])
def test_state_dict_round_trip_through_json(split):
    metrics = [1.0] * 4 + [0.5] * 3 + [0.49, 0.48, 0.48, 0.48, 0.6, 0.6]
    a = PRDP(use_ema=False)
    run(a, metrics[:split])
    b = PRDP(use_ema=False)
    b.load_state_dict(json.loads(json.dumps(a.state_dict())))
    assert (b.k, b.refining, b.history) == (a.k, a.refining, a.history)
    assert run(b, metrics[split:]) == run(a, metrics[split:])
    assert b.history == a.history
    assert all(isinstance(s, PRDPStep) for s in b.history)
    with pytest.raises(ValueError, match="missing"):
        PRDP().load_state_dict({"k": 1})


def test_level_counts_refinements_from_k_min():
    ctrl = PRDP(k_init=3, k_min=3)
    assert ctrl.level == 0
    run(ctrl, [1.0] * 4)  # refines once
    assert (ctrl.k, ctrl.level) == (4, 1)


def test_refinement_is_logged(caplog):
    with caplog.at_level(logging.INFO, logger="prdp_petsc.prdp"):
        run(PRDP(), [1.0] * 5)
    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert any("K 1 -> 2" in m for m in messages)
    assert any("stop refining at K=2" in m for m in messages)


def test_state_dict_round_trip_through_a_checkpoint():
    """The state a training checkpoint saves (``torch.load(weights_only=True)``), with
    every field in play: a restarted window, an infinite checkpoint."""
    import io

    import torch

    metrics = [1.0, 1.0, 2.0, 0.5, 0.5, 0.5, 0.49, 0.6, 0.6, 0.6, 0.3]
    for split in range(len(metrics) + 1):
        a = PRDP(restart_window=True, window=2, ema_window=3, k_max=4)
        run(a, metrics[:split])
        buffer = io.BytesIO()
        torch.save(a.state_dict(), buffer)
        buffer.seek(0)
        b = PRDP(restart_window=True, window=2, ema_window=3, k_max=4)
        b.load_state_dict(torch.load(buffer, weights_only=True))
        assert b.state_dict() == a.state_dict()
        assert run(b, metrics[split:]) == run(a, metrics[split:])
        assert b.history == a.history and b.refining == a.refining
    assert a.k == 4
    assert a.state_dict()["fresh"] is False and a.state_dict()["start"] > 1
    empty = PRDP().state_dict()
    assert empty["checkpoint"] == math.inf and empty["ema"] == [] and empty["history"] == []
