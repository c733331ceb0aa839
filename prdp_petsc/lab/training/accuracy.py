"""Equal accuracy: when a run counts as trained as well as full fidelity, and how soon."""

from __future__ import annotations

import math

from prdp_petsc.prdp import ACCURACY_BAND

__all__ = ["ACCURACY_RATIO", "CONSTANT_FRACTIONS", "WORST_SEED_RATIO", "accuracy_target",
           "constant_caps", "equal_accuracy_k", "equal_over_seeds", "fraction_of",
           "probe_errors", "probed_at", "time_to_accuracy", "worst_ratio"]  # fmt: skip

#: Largest ratio of final validation errors (run / full fidelity) that counts as equal accuracy.
ACCURACY_RATIO = 1.0 + ACCURACY_BAND
#: Largest ratio one seed may reach where the seeds' geometric mean counts as equal accuracy.
WORST_SEED_RATIO = 1.10
#: The constant caps a baseline tries, as fractions of K_full (rounded up): the best one at
#: equal accuracy is what stopping below K_full saves without a schedule
CONSTANT_FRACTIONS = (1 / 8, 1 / 4, 1 / 2)


def fraction_of(k_full: int, fraction: float) -> int:
    """`fraction` of K_full as a cap: rounded up, at least 1."""
    return max(1, math.ceil(fraction * k_full))


def constant_caps(k_full: int) -> dict[str, int]:
    """The baselines' constant caps by label: ``{"K_full/8": ..., "K_full/4": ...,
    "K_full/2": ...}`` (`CONSTANT_FRACTIONS` of `k_full`, `fraction_of`)."""
    return {f"K_full/{round(1 / f)}": fraction_of(k_full, f) for f in CONSTANT_FRACTIONS}


def probe_errors(k_full) -> dict[str, float]:
    """A `prdp_petsc.find_k_full` result's errors of the capped solves as a record:
    ``{"k": error}`` (JSON keys), by cap."""
    return {str(k): float(e) for k, e in sorted(getattr(k_full, "errors", {}).items())}


def probed_at(rows, label: str) -> list[float] | None:
    """Per row (a seed's record with ``k_full`` and `probe_errors`' ``probe_errors``),
    the probe's error of the solve capped at the constant cap `label` of
    `constant_caps`; None where any row lacks it (recorded before it was kept)."""
    errors = []
    for row in rows:
        error = (row.get("probe_errors") or {}).get(str(constant_caps(row["k_full"])[label]))
        if error is None:
            return None
        errors.append(error)
    return errors


def worst_ratio(ratios) -> float:
    """The largest of the seeds' error ratios; NaN where any is NaN (a diverged seed is
    the worst, whatever its place: ``max`` alone depends on the order)."""
    ratios = list(ratios)
    return math.nan if any(math.isnan(r) for r in ratios) else max(ratios)


def equal_over_seeds(geometric_mean: float, worst: float) -> bool:
    """Whether error ratios over seeds count as equal accuracy: their geometric mean at
    most `ACCURACY_RATIO`, no seed above `WORST_SEED_RATIO`."""
    return geometric_mean <= ACCURACY_RATIO and worst <= WORST_SEED_RATIO


def accuracy_target(logs: dict, full_name: str) -> float | None:
    """`ACCURACY_RATIO` × the final validation error of run `full_name` (full fidelity),
    or None where that run is missing or recorded no epoch."""
    full = logs.get(full_name)
    if not full or not full["epochs"]:
        return None
    return ACCURACY_RATIO * full["epochs"][-1]["val_metric"]


def time_to_accuracy(log: dict, target: float) -> float | None:
    """Wall time a run needed to reach `target` and stay there; None if it never did.

    The run reaches it at the first epoch from which on its validation error stays at
    or below the target to the end (a run that dips below and drifts back has not); its
    time is the cumulative wall time up to and including that epoch.  A run that
    stopped early never reaches it, nor does any run against a NaN target.
    """
    epochs = log["epochs"]
    if log.get("stopped"):
        return None
    first = len(epochs)  # the first epoch from which on the run stays at the target
    while first > 0 and epochs[first - 1]["val_metric"] <= target:
        first -= 1
    if first == len(epochs):
        return None
    return sum(e["wall_time"] for e in epochs[: first + 1])


def equal_accuracy_k(errors: dict, k_full: int, tol: float = ACCURACY_BAND) -> dict:
    """Smallest constant cap K that trains to within ``tol`` of full fidelity.

    Model (docs/maths.md §7): a network trained through a solve capped at K ends at
    e(K) = e_full + C ρ^K.  The two largest caps K_a < K_b below `k_full` fix C and ρ
    if e(K_a) > e(K_b) > e_full; then K_tol = K_b + ln(tol e_full / (e(K_b) - e_full)) / ln ρ.

    Parameters
    ----------
    errors : dict
        ``{K: final validation error}`` of constant-K runs over the same epochs; must
        hold `k_full` (its error is e_full).
    k_full : int
        The converged cap.
    tol : float
        Relative accuracy, > 0 (0.05: within 5 %).

    Returns
    -------
    dict
        ``measured``: the smallest K in `errors` within tol of e_full (at worst
        `k_full`); ``fitted``: ceil(K_tol) clamped to [1, k_full], or None where the
        runs do not fit the model; ``pair``: (K_a, K_b) or None; ``rho``: ρ or None;
        ``ic_bound``: 1 - K / k_full with the fitted K (else the measured one), the
        most incomplete convergence can save at that accuracy.
    """
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be finite and > 0, got {tol}")
    if k_full not in errors:
        raise ValueError(f"errors must hold the converged cap k_full={k_full}")
    e_full = float(errors[k_full])
    within = [k for k, e in errors.items() if k < k_full and e <= (1 + tol) * e_full]
    measured = min(within, default=k_full)  # a NaN e_full leaves K_full itself
    out = {"measured": measured, "fitted": None, "pair": None, "rho": None}
    below = sorted(k for k in errors if k < k_full)
    if len(below) >= 2 and e_full > 0:
        k_a, k_b = below[-2:]
        d_a, d_b = errors[k_a] - e_full, errors[k_b] - e_full
        if math.isfinite(d_a) and d_a > d_b > 0:
            log_rho = math.log(d_b / d_a) / (k_b - k_a)
            k_tol = k_b + math.log(tol * e_full / d_b) / log_rho
            fitted = min(k_full, max(1, math.ceil(k_tol - 1e-9)))
            out.update(fitted=fitted, pair=(k_a, k_b), rho=math.exp(log_rho))
    out["ic_bound"] = 1.0 - (out["fitted"] or measured) / k_full
    return out
