"""Equal accuracy: over seeds, and the smallest constant K within tol of full fidelity."""

import math

import pytest

from prdp_petsc.lab.training.accuracy import equal_accuracy_k, equal_over_seeds, worst_ratio


def _model_errors(ks, e_full=1e-3, c=0.5, rho=0.85):
    return {k: e_full + c * rho**k for k in ks}


def test_equal_accuracy_k_recovers_the_model():
    errors = _model_errors([1, 21, 42, 84])
    errors[84] = 1e-3  # converged: the rho^84 remainder is below the fit's resolution
    out = equal_accuracy_k(errors, 84)
    k_tol = math.log(0.05 * 1e-3 / 0.5) / math.log(0.85)  # c rho^K = tol e_full
    assert out["fitted"] == math.ceil(k_tol)
    assert out["pair"] == (21, 42) and out["rho"] == pytest.approx(0.85, rel=1e-3)
    assert out["measured"] == 84  # fixed:42 is 1.54x e_full
    assert out["fitted"] == 57  # ln(1e-4) / ln(0.85) = 56.67
    assert out["ic_bound"] == pytest.approx(27 / 84)  # 1 - 57/84


def test_equal_accuracy_k_measured_is_the_smallest_run_within_tol():
    errors = {1: 3.0, 10: 1.04, 20: 1.01, 40: 1.0}
    out = equal_accuracy_k(errors, 40)
    assert out["measured"] == 10
    # 10 and 20 both sit above e_full and decrease: C ρ^10 = 0.04, C ρ^20 = 0.01, so
    # ρ^10 = 1/4 and C ρ^K = 0.05 at K = 20 - 10 ln 5 / ln 4 = 8.39: fitted 9, below 10
    assert out["fitted"] == 9 and out["pair"] == (10, 20)
    assert out["rho"] == pytest.approx(0.25**0.1)
    assert out["ic_bound"] == pytest.approx(0.775)  # 1 - 9/40


@pytest.mark.parametrize(
    "errors, measured, ic_bound",
    [
        ({9: 0.998, 18: 1.0, 36: 1.0}, 9, 0.75),  # below e_full: no solver error to fit
        ({9: 1.2, 18: 1.3, 36: 1.0}, 36, 0.0),  # rising: not the model
        ({18: 1.2, 36: 1.0}, 36, 0.0),  # one coarse run only
    ],
)
def test_equal_accuracy_k_without_a_fit_falls_back_to_the_runs(errors, measured, ic_bound):
    out = equal_accuracy_k(errors, 36)
    assert out["fitted"] is None and out["pair"] is None and out["rho"] is None
    assert out["measured"] == measured
    assert out["ic_bound"] == pytest.approx(ic_bound)


def test_equal_accuracy_k_clamps_and_validates():
    # a fit that asks for more than K_full is clamped to K_full
    errors = {10: 2.0, 20: 1.9, 40: 1.0}
    assert equal_accuracy_k(errors, 40)["fitted"] == 40
    with pytest.raises(ValueError, match="k_full"):
        equal_accuracy_k({10: 2.0}, 40)
    nan = equal_accuracy_k({10: 2.0, 20: 1.5, 40: math.nan}, 40)  # a run that ended in NaN
    assert nan["measured"] == 40 and nan["fitted"] is None and nan["ic_bound"] == 0.0
    with pytest.raises(ValueError, match="tol"):
        equal_accuracy_k({40: 1.0}, 40, tol=0)


@pytest.mark.parametrize(
    "ratios, equal",
    [
        ((1.0, 1.02, 1.08), True),  # mean 1.0328, worst 1.08
        ((1.04, 1.05, 1.06), True),  # mean 1.04997: the bound is inclusive
        ((1.0, 1.0, 1.12), False),  # mean 1.0385 but one seed above 1.10
        ((1.06, 1.06, 1.06), False),  # no seed above 1.10 but the mean above 1.05
    ],
)
def test_equal_over_seeds_bounds_the_mean_and_the_worst_seed(ratios, equal):
    mean = math.prod(ratios) ** (1 / len(ratios))
    assert equal_over_seeds(mean, max(ratios)) is equal


@pytest.mark.parametrize("ratios", [(1.0, math.nan), (math.nan, 1.0), (1.0, 1.2, math.nan)])
def test_a_diverged_seed_is_the_worst_wherever_it_stands(ratios):
    worst = worst_ratio(ratios)
    assert math.isnan(worst) and not equal_over_seeds(1.0, worst)
    assert worst_ratio((1.0, 1.2, 1.1)) == 1.2
