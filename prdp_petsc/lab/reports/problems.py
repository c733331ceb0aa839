"""Standard linear test problems built from the library, for benchmarks and tests.

The `Problem` set (`PROBLEMS`, by name) is a parametric operator ``A(θ)`` on the
unknowns (Dirichlet degrees of freedom eliminated), a right-hand side and the loss
``L(x) = ‖x − d‖² / (2n)`` with data ``d`` the solution for a smoothly perturbed
coefficient, so that forward errors and gradients ``∂L/∂θ`` can be measured against
a direct solve:

``poisson``
    ``−∇·(κ∇u) = 1`` on ``plate_holes``, ``u = 0`` on every boundary; P1, κ per element.
``heat3d``
    One backward-Euler step ``(M + Δt K(κ)) u¹ = M u⁰`` on the tetrahedral ``box3d``
    mesh, insulated walls; κ per element.
``advection``
    ``−∇·(ε∇u) + β·∇u = 1`` on the ``annulus``, ``u = 0`` on both circles, spiral wind
    `spiral_wind`; ε per element.  Galerkin P1, mesh Péclet number about 1.

The benchmarks' own operators live here too: `plate_reaction` (``bench bridge``),
`five_point` (``bench bridge``, ``bench jax``), `clamped_cube` (``bench elasticity``)
and `warm_spot`, the initial temperature of every 3D heat step (``bench mpi``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from prdp_petsc import Dirichlet, ParametricMatrix, diffusion_operator, load_mesh, mass_matrix

__all__ = [
    "PROBLEMS",
    "Problem",
    "build_problem",
    "clamped_cube",
    "direct_gradient",
    "five_point",
    "mean_edge_length",
    "plate_reaction",
    "poisson_problem",
    "unit_load",
    "warm_spot",
]


@dataclass(eq=False)
class Problem:
    """A linear problem ``A(θ) x = b`` at reference θ, with the data ``d`` of its loss;
    `symmetric` says whether CG and ICC apply, `info` holds sizes for reports."""

    name: str
    A: ParametricMatrix
    theta: np.ndarray
    b: np.ndarray
    data: np.ndarray
    symmetric: bool
    description: str
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of unknowns."""
        return self.A.shape[0]

    def matrix(self, theta: np.ndarray | None = None) -> sp.csr_matrix:
        """Assembled ``A(θ)`` (default: the reference θ)."""
        return self.A.matrix(self.theta if theta is None else theta)

    def loss(self, x):
        """``L(x) = ‖x − d‖² / (2n)`` for a numpy array or a torch tensor."""
        r = x - (self.data if isinstance(x, np.ndarray) else x.new_tensor(self.data))
        return 0.5 * (r * r).sum() / self.n

    def loss_grad(self, x: np.ndarray) -> np.ndarray:
        """``∂L/∂x = (x − d) / n``."""
        return (x - self.data) / self.n


def mean_edge_length(mesh) -> float:
    """Mean length of the edges (2D: facets) of a scikit-fem simplex mesh."""
    edges = mesh.facets if mesh.dim() == 2 else mesh.edges
    return float(np.linalg.norm(np.diff(mesh.p[:, edges], axis=1)[:, 0], axis=0).mean())


def _smooth_perturbation(mesh, theta: np.ndarray) -> np.ndarray:
    """θ times a smooth positive field in [0.5, 1.5] (per element), the data's coefficient."""
    c = mesh.p[:, mesh.t].mean(axis=1)
    return theta * (1.0 + 0.5 * np.sin(2 * np.pi * c[0]) * np.cos(np.pi * c[1]))


def _finish(name, A, theta, b, mesh, symmetric, description, info: dict) -> Problem:
    """The problem, its data ``d`` the solution for a smoothly perturbed coefficient."""
    from scipy.sparse.linalg import splu

    d = splu(A.matrix(_smooth_perturbation(mesh, theta)).tocsc()).solve(b)
    sizes = {"unknowns": int(A.shape[0]), "nnz": int(A.nnz), "parameters": int(A.n_params)}
    info = {**sizes, "h": mean_edge_length(mesh), **info}
    return Problem(name, A, theta, b, d, symmetric, description, info)


