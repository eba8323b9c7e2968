# Sourced by the experiments/device_*.sh scripts on the GPU machine: installs the carried
# wheels (.whl, from ../shared/tools/device-wheels), sets PYTHONPATH, OUT, RL2S and W, and
# defines run_logged.
# Once per machine: a script sourced beside a running job must not rewrite its packages.
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
W=/tmp/work && mkdir -p "$W" "$OUT"

# run_logged LOG CMD...: the GPU's name, then CMD timed with its warnings dropped, to stdout
# and appended to $OUT/LOG line by line (another job may be waiting for a line of it).
run_logged() {
  local log=$OUT/$1
  shift
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$log"
  { time "$@" ; } 2>&1 | grep --line-buffered -v -i -e warn -e "Failed to import" \
    | tee -a "$log"
}
