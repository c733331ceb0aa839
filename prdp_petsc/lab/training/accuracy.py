"""Reading constant-K runs: the smallest cap that trains as accurately as full fidelity."""

from __future__ import annotations

import math

from prdp_petsc.prdp import ACCURACY_BAND

__all__ = ["equal_accuracy_k"]


def equal_accuracy_k(errors: dict, k_full: int, tol: float = ACCURACY_BAND) -> dict:
    """Smallest constant cap K that trains to within ``tol`` of full fidelity.

    Model (docs/maths.md §7, "How far incomplete convergence can go"): a network
    trained through a solve capped at K learns to undo the part of the solve's error
    that K iterations leave, which a stationary solver contracts geometrically, so its
    final validation error is e(K) = e_full + C ρ^K.  The two largest constant caps
    K_a < K_b below `k_full` fix C and ρ if e(K_a) > e(K_b) > e_full; then
    K_tol = K_b + ln(tol e_full / (e(K_b) - e_full)) / ln ρ.

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
