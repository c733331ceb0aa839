"""The library and the lab apart: what the library imports, what it needs installed,
and which names the lab may use.

The library is ``prdp_petsc`` without ``prdp_petsc.lab``; the lab (``prdp_petsc.lab``,
the ``lab`` extra) may use only the names ``prdp_petsc`` exports.
"""

import ast
import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

import prdp_petsc

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "prdp_petsc"
LAB = PACKAGE / "lab"
LIBRARY = sorted(p for p in PACKAGE.rglob("*.py") if LAB not in p.parents)
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def imported_modules(path: Path) -> list[tuple[str, list[str], int]]:
    """(absolute module, imported names, line) of every import in `path`."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts)
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(alias.name, [], node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")
            if node.level:
                base = base[: len(base) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module
            out.append((module, [alias.name for alias in node.names], node.lineno))
    return out


def test_the_library_imports_nothing_from_the_lab_nor_plotting_nor_progress_bars():
    offending = [
        f"{path.relative_to(ROOT)}:{line}: {module}"
        for path in LIBRARY
        for module, names, line in imported_modules(path)
        if module.startswith(("prdp_petsc.lab", "matplotlib", "tqdm"))
        or (module == "prdp_petsc" and "lab" in names)
    ]
    assert offending == []


def test_the_library_depends_on_the_numerical_stack_only():
    names = {
        d.split(">")[0].split("<")[0].split("=")[0] for d in PYPROJECT["project"]["dependencies"]
    }
    assert names == {"numpy", "scipy", "scikit-fem", "meshio", "torch", "petsc4py"}
    assert {"matplotlib", "tqdm"} <= {
        d.split(">")[0] for d in PYPROJECT["project"]["optional-dependencies"]["lab"]
    }


def test_the_lab_uses_only_the_librarys_public_names():
    """The lab's modules, the shipped scenes and the documented examples: names of the
    top level, or names a library module lists in its ``__all__``."""
    public = set(prdp_petsc.__all__)
    offending = []
    users = [*LAB.rglob("*.py"), *(ROOT / "demos").glob("*.py"), *(ROOT / "docs").rglob("*.py")]
    for path in sorted(users):
        for module, names, line in imported_modules(path):
            where = f"{path.relative_to(ROOT)}:{line}"
            if module == "prdp_petsc":
                offending += [f"{where}: {n}" for n in names if n not in public | {"lab"}]
            elif module.startswith("prdp_petsc.") and not module.startswith("prdp_petsc.lab"):
                exported = set(getattr(importlib.import_module(module), "__all__", ()))
                offending += [f"{where}: {module}.{n}" for n in names if n not in exported]
    assert offending == []


def test_the_top_level_is_what_a_training_loop_needs():
    """A short list to learn in minutes; every other public name lives in its module."""
    assert len(prdp_petsc.__all__) <= 25
    for name in ("KSPSolver", "Structure", "solve", "Dirichlet", "PRDP", "gradient_check"):
        assert name in prdp_petsc.__all__
    assert not hasattr(prdp_petsc, "laplacian")  # prdp_petsc.fem.fd.laplacian


def test_library_tests_do_not_import_the_lab():
    offending = [
        f"{path.name}:{line}: {module}"
        for path in sorted((ROOT / "tests").glob("*.py"))
        for module, names, line in imported_modules(path)
        if module.startswith("prdp_petsc.lab") or (module == "prdp_petsc" and "lab" in names)
    ]
    assert offending == []


# a capped solve and its gradient, in a process where matplotlib and tqdm cannot be imported
WITHOUT_LAB_PACKAGES = """
import importlib.abc, sys

class Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("matplotlib", "tqdm"):
            raise ModuleNotFoundError(f"No module named {name!r}")

sys.meta_path.insert(0, Absent())
import pkgutil, importlib
import prdp_petsc as pp
for info in pkgutil.walk_packages(pp.__path__, "prdp_petsc."):
    if not info.name.startswith("prdp_petsc.lab"):
        importlib.import_module(info.name)
import scipy.sparse as sp, torch
A = (sp.diags([-1, 2, -1], [-1, 0, 1], shape=(50, 50))).tocsr()
b = torch.ones(50, dtype=torch.float64, requires_grad=True)
with pp.KSPSolver({"ksp_type": "cg", "pc_type": "jacobi"}, max_it=5) as solver:
    sol = pp.solve(A, b, solver, return_solution=True)
    sol.value.square().sum().backward()
assert torch.isfinite(b.grad).all() and sol.iterations == 5 == sol.adjoint[0].iterations
assert "matplotlib" not in sys.modules and "tqdm" not in sys.modules
print("ok")
"""


def test_the_library_works_without_the_lab_packages():
    done = subprocess.run(
        [sys.executable, "-c", WITHOUT_LAB_PACKAGES], capture_output=True, text=True, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip() == "ok"


def test_names_that_moved_to_the_lab_say_where():
    import pytest

    moved = (
        ("Scene", "prdp_petsc.lab.Scene"),
        ("equal_accuracy_k", "accuracy"),
        ("NonlinearHeat", "demos/heat_nonlinear.py"),
    )
    for name, where in moved:
        with pytest.raises(AttributeError, match=f"moved out of the library: .*{where}"):
            getattr(prdp_petsc, name)
