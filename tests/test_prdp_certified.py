"""PRDP built from the problem (`PRDP.for_problem`) and its certified checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

import prdp_petsc as pp
from prdp_petsc.prdp import ACCURACY_BAND, CHECK_BUDGET, fidelity_gap


def gap_check(rho=0.7, scale=1.0):
    """A check whose answer at cap k is off from K_full's by scale·rho^k (relative)."""

    def check(k):
        return np.array([1.0 + scale * rho**k, 1.0])

    return check


def test_for_problem_takes_start_step_and_cap_from_k_full():
    ctrl = pp.PRDP.for_problem(104)
    assert (ctrl.k_init, ctrl.k_max, ctrl.k_full, ctrl.tol) == (13, 104, 104, ACCURACY_BAND)
    ks, k = [], ctrl.k
    while True:
        ks.append(k)
        if k == 104:
            break
        k = ctrl.next_k(k)
    assert ks == [13, 26, 52, 104]
    assert pp.PRDP.for_problem(3).k_init == 1
    assert pp.PRDP.for_problem(104, k_init=5).k_init == 5  # overrides win
    with pytest.raises(ValueError, match="k_full"):
        pp.PRDP.for_problem(0)


def test_the_reference_constants_are_one_named_preset():
    ctrl = pp.PRDP.paper()
    assert (ctrl.k_init, ctrl.k_step, ctrl.growth, ctrl.k_max, ctrl.k_full) == (
        1,
        1,
        1.0,
        None,
        None,
    )
    assert (ctrl.tau_step, ctrl.tau_stop, ctrl.ema_window, ctrl.window) == (0.98, 0.9, 6, 3)
    assert ctrl.next_k() == 2
    assert pp.PRDP.paper(k_init=25, k_step=10).next_k() == 35  # the paper's Poisson runs


def test_fidelity_gap_of_numbers_and_arrays():
    assert fidelity_gap(1.1, 1.0) == pytest.approx(0.1)
    assert fidelity_gap(np.array([[1.0, 2.0]]), np.array([[1.0, 1.0]])) == pytest.approx(1 / 2**0.5)


@pytest.mark.parametrize(
    ("at_k", "at_full", "match"),
    [
        ([3.0, 4.0], [0.0, 0.0], "all zeros"),  # would certify nothing / anything
        (np.zeros(3), np.zeros(3), "all zeros"),  # 0/0 used to certify any K
        (np.array([np.nan]), np.array([1.0]), "NaN or Inf at K"),
        (np.array([1.0]), np.array([math.inf]), "NaN or Inf at K_full"),
    ],
)
def test_a_check_that_cannot_decide_raises(at_k, at_full, match):
    with pytest.raises(ValueError, match=match):
        fidelity_gap(at_k, at_full)


def test_a_zero_check_raises_in_the_loop():
    ctrl = pp.PRDP.for_problem(64, check=lambda k: np.zeros(4))
    with pytest.raises(ValueError, match="all zeros"):
        for _ in range(10):
            ctrl.update(1.0)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_metric_raises_and_leaves_k(bad):
    ctrl = pp.PRDP.for_problem(64, check=gap_check())
    ctrl.update(1.0)
    with pytest.raises(ValueError, match="diverged"):
        ctrl.update(bad)
    assert ctrl.k == 8 and len(ctrl.history) == 1


def test_refines_until_the_check_certifies_then_stays():
    # gap at k against 2k: (0.65^k - 0.65^2k) / sqrt(2) -> 2.2 % at k = 8, inside half
    # the band; K_full 64: 8, 16, 32, 64
    ctrl = pp.PRDP.for_problem(64, check=gap_check(rho=0.65))
    for _ in range(40):
        ctrl.update(1.0)  # a flat metric: every window is a plateau
    assert ctrl.k == 8 and not ctrl.refining
    s = ctrl.savings()
    assert s["certified"] is True and s["gap"] < 0.025 and s["ic"] == pytest.approx(1 - 8 / 64)
    # a recheck (8 + 16) and the end's certificate (8 + 64) would pass 10 % of these 40
    # epochs at K = 8, so none is made
    assert s["checks"] == 1
    # every check (one evaluation at K, one at the cap it is compared with) is counted,
    # as an epoch at its cap
    spent = 40 * 8 + sum(c.k + c.against for c in ctrl.checks)
    assert s["total"] == pytest.approx(1 - spent / (40 * 64))
    assert s["check_share"] == pytest.approx(1 - 40 * 8 / spent)
    half = ctrl.savings(check_weight=0.5)  # a check half as large as an epoch
    assert half["total"] == pytest.approx(1 - (40 * 8 + (spent - 320) / 2) / (40 * 64))
    assert ctrl.savings(check_weight=0)["total"] == pytest.approx(1 - 8 / 64)


