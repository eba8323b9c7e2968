#!/usr/bin/env bash
# The real-env control of policy improvement on the GPU machine (run through the device tool
# with the .whl carried): experiments/improve_control.py; extra arguments go to it. $OUT gets
# control_<task>.json and the log control.log.
#   bash experiments/device_control.sh [--tasks hopper,walker2d --seeds 2 --plain ...]
set -euo pipefail
source experiments/device_env.sh
run_logged control.log python3 experiments/improve_control.py --out $OUT "$@"
