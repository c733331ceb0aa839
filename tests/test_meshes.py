"""The shipped meshes load with the right dimension, size, geometry and boundary tags."""

import shutil

import meshio
import numpy as np
import pytest
import skfem

from prdp_petsc.errors import MeshError
from prdp_petsc.fem.meshes import (
    MESH_DIR_ENV,
    available_meshes,
    load_mesh,
    mesh_dir,
    min_angle_degrees,
)

# Geometry of meshes/generate.py: the holes of plate_holes are (x, y, r).
PLATE_HOLES = ((0.5, 0.5, 0.2), (1.2, 0.3, 0.15), (1.5, 0.7, 0.15))
ANNULUS = (0.3, 1.0)

# name: (dimension, boundary names, vertex range, exact area or volume)
SHIPPED = {
    "lshape": (2, {"boundary"}, (1000, 3000), 0.75),
    "annulus": (2, {"inner", "outer"}, (1000, 3000), np.pi * (ANNULUS[1] ** 2 - ANNULUS[0] ** 2)),
    "box3d": (3, {"boundary"}, (1000, 4000), 1.0),
    "plate_holes": (
        2,
        {"outer", "holes"},
        (3000, 5000),
        2.0 - np.pi * sum(r**2 for _, _, r in PLATE_HOLES),
    ),
    "sliver": (2, {"boundary"}, (100, 500), 1.0),
}


def signed_volumes(p, t):
    """Signed areas (triangles) or volumes (tetrahedra) of the cells ``t`` of points ``p``."""
    e = [p[:, t[k]] - p[:, t[0]] for k in range(1, t.shape[0])]
    if t.shape[0] == 3:
        return 0.5 * (e[0][0] * e[1][1] - e[0][1] * e[1][0])
    return np.einsum("ij,ij->j", e[0], np.cross(e[1].T, e[2].T).T) / 6.0


def volumes(mesh):
    # scikit-fem sorts the vertices of each cell, so only |volume| is meaningful.
    return np.abs(signed_volumes(mesh.p, mesh.t))


def segment_area(mesh, facets, radius):
    """Area between the chords ``facets`` and the circle of ``radius`` they are inscribed in."""
    ends = mesh.p[:, mesh.facets[:, facets]]
    chord = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=0)
    theta = 2.0 * np.arcsin(chord / (2.0 * radius))
    return float(np.sum(0.5 * radius**2 * (theta - np.sin(theta))))


def test_available_meshes_lists_shipped():
    assert available_meshes() == sorted(SHIPPED)


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_shipped_mesh(name):
    dim, boundaries, (lo, hi), measure = SHIPPED[name]
    mesh = load_mesh(name)
    assert isinstance(mesh, skfem.MeshTet1 if dim == 3 else skfem.MeshTri1)
    assert mesh.p.shape[0] == dim
    assert lo <= mesh.nvertices <= hi <= 5000
    # every vertex belongs to an element
    assert np.unique(mesh.t).size == mesh.nvertices
    vol = volumes(mesh)
    assert vol.min() > 0.0
    if name not in ("annulus", "plate_holes"):  # polygonal domains are exact
        assert vol.sum() == pytest.approx(measure, rel=1e-12)
    # every boundary facet carries exactly one of the named physical groups
    assert set(mesh.boundaries) == boundaries
    tagged = np.concatenate([np.asarray(mesh.boundaries[b]) for b in boundaries])
    np.testing.assert_array_equal(np.sort(tagged), mesh.boundary_facets())


def test_shipped_files_positively_oriented():
    for name in SHIPPED:
        raw = meshio.read(mesh_dir() / f"{name}.msh", file_format="gmsh")
        kind = "tetra" if "tetra" in raw.cells_dict else "triangle"
        dim = 3 if kind == "tetra" else 2
        signed = signed_volumes(raw.points.T[:dim], raw.cells_dict[kind].T)
        assert signed.min() > 0.0, name