@pytest.mark.parametrize("epochs", [None, 400])
def test_a_gap_near_the_band_that_no_recheck_can_follow_refines(epochs):
    # gap 3.8 % at K = 8 against 16: above half the band.  A 40-epoch run (not told its
    # length) can pay for no recheck, so K = 8 is not certified on it and K doubles
    # (0.2 % at 16); told 400 epochs, the controller certifies 8 and checks it again
    ctrl = pp.PRDP.for_problem(64, check=gap_check(rho=0.7), epochs=epochs)
    for _ in range(40 if epochs is None else epochs):
        ctrl.update(1.0)
    first = ctrl.checks[0]
    assert (first.k, first.against) == (8, 16) and 0.025 < first.gap <= 0.05
    assert first.certified  # within the band: what refines is the budget, not the gap
    assert ctrl.certify().certified
    if epochs is None:
        assert ctrl.k == 16 and [c.k for c in ctrl.checks][:2] == [8, 16]
    else:
        assert ctrl.k == 8 and len(ctrl.checks) > 2  # rechecked while the run goes on


def test_too_small_k_is_refined_even_while_the_metric_keeps_falling():
    # a steadily improving metric never plateaus; the due check still finds K too small
    ctrl = pp.PRDP.for_problem(64, k_init=2, check=gap_check(rho=0.9))
    for epoch in range(60):
        ctrl.update(0.97**epoch)
    assert ctrl.k >= 32  # 0.9^k / sqrt(2) < 0.05 needs k >= 32
    assert ctrl.checks[-1].certified


def test_a_learning_rate_decay_plateau_cannot_stop_refinement():
    # the metric flattens (a decayed learning rate) while K is still too small:
    # the reference's test stops ("the refinement bought < 10 %"), the certified one refines
    metric = [1.0 / (1 + e) for e in range(8)] + [0.125] * 52
    ref = pp.PRDP(k_init=8, k_step=8, k_max=64)
    cert = pp.PRDP.for_problem(64, check=gap_check(rho=0.9))
    for m in metric:
        ref.update(m)
        cert.update(m)
    assert ref.k < 32 and not ref.refining
    assert cert.k >= 32 and cert.savings()["certified"] is True


def test_a_metric_that_rises_with_k_does_not_ratchet_k():
    # compliance through a capped solve reads low at small K: raising K raises the metric,
    # which the reference reads as "got worse" and answers with another refinement
    def metric_at(k):
        return 15.4 - 2.0 * 0.8**k

    check = gap_check(rho=0.6)  # K = 8 is enough: 0.6^8 / sqrt(2) < 0.05
    ref, cert = pp.PRDP(k_init=1, k_max=64), pp.PRDP.for_problem(64, check=check)
    for _ in range(60):
        ref.update(metric_at(ref.k))
        cert.update(metric_at(cert.k))
    assert ref.k > 20
    assert cert.k == 8 and cert.savings()["certified"] is True


def test_certify_at_the_end_reports_a_failure_and_savings_say_so():
    ctrl = pp.PRDP.for_problem(64)
    for _ in range(5):
        ctrl.update(1.0)  # no check given: nothing certified
    assert ctrl.savings()["certified"] is None
    with pytest.raises(ValueError, match="needs a check"):
        ctrl.certify()
    ctrl = pp.PRDP.for_problem(64, check=gap_check(rho=0.99), window=10)
    for _ in range(5):
        ctrl.update(1.0)  # within the first window: no check yet
    assert ctrl.savings()["certified"] is None and not ctrl.checks
    cert = ctrl.certify()
    assert not cert.certified and "NOT certified" in cert.describe()
    assert ctrl.savings()["certified"] is False
    with pytest.raises(ValueError, match="k_full"):
        pp.PRDP(check=gap_check())
    with pytest.raises(ValueError, match="callable"):
        pp.PRDP.for_problem(64, check=3.0)


