"""Settings of the transpose (adjoint) solve and validation of tolerances."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError, plain

__all__ = ["AdjointSettings", "check_tolerances"]


@dataclass
class AdjointSettings:
    """Settings of the transpose solve; every ``None`` falls back to the forward one.

    Parameters
    ----------
    options : dict or str, optional
        PETSc options merged over the forward options (e.g. ``{"ksp_type": "gmres"}``).
        Without ``pc_*`` keys the adjoint shares the forward preconditioner, so the
        PC is set up once per operator for both solves.
    max_it, rtol, atol : optional
        Tolerances of the adjoint solve; ``None`` follows the forward solver, also
        when its ``max_it`` changes later.
    prefix : str, optional
        Options prefix; defaults to the forward prefix + ``"adj_"``.
    symmetric_pc : bool, optional
        Whether the adjoint preconditioner is a symmetric operator when A is
        symmetric.  For a symmetric A the transpose solve then *is* a forward
        solve, and `KSPSolver` runs ``KSPSolve`` instead of ``KSPSolveTranspose``
        (same iterates, no slower transposed products).  ``None`` (default) trusts
        only PCs that are symmetric by construction (none, jacobi, pbjacobi, icc,
        cholesky); ``True`` asserts it (e.g. GAMG with its default
        Chebyshev/Jacobi smoothers); ``False`` always uses ``KSPSolveTranspose``.
    """

    options: dict | str | None = None
    max_it: int | None = None
    rtol: float | None = None
    atol: float | None = None
    prefix: str | None = None
    symmetric_pc: bool | None = None


def check_tolerances(max_it, rtol, atol, what: str = "") -> None:
    """Raise ValueError unless ``max_it >= 1`` (int) and rtol, atol are finite and >= 0."""
    if isinstance(max_it, bool) or not isinstance(max_it, int | np.integer) or max_it < 1:
        raise InputError(f"{what}max_it must be an integer >= 1, got {plain(max_it)!r}")
    for name, val in (("rtol", rtol), ("atol", atol)):
        if isinstance(val, bool) or not np.isfinite(val) or val < 0:
            raise InputError(f"{what}{name} must be finite and >= 0, got {plain(val)!r}")