def test_annulus_geometry():
    inner, outer = ANNULUS
    mesh = load_mesh("annulus")
    for name, r in (("inner", inner), ("outer", outer)):
        radii = np.linalg.norm(mesh.p[:, mesh.facets[:, mesh.boundaries[name]]], axis=0)
        np.testing.assert_allclose(radii, r, rtol=1e-10)
    # polygon area + circular segments outside - segments of the hole = exact area
    area = volumes(mesh).sum()
    area += segment_area(mesh, mesh.boundaries["outer"], outer)
    area -= segment_area(mesh, mesh.boundaries["inner"], inner)
    assert area == pytest.approx(SHIPPED["annulus"][3], rel=1e-10)
    assert volumes(mesh).sum() == pytest.approx(SHIPPED["annulus"][3], rel=1e-3)


def test_plate_holes_geometry():
    mesh = load_mesh("plate_holes")
    holes = np.asarray(mesh.boundaries["holes"])
    mid = mesh.p[:, mesh.facets[:, holes]].mean(axis=1)
    centres = np.array([[x, y] for x, y, _ in PLATE_HOLES]).T
    nearest = np.argmin(np.linalg.norm(mid[:, :, None] - centres[:, None, :], axis=0), axis=1)
    area = volumes(mesh).sum()
    for k, (x, y, r) in enumerate(PLATE_HOLES):
        on_k = holes[nearest == k]
        ends = mesh.p[:, mesh.facets[:, on_k]] - np.array([x, y])[:, None, None]
        np.testing.assert_allclose(np.linalg.norm(ends, axis=0), r, rtol=1e-10)
        area -= segment_area(mesh, on_k, r)
    assert area == pytest.approx(SHIPPED["plate_holes"][3], rel=1e-10)
    ends = mesh.p[:, mesh.facets[:, mesh.boundaries["outer"]]]
    on_edge = np.isclose(ends[0], 0) | np.isclose(ends[0], 2) | np.isclose(ends[1], 0)
    assert np.all(on_edge | np.isclose(ends[1], 1))


def test_plate_holes_refined_is_benchmark_size():
    mesh = load_mesh("plate_holes", refine=2)
    assert 6e4 <= mesh.nvertices <= 8e4
    assert volumes(mesh).sum() == pytest.approx(volumes(load_mesh("plate_holes")).sum(), rel=1e-12)


def test_sliver_has_slivers():
    mesh = load_mesh("sliver")
    assert min_angle_degrees(mesh) < 5.0
    assert min_angle_degrees(mesh) == pytest.approx(np.degrees(np.arctan(0.002 * 16)), rel=1e-6)
    assert len(mesh.subdomains["strip"]) == 2 * 16
    for name in ("lshape", "annulus", "plate_holes"):
        assert min_angle_degrees(load_mesh(name)) > 20.0


def test_min_angle_of_right_triangles():
    assert min_angle_degrees(skfem.MeshTri()) == pytest.approx(45.0, rel=1e-12)
    with pytest.raises(ValueError, match="2D triangle"):
        min_angle_degrees(skfem.MeshTet())


@pytest.mark.parametrize(("name", "factor"), [("lshape", 4), ("sliver", 4), ("box3d", 8)])
def test_refine_multiplies_elements(name, factor):
    coarse = load_mesh(name)
    for r in (1, 2):
        fine = load_mesh(name, refine=r)
        assert fine.nelements == factor**r * coarse.nelements
        assert volumes(fine).sum() == pytest.approx(volumes(coarse).sum(), rel=1e-12)
    assert set(load_mesh("lshape", refine=1).boundaries) == {"boundary"}


def test_unknown_name_lists_available():
    with pytest.raises(FileNotFoundError, match="lshape") as info:
        load_mesh("no_such_mesh")
    assert "available names" in str(info.value)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_mesh("/nonexistent/dir/x.msh")
    with pytest.raises(ValueError, match="refine"):
        load_mesh("lshape", refine=-1)