def test_full_fidelity_counts_as_certified():
    ctrl = pp.PRDP.for_problem(4, k_init=4, check=gap_check())
    ctrl.update(1.0)
    assert ctrl.savings()["certified"] is True and ctrl.savings()["gap"] == 0.0


def test_state_round_trip_keeps_checks_and_schedule():
    ctrl = pp.PRDP.for_problem(64, check=gap_check())
    for _ in range(12):
        ctrl.update(1.0)
    clone = pp.PRDP.for_problem(64, check=gap_check())
    clone.load_state_dict(ctrl.state_dict())
    assert clone.checks == ctrl.checks and clone.k == ctrl.k
    for _ in range(20):
        assert clone.update(1.0) == ctrl.update(1.0)
    assert clone.checks == ctrl.checks


def test_fidelity_gap_of_per_parameter_lists_and_mismatched_checks():
    grads_k = [np.array([[1.0, 0.0]]), np.array([2.0])]  # e.g. a list of parameter gradients
    grads_full = [np.array([[1.0, 0.0]]), np.array([1.0])]
    assert fidelity_gap(grads_k, grads_full) == pytest.approx(1 / 2**0.5)
    with pytest.raises(ValueError, match="values at K"):
        fidelity_gap(np.ones(3), np.ones(4))


def test_certify_after_the_last_epochs_own_check_reuses_it():
    calls = []

    def check(k):
        calls.append(k)
        return gap_check()(k)

    # K = 32: its checks compare with K_full (the next level), as certify does
    ctrl = pp.PRDP.for_problem(64, k_init=32, check=check, window=2)
    while not ctrl.checks:
        ctrl.update(1.0)  # until the first due check (K = 32 is certified)
    assert ctrl.checks[-1].epoch == len(ctrl.history) - 1 and len(calls) == 2
    assert ctrl.certify() is ctrl.checks[-1] and len(calls) == 2  # same weights, same K
    ctrl.update(1.0)  # an epoch trained since: a new check
    ctrl.certify()
    assert len(calls) == 4 and len(ctrl.checks) == 2


def test_a_gap_far_inside_the_band_is_not_rechecked_every_doubling():
    # gap at K = 8: 0.3^8 / sqrt(2) ~ 5e-5, a thousandth of the band, and the metric halves
    # every 14 epochs: the old schedule rechecked at epochs 3, 6, 12, 24, 48 and at every
    # halving; a gap this far inside is checked once at its K, and once more by certify
    ctrl = pp.PRDP.for_problem(64, check=gap_check(rho=0.3))
    for epoch in range(60):
        ctrl.update(0.95**epoch)
    assert ctrl.k == 8 and len(ctrl.checks) == 1
    assert ctrl.certify().certified and len(ctrl.checks) == 2


class Metered:
    """A check that measures itself as `prdp_petsc.gradient_check` does (``spent()``):
    a check at cap k costs k, an epoch at K costs ``batches * K``."""

    def __init__(self, check, batches):
        self.check, self.batches = check, batches
        self.checks = self.total = 0

    def __call__(self, k):
        self.checks += k
        self.total += k
        return self.check(k)

    def epoch(self, k):
        self.total += self.batches * k

    def run(self, ctrl, epochs):
        """`epochs` epochs of `ctrl` at its K, metered, on a flat metric."""
        for _ in range(epochs):
            self.epoch(ctrl.k)
            ctrl.update(1.0)

    def spent(self):
        return self.checks, self.total


def drifting(epoch):
    """The bias grows with training (a model that specialises): 1 % at the start, 5 % by
    epoch 20 at K = 8."""
    return lambda k: np.array([1.0, 0.01 * (1 + epoch[0] / 5) * 0.5 ** (k - 8)])


