"""The exceptions and warnings of prdp_petsc: what went wrong, and whose move it is.

Every layer raises these; this module imports neither PETSc nor torch, so the
command line can apply ``-W error::prdp_petsc.errors.UnusedOptionWarning`` before
PETSc starts (`prdp_petsc.lab.cli.apply_warning_options`: Python itself reads ``-W``
before site-packages are importable and drops filters of installed packages).
The taxonomy tells a caller, and the training harness, what to do:

`SolverError`
    A PETSc solve really failed (NaN in the iteration, breakdown, indefinite PC,
    DIVERGED_DTOL, a PC without a transpose).  Hitting ``max_it`` is not an error.

    `SingularOperatorError`
        The operator is singular and no null space that covers its kernel was
        declared (elasticity without Dirichlet conditions, a pure Neumann problem):
        the iterate blew up along a null vector.  Declare ``Structure(nullspace=...)``.
`InputError`
    The library was given something it cannot use.  A ``ValueError``, so code that
    catches ``ValueError`` keeps working.  Subclasses name the kind:

    `NonFiniteError`
        NaN or Inf in a right-hand side, cotangent, parameter, loss or metric.
        Never turned into a number.
    `StructureError`
        A method whose assumptions the operator breaks: a symmetric-only KSP or PC
        (CG, MINRES, ICC, Cholesky, ...) on an operator known to be non-symmetric,
        a form that is not affine in its coefficient.
    `MeshError`
        A mesh file that cannot be read (an exception, never an exit).

`NotConvergedWarning`
    A solve with a tolerance (``rtol > 0`` or ``atol > 0``) hit ``max_it`` without
    meeting it; the message gives the true residual.  ``KSPSolver(not_converged=
    "raise")`` makes it a `SolverError`, ``"ignore"`` silences it.  A capped solve
    without a tolerance (the training mode: exactly K iterations) is not warned about.

The harness (`prdp_petsc.lab.training.harness.run`) records a `SolverError` or an
`InputError` raised during training as a stopped run with a named reason and
lets every other exception propagate: a bug in a scene (a numpy broadcast error,
a plain ``ValueError``) is not a solver outcome.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = [
    "InputError",
    "MeshError",
    "NonFiniteError",
    "NotConvergedWarning",
    "PrdpPetscError",
    "SingularOperatorError",
    "SolverError",
    "StructureError",
    "UnusedOptionWarning",
    "caller_stacklevel",
    "plain",
]


class PrdpPetscError(Exception):
    """Base class of the errors this library raises on purpose."""

    #: short name recorded as ``stopped.reason`` in a training run's results
    reason = "ERROR"


class SolverError(PrdpPetscError, RuntimeError):
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


class SingularOperatorError(SolverError):
    """The operator is singular and its null space was not declared (or not all of it).

    Raised when a solve returns, or breaks down at, an iterate x that is a null vector
    of A to the tolerance a declared null vector must meet (``‖A x‖ ≤ 1e-8 ‖A‖ ‖x‖``)
    while the true residual ``‖b − A x‖`` was not reduced: Krylov iterates grew along
    the kernel (rigid-body modes of elasticity without Dirichlet conditions, the
    constants of a pure Neumann problem, the gradients of curl-curl) instead of
    converging.  Declare the kernel, e.g. ``Structure(nullspace=rigid_body_modes(basis))``,
    ``nullspace=discrete_gradient(basis, dofs)`` or ``nullspace="constant"``, or add
    boundary conditions.  `reason` is ``"SINGULAR"``; the message names PETSc's
    own reason.
    """

    def __init__(self, message: str, reason: str = "SINGULAR"):
        super().__init__(message, reason)


class InputError(PrdpPetscError, ValueError):
    """An input the library cannot use (shape, value, setting); names the argument."""

    reason = "INVALID_INPUT"


class NonFiniteError(InputError):
    """NaN or Inf where a number is needed: right-hand side, cotangent, loss, metric."""

    reason = "NON_FINITE"


class StructureError(InputError):
    """A method whose assumptions the operator breaks (CG on a non-symmetric matrix)."""

    reason = "STRUCTURE"


class MeshError(InputError):
    """A mesh file that cannot be read or converted."""

    reason = "MESH"


class UnusedOptionWarning(UserWarning):
    """Options of a `KSPSolver` that PETSc never read (misspelt, or meant for another type).

    A warning, not an error: ``-fwd_ksp_type cg`` on the command line legitimately
    leaves a scene's ``ksp_richardson_scale`` unread.  Turn it into an error with
    ``warnings.simplefilter("error", UnusedOptionWarning)`` in a script, or for a
    command-line run with ``python -W error::prdp_petsc.errors.UnusedOptionWarning -m
    prdp_petsc.lab.cli ...`` (``PYTHONWARNINGS=...`` for ``prdp-petsc``), which the
    command line applies when it starts.
    """


class NotConvergedWarning(UserWarning):
    """A solve with a tolerance ended without meeting it (``DIVERGED_MAX_IT``).

    Given by `prdp_petsc.KSPSolver` with ``not_converged="warn"`` (the default) when
    a solve with ``rtol > 0`` or ``atol > 0`` hits ``max_it``: the message names the
    KSP/PC, the iterations, the tolerances and the true residual ``‖b − A x‖/‖b‖``,
    and what to do (raise ``max_it``, loosen ``rtol``, or choose another KSP/PC).
    A capped solve with ``rtol = atol = 0`` (exactly K iterations, how PRDP trains)
    is never warned about.  ``not_converged="raise"`` turns it into a `SolverError`
    with reason ``DIVERGED_MAX_IT`` (what a training harness records as a stopped
    run); ``warnings.simplefilter("error", NotConvergedWarning)`` raises the warning
    itself instead.
    """


def plain(value):
    """`value` as an error message should show it: numpy scalars and arrays (also
    inside tuples and lists) as Python numbers and lists, so that a message says
    ``482``, not ``np.int32(482)`` (numpy 2's repr).  Anything else is returned as is.
    """
    if isinstance(value, tuple | list):
        return type(value)(plain(v) for v in value)
    tolist = getattr(value, "tolist", None)
    return tolist() if callable(tolist) and type(value).__module__ == "numpy" else value


#: a warning points at the first frame outside this package: the caller's line
_PACKAGE = str(Path(__file__).parent) + os.sep


def caller_stacklevel() -> int:
    """The ``stacklevel`` for a warning given in the function that calls this one: the
    first frame outside prdp_petsc (and torch's autograd, which runs the bridge), so
    that the warning names the caller's line."""
    internal = (_PACKAGE,)
    torch = sys.modules.get("torch")  # only its path: this module imports no torch
    if torch is not None:
        internal += (str(Path(torch.__file__).parent) + os.sep,)
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(internal):
        frame, level = frame.f_back, level + 1
    return level
