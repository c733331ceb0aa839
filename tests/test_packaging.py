"""Packaging: the wheel ships every package and the meshes; licence, build floor, torch pin."""

import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from prdp_petsc.fem import meshes
from prdp_petsc.fem.meshes import MESH_DIR_ENV, available_meshes, load_mesh, mesh_dir

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
MESHES = sorted(p.name for p in (ROOT / "meshes").glob("*.msh"))


def test_every_package_is_listed():
    on_disk = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for p in (ROOT / "prdp_petsc").rglob("__init__.py")
    }
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    assert listed == on_disk | {"prdp_petsc.meshes"}
    assert PYPROJECT["tool"]["setuptools"]["package-dir"] == {"prdp_petsc.meshes": "meshes"}
    assert len(MESHES) == 5


def test_license_and_build_floor():
    assert PYPROJECT["project"]["license"] == "MIT"
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "2026 the prdp_petsc developers" in text
    (setuptools,) = [r for r in PYPROJECT["build-system"]["requires"] if r.startswith("setuptools")]
    floor = re.fullmatch(r"setuptools>=(\d+)(\.\d+)*", setuptools)
    assert floor and int(floor.group(1)) >= 77  # first to accept an SPDX license string


def test_torch_pinned_by_make_not_by_the_library():
    (torch,) = [d for d in PYPROJECT["project"]["dependencies"] if d.startswith("torch")]
    assert "==" not in torch
    constraints = (ROOT / "constraints.txt").read_text().split("\n")
    assert any(re.fullmatch(r"torch==[\d.]+", line) for line in constraints)
    makefile = (ROOT / "Makefile").read_text()
    installs = re.findall(r"\$\(PIP\) install[^;\n]*", makefile)
    assert installs and all("-c $(CONSTRAINTS)" in line for line in installs)
    assert "CONSTRAINTS := constraints.txt" in makefile
    assert "torch==" not in makefile  # one pin, in constraints.txt


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """Build the wheel from a copy of the sources (nothing is written to the checkout)."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "prdp_petsc", src / "prdp_petsc", ignore=ignore)
    shutil.copytree(ROOT / "meshes", src / "meshes", ignore=ignore)
    dist = tmp_path_factory.mktemp("dist")
    cmd = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation"]
    done = subprocess.run([*cmd, "-w", str(dist), str(src)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    (path,) = dist.glob("prdp_petsc-*.whl")
    return path


def test_wheel_contents(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    shipped = sorted(n.split("/")[-1] for n in names if n.startswith("prdp_petsc/meshes/"))
    assert [n for n in shipped if n.endswith(".msh")] == MESHES
    modules = {str(p.relative_to(ROOT)) for p in (ROOT / "prdp_petsc").rglob("*.py")}
    assert modules <= set(names)
    assert "prdp_petsc/lab/reports/templates/page.md.j2" in names  # the results pages
    assert any(re.fullmatch(r"prdp_petsc-[^/]+\.dist-info/licenses/LICENSE", n) for n in names)
    metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(metadata).decode()
    assert "License-Expression: MIT" in text
    requires = [line for line in text.split("\n") if line.startswith("Requires-Dist: torch")]
    assert requires == ["Requires-Dist: torch>=2.1"]


def test_installed_wheel_finds_its_meshes(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)  # what pip install puts in site-packages
    code = (
        "import prdp_petsc.fem.meshes as m\n"
        "print(m.__file__)\nprint(m.mesh_dir())\nprint(','.join(m.available_meshes()))\n"
        "print(m.load_mesh('lshape').nvertices)"
    )
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    module_file, folder, names, nvertices = done.stdout.split("\n")[:4]
    assert Path(module_file).is_relative_to(site)
    assert Path(folder) == site / "prdp_petsc" / "meshes"
    assert names.split(",") == [m.removesuffix(".msh") for m in MESHES]
    assert int(nvertices) == load_mesh("lshape").nvertices


def test_mesh_dir_prefers_package_data(tmp_path, monkeypatch):
    # an installed layout: <site>/prdp_petsc/meshes/*.msh
    package = tmp_path / "prdp_petsc"
    (package / "meshes").mkdir(parents=True)
    shutil.copy(ROOT / "meshes" / "sliver.msh", package / "meshes" / "sliver.msh")
    monkeypatch.delenv(MESH_DIR_ENV, raising=False)
    monkeypatch.setattr("importlib.resources.files", lambda name: package)
    assert mesh_dir() == package / "meshes"
    assert available_meshes() == ["sliver"]
    (package / "meshes" / "sliver.msh").unlink()  # no meshes there: the checkout's folder
    assert mesh_dir() == ROOT / "meshes"
    monkeypatch.setenv(MESH_DIR_ENV, str(tmp_path))
    assert mesh_dir() == tmp_path.resolve()


def test_checkout_finds_repository_meshes(monkeypatch):
    monkeypatch.delenv(MESH_DIR_ENV, raising=False)
    assert mesh_dir() == ROOT / "meshes"
    assert [f"{n}.msh" for n in available_meshes()] == MESHES
    assert meshes.MESH_DIR_ENV == "PRDP_PETSC_MESH_DIR"


def test_unknown_mesh_names_the_choices_and_the_variable():
    with pytest.raises(FileNotFoundError) as info:
        load_mesh("no_such_mesh")
    message = str(info.value)
    assert "'no_such_mesh'" in message and MESH_DIR_ENV in message
    for name in MESHES:
        assert name.removesuffix(".msh") in message
