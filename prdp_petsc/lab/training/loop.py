"""The epoch loop of a training run (`train`) and what it records: per-epoch costs and
their `totals`.  A solver outcome (`SolverError`, `InputError`: a diverged solve, a
non-finite loss) stops the loop with a ``stopped`` record; anything else propagates.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict

import numpy as np
import torch

from prdp_petsc import PRDP, InputError, SolverError
from prdp_petsc.errors import NonFiniteError

from .checkpoint import CHECKPOINT, restore, save_checkpoint
from .curves import Curves
from .parallel import Parallel
from .records import RESULTS, to_json, write_json
from .schedules import Schedule, gradient_check, rtol_from_level

__all__ = ["interrupted", "totals", "train"]

logger = logging.getLogger(__name__)


def interrupted(result: dict) -> None:
    """Record in `result` that Ctrl-C stopped its run (the caller re-raises)."""
    epoch = len(result["epochs"])
    logger.error("epoch %d: interrupted (Ctrl-C)", epoch)
    message = f"KeyboardInterrupt during epoch {epoch}; earlier epochs are complete"
    result["stopped"] = {"epoch": epoch, "reason": "interrupted", "message": message}


def train(
    scene,
    result: dict,
    plan: Schedule,
    epochs: int,
    torch_seed: int,
    out,
    progress: bool,
    ranks: Parallel,
    *,
    every: int = 1,
    state: dict | None = None,
) -> None:
    """Fill ``result["epochs"]`` (and ``stopped``) in place, from a checkpoint's `state`
    if given; into `out` a checkpoint every `every` epochs, ``results.json`` and the
    TensorBoard curves after every epoch."""
    from tqdm.auto import tqdm

    generator = torch.Generator().manual_seed(torch_seed)
    check = gradient_check(scene) if plan.kind == "auto" else None
    if plan.kind == "auto":
        start = {"k_init": scene.prdp["k_init"]} if "k_init" in scene.prdp else {}
        controller = PRDP.for_problem(scene.prdp["k_full"], check=check, **start)
    else:
        controller = PRDP(**scene.prdp) if plan.kind != "fixed" else None
    levels = result.get("rtol") if plan.kind == "rtol" else None
    start = 0
    if state is not None:
        restore(scene, state, controller=controller, generator=generator)
        start = state["epoch"]
    k = plan.k if plan.kind == "fixed" else levels["max_it"] if levels else controller.k
    level = controller.level if levels else None  # rtol: the controller's K counts levels
    bar = tqdm(
        range(start, epochs),
        desc=f"{result['scene']} {result['schedule']}",
        initial=start,
        total=epochs,
        disable=None if progress else True,  # None: tqdm hides itself when not a terminal
        leave=False,
    )
    curves = Curves(out, result, start) if out is not None else None
    try:
        for epoch in bar:
            rtol = None
            if levels:  # PRDP's level as PETSc's rtol (the adjoint follows unless set apart)
                rtol = rtol_from_level(level, levels["rtol_init"], levels["factor"],
                                       levels["rtol_min"])  # fmt: skip
            for s in scene.solvers:
                s.max_it = k
                if rtol is not None:
                    s.rtol = rtol
                s.reset_stats()
            t0 = time.perf_counter()
            try:
                losses = []
                for batch in scene.batches(epoch, generator):
                    losses.append(ranks.step(scene, batch))
                    _check_finite(losses[-1], f"the training loss of batch {len(losses) - 1}")
                if scene.scheduler is not None:
                    scene.scheduler.step()
                metric = ranks.validate(scene)
                _check_finite(metric, "the validation metric")
                if controller is not None:  # its checks' solves count in this epoch's costs
                    following = ranks.agree(controller.update(metric))
                if check is not None and epoch == epochs - 1:  # the certified end
                    _certify(controller, result)
            except (SolverError, InputError) as err:  # outcomes, not bugs (prdp_petsc.errors)
                logger.error("epoch %d: %s", epoch, err)
                result["stopped"] = {"epoch": epoch, "reason": err.reason, "message": str(err)}
                return
            wall = time.perf_counter() - t0
            stats = [s.stats for s in scene.solvers]
            names = ["forward_iterations", "adjoint_iterations"]
            if any(s.pc_lag > 1 for s in scene.solvers):  # what reusing the PC saved
                names += ["pc_setups", "pc_quality_rebuilds"]
            if rtol is not None:  # what the tolerance bought: solves and real iterations
                names += ["forward_solves", "adjoint_solves"]
            counts, solver_time = ranks.totals(
                [sum(getattr(s, name) for s in stats) for name in names],
                sum(s.forward_time + s.adjoint_time for s in stats),
            )
            counts = dict(zip(names, counts, strict=True))
            record = {
                "epoch": epoch,
                "k": k,
                "train_loss": float(np.mean(losses)) if losses else math.nan,
                "val_metric": metric,
                "wall_time": wall,
                "fwd_iterations": counts.pop("forward_iterations"),
                "adj_iterations": counts.pop("adjoint_iterations"),
                "solver_time": solver_time,
            }
            if rtol is not None:
                record.update(rtol=rtol, rtol_level=level, fwd_solves=counts.pop("forward_solves"),
                              adj_solves=counts.pop("adjoint_solves"))  # fmt: skip
            record.update(counts)
            result["epochs"].append(record)
            bar.set_postfix(K=k, val=f"{metric:.3e}", **({"rtol": f"{rtol:.0e}"} if rtol else {}))
            if controller is not None:
                if levels:  # rtol: the level moves, the cap stays
                    level = following - controller.k_min
                else:
                    k = following
            result["totals"] = totals(result["epochs"])
            if out is not None:
                done = epoch + 1
                if done % every == 0 or done == epochs:
                    save_checkpoint(
                        out / CHECKPOINT, scene, epoch=done, k=k, controller=controller,
                        generator=generator, result=to_json(result),
                    )  # fmt: skip
                    result["checkpoint"] = {"file": CHECKPOINT, "epoch": done}
                write_json(out / RESULTS, result)
                curves.add(record, result["totals"], controller)
    finally:
        bar.close()
        if curves is not None:
            curves.close()


def _certify(controller: PRDP, result: dict) -> None:
    cert = controller.certify()
    result["certificate"] = {**asdict(cert), "certified": cert.certified}
    logger.info("%s %s: %s", result["scene"], result["schedule"], cert.describe())


def _check_finite(value: float, what: str) -> None:
    """A NaN or Inf loss or metric stops the run (`NonFiniteError`), never trains on."""
    if not math.isfinite(value):
        raise NonFiniteError(
            f"{what} is {value}: training cannot continue (a diverged network, a too large "
            "learning rate, or a solve that lost accuracy); earlier epochs are complete"
        )


def totals(log: list[dict]) -> dict:
    """A run's totals over the epochs of `log` and its final and best validation error."""
    if not log:
        return {"epochs": 0}
    return {
        "epochs": len(log),
        "wall_time": sum(e["wall_time"] for e in log),
        "solver_time": sum(e["solver_time"] for e in log),
        "fwd_iterations": sum(e["fwd_iterations"] for e in log),
        "adj_iterations": sum(e["adj_iterations"] for e in log),
        "final_val_error": log[-1]["val_metric"],
        "best_val_error": min(e["val_metric"] for e in log),
        "k_final": log[-1]["k"],
        **({"rtol_final": log[-1]["rtol"]} if "rtol" in log[-1] else {}),
    }

