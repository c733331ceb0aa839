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

# public name -> module that defines it
_EXPORTS = {
    "matvec": ".autograd.bridge",
    "solve": ".autograd.bridge",
    "LinearSolution": ".autograd.solution",
    "WarmStarts": ".autograd.warm_starts",
    "Dirichlet": ".autograd.dirichlet",
    "once_differentiable": ".autograd.once",
    "gradient_check": ".autograd.check",
    "sum_over_ranks": ".autograd.owned",
    "NonlinearProblem": ".autograd.nonlinear",
    "NonlinearSolution": ".autograd.nonlinear",
    "newton_solve": ".autograd.nonlinear",
    "grid_points": ".fem.fd",
    "laplacian": ".fem.fd",
    "available_meshes": ".fem.meshes",
    "load_mesh": ".fem.meshes",
    "min_angle_degrees": ".fem.meshes",
    "ParametricMatrix": ".fem.parametric",
    "csr_pattern": ".fem.parametric",
    "DistributedParametricMatrix": ".fem.distributed",
    "PartitionedMesh": ".fem.partition",
    "diffusion_operator": ".fem.forms",
    "elasticity_operator": ".fem.forms",
    "from_form": ".fem.forms",
    "mass_matrix": ".fem.forms",
    "block_size": ".fem.vector",
    "rigid_body_modes": ".fem.vector",
    "ACCURACY_BAND": ".prdp",
    "Certificate": ".prdp",
    "PRDP": ".prdp",
    "PRDPStep": ".prdp",
    "find_k_full": ".core.probe",
    "savings": ".prdp",
    "AdjointSettings": ".core.settings",
    "KSPSolver": ".core.solver",
    "split_petsc_options": ".core.options",
    "Structure": ".core.structure",
    "use_comm": ".core.parallel",
    "default_comm": ".core.parallel",
    "SolveInfo": ".core.results",
    "SolverError": ".errors",
    "SingularOperatorError": ".errors",
    "InputError": ".errors",
    "NonFiniteError": ".errors",
    "StructureError": ".errors",
    "MeshError": ".errors",
    "UnusedOptionWarning": ".errors",
    "SolverStats": ".core.results",
}

__all__ = sorted([*_EXPORTS, "__version__"])

# names that moved to the lab (prdp_petsc.lab, the ``lab`` extra): the library cannot
# import the lab, so these raise, naming where they are now
_MOVED = {
    "Scene": "prdp_petsc.lab.Scene",
    "NonlinearHeat": "prdp_petsc.lab.NonlinearHeat",
    "equal_accuracy_k": "prdp_petsc.lab.training.accuracy.equal_accuracy_k",
}


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    if name in _MOVED:
        raise AttributeError(
            f"prdp_petsc.{name} moved to the lab: {_MOVED[name]} (pip install 'prdp-petsc[lab]')"
        )
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
