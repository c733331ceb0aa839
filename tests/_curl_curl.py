"""Curl-curl on lowest-order Nédélec elements, shared by the test files: singular for
ε = 0 (every gradient is in its kernel), with a load whose part along the gradients
makes ``A u = b`` incompatible."""

import skfem
from skfem import BilinearForm, LinearForm
from skfem.helpers import curl, dot


def curl_curl(mesh, element, eps: float = 0.0):
    """(basis, A, b): ``(curl u, curl v) + eps (u, v)`` and a load that is not divergence
    free."""
    basis = skfem.Basis(mesh, element())

    @BilinearForm
    def form(u, v, w):
        return dot(curl(u), curl(v)) + eps * dot(u, v)

    @LinearForm
    def load(v, w):
        x = w.x
        return v[0] * (1 + x[0]) + v[1] * x[1] ** 2

    return basis, form.assemble(basis).tocsr(), load.assemble(basis)


def interior(basis, A, b):
    """A and b without the boundary dofs (``u × n = 0``), and the kept dofs."""
    kept = basis.complement_dofs(basis.get_dofs())
    return A[kept][:, kept].tocsr(), b[kept], kept


def triangles(refine: int = 4, eps: float = 0.0):
    """(basis, A, b, kept) on the unit square with u × n = 0: ``ElementTriN1``."""
    basis, A, b = curl_curl(skfem.MeshTri().refined(refine), skfem.ElementTriN1, eps)
    return (basis, *interior(basis, A, b))
