# Two commands do all the set-up:  `make demo`  and  `make test`.
# `make test` runs pytest, builds the documentation (mkdocs --strict), then the MPI tests
# (all of tests/mpi on two ranks, the owned-layout tests also on three).
# Each creates .venv if needed and installs everything first.  The install is
# recorded in a stamp file keyed on the hash of pyproject.toml, constraints.txt and
# this Makefile, so a second run skips it and starts in seconds.  Every pip install
# here takes constraints.txt (the exact torch the project is tested with).
#
#   PRDP_PETSC_SKIP_PETSC=1   use an existing petsc4py (conda, system PETSc):
#                             the venv sees system site-packages and PETSc is
#                             not built.
#   PYTHON=python3.12         interpreter used to create .venv.
#   MPIEXEC=mpiexec           MPI launcher of the two-rank tests (tests/mpi).

SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
CONSTRAINTS := constraints.txt
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml $(CONSTRAINTS) Makefile | sha1sum | cut -c1-12)
DEB_PKGS := libopenmpi-dev openmpi-bin libopenblas-dev
PETSC_SPEC := petsc>=3.26,<3.27
PETSC4PY_SPEC := petsc4py>=3.26,<3.27
OUT ?= results
MPIEXEC ?= mpiexec
# Open MPI refuses root without the first two, and more ranks than cores without the third
MPI_ENV := OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OMPI_MCA_rmaps_base_oversubscribe=1

.PHONY: test demo setup lint bench docs pages clean petsc-cuda

test: $(STAMP)
	$(PY) -m pytest -q
	$(MAKE) --no-print-directory docs
	$(MPI_ENV) timeout 900 $(MPIEXEC) -n 2 $(PY) -m pytest -q -p no:cacheprovider tests/mpi
	$(MPI_ENV) timeout 600 $(MPIEXEC) -n 3 $(PY) -m pytest -q -p no:cacheprovider tests/mpi/test_owned.py

demo: $(STAMP)
	$(PY) -m prdp_petsc.lab.cli compare demos/heat.py --preset paper --routes cg/icc --out $(OUT)/heat2d

bench: $(STAMP)
	$(PY) -m prdp_petsc.lab.cli bench bridge --out $(OUT)

# The documentation site, into site/; any warning (a broken link, a docstring mkdocstrings
# cannot read) fails the build.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

# docs/results/ and the README's generated fragments, from the recorded data in docs/data/
pages: $(STAMP)
	$(PY) -m prdp_petsc.lab.cli pages --out docs/results

# PETSc with CUDA (sm_90) and petsc4py for Python 3.12, built on this machine (no GPU needed)
# into build/petsc-cuda/: the folder a GPU machine gets, run there by .ci/device-run.sh.  The
# build tree (several GB) stays in PETSC_CUDA_WORK.  Never part of `make test`.
PETSC_CUDA_WORK ?= $(or $(TMPDIR),/tmp)/petsc-cuda-work
petsc-cuda: $(STAMP)
	bash .ci/petsc-cuda.sh build/petsc-cuda $(PETSC_CUDA_WORK)

lint: $(STAMP)
	$(VENV)/bin/ruff check prdp_petsc tests demos meshes docs/examples
	$(VENV)/bin/ruff format --check prdp_petsc tests demos meshes docs/examples

setup: $(STAMP)

$(STAMP):
	@set -euo pipefail; \
	if [ "$${PRDP_PETSC_SKIP_PETSC:-0}" = 1 ]; then \
	  echo ">> PRDP_PETSC_SKIP_PETSC=1: using the petsc4py already installed"; \
	  [ -x $(PY) ] || $(PYTHON) -m venv --system-site-packages $(VENV); \
	else \
	  missing=""; \
	  for p in $(DEB_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	  if [ -n "$$missing" ]; then \
	    if [ "$$(id -u)" = 0 ]; then \
	      echo ">> installing Debian packages:$$missing"; \
	      apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	    else \
	      echo "!! PETSc needs the Debian packages:$$missing"; \
	      echo "!! run: sudo apt-get install$$missing   (or set PRDP_PETSC_SKIP_PETSC=1)"; \
	      exit 1; \
	    fi; \
	  fi; \
	  [ -x $(PY) ] || $(PYTHON) -m venv $(VENV); \
	fi; \
	$(PIP) install -q -c $(CONSTRAINTS) --upgrade pip wheel setuptools cython numpy; \
	if [ "$${PRDP_PETSC_SKIP_PETSC:-0}" != 1 ]; then \
	  if ! $(PY) -c "import petsc4py" 2>/dev/null; then \
	    echo ">> building PETSc 3.26 from PyPI (about 8 minutes the first time on this machine; pip caches the wheel)"; \
	    PETSC_CONFIGURE_OPTIONS="--with-fc=0 $${PETSC_CONFIGURE_OPTIONS:-}" $(PIP) install -q -c $(CONSTRAINTS) "$(PETSC_SPEC)"; \
	    $(PIP) install -q -c $(CONSTRAINTS) --no-build-isolation "$(PETSC4PY_SPEC)"; \
	  fi; \
	fi; \
	$(PIP) install -q -c $(CONSTRAINTS) torch; \
	$(PIP) install -q -c $(CONSTRAINTS) --no-build-isolation -e ".[lab,test,dev,mpi,docs]"; \
	$(PY) -c "import petsc4py, torch, skfem, prdp_petsc; from petsc4py import PETSc; \
	print('>> PETSc', '.'.join(map(str, PETSc.Sys.getVersion())), '| torch', torch.__version__, '| scikit-fem ok')"; \
	rm -f $(VENV)/.installed-*; touch $@

clean:
	rm -rf $(VENV) .pytest_cache results site
