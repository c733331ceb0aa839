"""Preconditioner lag: reuse a PC while the operator drifts, with a guard on its quality.

A `KSPSolver` sets its preconditioner up again whenever the operator's values
change.  When the operator drifts slowly (θ updated by an optimizer step, a Newton
Jacobian), an older PC often preconditions the new operator almost as well, and
building it (ILU, GAMG) can cost more than the capped solve.  `PCLag` decides, per
PC, whether a solve sets the PC up (``KSPSetReusePreconditioner`` off) or reuses
it (on), as SNES's ``-snes_lag_preconditioner N``: a new PC every N-th operator
value change, and at once for a new Mat (another pattern or size).

A capped solve must not become silently worse, so every solve is measured: its
residual reduction per iteration (`prdp_petsc.core.step.reduction_rate`) on a
fresh PC becomes the reference (the mean of ``log rate`` over the solves before
the next operator change), and a solve on a reused PC gets
``k_equivalent = K · log(rate_fresh) / log(rate)``, the iterations the stale PC
needs to match the fresh one.  When a call's mean ``log rate_fresh / log rate``
(``k_equivalent / K``) exceeds `tol`, the PC is set up again before the next
solve, and the reason is logged.

The reference is measured on the operator the PC was built for, so
``k_equivalent`` counts what the drift made harder together with what the PC
lost: after an operator jump (θ × 100 in a heat step) the fresh PC may do little
better than the stale one.  The first solves on the new PC say so in the log
("the operator got harder"), and their rates become the new reference.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

from petsc4py import PETSc

from ..errors import InputError, plain
from .results import SolveInfo, SolverStats

__all__ = ["PCLag"]

logger = logging.getLogger(__name__)


@dataclass
class _Slot:
    """One PC's history: when it was set up, and its fresh rates per kind of solve."""

    built: int = -1  # `PCLag.changes` at the last set-up; -1: must be set up
    stale: bool = False  # the guard asked for a new set-up
    fresh: dict = field(default_factory=dict)  # kind -> [sum of log rates, count]
    trigger: dict = field(default_factory=dict)  # kind -> the stale mean log rate that
    # made the guard set the PC up (checked against the fresh PC's, once)


