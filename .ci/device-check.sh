#!/usr/bin/env bash
# Issue 36's checks on a GPU machine: one command from the repository root against the folder
# `make petsc-cuda` built, writing logs and results into OUT, running the PHASEs named in turn:
#
#   bash .ci/device-check.sh build/petsc-cuda OUT tests overhead full
#
#   tests      tests/gpu: the CUDA path against the CPU path, named errors, a batch of 16
#              operators, the host-device copies of training steps, `bench gpu --preset quick`
#   transfers  the copies test again under -log_view (PETSc's GPU copy columns)
#   overhead   -log_view of the bridge alone and of raw petsc4py alone, on heat3d41 at K = 100
#   small      `bench gpu` on the two small problems (≈ 1 min)
#   full       `bench gpu`: the four problems, K = 10, 100, 300, the time to a 1e-6 gradient
#              with Jacobi CG and with GAMG (BUDGET_S, ROUNDS, CALLS); its JSON is written
#              after each problem, so a run cut short keeps what it measured.  On an H200 the
#              first three problems took 105 s and lshape9 (784 k) did not finish in the
#              rest of a 560 s call: give it a call of its own
#
# Each step has its own time limit and the run goes on past a failed step; the exit status
# is that of the first failure.
set -uo pipefail

DIR=${1:?usage: device-check.sh FOLDER OUT PHASE...}
OUT=${2:?usage: device-check.sh FOLDER OUT PHASE...}
shift 2
PHASES=("${@:-tests}")
mkdir -p "$OUT"
export PYTHON=${PYTHON:-python3} PYTHONUNBUFFERED=1
status=0
step() {  # step SECONDS LOG COMMAND...: COMMAND through device-run.sh, its output into OUT/LOG
  # (LOG "-": nowhere)
  local limit=$1 log=$OUT/$2
  shift 2
  [ "$log" != "$OUT/-" ] || log=/dev/null
  echo ">> device-check: $* (at most ${limit} s)"
  timeout "$limit" bash .ci/device-run.sh "$DIR" "$@" 2>&1 | tee "$log"
  local rc=${PIPESTATUS[0]}
  echo ">> device-check: exit status $rc"
  [ "$status" != 0 ] || status=$rc
}

for phase in "${PHASES[@]}"; do
  case $phase in
  tests)  # the CUDA path against the CPU path, errors, batches, host-device copies
    nvidia-smi >"$OUT/nvidia-smi.txt" 2>&1 || true
    step 240 pytest_gpu.log "$PYTHON" -m pytest -q -rA -p no:cacheprovider tests/gpu
    ;;
  transfers)  # the copies test again, under -log_view (PETSc's GPU copy columns)
    PETSC_OPTIONS="-log_view :$OUT/log_view_batch16.txt" \
      step 90 log_view_run.log "$PYTHON" -m pytest -q -p no:cacheprovider \
      tests/gpu/test_transfers_cuda.py
    ;;
  overhead)  # -log_view of the bridge and of raw petsc4py alone, same cell
    for who in prdp_petsc raw_petsc; do
      others=$(echo prdp_petsc prdp_petsc_sr raw_petsc raw_petsc_sr raw_petsc_transpose \
        jax_cg lineax_cg torch_pcg | tr ' ' '\n' | grep -vx "$who" | paste -sd,)
      PETSC_OPTIONS="-log_view :$OUT/log_view_$who.txt" \
        step 120 - "$PYTHON" -m prdp_petsc.lab.reports.bench_gpu --out "/tmp/overhead_$who" \
        --problems heat3d41 --k 100 --tol-problems '' --skip "$others" --rounds 2 --calls 5
    done
    ;;
  small)  # bench gpu on the two small problems
    step 200 bench_small.log "$PYTHON" -m prdp_petsc.lab.reports.bench_gpu --out "$OUT/small" \
      --problems lshape6,heat3d41 --tol-problems '' --rounds 3 --calls 3 --budget-s 120
    ;;
  full)  # bench gpu as its defaults say, but for --budget-s and the rounds
    step 540 bench_full.log "$PYTHON" -m prdp_petsc.lab.reports.bench_gpu --out "$OUT/bench" \
      --budget-s "${BUDGET_S:-360}" --rounds "${ROUNDS:-5}" --calls "${CALLS:-5}"
    ;;
  *)
    echo "!! unknown phase $phase (tests, transfers, overhead, small or full)" >&2
    exit 2
    ;;
  esac
done
exit "$status"
