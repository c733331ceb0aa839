"""prdp_petsc: train neural networks through capped PETSc solves with PRDP.

scikit-fem assembles sparse operators, petsc4py KSP solves them with a capped
iteration count, transpose solves give implicit gradients through a torch
autograd bridge, and the `PRDP` controller raises the cap only as far as the
validation metric needs.

The public names below are imported on first use (PEP 562), so that
``import prdp_petsc`` (and the ``prdp-petsc`` command line) imports neither
PETSc nor torch: the command line must call ``petsc4py.init`` with its PETSc
options (``-log_view``, ...) before PETSc is first imported.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("prdp-petsc")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

# public name -> module that defines it: what a training loop needs.  The rest is public
# in the module that defines it (listed in its ``__all__`` and in the API reference):
# prdp_petsc.errors (every error and warning), prdp_petsc.prdp (Certificate, PRDPStep,
# savings, ACCURACY_BAND), prdp_petsc.fem.* (finite differences, meshes, the owned
# layout's DistributedParametricMatrix and PartitionedMesh), prdp_petsc.autograd.*
# (matvec, WarmStarts, sum_over_ranks), prdp_petsc.core.* (use_comm, SolverStats, ...).
_EXPORTS = {
    # configure and run a differentiable solve; read its outcome
    "KSPSolver": ".core.solver",
    "Structure": ".core.structure",
    "AdjointSettings": ".core.settings",
    "solve": ".autograd.bridge",
    "Dirichlet": ".autograd.dirichlet",
    "LinearSolution": ".core.solution",
    "newton_solve": ".autograd.nonlinear",
    "NonlinearProblem": ".autograd.nonlinear",
    "NonlinearSolution": ".autograd.nonlinear",
    # operators and meshes
    "ParametricMatrix": ".fem.parametric",
    "diffusion_operator": ".fem.forms",
    "elasticity_operator": ".fem.forms",
    "mass_matrix": ".fem.forms",
    "from_form": ".fem.forms",
    "rigid_body_modes": ".fem.vector",
    "discrete_gradient": ".fem.nedelec",
    "load_mesh": ".fem.meshes",
    # PRDP in a training loop
    "PRDP": ".prdp",
    "gradient_check": ".autograd.check",
    "find_k_full": ".core.probe",
    # the errors a training loop catches (the rest: prdp_petsc.errors)
    "SolverError": ".errors",
    "InputError": ".errors",
}

__all__ = sorted([*_EXPORTS, "__version__"])

# names that moved to the lab (prdp_petsc.lab, the ``lab`` extra): the library cannot
# import the lab, so these raise, naming where they are now
_MOVED = {
    "Scene": "prdp_petsc.lab.Scene",
    "NonlinearHeat": "demos/heat_nonlinear.py (the physics of that scene)",
    "equal_accuracy_k": "prdp_petsc.lab.training.accuracy.equal_accuracy_k",
}


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    if name in _MOVED:
        where = _MOVED[name]
        how = "" if where.startswith("demos/") else " (pip install 'prdp-petsc[lab]')"
        raise AttributeError(f"prdp_petsc.{name} moved out of the library: {where}{how}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
