"""One implicit-Euler step of the nonlinear heat equation, assembled with scikit-fem.

The step from ``u_prev`` to ``u`` of ``u_t = ∇·(κ(u) ∇u) + f`` with
``κ(u) = 1 + α u²`` and ``u = g`` on the Dirichlet boundary is the root of the
residual (P1 Galerkin, φ_i the test functions of the unknown nodes I)

    R_i(u) = ∫ (u − u_prev − Δt f) φ_i + Δt ∫ κ(u) ∇u·∇φ_i ,    i ∈ I,

with the full vector ``u = (u_I, g)``.  `NonlinearHeat` assembles, in numpy and
scipy, everything a Newton or Picard loop and its adjoint need:

* the residual R(u_I),
* the Newton Jacobian ``J = M + Δt K(κ(u)) + Δt C(u)``, where
  ``C_ij = ∫ κ'(u) φ_j ∇u·∇φ_i`` (κ' = 2αu) makes J non-symmetric,
* the Picard operator ``M + Δt K(κ(u))`` (symmetric positive definite), the
  frozen-coefficient linearisation,
* the products ``λᵀ ∂R/∂p`` for the inputs p = (u_prev, f, g, α).

It is the `prdp_petsc.autograd.nonlinear` problem protocol (``n``, ``residual``,
``jacobian``, ``picard``, ``vjp`` and the symmetry declarations); nothing here
imports torch or PETSc.  Nodal vectors (u_prev, f) have ``basis.N`` entries,
the unknowns ``len(interior)``, boundary values ``len(boundary)``, α is a scalar.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .forms import mass_matrix

__all__ = ["NonlinearHeat"]


class NonlinearHeat:
    """Residual, Jacobian and adjoint products of an implicit nonlinear heat step.

    Parameters
    ----------
    basis : skfem.CellBasis
        A scalar Lagrange basis (P1 on triangles or tetrahedra is the intended use).
    dt : float
        Time step Δt > 0.
    dirichlet : array of int, optional
        Dirichlet degrees of freedom (e.g. ``basis.get_dofs()``).  Without them
        every node is an unknown and the boundary is insulated (natural
        condition); g is then an empty vector.

    Notes
    -----
    The unknowns are ``u_I``; `expand` returns the full nodal vector.  All
    callables take the parameters in the order ``(u_prev, f, g, alpha)``.  The
    forms are scikit-fem `BilinearForm` / `LinearForm` objects with the current
    iterate passed as the field ``w["u"]`` (``basis.interpolate``), assembled
    with the basis' own quadrature, so the Jacobian is the exact derivative of
    the discrete residual.
    """

    jacobian_symmetric = False
    picard_symmetric = True

    def __init__(self, basis, dt: float, *, dirichlet=None):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and > 0, got {dt!r}")
        self.basis = basis
        self.dt = float(dt)
        n = basis.N
        boundary = np.zeros(0, dtype=np.int64) if dirichlet is None else dirichlet
        self.boundary = np.unique(np.asarray(boundary, dtype=np.int64).ravel())
        if self.boundary.size and (self.boundary[0] < 0 or self.boundary[-1] >= n):
            raise ValueError(f"dirichlet indices must lie in [0, {n})")
        self.interior = np.setdiff1d(np.arange(n), self.boundary)
        self.M = mass_matrix(basis)
        self._M_I = self.M[self.interior].tocsr()  # rows I of M: the residual's mass term
        self._forms = _forms()

    @property
    def n(self) -> int:
        """Number of unknowns (interior nodes)."""
        return len(self.interior)

    def expand(self, u_i: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Full nodal vector with ``u[I] = u_i`` and ``u[B] = g``."""
        u = np.empty(self.basis.N)
        u[self.interior] = u_i
        u[self.boundary] = g
        return u

    def _fields(self, u_i, g, alpha) -> dict:
        u = self.expand(u_i, g)
        return {"u": self.basis.interpolate(u), "alpha": float(alpha), "dt": self.dt}

    def residual(self, u_i, u_prev, f, g, alpha) -> np.ndarray:
        """``R(u_I)`` on the unknowns, shape ``(n,)``."""
        u = self.expand(u_i, g)
        flux = self._forms["flux"].assemble(self.basis, **self._fields(u_i, g, alpha))
        return self._M_I @ (u - u_prev - self.dt * f) + self.dt * flux[self.interior]

    def _operator(self, name, u_i, g, alpha) -> sp.csr_matrix:
        return self._forms[name].assemble(self.basis, **self._fields(u_i, g, alpha)).tocsr()

    def jacobian(self, u_i, u_prev, f, g, alpha) -> sp.csr_matrix:
        """Newton Jacobian ``∂R/∂u_I`` (non-symmetric: it holds the κ'(u) term)."""
        J = self._operator("jacobian", u_i, g, alpha)
        return J[self.interior][:, self.interior].tocsr()

    def picard(self, u_i, u_prev, f, g, alpha) -> sp.csr_matrix:
        """Picard operator ``M + Δt K(κ(u))`` on the unknowns (symmetric positive definite)."""
        A = self._operator("picard", u_i, g, alpha)
        return A[self.interior][:, self.interior].tocsr()

    def vjp(self, u_i, lam, u_prev, f, g, alpha, *, needs=(True, True, True, True)) -> tuple:
        """``λᵀ ∂R/∂p`` for p = (u_prev, f, g, α); None where `needs` is False.

        ``∂R/∂u_prev = −M_I·``, ``∂R/∂f = −Δt M_I·``, ``∂R/∂g = J_IB`` (the full
        Jacobian's boundary columns) and ``∂R/∂α = Δt ∫ u² ∇u·∇φ_i``.
        """
        mt_lam = self._M_I.T @ lam  # M_Iᵀ λ, a nodal vector
        out = [
            -mt_lam if needs[0] else None,
            -self.dt * mt_lam if needs[1] else None,
            None,
            None,
        ]
        if needs[2]:
            J = self._operator("jacobian", u_i, g, alpha)
            out[2] = J[self.interior][:, self.boundary].T @ lam
        if needs[3]:
            fields = self._fields(u_i, g, alpha)
            d_alpha = self._forms["d_alpha"].assemble(self.basis, **fields)
            out[3] = np.asarray(self.dt * (d_alpha[self.interior] @ lam))
        return tuple(out)


def _forms() -> dict:
    from skfem import BilinearForm, LinearForm
    from skfem.helpers import dot, grad

    @LinearForm
    def flux(v, w):
        return (1.0 + w.alpha * w.u**2) * dot(grad(w.u), grad(v))

    @LinearForm
    def d_alpha(v, w):
        return w.u**2 * dot(grad(w.u), grad(v))

    @BilinearForm
    def picard(u, v, w):
        return u * v + w.dt * (1.0 + w.alpha * w.u**2) * dot(grad(u), grad(v))

    @BilinearForm
    def jacobian(u, v, w):
        kappa = 1.0 + w.alpha * w.u**2
        d_kappa = 2.0 * w.alpha * w.u
        return u * v + w.dt * (
            kappa * dot(grad(u), grad(v)) + d_kappa * u * dot(grad(w.u), grad(v))
        )

    return {"flux": flux, "d_alpha": d_alpha, "picard": picard, "jacobian": jacobian}
