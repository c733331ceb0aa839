"""Vector problems: block sizes and near-null spaces, declared once on the solver.

A solver's ``block_size=`` and ``near_nullspace=`` must reach every Mat it builds
(new θ, a batch of operators, a new size, a clone, the adjoint) and make GAMG
converge in few iterations where scalar GAMG does not.
"""

import numpy as np
import pytest
import torch
from _vector import body_load, clamped, elasticity

import prdp_petsc as pp
from prdp_petsc.errors import InputError
from prdp_petsc.fem.fd import laplacian

GAMG = {"ksp_type": "cg", "pc_type": "gamg"}


# -- GAMG with the modes --------------------------------------------------------------------
@pytest.fixture(scope="module")
def cantilever():
    """A 4:1 cantilever (2 176 unknowns after the clamp), E = 1, a load along it."""
    basis, A = elasticity(n=16, length=4.0)
    bc = clamped(basis, A)
    M = bc.A_II.matrix(np.ones(A.n_params))
    return basis, A, bc, M, body_load(basis)[bc.interior]


def _structure(basis, bc, **more):
    return pp.Structure(
        near_nullspace=pp.rigid_body_modes(basis, bc.interior), block_size=2, **more
    )


def test_gamg_needs_the_modes_on_a_cantilever(cantilever):
    """Scalar GAMG needs 80 iterations to 1e-8 here, GAMG with the modes 17; a
    capped K = 10 solve is close only with the modes."""
    basis, _, bc, M, f = cantilever
    exact = np.linalg.solve(M.toarray(), f)
    counts, errors = {}, {}
    for name, structure in (("scalar", None), ("modes", _structure(basis, bc))):
        with pp.KSPSolver(GAMG, max_it=1000, rtol=1e-8, structure=structure) as s:
            s.set_operator(M)
            counts[name] = s.solve(f).iterations
            s.rtol, s.max_it = 0.0, 10
            errors[name] = np.linalg.norm(s.solve(f).value - exact) / np.linalg.norm(exact)
    assert counts["modes"] <= 20 and counts["scalar"] >= 3 * counts["modes"], counts
    assert errors["modes"] <= 1e-4 and errors["scalar"] >= 1e-2, errors


def test_structure_reaches_every_mat(cantilever):
    """New θ (same Mat), a batch of operators, another size, a clone and the adjoint."""
    basis, A, bc, M, f = cantilever
    with pp.KSPSolver(GAMG, max_it=1000, rtol=1e-8, structure=_structure(basis, bc)) as s:
        theta = torch.ones((2, A.n_params), dtype=torch.float64, requires_grad=True)
        theta.data[1] *= 3.0
        b = torch.from_numpy(np.stack([f, f]))
        # a batch of operators: two set-ups
        sol = pp.solve(bc.A_II, b, s, theta=theta, return_solution=True)
        sol.value.sum().backward()
        for call in (sol.info, sol.adjoint):
            assert call.converged and call.iterations.max() <= 20, call.iterations
        assert s.mat.getBlockSize() == 2 and s.mat.getNearNullSpace().getVecs()
        mat = s.mat
        # new values: the same Mat
        sol = pp.solve(bc.A_II, b[0], s, theta=theta[0].detach() * 2, return_solution=True)
        assert s.mat is mat and sol.iterations <= 20
        copy = s.clone()
        declared = copy.structure
        assert declared.block_size == 2 and declared.near_nullspace.shape == (3, len(bc.interior))
        copy.destroy()
    with pytest.raises(InputError, match="entries"):  # another size, other modes needed
        small = elasticity(n=4, length=4.0)[1]
        with pp.KSPSolver(GAMG, max_it=50, structure=_structure(basis, bc)) as s:
            s.set_operator(small.matrix(np.ones(small.n_params)))


def test_a_new_size_gets_the_new_modes():
    """One solver, two meshes in turn: each Mat gets the structure (via clone for the
    new modes), and the iteration counts stay low on both."""
    counts = []
    solver = None
    for n in (8, 16):
        basis, A = elasticity(n=n, length=4.0)
        bc = clamped(basis, A)
        structure = _structure(basis, bc)
        solver = (
            pp.KSPSolver(GAMG, max_it=500, rtol=1e-8, structure=structure)
            if solver is None
            else solver.clone(structure=structure)
        )
        solver.set_operator(bc.A_II.matrix(np.ones(A.n_params)))
        counts.append(solver.solve(body_load(basis)[bc.interior]).iterations)
    solver.destroy()
    assert max(counts) <= 20, counts


def test_block_size_is_validated():
    with pytest.raises(InputError, match="block_size"):
        pp.KSPSolver(max_it=5, structure=pp.Structure(block_size=0))
    with pytest.raises(InputError, match="block_size"):
        pp.KSPSolver(max_it=5, structure=pp.Structure(block_size=2.0))
    with (
        pp.KSPSolver(max_it=5, structure=pp.Structure(block_size=2)) as s,
        pytest.raises(InputError, match="multiple"),
    ):
        s.set_operator(laplacian((3,)))


def test_describe_records_the_structure(cantilever):
    basis, _, bc, M, _ = cantilever
    fields = {"a": np.arange(0, M.shape[0], 2), "b": np.arange(1, M.shape[0], 2)}
    with pp.KSPSolver(GAMG, max_it=5, structure=_structure(basis, bc, fields=fields)) as s:
        record = s.describe()
    assert (record["block_size"], record["near_nullspace"]) == (2, 3)
    assert record["fields"] == {"a": M.shape[0] // 2, "b": M.shape[0] // 2}


def test_a_petsc_nullspace_is_read_once():
    """``MatNullSpaceCreateRigidBody`` from node coordinates (interleaved, block size 2):
    the same space as `rigid_body_modes`, accepted as a spec and carried like it."""
    from petsc4py import PETSc

    basis, A = elasticity(n=4)
    coordinates = PETSc.Vec().createWithArray(basis.doflocs[:, ::2].T.ravel().copy())
    coordinates.setBlockSize(2)
    rigid = PETSc.NullSpace().createRigidBody(coordinates)
    K = A.matrix(np.ones(A.n_params))
    b = body_load(basis)
    out = []
    for spec in (rigid, pp.rigid_body_modes(basis)):
        with pp.KSPSolver(
            GAMG,
            max_it=500,
            rtol=1e-12,
            structure=pp.Structure(nullspace=spec, near_nullspace=spec),
        ) as s:
            s.set_operator(K)
            out.append(s.solve(b).value)
            with s.clone() as copy:
                assert copy.structure.nullspace.shape == (3, basis.N)
    np.testing.assert_allclose(out[0], out[1], atol=1e-9 * np.abs(out[1]).max())
