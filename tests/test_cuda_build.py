"""The CUDA build's scripts, checked without CUDA.

``.ci/petsc-cuda.sh`` builds PETSc with CUDA into the folder a GPU machine is given, and
``.ci/device-run.sh`` runs a command there against it; neither can run here in full. What
can be checked on a CPU: both scripts parse, ``make petsc-cuda`` calls the build, the
toolkit pins are all CUDA 13.0 (what the GPU machines' driver runs), the packages carried
are enough to import the library beside numpy, scipy and torch alone, and the run
script's own logic (unpacking, paths, its refusals), on a folder made from the CPU build
of petsc4py.
"""

import importlib.metadata
import os
import re
import shutil
import subprocess
import sys
import tarfile
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BUILD = ROOT / ".ci" / "petsc-cuda.sh"
RUN = ROOT / ".ci" / "device-run.sh"
CHECK = ROOT / ".ci" / "device-check.sh"
PINS = ROOT / ".ci" / "cuda-toolkit.txt"

# CUDA 13.0's components: those versioned with the toolkit, and the maths libraries with
# their own numbers (the CUDA 13.0 release notes' table of component versions)
TOOLKIT_VERSIONED = {
    "nvidia-cuda-nvcc",
    "nvidia-cuda-crt",
    "nvidia-nvvm",
    "nvidia-cuda-runtime",
    "nvidia-cuda-cccl",
    "nvidia-nvjitlink",
    "nvidia-nvtx",
    "nvidia-cublas",
}
OWN_VERSION = {
    "nvidia-cusparse": "12.6",
    "nvidia-cusolver": "12.0",
    "nvidia-cufft": "12.0",
    "nvidia-curand": "10.4",
}
# what a GPU machine's Python is expected to have: the rest is carried
DEVICE_HAS = ("numpy", "scipy", "torch")


def pins() -> dict[str, str]:
    lines = [ln.strip() for ln in PINS.read_text().splitlines()]
    found = {}
    for line in lines:
        if not line or line.startswith("#"):
            continue
        name, sep, version = line.partition("==")
        assert sep and re.fullmatch(r"[\d.]+", version), f"not an exact pin: {line!r}"
        found[name] = version
    return found


@pytest.mark.parametrize("script", [BUILD, RUN, CHECK], ids=lambda p: p.name)
def test_scripts_parse(script):
    assert subprocess.run(["bash", "-n", str(script)]).returncode == 0


