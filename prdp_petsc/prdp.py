"""PRDP controller: raise the solver's iteration cap K only as far as validation needs.

Progressively Refined Differentiable Physics (reference: tum-pbs/PRDP,
``experiments/src/prdp.py``; docs/maths.md §7). Plain Python, no torch or PETSc.
"""

from __future__ import annotations

import logging
import math
import operator
from dataclasses import asdict, dataclass

__all__ = ["PRDP", "PRDPStep", "equal_accuracy_k", "rtol_from_level", "savings"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PRDPStep:
    """Record of one :meth:`PRDP.update` call (one epoch).

    Attributes
    ----------
    k : int
        K used in the epoch whose metric this call received.
    metric : float
        The metric as given (NaN / inf kept).
    ema : float
        Smoothed metric; over a non-finite metric the last finite one (NaN if none yet).
    refined, k_next : bool, int
        Whether this call raised K; the K it returned for the next epoch.
    """

    k: int
    metric: float
    ema: float
    refined: bool
    k_next: int


def _ratio(num: float, den: float) -> float:
    """``num / den`` for non-negative values; ``den = inf`` gives 0, ``0 / 0`` gives 1."""
    if den > 0:
        return num / den
    return math.inf if num > 0 else 1.0


def savings(ks=None, k_full=None, *, costs=None, cost_full=None) -> dict[str, float]:
    """Savings of a PRDP run against a constant-``k_full`` run of the same length.

    total = 1 - sum_t c_t / (T c_full), IC = 1 - c_final / c_full, PR = total - IC.

    Parameters
    ----------
    ks, k_full : sequence of int, float, optional
        K used in each of the T epochs (``PRDPStep.k``, not ``k_next``); baseline K.
    costs : sequence of float, optional
        Per-epoch cost to use instead of ``ks``: inner iterations (forward + adjoint) or
        seconds. If given, ``ks`` / ``k_full`` are ignored (``ks`` must match in length).
    cost_full : float or sequence of float, optional
        Baseline cost per epoch, or the baseline's T per-epoch costs (their sum is the
        baseline total, their mean the per-epoch cost in IC). Required with ``costs``.

    Returns
    -------
    dict
        ``{"total", "pr", "ic"}`` as fractions (0.82 = 82 % saved; negative = cost more).
    """
    if costs is None:
        if ks is None or k_full is None:
            raise ValueError("give ks and k_full, or costs and cost_full")
        costs, cost_full = ks, k_full
    elif cost_full is None:
        raise ValueError("cost_full is required with costs")
    elif ks is not None and len(ks) != len(costs):
        raise ValueError(f"ks has {len(ks)} epochs but costs has {len(costs)}")
    c = [float(x) for x in costs]
    if not c:
        raise ValueError("costs (or ks) is empty: no epochs to compare")
    if not all(math.isfinite(x) and x >= 0 for x in c):
        raise ValueError("costs (or ks) must be finite and >= 0")
    full = [float(x) for x in cost_full] if hasattr(cost_full, "__len__") else [float(cost_full)]
    full = full * len(c) if len(full) == 1 else full
    if len(full) != len(c):
        raise ValueError(f"cost_full has {len(full)} epochs but costs has {len(c)}")
    if not all(math.isfinite(x) and x > 0 for x in full):
        raise ValueError("cost_full (or k_full) must be finite and > 0")
    total = 1.0 - sum(c) / sum(full)
    ic = 1.0 - c[-1] / (sum(full) / len(full))
    return {"total": total, "pr": total - ic, "ic": ic}


def equal_accuracy_k(errors: dict, k_full: int, tol: float = 0.05) -> dict:
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


def rtol_from_level(
    level: int, rtol_init: float = 1e-1, factor: float = 0.5, rtol_min: float = 1e-10
) -> float:
    """Krylov rtol for refinement level ``level``: max(rtol_init * factor**level, rtol_min)."""
    if operator.index(level) < 0:
        raise ValueError(f"level must be >= 0, got {level}")
    if not 0 < rtol_min <= rtol_init:
        raise ValueError(f"need 0 < rtol_min <= rtol_init, got {rtol_min}, {rtol_init}")
    if not 0 < factor < 1:
        raise ValueError(f"factor must lie in (0, 1), got {factor}")
    return max(rtol_init * factor**level, rtol_min)


class PRDP:
    """Per-epoch controller of the inner-solver iteration cap K (docs/maths.md §7).

    Each :meth:`update` gets the validation metric e_t (lower is better, >= 0):

    1. Append it to H; E_0 = H_0, E_t = a H_t + (1 - a) E_{t-1}, a = 2 / (ema_window + 1)
       (``use_ema=False`` or ``ema_window=1``: E = H).
    2. While len(E) <= window keep K.
    3. r = E[-1] / E[-window]. If r <= tau_step the metric still improves: keep K.
    4. Plateau: r_c = E[-1] / checkpoint (checkpoint starts at +inf). If r_c < tau_stop or
       r_c > tau_worse: K <- min(K + k_step, k_max), checkpoint <- E[-1]. Otherwise the
       last refinement bought less than 1 - tau_stop: ``refining`` becomes False.

    Parameters
    ----------
    k_init, k_step, k_max : int
        First K, its increment (>= 1) and cap (>= k_init; None: no cap).
    tau_step : float
        Plateau threshold (> 0); r == tau_step still counts as improving.
    tau_stop : float
        Required gain per refinement, in (0, 1].
    ema_window, window : int
        EMA span and plateau window (>= 1).
    k_min : int
        Smallest K the caller considers meaningful (1 <= k_min <= k_init); origin of
        :attr:`level`, so ``to_rtol()`` gives ``rtol_init`` at K = k_min.
    use_ema : bool
        Smooth the metric (reference: yes, except Poisson).
    restart_window : bool
        Not in the reference. If True, each refinement starts a new EMA from the first
        metric measured with the new K, and the plateau test waits for ``window`` such
        metrics: the tests then see the current K only.  Without it a metric that
        blows up at a small K (an unstable rollout: 1e4 where the plateau is 1) stays
        in the EMA for dozens of epochs and reads as "still improving" while the
        metric measured with the new K rises.
    tau_worse : float
        "Got worse" threshold (>= 1); the reference uses 1.

    Notes
    -----
    Semantics as in the reference's ``should_refine``, verified against its source:

    * ``E[-window]`` is Python indexing: with window 3 the test compares E_t with
      E_{t-2}, and the first test comes at the (window+1)-th call, so E_0 only seeds the
      EMA. ``window=1`` makes every epoch a plateau (pure checkpoint control).
    * The reference does **not** restart the window after a refinement: the test runs
      every epoch, and right after a refinement r_c = E_t / E_{t-1}, so it stops unless
      the metric rose, which refines again. On a noisy plateau an EMA peak just above
      the checkpoint counts as "worse" and ratchets K up; ``tau_worse > 1`` (above the
      EMA's noise) or ``restart_window=True`` damp that.
    * The stop is soft: ``refining`` only reports the last checkpoint test, which runs
      on every plateau, so refinement resumes if the metric rises above the checkpoint
      or falls below ``tau_stop`` times it. The reference's notebooks set the
      checkpoint to 100 instead of +inf, and also feed the untrained model's metric as
      H_0 (call ``update`` once before training to match; drop that record from savings).

    A non-finite metric is "worse": K is raised at once (even within the first window),
    the checkpoint becomes the last finite E, and the metric stays out of the EMA and
    out of the window count (it is kept in :attr:`history`).

    The harness owns how K reaches the solver. `prdp_petsc.training.harness.run` sets
    ``solver.max_it = K`` on every scene solver, and the adjoint follows (forward and
    adjoint together). To drive them separately, set ``solver.adjoint_max_it`` (e.g.
    ``ceil(adjoint_ratio * K)``) or give the solver ``AdjointSettings(max_it=...)``; to
    make one K one GMRES restart cycle (reference Navier-Stokes), set
    ``max_it = 8 * K``. For Krylov methods whose count varies, read K as a level and
    control the tolerance instead: ``solver.set_tolerances(rtol=controller.to_rtol())``
    with a generous ``max_it`` (see :func:`rtol_from_level`).
    """

    def __init__(
        self, k_init=1, k_step=1, k_max=None, tau_step=0.98, tau_stop=0.9, ema_window=6,
        window=3, k_min=1, use_ema=True, *, restart_window=False, tau_worse=1.0,
    ):  # fmt: skip
        def _int(name, value, low):
            value = operator.index(value)
            if value < low:
                raise ValueError(f"{name} must be >= {low}, got {value}")
            return value

        self.k_init = _int("k_init", k_init, 1)
        self.k_step = _int("k_step", k_step, 1)
        self.k_max = None if k_max is None else _int("k_max", k_max, self.k_init)
        self.k_min = _int("k_min", k_min, 1)
        if self.k_min > self.k_init:
            raise ValueError(f"k_min must be <= k_init={self.k_init}, got {self.k_min}")
        self.ema_window = _int("ema_window", ema_window, 1)
        self.window = _int("window", window, 1)
        for name, value, ok, rule in (
            ("tau_step", tau_step, lambda v: v > 0, "> 0"),
            ("tau_stop", tau_stop, lambda v: 0 < v <= 1, "in (0, 1]"),
            ("tau_worse", tau_worse, lambda v: v >= 1, ">= 1"),
        ):
            if not (math.isfinite(float(value)) and ok(float(value))):
                raise ValueError(f"{name} must be finite and {rule}, got {value}")
        self.tau_step, self.tau_stop = float(tau_step), float(tau_stop)
        self.tau_worse = float(tau_worse)
        self.use_ema, self.restart_window = bool(use_ema), bool(restart_window)
        self.alpha = 2.0 / (self.ema_window + 1.0) if self.use_ema else 1.0
        self._k, self._refining, self._checkpoint = self.k_init, True, math.inf
        self._ema: list[float] = []  # E over the finite metrics only
        self._start = 1  # E[-window] must have index >= _start for a plateau test
        self._fresh = False  # the next finite metric starts a new EMA (restart_window)
        self._history: list[PRDPStep] = []

    @property
    def k(self) -> int:
        """K for the next epoch."""
        return self._k

    @property
    def level(self) -> int:
        """Refinement level ``k - k_min`` (for :func:`rtol_from_level`)."""
        return self._k - self.k_min

    @property
    def refining(self) -> bool:
        """False once the last checkpoint test found the last refinement bought too little."""
        return self._refining

    @property
    def history(self) -> list[PRDPStep]:
        """One :class:`PRDPStep` per :meth:`update` call (a copy)."""
        return list(self._history)

    def update(self, metric) -> int:
        """Record the metric of the epoch just trained with :attr:`k`; return K for the next."""
        value, k = float(metric), self._k
        if not math.isfinite(value):
            reason = f"non-finite metric {value}"
            ema = self._ema[-1] if self._ema else math.nan
            refine = True
        else:
            if value < 0:
                raise ValueError(f"metric must be >= 0 (PRDP compares ratios), got {value}")
            if not self._ema or self._fresh:
                ema, self._fresh = value, False
            else:
                ema = self.alpha * value + (1 - self.alpha) * self._ema[-1]
            self._ema.append(ema)
            refine, reason = self._test()
        if refine:
            if self._ema:
                self._checkpoint = self._ema[-1]
            if self.restart_window:
                self._start, self._fresh = len(self._ema), True
            self._refining = True
            self._k = k + self.k_step if self.k_max is None else min(k + self.k_step, self.k_max)
        step = PRDPStep(k=k, metric=value, ema=ema, refined=self._k > k, k_next=self._k)
        self._history.append(step)
        if refine:
            logger.info("PRDP epoch %d: K %d -> %d (%s)", len(self._history), k, self._k, reason)
        else:
            logger.debug("PRDP epoch %d: keep K=%d (%s)", len(self._history), k, reason)
        return self._k

    def _test(self) -> tuple[bool, str]:
        """Plateau and checkpoint tests on the EMA; updates ``refining`` on a stop."""
        e = self._ema
        if len(e) - self.window < self._start:
            return False, "window not filled"
        r = _ratio(e[-1], e[-self.window])
        if r <= self.tau_step:
            return False, f"improving, r={r:.4g}"
        r_c = _ratio(e[-1], self._checkpoint)
        if r_c < self.tau_stop or r_c > self.tau_worse:
            return True, f"plateau r={r:.4g}, checkpoint ratio {r_c:.4g}"
        if self._refining:
            logger.info(
                "PRDP: stop refining at K=%d (checkpoint ratio %.4g: last refinement "
                "gained less than %.3g%%)", self._k, r_c, 100 * (1 - self.tau_stop),
            )  # fmt: skip
        self._refining = False
        return False, f"plateau r={r:.4g}, stopped, checkpoint ratio {r_c:.4g}"

    def to_rtol(self, rtol_init: float = 1e-1, factor: float = 0.5, rtol_min: float = 1e-10):
        """``rtol_from_level(self.level, ...)``: the Krylov rtol for the current K."""
        return rtol_from_level(self.level, rtol_init, factor, rtol_min)

    def savings(self, k_full=None, *, costs=None, cost_full=None) -> dict[str, float]:
        """:func:`savings` over the K's of :attr:`history` (or the given per-epoch costs)."""
        return savings([s.k for s in self._history], k_full, costs=costs, cost_full=cost_full)

    def state_dict(self) -> dict:
        """Mutable state as plain (JSON-serialisable) Python objects; settings excluded."""
        return {
            "k": self._k, "refining": self._refining, "checkpoint": self._checkpoint,
            "ema": list(self._ema), "start": self._start, "fresh": self._fresh,
            "history": [asdict(s) for s in self._history],
        }  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned (into a PRDP built with the same settings)."""
        missing = {"k", "refining", "checkpoint", "ema", "start", "history"} - set(state)
        if missing:
            raise ValueError(f"state is missing {sorted(missing)}")
        k = operator.index(state["k"])
        if k < self.k_min or (self.k_max is not None and k > self.k_max):
            raise ValueError(f"state k={k} outside [k_min, k_max] of this PRDP")
        self._k, self._refining = k, bool(state["refining"])
        self._checkpoint, self._start = float(state["checkpoint"]), int(state["start"])
        self._fresh = bool(state.get("fresh", False))  # absent in older checkpoints
        self._ema = [float(x) for x in state["ema"]]
        self._history = [PRDPStep(**s) for s in state["history"]]
