"""One right-hand side through one KSP: scaling, solve, outcome check, rescue.

`SolveStep` is the inner loop of `KSPSolver`; it runs once per right-hand side,
so the common case (a finished solve, capped or converged) costs a handful of
PETSc queries, and everything else (rescue, errors) happens off that path.

What a finished solve costs besides PETSc's own work: a capped one two vector
norms (``‖x‖``, ``‖b‖``; ``‖A‖`` is kept per operator), a converged one a
``MatMult`` for its true residual (`prdp_petsc.core.safeguards.judge`), and so does
one that had a tolerance to meet and hit ``max_it`` instead (`SolveStep.unconverged`).
"""

from __future__ import annotations

import math

import numpy as np
from petsc4py import PETSc

from ..errors import SingularOperatorError
from . import safeguards
from .results import Side, SolveInfo, SolverError, reason_name

__all__ = ["SolveStep", "reduction_rate"]

_MAX_IT = PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT
_REASON = PETSc.KSP.ConvergedReason
#: convergence claims that met a residual tolerance (or a user's test); CONVERGED_ITS
#: (K iterations run without a norm to test: preonly, Richardson+SOR) is a capped solve
_TOLERANCE_MET = frozenset(
    {_REASON.CONVERGED_RTOL, _REASON.CONVERGED_ATOL, _REASON.CONVERGED_USER}
    | {_REASON.CONVERGED_RTOL_NORMAL_EQUATIONS, _REASON.CONVERGED_ATOL_NORMAL_EQUATIONS}
)
_ITS = _REASON.CONVERGED_ITS
_NO_NORM = PETSc.KSP.NormType.NONE


def reduction_rate(history: list | np.ndarray) -> float | None:
    """Geometric mean residual reduction per iteration, ``(h[-1]/h[0])^(1/(len(h)-1))``.

    `history` is a KSP's residual history of one solve (``KSPGetResidualHistory``:
    the initial norm, then one per iteration).  None without an iteration or
    without a positive finite initial norm; 0.0 for an exact solve.
    """
    if len(history) < 2:
        return None
    first, last = float(history[0]), float(history[-1])
    if not (math.isfinite(first) and first > 0):
        return None
    ratio = last / first
    if not math.isfinite(ratio):
        return None
    return ratio ** (1.0 / (len(history) - 1))


