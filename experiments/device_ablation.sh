#!/usr/bin/env bash
# The model-family ablation for one task on the GPU machine (run through the device tool with
# .whl carried): experiments/ablation_model.py at its gpu sizes; extra arguments go to it (e.g.
# --variants rl2s). The data stays in $W (reused by later calls while the machine is warm);
# $OUT gets ablation_<task>_<variant>.json, ablation_<task>.{json,md} and the log.
#   bash experiments/device_ablation.sh TASK [ablation_model.py args]
set -euo pipefail
TASK=${1:?usage: bash experiments/device_ablation.sh TASK [ablation_model.py args]}
shift
source experiments/device_env.sh
run_logged ablation_$TASK.log python3 experiments/ablation_model.py --task $TASK --profile gpu \
  --out $OUT --data-dir $W "$@"
