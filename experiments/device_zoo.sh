#!/usr/bin/env bash
# Rebuild zoos on the GPU machine (device tool), the tasks side by side on the one GPU:
#   bash experiments/device_zoo.sh TASK [TASK ...]
# Needs the wheels from ../shared/tools/device-wheels carried as .whl. Writes $OUT/zoo_<task>/.
set -u
source experiments/device_env.sh
export XLA_PYTHON_CLIENT_MEM_FRACTION=$(python3 -c "print(round(0.9 / $#, 2))")
nvidia-smi -L
python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
for task in "$@"; do
  timeout "${ZOO_TIMEOUT:-570}" python3 -m rl2s_jax.cli zoo --task "$task" \
    --out "$OUT/zoo_$task" > "$OUT/zoo_$task.log" 2>&1 &
done
wait
for task in "$@"; do grep -v -i "warn" "$OUT/zoo_$task.log"; done
