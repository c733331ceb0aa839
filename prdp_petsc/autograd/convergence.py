"""PETSc's stopping and breakdown tests for the torch-unrolled iterations, one column per sample.

`Convergence` repeats, column by column, what PETSc decides inside ``KSPSolve``:

* ``KSPConvergedDefault``: with ``(rtol, atol, divtol, max_it)`` read from the
  KSP (``KSPGetTolerances``) and ``r₀`` the residual norm at iteration 0, a column
  converges when ``‖r‖ ≤ max(rtol ‖r₀‖, atol)`` (``CONVERGED_ATOL`` when
  ``‖r‖ < atol``, else ``CONVERGED_RTOL``) and diverges when ``‖r‖ ≥ divtol ‖r₀‖``
  (``DIVERGED_DTOL``; PETSc's default divtol is 1e5); a NaN or Inf norm is
  ``DIVERGED_NANORINF``.  With ``-ksp_norm_type none`` nothing is tested.
* the checks of ``KSPCheckDot``/``KSPCheckNorm`` (NaN or Inf inner products) and
  the breakdowns of ``KSPSolve_CG``, applied by the iteration through `stop`.

Norms are compared, never differentiated.  A stopped column keeps its reason,
iteration count and last residual norm (PETSc's ``ksp->rnorm``), which `info`
reports as a `SolveInfo`; `check` raises the `SolverError` implicit mode raises.
"""

from __future__ import annotations

import numpy as np
import torch
from petsc4py import PETSc

from ..core.results import CallInfo, SolveInfo, SolverError, reason_name

__all__ = ["Convergence", "Reason"]

Reason = PETSc.KSP.ConvergedReason
_NONE = PETSc.KSP.NormType.NONE
_NATURAL = PETSc.KSP.NormType.NATURAL
_UNPRECONDITIONED = PETSc.KSP.NormType.UNPRECONDITIONED


class Convergence:
    """Per-column state of PETSc's convergence test.

    Parameters
    ----------
    ksp : PETSc.KSP
        The forward KSP: tolerances and norm type are read from it.
    exponents : ndarray of int, shape (columns,)
        Power of two by which each column's right-hand side was divided
        (`prdp_petsc.core.safeguards.rhs_exponents`); atol is scaled along and
        reported norms are scaled back, as `KSPSolver` does.
    """

    def __init__(self, ksp: PETSc.KSP, exponents: np.ndarray):
        rtol, atol, divtol, _ = ksp.getTolerances()
        self.norm_type = ksp.getNormType()
        self.rtol, self.divtol = rtol, divtol
        self.exponents = np.asarray(exponents, dtype=np.int64)
        self.atol = torch.from_numpy(np.ldexp(atol, -self.exponents))
        columns = len(self.exponents)
        self.reason = torch.zeros(columns, dtype=torch.int64)
        self.iterations = torch.zeros(columns, dtype=torch.int64)
        self.norm = torch.zeros(columns, dtype=torch.float64)
        self.rnorm0 = self.ttol = None

    @property
    def active(self) -> torch.Tensor:
        """Mask of the columns still iterating."""
        return self.reason == 0

    def stop(self, where: torch.Tensor, reason: int) -> None:
        """Stop the active columns in `where` with PETSc reason `reason`."""
        self.reason = torch.where(self.active & where, int(reason), self.reason)

    def check_finite(self, value: torch.Tensor) -> None:
        """``KSPCheckDot``: a NaN or Inf inner product stops with ``DIVERGED_NANORINF``."""
        self.stop(~torch.isfinite(value), Reason.DIVERGED_NANORINF)

    def count(self, iterations: int) -> None:
        """Set the iteration number (PETSc's ``ksp->its``) of the active columns."""
        self.iterations = torch.where(self.active, iterations, self.iterations)

    def residual_norm(self, r, z, rz) -> torch.Tensor:
        """Norm of the KSP's norm type: ‖z‖ (preconditioned), ‖r‖, √|zᵀr| or 0 (none)."""
        with torch.no_grad():
            if self.norm_type == _NONE:
                return torch.zeros(r.shape[1], dtype=r.dtype)
            if self.norm_type == _UNPRECONDITIONED:
                return torch.linalg.vector_norm(r, dim=0)
            if self.norm_type == _NATURAL:
                return rz.abs().sqrt()
            return torch.linalg.vector_norm(z, dim=0)  # preconditioned (PETSc's default)

    def test(self, n: int, norm: torch.Tensor) -> None:
        """``KSPConvergedDefault`` at iteration `n` for the active columns."""
        active = self.active
        norm = norm.detach()
        self.norm = torch.where(active, norm, self.norm)
        if self.norm_type == _NONE:
            return
        if n == 0:
            self.rnorm0 = norm
            self.ttol = torch.maximum(self.rtol * norm, self.atol)
        converged = torch.where(
            norm < self.atol, int(Reason.CONVERGED_ATOL), int(Reason.CONVERGED_RTOL)
        )
        diverged = torch.where(norm >= self.divtol * self.rnorm0, int(Reason.DIVERGED_DTOL), 0)
        reason = torch.where(norm <= self.ttol, converged, diverged)
        reason = torch.where(torch.isfinite(norm), reason, int(Reason.DIVERGED_NANORINF))
        self.reason = torch.where(active, reason, self.reason)

    def finish(self, reason: int) -> None:
        """Give the columns still iterating after the last iteration `reason`."""
        self.stop(self.active, reason)

    def info(self, column: int = -1) -> SolveInfo:
        """`SolveInfo` of one column (default the last), as PETSc reports it."""
        norm = float(np.ldexp(float(self.norm[column]), int(self.exponents[column])))
        if self.norm_type == _NONE:  # PETSc computes no norm: not computed, never 0
            norm = None
        return SolveInfo(int(self.iterations[column]), reason_name(int(self.reason[column])), norm)

    def call_info(self) -> CallInfo:
        """`CallInfo` of every column, as `KSPSolver` reports a batch."""
        return CallInfo("forward", tuple(self.info(i) for i in range(len(self.reason))))

    def failed(self) -> int | None:
        """Index of the first column that diverged (hitting max_it is no failure), or None."""
        bad = (self.reason < 0) & (self.reason != int(Reason.DIVERGED_MAX_IT))
        return int(torch.nonzero(bad)[0, 0]) if bool(bad.any()) else None

    def check(self, what: str) -> None:
        """Raise `SolverError` with PETSc's reason if a column diverged.

        `what` names the method (``"cg/jacobi"``).  As in implicit mode the first
        failing column is reported, with its iterations and residual norm.
        """
        column = self.failed()
        if column is None:
            return
        info = self.info(column)
        where = f" (sample {column} of the batch)" if len(self.reason) > 1 else ""
        norm = "not computed" if info.residual_norm is None else f"{info.residual_norm:.3e}"
        raise SolverError(
            f"unrolled forward solve diverged{where}: {info.reason} after {info.iterations} "
            f"iterations ({what}, residual {norm}); check the operator "
            "and the PC, or lower the Richardson scale",
            reason=info.reason,
        )
