"""Coverage of each test policy's states by the training policies' states (session 22): the
distance from each logged test state to its nearest logged training state, per dim
standardised by the training data (RMS over dims), median and 90th percentile per test
policy, beside the policy's true value. Collects the zoo's data as experiments/paper.py does.

    python experiments/cpu_runs/2026-11-26b/coverage.py walker2d 2000 OUT.json
"""
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))
from paper import load_or_collect  # noqa: E402

task, per_policy, out_path = sys.argv[1], int(sys.argv[2]), sys.argv[3]
t0 = time.time()
sizes = dict(transitions_per_policy=per_policy, value_episodes=4)
ds, _ = load_or_collect(task, sizes, f"/tmp/coverage_{task}", 0, None, False)
train, test = ds["train"], ds["test"]
x = np.asarray(train.obs, np.float64)
mu, sd = x.mean(0), x.std(0) + 1e-8
xn = ((x - mu) / sd).astype(np.float32)
sq = (xn ** 2).sum(1)
names = test.meta.get("policy_names") or [str(p) for p in range(test.n_policies)]
rows = []
for p in range(test.n_policies):
    q = ((np.asarray(test.obs, np.float64)[np.asarray(test.policy_id) == p] - mu) / sd)
    q = q.astype(np.float32)
    best = np.full(len(q), np.inf, np.float32)
    for i in range(0, len(q), 512):
        b = q[i:i + 512]
        d2 = (b ** 2).sum(1)[:, None] + sq[None, :] - 2.0 * b @ xn.T
        best[i:i + 512] = np.maximum(d2.min(1), 0.0)
    rms = np.sqrt(best / xn.shape[1])
    rows.append({"policy": names[p], "true_value": float(np.asarray(test.value)[p]),
                 "median": float(np.median(rms)), "p90": float(np.quantile(rms, 0.9))})
    print(f"{names[p]:>14}  value {rows[-1]['true_value']:8.1f}  nearest training state: "
          f"median {rows[-1]['median']:.3f}  p90 {rows[-1]['p90']:.3f}")
res = {"task": task, "transitions_per_policy": per_policy, "train_policies": train.n_policies,
       "command": "python " + " ".join(sys.argv), "seconds": round(time.time() - t0, 1),
       "policies": rows}
with open(out_path, "w") as f:
    json.dump(res, f, indent=1)
print(f"{time.time() - t0:.0f}s -> {out_path}")