def unit_load(basis) -> np.ndarray:
    """The load vector of the source f = 1 on `basis`."""
    from skfem import LinearForm

    return LinearForm(lambda v, w: 1.0 * v).assemble(basis)


def poisson_problem(mesh, *, dirichlet: bool = True, form=None):
    """(A(θ), load vector of f = 1, P1 basis) for −∇·(κ∇u) = 1 on `mesh` (triangles), κ
    per triangle (`form`: another P0-parametrised bilinear form, `prdp_petsc.from_form`);
    with `dirichlet`, A and b on the unknowns of u = 0 on the whole boundary."""
    from skfem import Basis, ElementTriP0, ElementTriP1

    from prdp_petsc import from_form

    basis = Basis(mesh, ElementTriP1())
    if form is None:
        A = diffusion_operator(basis)
    else:
        A = from_form(form, basis, basis.with_element(ElementTriP0()), positive=True)
    b = unit_load(basis)
    if not dirichlet:
        return A, b, basis
    d = Dirichlet(A, basis.get_dofs())
    return d.A_II, b[d.interior], basis


def poisson(refine: int = 2) -> Problem:
    """2D Poisson ``−∇·(κ∇u) = 1`` on ``plate_holes``, zero Dirichlet values everywhere."""
    mesh = load_mesh("plate_holes", refine)
    A, b, _ = poisson_problem(mesh)
    description = f"−∇·(κ∇u) = 1 on plate_holes (refine {refine}), P1, u = 0 on all boundaries"
    info = {"mesh": "plate_holes", "refine": refine}
    return _finish("poisson", A, np.ones(mesh.t.shape[1]), b, mesh, True, description, info)


def heat3d(refine: int = 1, dt_ratio: float = 10.0) -> Problem:
    """One implicit heat step on ``box3d``: ``(M + Δt K(κ)) u¹ = M u⁰``, insulated walls,
    ``Δt = dt_ratio · h² / κ`` with h the mean edge length and κ = 1."""
    from skfem import Basis, ElementTetP1

    mesh = load_mesh("box3d", refine)
    basis = Basis(mesh, ElementTetP1())
    dt = dt_ratio * mean_edge_length(mesh) ** 2
    M = mass_matrix(basis)
    A = dt * diffusion_operator(basis) + M
    description = (
        f"(M + Δt K(κ)) u¹ = M u⁰ on box3d (refine {refine}, tetrahedra), Δt κ/h² = {dt_ratio:g}"
    )
    theta, b = np.ones(mesh.t.shape[1]), M @ warm_spot(mesh.p)
    info = {"mesh": "box3d", "refine": refine, "dt": dt, "dt_kappa_over_h2": dt_ratio}
    return _finish("heat3d", A, theta, b, mesh, True, description, info)


def warm_spot(points: np.ndarray) -> np.ndarray:
    """The initial temperature of the 3D heat steps: a Gaussian spot at (0.3, 0.6, 0.5)."""
    x, y, z = points
    return np.exp(-20 * ((x - 0.3) ** 2 + (y - 0.6) ** 2 + (z - 0.5) ** 2))


