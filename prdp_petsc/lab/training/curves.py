"""Live training curves: TensorBoard event files beside a run's ``results.json``.

`Curves` writes a run's scalars after every epoch and flushes them, so
``tensorboard --logdir results/`` draws a run while it trains; every run folder of a
comparison (``prdp/``, ``fixed_43/``, ``prdp_on_cg-icc/``) is one TensorBoard run.
The step is the epoch (``results.json``'s ``epoch``, from 0):

* ``loss/train``: the epoch's mean training loss;
* ``metric/validation``: the validation metric the controller reads;
* ``solver/K``: the iteration cap (``max_it``) the epoch ran with; under the ``rtol``
  schedule also ``solver/rtol``;
* ``solver/inner_iterations``: forward + adjoint iterations PETSc ran since the run
  began, the solves of the controller's checks included;
* ``time/wall``: seconds of training since the run began (as ``results.json``'s
  ``wall_time``: checkpoint saves and these writes not counted);
* ``prdp/check_gap``: the fidelity gap of a check (the ``auto`` schedule), in the
  epochs that made one, and ``prdp/check_iterations``: the inner iterations of the
  controller's checks so far (`prdp_petsc.Certificate`'s ``cost``; they are part of
  ``solver/inner_iterations`` too).

The run's scene, preset, schedule, route (the KSP/PC types of its solvers) and seeds
are its hparams (TensorBoard's HPARAMS tab).  A resumed run purges the steps from its
checkpoint on, so epochs trained again are not drawn twice.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["Curves", "route"]


def route(solvers: list[dict]) -> str:
    """The KSP/PC types PETSc used, ``ksp/pc`` per scene solver (`KSPSolver.describe`
    records), comma-separated: ``"cg/icc"``, ``"richardson/jacobi,cg/gamg"``."""
    return ",".join(f"{s['forward']['ksp_type']}/{s['forward']['pc_type']}" for s in solvers)


class Curves:
    """TensorBoard event files of one run, in its output folder `out`.

    `result` is the run's ``results.json`` record as `prdp_petsc.lab.training.harness.run`
    starts it (its hparams are read from it); `start` is the first epoch to be trained
    (a resumed run's checkpoint epoch).  Use as a context manager, or `close`.
    """

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
            "route": route(result["solvers"]),
            "seed": result["seed"],
            "torch_seed": result["torch_seed"],
        }
        metrics = {"metric/validation": None, "loss/train": None}  # names: the values are curves
        writer = self._writer.file_writer  # the run's own folder (add_hparams makes a new one)
        for summary in hparams(settings, metrics):
            writer.add_summary(summary)
        self._writer.flush()

    def add(self, record: dict, totals: dict, controller=None) -> None:
        """One epoch: its `record` (an entry of ``results.json``'s ``epochs``), the run's
        `totals` after it and its `controller` (a `prdp_petsc.PRDP`, None for a constant
        K), whose checks it reports; flushed to disk."""
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
            costs = [c.cost for c in controller.checks if c.cost is not None]
            if costs:
                scalars["prdp/check_iterations"] = sum(costs)
        for tag, value in scalars.items():
            self._writer.add_scalar(tag, value, step)
        self._writer.flush()

    def close(self) -> None:
        """Flush and close the event file."""
        self._writer.close()

    def __enter__(self) -> Curves:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
