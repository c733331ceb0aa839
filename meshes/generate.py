"""Regenerate the meshes shipped in this folder with gmsh.

Run ``python meshes/generate.py`` (needs the optional ``gmsh`` dependency,
``pip install prdp-petsc[mesh]``). Every mesh is written as first-order
triangles or tetrahedra in gmsh's MSH 4.1 ASCII format, which meshio 5.3 reads
back, with physical groups for the domain and its boundary pieces:

==================  ===  ==================================================  =====================
name                dim  geometry                                            physical groups
==================  ===  ==================================================  =====================
``lshape``          2    [0, 1]^2 minus [0.5, 1] x [0.5, 1]                  domain, boundary
``annulus``         2    0.3 <= r <= 1                                       domain, inner, outer
``box3d``           3    unit cube [0, 1]^3                                  domain, boundary
``plate_holes``     2    [0, 2] x [0, 1] minus three discs                   domain, outer, holes
``sliver``          2    unit square; a strip of height 0.002 along y = 0    domain, strip, boundary
                         meshed with one layer of slivers (angles < 5 deg)
==================  ===  ==================================================  =====================

The meshes are deterministic: gmsh runs single-threaded with a fixed random
seed, and :func:`main` checks each file by reading it back with meshio.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: Holes of ``plate_holes``: (centre x, centre y, radius).
PLATE_HOLES = ((0.5, 0.5, 0.2), (1.2, 0.3, 0.15), (1.5, 0.7, 0.15))

#: Height of the sliver strip at the bottom of ``sliver`` and its node count along x.
SLIVER_STRIP = 0.002
SLIVER_NX = 17


def _start(gmsh, name: str, size: float) -> None:
    """Open a fresh gmsh model with the settings shared by every mesh."""
    gmsh.model.add(name)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.RandomSeed", 1)
    gmsh.option.setNumber("Mesh.ElementOrder", 1)
    gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay (2D)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay (3D)
    gmsh.option.setNumber("Mesh.MeshSizeMin", size)
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.Binary", 0)
    gmsh.option.setNumber("Mesh.SaveAll", 0)


def _group(gmsh, dim: int, tags: list[int], name: str) -> None:
    gmsh.model.addPhysicalGroup(dim, tags, name=name)


def _boundary_curves(gmsh, surfaces: list[int]) -> list[int]:
    dim_tags = gmsh.model.getBoundary([(2, s) for s in surfaces], oriented=False)
    return sorted({abs(tag) for _, tag in dim_tags})


def _finish(gmsh, dim: int, path: Path) -> None:
    gmsh.model.mesh.generate(dim)
    gmsh.write(str(path))
    gmsh.model.remove()


def lshape(gmsh, path: Path) -> None:
    """L-shaped domain [0, 1]^2 minus [0.5, 1] x [0.5, 1], area 0.75."""
    _start(gmsh, "lshape", 0.025)
    occ = gmsh.model.occ
    square = occ.addRectangle(0.0, 0.0, 0.0, 1.0, 1.0)
    corner = occ.addRectangle(0.5, 0.5, 0.0, 0.5, 0.5)
    (dom,), _ = occ.cut([(2, square)], [(2, corner)])
    occ.synchronize()
    _group(gmsh, 2, [dom[1]], "domain")
    _group(gmsh, 1, _boundary_curves(gmsh, [dom[1]]), "boundary")
    _finish(gmsh, 2, path)


def annulus(gmsh, path: Path) -> None:
    """Annulus 0.3 <= r <= 1 centred at the origin."""
    _start(gmsh, "annulus", 0.045)
    occ = gmsh.model.occ
    outer = occ.addDisk(0.0, 0.0, 0.0, 1.0, 1.0)
    inner = occ.addDisk(0.0, 0.0, 0.0, 0.3, 0.3)
    (dom,), _ = occ.cut([(2, outer)], [(2, inner)])
    occ.synchronize()
    _group(gmsh, 2, [dom[1]], "domain")
    inner_c, outer_c = [], []
    for c in _boundary_curves(gmsh, [dom[1]]):
        x0, y0, _, x1, y1, _ = gmsh.model.getBoundingBox(1, c)
        (inner_c if max(x1 - x0, y1 - y0) < 1.0 else outer_c).append(c)
    _group(gmsh, 1, inner_c, "inner")
    _group(gmsh, 1, outer_c, "outer")
    _finish(gmsh, 2, path)


def box3d(gmsh, path: Path) -> None:
    """Unit cube [0, 1]^3 in tetrahedra."""
    _start(gmsh, "box3d", 0.1)
    occ = gmsh.model.occ
    box = occ.addBox(0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    occ.synchronize()
    _group(gmsh, 3, [box], "domain")
    faces = gmsh.model.getBoundary([(3, box)], oriented=False)
    _group(gmsh, 2, sorted(abs(t) for _, t in faces), "boundary")
    _finish(gmsh, 3, path)


def plate_holes(gmsh, path: Path) -> None:
    """Rectangle [0, 2] x [0, 1] with the three discs of :data:`PLATE_HOLES` removed."""
    _start(gmsh, "plate_holes", 0.021)
    occ = gmsh.model.occ
    plate = occ.addRectangle(0.0, 0.0, 0.0, 2.0, 1.0)
    disks = [(2, occ.addDisk(x, y, 0.0, r, r)) for x, y, r in PLATE_HOLES]
    (dom,), _ = occ.cut([(2, plate)], disks)
    occ.synchronize()
    _group(gmsh, 2, [dom[1]], "domain")
    outer, holes = [], []
    for c in _boundary_curves(gmsh, [dom[1]]):
        x0, y0, _, x1, y1, _ = gmsh.model.getBoundingBox(1, c)
        on_edge = min(x0, y0) < 1e-9 or x1 > 2.0 - 1e-9 or y1 > 1.0 - 1e-9
        (outer if on_edge else holes).append(c)
    _group(gmsh, 1, outer, "outer")
    _group(gmsh, 1, holes, "holes")
    _finish(gmsh, 2, path)


def sliver(gmsh, path: Path) -> None:
    """Unit square whose bottom strip of height :data:`SLIVER_STRIP` is one layer of slivers.

    The strip is a transfinite (structured) surface with :data:`SLIVER_NX` nodes
    along x and two across, so its triangles have legs ``1 / (SLIVER_NX - 1)``
    and ``SLIVER_STRIP``: the smallest angle is ``atan(0.032)``, about 1.8
    degrees. The rest of the square is an ordinary unstructured mesh sharing the
    strip's top nodes.
    """
    h = 1.0 / (SLIVER_NX - 1)
    _start(gmsh, "sliver", h)
    geo = gmsh.model.geo
    s = SLIVER_STRIP
    pts = [geo.addPoint(x, y, 0.0) for x, y in [(0, 0), (1, 0), (1, s), (0, s), (1, 1), (0, 1)]]
    bottom = geo.addLine(pts[0], pts[1])
    right_s = geo.addLine(pts[1], pts[2])
    interface = geo.addLine(pts[2], pts[3])
    left_s = geo.addLine(pts[3], pts[0])
    right = geo.addLine(pts[2], pts[4])
    top = geo.addLine(pts[4], pts[5])
    left = geo.addLine(pts[5], pts[3])
    strip = geo.addPlaneSurface([geo.addCurveLoop([bottom, right_s, interface, left_s])])
    bulk = geo.addPlaneSurface([geo.addCurveLoop([-interface, right, top, left])])
    geo.synchronize()
    for c in (bottom, interface):
        gmsh.model.mesh.setTransfiniteCurve(c, SLIVER_NX)
    for c in (right_s, left_s):
        gmsh.model.mesh.setTransfiniteCurve(c, 2)
    gmsh.model.mesh.setTransfiniteSurface(strip, "Right")
    _group(gmsh, 2, [strip, bulk], "domain")
    _group(gmsh, 2, [strip], "strip")
    _group(gmsh, 1, [bottom, right_s, left_s, right, top, left], "boundary")
    _finish(gmsh, 2, path)


MESHES = {
    "lshape": lshape,
    "annulus": annulus,
    "box3d": box3d,
    "plate_holes": plate_holes,
    "sliver": sliver,
}


def _check(path: Path) -> str:
    """Read ``path`` back with meshio and summarise it."""
    import meshio

    m = meshio.read(path, file_format="gmsh")
    kind = "tetra" if "tetra" in m.cells_dict else "triangle"
    cells = m.cells_dict[kind]
    used = len(set(cells.ravel().tolist()))
    if used != len(m.points):
        raise RuntimeError(f"{path.name}: {len(m.points) - used} vertices unused by {kind} cells")
    return f"{path.name}: {len(m.points)} vertices, {len(cells)} {kind}"


def main(argv: list[str] | None = None) -> dict[str, str]:
    """Write the requested meshes (default: all) and return a summary per name."""
    import gmsh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help=f"meshes to build, of {sorted(MESHES)}")
    parser.add_argument("--out", type=Path, default=HERE, help="output folder")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(MESHES))
    if unknown:
        parser.error(f"unknown mesh names {unknown}; choose from {sorted(MESHES)}")
    args.out.mkdir(parents=True, exist_ok=True)

    summary = {}
    gmsh.initialize(readConfigFiles=False)
    try:
        for name in args.names or MESHES:
            path = args.out / f"{name}.msh"
            MESHES[name](gmsh, path)
            summary[name] = _check(path)
            print(summary[name])
    finally:
        gmsh.finalize()
    return summary


if __name__ == "__main__":
    main()