def spiral_wind(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Divergence-free wind ``(−y, x) + 0.3 (x, y) / r²`` of the advection problem."""
    r2 = x**2 + y**2
    return -y + 0.3 * x / r2, x + 0.3 * y / r2


def advection(refine: int = 1, epsilon: float = 0.01) -> Problem:
    """``−∇·(ε∇u) + β·∇u = 1`` on the annulus (Galerkin P1), ``u = 0`` on both circles."""
    from skfem import Basis, BilinearForm, ElementTriP1

    mesh = load_mesh("annulus", refine)
    basis = Basis(mesh, ElementTriP1())

    @BilinearForm
    def convection(u, v, w):
        bx, by = spiral_wind(*w.x)
        return (bx * u.grad[0] + by * u.grad[1]) * v

    bc = Dirichlet(diffusion_operator(basis) + convection.assemble(basis), basis.get_dofs())
    description = f"−∇·(ε∇u) + β·∇u = 1 on annulus (refine {refine}), ε = {epsilon:g}, spiral wind"
    theta, b = np.full(mesh.t.shape[1], float(epsilon)), unit_load(basis)[bc.interior]
    peclet = mean_edge_length(mesh) / (2 * epsilon)
    info = {"mesh": "annulus", "refine": refine, "epsilon": epsilon, "mesh_peclet": peclet}
    return _finish("advection", bc.A_II, theta, b, mesh, False, description, info)


#: name -> (builder, keyword arguments of the full size, of the quick size)
PROBLEMS = {
    "poisson": (poisson, {"refine": 2}, {"refine": 0}),
    "heat3d": (heat3d, {"refine": 1}, {"refine": 0}),
    "advection": (advection, {"refine": 2}, {"refine": 0}),
}


def build_problem(name: str, quick: bool = False, **kwargs) -> Problem:
    """Build a standard problem by name at its full (or quick) size; kwargs override."""
    if name not in PROBLEMS:
        raise ValueError(f"unknown problem {name!r}; choose from {sorted(PROBLEMS)}")
    builder, full, small = PROBLEMS[name]
    return builder(**{**(small if quick else full), **kwargs})


def direct_gradient(problem: Problem, theta: np.ndarray | None = None):
    """Converged reference: ``(x, λ, ∂L/∂θ)`` from a sparse LU factorisation."""
    from scipy.sparse.linalg import splu

    lu = splu(problem.matrix(theta).tocsc())
    x = lu.solve(problem.b)
    lam = lu.solve(problem.loss_grad(x), trans="T")
    return x, lam, problem.A.theta_gradient(lam, x)


# P1 unknowns of plate_holes: 4851 at refine 0, about 4x per refinement.
_PLATE_HOLES_N0 = 4851


def plate_reaction(n: int, seed: int = 0):
    """``(A, θ, b, g, refine)``: ``−∇·(κ∇u) + u`` on ``plate_holes`` refined to about n
    P1 unknowns, κ per element (SPD, no boundary condition), random θ in [1, 1.5]."""
    import skfem

    refine = max(0, round(float(np.log(n / _PLATE_HOLES_N0) / np.log(4.0))))
    basis = skfem.Basis(load_mesh("plate_holes", refine=refine), skfem.ElementTriP1())
    A = diffusion_operator(basis, "P0", reaction=1.0)
    rng = np.random.default_rng(seed)
    theta = 1.0 + 0.5 * rng.random(A.n_params)
    return A, theta, rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0]), refine


def five_point(side: int, seed: int = 0):
    """``(A, b, g)``: the SPD five-point ``−Δ`` on a side × side grid (scipy CSR, Dirichlet)
    and two random vectors."""
    from prdp_petsc.fem.fd import laplacian

    A = (-laplacian((side, side))).tocsr()
    A.sort_indices()
    rng = np.random.default_rng(seed)
    return A, rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])


def clamped_cube(n: int):
    """``(basis, Dirichlet, load)``: linear elasticity (E = 1, ν = 0.3) on the unit cube of
    n³ Q1 hexahedra, clamped at x = 0, loaded by its weight along −z (on the unknowns)."""
    import skfem

    from prdp_petsc import elasticity_operator

    t = np.linspace(0.0, 1.0, n + 1)
    element = skfem.ElementVector(skfem.ElementHex1())
    basis = skfem.Basis(skfem.MeshHex.init_tensor(t, t, t), element)
    clamped = basis.get_dofs(lambda x: np.isclose(x[0], 0.0)).all()
    bc = Dirichlet(elasticity_operator(basis), clamped)

    @skfem.LinearForm
    def weight(v, w):
        return -v[2]

    return basis, bc, weight.assemble(basis)[bc.interior]  # the clamp holds u = 0
