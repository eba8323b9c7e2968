#!/usr/bin/env bash
# The real-env control of policy improvement on the GPU machine (run through the device tool
# with the .whl carried): experiments/improve_control.py; extra arguments go to it. $OUT gets
# control_<task>.json and the log control.log.
#   bash experiments/device_control.sh [--tasks hopper,walker2d --seeds 2 --plain ...]
set -euo pipefail
source experiments/device_env.sh
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee $OUT/control.log
{ time python3 experiments/improve_control.py --out $OUT "$@" ; } \
  2>&1 | grep -v -i -e warn -e "Failed to import" | tee -a $OUT/control.log
