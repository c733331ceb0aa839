"""Load the shipped meshes (or any file meshio reads) as scikit-fem meshes.

The meshes in the repository's ``meshes/`` folder are made by
``meshes/generate.py`` (gmsh) and are addressed by bare name::

    >>> from prdp_petsc.fem.meshes import load_mesh
    >>> mesh = load_mesh("lshape", refine=1)  # doctest: +SKIP

A wheel ships them as package data (``prdp_petsc/meshes/*.msh``); a source
checkout (editable install) reads the repository's ``meshes/`` folder.  Set the
environment variable ``PRDP_PETSC_MESH_DIR`` to look for named meshes in another
folder.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import skfem

from ..errors import InputError, MeshError, plain

__all__ = ["available_meshes", "load_mesh", "mesh_dir", "min_angle_degrees"]

#: Environment variable that overrides the folder of named meshes.
MESH_DIR_ENV = "PRDP_PETSC_MESH_DIR"

# meshio cell type -> (scikit-fem mesh class, meshio type of its facets)
_SIMPLICES = {"tetra": (skfem.MeshTet1, "triangle"), "triangle": (skfem.MeshTri1, "line")}


def mesh_dir() -> Path:
    """Return the folder searched for named meshes.

    Returns
    -------
    pathlib.Path
        ``$PRDP_PETSC_MESH_DIR`` if set; else the package data folder
        ``prdp_petsc/meshes`` of an installed wheel if it holds meshes; else the
        repository's ``meshes/`` folder next to the ``prdp_petsc`` package (a source
        checkout or editable install).
    """
    override = os.environ.get(MESH_DIR_ENV)
    if override:
        return Path(override).expanduser().resolve()
    return _shipped_dir()


def _shipped_dir() -> Path:
    """The shipped meshes: package data in a wheel, ``meshes/`` in a source checkout."""
    from importlib.resources import files

    # A wheel maps the repository's meshes/ to prdp_petsc/meshes (see pyproject.toml).
    # Installed packages live on the file system, so the Traversable is a real path.
    packaged = Path(str(files("prdp_petsc") / "meshes"))
    if packaged.is_dir() and any(packaged.glob("*.msh")):
        return packaged
    return Path(__file__).resolve().parents[2] / "meshes"


def available_meshes() -> list[str]:
    """Return the sorted names of the ``.msh`` files in :func:`mesh_dir`."""
    folder = mesh_dir()
    return sorted(p.stem for p in folder.glob("*.msh")) if folder.is_dir() else []


def _resolve(name_or_path: str | os.PathLike) -> Path:
    """Map a bare mesh name or a file path to an existing file."""
    path = Path(name_or_path)
    is_name = isinstance(name_or_path, str) and path.suffix == "" and len(path.parts) == 1
    if is_name:
        shipped = mesh_dir() / f"{name_or_path}.msh"
        if shipped.is_file():
            return shipped
        raise FileNotFoundError(
            f"no mesh named {name_or_path!r} in {mesh_dir()}; available names: "
            f"{available_meshes()}; pass the path of a mesh file meshio reads, or set "
            f"{MESH_DIR_ENV} to a folder of <name>.msh files"
        )
    if not path.is_file():
        raise FileNotFoundError(
            f"mesh file {path} does not exist; shipped mesh names: {available_meshes()}"
        )
    return path


def _read(path: Path):
    """Read ``path`` with meshio, turning every way it can fail into a `MeshError`.

    ``.msh`` is tried as gmsh first, then as ANSYS, through those formats' own
    readers, which raise rather than print.  Any other file goes through
    ``meshio.read``, which on a file it cannot parse prints the reason and calls
    ``sys.exit(1)``; that exit, and whatever a parser raises on a malformed or
    truncated file (``ValueError``, ``KeyError``, ``IndexError``, ...), becomes a
    `MeshError` naming the file.  ``KeyboardInterrupt`` and ``MemoryError`` pass.
    """
    import meshio

    if path.stat().st_size == 0:
        raise MeshError(f"cannot read mesh file {path}: the file is empty")
    try:
        if path.suffix == ".msh":
            return _read_msh(path)
        return meshio.read(path)
    except (MeshError, MemoryError):
        raise
    except SystemExit:
        # meshio has printed its reason (to stdout and stderr) before exiting
        raise MeshError(
            f"cannot read mesh file {path}: meshio could not parse it as a "
            f"{path.suffix or 'suffix-less'} file (its reason is printed above)"
        ) from None
    except Exception as exc:
        raise MeshError(f"cannot read mesh file {path}: {_cause(exc)}") from exc


def _read_msh(path: Path):
    """Read a ``.msh`` file as gmsh, else as ANSYS; a `MeshError` names both failures."""
    import meshio

    try:
        return meshio.gmsh.read(str(path))
    except meshio.ReadError as exc:  # not gmsh at all; a malformed gmsh file raises others
        gmsh_error = exc
    try:
        return meshio.ansys.read(str(path))
    except MemoryError:
        raise
    except Exception as exc:
        raise MeshError(
            f"cannot read mesh file {path}: not a gmsh file ({_cause(gmsh_error)}), "
            f"and reading it as ANSYS failed ({_cause(exc)})"
        ) from exc


def _cause(exc: BaseException) -> str:
    """``ValueError: text`` for `exc`, or its type alone when it carries no message."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _simplex_part(m, path: Path):
    """Keep only the top-dimensional simplices and their facets from meshio mesh ``m``.

    Vertices, lower-dimensional cells and meshio's ``gmsh:*`` bookkeeping sets are
    dropped; vertices used by no top-dimensional cell are removed and the cells
    renumbered. Named physical groups survive as cell sets. ``path`` (the file ``m``
    was read from) only names the file in a `MeshError`.
    """
    import meshio

    kind = next((k for k in _SIMPLICES if k in m.cells_dict), None)
    if kind is None:
        raise MeshError(
            f"mesh file {path} has no triangle or tetra cells (found {sorted(m.cells_dict)}); "
            "only first-order simplex meshes are supported"
        )
    facet = _SIMPLICES[kind][1]
    keep = [i for i, block in enumerate(m.cells) if block.type in (kind, facet)]

    top = [m.cells[i].data.ravel() for i in keep if m.cells[i].type == kind]
    used = np.unique(np.concatenate(top))
    new_index = np.full(len(m.points), -1, dtype=np.int64)
    new_index[used] = np.arange(len(used))
    cells, blocks = [], []
    for i in keep:
        data = new_index[m.cells[i].data]
        if (data < 0).any():  # a facet off the mesh: drop the block rather than guess
            continue
        cells.append((m.cells[i].type, data))
        blocks.append(i)

    def select(per_block: dict) -> dict:
        return {
            k: [v[i] for i in blocks]
            for k, v in per_block.items()
            if not k.startswith("gmsh:") or k == "gmsh:physical"
        }

    points = m.points[used]
    if kind == "triangle" and points.shape[1] == 3:
        z = points[:, 2]
        scale = max(np.ptp(points[:, :2], axis=0).max(), 1.0)
        if np.ptp(z) > 1e-12 * scale:
            raise MeshError(
                f"triangle mesh {path} does not lie in a plane z = const; cannot make it 2D"
            )
        points = points[:, :2]
    return meshio.Mesh(
        points,
        cells,
        cell_data=select(m.cell_data),
        cell_sets=select(m.cell_sets),
        field_data=m.field_data,
    )


