"""PRDP built from the problem (`PRDP.for_problem`) and its certified checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

import prdp_petsc as pp
from prdp_petsc.prdp import fidelity_gap


def gap_check(rho=0.7, scale=1.0):
    """A check whose answer at cap k is off from K_full's by scale·rho^k (relative)."""

    def check(k):
        return np.array([1.0 + scale * rho**k, 1.0])

    return check


def test_for_problem_takes_start_step_and_cap_from_k_full():
    ctrl = pp.PRDP.for_problem(104)
    assert (ctrl.k_init, ctrl.k_max, ctrl.k_full, ctrl.tol) == (13, 104, 104, pp.ACCURACY_BAND)
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


def test_the_reference_constants_stay_the_plain_constructor():
    ctrl = pp.PRDP()
    assert (ctrl.k_init, ctrl.k_step, ctrl.growth, ctrl.k_max, ctrl.k_full) == (
        1,
        1,
        1.0,
        None,
        None,
    )
    assert ctrl.next_k() == 2


def test_fidelity_gap_of_numbers_and_arrays():
    assert fidelity_gap(1.1, 1.0) == pytest.approx(0.1)
    assert fidelity_gap([3.0, 4.0], [0.0, 0.0]) == math.inf
    assert fidelity_gap(np.zeros(3), np.zeros(3)) == 0.0
    assert math.isnan(fidelity_gap(np.array([np.nan]), np.array([1.0])))
    assert fidelity_gap(np.array([[1.0, 2.0]]), np.array([[1.0, 1.0]])) == pytest.approx(1 / 2**0.5)


def test_refines_until_the_check_certifies_then_stays():
    # gap at k: 0.7^k / sqrt(2) -> within 5 % from k = 8; K_full 64: 8, 16, 32, 64
    ctrl = pp.PRDP.for_problem(64)
    check = gap_check()
    for _ in range(40):
        ctrl.update(1.0, check=check)  # a flat metric: every window is a plateau
    assert ctrl.k == 8 and not ctrl.refining
    s = ctrl.savings()
    assert s["certified"] is True and s["gap"] < 0.05 and s["total"] == pytest.approx(1 - 8 / 64)
    assert 2 <= s["checks"] <= 10  # checks at doubling intervals, not every epoch


def test_too_small_k_is_refined_even_while_the_metric_keeps_falling():
    # a steadily improving metric never plateaus; the due check still finds K too small
    ctrl = pp.PRDP.for_problem(64, k_init=2)
    check = gap_check(rho=0.9)
    for epoch in range(60):
        ctrl.update(0.97**epoch, check=check)
    assert ctrl.k >= 32  # 0.9^k / sqrt(2) < 0.05 needs k >= 32
    assert ctrl.checks[-1].certified


def test_a_learning_rate_decay_plateau_cannot_stop_refinement():
    # the metric flattens (a decayed learning rate) while K is still too small:
    # the reference's test stops ("the refinement bought < 10 %"), the certified one refines
    check = gap_check(rho=0.9)
    metric = [1.0 / (1 + e) for e in range(8)] + [0.125] * 52
    ref = pp.PRDP(k_init=8, k_step=8, k_max=64)
    cert = pp.PRDP.for_problem(64)
    for m in metric:
        ref.update(m)
        cert.update(m, check=check)
    assert ref.k < 32 and not ref.refining
    assert cert.k >= 32 and cert.savings()["certified"] is True


def test_a_metric_that_rises_with_k_does_not_ratchet_k():
    # compliance through a capped solve reads low at small K: raising K raises the metric,
    # which the reference reads as "got worse" and answers with another refinement
    def metric_at(k):
        return 15.4 - 2.0 * 0.8**k

    check = gap_check(rho=0.6)  # K = 8 is enough: 0.6^8 / sqrt(2) < 0.05
    ref, cert = pp.PRDP(k_init=1, k_max=64), pp.PRDP.for_problem(64)
    for _ in range(60):
        ref.update(metric_at(ref.k))
        cert.update(metric_at(cert.k), check=check)
    assert ref.k > 20
    assert cert.k == 8 and cert.savings()["certified"] is True


def test_certify_at_the_end_reports_a_failure_and_savings_say_so():
    ctrl = pp.PRDP.for_problem(64)
    for _ in range(5):
        ctrl.update(1.0)  # no check given: nothing certified
    assert ctrl.savings()["certified"] is None
    cert = ctrl.certify(gap_check(rho=0.99))
    assert not cert.certified and "NOT certified" in cert.describe()
    assert ctrl.savings()["certified"] is False
    with pytest.raises(ValueError, match="k_full"):
        pp.PRDP().update(1.0, check=gap_check())


def test_full_fidelity_counts_as_certified():
    ctrl = pp.PRDP.for_problem(4, k_init=4)
    ctrl.update(1.0, check=gap_check())
    assert ctrl.savings()["certified"] is True and ctrl.savings()["gap"] == 0.0


def test_state_round_trip_keeps_checks_and_schedule():
    ctrl = pp.PRDP.for_problem(64)
    check = gap_check()
    for _ in range(12):
        ctrl.update(1.0, check=check)
    clone = pp.PRDP.for_problem(64)
    clone.load_state_dict(ctrl.state_dict())
    assert clone.checks == ctrl.checks and clone.k == ctrl.k
    for _ in range(20):
        assert clone.update(1.0, check=check) == ctrl.update(1.0, check=check)
    assert clone.checks == ctrl.checks


def test_fidelity_gap_of_per_parameter_lists_and_mismatched_checks():
    grads_k = [np.array([[1.0, 0.0]]), np.array([2.0])]  # e.g. a list of parameter gradients
    grads_full = [np.array([[1.0, 0.0]]), np.array([1.0])]
    assert fidelity_gap(grads_k, grads_full) == pytest.approx(1 / 2**0.5)
    with pytest.raises(ValueError, match="values at K"):
        fidelity_gap(np.ones(3), np.ones(4))
