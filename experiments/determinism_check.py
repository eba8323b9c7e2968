"""Is a paired measurement exact? Each zoo's test policies measured twice in one batch
(``measure_values(common_groups=2)``: the copies share start states and action-noise draws),
and the whole measurement repeated, so any difference is the backend's arithmetic.

    python experiments/determinism_check.py --out DIR [--tasks hopper,walker2d,...]
        [--episodes 32] [--repeats 2]

Run it with and without XLA_FLAGS=--xla_gpu_deterministic_ops=true to see what the flag
changes: per task the largest |return| difference between the two copies of a policy, the
share of episodes that differ, the largest difference between repeats, and the seconds of
each measurement. Writes DIR/determinism_<flag>.json.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from rl2s_jax.collect import measure_values  # noqa: E402
from rl2s_jax.policies import index_params, load_zoo  # noqa: E402
from rl2s_jax.tasks import get_task  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", default="hopper,walker2d,halfcheetah,ant")
    ap.add_argument("--out", required=True)
    ap.add_argument("--episodes", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    flags = os.environ.get("XLA_FLAGS", "")
    tag = "deterministic" if "xla_gpu_deterministic_ops=true" in flags else "default"
    out = {"xla_flags": flags, "backend": jax.default_backend(),
           "device": str(jax.devices()[0]), "tasks": {}}
    for name in args.tasks.split(","):
        task, zoo = get_task(name), load_zoo(name)
        pols = index_params(zoo.params, np.asarray(zoo.split_ids("test")))
        both = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x]), pols)
        P = len(zoo.split_ids("test"))
        runs, secs = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            r = measure_values(task.make_env(), both, key=jax.random.PRNGKey(7),
                               n_episodes=args.episodes, episode_length=task.episode_length,
                               common_groups=2, per_episode=True)["returns"]
            secs.append(round(time.perf_counter() - t0, 2))
            runs.append(np.asarray(r, np.float64))
        d = np.abs(runs[0][:P] - runs[0][P:])
        rep = max(float(np.abs(x - runs[0]).max()) for x in runs[1:]) if len(runs) > 1 else 0.0
        out["tasks"][name] = {
            "policies": P, "episodes": args.episodes,
            "copies_max_abs_diff": float(d.max()),
            "copies_share_of_episodes_differing": float((d > 0).mean()),
            "copies_mean_abs_diff_of_policy_means": float(np.abs(d.mean(1)).mean()),
            "repeats_max_abs_diff": rep, "seconds": secs}
        print(name, tag, json.dumps(out["tasks"][name]), flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, f"determinism_{tag}.json"), "w") as f:
        json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