class SolveStep:
    """Solve ``A x = b`` (``Aᵀ x = b`` with `transpose`) for one row at a time.

    Parameters
    ----------
    ksp : PETSc.KSP
    mat : PETSc.Mat
        The operator (for the rescue's backward-error check).
    b_vec, x_vec : PETSc.Vec
        Work vectors, reused for every row.
    layout : RowLayout
        How rows and results map onto the Vecs (`prdp_petsc.core.parallel`).
    kind : Side
        Which solve this is, named in error messages.
    transpose : bool
        Run ``KSPSolveTranspose`` instead of ``KSPSolve``.
    norm : callable
        Returns ``max(‖A‖₁, ‖A‖_∞)`` of the operator (kept by its owner per set of
        values; called only when a finished solve is checked).
    """

    __slots__ = (
        "ksp",
        "mat",
        "b_vec",
        "x_vec",
        "layout",
        "kind",
        "transpose",
        "run",
        "infos",
        "norm",
        "kernel",
        "finite",
        "safe_norms",
        "unconverged",
    )

    def __init__(self, ksp, mat, b_vec, x_vec, layout, kind: Side, transpose: bool, norm):
        self.ksp, self.mat, self.kind, self.transpose = ksp, mat, kind, transpose
        self.b_vec, self.x_vec, self.layout, self.norm = b_vec, x_vec, layout, norm
        self.run = ksp.solveTranspose if transpose else ksp.solve
        self.infos: list[SolveInfo] = []  # one per row solved (the failing one included)
        self.finite = True  # every row's x had a finite norm (so no NaN/Inf entry) so far
        #: (row, `safeguards.Residual`) of every row that had a tolerance and hit max_it
        self.unconverged: list[tuple[int, safeguards.Residual]] = []
        # ‖b‖ in this range: every entry's size is in SAFE_RANGE or 0, and b is not scaled
        low, high = safeguards.SAFE_RANGE
        self.safe_norms = (low * math.sqrt(b_vec.getSize()), high)
        # the solutions of a singular system differ by its kernel: null(A), or null(Aᵀ)
        # for a transpose solve.  A right preconditioner (FGMRES, fieldsplit) can put a
        # kernel part into x, so it is removed: x is the minimum-norm solution A⁺b
        kernel = mat.getTransposeNullSpace() if transpose else mat.getNullSpace()
        self.kernel = kernel if kernel is not None and bool(kernel) else None

    def __call__(self, row: np.ndarray, out: np.ndarray) -> int:
        """Solve for `row` into `out`; return the iterations run (rescue re-runs included).

        The scaling exponent of the right-hand side (`safeguards.rhs_exponent`) is
        decided from ‖b‖, which the outcome check needs anyway (PETSc keeps it while
        b is unchanged): only a norm outside ``[2⁻¹⁰⁰ √n, 2¹⁰⁰]`` (an underflowed or
        overflowed one included) can come from an entry outside
        `safeguards.SAFE_RANGE`, and only then are the entries read.  At the edges
        of that range the two tests may disagree by a rounding; a power-of-two
        scaling changes no bit of a capped solve there, so neither does that.
        """
        ksp, x_vec, b_vec = self.ksp, self.x_vec, self.b_vec
        local = self.layout.local(row)
        b_vec.setArray(local)
        exponent = 0
        if not self.safe_norms[0] <= b_vec.norm() <= self.safe_norms[1]:
            exponent = self._exponent(row)
            if exponent:  # new values (a power of two: exact), and no stale ‖b‖: PETSc's
                # norm squares the entries, so that of the unscaled b may have
                # underflowed or overflowed
                b_vec.setArray(np.ldexp(local, -exponent))
        # one process holds all of x: PETSc writes it straight into the caller's row
        placed = not self.layout.distributed and out.flags.c_contiguous
        if placed:
            x_vec.placeArray(out)
        try:
            rescued = self._solve(exponent)
            if not placed:
                x = self.layout.gather(x_vec)
                out[:] = x
        finally:
            if placed:
                x_vec.resetArray()
        if exponent:
            np.ldexp(out, exponent, out=out)
        return ksp.getIterationNumber() + rescued

    def solve_vecs(self, b_vec: PETSc.Vec, x_vec: PETSc.Vec) -> int:
        """Solve for the Vec `b_vec` into the Vec `x_vec` (the device path: both wrap a
        caller's memory, `prdp_petsc.core.device`); return the iterations run.

        As `__call__`, without reading an entry on the host: the scaling exponent comes
        from ``‖b‖_∞`` (a PETSc norm, asked only when ``‖b‖₂`` is outside the safe
        range), a scaled b is a copy in the step's own work Vec (the caller's b is never
        written), and x is scaled back in place.
        """
        exponent = 0
        if not self.safe_norms[0] <= b_vec.norm() <= self.safe_norms[1]:
            exponent = safeguards.exponent_of(b_vec.norm(PETSc.NormType.INFINITY))
            if exponent:
                work = self.b_vec
                b_vec.copy(work)
                work.scale(math.ldexp(1.0, -exponent))
                b_vec = work
        saved = self.b_vec, self.x_vec
        self.b_vec, self.x_vec = b_vec, x_vec
        try:
            rescued = self._solve(exponent)
        finally:
            self.b_vec, self.x_vec = saved
        if exponent:
            x_vec.scale(math.ldexp(1.0, exponent))
        return self.ksp.getIterationNumber() + rescued

    def _solve(self, exponent: int) -> int:
        """Solve for the b set in `b_vec` (scaled by 2^-exponent) into `x_vec`, check the
        outcome; return the iterations of a discarded run (0 unless rescued)."""
        ksp, x_vec = self.ksp, self.x_vec
        x_vec.set(0.0)
        atol = ksp.getTolerances()[1] if exponent else 0.0
        if atol > 0:  # atol is absolute: scale it along
            ksp.setTolerances(atol=math.ldexp(atol, -exponent))
        try:
            self.run(self.b_vec, x_vec)
        except PETSc.Error as err:
            raise self._petsc_failure(err) from err
        finally:
            if atol > 0:
                ksp.setTolerances(atol=atol)
        reason = ksp.getConvergedReason()
        history = ksp.getConvergenceHistory().tolist()  # Python floats: a few, cheap
        rescued = 0
        if reason in safeguards.LATE_REASONS or safeguards.went_far(ksp, history):
            self.finite = False
            rescued = self._verify(reason, exponent)
        elif reason < 0 and reason != _MAX_IT:
            self.infos.append(self._info(exponent, history, reason))
            raise self._diverged(self.infos[-1], self._diagnose())
        else:
            self.infos.append(self._info(exponent, history, reason))
            size, residual = self._check_iterate(reason)
            if exponent or not math.isfinite(size):
                self.finite = False  # the caller tests the entries
            if reason == _MAX_IT and math.isfinite(size) and any(self.ksp.getTolerances()[:2]):
                # a tolerance was set and not met: its true residual, for the report
                if residual is None:
                    residual = safeguards.true_residual(
                        self.mat, self.b_vec, x_vec, transpose=self.transpose, norm=self.norm()
                    )
                self.unconverged.append((len(self.infos) - 1, residual))
        if self.kernel is not None:
            self.kernel.remove(x_vec)
            self.finite = False  # x changed after its norm was taken
        return rescued

    def _exponent(self, row: np.ndarray) -> int:
        """`safeguards.rhs_exponent` of the whole right-hand side (agreed by the ranks
        when each holds only its rows; they all get here together, ‖b‖ being global)."""
        exponent = safeguards.rhs_exponent(row)
        if self.layout.distributed and not self.layout.replicated:
            exponent = int(self.layout.agree_max(np.array([exponent]))[0])
        return exponent

    def reset(self) -> None:
        """Forget the rows of the last call (the step is kept for the next one)."""
        self.infos = []
        self.finite = True
        self.unconverged = []

    def info(self) -> SolveInfo | None:
        """`SolveInfo` of the last row (PETSc's own outcome when a solve failed)."""
        return self.infos[-1] if self.infos else None

    def _info(
        self, exponent: int, history: list | None = None, reason: int | None = None
    ) -> SolveInfo:
        """PETSc's outcome of the solve just run; no residual where PETSc computed none.

        The KSPs record their residual history (reset at every solve), so norm type
        none or an empty history means no norm was computed (``preonly``, ``-ksp_norm_type none``,
        Richardson+SOR), and ``KSPGetResidualNorm``'s 0 means nothing.
        """
        ksp = self.ksp
        if history is None:
            history = ksp.getConvergenceHistory().tolist()
        if reason is None:
            reason = ksp.getConvergedReason()
        computed = len(history) > 0 and ksp.getNormType() != _NO_NORM
        return SolveInfo(
            ksp.getIterationNumber(),
            reason_name(reason),
            math.ldexp(ksp.getResidualNorm(), exponent) if computed else None,
            reduction_rate(history) if computed else None,
        )

    def _check_iterate(self, reason: int) -> tuple[float, safeguards.Residual | None]:
        """Refuse a finished solve's x that did not solve the system (`safeguards.judge`);
        return ‖x‖ and the `Residual` if it was computed.

        Converged: its true residual, one ``MatMult``.  Capped: only when
        ``‖A‖ ‖x‖ > ‖b‖ / NULL_TOLERANCE`` (two vector norms decide).
        """
        size = self.x_vec.norm()
        if not math.isfinite(size):
            return size, None  # the caller's finiteness check raises (DIVERGED_NANORINF)
        if reason in _TOLERANCE_MET:
            outcome = "converged"
        elif reason > 0 and reason != _ITS:
            outcome = "stopped"
        else:
            outcome = "capped"
        norm = None
        if outcome == "capped":
            norm = self.norm()
            if not norm * size > self.b_vec.norm() / safeguards.NULL_TOLERANCE:
                return size, None
        residual = safeguards.true_residual(
            self.mat, self.b_vec, self.x_vec, transpose=self.transpose, norm=norm or self.norm()
        )
        rtol = self.ksp.getTolerances()[0] if outcome == "stopped" else 0.0
        verdict = safeguards.judge(residual, outcome, rtol)
        if verdict == "singular":
            raise self._singular(self.infos[-1], residual)
        if verdict == "not solved":
            info = self.infos[-1]
            raise SolverError(
                f"{self.kind} solve ({self._types()}) reported {info.reason} after "
                f"{info.iterations} iterations, but its iterate does not solve the system "
                f"({residual.describe()}): PETSc tested no residual, or the KSP's own "
                "(often preconditioned) norm, which the true one contradicts. Check the "
                "preconditioner (-ksp_norm_type unpreconditioned tests the true residual) "
                f"and whether the operator is singular: if it is, {safeguards.DECLARE_NULLSPACE}",
                reason="FALSE_CONVERGENCE",
            )
        return size, residual

    def _kernel_named(self) -> str:
        """The kernel as the messages name it: with the declared one, if any."""
        declared = self.mat.getNullSpace()
        has = declared is not None and bool(declared)
        return "a null space the declared one does not cover" if has else "a null space"

    def _singular(self, info: SolveInfo, residual) -> SingularOperatorError:
        return SingularOperatorError(
            f"{self.kind} solve ({self._types()}): the operator is singular, with "
            f"{self._kernel_named()}: after {info.iterations} iterations ({info.reason}) x "
            f"is a null vector of A, {residual.describe()}; {safeguards.DECLARE_NULLSPACE}",
        )

    def near_null_hint(self, residual: safeguards.Residual | None) -> str:
        """A sentence saying how to declare a null space if the iterate of `residual`
        looks like a null vector of A (`safeguards.looks_singular`), else ``""``."""
        if residual is None or not safeguards.looks_singular(residual):
            return ""
        ratio = residual.product / residual.scale
        return (
            f"x is nearly a null vector of A (‖A x‖/(‖A‖ ‖x‖) = {ratio:.2g}): if the "
            f"operator is singular, with {self._kernel_named()}, " + safeguards.DECLARE_NULLSPACE
        )

    def _verify(self, reason: int, exponent: int) -> int:
        """A solve that ran past rounding level: accept, re-run (`safeguards.rescue`) or raise.

        Returns the iterations of a discarded run.
        """
        reported = self._info(exponent)  # PETSc's own outcome, before any re-run
        late = reported.reason in safeguards.LATE_BREAKDOWNS
        found = self._diagnose() if late else None  # of PETSc's iterate, before a re-run
        rescued = safeguards.rescue(
            self.ksp, self.mat, self.b_vec, self.x_vec, transpose=self.transpose
        )
        if rescued is None:
            self.infos.append(reported)
            if late:
                raise self._diverged(reported, found)
            raise SolverError(
                f"{self.kind} solve ({self._types()}) ran far beyond convergence and its "
                f"iterate lost accuracy after {reported.iterations} iterations; lower "
                "max_it or set rtol > 0",
                reason="LOST_ACCURACY",
            )
        self.infos.append(self._info(exponent))
        return rescued

    def _diagnose(self) -> safeguards.Residual | None:
        """The `Residual` of the iterate of a failed solve (None if it is not finite):
        one ``MatMult``, off the hot path."""
        if not np.isfinite(self.x_vec.norm()):
            return None
        return safeguards.true_residual(
            self.mat, self.b_vec, self.x_vec, transpose=self.transpose, norm=self.norm()
        )

    def _diverged(self, info: SolveInfo, found: safeguards.Residual | None) -> SolverError:
        """The error of a failed solve: `SingularOperatorError` if its iterate `found`
        says so (`safeguards.judge`), else PETSc's reason."""
        if found is not None and safeguards.judge(found, "failed") == "singular":
            return self._singular(info, found)
        residual = "not computed" if info.residual_norm is None else f"{info.residual_norm:.3e}"
        hint = "check the operator and the PC"
        if self.ksp.getType() == "richardson":
            hint += ", or lower the Richardson scale (-ksp_richardson_scale)"
        if singular := self.near_null_hint(found):
            hint = f"{singular}; otherwise {hint}"
        return SolverError(
            f"{self.kind} solve diverged: {info.reason} after {info.iterations} iterations "
            f"({self._types()}, residual {residual}); {hint}",
            reason=info.reason,
        )

    def _types(self) -> str:
        return f"{self.ksp.getType()}/{self.ksp.getPC().getType()}"

    def _petsc_failure(self, err: PETSc.Error) -> SolverError:
        if self.kind is Side.ADJOINT and getattr(err, "ierr", None) == 56:  # PETSC_ERR_SUP
            return SolverError(
                f"adjoint {self._types()}: the PC has no transpose (PCApplyTranspose) in "
                "PETSc. Choose another adjoint pc_type, or solve with an explicit "
                "transpose: AdjointSettings(options={'ksp_use_explicittranspose': True}).",
                reason="NO_TRANSPOSE",
            )
        hint = (
            " A PC without a transpose cannot serve the adjoint: choose another adjoint pc_type."
            if self.kind is Side.ADJOINT
            else ""
        )
        if getattr(err, "ierr", None) == 92 and self.mat.getComm().getSize() > 1:
            hint = (  # PETSC_ERR_MISSING_FACTOR: e.g. icc/ilu on a distributed matrix
                " PETSc has no parallel factorization for this PC on a distributed matrix: "
                "use pc_type bjacobi with sub_pc_type icc (or ilu), or gamg."
            )
        return SolverError(
            f"{self.kind} KSPSolve failed inside PETSc ({self._types()}): {err}.{hint}",
            reason="PETSC_ERROR",
        )
