"""PETSc KSP solves with a capped iteration count, forward and transpose.

`KSPSolver` owns two PETSc KSP objects on the same matrix: one for the forward
solve ``A x = b`` and one for the adjoint (transpose) solve ``Aᵀ λ = g``.  Both
are configured from PETSc options under their own prefix, so everything a PETSc
user knows (``-fwd_ksp_type gmres -fwd_pc_type gamg -fwd_ksp_monitor``) works.
The solver knows nothing of torch; `prdp_petsc.autograd.bridge` connects it to autograd.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from . import safeguards
from .nullspace import check_nullspace, normalize_nullspace, petsc_nullspace
from .options import option_value, parse_options
from .sparsity import nearly_equal, transpose_permutation

__all__ = ["AdjointSettings", "KSPSolver", "SolveInfo", "SolverError", "SolverStats"]

logger = logging.getLogger(__name__)

_REASONS = {
    getattr(PETSc.KSP.ConvergedReason, name): name
    for name in dir(PETSc.KSP.ConvergedReason)
    if name.isupper() and isinstance(getattr(PETSc.KSP.ConvergedReason, name), int)
}
_MAX_IT = PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT
_TOLERANCE_KEYS = ("ksp_rtol", "ksp_atol", "ksp_max_it")
# PCs that are symmetric operators whenever A is: for them Aᵀλ = g is a forward solve
_SYMMETRIC_PCS = frozenset({"none", "jacobi", "pbjacobi", "icc", "cholesky"})


def reason_name(reason: int) -> str:
    """Name of a PETSc ``KSPConvergedReason`` value, e.g. ``"DIVERGED_MAX_IT"``."""
    return _REASONS.get(int(reason), f"UNKNOWN({int(reason)})")


class SolverError(RuntimeError):
    """A KSP solve really diverged (NaN, breakdown, indefinite PC, DTOL, no transpose).

    Hitting ``max_it`` is *not* an error; it is the normal outcome of a capped solve.

    Attributes
    ----------
    reason : str
        PETSc reason name (``"DIVERGED_DTOL"``, ``"DIVERGED_NANORINF"``, ...).
    """

    def __init__(self, message: str, reason: str = "UNKNOWN"):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class SolveInfo:
    """Outcome of one KSP solve: iteration count, reason name and residual norm."""

    iterations: int
    reason: str
    residual_norm: float

    @property
    def converged(self) -> bool:
        """True when PETSc reports convergence (not when the cap was hit)."""
        return self.reason.startswith("CONVERGED")


@dataclass
class SolverStats:
    """Counters of forward and adjoint work since the last `KSPSolver.reset_stats`."""

    forward_solves: int = 0
    forward_iterations: int = 0
    forward_time: float = 0.0
    adjoint_solves: int = 0
    adjoint_iterations: int = 0
    adjoint_time: float = 0.0
    operator_updates: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


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
        symmetric.  For a symmetric A (checked on its values) the transpose solve
        then *is* a forward solve, and `KSPSolver` runs ``KSPSolve`` instead of
        ``KSPSolveTranspose`` (same iterates, no slower transposed products).
        ``None`` (default) trusts only PCs that are symmetric by construction
        (none, jacobi, pbjacobi, icc, cholesky); ``True`` asserts it (e.g. GAMG
        with its default Chebyshev/Jacobi smoothers); ``False`` always uses
        ``KSPSolveTranspose``.
    """

    options: dict | str | None = None
    max_it: int | None = None
    rtol: float | None = None
    atol: float | None = None
    prefix: str | None = None
    symmetric_pc: bool | None = None


def _check_tolerances(max_it, rtol, atol, what: str) -> None:
    if isinstance(max_it, bool) or not isinstance(max_it, int | np.integer) or max_it < 1:
        raise ValueError(f"{what}max_it must be an integer >= 1, got {max_it!r}")
    for name, val in (("rtol", rtol), ("atol", atol)):
        if not np.isfinite(val) or val < 0:
            raise ValueError(f"{what}{name} must be finite and >= 0, got {val!r}")


