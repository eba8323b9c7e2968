#!/usr/bin/env bash
# The one runner of the GPU experiments (run through the device tool with the wheels of
# ../shared/tools/device-wheels carried as .whl). Every subcommand first installs the wheels
# (once per machine), sets PYTHONPATH, deterministic GPU ops, OUT (default /tmp/out), W (the
# data dir /tmp/work, kept while the machine is warm, so a later call reuses its data) and
# writes its log to $OUT line by line with the GPU's name and the time taken.
#
#   bash experiments/device.sh paper TASK [paper.py args]        the protocol for one task
#       ([LIMIT=585]: paper.py stopped after LIMIT s; $OUT/<task>.json, paper_<task>.log)
#   bash experiments/device.sh tasks "TASK ..."|T1,T2 [paper.py args]  tasks over the
#       GPUs as (task, family) units (experiments/paper_all.sh; LIMIT=560 per process, 450 x
#       k where k share one GPU (paper_schedule's per_gpu_count: PAPER_PER_GPU, auto 2 with
#       one GPU and two tasks or more);
#       $OUT/results.tgz; RL2S_MPS=1: under NVIDIA's MPS, started first if not running)
#   bash experiments/device.sh jobs "GPU NAME AFTER args" ...     paper.py jobs side by side,
#       one GPU each, a job waiting for AFTER's data phase ("-": none); LIMIT=570 for all;
#       $OUT/NAME/<task>.json, $OUT/NAME/paper.log; fails if a job failed
#   bash experiments/device.sh ablation TASK [ablation_model.py args]
#   bash experiments/device.sh model_fit TASK [model_fit.py args]
#   bash experiments/device.sh control [improve_control.py args]  the real-env improvement
#   bash experiments/device.sh race                               the official loop's torch
#       port (.race/official_loop.py: copy ../shared/tools/official_port/ to .race/ here, git
#       ignores it, carry it) at P=17 and 64, then bench_train.py --official-sizes --breakdown
#       (equal work) and the default family beside it (--breakdown too: where the protocol
#       step's time goes), then equal work again with XLA's
#       command buffers over loops; $OUT/official_p<P>.json, race_equal_work.json,
#       race_default.json, race_equal_work_cmdbuf.json (each with its "race" ratios)
#   bash experiments/device.sh levers [MODE ...]                  the step-level levers of
#       issue 63, one after another on one GPU: the adversarial and the likelihood family's
#       steps (bench_train.py, 6 lanes vmapped, P=17) and the equal-work step (one lane),
#       per MODE: control (as run: deterministic ops), nondeterministic, autotune0 (GEMM
#       autotuning off: compile time), up_front (batches_up_front, and its bit-for-bit
#       test on this GPU) and flat (flat_optimizer, its test, and experiments/step_ops.py's
#       ops per update with and without it: ops_{default,flat}.json); default all but flat;
#       Hopper's collection in control and nondeterministic where nondeterministic is asked
#       for; $OUT/levers.tgz
#       ({rl2s,bc,equal,collect}_<mode>.json), levers.log
#   bash experiments/device.sh kernels [MODE ...]                 where a one-lane step's GPU
#       time goes, kernel by kernel (experiments/kernel_trace.py): the equal-work, the
#       adversarial and the likelihood step (one lane, then 6 vmapped) per MODE: control
#       (as run), triton_any (--xla_gpu_triton_gemm_any), cublaslt (--xla_gpu_enable_cublaslt),
#       no_cmdbuf (command buffers off), flat (flat_optimizer); default control no_cmdbuf
#       flat; $OUT/kernels.tgz, kernels.log
#   bash experiments/device.sh zoo TASK [TASK ...]                `rl2s zoo` side by side
#       ([ZOO_LIMIT=320] [ZOO_TIMEOUT=530] [ZOO_ARGS_<task>="..."] [ZOO_EXPORT=1]
#       [ZOO_IMPORT=DIR] [ZOO_MEM_FRACTION]; $OUT/zoo_<task>.tar, untar into
#       rl2s_jax/zoo/shipped/; ZOO_EXPORT / ZOO_IMPORT continue a run on a fresh machine)
#   bash experiments/device.sh smoke [STEPS] [TRANSITIONS]        every method at paper sizes
#       on Hopper, then a checkpoint loaded in a fresh process ([METHODS="rl2s gail ..."])
#   bash experiments/device.sh share [gpu_share.py args]          processes sharing one GPU
#       (SHARE_GPU, default 0): one alone, two at once, then both again under NVIDIA's MPS
#       (started here, stopped after) where the machine has it; $OUT/share.tgz (a JSON per
#       process and the summary's), the summary also in $OUT/share.log
#   bash experiments/device.sh run LOG CMD...                     any command, logged to
#       $OUT/LOG (e.g. python3 experiments/planted_train.py --out $W/planted)
#   bash experiments/device.sh streams "SUB args; SUB args" ...    runs that outlast a call:
#       each argument a stream of device.sh subcommands run one after another, the streams
#       side by side on the GPU(s) (XLA_PYTHON_CLIENT_MEM_FRACTION 0.9 / streams), detached
#       (setsid) from a copy of the repo ($STREAMS_repo); returns at once. Each run's OUT is
#       $STREAMS/<stream>_<k> (STREAMS=/tmp/streams), progress in $STREAMS/progress.log. A
#       stream that begins with "@N " runs on GPU N alone, "@N,M " on GPUs N and M
#       (CUDA_VISIBLE_DEVICES; RL2S_GPUS their count, what paper_all.sh schedules over;
#       memory 0.9 / the most streams pinned to one of them); unpinned streams see every
#       GPU. A run may begin with NAME=VALUE words, its environment (RL2S_WORK=DIR: its
#       data dir W instead of /tmp/work, so two runs of one task do not share data).
#       POLL=S: poll for S s in the same call (the machine is given back 30 s after a call
#       ends, and the detached streams with it: launching and polling in one call leaves no
#       gap)
#   bash experiments/device.sh waitdata TASK [MAX_S]              waits (at most MAX_S, default
#       900) until paper.py's data of TASK is in $W: a stream that begins with it reuses the
#       data another stream is collecting instead of collecting it beside it
#   bash experiments/device.sh poll [WAIT_S]                       waits until every stream
#       ended or WAIT_S (default 540) passed, prints the progress, packs $STREAMS into
#       $OUT/streams.tgz; call it again (within the machine's 30 s idle window) to go on
#
# RL2S_NONDETERMINISTIC=1 leaves XLA's default (faster, not repeatable) GPU ops.
set -uo pipefail