def test_path_and_env_override(tmp_path, monkeypatch):
    shutil.copy(mesh_dir() / "sliver.msh", tmp_path / "other.msh")
    by_path = load_mesh(tmp_path / "other.msh")
    assert by_path.nvertices == load_mesh("sliver").nvertices
    monkeypatch.setenv(MESH_DIR_ENV, str(tmp_path))
    assert available_meshes() == ["other"]
    assert load_mesh("other").nelements == by_path.nelements
    with pytest.raises(FileNotFoundError, match="other"):
        load_mesh("lshape")


def test_other_formats_drop_extras(tmp_path):
    # a 3D-embedded planar triangle mesh with a stray point, a vertex cell and lines
    points = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 0]], dtype=float)
    cells = [
        ("vertex", np.array([[4]])),
        ("line", np.array([[0, 1], [1, 2]])),
        ("triangle", np.array([[0, 1, 2], [0, 2, 3]])),
    ]
    meshio.write(tmp_path / "square.vtu", meshio.Mesh(points, cells))
    mesh = load_mesh(str(tmp_path / "square.vtu"))
    assert isinstance(mesh, skfem.MeshTri1)
    assert mesh.p.shape == (2, 4)
    assert volumes(mesh).sum() == pytest.approx(1.0)

    points[0, 2] = 0.5  # no longer planar
    meshio.write(tmp_path / "bent.vtu", meshio.Mesh(points, cells))
    with pytest.raises(MeshError, match="bent.vtu does not lie in a plane"):
        load_mesh(tmp_path / "bent.vtu")
    meshio.write(tmp_path / "lines.vtu", meshio.Mesh(points, cells[:2]))
    with pytest.raises(MeshError, match="lines.vtu has no triangle or tetra"):
        load_mesh(tmp_path / "lines.vtu")


# file name: (content, what the message must say about the cause)
UNREADABLE = {
    "garbage.msh": (b"garbage\nnot a mesh\n", "not a gmsh file"),
    "empty.msh": (b"", "empty"),
    "empty.vtu": (b"", "empty"),
    "garbage.vtu": (b"<VTKFile>\n", "could not parse it as a .vtu file"),
    "mesh.unknown": (b"0 0 0\n", "Could not deduce file format"),
}


@pytest.mark.parametrize("name", sorted(UNREADABLE))
def test_unreadable_file_raises_mesh_error(tmp_path, name):
    # meshio itself calls sys.exit(1) on several of these; load_mesh must raise instead
    content, cause = UNREADABLE[name]
    path = tmp_path / name
    path.write_bytes(content)
    try:
        load_mesh(path)
    except MeshError as error:
        assert str(path) in str(error)
        assert cause in str(error)
        assert isinstance(error, ValueError)  # code that catches ValueError keeps working
    except SystemExit:  # pragma: no cover - the failure this test guards against
        pytest.fail(f"load_mesh({name}) exited the process")
    else:  # pragma: no cover
        pytest.fail(f"load_mesh({name}) read an unreadable file")


@pytest.mark.parametrize("name", sorted(SHIPPED))
@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_truncated_shipped_mesh_raises_mesh_error(tmp_path, name, fraction):
    data = (mesh_dir() / f"{name}.msh").read_bytes()
    path = tmp_path / f"{name}.msh"
    path.write_bytes(data[: int(fraction * len(data))])
    try:
        load_mesh(path)
    except MeshError as error:
        assert str(path) in str(error)
    except SystemExit:  # pragma: no cover
        pytest.fail(f"load_mesh of a truncated {name}.msh exited the process")
    else:  # pragma: no cover
        pytest.fail(f"load_mesh read a truncated {name}.msh")


def test_keyboard_interrupt_is_not_a_mesh_error(tmp_path, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(meshio.gmsh, "read", interrupted)
    monkeypatch.setattr(meshio, "read", interrupted)
    shutil.copy(mesh_dir() / "sliver.msh", tmp_path / "sliver.msh")
    (tmp_path / "square.vtu").write_bytes(b"<VTKFile>\n")
    for name in ("sliver.msh", "square.vtu"):
        with pytest.raises(KeyboardInterrupt):
            load_mesh(tmp_path / name)
