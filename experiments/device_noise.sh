#!/usr/bin/env bash
# GPU experiment: does rolling p_phi out with its mean (sim_noise=0) instead of samples
# (sim_noise=1) lower the test policies' VD? Paper sizes, Hopper, shipped zoo.
#   METHODS="bc rl2s" bash experiments/device_noise.sh [STEPS] [TRANSITIONS_PER_POLICY]
set -euo pipefail
STEPS=${1:-1000}
TPP=${2:-20000}
source experiments/device_env.sh
for S in train test; do
  [ -f $W/hopper_$S.npz ] || $RL2S collect --task hopper --split $S --transitions-per-policy \
    $TPP --value-episodes 16 --out $W/hopper_$S.npz 2>&1 | grep -v -i warn | tail -2
done
for M in ${METHODS:-bc rl2s}; do
  for N in 1 0; do
    rm -rf $W/${M}_$N
    $RL2S train --data $W/hopper_train.npz --method $M --steps $STEPS --profile gpu \
      --out $W/${M}_$N --quiet --save-every $STEPS --chunk 50 --set sim_noise=$N \
      --eval-data $W/hopper_test.npz --eval-every $((STEPS / 4)) 2>&1 | grep -E "AVD|error"
    python3 - <<PY | tee -a $OUT/noise.txt
import json
rows = [json.loads(l) for l in open("$W/${M}_$N/eval.jsonl")]
print("$M sim_noise=$N", [(r["step"], round(r["avd"]), round(r["mvd"]), round(r["kendall_tau"], 3),
                          round(r["ndcg@1"], 3)) for r in rows])
PY
    cp $W/${M}_$N/eval.jsonl $OUT/eval_${M}_$N.jsonl
  done
done
