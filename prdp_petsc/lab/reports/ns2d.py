"""The report commands of the Navier–Stokes corrector scene (``demos/ns2d.py``).

``prdp-petsc scene demos/ns2d.py adjoint ...`` (`adjoint_report`) and ``... energy
RUN_FOLDER ...`` (`energy_report`).  The functions take the scene module and use its
``setup`` and ``hybrid_loss``; the scene declares ``COMMANDS = commands(<its module>)``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import torch

import prdp_petsc as pp

from ..cli.arguments import add_k, add_preset
from ..training.scene import preset_config
from .kinds import text_table

__all__ = [
    "adjoint_report",
    "commands",
    "energy_report",
    "format_adjoint_report",
    "format_energy_report",
]


def adjoint_report(
    scene: ModuleType, preset: str, ks=(8, 64), *, seed: int = 0, warmup: int = 4
) -> dict:
    """What the physics gradient costs and changes, on one training batch of `preset`.

    The corrector is first trained for `warmup` batches at K = 64 (the untrained
    projection is zero); then the 2-step loss of the first batch is differentiated with
    the solver at each K of `ks`, converged (forward and adjoint to rtol 1e-8), and
    converged but detached (no physics gradient).  Per case: iterations and seconds
    forward and adjoint, and the network gradient's relative distance from the
    converged and the detached one and its cosine with the converged one.
    """
    torch.manual_seed(seed)
    config = preset_config(scene, preset)  # "paper n=32": a preset, changed
    parts = scene.setup(config, seed)
    train, solver, hybrid = parts["train"], parts["solver"], parts["hybrid"]
    hybrid_loss = scene.hybrid_loss
    params = list(hybrid.net.parameters())
    optimizer = torch.optim.Adam(params, lr=config["lr"])
    order = torch.randperm(train.shape[1], generator=torch.Generator().manual_seed(seed))
    batch = config["batch"]
    solver.max_it = 64
    for i in range(warmup):
        idx = order[(i * batch) % len(order) :][:batch]
        optimizer.zero_grad()
        hybrid_loss(hybrid, solver, train[:, idx]).backward()
        optimizer.step()
    windows = train[:, order[:batch]]
    converged = solver.clone(
        max_it=100_000, rtol=1e-8, adjoint=pp.AdjointSettings(rtol=1e-8, max_it=100_000)
    )
    cases = [(f"K={k}", solver, k, True) for k in ks]
    cases += [("converged", converged, None, True), ("detached", converged, None, False)]
    grads, rows = {}, {}
    solver.max_it = ks[0]  # first-call costs (options, transpose set-up) outside the timings
    torch.autograd.grad(hybrid_loss(hybrid, solver, windows[:, :1]), params)
    for name, s, k, grad in cases:
        if k is not None:
            s.max_it = k
        s.reset_stats()
        loss = hybrid_loss(hybrid, s, windows, solver_grad=grad)
        g = torch.autograd.grad(loss, params)
        grads[name] = torch.cat([x.flatten() for x in g]).double()
        st = s.stats
        rows[name] = {
            "fwd_iterations": st.forward_iterations,
            "adj_iterations": st.adjoint_iterations,
            "fwd_seconds": st.forward_time,
            "adj_seconds": st.adjoint_time,
            "adj_over_fwd_time": st.adjoint_time / st.forward_time,
            "loss": float(loss.detach()),
        }
    ref, det = grads["converged"], grads["detached"]
    for name, g in grads.items():
        rows[name]["rel_to_converged"] = float((g - ref).norm() / ref.norm())
        rows[name]["rel_to_detached"] = float((g - det).norm() / det.norm())
        rows[name]["cosine_to_converged"] = float(g @ ref / (g.norm() * ref.norm()))
    converged.destroy()
    return {"preset": preset, "batch": int(windows.shape[1]), "warmup": warmup, "cases": rows}


def format_adjoint_report(report: dict) -> str:
    """The `adjoint_report` as a table."""
    header = ["case", "fwd its", "adj its", "fwd s", "adj s", "adj/fwd", "|g-g_conv|",
              "|g-g_det|", "cos"]  # fmt: skip
    rows = [
        (name, r["fwd_iterations"], r["adj_iterations"], f"{r['fwd_seconds']:.2f}",
         f"{r['adj_seconds']:.2f}", f"{r['adj_over_fwd_time']:.2f}",
         f"{r['rel_to_converged']:.3e}", f"{r['rel_to_detached']:.3e}",
         f"{r['cosine_to_converged']:.3f}")
        for name, r in report["cases"].items()
    ]  # fmt: skip
    return f"preset {report['preset']}, batch {report['batch']}\n" + text_table(header, rows)


def energy_report(scene: ModuleType, folder: str, steps: int | None = None) -> dict:
    """Error, energy and correlation per step of a trained run's held-out rollout.

    Rolls the validation flows of the run in `folder` out with the full-fidelity solver,
    with and without its corrector; per step, averaged over the flows: the normalised
    velocity error, the energy ratio ‖(û, v̂)‖/‖(u, v)‖ and the correlation
    ⟨(û, v̂), (u, v)⟩/(‖(û, v̂)‖‖(u, v)‖) against the reference.
    """
    from ..training.building import release
    from ..training.checkpoint import load_trained

    trained = load_trained(folder, module=scene)
    record = json.loads((Path(folder) / "results.json").read_text())
    config, seed = record["config"], record["seed"]
    parts = scene.setup(config, seed)
    weights = [p for group in trained.optimizer.param_groups for p in group["params"]]
    with torch.no_grad():
        for p, q in zip(parts["hybrid"].net.parameters(), weights, strict=True):
            p.copy_(q)
    release(trained)
    hybrid, full, val = parts["hybrid"], parts["full"], parts["val"]
    steps = steps or config["rollout_steps"]
    count = val.shape[1]

    def curves(step) -> dict:
        rows, s = [], val[0]
        with torch.no_grad():
            for t in range(steps):
                s = step(s)
                pred = s.reshape(count, 3, -1)[:, :2].flatten(1)
                ref = val[t + 1].reshape(count, 3, -1)[:, :2].flatten(1)
                norms = pred.norm(dim=1), ref.norm(dim=1)
                rows.append(
                    [
                        float(((pred - ref).norm(dim=1) / norms[1]).mean()),
                        float((norms[0] / norms[1]).mean()),
                        float(((pred * ref).sum(1) / (norms[0] * norms[1])).mean()),
                    ]
                )
        columns = [list(column) for column in zip(*rows, strict=True)]
        return dict(zip(("error", "energy", "correlation"), columns, strict=True))

    out = {
        "folder": str(folder),
        "corrected": curves(lambda s: hybrid(s, full)),
        "uncorrected": curves(lambda s: hybrid.solve(s, full)),
    }
    for solver in (parts["solver"], full):
        solver.destroy()
    return out


def format_energy_report(report: dict, marks=(1, 10, 20, 30, 40, 50)) -> str:
    """`energy_report` at a few steps, as a table (``(none)``: without the corrector)."""
    c, u = report["corrected"], report["uncorrected"]
    header = ["step", "error", "(none)", "energy", "(none)", "corr", "(none)"]
    rows = [
        (t, *(f"{curve[key][t - 1]:.3f}" for key in ("error", "energy", "correlation")
              for curve in (c, u)))
        for t in marks
        if t <= len(c["error"])
    ]  # fmt: skip
    return report["folder"] + "\n" + text_table(header, rows)


def commands(scene: ModuleType) -> dict[str, Callable]:
    """The scene file's ``COMMANDS`` (`prdp_petsc.lab.training.scene`): ``adjoint`` and
    ``energy`` on the scene module `scene`."""

    def adjoint_command(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
        """Print the adjoint figures of one training batch (`adjoint_report`), on one thread."""
        add_preset(parser)
        add_k(parser, [8, 64], "the capped Ks (GMRES iterations) to differentiate with")

        def run(args: argparse.Namespace) -> int:
            torch.set_num_threads(1)
            print(format_adjoint_report(adjoint_report(scene, args.preset, tuple(args.k))))
            return 0

        return run

    def energy_command(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
        """Error, energy and correlation of trained runs' rollouts, corrected or not.

        With and without the corrector, per step (`energy_report`).
        """
        parser.add_argument(
            "folders", nargs="+", help="run folders (a compare run's out/<schedule>)"
        )
        parser.add_argument("--steps", type=int, help="rollout steps (default: the run's)")

        def run(args: argparse.Namespace) -> int:
            torch.set_num_threads(1)
            for folder in args.folders:
                print(format_energy_report(energy_report(scene, folder, args.steps)))
            return 0

        return run

    return {"adjoint": adjoint_command, "energy": energy_command}
