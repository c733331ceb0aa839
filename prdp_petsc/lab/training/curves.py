"""Live training curves: TensorBoard event files beside a run's ``results.json``
(``tensorboard --logdir results/`` draws the runs as they train).

Per epoch (the step): ``loss/train``, ``metric/validation``, ``solver/K`` (and
``solver/rtol``), ``solver/inner_iterations`` and ``time/wall`` since the run began,
and, for a controller's checks, ``prdp/check_gap``, ``prdp/check_descent`` and
``prdp/check_iterations``.  The
scene, preset, schedule, route and seeds are the run's hparams.  A resumed run purges
the steps from its checkpoint on.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["Curves"]


class Curves:
    """TensorBoard event files of one run in `out`, from its `result` as
    `prdp_petsc.lab.training.harness.run` starts it, from epoch `start` on."""

    def __init__(self, out: str | Path, result: dict, start: int = 0):
        from torch.utils.tensorboard import SummaryWriter

        # purge_step: TensorBoard hides the earlier files' events from `start` on
        self._writer = SummaryWriter(log_dir=str(out), purge_step=start or None)
        if start == 0:  # a resumed run's hparams are in its first event file
            self._hparams(result)

    def _hparams(self, result: dict) -> None:
        from torch.utils.tensorboard.summary import hparams

        settings = {
            "scene": result["scene"],
            "preset": result["preset"],
            "schedule": result["schedule"],
            "route": ",".join(  # ksp/pc of every solver, as PETSc ran them
                f"{s['forward']['ksp_type']}/{s['forward']['pc_type']}" for s in result["solvers"]
            ),
            "seed": result["seed"],
            "torch_seed": result["torch_seed"],
        }
        metrics = {"metric/validation": None, "loss/train": None}  # names: the values are curves
        writer = self._writer.file_writer  # the run's own folder (add_hparams makes a new one)
        for summary in hparams(settings, metrics):
            writer.add_summary(summary)
        self._writer.flush()

    def add(self, record: dict, totals: dict, controller=None) -> None:
        """One epoch's `record`, the run's `totals` after it and its `controller`'s checks."""
        step = record["epoch"]
        scalars = {
            "loss/train": record["train_loss"],
            "metric/validation": record["val_metric"],
            "solver/K": record["k"],
            "solver/inner_iterations": totals["fwd_iterations"] + totals["adj_iterations"],
            "time/wall": totals["wall_time"],
        }
        if "rtol" in record:
            scalars["solver/rtol"] = record["rtol"]
        if controller is not None:
            gap = controller.history[-1].gap
            if gap is not None:
                scalars["prdp/check_gap"] = gap
                descent = controller.checks[-1].descent
                if descent is not None:
                    scalars["prdp/check_descent"] = descent
            costs = [c.cost for c in controller.checks if c.cost is not None]
            if costs:
                scalars["prdp/check_iterations"] = sum(costs)
        for tag, value in scalars.items():
            self._writer.add_scalar(tag, value, step)
        self._writer.flush()

    def close(self) -> None:
        """Flush and close the event file."""
        self._writer.close()
