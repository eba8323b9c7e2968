#!/usr/bin/env bash
# Several experiments/paper.py runs side by side on a GPU machine of several GPUs (through the
# device tool, .whl carried), one GPU each, sharing the data in $W. A job may wait for another
# job's data phase, so a second job of a task reuses the data instead of collecting it again
# (e.g. more seeds with --first-seed, or the other --families). Each job NAME writes
# $OUT/NAME/<task>.json and $OUT/NAME/paper.log. LIMIT=S (default 570) stops every job S
# seconds after the script started; the script fails if a job failed, after all have ended.
#   [LIMIT=570] bash experiments/device_jobs.sh "GPU NAME AFTER paper.py args" ...
# AFTER is "-" or the NAME of a job whose data phase must end first. Example:
#   bash experiments/device_jobs.sh "0 hop_adv - --task hopper --families adversarial" \
#     "1 hop_mle hop_adv --task hopper --families mle"
set -uo pipefail
[ $# -gt 0 ] || { echo "usage: bash experiments/device_jobs.sh \"GPU NAME AFTER args\" ..." >&2; exit 2; }
source experiments/device_env.sh
LIMIT=${LIMIT:-570}
START=$SECONDS
declare -A GPU_OF
for spec in "$@"; do  # refuse bad specs before any job starts
  read -r gpu name after _ <<<"$spec"
  [[ "$gpu" =~ ^[0-9]+$ && -n "$name" && -n "$after" ]] || {
    echo "job spec: expected \"GPU NAME AFTER paper.py args\", got \"$spec\"" >&2; exit 2; }
  [ -z "${GPU_OF[$name]:-}" ] || { echo "job spec: NAME $name given twice" >&2; exit 2; }
  GPU_OF[$name]=$gpu
done
for spec in "$@"; do
  read -r _ name after _ <<<"$spec"
  [ "$after" = - ] || [ -n "${GPU_OF[$after]:-}" ] || {
    echo "job spec: $name waits for $after, which is no job's NAME" >&2; exit 2; }
done

run_job() {  # GPU NAME AFTER ARGS...
  local gpu=$1 name=$2 after=$3
  shift 3
  local log=$OUT/$name/paper.log
  mkdir -p "$OUT/$name"
  if [ "$after" != - ]; then
    until grep -q "^\[paper\] data: " "$OUT/$after/paper.log" 2>/dev/null; do
      if [ $((SECONDS - START)) -ge "$LIMIT" ] || [ -e "$OUT/$after/.done" ]; then
        echo "[jobs] $name: $after never finished its data phase" | tee -a "$log"
        touch "$OUT/$name/.done"
        return 1
      fi
      sleep 1
    done
  fi
  local left=$((LIMIT - (SECONDS - START)))
  echo "[jobs] $name on GPU $gpu at ${SECONDS}s, ${left}s left: paper.py $*" | tee -a "$log"
  export CUDA_VISIBLE_DEVICES=$gpu  # this job's subshell only
  run_logged "$name/paper.log" timeout "$left" python3 experiments/paper.py --profile gpu \
    --data-dir "$W" --out "$OUT/$name" "$@" >/dev/null  # its log, line by line
  local rc=$?  # paper.py's status (pipefail)
  echo "[jobs] $name ended with $rc at ${SECONDS}s" | tee -a "$log"
  touch "$OUT/$name/.done"
  return "$rc"
}

nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader
pids=()
names=()
for spec in "$@"; do
  read -r gpu name after args <<<"$spec"
  # shellcheck disable=SC2086  # the paper.py arguments are split on purpose
  run_job "$gpu" "$name" "$after" $args &
  pids+=($!)
  names+=("$name")
done
failed=0
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || { echo "[jobs] ${names[$i]} FAILED"; failed=1; }
done
rm -f "$OUT"/*/.done
for name in "${names[@]}"; do
  echo "== $name"
  tail -n 12 "$OUT/$name/paper.log"
done
exit $failed
