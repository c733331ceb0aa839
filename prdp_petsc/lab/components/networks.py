"""Networks for fields on unstructured meshes and on periodic grids.

`MeshNet` is a message-passing network over the edges of the mesh (the sparsity
pattern of the finite-element operator): each layer sums the neighbours' channel
vectors with a learnable weight per edge, mixes the channels, and applies GELU.
It suits emulators of local PDE time steps: its receptive field grows by one
ring of neighbours per layer, its cost is linear in the number of edges, and it
runs on any mesh, 2D or 3D, without a regular grid.  The edge sum is a scipy
CSR product inside a small autograd function (no torch-geometric dependency):
one layer costs O(nnz · batch · channels), forward and backward.

`ResidualMLP` is a dense network over all nodal values, ``u + MLP(u)``: the
paper's emulator class, blind to the mesh.

`ConvResNet` is a convolutional residual network with circular padding for
fields on periodic structured grids (a corrector of a coarse solver).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from prdp_petsc.autograd.once import once_differentiable

__all__ = ["ConvResNet", "MeshNet", "ResidualMLP"]


class MeshNet(torch.nn.Module):
    """Residual message passing on a mesh graph: ``h ← h + σ(Θ_l (W_l h))``.

    Parameters
    ----------
    adjacency : scipy.sparse matrix, shape (n, n)
        Graph of the nodes (e.g. the pattern of the FE operator on the unknowns);
        self-loops are added.  Edge weights start at the row-normalised adjacency.
    channels : int
        Hidden channels per node.
    layers : int
        Message-passing layers (receptive field: `layers` rings of neighbours).
    features : array_like, shape (n, f), optional
        Fixed per-node inputs appended to u (e.g. coordinates), so the network can
        tell the boundary layer from the interior.
    activation : {"gelu", None}
        Nonlinearity after each layer; None makes the network linear in its inputs
        (a product of learnable sparse operators), the right class for the step of
        a linear PDE.

    Notes
    -----
    Input and output have shape (B, n) (float64).  u is lifted to `channels`
    channels (channel 0 carries u itself), each layer adds ``σ(Θ_l (W_l h))`` with
    ``W_l`` the edge-weighted neighbour sum, and a linear readout gives û.  All
    channel mixings start at zero, so the network starts as the identity map, the
    natural first guess for a small time step, and trains like a residual network.
    """

    def __init__(
        self, adjacency, channels: int = 4, layers: int = 3, features=None, activation="gelu"
    ):
        super().__init__()
        if activation not in ("gelu", None):
            raise ValueError(f"activation must be 'gelu' or None, got {activation!r}")
        self.activation = activation
        A = sp.csr_matrix(adjacency, dtype=np.float64)
        A = (abs(A) + sp.identity(A.shape[0], format="csr")).tocsr()
        A.data[:] = 1.0
        A = sp.diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
        A = A.tocsr()
        A.sort_indices()
        self._pattern = _Pattern(A.indptr, A.indices, A.shape)
        feats = np.zeros((A.shape[0], 0)) if features is None else np.asarray(features)
        if feats.shape[0] != A.shape[0]:
            raise ValueError(f"features must have {A.shape[0]} rows, got {feats.shape}")
        self.register_buffer("features", torch.from_numpy(feats.astype(np.float64)))
        self.n = A.shape[0]
        start = torch.from_numpy(A.data)
        self.edge_weights = torch.nn.ParameterList(
            [torch.nn.Parameter(start.clone()) for _ in range(layers)]
        )
        self.lift = torch.nn.Linear(1 + feats.shape[1], channels).double()
        self.mix = torch.nn.ModuleList(
            [torch.nn.Linear(channels, channels).double() for _ in range(layers)]
        )
        self.readout = torch.nn.Linear(channels, 1).double()
        with torch.no_grad():  # start as the identity map: channel 0 carries u through
            self.lift.weight[0].zero_()
            self.lift.weight[0, 0] = 1.0
            self.lift.bias[0] = 0.0
            for mix in self.mix:
                mix.weight.zero_()
                mix.bias.zero_()
            self.readout.weight.zero_()
            self.readout.weight[0, 0] = 1.0
            self.readout.bias.zero_()

    def _propagate(self, h: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Edge-weighted neighbour sum of h, shape (n, B, C)."""
        flat = h.reshape(self.n, -1)
        return _EdgeSum.apply(weights, flat, self._pattern).reshape(h.shape)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        if u.shape[-1] != self.n:
            raise ValueError(f"MeshNet expects (batch, {self.n}), got {tuple(u.shape)}")
        squeeze = u.ndim == 1
        u = u[None] if squeeze else u
        inputs = [u.T[..., None]]  # nodes first: (n, B, 1)
        if self.features.shape[1]:
            inputs.append(self.features[:, None, :].expand(-1, u.shape[0], -1))
        h = self.lift(torch.cat(inputs, dim=-1))
        for weights, mix in zip(self.edge_weights, self.mix, strict=True):
            update = mix(self._propagate(h, weights))
            h = h + (torch.nn.functional.gelu(update) if self.activation else update)
        out = self.readout(h)[..., 0].T
        return out[0] if squeeze else out


