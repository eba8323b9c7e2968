#!/usr/bin/env bash
# Several tasks of the paper's protocol on the GPU machine (run through the device tool with
# .whl carried): experiments/paper_all.sh (the tasks round-robin over the visible GPUs, one
# experiments/paper.py process per GPU at a time) at the gpu profile, all sharing the data dir
# $W. Extra arguments go to every paper.py. Each process is stopped after LIMIT seconds
# (default 560; paper.py writes its JSON after each phase, so a stop during improvement keeps
# the ranking results); a GPU's tasks run one after another, so name at most one task per GPU
# to stay within one device call. $OUT gets results.tgz (<task>.json, paper_<task>.log,
# tables.md).
#   LIMIT=560 bash experiments/device_tasks.sh "hopper walker2d" [paper.py args]
set -uo pipefail
export TASKS=${1:?usage: bash experiments/device_tasks.sh "TASK ..." [paper.py args]}
shift
source experiments/device_env.sh
PY="timeout ${LIMIT:-560} python3" DATA_DIR=$W bash experiments/paper_all.sh $OUT/res \
  --profile gpu "$@"
tail -n 30 $OUT/res/paper_*.log
tar -C $OUT/res -czf $OUT/results.tgz . && rm -rf $OUT/res
