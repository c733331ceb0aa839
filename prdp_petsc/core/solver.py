"""PETSc KSP solves with a capped iteration count, forward and transpose.

`KSPSolver` owns two PETSc KSP objects on the same matrix: one for the forward
solve ``A x = b`` and one for the adjoint (transpose) solve ``Aᵀ λ = g``.  Both
are configured from PETSc options under their own prefix, so everything a PETSc
user knows (``-fwd_ksp_type gmres -fwd_pc_type gamg -fwd_ksp_monitor``) works.
The solver knows nothing of torch; `prdp_petsc.autograd.bridge` connects it to
autograd.

Inside, each of the two solves is one `_Side` (`Side.FORWARD`, `Side.ADJOINT`: its KSP,
prefix and what is kept of it between calls), and the operator is one
`prdp_petsc.core.operator.OperatorLayout`, whose class the operator's kind chooses.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from ..errors import InputError, NonFiniteError, NotConvergedWarning, caller_stacklevel
from . import safeguards
from .configuration import Configuration, UnusedOptionWarning, rejected_options_message
from .device import DeviceTypes, WrappedRows
from .fields import attach_fields
from .lag import PCLag
from .nullspace import (
    attach_near_nullspace,
    attach_nullspaces,
    check_nullspaces,
)
from .operator import Change, DLPackCSR, OperatorLayout, OwnedCSR, ReplicatedCSR, layout_for
from .options import PushedOptions
from .parallel import RowLayout, as_petsc_comm
from .results import CallInfo, Side, SolveInfo, SolverError, SolverStats
from .settings import AdjointSettings
from .solution import LinearSolution
from .step import SolveStep
from .structure import Structure, check_structure

if TYPE_CHECKING:  # mpi4py is optional (the `mpi` extra)
    from mpi4py import MPI

__all__ = ["KSPSolver", "UnusedOptionWarning"]

logger = logging.getLogger(__name__)

_NOTHING_PUSHED = PushedOptions([])  # a solve without a set-up reads no options

# PCs that are symmetric operators whenever A is: for them Aᵀλ = g is a forward solve
_SYMMETRIC_PCS = frozenset({"none", "jacobi", "pbjacobi", "icc", "cholesky"})
#: what `KSPSolver(not_converged=...)` does with a tolerance solve that hit max_it
NOT_CONVERGED = ("warn", "raise", "ignore")


class _Side:
    """One of a `KSPSolver`'s two solves (`Side.FORWARD` or `Side.ADJOINT`): its KSP and
    what the solver keeps of it between calls.

    A rebuild (`KSPSolver.rebuild_on`) gives it a new KSP and forgets what belonged to
    the old one.
    """

    __slots__ = (
        "has_fields",
        "kind",
        "ksp",
        "prefix",
        "setup_version",
        "step",
        "unchecked",
    )

    def __init__(self, kind: Side, prefix: str) -> None:
        self.kind = kind
        #: its options prefix (the adjoint's is ``<prefix>adj_`` unless set)
        self.prefix = prefix
        self.use(None)

    def use(self, ksp: PETSc.KSP | None) -> None:
        """Take `ksp` (None: none) with nothing done on it yet."""
        self.ksp: PETSc.KSP | None = ksp
        #: the operator version its PC was set up for at its last call (-1: none yet)
        self.setup_version = -1
        #: the check for options PETSc never read is pending (it follows the first call)
        self.unchecked = True
        #: ``PCFieldSplitSetIS`` was called on its PC
        self.has_fields = False
        #: ``(key, SolveStep)`` kept between calls while the key holds (`KSPSolver._step`)
        self.step: tuple | None = None

    @property
    def transpose(self) -> bool:
        """Whether it solves with Aᵀ."""
        return self.kind is Side.ADJOINT

    def types(self) -> str:
        """``"ksp_type/pc_type"`` as PETSc runs them."""
        return f"{self.ksp.getType()}/{self.ksp.getPC().getType()}"

    def destroy(self) -> None:
        """Free the KSP."""
        if self.ksp is not None:
            self.ksp.destroy()
        self.use(None)


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
        Stopping tolerances; 0 disables them ("fixed" mode).  Properties, like
        `max_it`: a new value applies to the next solve.
    not_converged : {"warn", "raise", "ignore"}
        What a solve *with a tolerance* (``rtol > 0`` or ``atol > 0``, forward or
        adjoint) that hits its ``max_it`` without meeting it does: ``"warn"``
        (default) gives a `prdp_petsc.errors.NotConvergedWarning` naming the true
        residual ``‖b − A x‖/‖b‖`` (one ``MatMult``) and what to do, once per call
        (the worst row of a batch); ``"raise"`` makes that a `SolverError` (reason
        ``DIVERGED_MAX_IT``); ``"ignore"`` returns as PETSc does, with only the
        result's ``converged`` False.  A capped solve in fixed mode (``rtol = atol =
        0``: exactly K iterations, how PRDP trains) is the normal outcome and never
        reported.  Set here only, for the solver's life (`clone` copies it).
    adjoint : AdjointSettings or dict, optional
        Settings of the transpose solve; by default the forward ones.
    divtol : float, optional
        PETSc divergence tolerance (default: PETSc's own, ``PETSC_DEFAULT``).
    structure : Structure, optional
        What is known about every operator this solver gets — symmetry, null
        spaces, the near-null space, the block size, the fields of a block operator
        — declared once (`prdp_petsc.core.structure.Structure`); set on every Mat
        and PC the solver builds.  Default: nothing declared (``Structure()``).
    check_structure : bool
        Refuse a symmetric-only KSP or PC (CG, MINRES, CR, ICC, Cholesky, ...; see
        `prdp_petsc.core.structure`) on an operator known to be non-symmetric, with
        a `prdp_petsc.errors.StructureError` naming an alternative (default True).
        ``False`` is the expert's opt-out.
    pc_lag : int
        Set the preconditioner up again only every `pc_lag`-th time the operator's
        values change (PETSc's ``KSPSetReusePreconditioner`` in between), as SNES's
        ``-snes_lag_preconditioner``; a new Mat (pattern, size) always gets a new
        PC.  1 (default): a new PC at every change.  The adjoint KSP follows the
        same rule; sharing the forward PC (the default), it sees the same age.
        Every solve's `SolveInfo` records ``pc_age`` and, on a reused PC,
        ``k_equivalent`` (see `prdp_petsc.core.lag`).
    pc_lag_tol : float
        Quality guard of `pc_lag` (≥ 1, default 1.2): when a call on a reused PC
        reduces the residual per iteration so much less than the fresh PC did that
        it needs more than `pc_lag_tol` times the iterations
        (``log rate_fresh / log rate``), the PC is set up before the next solve,
        counted in ``stats.pc_quality_rebuilds`` and logged (INFO).  A call that
        fails on a reused PC (`SolverError`: a stale GAMG may be indefinite for CG)
        runs again on a fresh PC (logged as a warning; counted the same way).
    comm : PETSc.Comm or mpi4py communicator, optional
        Communicator of the KSPs and of the Mat made from a scipy operator
        (default: `prdp_petsc.core.parallel.default_comm`, i.e. ``COMM_SELF``
        unless inside ``use_comm``).  On more than one rank every solve is
        collective: each rank passes the same full operator and right-hand sides,
        keeps its own rows in an MPIAIJ matrix, and gets the full solution back
        (the *replicated* layout of `prdp_petsc.core.parallel`).

    Notes
    -----
    Options that apply: any ``-{prefix}ksp_*`` / ``-{prefix}pc_*`` option, and the
    same under the adjoint prefix (``-{prefix}adj_ksp_type``).  An option that is a
    flag (``-pc_fieldsplit_detect_saddle_point``) is given in an options dict with
    the value None or True (``{"pc_fieldsplit_detect_saddle_point": None}``); False
    writes the value ``false``.

    Structure is declared once, here, and read back as `structure` (the solver
    mirrors none of its fields): its `nullspace`, `transpose_nullspace`,
    `near_nullspace` and `block_size` are set on every Mat the solver gets (a new
    pattern, a new size, another communicator, every operator of a batch; new
    values of the same pattern keep the Mat and with it what was set), `fields` on
    the PCs; `clone` copies them, and the adjoint solve uses the same Mat and, with
    a shared PC, the same fields.  The KSPs are built
    at construction, so a bad option value raises ``ValueError`` here, and after
    the first forward (adjoint) solve an option of this solver that PETSc never
    read (a misspelt ``pc_typ``) is named in an `UnusedOptionWarning`.  Given a
    caller's distributed PETSc Mat, vectors hold this rank's rows only (the
    *owned* layout).  Tolerances are
    set from the keyword arguments, not from options, because the PRDP controller
    owns ``max_it``: ``-{prefix}ksp_max_it`` / ``ksp_rtol`` / ``ksp_atol`` /
    ``ksp_divtol`` in the options or on the command line are refused.  The KSPs
    live on ``PETSC_COMM_SELF`` until an operator on a larger communicator arrives.
    Hitting the cap (``DIVERGED_MAX_IT``) is a normal outcome in fixed mode, and
    with a tolerance is reported as ``not_converged`` says; every other
    negative reason raises `SolverError`, except a breakdown (or BiCGStab's late
    divergence) after the residual reached rounding level when run far beyond
    convergence: the iterate at rounding level (and below the initial residual) is
    returned with PETSc's reason in its result (see `prdp_petsc.core.safeguards`).
    What PETSc calls converged is checked against the true residual ``‖b − A x‖``
    (one ``MatMult``), a capped iterate only when it is suspiciously large (two vector
    norms): an iterate that blew up along the kernel of a singular operator whose
    null space was not declared raises `prdp_petsc.errors.SingularOperatorError`, a
    convergence claim the true residual contradicts a `SolverError` with reason
    ``FALSE_CONVERGENCE``.  With a null space declared, its part is removed from every
    solution (a right preconditioner may add one), so x is the minimum-norm
    solution.  A right-hand side with
    entries beyond ``2^±100`` is scaled by a power of two before the solve (exact;
    ``atol`` is scaled along).  The adjoint refuses KSP types whose transpose
    solve is wrong (``cgls``) and reports a PC without ``PCApplyTranspose`` (e.g.
    ``sor``) as a `SolverError`; ``AdjointSettings(options={"ksp_use_explicit
    transpose": True})`` solves such an adjoint with an explicit Aᵀ instead.
    Free the PETSc objects with `destroy` or a ``with`` block.

    Options that name a ``vec_type`` or ``mat_type`` (``{"vec_type": "cuda",
    "mat_type": "aijcusparse"}``, or ``-{prefix}vec_type`` on the command line) put
    the solver on the *device path* (`prdp_petsc.core.device`; `vec_type` says which
    path): every Mat it makes is of that type, `solve` and `solve_transpose` take
    DLPack arrays in that memory and write into ``out=``, and a
    `~prdp_petsc.core.operator.DLPackCSR` operator's values are set from their own
    memory.  The types are read from the forward options only (the adjoint shares
    the Mat); one process.  Host types (``standard`` / ``aij``) run the same path on
    the CPU.

    With ``pc_lag > 1`` the solver sets PETSc's reuse flag before every solve
    (``-{prefix}ksp_reuse_preconditioner`` is then overridden); with 1 it leaves
    the flag alone.  A reused PC changes the iterates of a capped solve, not the
    answer of a converged one.  The quality measure is a residual reduction rate in
    the KSP's norm type (preconditioned for left-preconditioned CG/GMRES), and it
    varies with the right-hand side and K: the guard errs towards an extra set-up,
    never towards a worse solve going unreported.  A caller's Mat edited in place
    (the same Mat passed again) is not seen as a change; PETSc sets its PC up again.

    The outcome of a call is read from what it returns, one place: `solve` and
    `solve_transpose` return a `prdp_petsc.core.solution.LinearSolution` (as
    ``prdp_petsc.solve(..., return_solution=True)`` does, with a tensor value):
    ``sol.value`` with ``sol.iterations``, ``sol.reason``, ``sol.residual_norm``,
    ``sol.converged`` and ``sol.info``, every sample's `SolveInfo` (a residual PETSc
    did not compute is None, never 0).  The solver keeps no per-call outcome, only
    the running totals in `stats` (`SolverStats`).  A NaN or Inf
    in a right-hand side raises `prdp_petsc.errors.NonFiniteError` before PETSc
    sees it; a solve that returns NaN or Inf raises `SolverError`.
    """

    def __init__(
        self,
        options: dict | str | None = None,
        *,
        prefix: str = "",
        max_it: int,
        rtol: float = 0.0,
        atol: float = 0.0,
        not_converged: str = "warn",
        adjoint: AdjointSettings | dict | None = None,
        divtol: float | None = None,
        structure: Structure | None = None,
        check_structure: bool = True,
        pc_lag: int = 1,
        pc_lag_tol: float = 1.2,
        comm: PETSc.Comm | MPI.Comm | None = None,
    ) -> None:
        if not_converged not in NOT_CONVERGED:
            raise InputError(
                f"not_converged must be one of {', '.join(map(repr, NOT_CONVERGED))}, "
                f"got {not_converged!r}"
            )
        self._not_converged = not_converged
        self.comm = as_petsc_comm(comm)
        self._lag = PCLag(pc_lag, pc_lag_tol)
        #: options, prefixes and tolerances (`prdp_petsc.core.configuration.Configuration`)
        self.config = Configuration(options, prefix, max_it, rtol, atol, adjoint, divtol)
        #: the declared structure of every operator (`prdp_petsc.core.structure.Structure`)
        self.structure = Structure() if structure is None else structure
        if not isinstance(self.structure, Structure):
            raise TypeError(f"structure must be a pp.Structure, got {type(structure).__name__}")
        self.check_structure = bool(check_structure)
        self.stats = SolverStats()
        self._types: DeviceTypes | None = None  # set by `_build` from the options
        #: the operator's layout (`prdp_petsc.core.operator`), chosen by its kind
        self._op: OperatorLayout = ReplicatedCSR(self.comm, self.structure.block_size)
        self._x: PETSc.Vec | None = None
        self._b: PETSc.Vec | None = None
        self._layout: RowLayout | None = None
        #: the forward and the adjoint solve, one object each
        self._fwd = _Side(Side.FORWARD, self.prefix)
        self._adj = _Side(Side.ADJOINT, self.adjoint_prefix)
        self._kernels: dict = {}  # layout -> PETSc null spaces, made once (`attach_nullspaces`)
        self._build(self.comm)

    # -- PETSc objects ------------------------------------------------------------
    @property
    def ksp(self) -> PETSc.KSP:
        """The forward PETSc KSP."""
        self._alive()
        return self._fwd.ksp

    @property
    def adjoint_ksp(self) -> PETSc.KSP:
        """The transpose-solve PETSc KSP."""
        self._alive()
        return self._adj.ksp

    @property
    def mat(self) -> PETSc.Mat:
        """The current PETSc operator."""
        if self._op.mat is None:
            raise RuntimeError("no operator yet: call set_operator(A) first")
        return self._op.mat

    @property
    def vec_type(self) -> str | None:
        """The PETSc Vec type of the device path, None on the default path.

        Options (with the solver's prefix, or on the command line) that name a
        ``vec_type`` or ``mat_type`` put the solver on the device path
        (`prdp_petsc.core.device`): its Mats are of that type, and `solve` and
        `solve_transpose` take DLPack arrays in that memory (``solve(b, out=x)``)
        and solve in them, no vector copied.  Without them (None) they take and
        return numpy arrays.
        """
        return None if self._types is None else self._types.vec_type

    @property
    def is_symmetric(self) -> bool | None:
        """Whether the current operator is symmetric: declared (``structure.symmetric``,
        else `set_operator`'s ``known_symmetric``), else tested; None if unknown (a
        caller's PETSc Mat without ``MAT_SYMMETRIC`` set)."""
        return self._op.symmetric

    @property
    def not_converged(self) -> str:
        """What a tolerance solve that hit max_it does: ``"warn"``, ``"raise"`` or
        ``"ignore"`` (set at construction)."""
        return self._not_converged

    @property
    def pc_lag(self) -> int:
        """Set the PC up every `pc_lag`-th operator value change (1: at every change)."""
        return self._lag.lag

    @property
    def pc_lag_tol(self) -> float:
        """Quality guard of `pc_lag`: the most ``log rate_fresh / log rate`` a reused
        PC may show before it is set up again."""
        return self._lag.tol

    @property
    def operator_version(self) -> int:
        """Increases whenever the operator (or its values) changes; compare to skip work."""
        return self._op.version

    def _sides(self) -> tuple[_Side, _Side]:
        return self._fwd, self._adj

    def _alive(self) -> None:
        if self._fwd.ksp is None:
            raise RuntimeError("this KSPSolver was destroyed")

    def _build(self, comm) -> None:
        """Create and configure both KSPs on `comm`, fully or not at all."""
        self._items = self.config.option_items()
        self._lag.reset()  # new KSPs: every PC is set up at its first solve
        ksp = adj = None
        pushed = PushedOptions(self._items, watch=True)
        try:
            ksp = PETSc.KSP().create(comm=comm)
            ksp.setOptionsPrefix(self.prefix)
            adj = PETSc.KSP().create(comm=comm)
            adj.setOptionsPrefix(self.adjoint_prefix)
            self._shared_pc = self.config.shares_pc()
            if self._shared_pc:
                adj.setPC(ksp.getPC())
            with pushed:
                ksp.setFromOptions()
                adj.setFromOptions()
                opts = PETSc.Options()  # read as PETSc reads them: the command line wins
                names = [self.prefix + k for k in ("vec_type", "mat_type")]
                types = [opts.getString(n) if opts.hasName(n) else None for n in names]
            self._types = DeviceTypes.resolve(*types)
            if self._types is not None and comm.getSize() > 1:
                raise InputError(
                    "vec_type/mat_type options (the device path) run on one process; "
                    "drop them for a solve on several ranks"
                )
        except (PETSc.Error, InputError) as err:
            for obj in (ksp, adj):
                if obj is not None:
                    obj.destroy()
            if isinstance(err, InputError):
                raise
            raise InputError(rejected_options_message(self._items, err)) from err
        self._used = set(pushed.used)
        for obj in (ksp, adj):  # read by safeguards.rescue
            obj.setConvergenceHistory(reset=True)
        self._fwd.use(ksp)
        self._adj.use(adj)
        self.config.apply(ksp, adj)
        logger.debug("KSPs %r, %r built", self.prefix, self.adjoint_prefix)

    def rebuild_on(self, comm: PETSc.Comm | None = None) -> None:
        """Rebuild the KSPs on `comm` if its size differs from theirs (else nothing to do).

        Called when an operator on another communicator arrives; `comm` (the
        attribute) stays the one Mats made from scipy operators live on.  (Not
        PETSc's ``KSPSetUp``, which every solve runs as needed.)
        """
        self._alive()
        if comm is not None and comm.getSize() != self._fwd.ksp.getComm().getSize():
            self._destroy_ksps()
            self._build(comm)
            if self._op.mat is not None:  # a caller's distributed Mat: re-attach it
                for side in self._sides():
                    side.ksp.setOperators(self._op.mat)
                self._op.version += 1

    def destroy(self) -> None:
        """Free the KSPs, the Mat made here and the work vectors; the solver is unusable."""
        self._op.destroy()
        self._kernels = {}
        self._free_vecs()
        self._destroy_ksps()

    def _free_vecs(self) -> None:
        for side in self._sides():
            side.step = None  # it holds the Vecs
        for obj in (self._x, self._b, self._layout):
            if obj is not None:
                obj.destroy()
        self._x = self._b = self._layout = None

    def _destroy_ksps(self) -> None:
        for side in self._sides():
            side.destroy()

    def __enter__(self) -> KSPSolver:
        return self

    def __exit__(self, *exc) -> None:
        self.destroy()

    # -- configuration (`Configuration` holds it; PETSc gets it at once) ------------------
    options = property(lambda self: self.config.options, doc="PETSc options (no prefix).")
    adjoint_options = property(
        lambda self: self.config.adjoint_options, doc="Options of the adjoint KSP."
    )
    prefix = property(lambda self: self.config.prefix, doc="Options prefix of the forward KSP.")
    adjoint_prefix = property(
        lambda self: self.config.adjoint_prefix, doc="Options prefix of the adjoint KSP."
    )
    adjoint = property(lambda self: self.config.adjoint, doc="The `AdjointSettings`.")
    divtol = property(
        lambda self: self.config.divtol, doc="Divergence tolerance (None: PETSc's, 1e5)."
    )

    @property
    def max_it(self) -> int:
        """Forward iteration cap K (the adjoint follows unless set on its own)."""
        return self.config.max_it

    @max_it.setter
    def max_it(self, value: int) -> None:
        self.config.set_tolerances(max_it=value)
        self._apply_tolerances()

    @property
    def rtol(self) -> float:
        """Forward relative tolerance (0: off); a new value applies to the next solve."""
        return self.config.rtol

    @rtol.setter
    def rtol(self, value: float) -> None:
        self.config.set_tolerances(rtol=value)
        self._apply_tolerances()

    @property
    def atol(self) -> float:
        """Forward absolute tolerance (0: off)."""
        return self.config.atol

    @atol.setter
    def atol(self, value: float) -> None:
        self.config.set_tolerances(atol=value)
        self._apply_tolerances()

    @property
    def adjoint_max_it(self) -> int:
        """Adjoint iteration cap: `AdjointSettings.max_it` or the forward `max_it`."""
        return self.config.adjoint_max_it

    @adjoint_max_it.setter
    def adjoint_max_it(self, value: int | None) -> None:
        self.config.set_adjoint_max_it(value)
        self._apply_tolerances()

    def _apply_tolerances(self) -> None:
        if self._fwd.ksp is not None:
            self.config.apply(self._fwd.ksp, self._adj.ksp)

    def describe(self) -> dict:
        """JSON-ready record of the solver: prefixes, tolerances, options and the
        KSP/PC types PETSc really uses (command-line options included)."""
        structure = self.structure
        fields = structure.fields
        return {
            **self.config.describe(),
            "forward": {"ksp_type": self.ksp.getType(), "pc_type": self.ksp.getPC().getType()},
            "adjoint": {
                "ksp_type": self.adjoint_ksp.getType(),
                "pc_type": self.adjoint_ksp.getPC().getType(),
            },
            "ranks": self.ksp.getComm().getSize(),
            "pc_lag": self.pc_lag,
            "pc_lag_tol": self.pc_lag_tol,
            "not_converged": self.not_converged,
            "block_size": structure.block_size,
            "near_nullspace": _describe_space(structure.near_nullspace),
            "fields": None if fields is None else {k: v.size for k, v in fields.items()},
        }

    def clone(self, **changes: Any) -> KSPSolver:
        """A new solver with the same settings, some of them changed.

        Options, prefix, tolerances, ``not_converged``, adjoint settings, ``divtol``,
        null spaces, block size, near-null space, fields, the symmetry declaration,
        the structure check, the PC lag and the communicator are copied;
        keyword arguments (any of `KSPSolver`'s) replace them, e.g.
        ``clone(structure=Structure(nullspace="constant"))`` for another structure.
        """
        kwargs = {
            **self.config.arguments(),
            "not_converged": self.not_converged,
            "structure": self.structure,
            "check_structure": self.check_structure,
            "pc_lag": self.pc_lag,
            "pc_lag_tol": self.pc_lag_tol,
            "comm": self.comm,
            **changes,
        }
        return type(self)(**kwargs)

    def _unused_after(self, side: _Side, pushed: PushedOptions) -> str | None:
        """After the first call of `side`: the message naming options of this solver that
        PETSc never read (misspelt, or meant for another type or split), or None."""
        side.unchecked = False
        self._used |= pushed.used
        unused = self.config.unused(side.kind, self._used)
        if not unused:
            return None
        return (
            f"PETSc never read these options of the {side.kind.value} KSP (prefix "
            f"{side.prefix!r}, {side.types()}): "
            + ", ".join("-" + n for n in unused)
            + "; check their spelling (-help lists the options PETSc reads; a split's "
            "options are fieldsplit_<name>_..., with the names of fields=)"
        )

    def host_arrays(self) -> list[np.ndarray]:
        """The numpy arrays this solver keeps of its operator (values, pattern, transpose
        permutation), e.g. to measure its memory besides PETSc's Mat."""
        return self._op.arrays()

    def operator_csr(self) -> tuple | None:
        """``(indptr, indices, data, shape)`` of the operator as this solver keeps it:
        read-only arrays that are never edited (new values replace them), so a caller
        may hold them, e.g. an autograd backward that must set the forward's operator
        again after another solve replaced it (`set_operator` recognises them at no
        cost).  None for a caller's PETSc Mat or `OwnedCSR` operator."""
        return self._op.csr()

    def set_operator(
        self,
        A: sp.spmatrix | PETSc.Mat | OwnedCSR | DLPackCSR | tuple,
        *,
        known_symmetric: bool | None = None,
    ) -> None:
        """Set the matrix; the PC is set up again only if its values changed (and then
        only every `pc_lag`-th time).

        Parameters
        ----------
        A : scipy.sparse matrix, PETSc.Mat, OwnedCSR, DLPackCSR or tuple ``(indptr, ..., shape)``
            A PETSc Mat is used as given (any communicator, e.g. distributed); an
            `~prdp_petsc.core.operator.OwnedCSR` (this rank's rows only) becomes an
            MPIAIJ Mat of those rows.  Both give the owned layout.  A
            `~prdp_petsc.core.operator.DLPackCSR` (values in DLPack memory, the device
            path) becomes a Mat of the solver's ``mat_type`` by COO assembly.
        known_symmetric : bool, optional
            Whether A = Aᵀ, if the caller knows (e.g. `ParametricMatrix.is_symmetric`,
            which the bridge passes: it spares the test); the declared
            ``structure.symmetric`` wins.  Otherwise a CSR operator is tested entry
            against mirror whenever its values change, and a PETSc Mat is asked
            (``MatIsSymmetricKnown``).  The outcome is `is_symmetric`.
        """
        self._alive()
        structure = self.structure
        if structure.symmetric is not None:
            known_symmetric = structure.symmetric
        self._op = layout_for(
            A, self._op, comm=self.comm, block_size=structure.block_size, types=self._types
        )
        change = self._op.update(A, known_symmetric)
        if change is Change.NEW:
            self._attach(self._op.mat)
            self._lag.operator_changed(new_mat=True)
        elif change is Change.VALUES:
            self._lag.operator_changed()
            self.stats.operator_updates += 1
            if structure.nullspace is not None:
                check_nullspaces(self._op.mat)

    def _attach(self, mat: PETSc.Mat) -> None:
        """Put a new Mat (new pattern, size or communicator) under both KSPs, with the
        declared structure: null spaces, near-null space, fields."""
        if mat.getComm().getSize() != self._fwd.ksp.getComm().getSize():
            self.rebuild_on(mat.getComm())
        structure = self.structure
        if structure.nullspace is not None:
            attach_nullspaces(
                mat, structure.nullspace, structure.transpose_nullspace, self._kernels
            )
        if structure.near_nullspace is not None:
            attach_near_nullspace(mat, structure.near_nullspace)
        if self._x is not None and self._x.getSizes() != mat.getSizes()[1]:
            for side in self._sides():  # another size: KSPReset, options stay
                side.ksp.reset()
                side.has_fields = False  # the reset dropped them
        for side in self._sides():
            side.ksp.setOperators(mat)
        if structure.fields is not None:
            self._attach_fields(mat)
        self._free_vecs()
        self._x, self._b = mat.createVecs()
        self._layout = RowLayout(self._b, replicated=self._op.replicated)
        self.stats.operator_updates += 1

    def _attach_fields(self, mat: PETSc.Mat) -> None:
        """``PCFieldSplitSetIS`` on the forward PC and on an adjoint PC of its own, once
        per PC (PETSc keeps them for a new Mat, and a second call adds them twice)."""
        for side in self._sides():
            if side is self._adj and self._shared_pc:
                continue  # the forward PC's fields serve both
            if side.has_fields:
                continue
            attach_fields(side.ksp.getPC(), self.structure.fields, mat)
            side.has_fields = True

    def _adjoint_is_forward(self) -> bool:
        """True when ``Aᵀλ = g`` can run as a forward solve of the adjoint KSP."""
        self._op.refresh_symmetry()  # a caller's Mat may have been edited
        if not self._op.symmetric or self.adjoint.symmetric_pc is False:
            return False
        return self.adjoint.symmetric_pc or self._adj.ksp.getPC().getType() in _SYMMETRIC_PCS

    # -- solves ---------------------------------------------------------------------
    def solve(self, b, *, out=None) -> LinearSolution:
        """Solve ``A x = b`` from a zero initial guess; `b` is ``(n,)`` or ``(B, n)``.

        On the device path (`vec_type` not None) `b` is an array with ``__dlpack__``
        of shape ``(n,)``, or a sequence of them (the rows of a batch), in the
        memory of the solver's types, and `out` the same for x: PETSc reads b and
        writes x in place, no copy (`prdp_petsc.core.device`).  `out` is required
        except for a numpy `b` on host types, whose x is a new array as by default.

        Returns
        -------
        LinearSolution
            x as ``.value`` (an ndarray, shape of `b`; on the device path `out`
            itself) with this call's outcome: ``.iterations``, ``.reason``,
            ``.residual_norm``, ``.converged`` and ``.info``, every sample's
            `SolveInfo`.
        """
        return self._run(b, self._fwd, out)

    def solve_transpose(self, g, *, out=None) -> LinearSolution:
        """Solve ``Aᵀ λ = g`` with the adjoint settings; `g` is ``(n,)`` or ``(B, n)``
        (on the device path DLPack arrays and `out`, as in `solve`).

        Returns
        -------
        LinearSolution
            λ as ``.value`` with this call's outcome, as `solve` (``.info.kind`` is
            ``"adjoint"``).
        """
        safeguards.check_transpose_ksp(self.adjoint_ksp)
        return self._run(g, self._adj, out)

    def _run(self, rhs, side: _Side, out=None) -> LinearSolution:
        self._alive()
        mat = self.mat
        layout = self._layout
        kind = side.kind
        if self._types is not None:
            value = None
            if out is None and isinstance(rhs, np.ndarray) and self._types.memory == "cpu":
                # numpy on host types (the K_full probe): x in a new array, as by default
                rhs = np.ascontiguousarray(rhs, dtype=np.float64)
                value = np.empty_like(rhs)
                rhs, out = (rhs, value) if rhs.ndim == 1 else (list(rhs), list(value))
            rows = WrappedRows(rhs, out, layout.size, self._types.memory, kind, value)
            try:
                return self._run_rows(side, mat, rows, None, None, None)
            finally:
                rows.destroy()
        if out is not None:
            raise InputError(
                "out= is the device path's (options naming vec_type/mat_type); this "
                "solver returns a new array"
            )
        rhs = np.asarray(rhs, dtype=np.float64)
        batch = rhs.reshape(-1, rhs.shape[-1])
        if batch.shape[1] != layout.size:
            where = "rows" if layout.replicated or not layout.distributed else "local rows"
            raise InputError(
                f"right-hand side has {batch.shape[1]} entries, operator has {layout.size} {where}"
            )
        self._check_finite(batch, kind)
        out = np.empty_like(batch)
        return self._run_rows(side, mat, None, batch, out, rhs.shape)

    def _run_rows(
        self,
        side: _Side,
        mat: PETSc.Mat,
        rows: WrappedRows | None,
        batch: np.ndarray | None,
        out: np.ndarray | None,
        shape: tuple | None,
    ) -> LinearSolution:
        """Solve every row: the caller's wrapped Vecs (`rows`), or numpy rows of `batch`
        into `out`; value of the result: ``rows.value()``, or `out` in `shape`."""
        layout = self._layout
        kind = side.kind
        if rows is not None:
            batch = rows
        ksp = side.ksp
        step = self._step(side, mat)
        check = side.unchecked
        slot = Side.FORWARD if self._shared_pc else kind  # a shared PC has one age
        age = self._lag.before_solve(slot, ksp, self.stats)
        t0 = time.perf_counter()
        iterations = 0
        infos: list[SolveInfo] = []
        # the options are in PETSc's database while it may read them: at the PC set-up
        # after a new operator (GAMG reads its level options there), and at the first
        # solve, to learn which were never read.  KSPSolve itself reads none.
        setup = check or side.setup_version != self._op.version
        pushed = PushedOptions(self._items, watch=check) if setup else _NOTHING_PUSHED
        try:
            with pushed:
                if setup and self.check_structure:
                    self._check_structure(ksp, kind)
                try:
                    for i in range(len(batch)):
                        iterations += (
                            rows.solve(step, i) if rows is not None else step(batch[i], out[i])
                        )
                except SolverError as err:
                    if age == 0:
                        raise
                    # failed on a reused PC (a stale GAMG can be indefinite): run the call
                    # again on a fresh one; a failure then is the operator's own
                    logger.warning(
                        "%s solve failed on a PC %d operator changes old (%s); set up again",
                        kind,
                        age,
                        err.reason,
                    )
                    if len(step.infos) > i:  # the failed row's own work counts too
                        iterations += step.infos[i].iterations
                    self._lag.mark_stale(slot)
                    age = self._lag.before_solve(slot, ksp, self.stats)
                    step = SolveStep(
                        ksp, mat, self._b, self._x, layout, kind, step.transpose, self._op.norm
                    )
                    for i in range(len(batch)):
                        iterations += (
                            rows.solve(step, i) if rows is not None else step(batch[i], out[i])
                        )
                finally:
                    infos = self._lag.after_solve(slot, kind, step.infos, age)
        except SolverError as err:
            if check and (unused := self._unused_after(side, pushed)):
                # a misspelt option (a split's, say) is often why the set-up failed
                raise type(err)(f"{err}; {unused}", reason=err.reason) from err
            raise
        side.setup_version = self._op.version
        if check and (unused := self._unused_after(side, pushed)):
            warnings.warn(unused, UnusedOptionWarning, stacklevel=4)
        if rows is not None:  # the device path: `nonfinite` of every row, where it lives
            finite = rows.finite()
        else:  # the step saw a finite ‖x‖ of every row (so no NaN/Inf), or a sum
            finite = step.finite or bool(np.isfinite(out.sum()) or np.all(np.isfinite(out)))
        if layout.distributed and not layout.replicated:
            finite = bool(layout.agree_max(np.array([not finite]))[0] == 0)
        if not finite:
            raise SolverError(f"{kind} solve returned NaN/Inf", reason="DIVERGED_NANORINF")
        elapsed = time.perf_counter() - t0
        self.stats.record(kind, len(batch), iterations, elapsed)
        if step.unconverged and self.not_converged != "ignore":
            self._report_unconverged(side, step, len(batch))
        value = rows.value() if rows is not None else out.reshape(shape)
        return LinearSolution(value, CallInfo(kind.value, tuple(infos)))

    def _report_unconverged(self, side: _Side, step: SolveStep, rows: int) -> None:
        """`NotConvergedWarning` (or `SolverError`) for the rows of this call that had a
        tolerance and hit max_it, naming the worst one's true residual."""
        row, residual = max(step.unconverged, key=lambda item: item[1].relative)
        info = step.infos[row]
        ksp, kind = side.ksp, side.kind
        rtol, atol = ksp.getTolerances()[:2]
        count = len(step.unconverged)
        which = "" if rows == 1 else f" (row {row}, the worst of {count} of {rows})"
        adjoint = side.transpose
        relation = "‖g − Aᵀλ‖/‖g‖" if adjoint else "‖b − A x‖/‖b‖"
        cap = "the adjoint's max_it (AdjointSettings(max_it=...))" if adjoint else "max_it"
        message = (
            f"{kind} solve ({side.types()}) did not converge: "
            f"{info.reason} after {info.iterations} iterations with rtol={rtol:g}, "
            f"atol={atol:g}{which}; true residual {relation} = {residual.relative:.3g}. "
            f"Raise {cap}, loosen rtol, or choose another KSP/PC"
        )
        if singular := step.near_null_hint(residual):
            message += f"; {singular}"
        if self.not_converged == "raise":
            raise SolverError(message, reason=info.reason)
        message += " (KSPSolver(not_converged='ignore') accepts such solves silently)"
        warnings.warn(message, NotConvergedWarning, stacklevel=caller_stacklevel())

    def _step(self, side: _Side, mat: PETSc.Mat) -> SolveStep:
        """The `SolveStep` of this call: kept on its side while the operator (a Mat made
        here, whose null spaces only this solver sets) and the adjoint's maths (PC
        type, ``symmetric_pc``) stay."""
        transpose = side.transpose
        if not self._op.made_here:  # a caller's Mat may be edited: ask it every call
            as_transpose = transpose and not self._adjoint_is_forward()
            return SolveStep(
                side.ksp,
                mat,
                self._b,
                self._x,
                self._layout,
                side.kind,
                as_transpose,
                self._op.norm,
            )
        # what `_adjoint_is_forward` reads (the PC type: a caller may set it on `adjoint_ksp`)
        pc_type = self._adj.ksp.getPC().getType() if transpose else None
        key = (self._op.version, self.adjoint.symmetric_pc, pc_type)
        if side.step is not None and side.step[0] == key:
            side.step[1].reset()
            return side.step[1]
        as_transpose = transpose and not self._adjoint_is_forward()
        step = SolveStep(
            side.ksp, mat, self._b, self._x, self._layout, side.kind, as_transpose, self._op.norm
        )
        side.step = (key, step)
        return step

    def _check_finite(self, batch: np.ndarray, kind: Side) -> None:
        """NaN or Inf in a right-hand side: `NonFiniteError` before any row is solved
        (PETSc would return x = 0 with ``DIVERGED_NANORINF``).  One pass: the sum of
        every entry is finite unless one is NaN or Inf (or the sum overflows: then the
        entries are tested)."""
        bad = not (math.isfinite(batch.sum()) or np.all(np.isfinite(batch)))
        if self._layout.distributed and not self._layout.replicated:
            bad = bool(self._layout.agree_max(np.array([bad]))[0])
        if bad:
            rows = np.flatnonzero(~np.all(np.isfinite(batch), axis=1)).tolist()
            where = f" (rows {rows[:5]}{', ...' if len(rows) > 5 else ''})" if rows else ""
            rhs = "right-hand side (cotangent)" if kind is Side.ADJOINT else "right-hand side"
            raise NonFiniteError(f"{kind} solve: the {rhs} contains NaN or Inf{where}")

    def _check_structure(self, ksp: PETSc.KSP, kind: Side) -> None:
        """`check_structure` of `ksp` against the operator, its sub-solvers after set-up."""
        symmetric = self._op.symmetric
        check_structure(ksp, symmetric, kind)  # before set-up: the cheap, common case
        if symmetric is False and ksp.getPC().getType() in ("bjacobi", "asm"):
            ksp.setUp()  # KSPSolve would; now the blocks' KSPs exist
            check_structure(ksp, symmetric, kind, set_up=True)

    def reset_stats(self) -> None:
        """Zero the counters in `stats`."""
        self.stats = SolverStats()

    def __repr__(self) -> str:
        return (
            f"KSPSolver(options={self.options!r}, prefix={self.prefix!r}, max_it={self.max_it}, "
            f"rtol={self.rtol}, atol={self.atol}, adjoint_max_it={self.adjoint_max_it})"
        )


def _describe_space(spec) -> str | int | None:
    """A (near-)null space in a JSON record: ``"constant"``, its vector count, or None."""
    if spec is None or isinstance(spec, str):
        return spec
    return spec.shape[1] if sp.issparse(spec) else len(spec)