class KSPSolver:
    """A PETSc KSP with a capped iteration count and a matching transpose solve.

    Parameters
    ----------
    options : dict or str, optional
        PETSc options without prefix, e.g. ``{"ksp_type": "cg", "pc_type": "gamg"}``
        or ``"-ksp_type cg -pc_type gamg"``.  They are written under `prefix`, then
        ``KSPSetFromOptions`` runs, so options given on the command line with that
        prefix take precedence, as in any PETSc program.
    prefix : str
        Options prefix of the forward KSP (e.g. ``"fwd_"``).
    max_it : int
        Iteration cap K.  With ``rtol = atol = 0`` exactly K iterations run.
        Can be changed between solves without rebuilding the preconditioner.
    rtol, atol : float
        Stopping tolerances; 0 disables them ("fixed" mode).
    adjoint : AdjointSettings or dict, optional
        Settings of the transpose solve; by default the forward ones.
    divtol : float, optional
        PETSc divergence tolerance (default: PETSc's own, ``PETSC_DEFAULT``).
    nullspace : "constant" or array_like (k, n), optional
        Null space of a singular operator (pure Neumann, periodic), attached to the
        matrix with ``MatSetNullSpace``.  Krylov iterates stay orthogonal to it and
        the right-hand side is projected onto the range of A, so the solve returns
        the minimum-norm least-squares solution ``A⁺ b``, also when b is not
        compatible (documented projection, no error).  It must not depend on θ.
    transpose_nullspace : "constant" or array_like (k, n), optional
        Null space of Aᵀ (``MatSetTransposeNullSpace``); defaults to `nullspace`,
        right for symmetric operators.  Both are checked against every new operator
        (``‖A v‖ ≤ 1e-8 ‖A‖ ‖v‖``), since a wrong one would silently solve another
        problem.

    Notes
    -----
    Options that apply: any ``-{prefix}ksp_*`` / ``-{prefix}pc_*`` option, and the
    same under the adjoint prefix (``-{prefix}adj_ksp_type``).  Tolerances are set
    from the keyword arguments, not from options, because the PRDP controller owns
    ``max_it``.  The KSP is created on the communicator of the first operator;
    scipy matrices are serial objects and become ``MATSEQAIJ`` on ``COMM_SELF``.
    Hitting the cap (``DIVERGED_MAX_IT``) is a normal outcome; every other negative
    reason raises `SolverError`, except a breakdown (or BiCGStab's late divergence)
    after the residual reached rounding level when run far beyond convergence: the
    iterate at rounding level is returned and PETSc's reason is kept in `last`
    (see `prdp_petsc.core.safeguards`).  A right-hand side with entries beyond
    ``2^±100`` is scaled by a power of two before the solve (exact; ``atol`` is
    scaled along) so that 1e±150 neither under- nor overflows inside the KSP.
    The adjoint refuses KSP types whose transpose solve is wrong (``cgls``) and
    reports a PC without ``PCApplyTranspose`` (e.g. ``sor``) as a `SolverError`;
    ``AdjointSettings(options={"ksp_use_explicittranspose": True})`` solves such
    an adjoint with an explicit Aᵀ and its own PC instead.
    """

    def __init__(
        self,
        options: dict | str | None = None,
        *,
        prefix: str = "",
        max_it: int,
        rtol: float = 0.0,
        atol: float = 0.0,
        adjoint: AdjointSettings | dict | None = None,
        divtol: float | None = None,
        nullspace=None,
        transpose_nullspace=None,
    ):
        _check_tolerances(max_it, rtol, atol, "")
        self.options = parse_options(options)
        bad = [k for k in self.options if k in _TOLERANCE_KEYS]
        if bad:
            raise ValueError(
                f"pass {bad} as keyword arguments (max_it=, rtol=, atol=), not options"
            )
        if adjoint is None:
            adjoint = AdjointSettings()
        elif isinstance(adjoint, dict):
            adjoint = AdjointSettings(**adjoint)
        else:
            adjoint = dataclasses.replace(adjoint)  # ours to change (adjoint_max_it)
        self.adjoint = adjoint
        if adjoint.max_it is not None or adjoint.rtol is not None or adjoint.atol is not None:
            _check_tolerances(
                max_it if adjoint.max_it is None else adjoint.max_it,
                0.0 if adjoint.rtol is None else adjoint.rtol,
                0.0 if adjoint.atol is None else adjoint.atol,
                "adjoint ",
            )
        own = parse_options(adjoint.options)
        bad = [k for k in own if k in _TOLERANCE_KEYS]
        if bad:
            raise ValueError(
                f"pass {bad} as AdjointSettings(max_it=, rtol=, atol=), not adjoint options"
            )
        self.adjoint_options = {**self.options, **own}
        self.prefix = prefix
        self.adjoint_prefix = adjoint.prefix if adjoint.prefix is not None else prefix + "adj_"
        self._max_it = int(max_it)
        self.rtol = float(rtol)
        self.atol = float(atol)
        self.divtol = divtol
        self.nullspace = normalize_nullspace(nullspace)
        self.transpose_nullspace = (
            self.nullspace
            if transpose_nullspace is None
            else normalize_nullspace(transpose_nullspace, "transpose_nullspace")
        )
        self.stats = SolverStats()
        self.last: SolveInfo | None = None
        self._ksp: PETSc.KSP | None = None
        self._adj: PETSc.KSP | None = None
        self._mat: PETSc.Mat | None = None
        self._pattern: tuple[np.ndarray, np.ndarray, tuple] | None = None
        self._source: tuple | None = None  # the caller's (indptr, indices), for an `is` test
        self._tperm: np.ndarray | None = None  # CSR position of each entry's transpose
        self._values: np.ndarray | None = None
        self.symmetric = False

    # -- tolerances -------------------------------------------------------------
    @property
    def max_it(self) -> int:
        """Forward iteration cap K (the adjoint follows unless set on its own)."""
        return self._max_it

    @max_it.setter
    def max_it(self, value: int) -> None:
        _check_tolerances(value, self.rtol, self.atol, "")
        self._max_it = int(value)
        self._apply_tolerances()

    @property
    def adjoint_max_it(self) -> int:
        """Adjoint iteration cap: `AdjointSettings.max_it` or the forward `max_it`."""
        return self.adjoint.max_it if self.adjoint.max_it is not None else self._max_it

    @adjoint_max_it.setter
    def adjoint_max_it(self, value: int | None) -> None:
        if value is not None:
            _check_tolerances(value, 0.0, 0.0, "adjoint ")
        self.adjoint.max_it = None if value is None else int(value)
        self._apply_tolerances()

    def set_tolerances(self, *, rtol: float | None = None, atol: float | None = None) -> None:
        """Change the forward stopping tolerances (e.g. for an rtol schedule)."""
        rtol = self.rtol if rtol is None else float(rtol)
        atol = self.atol if atol is None else float(atol)
        _check_tolerances(self._max_it, rtol, atol, "")
        self.rtol, self.atol = rtol, atol
        self._apply_tolerances()

    def _apply_tolerances(self) -> None:
        if self._ksp is None:
            return
        dt = self.divtol if self.divtol is not None else PETSc.DEFAULT
        self._ksp.setTolerances(rtol=self.rtol, atol=self.atol, divtol=dt, max_it=self._max_it)
        adj = self.adjoint
        self._adj.setTolerances(
            rtol=self.rtol if adj.rtol is None else adj.rtol,
            atol=self.atol if adj.atol is None else adj.atol,
            divtol=dt,
            max_it=self.adjoint_max_it,
        )

    # -- PETSc objects ------------------------------------------------------------
    @property
    def ksp(self) -> PETSc.KSP:
        """The forward PETSc KSP (exists once an operator has been set)."""
        if self._ksp is None:
            raise RuntimeError("no operator yet: call set_operator(A) or solve() first")
        return self._ksp

    @property
    def adjoint_ksp(self) -> PETSc.KSP:
        """The transpose-solve PETSc KSP (exists once an operator has been set)."""
        self.ksp  # noqa: B018  (raises the same error)
        return self._adj

    def _shares_pc(self) -> bool:
        own = parse_options(self.adjoint.options)
        if any(k.startswith("pc_") for k in own):
            return False
        cmdline = PETSc.Options().getAll()
        # an explicit transpose re-points the adjoint's operators (and a shared PC) to Aᵀ
        off = ("0", "false", "no")
        explicit = "ksp_use_explicittranspose"
        if explicit in self.adjoint_options:
            if option_value(self.adjoint_options[explicit]) not in off:
                return False
        if cmdline.get(self.adjoint_prefix + explicit, "false") not in off:
            return False
        return not any(k.startswith(self.adjoint_prefix + "pc_") for k in cmdline)

    def setup(self, comm=None) -> None:
        """Create and configure the KSPs now (otherwise done by the first operator).

        `comm` defaults to ``PETSc.COMM_SELF``; nothing happens if they exist.
        """
        if self._ksp is None:
            self._create(comm if comm is not None else PETSc.COMM_SELF)

    @contextmanager
    def _options_in_database(self):
        """Write this solver's options into PETSc's database for the duration.

        Needed at ``KSPSetFromOptions`` and again at every solve, because PCs read
        some options only at set-up (GAMG level smoothers, bjacobi sub-solvers).
        Names already in the database (the command line) are left alone: they win.
        The adjoint inherits the forward options *as the forward KSP sees them*, so
        ``-fwd_ksp_type cg`` on the command line changes both solves unless
        ``-fwd_adj_ksp_type`` says otherwise.  Removing ours afterwards keeps
        solvers with the same prefix independent.
        """
        opts = PETSc.Options()
        forward = dict(self.options)
        for name, value in opts.getAll().items():
            if name.startswith(self.prefix) and not name.startswith(self.adjoint_prefix):
                forward[name[len(self.prefix) :]] = value
        adjoint = {**forward, **parse_options(self.adjoint.options)}
        pushed = []
        try:
            for prefix, options in ((self.prefix, self.options), (self.adjoint_prefix, adjoint)):
                for key, value in options.items():
                    name = prefix + key
                    if name in pushed or opts.hasName(name):
                        continue
                    opts.setValue(name, option_value(value))
                    pushed.append(name)
            yield
        finally:
            for name in pushed:
                opts.delValue(name)

    def _create(self, comm) -> None:
        self._ksp = PETSc.KSP().create(comm=comm)
        self._ksp.setOptionsPrefix(self.prefix)
        self._adj = PETSc.KSP().create(comm=comm)
        self._adj.setOptionsPrefix(self.adjoint_prefix)
        if self._shares_pc():
            self._adj.setPC(self._ksp.getPC())
        with self._options_in_database():
            self._ksp.setFromOptions()
            self._adj.setFromOptions()
        for ksp in (self._ksp, self._adj):  # read by safeguards.rescue
            ksp.setConvergenceHistory(reset=True)
        self._apply_tolerances()
        logger.debug(
            "KSP %r: %s/%s, adjoint %r: %s/%s",
            self.prefix,
            self._ksp.getType(),
            self._ksp.getPC().getType(),
            self.adjoint_prefix,
            self._adj.getType(),
            self._adj.getPC().getType(),
        )

    def set_operator(self, A, *, symmetric: bool | None = None) -> None:
        """Set the matrix; the PC is set up again only if its values changed.

        Parameters
        ----------
        A : scipy.sparse matrix, PETSc.Mat or tuple ``(indptr, indices, data, shape)``
            A PETSc Mat is used as given (any communicator, e.g. distributed).
        symmetric : bool, optional
            Whether A = Aᵀ, if the caller knows (e.g. `ParametricMatrix.is_symmetric`);
            by default it is checked exactly on the values whenever they change.
        """
        if isinstance(A, PETSc.Mat):
            if A is not self._mat:
                self._pattern = self._source = self._values = None
                known, flag = A.isSymmetricKnown()
                self.symmetric = bool(known and flag)
                self._set_mat(A)
            return
        if isinstance(A, tuple):
            indptr, indices, data, shape = A
        else:
            if not sp.issparse(A):
                raise TypeError(f"A must be a scipy sparse matrix or PETSc.Mat, got {type(A)}")
            A = A.tocsr()
            if not A.has_sorted_indices:
                A = A.sorted_indices()
            indptr, indices, data, shape = A.indptr, A.indices, A.data, A.shape
        if shape[0] != shape[1]:
            raise ValueError(f"A must be square, got shape {shape}")
        data = np.asarray(data, dtype=np.float64)
        if not np.all(np.isfinite(data)):
            raise ValueError("A has NaN or Inf entries")
        same_pattern = self._pattern is not None and (
            (self._source[0] is indptr and self._source[1] is indices)
            or (
                self._pattern[2] == tuple(shape)
                and np.array_equal(self._pattern[0], indptr)
                and np.array_equal(self._pattern[1], indices)
            )
        )
        if same_pattern:
            # compare with a private copy: the caller may have changed `data` in place
            if np.array_equal(data, self._values):
                return
            self._mat.setValuesCSR(self._pattern[0], self._pattern[1], data)
            self._mat.assemble()
            self._values = data.copy()
            self._source = (indptr, indices)
            self._mark_symmetry(symmetric=symmetric)
            self.stats.operator_updates += 1
            self._check_nullspaces()
            return
        ip = np.asarray(indptr, dtype=PETSc.IntType)
        ix = np.asarray(indices, dtype=PETSc.IntType)
        mat = PETSc.Mat().createAIJ(size=tuple(shape), csr=(ip, ix, data), comm=PETSc.COMM_SELF)
        mat.assemble()
        self._pattern = (ip, ix, tuple(shape))
        self._source = (indptr, indices)
        self._values = data.copy()
        self._tperm = transpose_permutation(ip, ix, tuple(shape))
        self._mark_symmetry(mat, symmetric=symmetric)
        self._set_mat(mat)

    def _mark_symmetry(self, mat: PETSc.Mat | None = None, symmetric: bool | None = None) -> None:
        """Check A = Aᵀ exactly on the values (unless the caller knows) and tell PETSc."""
        if symmetric is None:
            symmetric = self._tperm is not None and nearly_equal(
                self._values, self._values[self._tperm]
            )
        self.symmetric = bool(symmetric)
        (mat or self._mat).setOption(PETSc.Mat.Option.SYMMETRIC, self.symmetric)

    def _adjoint_is_forward(self) -> bool:
        """True when ``Aᵀλ = g`` can run as a forward solve of the adjoint KSP."""
        if self._pattern is None and self._mat is not None:  # a user's Mat: ask it now
            known, flag = self._mat.isSymmetricKnown()
            self.symmetric = bool(known and flag)
        if not self.symmetric or self.adjoint.symmetric_pc is False:
            return False
        return self.adjoint.symmetric_pc or self._adj.getPC().getType() in _SYMMETRIC_PCS

    def _set_mat(self, mat: PETSc.Mat) -> None:
        if self._ksp is None:
            self._create(mat.getComm())
        self._mat = mat
        if self.nullspace is not None:
            mat.setNullSpace(petsc_nullspace(self.nullspace, mat))
            mat.setTransposeNullSpace(petsc_nullspace(self.transpose_nullspace, mat))
            self._check_nullspaces()
        self._ksp.setOperators(mat)
        self._adj.setOperators(mat)
        self.stats.operator_updates += 1

    def _check_nullspaces(self) -> None:
        if self.nullspace is not None:
            check_nullspace(self._mat, self._mat.getNullSpace(), transpose=False, name="nullspace")
            check_nullspace(
                self._mat,
                self._mat.getTransposeNullSpace(),
                transpose=True,
                name="transpose_nullspace",
            )

    @property
    def mat(self) -> PETSc.Mat:
        """The current PETSc operator."""
        if self._mat is None:
            raise RuntimeError("no operator yet: call set_operator(A) first")
        return self._mat

    # -- solves ---------------------------------------------------------------------
    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` from a zero initial guess; `b` is ``(n,)`` or ``(B, n)``."""
        return self._run(self.ksp, b, transpose=False)

    def solve_transpose(self, g: np.ndarray) -> np.ndarray:
        """Solve ``Aᵀ λ = g`` with the adjoint settings; `g` is ``(n,)`` or ``(B, n)``."""
        if self.adjoint_ksp.getType() in safeguards.NO_TRANSPOSE_KSP:
            raise SolverError(
                f"adjoint ksp_type {self._adj.getType()!r} has no correct transpose solve in "
                "PETSc (it would return a wrong gradient); choose another adjoint ksp_type, "
                "e.g. AdjointSettings(options={'ksp_type': 'gmres'})",
                reason="NO_TRANSPOSE",
            )
        return self._run(self.adjoint_ksp, g, transpose=True)

    def _run(self, ksp: PETSc.KSP, rhs: np.ndarray, *, transpose: bool) -> np.ndarray:
        with self._options_in_database():
            return self._run_batch(ksp, rhs, transpose=transpose)

    def _run_batch(self, ksp: PETSc.KSP, rhs: np.ndarray, *, transpose: bool) -> np.ndarray:
        rhs = np.asarray(rhs, dtype=np.float64)
        batch = rhs.reshape(-1, rhs.shape[-1])
        x_vec, b_vec = self._mat.createVecs()
        if batch.shape[1] != b_vec.getLocalSize():
            raise ValueError(
                f"right-hand side has {batch.shape[1]} entries, operator has "
                f"{b_vec.getLocalSize()} local rows"
            )
        out = np.empty_like(batch)
        kind = "adjoint" if transpose else "forward"
        t0 = time.perf_counter()
        iterations = 0
        as_transpose = transpose and not self._adjoint_is_forward()
        run = ksp.solveTranspose if as_transpose else ksp.solve
        exponents = safeguards.rhs_exponents(batch)  # 0 unless |b| is extreme
        for i, row in enumerate(batch):
            exponent = int(exponents[i])
            b_vec.array[:] = np.ldexp(row, -exponent) if exponent else row
            x_vec.set(0.0)
            tolerances = ksp.getTolerances() if exponent else None
            if exponent and tolerances[1] > 0:  # atol is absolute: scale it along
                ksp.setTolerances(atol=float(np.ldexp(tolerances[1], -exponent)))
            try:
                run(b_vec, x_vec)
            except PETSc.Error as err:
                if transpose and getattr(err, "ierr", None) == 56:  # PETSC_ERR_SUP
                    raise SolverError(
                        f"adjoint {ksp.getType()}/{ksp.getPC().getType()}: the PC has no "
                        "transpose (PCApplyTranspose) in PETSc. Choose another adjoint "
                        "pc_type, or solve with an explicit transpose: AdjointSettings("
                        "options={'ksp_use_explicittranspose': True}).",
                        reason="NO_TRANSPOSE",
                    ) from err
                hint = (
                    " A PC without a transpose cannot serve the adjoint: choose another "
                    "adjoint pc_type."
                    if transpose
                    else ""
                )
                raise SolverError(
                    f"{kind} KSPSolve failed inside PETSc ({ksp.getType()}/"
                    f"{ksp.getPC().getType()}): {err}.{hint}",
                    reason="PETSC_ERROR",
                ) from err
            finally:
                if exponent and tolerances[1] > 0:
                    ksp.setTolerances(atol=tolerances[1])
            reason = ksp.getConvergedReason()
            reported = SolveInfo(  # PETSc's own outcome, before any rescue re-run
                ksp.getIterationNumber(),
                reason_name(reason),
                float(np.ldexp(ksp.getResidualNorm(), exponent)),
            )
            rescued = None
            late = reported.reason in safeguards.LATE_BREAKDOWNS
            if late or safeguards.went_far(ksp):  # ran past rounding level: verify
                rescued = safeguards.rescue(ksp, self._mat, b_vec, x_vec, transpose=as_transpose)
                if rescued is not None:
                    iterations += rescued
                elif not late:
                    self.last = reported
                    raise SolverError(
                        f"{kind} solve ({ksp.getType()}/{ksp.getPC().getType()}) ran far "
                        f"beyond convergence and its iterate lost accuracy after "
                        f"{reported.iterations} iterations; lower max_it or set rtol > 0",
                        reason="LOST_ACCURACY",
                    )
            info = (
                reported
                if rescued is None
                else SolveInfo(
                    ksp.getIterationNumber(),
                    reason_name(ksp.getConvergedReason()),
                    float(np.ldexp(ksp.getResidualNorm(), exponent)),
                )
            )
            self.last = info
            iterations += info.iterations
            if reason < 0 and reason != _MAX_IT and rescued is None:
                self.last = reported
                raise SolverError(
                    f"{kind} solve diverged: {reported.reason} after {reported.iterations} "
                    f"iterations ({ksp.getType()}/{ksp.getPC().getType()}, residual "
                    f"{reported.residual_norm:.3e}); check the operator and the PC, or lower "
                    "the Richardson scale",
                    reason=reported.reason,
                )
            out[i] = np.ldexp(x_vec.array_r, exponent) if exponent else x_vec.array_r
        if not np.all(np.isfinite(out)):
            raise SolverError(f"{kind} solve returned NaN/Inf", reason="DIVERGED_NANORINF")
        elapsed = time.perf_counter() - t0
        if transpose:
            self.stats.adjoint_solves += len(batch)
            self.stats.adjoint_iterations += iterations
            self.stats.adjoint_time += elapsed
        else:
            self.stats.forward_solves += len(batch)
            self.stats.forward_iterations += iterations
            self.stats.forward_time += elapsed
        return out.reshape(rhs.shape)

    def clone(self, **changes) -> KSPSolver:
        """A new, unconfigured solver with the same settings, some of them changed.

        Options, prefix, tolerances, adjoint settings, ``divtol`` and null spaces are
        copied; keyword arguments (any of `KSPSolver`'s) replace them.
        """
        kwargs = {
            "options": dict(self.options),
            "prefix": self.prefix,
            "max_it": self._max_it,
            "rtol": self.rtol,
            "atol": self.atol,
            "adjoint": self.adjoint,
            "divtol": self.divtol,
            "nullspace": self.nullspace,
            "transpose_nullspace": self.transpose_nullspace,
        }
        kwargs.update(changes)
        return KSPSolver(**kwargs)

    def describe(self) -> dict:
        """JSON-ready record of the solver: prefixes, tolerances and, once the KSPs
        exist, the KSP/PC types PETSc really uses (command-line options included)."""
        record = {
            "prefix": self.prefix,
            "adjoint_prefix": self.adjoint_prefix,
            "options": {k: option_value(v) for k, v in self.options.items()},
            "max_it": self._max_it,
            "rtol": self.rtol,
            "atol": self.atol,
            "adjoint_max_it": self.adjoint_max_it,
        }
        if self._ksp is not None:
            for key, ksp in (("forward", self._ksp), ("adjoint", self._adj)):
                record[key] = {"ksp_type": ksp.getType(), "pc_type": ksp.getPC().getType()}
        return record

    def reset_stats(self) -> None:
        """Zero the counters in `stats`."""
        self.stats = SolverStats()

    def __repr__(self) -> str:
        return (
            f"KSPSolver(options={self.options!r}, prefix={self.prefix!r}, max_it={self._max_it}, "
            f"rtol={self.rtol}, atol={self.atol}, adjoint_max_it={self.adjoint_max_it})"
        )
