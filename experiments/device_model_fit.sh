#!/usr/bin/env bash
# The likelihood model's fit on one task on the GPU machine (run through the device tool with
# .whl carried): experiments/model_fit.py at its gpu sizes; extra arguments go to it (e.g.
# --variants bc,bc:gen_activation=silu). $OUT gets model_fit_<task>_<variant>.json, the table
# model_fit_<task>.md and the log.
#   bash experiments/device_model_fit.sh TASK [model_fit.py args]
set -euo pipefail
TASK=${1:?usage: bash experiments/device_model_fit.sh TASK [model_fit.py args]}
shift
source experiments/device_env.sh
run_logged model_fit_$TASK.log python3 experiments/model_fit.py --task $TASK --profile gpu \
  --out $OUT --data-dir $W "$@"
