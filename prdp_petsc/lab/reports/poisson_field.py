"""The plot command of the coefficient-recovery scene (``demos/poisson_field.py``).

``prdp-petsc scene demos/poisson_field.py plot --preset paper --out fields.png``
recovers κ with PRDP (`recover`) and draws it against the scene's ``true_kappa``
(`plot_fields`); the scene declares ``COMMANDS = commands(<its module>)``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from types import ModuleType

import numpy as np

from prdp_petsc import load_mesh

from ..cli.arguments import add_preset
from .trained import train_and_keep

__all__ = ["commands", "plot_fields", "recover"]


def recover(
    scene: ModuleType, preset: str = "quick", schedule: str = "prdp", seed: int = 0
) -> np.ndarray:
    """Train once with `prdp_petsc.lab.training.harness.run`; return the recovered θ = log κ."""
    _, trained = train_and_keep(scene, schedule, preset=preset, seed=seed)
    return trained.optimizer.param_groups[0]["params"][0].detach().numpy().copy()


def plot_fields(scene: ModuleType, theta, out_png) -> None:
    """Draw the true and the recovered κ = exp(θ) per element side by side (tripcolor).

    The mesh is the L-shape at the refinement whose element count matches ``len(theta)``.
    """
    from matplotlib.figure import Figure
    from matplotlib.tri import Triangulation

    theta = np.asarray(theta, dtype=np.float64)
    refine = next((r for r in range(4) if 2808 * 4**r == len(theta)), None)
    if refine is None:
        raise ValueError(f"theta has {len(theta)} entries; no L-shape preset mesh has as many")
    mesh = load_mesh("lshape", refine=refine)
    tri = Triangulation(mesh.p[0], mesh.p[1], mesh.t.T)
    kappa_true = scene.true_kappa(mesh.p[:, mesh.t].mean(axis=1))
    kappa = np.exp(theta)
    e1 = mesh.p[:, mesh.t[1]] - mesh.p[:, mesh.t[0]]
    e2 = mesh.p[:, mesh.t[2]] - mesh.p[:, mesh.t[0]]
    area = np.abs(e1[0] * e2[1] - e1[1] * e2[0])  # the validation metric's weights
    error = np.sqrt(np.sum(area * (kappa - kappa_true) ** 2) / np.sum(area * kappa_true**2))
    vmin, vmax = min(kappa_true.min(), kappa.min()), max(kappa_true.max(), kappa.max())
    fig = Figure(figsize=(10, 4.4), layout="constrained")
    axes = fig.subplots(1, 2)
    for ax, values, title in (
        (axes[0], kappa_true, "true κ"),
        (axes[1], kappa, f"recovered κ (relative L2 error {error:.2f})"),
    ):
        image = ax.tripcolor(tri, facecolors=values, vmin=vmin, vmax=vmax, cmap="viridis")
        ax.set_aspect("equal")
        ax.set_title(title)
    fig.colorbar(image, ax=axes, shrink=0.9, label="κ")
    fig.savefig(out_png, dpi=120)


def commands(scene: ModuleType) -> dict[str, Callable]:
    """The scene file's ``COMMANDS`` (`prdp_petsc.lab.training.scene`): ``plot`` on the
    scene module `scene`."""

    def plot_command(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
        """Recover κ with PRDP on a preset and draw it against the true κ (`plot_fields`)."""
        add_preset(parser)
        parser.add_argument(
            "--out",
            default="poisson_field.png",
            help="the PNG to write (default poisson_field.png)",
        )

        def run(args: argparse.Namespace) -> int:
            plot_fields(scene, recover(scene, args.preset), args.out)
            return 0

        return run

    return {"plot": plot_command}
