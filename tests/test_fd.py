"""Finite-difference Laplacians: stencils, spectra, ordering and second-order convergence."""

import numpy as np
import pytest
import scipy.sparse as sp

from prdp_petsc.fem.fd import grid_points, laplacian, second_difference


def observed_rate(hs, errors):
    """Slope of log(error) against log(h), fitted by least squares."""
    return np.polyfit(np.log(hs), np.log(errors), 1)[0]


@pytest.mark.parametrize(
    ("shape", "bc"),
    [(7, "dirichlet"), (7, "periodic"), ((4, 5), "dirichlet"), ((3, 4, 5), "periodic"),
     ((4, 6), ("dirichlet", "periodic")), ((3, 4, 5), ("periodic", "dirichlet", "periodic"))],
)  # fmt: skip
def test_symmetric_float64_csr(shape, bc):
    L = laplacian(shape, bc=bc)
    assert sp.issparse(L) and L.format == "csr" and L.dtype == np.float64
    assert L.shape == (np.prod(shape),) * 2
    assert abs(L - L.T).max() == 0.0


def test_dirichlet_eigenvalues_1d():
    n = 20
    h = 1.0 / (n + 1)
    k = np.arange(1, n + 1)
    exact = -4.0 / h**2 * np.sin(k * np.pi * h / 2) ** 2
    computed = np.linalg.eigvalsh(laplacian(n).toarray())
    np.testing.assert_allclose(np.sort(computed), np.sort(exact), rtol=1e-12)
    assert computed.max() < 0.0  # negative definite


def test_periodic_eigenvalues_1d():
    n = 16
    k = np.arange(n)
    exact = -4.0 * n**2 * np.sin(np.pi * k / n) ** 2
    computed = np.linalg.eigvalsh(laplacian(n, bc="periodic").toarray())
    np.testing.assert_allclose(np.sort(computed), np.sort(exact), atol=1e-9)


def test_2d_eigenvalues_are_sums():
    shape = (5, 7)
    L = laplacian(shape)
    lam = [np.linalg.eigvalsh(second_difference(n, 1.0 / (n + 1)).toarray()) for n in shape]
    exact = np.add.outer(lam[0], lam[1]).ravel()
    np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(L.toarray())), np.sort(exact))
    assert np.linalg.eigvalsh(L.toarray()).max() < 0.0


def test_dirichlet_rate_1d():
    ns = np.array([8, 16, 32, 64, 128])
    errors = []
    for n in ns:
        x = grid_points(n)[0]
        u = np.sin(np.pi * x)
        errors.append(np.abs(laplacian(n) @ u + np.pi**2 * u).max())
    rate = observed_rate(1.0 / (ns + 1), errors)
    assert 1.8 <= rate <= 2.2
    assert errors[-1] < 1e-3


def test_periodic_rate_1d():
    ns = np.array([8, 16, 32, 64, 128])
    errors = []
    for n in ns:
        x = grid_points(n, bc="periodic")[0]
        u = np.sin(2 * np.pi * x)
        errors.append(np.abs(laplacian(n, bc="periodic") @ u + 4 * np.pi**2 * u).max())
    assert 1.8 <= observed_rate(1.0 / ns, errors) <= 2.2


def test_mixed_rate_2d():
    # sin(pi x) sin(2 pi y): Dirichlet in x, periodic in y; also checks the ordering
    ns = np.array([8, 16, 32, 64])
    bc = ("dirichlet", "periodic")
    errors = []
    for n in ns:
        x, y = grid_points((n, n), bc=bc)
        u = np.sin(np.pi * x) * np.sin(2 * np.pi * y)
        errors.append(np.abs(laplacian((n, n), bc=bc) @ u + 5 * np.pi**2 * u).max())
    assert 1.8 <= observed_rate(1.0 / ns, errors) <= 2.2


def test_dirichlet_rate_3d():
    ns = np.array([6, 12, 24])
    errors = []
    for n in ns:
        x = grid_points((n, n, n))
        u = np.prod(np.sin(np.pi * x), axis=0)
        errors.append(np.abs(laplacian((n, n, n)) @ u + 3 * np.pi**2 * u).max())
    assert 1.8 <= observed_rate(1.0 / (ns + 1), errors) <= 2.2


def test_row_sums():
    L = laplacian((3, 4, 5), bc="periodic")
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0.0, atol=1e-9)
    D = laplacian(6)  # only the two rows next to the boundary lose a neighbour
    np.testing.assert_allclose(np.asarray(D.sum(axis=1)).ravel(), [-49, 0, 0, 0, 0, -49])


def test_nnz_and_diagonal():
    # Dirichlet: N + sum_d (N / n_d) * 2 (n_d - 1); periodic: 7 N for n_d >= 3
    assert laplacian(10).nnz == 3 * 10 - 2
    assert laplacian((4, 5)).nnz == 20 + 5 * 6 + 4 * 8
    assert laplacian((3, 4, 5)).nnz == 60 + 20 * 4 + 15 * 6 + 12 * 8
    assert laplacian((3, 4, 5), bc="periodic").nnz == 7 * 60
    L = laplacian((3, 4), spacing=(0.5, 0.25))
    np.testing.assert_allclose(L.diagonal(), -2 * (1 / 0.5**2 + 1 / 0.25**2))


def test_c_ordering():
    # last axis fastest: neighbour along axis 1 is +1, along axis 0 is +n1
    L = laplacian((3, 4), spacing=(0.5, 0.25))
    assert L[0, 1] == pytest.approx(16.0)
    assert L[0, 4] == pytest.approx(4.0)
    assert L[3, 4] == 0.0  # end of a row does not wrap (Dirichlet)
    x, y = grid_points((3, 4), spacing=(0.5, 0.25))
    np.testing.assert_allclose(x, np.repeat([0.5, 1.0, 1.5], 4))
    np.testing.assert_allclose(y, np.tile([0.25, 0.5, 0.75, 1.0], 3))


def test_grid_points():
    np.testing.assert_allclose(grid_points(4), [[0.2, 0.4, 0.6, 0.8]])
    np.testing.assert_allclose(grid_points(4, bc="periodic"), [[0.0, 0.25, 0.5, 0.75]])
    assert grid_points((2, 3, 4)).shape == (3, 24)


def test_small_periodic():
    np.testing.assert_allclose(laplacian(1, bc="periodic").toarray(), [[0.0]])
    np.testing.assert_allclose(laplacian(2, bc="periodic").toarray(), [[-8, 8], [8, -8]])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"shape": (2, 2, 2, 2)}, "1 to 3"),
        ({"shape": 0}, ">= 1"),
        ({"shape": 2.5}, ">= 1"),
        ({"shape": 4, "bc": "neumann"}, "bc must be"),
        ({"shape": (4, 4), "bc": ("dirichlet",)}, "bc must be"),
        ({"shape": 4, "spacing": -0.1}, "spacing"),
        ({"shape": (4, 4), "spacing": (0.1, 0.1, 0.1)}, "spacing"),
    ],
)
def test_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        laplacian(**kwargs)
