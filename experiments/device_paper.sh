#!/usr/bin/env bash
# The paper's protocol for one task on the GPU machine (run through the device tool with .whl
# carried): experiments/paper.py at its gpu sizes; extra arguments go to paper.py. The data
# (hundreds of MB) stays in $W, so a second call on the warm machine reuses it (e.g. the other
# --families); $OUT gets <task>.json and the log paper_<task>.log. LIMIT=S stops paper.py
# after S seconds (its JSON is written after each phase).
#   [LIMIT=585] bash experiments/device_paper.sh TASK [--steps N --seeds N ...]
set -euo pipefail
TASK=${1:?usage: bash experiments/device_paper.sh TASK [paper.py args]}
shift
source experiments/device_env.sh
run_logged paper_$TASK.log ${LIMIT:+timeout $LIMIT} python3 experiments/paper.py --task $TASK \
  --profile gpu --out $OUT --data-dir $W "$@"
