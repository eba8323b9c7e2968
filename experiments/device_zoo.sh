#!/usr/bin/env bash
# Build zoos on the GPU machine (device tool), the given tasks side by side on the one GPU, each
# inside one call (issue 15):
#   [ZOO_LIMIT=320] [ZOO_TIMEOUT=530] [ZOO_ARGS_<task>="--seeds 3 ..."] [ZOO_EXPORT=1] \
#     [ZOO_IMPORT=DIR] [ZOO_MEM_FRACTION=0.45] bash experiments/device_zoo.sh TASK [TASK ...]
# Each task runs `rl2s zoo --task T --time-limit $ZOO_LIMIT --final`: it trains (resuming from
# /tmp/work/zoo_<task> when this machine ran it before) until the time limit or its env-step
# budget, then measures every snapshot (16 episodes x 1000 steps), chooses the zoo and writes
# zoo.npz, zoo.json, train_log.jsonl, curves.png, returns_hist.png and zoo.log, packed as
# $OUT/zoo_<task>.tar (untar into rl2s_jax/zoo/shipped/). ZOO_EXPORT=1 also writes
# $OUT/zoo_<task>_export.npz, the run to continue on a fresh machine: carry it in DIR and set
# ZOO_IMPORT=DIR. Needs the wheels from ../shared/tools/device-wheels carried as .whl.
set -u
source experiments/device_env.sh
export XLA_PYTHON_CLIENT_MEM_FRACTION=${ZOO_MEM_FRACTION:-$(python3 -c "print(round(0.9 / $#, 2))")}
nvidia-smi -L
python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
for task in "$@"; do
  extra_var="ZOO_ARGS_$task"
  args=(zoo --task "$task" --work "$W/zoo_$task" --out "$W/out_$task"
        --time-limit "${ZOO_LIMIT:-320}" --final ${!extra_var:-})
  [ "${ZOO_EXPORT:-0}" = 1 ] && args+=(--export "$OUT/zoo_${task}_export.npz")
  imp="${ZOO_IMPORT:-}/zoo_${task}_export.npz"
  [ -n "${ZOO_IMPORT:-}" ] && { [ -f "$imp" ] || [ -f "$imp.part00" ]; } && args+=(--import "$imp")
  mkdir -p "$W/out_$task"
  echo "== $task: rl2s ${args[*]}"
  timeout "${ZOO_TIMEOUT:-530}" python3 -m rl2s_jax.cli "${args[@]}" > "$W/out_$task/zoo.log" 2>&1 &
done
wait
for task in "$@"; do
  echo "== $task"
  grep -v -i "warn" "$W/out_$task/zoo.log" | tr '\r' '\n' | grep -v "^ *$" | tail -25
  tar -cf "$OUT/zoo_$task.tar" -C "$W" --transform "s,^out_$task,$task," "out_$task"
done
ls -la "$OUT"
