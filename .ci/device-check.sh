#!/usr/bin/env bash
# Issue 36's checks on a GPU machine, in two phases, each one command from the repository root
# against the folder `make petsc-cuda` built (build/petsc-cuda), writing its logs and results
# into OUT:
#
#   bash .ci/device-check.sh build/petsc-cuda OUT quick   (≈ 2–3 min)
#       tests/gpu (CUDA path = CPU path, errors, the 16-operator batch, the host-device copies
#       of training steps, `bench gpu --preset quick` on CUDA types), the same copies test
#       under -log_view, and `bench gpu` on the two small problems
#   bash .ci/device-check.sh build/petsc-cuda OUT full    (≈ 7–9 min)
#       `bench gpu` with its defaults: the four problems, K = 10, 100, 300, the time to a
#       1e-6 gradient with Jacobi CG and with GAMG; OUT/bench/bench_gpu.json is written after
#       each problem, so a run cut short keeps what it measured
#
# Each step has its own time limit and the phase goes on past a failed step; the exit status
# is that of the first failure.
set -uo pipefail

DIR=${1:?usage: device-check.sh FOLDER OUT quick|full}
OUT=${2:?usage: device-check.sh FOLDER OUT quick|full}
PHASE=${3:-quick}
mkdir -p "$OUT"
export PYTHON=${PYTHON:-python3} PYTHONUNBUFFERED=1
status=0
step() {  # step SECONDS LOG COMMAND...: run COMMAND through device-run.sh, its output into LOG
  local limit=$1 log=$2
  shift 2
  echo ">> device-check: $* (at most ${limit} s)"
  timeout "$limit" bash .ci/device-run.sh "$DIR" "$@" 2>&1 | tee "$OUT/$log"
  local rc=${PIPESTATUS[0]}
  echo ">> device-check: exit status $rc"
  [ "$status" != 0 ] || status=$rc
}

case $PHASE in
quick)
  nvidia-smi >"$OUT/nvidia-smi.txt" 2>&1 || true
  step 240 pytest_gpu.log "$PYTHON" -m pytest -q -rA -p no:cacheprovider tests/gpu
  PETSC_OPTIONS="-log_view :$OUT/log_view_batch16.txt" \
    step 90 log_view_run.log "$PYTHON" -m pytest -q -p no:cacheprovider tests/gpu/test_transfers_cuda.py
  step 200 bench_small.log "$PYTHON" -m prdp_petsc.lab.reports.bench_gpu --out "$OUT/small" \
    --problems lshape6,heat3d41 --tol-problems '' --rounds 3 --calls 3 --budget-s 120
  ;;
full)
  step 540 bench_full.log "$PYTHON" -m prdp_petsc.lab.reports.bench_gpu --out "$OUT/bench" \
    --budget-s "${BUDGET_S:-360}"
  ;;
*)
  echo "!! unknown phase $PHASE (quick or full)" >&2
  exit 2
  ;;
esac
exit "$status"