setup_env() {
  SITE=${RL2S_SITE:-/tmp/site}
  [ -e "$SITE/.rl2s_wheels" ] || { python3 -m pip install -q --no-index --no-deps --no-compile \
    --no-cache-dir --upgrade --target "$SITE" .whl/*.whl && mkdir -p "$SITE" \
    && touch "$SITE/.rl2s_wheels"; } || exit 1
  export PYTHONPATH=$SITE:$PWD PYTHONUNBUFFERED=1
  # Repeatable GPU numbers: without this flag identical policies from identical starts earn
  # different returns on walker2d, halfcheetah and ant (RESULTS@bf0c7b2, "Why pairing did not
  # help"); it cost 0-40% of wall time there, but large-batch collection may slow far more
  # (unmeasured: docs/BENCHMARKS.md). RL2S_NONDETERMINISTIC=1 leaves XLA's default.
  if [ "${RL2S_NONDETERMINISTIC:-0}" != 1 ]; then
    export XLA_FLAGS="${XLA_FLAGS:+$XLA_FLAGS }--xla_gpu_deterministic_ops=true"
  fi
  OUT=${OUT:-/tmp/out}
  RL2S="python3 -m rl2s_jax.cli"
  W=${RL2S_WORK:-/tmp/work} && mkdir -p "$W" "$OUT"

  # run_logged LOG CMD...: the GPU's name, then CMD timed with its warnings dropped, to stdout
  # and appended to $OUT/LOG line by line (another job may be waiting for a line of it).
  run_logged() {
    local log=$OUT/$1
    shift
    nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$log"
    { time "$@" ; } 2>&1 | grep --line-buffered -v -i -e warn -e "Failed to import" \
      | tee -a "$log"
  }
}

# start_mps: NVIDIA's Multi-Process Service for this machine's GPUs (the kernels of several
# processes on one GPU run at once instead of time-sliced); a no-op where it already runs.
start_mps() {
  MPS_CTL=$(command -v nvidia-cuda-mps-control || ls /usr/local/nvidia/bin/nvidia-cuda-mps-control \
    /usr/local/cuda/bin/nvidia-cuda-mps-control 2>/dev/null | head -n 1)
  [ -n "$MPS_CTL" ] || { echo "mps: no nvidia-cuda-mps-control on this machine" >&2; return 1; }
  # one daemon per set of visible GPUs: it serves the GPUs it saw when it started
  local tag=${CUDA_VISIBLE_DEVICES:-all}
  export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps_pipe_${tag//,/_} CUDA_MPS_LOG_DIRECTORY=/tmp/mps_log_${tag//,/_}
  mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
  [ -e "$CUDA_MPS_PIPE_DIRECTORY/control" ] || "$MPS_CTL" -d
}

usage() { sed -n '2,/^set -uo/p' "$0" | sed 's/^# \{0,1\}//' | head -n -1 >&2; exit 2; }

cmd_paper() {
  local task=${1:?usage: bash experiments/device.sh paper TASK [paper.py args]}
  shift
  run_logged paper_$task.log ${LIMIT:+timeout $LIMIT} python3 experiments/paper.py \
    --task $task --profile gpu --out $OUT --data-dir $W "$@"
}

cmd_tasks() {
  local tasks=${1:?usage: bash experiments/device.sh tasks "TASK ..." [paper.py args]}
  export TASKS=${tasks//,/ }  # "hopper walker2d" or hopper,walker2d (a streams word)
  shift
  if [ "${RL2S_MPS:-0}" = 1 ]; then start_mps || return 1; fi
  # 560 s for a paper.py alone; k sharing one GPU (paper_schedule's per_gpu_count: 2 on one
  # GPU with two tasks or more) each take ~0.8k as long: 450 s per process sharing the GPU
  local n_gpu=${RL2S_GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c '^GPU')} per limit
  per=$(python3 -c "import sys; sys.path.insert(0, 'experiments')
from paper_schedule import per_gpu_count
print(per_gpu_count(sys.argv[1], int(sys.argv[2]), int(sys.argv[3])))" \
    "${PAPER_PER_GPU:-auto}" "$n_gpu" "$(wc -w <<< "$TASKS")") || return 2
  if [ "$per" = 1 ]; then limit=560; else limit=$((450 * per)); fi
  PY="timeout ${LIMIT:-$limit} python3" DATA_DIR=$W bash experiments/paper_all.sh $OUT/res \
    --profile gpu "$@"
  tail -n 30 $OUT/res/paper_*.log
  tar -C $OUT/res -czf $OUT/results.tgz . && rm -rf $OUT/res
}

cmd_jobs() {
  LIMIT=${LIMIT:-570}
  START=$SECONDS
  declare -A GPU_OF
  for spec in "$@"; do  # refuse bad specs before any job starts
    read -r gpu name after _ <<<"$spec"
    [[ "$gpu" =~ ^[0-9]+$ && -n "$name" && -n "$after" ]] || {
      echo "job spec: expected \"GPU NAME AFTER paper.py args\", got \"$spec\"" >&2; return 2; }
    [ -z "${GPU_OF[$name]:-}" ] || { echo "job spec: NAME $name given twice" >&2; return 2; }
    GPU_OF[$name]=$gpu
  done
  for spec in "$@"; do
    read -r _ name after _ <<<"$spec"
    [ "$after" = - ] || [ -n "${GPU_OF[$after]:-}" ] || {
      echo "job spec: $name waits for $after, which is no job's NAME" >&2; return 2; }
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
  return $failed
}

cmd_ablation() {
  local task=${1:?usage: bash experiments/device.sh ablation TASK [ablation_model.py args]}
  shift
  run_logged ablation_$task.log python3 experiments/ablation_model.py --task $task \
    --profile gpu --out $OUT --data-dir $W "$@"
}

cmd_model_fit() {
  local task=${1:?usage: bash experiments/device.sh model_fit TASK [model_fit.py args]}
  shift
  run_logged model_fit_$task.log python3 experiments/model_fit.py --task $task \
    --profile gpu --out $OUT --data-dir $W "$@"
}

cmd_control() {
  run_logged control.log python3 experiments/improve_control.py --out $OUT "$@"
}

cmd_race() {
  [ -f .race/official_loop.py ] || { echo "race: expected .race/official_loop.py (cp -r" \
    "../shared/tools/official_port .race, then carry .race)" >&2; return 2; }
  for P in 17 64; do
    run_logged race.log timeout "${T_OFF:-240}" python3 .race/official_loop.py --device cuda \
      --policies $P | grep '^{' | tail -n 1 > "$OUT/official_p$P.json"
  done
  run_logged race.log python3 experiments/bench_train.py --official-sizes --breakdown \
    --policies 17 64 --horizons --sim-steps --vmap 8 --official-dir "$OUT" \
    --json "$OUT/race_equal_work.json"
  run_logged race.log python3 experiments/bench_train.py --policies 17 64 --horizons \
    --sim-steps --vmap 8 --breakdown --official-dir "$OUT" --json "$OUT/race_default.json"
  # The single run is launch-bound (BENCHMARKS, "The race"): the same equal-work rows with
  # XLA's command buffers (CUDA graphs) also capturing loops and conditionals, so a whole
  # scan of updates can launch as one graph (WHILE and CONDITIONAL are not in XLA's default)
  local cmdbuf="--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN"
  cmdbuf="$cmdbuf,CONDITIONAL,WHILE"
  XLA_FLAGS="${XLA_FLAGS:+$XLA_FLAGS }$cmdbuf" run_logged race.log python3 \
    experiments/bench_train.py --official-sizes --policies 17 64 --horizons --sim-steps \
    --vmap 8 --official-dir "$OUT" --json "$OUT/race_equal_work_cmdbuf.json"
}

cmd_zoo() {
  [ $# -gt 0 ] || { echo "usage: bash experiments/device.sh zoo TASK [TASK ...]" >&2; return 2; }
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
}

cmd_smoke() {
  local STEPS=${1:-200} TPP=${2:-20000}
  [ -f $W/hopper_train.npz ] || { time $RL2S collect --task hopper --split train --transitions-per-policy $TPP \
      --value-episodes 16 --out $W/hopper_train.npz ; } 2>&1 | grep -v -i warn | tail -5 \
    | tee $OUT/train.log
  METHODS=${METHODS:-rl2s gail bc rl2s-bc}
  for M in $METHODS; do
    echo "== $M" | tee -a $OUT/train.log
    rm -rf $W/run_$M
    { time $RL2S train --data $W/hopper_train.npz --method $M --steps $STEPS --profile gpu \
        --out $W/run_$M --quiet --save-every 100 --chunk 50 ; } 2>&1 | grep -v -i warn \
      | tee -a $OUT/train.log
    cp $W/run_$M/metrics.jsonl $OUT/metrics_$M.jsonl
  done
  python3 - <<PY 2>&1 | grep -v -i warn | tee -a $OUT/train.log
import json, jax, jax.numpy as jnp
from rl2s_jax import load_simulator
sim = load_simulator("$W/run_rl2s/checkpoints")
o, a = sim.norm.obs_mean.shape[0], sim.norm.act_mean.shape[0]
print("fresh-process load:", sim.task, sim.n_members, "members",
      sim.mean(jnp.ones((2, o)), jnp.zeros((2, a))).shape)
runs = {m: json.load(open(f"$W/run_{m}/summary.json")) for m in "$METHODS".split()}
json.dump(runs, open("$OUT/summaries.json", "w"), indent=1)
PY
}

cmd_streams() {
  local streams=${STREAMS:-/tmp/streams}
  local snap=${streams}_repo  # per STREAMS dir: a second set may start while the first runs
  [ -e "$streams/progress.log" ] && ! grep -q "^ALLDONE" "$streams/progress.log" && {
    echo "streams: streams are still running ($streams/progress.log)" >&2; return 2; }
  rm -rf "$streams" "$snap" && mkdir -p "$streams" "$snap" && cp -r . "$snap"/ || return 1
  # a new session (setsid): the device tool ends a call's other processes when it returns
  (cd "$snap" && STREAMS=$streams setsid bash experiments/device.sh _streams_run "$@" \
    > "$streams/driver.log" 2>&1 < /dev/null &)
  sleep 2
  echo "streams: $# stream(s) started from the copy $snap; progress:"
  cat "$streams/progress.log" 2>/dev/null
  [ -z "${POLL:-}" ] || STREAMS=$streams cmd_poll "$POLL"
}

cmd__streams_run() {  # the detached driver of cmd_streams (run from the repo's copy)
  local streams=${STREAMS:-/tmp/streams} i=0 spec pin g most
  declare -A ON_GPU  # streams pinned to each GPU
  for spec in "$@"; do
    if [[ "$spec" =~ ^@([0-9,]+)\  ]]; then
      for g in ${BASH_REMATCH[1]//,/ }; do ON_GPU[$g]=$((${ON_GPU[$g]:-0} + 1)); done
    fi
  done
  for spec in "$@"; do
    (
      pin=
      [[ "$spec" =~ ^@([0-9,]+)\ (.*)$ ]] && pin=${BASH_REMATCH[1]} spec=${BASH_REMATCH[2]}
      if [ -n "$pin" ]; then
        export CUDA_VISIBLE_DEVICES=$pin RL2S_GPUS=$(wc -w <<<"${pin//,/ }")
        most=1
        for g in ${pin//,/ }; do [ "${ON_GPU[$g]}" -gt "$most" ] && most=${ON_GPU[$g]}; done
        XLA_PYTHON_CLIENT_MEM_FRACTION=$(python3 -c "print(round(0.9 / $most, 2))")
      else
        XLA_PYTHON_CLIENT_MEM_FRACTION=$(python3 -c "print(round(0.9 / $#, 2))")
      fi
      export XLA_PYTHON_CLIENT_MEM_FRACTION
      k=0
      IFS=';' read -ra runs <<<"$spec"
      for run in "${runs[@]}"; do
        read -ra words <<<"$run"
        envs=()
        while [ ${#words[@]} -gt 0 ] && [[ "${words[0]}" =~ ^[A-Z_][A-Z0-9_]*= ]]; do
          envs+=("${words[0]}") && words=("${words[@]:1}")
        done
        [ ${#words[@]} -gt 0 ] || continue
        dir="$streams/s${i}_$k"
        mkdir -p "$dir"
        echo "[s$i] $k start $(date +%T)${pin:+ GPU $pin}: ${envs[*]:+${envs[*]} }${words[*]}" \
          >> "$streams/progress.log"
        env OUT="$dir" ${envs[@]+"${envs[@]}"} bash experiments/device.sh "${words[@]}" \
          > "$dir/stdout.log" 2>&1
        echo "[s$i] $k rc $? end $(date +%T)" >> "$streams/progress.log"
        k=$((k + 1))
      done
    ) &
    i=$((i + 1))
  done
  wait
  echo "ALLDONE $(date +%T)" >> "$streams/progress.log"
}

cmd_poll() {
  local streams=${STREAMS:-/tmp/streams} wait_s=${1:-540} t0=$SECONDS
  [ -d "$streams" ] || { echo "poll: no streams at $streams" >&2; return 2; }
  until grep -q "^ALLDONE" "$streams/progress.log" 2>/dev/null \
      || [ $((SECONDS - t0)) -ge "$wait_s" ]; do
    sleep 5
  done
  cat "$streams/progress.log"
  for f in "$streams"/*/stdout.log; do
    [ -e "$f" ] && { echo "== $f"; grep -v -i -e warn -e "Failed to import" "$f" | tail -6; }
  done
  tar -czf "$OUT/streams.tgz" -C "$(dirname "$streams")" "$(basename "$streams")"
}

cmd_waitdata() {
  local task=${1:?usage: bash experiments/device.sh waitdata TASK [MAX_S]} t0=$SECONDS
  # load_or_collect writes <task>_data.json after the datasets: its presence means complete
  until [ -s "$W/${task}_data.json" ]; do
    [ $((SECONDS - t0)) -ge "${2:-900}" ] && { echo "waitdata: no $W/${task}_data.json" >&2
                                              return 1; }
    sleep 5
  done
  sleep 2  # the file's few bytes, fully written
  echo "waitdata: $task's data in $W after $((SECONDS - t0)) s"
}

cmd_levers() {
  local off=${XLA_FLAGS:-} mode flags set
  off=${off//--xla_gpu_deterministic_ops=true/}
  local on="${off:+$off }--xla_gpu_deterministic_ops=true"
  local modes=("$@")
  [ ${#modes[@]} -gt 0 ] || modes=(control nondeterministic autotune0 up_front)
  for mode in "${modes[@]}"; do  # refused before any measurement
    [[ " control nondeterministic autotune0 up_front flat " == *" $mode "* ]] || {
      echo "levers: expected modes among control nondeterministic autotune0 up_front flat, got" \
        "$mode" >&2; return 2; }
  done
  for mode in "${modes[@]}"; do
    flags=$on set=()
    case $mode in
      nondeterministic) flags=$off ;;
      autotune0) flags="$on --xla_gpu_autotune_level=0" ;;  # compile time against step time
      up_front) set=(--set batches_up_front=true) ;;
      flat) set=(--set flat_optimizer=true) ;;
    esac
    echo "== $mode: XLA_FLAGS='$flags' ${set[*]}" | tee -a "$OUT/levers.log"
    XLA_FLAGS=$flags run_logged levers.log python3 experiments/bench_train.py --policies \
      --horizons --sim-steps --vmap 6 --steps 4 ${set[@]+"${set[@]}"} --json "$OUT/rl2s_$mode.json"
    XLA_FLAGS=$flags run_logged levers.log python3 experiments/bench_train.py --method bc \
      --policies --horizons --sim-steps --vmap 6 --steps 4 ${set[@]+"${set[@]}"} \
      --json "$OUT/bc_$mode.json"
    XLA_FLAGS=$flags run_logged levers.log python3 experiments/bench_train.py --official-sizes \
      --policies 17 --horizons --sim-steps --vmap ${set[@]+"${set[@]}"} \
      --json "$OUT/equal_$mode.json"
    if [[ "$mode" =~ ^(up_front|flat)$ ]]; then  # the same updates on this GPU too
      XLA_FLAGS=$flags run_logged levers.log python3 -m pytest -q -p no:cacheprovider \
        tests/test_train.py -k "${mode/up_front/batches_up_front}"
    fi
    if [ "$mode" = flat ]; then  # the GPU's kernels per update, default and flat
      XLA_FLAGS=$flags run_logged levers.log python3 experiments/step_ops.py \
        --official-sizes --json "$OUT/ops_default.json"
      XLA_FLAGS=$flags run_logged levers.log python3 experiments/step_ops.py \
        --official-sizes --set flat_optimizer=true --json "$OUT/ops_flat.json"
    fi
    # the collection only where its two modes are compared
    [[ "$mode" =~ ^(control|nondeterministic)$ && " ${modes[*]} " == *" nondeterministic "* ]] \
      || continue
    XLA_FLAGS=$flags run_logged levers.log timeout "${T_COLLECT:-240}" python3 \
      experiments/bench.py --task hopper --batch 2048 --steps 100 --reset-every-step-batch \
      --json "$OUT/collect_$mode.json"
  done
  # the archive is written beside $OUT, then moved in: tar exits 1 when the directory it
  # reads changes under it (the archive's creation did)
  tar -C "$OUT" -czf "${OUT%/}.levers.tgz" --exclude levers.log --exclude stdout.log . \
    && mv "${OUT%/}.levers.tgz" "$OUT/levers.tgz" \
    && find "$OUT" -maxdepth 1 -name "*.json" -delete  # the tool brings back 8 files
}

