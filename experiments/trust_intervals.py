"""Measure the value intervals of `rl2s evaluate --level` (issue 64, evaluate/trust.py) at CPU
sizes: collect a zoo's train and test data, a held-out calibration set of perturbed training
policies (app/value_intervals.py ``calibration_data``), train simulators over seeds, and
evaluate the test policies with intervals calibrated (a) on the perturbed policies, (b) on the
training policies alone (optimistic), (c) with all seeds together, and (d) a set of perturbed
test policies evaluated like the test policies. Every command is printed; the
reports land in OUT/*.json and a summary in OUT/summary.json.

    python experiments/trust_intervals.py --task pointmass --out runs/trust_pm
    python experiments/trust_intervals.py --task hopper --out runs/trust_hopper \
        --transitions 2000 --steps 300 --seeds 1

pointmass has no shipped zoo: one of 32 random small policies (different action biases) is
built, split 16 / 16.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.app.value_intervals import calibration_data
from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo import zoo as zoo_mod


def pointmass_zoo(out: str, n: int = 32) -> str:
    """A pointmass zoo of n small random policies, action biases spread over [-2.5, 2.5],
    alternately train / test."""
    rng = np.random.default_rng(0)
    ps = []
    for i, b in enumerate(rng.permutation(np.linspace(-2.5, 2.5, n))):
        p = pol.init_policy(jax.random.PRNGKey(100 + i), 2, 1, hidden=(8,))
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:1].set(float(b))
        p["layers"][0]["w"] = p["layers"][0]["w"] * float(rng.uniform(0.5, 3.0))
        ps.append(p)
    zoo_mod.save_zoo(zoo_mod.Zoo(task="pointmass", params=pol.stack_params(ps),
                                 returns=np.zeros(n, np.float32),
                                 return_se=np.zeros(n, np.float32), origins=[{}] * n,
                                 train_ids=list(range(0, n, 2)), test_ids=list(range(1, n, 2))),
                     out)
    return out


def run(cmd: list[str]) -> None:
    print("$ rl2s " + " ".join(cmd), flush=True)
    t0 = time.time()
    subprocess.run([sys.executable, "-m", "rl2s_jax.cli", *cmd], check=True)
    print(f"  ({time.time() - t0:.0f} s)", flush=True)


def summary(report: dict) -> dict:
    t = report["trust"]
    c = t["calibration"]
    return {"coverage": t["coverage"], "mean_width": t["mean_width"],
            "width_over_range": t["width_over_range"],
            "spread_interval": {k: t["spread_interval"][k] for k in
                                ("what", "coverage", "mean_width", "width_over_range",
                                 "scaled_mean_width")},
            "calibration": {k: c[k] for k in ("n", "n_heldout", "n_train", "used",
                                              "optimistic", "q")},
            "untrusted": [p["name"] for p in t["policies"] if not p["trusted"]],
            "worst": t["worst"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="pointmass")
    ap.add_argument("--out", required=True)
    ap.add_argument("--method", default="bc")
    ap.add_argument("--transitions", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--n-cal", type=int, default=24)
    ap.add_argument("--level", type=float, default=0.9)
    ap.add_argument("--value-episodes", type=int, default=16)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    o = lambda name: os.path.join(a.out, name)  # noqa: E731
    zoo = pointmass_zoo(o("zoo")) if a.task == "pointmass" else a.task
    for split in ("train", "test"):
        if not os.path.exists(o(f"{split}.npz")):
            run(["collect", "--task", a.task, "--zoo", zoo, "--split", split,
                 "--transitions-per-policy", str(a.transitions), "--value-episodes",
                 str(a.value_episodes), "--out", o(f"{split}.npz")])
    for name, split, seed in (("cal", "train", 0), ("test_perturbed", "test", 1)):
        if not os.path.exists(o(f"{name}.npz")):  # held-out calibration; a perturbed test set
            t0 = time.time()
            print(f"calibration_data({zoo!r}, {o(name + '.npz')!r}, n={a.n_cal}, "
                  f"split={split!r}, seed={seed})", flush=True)
            calibration_data(zoo, o(f"{name}.npz"), n=a.n_cal, split=split, seed=seed,
                             value_episodes=a.value_episodes,
                             transitions_per_policy=max(a.transitions // 4, 50))
            print(f"  ({time.time() - t0:.0f} s)", flush=True)
    ckpts = []
    for seed in range(a.seeds):
        run_dir = o(f"{a.method}_s{seed}")
        if not os.path.exists(os.path.join(run_dir, "summary.json")):
            run(["train", "--data", o("train.npz"), "--method", a.method, "--steps",
                 str(a.steps), "--seed", str(seed), "--out", run_dir, "--quiet"])
        ckpts.append(os.path.join(run_dir, "checkpoints"))
    base = ["evaluate", "--data", o("test.npz"), "--bootstrap", "0", "--level", str(a.level)]
    cases = {"perturbed": ["--ckpt", ckpts[0], "--calibration", o("cal.npz")],
             "train_only": ["--ckpt", ckpts[0]]}
    if len(ckpts) > 1:
        cases["seeds_perturbed"] = [x for c in ckpts for x in ("--ckpt", c)] + [
            "--calibration", o("cal.npz")]
    cases["test_perturbed_set"] = ["--ckpt", ckpts[0], "--calibration", o("cal.npz"),
                                   "--data", o("test_perturbed.npz")]  # the last --data wins
    out = {}
    for name, extra in cases.items():
        run(base + extra + ["--json", o(f"eval_{name}.json")])
        with open(o(f"eval_{name}.json")) as f:
            out[name] = summary(json.load(f))
    write_json(o("summary.json"), out)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