def test_a_gap_near_the_band_is_still_rechecked_and_a_drift_is_caught():
    # epochs of 20 batches: rechecks fit the budget; they follow the drift and refine
    epoch = [0]
    check = Metered(drifting(epoch), batches=20)
    ctrl = pp.PRDP.for_problem(64, check=check)
    for epoch[0] in range(60):
        check.epoch(ctrl.k)
        ctrl.update(1.0)
    assert ctrl.k >= 16
    assert [c.k for c in ctrl.checks][:1] == [8] and len(ctrl.checks) <= 6
    assert all(c.cost == c.k + c.against for c in ctrl.checks)  # each check's own cost
    ctrl.certify()
    assert check.checks <= CHECK_BUDGET * check.total


@pytest.mark.parametrize("batches", [1, 3])
def test_rechecks_wait_for_the_budget(batches):
    # epochs as cheap as a check: the same drift is rechecked only as the run's cost
    # allows, and the checks, the end's certificate included, stay within the budget
    epoch = [0]
    check = Metered(drifting(epoch), batches=batches)
    ctrl = pp.PRDP.for_problem(64, check=check)
    for epoch[0] in range(200):
        check.epoch(ctrl.k)
        ctrl.update(1.0)
    ctrl.certify()
    rechecks = [c for c in ctrl.checks if 3 < c.epoch < 200]  # neither the first nor the end
    assert rechecks, "a drift this large must be rechecked once the run can afford it"
    assert check.checks <= CHECK_BUDGET * check.total
    assert ctrl.k >= 16  # and the drift is still caught


def test_a_gradient_that_vanishes_at_convergence_does_not_force_k_full():
    # an optimisation loop: the full gradient decays geometrically (0.9^t) while the solve's
    # error at K = 8 stays a constant 1 % of the first gradient; relative to the current
    # gradient the gap grows without bound (the old rule ended at K_full), relative to the
    # largest gradient seen at this K it stays 1.4 %
    epoch = [0]

    def check(k):
        return np.array([0.9 ** epoch[0], 0.01 * 0.7 ** (k - 8)])

    ctrl = pp.PRDP.for_problem(64, check=check)
    for epoch[0] in range(60):
        ctrl.update(0.9 ** epoch[0])
    cert = ctrl.certify()
    assert ctrl.k == 8 and cert.certified and cert.gap < 0.02
    assert cert.at_full < 0.01  # the gradient itself vanished meanwhile


def test_checks_below_half_k_full_compare_with_the_next_level():
    # K = 8 of K_full = 64 is checked against K = 16 (a third of the cost of K_full);
    # the end certificate is against K_full itself
    calls = []

    def check(k):
        calls.append(k)
        return gap_check(rho=0.9)(k)

    ctrl = pp.PRDP.for_problem(64, check=check)
    for _ in range(60):
        ctrl.update(1.0)
    assert calls[:2] == [8, 16] and ctrl.checks[0].against == 16
    assert all(ref in (2 * k, 64) for k, ref in zip(calls[::2], calls[1::2], strict=True))
    cert = ctrl.certify()
    assert cert.against == 64 and calls[-2:] == [ctrl.k, 64]
    spent = sum(c.k + c.against for c in ctrl.checks)  # savings count what ran
    assert ctrl.savings()["check_share"] == pytest.approx(
        spent / (sum(h.k for h in ctrl.history) + spent)
    )


def test_certify_at_k_full_evaluates_nothing():
    calls = []

    def check(k):
        calls.append(k)
        return gap_check()(k)

    ctrl = pp.PRDP.for_problem(8, k_init=8, check=check)
    ctrl.update(1.0)
    cert = ctrl.certify()
    assert cert.certified and cert.gap == 0.0 and calls == [] and not ctrl.checks
    assert "is K_full" in cert.describe()


@pytest.mark.parametrize("rho", [0.6, 0.0])  # a fractional next check; an exact K (gap 0)
def test_a_resumed_controller_checks_when_the_uninterrupted_one_does(rho):
    """The next check's epoch (max(2, tol/gap) times the epochs run: fractional, or
    infinite for a gap of 0) survives state_dict -> JSON -> load_state_dict."""
    import json

    ctrl = pp.PRDP.for_problem(64, check=gap_check(rho=rho))
    for _ in range(7):
        ctrl.update(1.0)
    assert ctrl.checks and ctrl.checks[-1].certified
    clone = pp.PRDP.for_problem(64, check=gap_check(rho=rho))
    clone.load_state_dict(json.loads(json.dumps(ctrl.state_dict())))
    for _ in range(60):
        assert clone.update(1.0) == ctrl.update(1.0)
    assert [c.epoch for c in clone.checks] == [c.epoch for c in ctrl.checks]