def load_mesh(name_or_path: str | os.PathLike, refine: int = 0) -> skfem.Mesh:
    """Load a shipped mesh by name, or any first-order simplex mesh file meshio reads.

    Parameters
    ----------
    name_or_path : str or os.PathLike
        A bare name such as ``"lshape"`` (see :func:`available_meshes`), resolved
        to ``<mesh_dir>/<name>.msh``, or a path to a mesh file.
    refine : int, optional
        Number of uniform refinements applied after loading (each splits every
        triangle into 4, every tetrahedron into 8). Default 0.

    Returns
    -------
    skfem.MeshTri1 or skfem.MeshTet1
        Triangle meshes come back two-dimensional (the z coordinate is dropped).
        Physical groups of the file become ``mesh.subdomains`` (cells) and
        ``mesh.boundaries`` (facets).

    Raises
    ------
    FileNotFoundError
        Unknown name (the message lists the available names) or missing file.
    prdp_petsc.errors.MeshError
        The file cannot be read: meshio cannot parse it (garbage, empty, truncated,
        a format it does not know; meshio's own ``sys.exit`` is caught), it holds
        no triangles or tetrahedra, or its triangles do not lie in a plane.  The
        message names the file and the cause.  A subclass of ``ValueError``.
    prdp_petsc.errors.InputError
        ``refine`` negative or not an integer (a ``ValueError`` too).

    Notes
    -----
    Vertices, lines of a 3D mesh and other lower-dimensional cells are dropped,
    as are vertices no element uses. scikit-fem keeps named boundaries through
    refinement of triangle meshes but not of tetrahedral ones.
    """
    if not isinstance(refine, int | np.integer) or refine < 0:
        raise InputError(f"refine must be a non-negative integer, got {plain(refine)!r}")
    from skfem.io.meshio import from_meshio

    path = _resolve(name_or_path)
    mesh = from_meshio(_simplex_part(_read(path), path))
    return mesh.refined(int(refine)) if refine else mesh


def min_angle_degrees(mesh: skfem.MeshTri1) -> float:
    """Return the smallest interior angle, in degrees, over all triangles of ``mesh``.

    Parameters
    ----------
    mesh : skfem.MeshTri1
        A two-dimensional triangle mesh.

    Returns
    -------
    float
        The minimum angle; below about 5 degrees a triangle is a sliver.
    """
    if mesh.p.shape[0] != 2 or mesh.t.shape[0] != 3:
        raise ValueError("min_angle_degrees needs a 2D triangle mesh (MeshTri1)")
    corners = mesh.p[:, mesh.t]  # (2, 3, nelems)
    smallest = np.inf
    for k in range(3):
        a = corners[:, (k + 1) % 3] - corners[:, k]
        b = corners[:, (k + 2) % 3] - corners[:, k]
        cos = np.sum(a * b, axis=0) / (np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0))
        smallest = min(smallest, float(np.arccos(np.clip(cos, -1.0, 1.0)).min()))
    return float(np.degrees(smallest))
