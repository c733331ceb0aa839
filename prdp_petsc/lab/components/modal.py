"""A spectral network on a mesh: learned weights on the lowest Laplacian eigenmodes.

`ModalNet` projects a nodal field onto the m lowest eigenvectors of the generalised
problem ``K φ = λ M φ`` (stiffness and mass of the finite-element space: the mesh's
Fourier basis), multiplies each coefficient by a learnable weight, and returns the
field of the new coefficients.  It is the spectral layer of a Fourier neural
operator carried over to an unstructured mesh: its cost is two dense (n × m)
products, its parameters act on M-orthonormal coordinates, so gradient training
is well conditioned, and the modes it drops are the ones a diffusion step damps
most.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

__all__ = ["ModalNet", "laplacian_modes"]


def laplacian_modes(stiffness, mass, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The `count` smallest eigenpairs of ``K φ = λ M φ`` (shift-invert around 0).

    Parameters
    ----------
    stiffness, mass : scipy.sparse matrix, shape (n, n)
        Symmetric positive definite stiffness K (Dirichlet nodes eliminated) and mass M.
    count : int
        Number of modes, ``1 <= count < n``.

    Returns
    -------
    eigenvalues : numpy.ndarray, shape (count,)
        Ascending.
    modes : numpy.ndarray, shape (n, count)
        M-orthonormal: ``modesᵀ M modes = I``.
    """
    n = stiffness.shape[0]
    if not 1 <= count < n:
        raise ValueError(f"count must lie in [1, {n - 1}], got {count}")
    K, M = sp.csc_matrix(stiffness), sp.csc_matrix(mass)
    start = np.ones(n)  # a fixed start vector: the same modes (and signs) every call
    values, modes = spla.eigsh(K, k=count, M=M, sigma=0.0, which="LM", v0=start)
    order = np.argsort(values)
    return values[order], modes[:, order]


class ModalNet(torch.nn.Module):
    """``N(u) = Φ (w ⊙ Φᵀ M u)``: a learned multiplier per Laplacian eigenmode.

    Parameters
    ----------
    stiffness, mass : scipy.sparse matrix, shape (n, n)
        Stiffness and mass of the unknowns (see `laplacian_modes`).
    modes : int
        Number m of eigenmodes kept.

    Notes
    -----
    Input and output have shape (B, n) or (n,) (float64).  This is the spectral
    layer of a Fourier neural operator (a learned weight per mode, here with one
    channel) in the mesh's own eigenbasis.  A weight per mode, rather than a dense
    m × m matrix, is what keeps training and rollouts sound: a dense matrix trained
    through the solve reached a small one-step loss yet had eigenvalues above one in
    directions the data barely excite, and its rollouts grew.  With one weight per
    mode, each weight is fitted by that mode's content alone and is the map's own
    eigenvalue.  The weights start at one, so the network starts as the
    M-orthogonal projection onto the kept modes (the identity on smooth fields);
    components outside the m modes are dropped, so a rollout cannot amplify them.
    """

    def __init__(self, stiffness, mass, modes: int):
        super().__init__()
        eigenvalues, phi = laplacian_modes(stiffness, mass, modes)
        self.register_buffer("eigenvalues", torch.from_numpy(eigenvalues))
        self.register_buffer("phi", torch.from_numpy(np.ascontiguousarray(phi)))
        self.register_buffer(
            "project", torch.from_numpy(np.ascontiguousarray((sp.csr_matrix(mass) @ phi).T))
        )
        self.n = phi.shape[0]
        self.weight = torch.nn.Parameter(torch.ones(modes, dtype=torch.float64))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        if u.shape[-1] != self.n:
            raise ValueError(f"ModalNet expects (batch, {self.n}), got {tuple(u.shape)}")
        return ((u @ self.project.T) * self.weight) @ self.phi.T