def test_the_start_is_the_first_level_where_the_probe_solve_is_close():
    from prdp_petsc.core.probe import KFull

    assert pp.PRDP.for_problem(90).k_init == 12  # a plain count: an eighth of it
    assert pp.PRDP.for_problem(KFull(90, {12: 0.15, 23: 0.03, 45: 0.001})).k_init == 12
    assert pp.PRDP.for_problem(KFull(90, {12: 0.42, 23: 0.11, 45: 0.006})).k_init == 23
    assert pp.PRDP.for_problem(KFull(90, {12: 0.9, 23: 0.7, 45: 0.3})).k_init == 90
    assert pp.PRDP.for_problem(KFull(90, {12: 0.42}), k_init=5).k_init == 5  # overrides win
    ctrl = pp.PRDP.for_problem(KFull(90, {12: 0.42, 23: 0.11, 45: 0.006}))
    assert (ctrl.next_k(), ctrl.next_k(46), ctrl.k_full) == (45, 90, 90)


@pytest.mark.parametrize("k_full", [8, 10, 20, 43, 90, 188, 467])
def test_the_default_refines_through_the_probed_levels(k_full):
    # K_full/8, /4, /2 rounded up, then K_full: the caps whose errors the probe measured
    # and the constant caps the lab compares with, not doublings of a rounded-up start
    from prdp_petsc.core.probe import PROBED_FRACTIONS

    ctrl = pp.PRDP.for_problem(k_full)
    levels = [ctrl.k]
    while levels[-1] < k_full:
        levels.append(ctrl.next_k(levels[-1]))
    probed = sorted({max(1, math.ceil(f * k_full)) for f in PROBED_FRACTIONS} | {k_full})
    assert levels == probed


def test_without_k_full_or_growth_refinement_is_unchanged():
    assert pp.PRDP(k_init=3, growth=2.0).next_k() == 6  # no K_full: doubles
    assert pp.PRDP(k_init=3, k_step=2, k_full=10).next_k() == 5  # growth 1: additive steps
    assert pp.PRDP(k_init=3, growth=2.0, k_full=10).next_k() == 5  # the level 10 / 2


def test_a_gap_within_half_the_band_waits_for_the_budget():
    # 0.6^8 / sqrt(2) ~ 1.2 % at K = 8: rechecks only as the run can afford them (epochs
    # of three units of K: a recheck, 24, and the end's 72 fit 10 % after ~40 epochs; the
    # schedule alone, tol / gap = 4.3 times the 3 epochs run, would recheck at epoch 13)
    check = Metered(gap_check(rho=0.6), batches=3)
    ctrl = pp.PRDP.for_problem(64, check=check)
    check.run(ctrl, 60)
    epochs = [c.epoch for c in ctrl.checks]
    assert ctrl.k == 8 and epochs[0] == 2 and len(epochs) >= 2 and min(epochs[1:]) >= 13
    # the metric is flat from the start: its first plateau at the certified K is checked
    # once the checks so far, it and the end's certificate fit the budget
    plateau = ctrl.checks[1]
    spent_then = sum(c.cost for c in ctrl.checks[:2]) + 8 + 64
    assert spent_then <= CHECK_BUDGET * (3 * 8 * (plateau.epoch + 1) + spent_then)  # epochs 0..e
    ctrl.certify()
    assert check.checks <= CHECK_BUDGET * check.total


def optimum_at_epoch_20(epoch):
    """An optimisation loop that reaches the capped problem's optimum at epoch 20: then the
    gradient at a cap k < K_full fades as (k / 64)^3 against K_full's (its descent on the
    full problem: an eighth at each level); before, K = 8 is 1 % off."""

    def check(k):
        if epoch[0] < 20:
            return np.array([1.0, 0.01 * 0.5 ** (k - 8)])
        return np.array([min(1.0, (k / 64) ** 3), 0.0])

    return check


