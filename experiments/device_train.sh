#!/usr/bin/env bash
# GPU smoke of the simulator core at paper sizes (run through the device tool, .whl carried):
# collect a Hopper train set from the shipped zoo, train each method for STEPS train_steps,
# load one checkpoint in a fresh process. Logs and summaries go to $OUT.
#   [METHODS="rl2s gail bc rl2s-bc"] bash experiments/device_train.sh [STEPS] [TRANSITIONS_PER_POLICY]
set -euo pipefail
STEPS=${1:-200}
TPP=${2:-20000}
source experiments/device_env.sh
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
print("fresh-process load:", sim.task, [l["w"].shape for l in sim.gen],
      sim.mean(jnp.ones((2, 12)), jnp.zeros((2, 3))).shape)
runs = {m: json.load(open(f"$W/run_{m}/summary.json")) for m in "$METHODS".split()}
json.dump(runs, open("$OUT/summaries.json", "w"), indent=1)
PY