def test_make_target_runs_the_build():
    out = subprocess.run(
        ["make", "-n", "--no-print-directory", "petsc-cuda", "PETSC_CUDA_WORK=/scratch/w"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "bash .ci/petsc-cuda.sh build/petsc-cuda /scratch/w" in out.splitlines()


def test_toolkit_is_cuda_13_0_and_pinned_in_one_place():
    found = pins()
    assert set(found) == TOOLKIT_VERSIONED | set(OWN_VERSION)
    for name, version in found.items():
        series = "13.0" if name in TOOLKIT_VERSIONED else OWN_VERSION[name]
        assert version.startswith(series + "."), f"{name}=={version} is not CUDA 13.0's {series}"
    script = BUILD.read_text()
    assert '-r "$PINS"' in script and "PINS=$HERE/cuda-toolkit.txt" in script
    assert not re.search(r"nvidia-[\w-]+==", script), "a toolkit pin outside cuda-toolkit.txt"
    assert re.search(r"^CUDA_ARCH=90$", script, re.MULTILINE)  # sm_90: H100, H200


def carried() -> list[str]:
    m = re.search(r"^CARRY=\(([^)]*)\)$", BUILD.read_text(), re.MULTILINE)
    assert m, "no CARRY=(...) in petsc-cuda.sh"
    return m.group(1).split()


def test_carried_packages_complete_the_library():
    """With only the standard library, numpy, scipy, torch (and what torch requires),
    petsc4py and the carried packages importable, the library, scikit-fem and meshio import
    and a mesh file reads; an import of anything else fails, as on a bare GPU machine."""
    allowed_dists = {*DEVICE_HAS, "petsc4py"}
    for req in importlib.metadata.requires("torch") or []:
        allowed_dists.add(re.split(r"[\s;<>=!~\[]", req, maxsplit=1)[0])
    norm = {d.lower().replace("_", "-") for d in allowed_dists}
    allowed = {
        top
        for top, dists in importlib.metadata.packages_distributions().items()
        if any(d.lower().replace("_", "-") in norm for d in dists)
    }
    allowed |= set(carried()) | {"prdp_petsc"}
    probe = textwrap.dedent(
        f"""
        import importlib.abc, importlib.util, pkgutil, sys
        ALLOWED = {sorted(allowed)!r}
        blocked = set()

        class Device(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                top = name.partition(".")[0]
                if top in ALLOWED or top in sys.stdlib_module_names or top.startswith("_"):
                    return None
                blocked.add(top)
                raise ModuleNotFoundError(f"No module named {{name!r}} (not on the GPU machine)")

        sys.meta_path.insert(0, Device())
        import meshio, skfem, prdp_petsc
        for info in pkgutil.walk_packages(prdp_petsc.__path__, "prdp_petsc."):
            if not info.name.startswith("prdp_petsc.lab"):
                importlib.import_module(info.name)
        mesh = prdp_petsc.load_mesh("lshape")
        print("blocked:", sorted(blocked), "| mesh:", type(mesh).__name__)
        """
    )
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "| mesh: Mesh" in out.stdout


@pytest.fixture(scope="module")
def cpu_folder(tmp_path_factory):
    """A folder laid out as petsc-cuda.sh lays it out, from the CPU build of petsc4py (its
    files linked, not copied)."""
    petsc4py = pytest.importorskip("petsc4py")
    folder = tmp_path_factory.mktemp("petsc-cpu")
    lib = Path(petsc4py.get_config()["PETSC_DIR"]) / "lib"
    (folder / "lib").mkdir()
    for so in lib.glob("libpetsc.so.*"):
        (folder / "lib" / so.name).symlink_to(so)
    shutil.copytree(
        Path(petsc4py.__file__).parent, folder / "site" / "petsc4py", copy_function=os.symlink
    )
    return folder


def device_run(folder, *command, **env):
    full = {**os.environ, "PYTHON": sys.executable, **env}
    full.pop("LD_LIBRARY_PATH", None)
    return subprocess.run(
        ["bash", str(RUN), str(folder), *command],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=full,
    )


def test_device_run_uses_the_folder(cpu_folder, tmp_path):
    import petsc4py

    original = (Path(petsc4py.__file__).parent / "lib" / "petsc.cfg").read_text()
    report = tmp_path / "report.txt"
    code = (
        "import os, sys, petsc4py; "
        f"open({str(report)!r}, 'w').write(petsc4py.__file__ + '\\n' + "
        "os.environ['LD_LIBRARY_PATH']); sys.exit(7)"
    )
    out = device_run(cpu_folder, sys.executable, "-c", code, DEVICE_RUN_NEED_CUDA="0")
    assert out.returncode == 7, out.stdout + out.stderr  # the command's own status
    assert "cuda=False" in out.stdout
    where, ld_path = report.read_text().splitlines()
    assert Path(where).parent == cpu_folder / "site" / "petsc4py"
    assert ld_path.split(":")[0] == str(cpu_folder / "lib")
    cfg = cpu_folder / "site" / "petsc4py" / "lib" / "petsc.cfg"
    assert not cfg.is_symlink() and f"PETSC_DIR  = {cpu_folder}\n" in cfg.read_text()
    # the environment the folder was made from is untouched
    assert (Path(petsc4py.__file__).parent / "lib" / "petsc.cfg").read_text() == (original)


def test_device_run_refuses_a_petsc_without_cuda(cpu_folder, tmp_path):
    marker = tmp_path / "ran"
    out = device_run(cpu_folder, "touch", str(marker), DEVICE_RUN_CUDA_LIBS=str(tmp_path))
    assert out.returncode != 0 and not marker.exists()
    assert "built without CUDA" in out.stderr


def test_device_run_names_a_library_that_does_not_resolve(cpu_folder, tmp_path):
    folder = tmp_path / "broken"
    shutil.copytree(cpu_folder, folder, symlinks=True)
    for so in (folder / "lib").iterdir():
        so.unlink()
    marker = tmp_path / "ran"
    out = device_run(folder, "touch", str(marker), DEVICE_RUN_NEED_CUDA="0")
    assert out.returncode == 3 and not marker.exists()
    assert "needs libpetsc.so" in out.stderr


def test_device_run_unpacks_the_archive_beside_the_carried_folder(cpu_folder, tmp_path):
    name = re.search(r"^ARCHIVE=(\S+)", BUILD.read_text(), re.MULTILINE).group(1)
    assert f"archive=$DIR/{name}" in RUN.read_text()  # the name the build packs under
    carried = tmp_path / "petsc-cuda"
    carried.mkdir()
    with tarfile.open(carried / name, "w:gz") as tar:
        tar.add(cpu_folder / "lib", "lib")
        tar.add(cpu_folder / "site", "site")
    code = "import petsc4py; print('loaded', petsc4py.__file__)"
    out = device_run(carried, sys.executable, "-c", code, DEVICE_RUN_NEED_CUDA="0")
    assert out.returncode == 0, out.stdout + out.stderr
    unpacked = tmp_path / "petsc-cuda-unpacked"
    assert f"loaded {unpacked / 'site' / 'petsc4py' / '__init__.py'}" in out.stdout
    assert [p.name for p in carried.iterdir()] == [name]  # what is carried stays as it came
    again = device_run(carried, sys.executable, "-c", code, DEVICE_RUN_NEED_CUDA="0")
    assert again.returncode == 0 and "unpacking" not in again.stdout  # once per archive
