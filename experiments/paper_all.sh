#!/usr/bin/env bash
# `make paper`: experiments/paper.py for every task, then the tables. experiments/
# paper_schedule.py runs them. With two GPUs or more the units are (task, family) pairs
# (paper.py --families F): one queue, costliest first, a GPU that comes free takes the next
# ready unit, one process per GPU at a time (two processes training at once on one GPU only
# split it: docs/BENCHMARKS.md, "Two processes on one GPU"); a task's data
# is collected once, by its first unit, and its other unit starts only after that unit's data
# phase; then merge_results.py joins each task's units into OUT/<task>.json. With one GPU or
# none each task is one paper.py (both families): on one GPU two at a time by default
# (PAPER_PER_GPU=auto: the same results, 865 s against 1,103 s for two tasks on an H200),
# without one, one after another. The wall time per unit and in all: printed and
# OUT/schedule.json. Logs: OUT/paper_<task>[_<family>].log. A failed unit fails the run
# (exit 1, no tables) after the others have run, naming it and its log.
#   bash experiments/paper_all.sh [OUT] [paper.py args]
# Environment: PY (the python command, default python3), TASKS (default the four),
# DATA_DIR (collected data, default OUT/data), RL2S_GPUS (the GPU count, default nvidia-smi's;
# with CUDA_VISIBLE_DEVICES set, its first RL2S_GPUS ids are the GPUs used),
# PAPER_UNITS=task|family|auto (auto, the default: a whole task per unit when there are
# at least as many GPUs as tasks and fewer than twice as many, else (task, family) pairs),
# PAPER_PER_GPU=K|auto (K paper.py processes per GPU at once; auto, the default: 2 on one
# GPU with two tasks or more, else 1).
set -uo pipefail
OUT=${1:-results/paper}
shift || true
PY=${PY:-python3}
TASKS=${TASKS:-hopper walker2d halfcheetah ant}
DATA_DIR=${DATA_DIR:-$OUT/data}
mkdir -p "$OUT"
N_GPU=${RL2S_GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)}
# the scheduler needs only the standard library: python3, not $PY (which may be a prefix such
# as device.sh's `timeout 560 python3`, meant for each paper.py)
python3 experiments/paper_schedule.py --out "$OUT" --data-dir "$DATA_DIR" --gpus "${N_GPU:-0}" \
  --py "$PY" --tasks "$TASKS" -- "$@" || exit 1
$PY experiments/paper_tables.py --results "$OUT" --out "$OUT/tables.md"
