#!/usr/bin/env bash
# Run a command on a GPU machine against the folder .ci/petsc-cuda.sh built (PETSc with CUDA,
# petsc4py, scikit-fem, meshio), from the repository root, installing nothing:
#
#   bash .ci/device-run.sh build/petsc-cuda python -m pytest -q tests/gpu
#   bash .ci/device-run.sh build/petsc-cuda                  (the checks alone)
#
# It unpacks the folder's petsc-cuda.tar.gz (once, into FOLDER-unpacked); puts its libraries
# and the CUDA 13 libraries of the Python's own torch wheels (site-packages/nvidia/*/lib) on
# LD_LIBRARY_PATH, and its packages and the repository on PYTHONPATH; points petsc4py's
# petsc.cfg at wherever it was unpacked; checks that every library libpetsc and petsc4py need resolves,
# that the petsc4py imported is the folder's, that its PETSc has CUDA and that prdp_petsc
# imports; prints the GPU nvidia-smi sees; then runs the command and returns its exit status.
# Any failed check stops it before the command, saying why.
#
#   PYTHON=python3            the interpreter of the checks (default: python, else python3);
#                             the command should use the same one
#   DEVICE_RUN_CUDA_LIBS=D1:D2  where the CUDA 13 libraries are, instead of torch's wheels
#   DEVICE_RUN_NEED_CUDA=0    accept a PETSc without CUDA: lets the script's own logic be
#                             tested on a CPU machine with a CPU build of petsc4py
set -euo pipefail

DIR=${1:?usage: device-run.sh FOLDER [COMMAND...]}
shift
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PYTHON=${PYTHON:-$(command -v python || command -v python3)}
NEED_CUDA=${DEVICE_RUN_NEED_CUDA:-1}
say() { echo ">> device-run: $*"; }

# the folder arrives packed (petsc-cuda.tar.gz): unpack it once per archive into FOLDER-unpacked,
# beside it, so that FOLDER stays what is carried
archive=$DIR/petsc-cuda.tar.gz
if [ -f "$archive" ]; then
  into=${DIR%/}-unpacked
  if [ ! -e "$into/.unpacked" ] || [ "$archive" -nt "$into/.unpacked" ]; then
    say "unpacking $archive into $into"
    rm -rf "$into" && mkdir -p "$into"
    "$PYTHON" -c 'import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter="tar")' \
      "$archive" "$into"
    touch "$into/.unpacked"
  fi
  DIR=$into
fi
[ -d "$DIR/lib" ] && [ -d "$DIR/site/petsc4py" ] ||
  { echo "!! $DIR is not a folder made by .ci/petsc-cuda.sh (no lib/ or site/petsc4py/)" >&2; exit 2; }
DIR=$(cd "$DIR" && pwd)

# the CUDA 13 libraries that torch's wheels installed (nvidia/cu13/lib, or nvidia/<lib>/lib),
# or the folders DEVICE_RUN_CUDA_LIBS names (a system toolkit's lib64, say)
nvidia_libs=${DEVICE_RUN_CUDA_LIBS:-$("$PYTHON" - <<'EOF'
import glob, importlib.util, os
spec = importlib.util.find_spec("nvidia")
roots = list(spec.submodule_search_locations) if spec and spec.submodule_search_locations else []
print(":".join(sorted(d for r in roots for d in glob.glob(os.path.join(r, "*", "lib")))))
EOF
)}
if [ -z "$nvidia_libs" ]; then
  say "no nvidia/*/lib under $PYTHON's site-packages (torch's CUDA libraries)"
  [ "$NEED_CUDA" = 0 ] || { echo "!! libpetsc's CUDA libraries cannot be found" >&2; exit 3; }
fi
export LD_LIBRARY_PATH=$DIR/lib${nvidia_libs:+:$nvidia_libs}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
export PYTHONPATH=$DIR/site:$ROOT${PYTHONPATH:+:$PYTHONPATH}
export PETSC_DIR=$DIR
unset PETSC_ARCH

cfg=$DIR/site/petsc4py/lib/petsc.cfg
rm -f "$cfg"  # a fresh file, never written through a link
printf 'PETSC_DIR  = %s\nPETSC_ARCH = \n' "$DIR" >"$cfg"

missing=$(for so in "$DIR"/lib/libpetsc.so.* "$DIR"/site/petsc4py/lib/PETSc.*.so; do
  out=$(ldd "$so" 2>&1) || { echo "   ${so##*/}: $out"; continue; }
  echo "$out" | awk -v so="${so##*/}" '/not found/ {print "   " so " needs " $1}'
done)
if [ -n "$missing" ]; then
  echo "!! libraries that do not resolve, with LD_LIBRARY_PATH=$LD_LIBRARY_PATH" >&2
  echo "$missing" >&2
  exit 3
fi

"$PYTHON" - "$DIR" "$NEED_CUDA" <<'EOF'
import os, sys
folder, need_cuda = sys.argv[1], sys.argv[2] != "0"
import petsc4py
from petsc4py import PETSc
where = os.path.dirname(petsc4py.__file__)
if os.path.realpath(where) != os.path.realpath(os.path.join(folder, "site", "petsc4py")):
    sys.exit(f"!! petsc4py came from {where}, not from {folder}/site")
cuda = PETSc.Sys.hasExternalPackage("cuda")
version = ".".join(map(str, PETSc.Sys.getVersion()))
print(f">> device-run: PETSc {version} from {where}, cuda={cuda}, Python {sys.version.split()[0]}")
if need_cuda and not cuda:
    sys.exit("!! this PETSc was built without CUDA (set DEVICE_RUN_NEED_CUDA=0 to go on)")
import meshio, numpy, scipy, skfem, torch  # the machine's own, and the carried ones
from prdp_petsc import KSPSolver, load_mesh  # the library's modules load on first use

print(
    f">> device-run: prdp_petsc from {os.path.dirname(sys.modules['prdp_petsc'].__file__)},"
    f" torch {torch.__version__} (cuda available: {torch.cuda.is_available()}),"
    f" numpy {numpy.__version__}, scipy {scipy.__version__}, scikit-fem from"
    f" {os.path.dirname(skfem.__file__)}"
)
EOF

if command -v nvidia-smi >/dev/null; then
  say "GPU: $(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | head -1)"
else
  say "no nvidia-smi on this machine"
fi

[ $# -gt 0 ] || exit 0
say "running: $*"
exec "$@"
