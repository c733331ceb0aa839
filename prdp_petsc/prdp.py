"""PRDP controller: raise the solver's iteration cap K only as far as validation needs.

Progressively Refined Differentiable Physics (reference: tum-pbs/PRDP,
``experiments/src/prdp.py``; docs/maths.md §7). Python and numpy, no torch or PETSc.

Two constructions:

* ``PRDP.for_problem(k_full, check=check)``, the default for a new problem: start,
  step and cap come from K_full (the iterations a converged solve needs,
  `prdp_petsc.find_k_full`), and the ``check`` (the validation gradient through the
  solve at a cap k, on the current weights: `prdp_petsc.gradient_check`) certifies
  every stop against K_full.
* ``PRDP.paper()``: the reference's constants, for reproducing the paper;
  ``PRDP(k_init=..., ...)`` sets every setting by hand.

The check is given once, at construction; `PRDP.update` takes the metric only.
"""

from __future__ import annotations

import itertools
import logging
import math
import operator
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

__all__ = [
    "ACCURACY_BAND",
    "Certificate",
    "DESCENT",
    "PAPER",
    "PRDP",
    "PRDPStep",
    "savings",
]

#: the reference's constants (tum-pbs/PRDP, heat 1D): `PRDP.paper` builds a controller with them
PAPER = {"k_init": 1, "k_step": 1, "tau_step": 0.98, "tau_stop": 0.9, "ema_window": 6, "window": 3}

logger = logging.getLogger(__name__)

