# Sourced by the experiments/device_*.sh scripts on the GPU machine: installs the carried
# wheels (.whl, from ../shared/tools/device-wheels) and sets PYTHONPATH, OUT, RL2S and W.
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
RL2S="python3 -m rl2s_jax.cli"
W=/tmp/work && mkdir -p "$W" "$OUT"