cmd_share() {
  (
    local d=$OUT/share label n i
    mkdir -p "$d"
    export CUDA_VISIBLE_DEVICES=${SHARE_GPU:-0} XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 \
      JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
    share_case() {  # CASE N [gpu_share.py args]: N processes meet at a barrier, then time
      label=$1 n=$2
      shift 2
      local pids=()
      for ((i = 0; i < n; i++)); do
        timeout 400 python3 experiments/gpu_share.py --barrier "/tmp/share_$label" --n "$n" \
          --id "$i" --json "$d/${label}_$i.json" "$@" >> "$OUT/share.log" 2>&1 &
        pids+=($!)
      done
      wait "${pids[@]}"
    }
    nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$OUT/share.log"
    share_case alone 1 "$@" && share_case pair 2 "$@"
    if start_mps; then
      share_case mps_alone 1 "$@" && share_case mps_pair 2 "$@"
      echo quit | "$MPS_CTL"
    else
      echo "share: the MPS cases are not run" | tee -a "$OUT/share.log"
    fi
    python3 experiments/gpu_share.py --summary "$d" | tee -a "$OUT/share.log"
    tar -C "$OUT" -czf "$OUT/share.tgz" share && rm -rf "$d"  # the tool brings back 8 files
  )
}

cmd_kernels() {
  # kernel_trace.py per MODE (XLA flags or a TrainConfig option) on the equal-work step
  # (official sizes, one lane), the adversarial and the likelihood family's (one lane and
  # 6 vmapped); $OUT/kernels.tgz (JSON per mode and step; raw traces where they fit)
  local on=${XLA_FLAGS:-} mode flags step
  local modes=("$@")
  [ ${#modes[@]} -gt 0 ] || modes=(control no_cmdbuf flat)
  for mode in "${modes[@]}"; do  # refused before any measurement
    [[ " control triton_any cublaslt no_cmdbuf flat " == *" $mode "* ]] || {
      echo "kernels: expected modes among control triton_any cublaslt no_cmdbuf flat, got" \
        "$mode" >&2; return 2; }
  done
  local dir=$OUT/kernels
  mkdir -p "$dir"
  for mode in "${modes[@]}"; do
    local set=()
    case $mode in
      control) flags=$on ;;
      flat) flags=$on set=(--set flat_optimizer=true) ;;     # one clip and Adam per update
      triton_any) flags="$on --xla_gpu_triton_gemm_any=true" ;;  # dots fused with neighbours
      cublaslt) flags="$on --xla_gpu_enable_cublaslt=true" ;;    # bias+ReLU in the GEMM
      no_cmdbuf) flags="$on --xla_gpu_enable_command_buffer=" ;;  # no CUDA graphs at all
    esac
    for step in equal rl2s bc rl2s6 bc6; do
      local args=(--steps 3 ${set[@]+"${set[@]}"})
      case $step in
        equal) args+=(--official-sizes) ;;
        bc) args+=(--method bc --steps 10) ;;
        rl2s6) args+=(--vmap 6) ;;                                 # the protocol's 6 lanes
        bc6) args+=(--method bc --steps 10 --vmap 6) ;;
      esac
      echo "== $mode $step: XLA_FLAGS='$flags'" | tee -a "$OUT/kernels.log"
      XLA_FLAGS=$flags run_logged kernels.log python3 experiments/kernel_trace.py "${args[@]}" \
        --out "$dir/${mode}_$step"
    done
  done
  # the raw traces only where the pack stays under the 16-MiB limit on a file brought back
  tar -czf "$OUT/kernels.tgz" -C "$OUT" kernels
  [ "$(stat -c %s "$OUT/kernels.tgz")" -lt 15000000 ] \
    || tar -czf "$OUT/kernels.tgz" -C "$OUT" --exclude='*.xplane.pb' --exclude='*.trace.json.gz' kernels
  rm -rf "$dir"
}

cmd_run() {
  local log=${1:?usage: bash experiments/device.sh run LOG CMD...}
  shift
  [ $# -gt 0 ] || usage
  run_logged "$log" "$@"
}

sub=${1:-}
shift || true
case "$sub" in
  paper|tasks|ablation|model_fit|control|race|levers|kernels|zoo|smoke|share|run|poll|waitdata) setup_env
      "cmd_$sub" "$@" ;;
  streams) [ $# -gt 0 ] || usage
           setup_env; cmd_streams "$@" ;;
  _streams_run) setup_env; cmd__streams_run "$@" ;;
  jobs) [ $# -gt 0 ] || { echo "usage: bash experiments/device.sh jobs \"GPU NAME AFTER args\" ..." >&2
          exit 2; }
        setup_env; cmd_jobs "$@" ;;
  *) usage ;;
esac