class _Pattern:
    """CSR pattern of the graph with the positions needed by `_EdgeSum`'s backward."""

    def __init__(self, indptr, indices, shape):
        self.indptr, self.indices, self.shape = indptr, indices, shape
        self.rows = np.repeat(np.arange(shape[0]), np.diff(indptr))


class _EdgeSum(torch.autograd.Function):
    """``Y = W X`` for a sparse W with learnable values on a fixed pattern (scipy CSR)."""

    @staticmethod
    def forward(ctx, values, X, pattern):
        W = sp.csr_matrix(
            (values.detach().numpy(), pattern.indices, pattern.indptr), shape=pattern.shape
        )
        ctx.W, ctx.pattern = W, pattern
        ctx.save_for_backward(X)
        return torch.from_numpy(W @ X.detach().numpy())

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        (X,) = ctx.saved_tensors
        g = grad.contiguous().numpy()
        pattern = ctx.pattern
        grad_values = grad_X = None
        if ctx.needs_input_grad[0]:
            x = X.detach().numpy()
            grad_values = torch.from_numpy(
                np.einsum("km,km->k", g[pattern.rows], x[pattern.indices])
            )
        if ctx.needs_input_grad[1]:
            grad_X = torch.from_numpy(ctx.W.T @ g)
        return grad_values, grad_X, None


class ConvResNet(torch.nn.Module):
    """Residual CNN on periodic 2D grids: 1×1 lift, residual blocks, 1×1 projection.

    Each block is ``h ← h + conv(σ(conv(σ(h))))`` with 3×3 convolutions and circular
    padding (the grid is periodic), σ = GELU.

    Parameters
    ----------
    in_channels, out_channels : int
    hidden : int
        Channels inside the blocks.
    blocks : int
        Residual blocks (two 3×3 convolutions each).
    dtype : torch.dtype
        Parameter dtype (float32 by default: the convolutions dominate the cost and
        a corrector needs no float64); `forward` casts its input to it and its
        output back.
    zero_init : bool
        Zero the projection, so the network starts as the zero map (a corrector
        that starts by changing nothing).

    Notes
    -----
    Input and output have shape (B, C, H, W).  With ``hidden=64, blocks=3`` and 3
    channels in and out it has 222 019 parameters.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        hidden: int = 64,
        blocks: int = 3,
        *,
        dtype: torch.dtype = torch.float32,
        zero_init: bool = True,
    ):
        super().__init__()

        def conv(cin, cout, k):
            return torch.nn.Conv2d(cin, cout, k, padding=k // 2, padding_mode="circular")

        self.lift = conv(in_channels, hidden, 1)
        self.blocks = torch.nn.ModuleList(
            [torch.nn.ModuleList([conv(hidden, hidden, 3), conv(hidden, hidden, 3)])
             for _ in range(blocks)]
        )  # fmt: skip
        self.project = conv(hidden, out_channels, 1)
        if zero_init:
            with torch.no_grad():
                self.project.weight.zero_()
                self.project.bias.zero_()
        self.to(dtype)
        self.dtype = dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        act = torch.nn.functional.gelu
        h = self.lift(x.to(self.dtype))
        for first, second in self.blocks:
            h = h + second(act(first(act(h))))
        return self.project(h).to(x.dtype)


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


class ResidualMLP(torch.nn.Module):
    """``N(u) = u + MLP(u)`` over a field's n nodal values (float64, GELU).

    Parameters
    ----------
    n : int
        Number of values in and out.
    width, depth : int
        Hidden width and number of hidden layers (``Linear → GELU`` each).

    Notes
    -----
    The last layer starts at zero, so N starts as the identity: a time step of a
    smooth field is close to it.  N sees the field as a vector, not the mesh: it
    learns the step from data alone, and with few samples against n inputs its
    error stays far above a mesh-aware network's (heat2d's ``paper_mlp``).
    """

    def __init__(self, n: int, width: int, depth: int):
        super().__init__()
        self.mlp = mlp(n, n, width, depth)
        torch.nn.init.zeros_(self.mlp[-1].weight)
        torch.nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return u + self.mlp(u)
