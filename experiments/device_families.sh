#!/usr/bin/env bash
# One task's paper protocol on ONE GPU as two concurrent processes (run through the device tool
# with .whl carried): experiments/paper.py --families adversarial (data, oracle, rl2s + gail,
# their improvement) and, once that process has written the data to $W, --families mle
# (rl2s-bc + bc, their improvement) on the same data, each with half the GPU's memory and
# stopped after LIMIT seconds (default 560; paper.py writes its JSON after each phase). Extra
# arguments go to both. $OUT gets adv/ and mle/ (<task>.json, paper_<task>.log); join them with
#   python experiments/merge_results.py --task TASK --paper adv/TASK.json --paper mle/TASK.json
#   LIMIT=560 bash experiments/device_families.sh TASK [paper.py args]
set -uo pipefail
TASK=${1:?usage: bash experiments/device_families.sh TASK [paper.py args]}
shift
source experiments/device_env.sh
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.45}
LIMIT=${LIMIT:-560}
START=$(date +%s)
mkdir -p $OUT/adv $OUT/mle
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee $OUT/adv/LOG
run() {  # run FAMILY SECONDS [paper.py args]
  local fam=$1 secs=$2
  shift 2
  { time timeout $secs python3 experiments/paper.py --task $TASK --profile gpu --out $OUT/$fam \
      --data-dir $W --families $([ $fam = adv ] && echo adversarial || echo mle) "$@" ; } 2>&1 \
    | grep -v -i -e warn -e "Failed to import" > $OUT/$fam/paper_$TASK.log
}
run adv $LIMIT "$@" &
ADV=$!
# the data is complete once its key file exists (paper.load_or_collect writes it last)
while [ ! -f $W/${TASK}_data.json ] && kill -0 $ADV 2>/dev/null; do sleep 2; done
if [ -f $W/${TASK}_data.json ]; then
  run mle $((LIMIT - $(date +%s) + START)) --no-oracle "$@" &
  MLE=$!
  wait $MLE; echo "mle exit $?"
fi
wait $ADV; echo "adv exit $?"
tail -n 25 $OUT/adv/paper_$TASK.log $OUT/mle/paper_$TASK.log
