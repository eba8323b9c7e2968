#!/usr/bin/env bash
# Several tasks of the paper's protocol at once on the GPU machine (run through the device tool
# with .whl carried): one experiments/paper.py process per task, spread round-robin over the
# visible GPUs (each process sees one), all sharing the data dir $W. Extra arguments go to every
# paper.py. Each process is stopped after LIMIT seconds (default 560; paper.py writes its JSON
# after each training family, so a stop during improvement keeps the ranking results).
# $OUT gets results.tgz (<task>.json and paper_<task>.log for every task).
#   LIMIT=560 bash experiments/device_tasks.sh "hopper walker2d" [paper.py args]
set -uo pipefail
TASKS=${1:?usage: bash experiments/device_tasks.sh "TASK ..." [paper.py args]}
shift
source experiments/device_env.sh
N_GPU=$(nvidia-smi --query-gpu=name --format=csv,noheader | wc -l)
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.4}
mkdir -p $OUT/res
i=0
for TASK in $TASKS; do
  GPU=$((i % N_GPU)); i=$((i + 1))
  ( nvidia-smi -i $GPU --query-gpu=name,memory.total --format=csv,noheader
    { time CUDA_VISIBLE_DEVICES=$GPU timeout ${LIMIT:-560} python3 experiments/paper.py \
        --task $TASK --profile gpu --out $OUT/res --data-dir $W "$@" ; } 2>&1 \
      | grep -v -i -e warn -e "Failed to import" ) > $OUT/res/paper_$TASK.log 2>&1 &
done
wait
tail -n 30 $OUT/res/paper_*.log
tar -C $OUT/res -czf $OUT/results.tgz . && rm -rf $OUT/res