@pytest.mark.parametrize("told", [True, False])
def test_a_plateau_at_a_certified_k_is_checked_as_soon_as_the_run_can_afford_it(told):
    # K = 8 is certified at epoch 2; the metric stops falling at epoch 20, where every
    # level below K_full fails its descent.  A plateau check and the end's certificate
    # cost 8 + 16 + 8 + 64 units, 10 % of 1 200: told the run's 300 epochs of one solve
    # (2 400 units), the controller can afford it at the first plateau; not told, only
    # once the run so far has cost that (epoch ~135)
    epoch = [0]
    metered = Metered(optimum_at_epoch_20(epoch), batches=1)
    ctrl = pp.PRDP.for_problem(64, check=metered, epochs=300 if told else None)
    refined = None
    for epoch[0] in range(300):
        metered.epoch(ctrl.k)
        ctrl.update(0.9 ** min(epoch[0], 20))
        if refined is None and ctrl.k > 8:
            refined = epoch[0]
    ctrl.certify()
    assert ctrl.checks[0].epoch == 2 and ctrl.checks[0].certified
    assert refined is not None and (20 <= refined <= 40 if told else refined >= 100), refined
    assert ctrl.k == 64 and metered.checks <= CHECK_BUDGET * metered.total


@pytest.mark.parametrize(
    ("descent", "certified"), [(0.86, True), (0.5, True), (0.3, False), (0.0, False)]
)
def test_a_check_asks_for_a_stall_not_for_the_band_of_the_descent(descent, certified):
    # late in training the reference gradient has shrunk to 2 % of the largest at K, so
    # any gradient at K along it is inside the band; the descent <g_K, g_ref> / |g_ref|^2
    # certifies down to DESCENT (a slower step), not below (training at K stalls)
    from prdp_petsc.prdp import DESCENT

    at = {8: np.array([1.0, 0.5]), 16: np.array([1.0, 0.5])}
    ctrl = pp.PRDP(k_init=8, growth=2.0, k_full=16, check=lambda k: at[k])
    for _ in range(4):
        ctrl.update(1.0)
    assert ctrl.checks[0].certified and ctrl.k == 8  # the largest gradient at K: the scale
    at[16] = np.array([0.02, 0.0])
    at[8] = descent * at[16]
    cert = ctrl.certify()
    assert cert.descent == pytest.approx(descent) and cert.gap <= 0.02
    assert cert.certified is certified and (descent >= DESCENT) is certified


def test_savings_count_the_checks_as_measured_unless_the_count_misses_some():
    # epochs of 3 batches: a check at K (k + against units, as Metered counts it) costs a
    # third of an epoch's units per unit of K, so measured it weighs 1/3 of the old count
    check = Metered(gap_check(rho=0.6), batches=3)
    ctrl = pp.PRDP.for_problem(64, check=check)
    check.run(ctrl, 40)
    ks = [s.k for s in ctrl.history]
    units = sum(c.k + c.against for c in ctrl.checks)
    assert ctrl.checks and check.checks == units
    measured = ctrl.savings()
    assert measured["total"] == pytest.approx(1 - (sum(ks) + units / 3) / (40 * 64))
    assert measured["check_share"] == pytest.approx(check.checks / check.total)
    counted = ctrl.savings(check_weight=1.0)
    assert counted["total"] == pytest.approx(1 - (sum(ks) + units) / (40 * 64))
    # resumed with a new check, whose count starts again: the old count, not a wrong ratio
    fresh = Metered(gap_check(rho=0.6), batches=3)
    clone = pp.PRDP.for_problem(64, check=fresh)
    clone.load_state_dict(ctrl.state_dict())
    fresh.run(clone, 5)
    assert fresh.total > 0 and fresh.checks < sum(c.cost for c in clone.checks)
    assert clone.savings()["total"] == pytest.approx(clone.savings(check_weight=1.0)["total"])


def test_epochs_must_be_a_positive_count():
    with pytest.raises(ValueError, match="epochs must be >= 1"):
        pp.PRDP.for_problem(64, epochs=0)
