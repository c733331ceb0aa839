"""The multilayer perceptron that several scenes and reports share.

The scenes' own networks live in the scene that uses them: ``ModalNet`` and
``ResidualMLP`` in ``demos/heat.py``, ``MeshNet`` in ``demos/heat_nonlinear.py``,
``ConvResNet`` in ``demos/ns2d.py``.
"""

from __future__ import annotations

import torch

__all__ = ["mlp"]


def mlp(
    n_in: int, n_out: int, width: int, depth: int, activation=torch.nn.GELU
) -> torch.nn.Sequential:
    """A float64 multilayer perceptron: `depth` hidden layers ``Linear → activation`` of
    `width`, then a linear layer to `n_out` (torch's default initialisation)."""
    layers, size = [], n_in
    for _ in range(depth):
        layers += [torch.nn.Linear(size, width), activation()]
        size = width
    layers.append(torch.nn.Linear(size, n_out))
    return torch.nn.Sequential(*layers).double()
