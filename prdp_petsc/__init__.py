"""prdp_petsc: train neural networks through capped PETSc solves with PRDP.

scikit-fem assembles sparse operators, petsc4py KSP solves them with a capped
iteration count, transpose solves give implicit gradients through a torch
autograd bridge, and the `PRDP` controller raises the cap only as far as the
validation metric needs.
"""

from importlib.metadata import PackageNotFoundError, version

from .autograd.bridge import matvec, solve
from .autograd.dirichlet import Dirichlet
from .fem.fd import grid_points, laplacian
from .fem.meshes import available_meshes, load_mesh
from .fem.parametric import ParametricMatrix, diffusion_operator, from_form, mass_matrix
from .prdp import PRDP, PRDPStep, rtol_from_level, savings
from .training.scene import Scene
from .core.solver import AdjointSettings, KSPSolver, SolveInfo, SolverError, SolverStats

try:
    __version__ = version("prdp-petsc")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "PRDP",
    "AdjointSettings",
    "Dirichlet",
    "KSPSolver",
    "PRDPStep",
    "ParametricMatrix",
    "SolveInfo",
    "SolverError",
    "Scene",
    "SolverStats",
    "__version__",
    "available_meshes",
    "diffusion_operator",
    "from_form",
    "grid_points",
    "laplacian",
    "load_mesh",
    "mass_matrix",
    "matvec",
    "rtol_from_level",
    "savings",
    "solve",
]