#: relative accuracy that counts as "as accurate as full fidelity" (0.05: within 5 %)
ACCURACY_BAND = 0.05
#: a check certifies K only where a step along the gradient at K makes at least this
#: share of the reference gradient's first-order descent (`Certificate.descent`): below
#: it training at K stalls where full fidelity still moves
DESCENT = 0.5
#: `PRDP.for_problem`: the first K is this fraction of K_full (rounded up) ...
START_FRACTION = 1 / 8
#: ... or, where the probe measured the capped solve's error (`find_k_full`'s
#: ``KFull.errors``), the first probed cap whose solve is within this relative error of
#: the converged one (K_full if none is): training through a solve that is further off
#: can take the model where no later refinement brings it back
START_ERROR = 0.2
#: ... and every refinement takes K one level up, the levels K_full / GROWTH^j
GROWTH = 2.0
#: a certified K is checked again once it has run this many times the epochs it had run at
#: its last check, or ``tol / gap`` times where that is more (a gap far inside the band)
RECHECK_GROWTH = 2.0
#: ... and, where its gap was within half the band, only while the checks so far, that
#: recheck and the certificate at the end stay within this share of every inner iteration
#: of the run (else it waits until they do)
CHECK_BUDGET = 0.1


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
    gap : float or None
        The fidelity gap of a check made in this call (see `Certificate`), else None.
    """

    k: int
    metric: float
    ema: float
    refined: bool
    k_next: int
    gap: float | None = None


@dataclass(frozen=True)
class Certificate:
    """Outcome of one fidelity check: the same validation quantity at K and at a
    higher cap, the `reference` (K_full, or the next level below it), on the same weights.

    ``gap = ‖check(k) − check(reference)‖ / scale``, where `scale` is the largest
    ``‖check(reference)‖`` of the checks at this K so far (this one included); the model
    trained at K is *certified* when ``gap ≤ tol``: at its K the solve changes what
    training sees (the validation gradient, say) by less than the accuracy band of the
    gradient's size at this K.  A scale that is not the current gradient's keeps a
    converging optimisation (``‖check‖ → 0``) from reading a constant solve error as
    a growing one.

    Attributes
    ----------
    k, k_full : int
        The cap checked and the converged cap.
    at_k, at_full : float
        ``‖check(k)‖`` and ``‖check(reference)‖`` (the values themselves for numbers).
    gap, tol : float
        Relative fidelity gap and the band it is held to.
    epoch : int
        Number of `PRDP.update` calls before the check (the end of training for
        `PRDP.certify` after the last epoch).
    reference : int, optional
        The cap `k` was compared with (None: `k_full`).  `PRDP.certify` compares with
        K_full; a check during training with the next level, ``next_k(k)``, while that
        is below K_full (a solve at K_full / 4 costs a quarter of one at K_full, and
        for a solve whose error falls geometrically the next level's error is a small
        fraction of K's, so the two gaps agree).
    scale : float, optional
        The norm the gap is relative to (None: `at_full`).
    cost : float, optional
        What the check itself cost, as its ``spent()`` measures it (inner iterations for
        `prdp_petsc.gradient_check`); None for a check that does not measure itself.
    descent : float, optional
        ``⟨check(k), check(reference)⟩ / ‖check(reference)‖²`` for array checks: the share
        of the reference gradient's descent that a step along the gradient at K makes.
        Certified needs it ≥ `DESCENT` (1/2) as well: a solve error that only adds a
        small bias beside the reference gradient passes, but a gradient at K that
        misses the reference one (training at K has stalled where full fidelity still
        moves, the gradient at K near zero at the optimum of the capped problem)
        does not, however small the reference gradient has become.  The descent is
        relative to the current reference gradient, so late in training, as that
        gradient shrinks, a bias far inside the band moves it: the test asks for a
        stall, not for the band (poisson_inverse's K_full/2 at its optimum: 0.0 %;
        heat1d's harmless K_full/2 late in training: 86–106 %).  None for a number.
    """

    k: int
    k_full: int
    at_k: float
    at_full: float
    gap: float
    tol: float
    epoch: int
    reference: int | None = None
    scale: float | None = None
    cost: float | None = None
    descent: float | None = None

    @property
    def against(self) -> int:
        """The cap compared with: `reference`, or `k_full`."""
        return self.k_full if self.reference is None else self.reference

    @property
    def certified(self) -> bool:
        """``gap ≤ tol`` and ``descent ≥ DESCENT`` (never for a NaN gap)."""
        descends = self.descent is None or self.descent >= DESCENT
        return bool(self.gap <= self.tol and descends)

    def describe(self) -> str:
        """One line for logs and savings reports."""
        verdict = "certified" if self.certified else "NOT certified"
        if self.k >= self.k_full:
            return f"{verdict}: K={self.k} is K_full, nothing to compare"
        name = "K_full" if self.against == self.k_full else "K"
        scale = ""
        if self.scale is not None and self.scale != self.at_full:
            scale = f" of the largest {self.scale:.4g} at this K"
        descent = "" if self.descent is None else f", descent {100 * self.descent:.1f} %"
        return (
            f"{verdict}: check at K={self.k} {self.at_k:.4g}, at {name}={self.against} "
            f"{self.at_full:.4g} (gap {100 * self.gap:.2f} %{scale}{descent}, band "
            f"{100 * self.tol:.3g} %)"
        )


def fidelity_gap(at_k, at_full) -> float:
    """``‖at_k − at_full‖ / ‖at_full‖`` of two numbers or two arrays (any shape, flattened).

    Raises
    ------
    ValueError
        If either contains NaN or Inf, or `at_full` is all zeros: such a check cannot
        tell whether K is enough (a zero gradient at K_full would certify any K).
    """
    k, full = _flat(at_k), _flat(at_full)
    if k.shape != full.shape:
        raise ValueError(f"a check returned {k.size} values at K and {full.size} at K_full")
    for name, value in (("K", k), ("K_full", full)):
        if not np.all(np.isfinite(value)):
            raise ValueError(
                f"the check returned NaN or Inf at {name}: a diverged solve or network; "
                "a fidelity gap cannot be measured"
            )
    ref = float(np.linalg.norm(full))
    if ref == 0:
        raise ValueError(
            "the check returned all zeros at K_full: it does not see the solve (is the "
            "validation loss computed through the solver, with gradients enabled?)"
        )
    return float(np.linalg.norm(k - full)) / ref


def _flat(value) -> np.ndarray:
    """A number, an array (numpy, torch) or a list of them (per-parameter gradients) as
    one flat float64 array, without a Python loop over its entries."""
    if hasattr(value, "detach"):  # a torch tensor, without importing torch
        value = value.detach().cpu().numpy()
    if isinstance(value, list | tuple):
        parts = [_flat(item) for item in value]
        return np.concatenate(parts) if parts else np.zeros(0)
    return np.asarray(value, dtype=np.float64).ravel()


def _start(k_full: int, errors: dict | None) -> int:
    """`PRDP.for_problem`'s first K: ``ceil(k_full / 8)``, or with the probe's `errors`
    (``{k: relative error of the solve capped at k}``) the first probed k from there
    whose error is within `START_ERROR` (`k_full` if none is)."""
    start = max(1, math.ceil(k_full * START_FRACTION))
    if not errors:
        return start
    within = [k for k, e in sorted(errors.items()) if k >= start and e <= START_ERROR]
    return min(within[0] if within else k_full, k_full)


def _spent(check) -> tuple[float, float] | None:
    """``check.spent()``: (the checks' cost, the run's whole cost so far), if the check
    measures itself (`prdp_petsc.gradient_check` does, in inner iterations)."""
    spent = getattr(check, "spent", None)
    if spent is None:
        return None
    checks, total = spent()
    return float(checks), float(total)


def _norm(value) -> float:
    """The Euclidean norm of `value` flattened (`_flat`)."""
    return float(np.linalg.norm(_flat(value)))


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


class PRDP:
    """Per-epoch controller of the inner-solver iteration cap K (docs/maths.md §7).

    Each :meth:`update` gets the validation metric e_t (lower is better, >= 0):

    1. Append it to H; E_0 = H_0, E_t = a H_t + (1 - a) E_{t-1}, a = 2 / (ema_window + 1)
       (``use_ema=False`` or ``ema_window=1``: E = H).
    2. While len(E) <= window keep K.
    3. r = E[-1] / E[-window]. If r <= tau_step the metric still improves: keep K.
    4. Plateau, or a check due (see the Notes).  With a `check` (the certified test):
       evaluate it once at K and once at the next level (at K_full from K_full / 2 on)
       on the same weights; if the two agree within `tol` (`Certificate`), K is enough
       (certified: stop refining), else refine.  Without a check (the
       reference's test): r_c = E[-1] / checkpoint (checkpoint starts at +inf); if
       r_c < tau_stop or r_c > tau_worse refine, otherwise the last refinement bought
       less than 1 - tau_stop and ``refining`` becomes False.

    Refining sets K <- min(max(K + k_step, L), k_max), where L = ceil(growth K), or,
    with `k_full` and ``growth > 1``, the next level ``ceil(k_full / growth^j)`` above K:
    the levels are fractions of K_full (K_full/8, /4, /2 from the default start), so the
    rounding up of a small start does not compound (K_full = 10 steps 2, 3, 5, 10, not
    2, 4, 8, 10).

    Parameters
    ----------
    k_init, k_step, k_max : int
        First K, its increment (>= 1) and cap (>= k_init; None: `k_full`, or no cap).
    tau_step : float
        Plateau threshold (> 0); r == tau_step still counts as improving.
    tau_stop : float
        Required gain per refinement, in (0, 1] (the reference's test only).
    ema_window, window : int
        EMA span and plateau window (>= 1).
    k_min : int
        Smallest K the caller considers meaningful (1 <= k_min <= k_init); origin of
        :attr:`level`.
    use_ema : bool
        Smooth the metric (reference: yes, except Poisson).
    restart_window : bool
        Not in the reference. If True, each refinement (and each check) starts a new
        EMA from the next metric, and the plateau test waits for ``window`` such
        metrics: the tests then see the current K only.  Without it a metric that
        blows up at a small K stays in the EMA for dozens of epochs and reads as
        "still improving" while the metric measured with the new K rises.
    tau_worse : float
        "Got worse" threshold (>= 1); the reference uses 1.
    k_full : int, optional
        The converged cap (`prdp_petsc.find_k_full`): what a check compares with, and
        the default `k_max`.  Without it there is nothing to certify against.
    check : callable ``k -> array or float``, optional
        The certified test's check (see the Notes; `prdp_petsc.gradient_check` builds
        one): given, every plateau and every due check is decided by it, and
        `certify` uses it.  Needs `k_full`.
    growth : float
        Geometric refinement factor (>= 1; 1: the reference's additive steps).
    tol : float
        Accuracy band of a check (`ACCURACY_BAND`, 0.05).
    epochs : int, optional
        How many times `update` will be called (the run's epochs), if known: the
        checks' budget then counts the whole run (see the Notes).

    Notes
    -----
    **When a check runs** (with a ``check``): `window` epochs into every K; on a
    plateau while K is not yet certified (at most once per `window` epochs); on the
    first plateau after K is certified (once per K: training has reached what K lets
    it reach, where a capped optimum parts from the full one); and, once K is
    certified, again when K has run `RECHECK_GROWTH` (2) times the epochs it had run at
    its last check, or ``tol / gap`` times where that is more: a model specialises as
    it trains, so a K certified early is checked again, about log2(T) times over T
    epochs while its gap stays near the band, and not before the end when the gap is
    far inside it (a gap at a tenth of the band waits ten times as long).  Every check
    of a certified K (the plateau's and the rechecks) waits until it fits the budget:
    the checks so far, it, and the certificate at the end within `CHECK_BUDGET` (10 %)
    of every inner iteration of the run, as the check measures them
    (``check.spent()``: `prdp_petsc.gradient_check` counts its solvers' iterations),
    else counting an epoch at K as K and a check as ``k + reference``.  The run's cost
    is what it has cost so far plus, with `epochs` (the number of `update` calls the
    run will make), the epochs still to come at the current K: told the run's length,
    the controller spends the budget when a check is due rather than when the run so
    far has paid for it (a short run of cheap epochs affords no recheck at all).  The
    first check at each K and the checks before K is certified decide the refinements
    and are never postponed.  A check during training compares
    K with the next level (`Certificate.reference`) while that is below K_full, with
    K_full otherwise and always in `certify`.  A check that would certify K with a
    gap above half the band, when no recheck fits the budget, refines instead: a
    gap near the band can grow past it as the model trains, and nothing would see it
    before the end (a source inversion on a plate, certified at K_full/8 with gaps of
    3.6–4.7 % and never rechecked, ended 1.25–1.53× behind full fidelity and failed
    its certificate at 15–21 %).

    **Which metric.**  `update` takes the validation metric the user cares about (an
    error against ground truth, or the validation loss).  The ``check`` callable
    ``check(k)`` must depend on K: the gradient of the validation loss with respect
    to what is trained (weights, or the design in an optimisation loop), *through the
    solve capped at k*, on the current weights, without a training step
    (`prdp_petsc.gradient_check` does exactly this).  It may return a
    number instead (the validation loss itself), but a loss is a weak check: a solve
    error orthogonal to the misfit changes a squared loss only to second order,
    while it biases what training learns to first order.  Give a check whenever you can:
    only then does a stop mean "training sees what full fidelity would" rather than
    "the last refinement bought little", and neither a learning-rate decay (which
    makes a plateau) nor a metric that shifts with K (a compliance computed through
    the capped solve reads low at small K) can fool it: a plateau only triggers a
    check, and the check decides.

    Semantics of the reference's test, verified against its source:

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

    A NaN or Inf metric raises ``ValueError`` (a diverged network or solve is not a
    plateau to refine on), as does a check that returns NaN, Inf or all zeros.

    The caller owns how K reaches the solver: ``solver.max_it = controller.k`` before
    each epoch (the adjoint follows unless ``solver.adjoint_max_it`` or
    ``AdjointSettings(max_it=...)`` sets it apart; one GMRES restart cycle per K is
    ``max_it = 8 * K``).  For Krylov methods whose count varies, K may be read as a
    level (:attr:`level`) that sets PETSc's rtol instead, under a generous
    ``max_it``: the lab's ``rtol`` schedule does this.
    """

    def __init__(
        self, k_init=1, k_step=1, k_max=None, tau_step=0.98, tau_stop=0.9, ema_window=6,
        window=3, k_min=1, use_ema=True, *, restart_window=False, tau_worse=1.0,
        k_full=None, growth=1.0, tol=ACCURACY_BAND, check=None, epochs=None,
    ):  # fmt: skip
        def _int(name, value, low):
            value = operator.index(value)
            if value < low:
                raise ValueError(f"{name} must be >= {low}, got {value}")
            return value

        self.k_init = _int("k_init", k_init, 1)
        self.k_step = _int("k_step", k_step, 1)
        self.k_full = None if k_full is None else _int("k_full", k_full, 1)
        if k_max is None:
            k_max = None if self.k_full is None else max(self.k_full, self.k_init)
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
            ("growth", growth, lambda v: v >= 1, ">= 1"),
            ("tol", tol, lambda v: v > 0, "> 0"),
        ):
            if not (math.isfinite(float(value)) and ok(float(value))):
                raise ValueError(f"{name} must be finite and {rule}, got {value}")
        self.tau_step, self.tau_stop = float(tau_step), float(tau_stop)
        self.tau_worse, self.growth = float(tau_worse), float(growth)
        self.tol = float(tol)
        if check is not None and not callable(check):
            raise ValueError(f"check must be a callable k -> array or float, got {check!r}")
        if check is not None and self.k_full is None:
            raise ValueError("a check needs k_full (PRDP.for_problem(k_full, check=...) sets it)")
        self.check = check
        self.epochs = None if epochs is None else _int("epochs", epochs, 1)
        self.use_ema, self.restart_window = bool(use_ema), bool(restart_window)
        self.alpha = 2.0 / (self.ema_window + 1.0) if self.use_ema else 1.0
        self._k, self._refining, self._checkpoint = self.k_init, True, math.inf
        self._ema: list[float] = []  # E over the finite metrics only
        self._start = 1  # E[-window] must have index >= _start for a plateau test
        self._fresh = False  # the next finite metric starts a new EMA (restart_window)
        self._history: list[PRDPStep] = []
        self._checks: list[Certificate] = []
        self._level_start = 0  # epoch at which the current K began
        self._next_check = self.window  # epoch of the next due check
        self._last_check = -self.window  # epoch of the last check
        self._settled = None  # the certified K whose plateau has been checked once
        self._scale = 0.0  # largest norm of check(reference) at the current K

    @classmethod
    def for_problem(
        cls, k_full: int, *, check: Callable[[int], object] | None = None,
        tol: float = ACCURACY_BAND, **settings,
    ) -> PRDP:  # fmt: skip
        """The controller for a new problem, from its K_full alone.

        K starts at ``ceil(k_full / 8)`` (`START_FRACTION`) and every refinement moves
        it up one level, ``ceil(k_full / 4)``, ``ceil(k_full / 2)``, `k_full` (`GROWTH`;
        `next_k`): one decade of residual reduction at the
        start for a solve that needs eight to converge, and at most four levels
        (1/8, 1/4, 1/2, 1 of K_full) whatever the size of K_full, so that the
        refinement tests run often enough at every scale.  Where `k_full` comes from
        `prdp_petsc.find_k_full` it carries the error of the probe's solve capped at
        those levels (``k_full.errors``), and K starts at the first level within
        `START_ERROR` (20 %) of the converged solve instead: a solve that converges
        slowly at first (the error still large after an eighth of K_full) starts
        higher, so that the first epochs do no damage.  The plateau test restarts
        after every refinement (``restart_window``).  With a `check`, each plateau is
        decided by a certified check against `k_full`.

        Parameters
        ----------
        k_full : int
            Iterations a converged solve needs (`prdp_petsc.find_k_full`, whose
            ``errors`` choose the start).
        check : callable ``k -> array or float``, optional
            The validation gradient through the solve capped at k
            (`prdp_petsc.gradient_check`); without it nothing is certified.
        tol : float
            Accuracy band of the checks.
        **settings
            Any other `PRDP` argument, overriding these defaults; give ``epochs`` (the
            run's length) whenever it is known.
        """
        errors = getattr(k_full, "errors", None)
        k_full = operator.index(k_full)
        if k_full < 1:
            raise ValueError(f"k_full must be >= 1, got {k_full}")
        defaults = {
            "k_init": _start(k_full, errors),
            "k_step": 1,
            "growth": GROWTH,
            "restart_window": True,
        }
        return cls(**{**defaults, **settings, "k_full": k_full, "tol": tol, "check": check})

    @classmethod
    def paper(cls, **overrides) -> PRDP:
        """The reference's controller (tum-pbs/PRDP, `PAPER`): K from 1 in steps of 1,
        EMA span 6, plateau window 3, ``tau_step`` 0.98, ``tau_stop`` 0.9; any `PRDP`
        argument in `overrides` replaces its value (the paper's Poisson runs:
        ``k_init=25, k_step=10, k_max=600, use_ema=False, window=2, tau_step=0.92``)."""
        return cls(**{**PAPER, **overrides})

    @property
    def k(self) -> int:
        """K for the next epoch."""
        return self._k

    @property
    def level(self) -> int:
        """Refinement level ``k - k_min`` (a level read as a tolerance, say)."""
        return self._k - self.k_min

    @property
    def refining(self) -> bool:
        """False once a check certified K, or the reference's test found that the last
        refinement bought too little."""
        return self._refining

    @property
    def history(self) -> list[PRDPStep]:
        """One :class:`PRDPStep` per :meth:`update` call (a copy)."""
        return list(self._history)

    @property
    def checks(self) -> list[Certificate]:
        """Every fidelity check made so far, in order (a copy)."""
        return list(self._checks)

    @property
    def certificate(self) -> Certificate | None:
        """The last check if it was made at the current K, else None (not checked)."""
        if self._checks and self._checks[-1].k == self._k:
            return self._checks[-1]
        return None

    def next_k(self, k: int | None = None) -> int:
        """K after one refinement from `k` (default: the current K): with `k_full` and
        ``growth > 1`` the level ``ceil(k_full / growth^j)`` just above `k`, else
        ``ceil(growth k)``; at least ``k + k_step``, at most `k_max`."""
        k = self._k if k is None else operator.index(k)
        following = math.ceil(k * self.growth - 1e-9)
        if self.k_full is not None and self.growth > 1 and k < self.k_full:
            levels = (math.ceil(self.k_full / self.growth**j - 1e-9) for j in itertools.count())
            following = self.k_full
            for level in levels:  # falling from k_full to 1: stop at the first not above k
                if level <= k:
                    break
                following = level
        following = max(k + self.k_step, following)
        return following if self.k_max is None else min(following, self.k_max)

    def update(self, metric) -> int:
        """Record the metric of the epoch just trained with :attr:`k`; return K for the next.

        Parameters
        ----------
        metric : float
            Validation metric of that epoch (lower is better, finite, >= 0).  With a
            `check`, the check runs (at K and at `k_full`) when one is due.
        """
        value, k = float(metric), self._k
        if not math.isfinite(value):
            raise ValueError(
                f"metric is {value} at epoch {len(self._history)}: a diverged network or "
                "solve; PRDP cannot refine on it (lower the learning rate, or check the "
                "solver's outcome)"
            )
        if value < 0:
            raise ValueError(f"metric must be >= 0 (PRDP compares ratios), got {value}")
        if not self._ema or self._fresh:
            ema, self._fresh = value, False
        else:
            ema = self.alpha * value + (1 - self.alpha) * self._ema[-1]
        self._ema.append(ema)
        refine, reason, gap = self._test(self.check)
        if refine:
            self._refine()
        step = PRDPStep(k=k, metric=value, ema=ema, refined=self._k > k, k_next=self._k, gap=gap)
        self._history.append(step)
        if refine:
            logger.info("PRDP epoch %d: K %d -> %d (%s)", len(self._history), k, self._k, reason)
        else:
            logger.debug("PRDP epoch %d: keep K=%d (%s)", len(self._history), k, reason)
        return self._k

    def _refine(self) -> None:
        if self._ema:
            self._checkpoint = self._ema[-1]
        self._restart()
        self._refining = True
        epoch = len(self._history) + 1
        self._level_start, self._next_check = epoch, epoch + self.window
        self._k = self.next_k()
        self._scale = 0.0

    def _restart(self) -> None:
        if self.restart_window:
            self._start, self._fresh = len(self._ema), True

    def _test(self, check) -> tuple[bool, str, float | None]:
        """The certified test (with `check`), else the reference's plateau and
        checkpoint tests; updates ``refining`` on a stop."""
        if check is not None:
            return self._check_test(check)
        e = self._ema
        if len(e) - self.window < self._start:
            return False, "window not filled", None
        r = _ratio(e[-1], e[-self.window])
        if r <= self.tau_step:
            return False, f"improving, r={r:.4g}", None
        r_c = _ratio(e[-1], self._checkpoint)
        if r_c < self.tau_stop or r_c > self.tau_worse:
            return True, f"plateau r={r:.4g}, checkpoint ratio {r_c:.4g}", None
        if self._refining:
            logger.info(
                "PRDP: stop refining at K=%d (checkpoint ratio %.4g: last refinement "
                "gained less than %.3g%%)", self._k, r_c, 100 * (1 - self.tau_stop),
            )  # fmt: skip
        self._refining = False
        return False, f"plateau r={r:.4g}, stopped, checkpoint ratio {r_c:.4g}", None

    def _check_test(self, check) -> tuple[bool, str, float | None]:
        """Check when one is due (`window` epochs into a level, then after `_recheck`'s
        intervals) or on a plateau before K is certified: certify K or refine."""
        epoch, e = len(self._history) + 1, self._ema
        if self.k_max is not None and self._k >= self.k_max:
            self._refining = False
            return False, f"at the cap K={self._k}", None
        filled = len(e) - self.window >= self._start
        r = _ratio(e[-1], e[-self.window]) if filled else 0.0
        flat = filled and r > self.tau_step and epoch - self._last_check >= self.window
        plateau = self._refining and flat
        # the first plateau at a certified K: training has reached what K lets it reach,
        # where a capped optimum parts from the full one; checked once per K, as soon as
        # it fits the budget without the end's reserve
        settled = not self._refining and flat and self._settled != self._k
        if not (epoch >= self._next_check or plateau or settled):
            return False, f"r={r:.4g}, next check at epoch {self._next_check:.0f}", None
        reference = min(self.next_k(), self.k_full)
        last = self._checks[-1] if self._checks else None
        recheck = last is not None and last.k == self._k and last.certified
        if not self._refining and recheck and not self._affordable(reference):
            return False, f"recheck of K={self._k} waits: checks at the budget", None
        if settled:
            self._settled = self._k
        cert = self._check(check, reference)
        self._last_check = epoch
        if not cert.certified:
            return True, cert.describe(), cert.gap
        if self._refining and cert.gap > self.tol / 2 and not self._affordable(reference):
            # near the band with no recheck the budget could pay for: refine (the Notes)
            return True, f"{cert.describe()}; near the band, no recheck affordable", cert.gap
        self._refining = False
        self._next_check = self._recheck(epoch, cert.gap)
        logger.info("PRDP epoch %d: %s", epoch, cert.describe())
        return False, cert.describe(), cert.gap

    def _recheck(self, epoch: int, gap: float) -> float:
        """The epoch of the next check of a K certified at `epoch` with `gap`: once K
        has run ``max(RECHECK_GROWTH, tol / gap)`` times the epochs it had run."""
        if gap <= 0:
            return math.inf
        ran = max(self.window, epoch - self._level_start)
        return self._level_start + ran * max(RECHECK_GROWTH, self.tol / gap)

    def _affordable(self, reference: int) -> bool:
        """Whether one more check of K against `reference` (a recheck of a certified K,
        or the one a near-band certificate would need) keeps the checks within
        `CHECK_BUDGET` of the run's cost, the certificate at the end reserved.

        Costs are what the check's ``spent()`` measures (every check so far, and every
        inner iteration of the solvers it runs through, training included), a check
        estimated from the last one's cost per unit of ``k + reference``; for a check
        without ``spent()``, an epoch at K costs K and a check ``k + reference``.  The
        run's cost is what it has cost so far, plus, where `epochs` is known, the
        epochs still to come at the current K (each at the cost per unit of K that
        training has had so far).
        """
        units = self._k + reference + self._k + self.k_full  # this check and the end's
        last = self._checks[-1] if self._checks else None
        spent = _spent(self.check)
        if spent is not None and last is not None and last.cost is not None:
            checks, total = spent
            per_unit = last.cost / (last.k + last.against)
        else:
            checks = sum(c.k + c.against for c in self._checks)
            total = sum(s.k for s in self._history) + self._k + checks
            per_unit = 1.0
        estimate = units * per_unit
        future = 0.0
        if self.epochs is not None:  # `update` is deciding after the epoch just trained
            trained = sum(s.k for s in self._history) + self._k  # that epoch's K included
            per_k = (total - checks) / trained  # an epoch's cost per unit of K
            future = max(0, self.epochs - len(self._history) - 1) * self._k * per_k
        return checks + estimate <= CHECK_BUDGET * (total + estimate + future)

    def _check(self, check, reference: int) -> Certificate:
        """Evaluate `check` at K and at `reference` on the current weights; keep and
        return the `Certificate`, its gap relative to the largest reference norm at K."""
        before = _spent(check)
        at_k, at_ref = check(self._k), check(reference)
        after = _spent(check)
        cost = None if before is None or after is None else after[0] - before[0]
        size = _norm if not isinstance(at_ref, float | int) else float
        relative = fidelity_gap(at_k, at_ref)  # raises on NaN / Inf / all zeros
        norm = _norm(at_ref)
        self._scale = max(self._scale, norm)
        descent = None
        if not isinstance(at_ref, float | int):
            descent = float(np.dot(_flat(at_k), _flat(at_ref))) / norm**2
        cert = Certificate(
            k=self._k, k_full=self.k_full, at_k=size(at_k), at_full=size(at_ref),
            gap=relative * norm / self._scale, tol=self.tol, epoch=len(self._history),
            reference=reference, scale=self._scale, cost=cost, descent=descent,
        )  # fmt: skip
        self._checks.append(cert)
        return cert

    def certify(self) -> Certificate:
        """Check the current K against `k_full` now (at the end of training).

        One validation at K and one at K_full on the same weights with the `check`
        given at construction; the result is kept in :attr:`checks`, read by
        :meth:`savings`.  A failed certificate does not raise: K is not enough for the
        accuracy band, and the savings of the run are reported as not certified.
        A check against K_full that the last `update` made at the current K (on these
        weights: no epoch was trained since) is the answer, and costs nothing again; at
        K_full itself nothing is evaluated (a trivial certificate, gap 0, not kept in
        :attr:`checks`).  The gap is relative to the largest reference gradient of the
        checks at this K (`Certificate`).
        """
        if self.check is None:
            raise ValueError(
                "certify needs a check: PRDP.for_problem(k_full, check=pp.gradient_check(...))"
            )
        last = self._checks[-1] if self._checks else None
        if self.k_full is not None and self._k >= self.k_full:  # nothing to compare
            return Certificate(
                k=self._k, k_full=self.k_full, at_k=math.nan, at_full=math.nan, gap=0.0,
                tol=self.tol, epoch=len(self._history), reference=self.k_full,
            )  # fmt: skip
        if (
            last is not None
            and last.k == self._k
            and last.against == self.k_full
            and last.epoch == len(self._history) - 1
        ):
            logger.info("PRDP end (the last epoch's check): %s", last.describe())
            return last
        cert = self._check(self.check, self.k_full)
        logger.info("PRDP end: %s", cert.describe())
        return cert

    def savings(
        self, k_full=None, *, costs=None, cost_full=None, check_weight: float | None = None
    ) -> dict:
        """What the run saved against a constant-`k_full` run of the same length,
        every solve it caused counted, with the accuracy status.

        Without `costs`, an epoch at K costs K, and the checks are counted too: where
        the check measures itself (``check.spent()``, as `prdp_petsc.gradient_check`
        does, and every `Certificate.cost`), a check costs what it measured, in units
        of what an epoch cost per unit of K so far (``(total − checks) / Σ K_t`` of
        ``spent()``), so `check_share` is the measured share; otherwise a check at cap
        k costs ``check_weight * k`` (``check_weight`` 1 by default: as an epoch at k
        does when the check's gradient is as large a computation as one epoch's, an
        over-count when its batch is smaller).  ``total = 1 − (Σ K_t + checks) /
        (T K_full)``, ``ic = 1 − K_final / K_full``, ``pr = total − ic``.

        Parameters
        ----------
        k_full : int, optional
            Baseline K (default: the controller's `k_full`).
        costs, cost_full : sequence of float, float, optional
            Measured per-epoch costs (inner iterations or seconds) **with the checks'
            solves included**, and the baseline's (see :func:`savings`); replaces the
            count by K.
        check_weight : float, optional
            A check's cost relative to one epoch at the same cap (>= 0), instead of
            what the check measured (default: measured where it can be, else 1).

        Returns
        -------
        dict
            ``total``, ``pr``, ``ic`` (fractions; negative: cost more), ``check_share``
            (the share of this run's cost spent on checks; None with `costs`),
            ``certified`` (True / False from the last check if it was made at the
            final K; True at K_full itself; None: not checked, so the savings say
            nothing about accuracy), ``gap`` (that check's fidelity gap or None) and
            ``checks`` (how many checks ran).
        """
        if check_weight is not None and not (math.isfinite(check_weight) and check_weight >= 0):
            raise ValueError(f"check_weight must be finite and >= 0, got {check_weight}")
        if not self._history:
            raise ValueError("no epochs recorded yet: call update(metric) after each epoch")
        ks = [s.k for s in self._history]
        base = self.k_full if k_full is None else k_full
        share = None
        if costs is None:
            if base is None:
                raise ValueError("give k_full (no k_full was set at construction)")
            spent = [float(k) for k in ks]
            for c, units in zip(self._checks, self._check_units(check_weight), strict=True):
                spent[min(c.epoch, len(spent) - 1)] += units  # the end's: in the last epoch
            checked = sum(spent) - sum(ks)
            out = savings(costs=spent, cost_full=base)
            out["ic"] = 1.0 - ks[-1] / float(base)
            out["pr"] = out["total"] - out["ic"]
            share = checked / sum(spent) if sum(spent) > 0 else 0.0
        else:
            out = savings(ks, base, costs=costs, cost_full=cost_full)
        cert = self._checks[-1] if self._checks else None
        final = ks[-1]
        if self.k_full is not None and final >= self.k_full:  # full fidelity itself
            certified, gap = True, 0.0
        elif cert is not None and cert.k == final:
            certified, gap = cert.certified, cert.gap
        else:
            certified, gap = None, None
        return {
            **out, "check_share": share, "certified": certified, "gap": gap,
            "checks": len(self._checks),
        }  # fmt: skip

    def _check_units(self, check_weight: float | None) -> list[float]:
        """Each check's cost in units of K (`savings`): measured, or ``check_weight``
        times ``k + against``.  Measured only where the check's own count holds every
        check the controller made (not, say, after `load_state_dict` with a new check,
        whose ``spent()`` starts again: its epochs so far would be missing)."""
        measured = _spent(self.check) if check_weight is None else None
        costs = [c.cost for c in self._checks]
        if (
            measured is not None
            and None not in costs
            and math.isclose(measured[0], sum(costs), rel_tol=1e-9, abs_tol=1e-9)
        ):
            checks, total = measured
            per_k = (total - checks) / sum(s.k for s in self._history)
            if per_k > 0:
                return [c.cost / per_k for c in self._checks]
        weight = 1.0 if check_weight is None else check_weight
        return [weight * (c.k + c.against) for c in self._checks]

    def state_dict(self) -> dict:
        """Mutable state as plain (JSON-serialisable) Python objects; settings excluded."""
        return {
            "k": self._k, "refining": self._refining, "checkpoint": self._checkpoint,
            "ema": list(self._ema), "start": self._start, "fresh": self._fresh,
            "history": [asdict(s) for s in self._history],
            "checks": [asdict(c) for c in self._checks], "scale": self._scale,
            "level_start": self._level_start, "next_check": self._next_check,
            "last_check": self._last_check, "settled": self._settled,
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
        self._checks = [Certificate(**c) for c in state.get("checks", [])]
        self._scale = float(state.get("scale", 0.0))
        self._level_start = int(state.get("level_start", 0))
        self._next_check = float(state.get("next_check", self.window))  # inf: no recheck
        self._last_check = int(state.get("last_check", -self.window))
        self._settled = state.get("settled")  # absent in older checkpoints: not checked
