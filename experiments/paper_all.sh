#!/usr/bin/env bash
# `make paper`: experiments/paper.py for every task, then the tables. With GPUs, the tasks run
# as concurrent processes, each pinned to one GPU round-robin (two per GPU share it through
# XLA_PYTHON_CLIENT_MEM_FRACTION): the tasks are independent, and a process per GPU scales,
# where splitting one task's lanes over GPUs did not (docs/BENCHMARKS.md, "Lanes over several
# GPUs"). Without a GPU they run one after the other. Logs: OUT/paper_<task>.log.
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
pids=()
i=0
for t in $TASKS; do
  if [ "${N_GPU:-0}" -gt 0 ]; then
    CUDA_VISIBLE_DEVICES=$((i % N_GPU)) XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.45} \
      $PY experiments/paper.py --task "$t" --out "$OUT" --data-dir "$DATA_DIR" "$@" \
      > "$OUT/paper_$t.log" 2>&1 &
    pids+=($!)
  else
    $PY experiments/paper.py --task "$t" --out "$OUT" --data-dir "$DATA_DIR" "$@" 2>&1 \
      | tee "$OUT/paper_$t.log" || exit 1
  fi
  i=$((i + 1))
done
failed=0
for p in "${pids[@]}"; do wait "$p" || failed=1; done
[ "$failed" = 0 ] || { echo "paper_all: a task failed, see $OUT/paper_*.log" >&2; exit 1; }
$PY experiments/paper_tables.py --results "$OUT" --out "$OUT/tables.md"