class PCLag:
    """When a `KSPSolver`'s preconditioners are set up again.

    Parameters
    ----------
    lag : int
        Set a PC up again every `lag`-th operator value change (1: at every
        change, PETSc's default; the solver then leaves PETSc's reuse flag alone).
    tol : float
        Quality guard, ≥ 1: a reused PC whose call reduces the residual per
        iteration by less than the fresh PC did, ``log rate_fresh / log rate > tol``
        (it needs more than `tol` times the iterations), is set up again before
        the next solve.

    Notes
    -----
    Slots are named by the solver: ``"forward"``, and ``"adjoint"`` only when the
    adjoint KSP has a PC of its own (a shared PC is one slot, so the forward and
    adjoint solves see the same age).  Fresh rates are kept per kind of solve
    ("forward", "adjoint"), since a transpose solve with another right-hand side
    reduces its residual at another rate.
    """

    def __init__(self, lag: int, tol: float) -> None:
        if isinstance(lag, bool) or not isinstance(lag, int) or lag < 1:
            raise InputError(f"pc_lag must be an integer >= 1, got {plain(lag)!r}")
        if isinstance(tol, bool) or not isinstance(tol, int | float) or not (1 <= tol < math.inf):
            raise InputError(f"pc_lag_tol must be a finite number >= 1, got {plain(tol)!r}")
        self.lag = lag
        self.tol = float(tol)
        self.changes = 0  # operator value changes (and new Mats) so far
        self._slots: dict[str, _Slot] = {}

    def reset(self) -> None:
        """Forget every PC (new KSPs): each is set up at its next solve."""
        self._slots.clear()

    def operator_changed(self, *, new_mat: bool = False) -> None:
        """The operator's values changed; `new_mat`: a new Mat (pattern or size)."""
        self.changes += 1
        if new_mat:
            for slot in self._slots.values():
                slot.built = -1

    def mark_stale(self, name: str) -> None:
        """Set the PC of slot `name` up again at its next solve (a solve failed on it)."""
        self._slots[name].stale = True

    def before_solve(self, name: str, ksp: PETSc.KSP, stats: SolverStats) -> int:
        """Decide whether the PC of slot `name` is set up at this solve; return its age.

        Sets PETSc's reuse flag on the PC of `ksp` (only when ``lag > 1``) and counts
        a set-up in `stats`.  The age is 0 when this solve uses a freshly set-up PC.
        """
        slot = self._slots.get(name)
        if slot is None:
            slot = self._slots[name] = _Slot()
        age = self.changes - slot.built
        if age == 0 and self.lag == 1 and not slot.stale:
            return 0  # the PC is the operator's own: PETSc sets nothing up
        if slot.built < 0:
            why = "new operator"
        elif age == 0:
            why = None  # the PC is the operator's own: PETSc sets nothing up
        elif slot.stale:
            why = "quality"
        elif age >= self.lag:
            why = "lag"
        else:
            why = None
        if self.lag > 1:
            # reuse only on purpose: with an unchanged operator PETSc decides (and sets
            # up again a caller's Mat edited in place, as without a lag)
            ksp.getPC().setReusePreconditioner(why is None and age > 0)
        if why is None:
            return age
        if why == "quality":
            stats.pc_quality_rebuilds += 1
        else:
            slot.trigger.clear()
        logger.debug("%s PC set up (%s, %d operator changes old)", name, why, max(age, 0))
        stats.pc_setups += 1
        slot.built, slot.stale = self.changes, False
        slot.fresh.clear()
        return 0

    def after_solve(self, name: str, kind: str, infos: list[SolveInfo], age: int) -> list:
        """The call's `infos` with `pc_age` and `k_equivalent`; feed the quality guard.

        A fresh PC's rates become the reference of `kind`; a reused PC's call whose
        mean ``log rate_fresh / log rate`` exceeds `tol` marks the PC stale.
        """
        if self.lag == 1:  # every PC is fresh: no age, no reference rate to keep
            return infos
        slot = self._slots[name]
        logs = [_log(i.rate) for i in infos if i.rate is not None]
        if age == 0:
            total = slot.fresh.setdefault(kind, [0.0, 0])
            total[0] += sum(logs)
            total[1] += len(logs)
            stale = slot.trigger.pop(kind, None)
            if stale is not None and logs and sum(logs) / len(logs) > self.tol * stale:
                logger.info(
                    "%s PC set up again by the quality guard: %s solves reduce the residual "
                    "by %.3g per iteration on it, %.3g on the old one; the operator got "
                    "harder, more than the PC staler",
                    name,
                    kind,
                    math.exp(sum(logs) / len(logs)),
                    math.exp(stale),
                )
            return infos
        fresh = slot.fresh.get(kind)
        ref = fresh[0] / fresh[1] if fresh and fresh[1] else None  # mean log rate, fresh PC
        out = [
            replace(
                i,
                pc_age=age,
                k_equivalent=None if i.rate is None else _k_equivalent(i, ref),
            )
            for i in infos
        ]
        if ref is not None and ref < 0 and logs:
            mean = sum(logs) / len(logs)
            worse = math.inf if mean >= 0 else (ref / mean if mean > -math.inf else 0.0)
            if worse > self.tol:
                slot.stale = True
                slot.trigger[kind] = mean
                logger.info(
                    "%s PC, %d operator changes old: %s solves reduce the residual by %.3g "
                    "per iteration against %.3g on the fresh PC (%.2f times the iterations, "
                    "above pc_lag_tol %.2f); set up again before the next solve",
                    name,
                    age,
                    kind,
                    math.exp(mean),
                    math.exp(ref),
                    worse,
                    self.tol,
                )
        return out


def _log(rate: float) -> float:
    return math.log(rate) if rate > 0 else -math.inf


def _k_equivalent(info: SolveInfo, ref: float | None) -> float | None:
    """``K · log(rate_fresh) / log(rate)``: None without a fresh PC that reduced anything."""
    if ref is None or ref >= 0:
        return None
    k, log_rate = info.iterations, _log(info.rate)
    if log_rate >= 0:
        return math.inf  # the stale PC reduces nothing: no K matches
    if log_rate == -math.inf:  # exact in K iterations: no more than K needed
        return float(k)
    return k * ref / log_rate
