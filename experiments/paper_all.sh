#!/usr/bin/env bash
# `make paper`: experiments/paper.py for every task, then the tables. With GPUs, each GPU runs
# its share of the tasks (round-robin) one after another, one process at a time: the tasks are
# independent, and a process per GPU scales, where splitting one task's lanes over GPUs did not
# (docs/BENCHMARKS.md, "Lanes over several GPUs"), nor did two processes sharing one GPU at the
# fitted model family's sizes (no faster than one after the other; "The 4-task protocol on
# one H100"). Without a GPU they run one after the other. Logs: OUT/paper_<task>.log.
#   bash experiments/paper_all.sh [OUT] [paper.py args]
# Environment: PY (the python command, default python3), TASKS (default the four),
# DATA_DIR (collected data, default OUT/data).
set -uo pipefail
OUT=${1:-results/paper}
shift || true
PY=${PY:-python3}
TASKS=${TASKS:-hopper walker2d halfcheetah ant}
DATA_DIR=${DATA_DIR:-$OUT/data}
mkdir -p "$OUT"
N_GPU=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)
run_task() {  # run_task TASK [paper.py args]: one task's paper.py run
  local t=$1
  shift
  $PY experiments/paper.py --task "$t" --out "$OUT" --data-dir "$DATA_DIR" "$@"
}
failed=0
if [ "${N_GPU:-0}" -gt 0 ]; then
  pids=()
  for ((g = 0; g < N_GPU; g++)); do
    mine=() i=0
    for t in $TASKS; do
      [ $((i % N_GPU)) = $g ] && mine+=("$t")
      i=$((i + 1))
    done
    [ ${#mine[@]} = 0 ] && continue
    (
      export CUDA_VISIBLE_DEVICES=$g
      rc=0
      for t in "${mine[@]}"; do run_task "$t" "$@" > "$OUT/paper_$t.log" 2>&1 || rc=1; done
      exit $rc
    ) &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait "$p" || failed=1; done
else
  for t in $TASKS; do
    run_task "$t" "$@" 2>&1 | tee "$OUT/paper_$t.log" || failed=1
  done
fi
[ "$failed" = 0 ] || { echo "paper_all: a task failed, see $OUT/paper_*.log" >&2; exit 1; }
$PY experiments/paper_tables.py --results "$OUT" --out "$OUT/tables.md"
