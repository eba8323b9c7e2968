"""Why the deployment guard values full episodes: a policy fine-tuned over short simulated
episodes can gain over them and lose over the real ones (issue 39, `make hopper`'s CPU bar).

    python experiments/guard_horizon.py [--run results/hopper] [--method bc] [--policy 15]
        [--episodes 8] [--lengths 100,300,1000]

Re-runs `rl2s pipeline`'s SAC fine-tuning in one method's simulator of a finished CPU pipeline
run (its test data and checkpoint; the pipeline's key for that method, so the same fine-tuned
actors as its report), then measures the start and fine-tuned policy's real returns, paired
(the same start states and noise), over episodes of each length, and each elite member's
predicted gain at the fine-tuning's horizon and at the full episode. Prints one line each.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.app.pipeline import PROFILES, pipeline_keys
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.improve.finetune import improve_policies, member_values, paired_episode_returns
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.policy.sac import SACConfig
from rl2s_jax.train.checkpoint import load_simulator
from rl2s_jax.train.config import METHODS  # the pipeline's default order of its checkpoints
from rl2s_jax.zoo.zoo import policies_for


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", default="results/hopper", help="a `rl2s pipeline` --out (cpu)")
    ap.add_argument("--method", default="bc", choices=METHODS)
    ap.add_argument("--policy", type=int, default=15, help="test policy index (15: hopper-032)")
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--lengths", default="100,300,1000")
    ap.add_argument("--horizon", type=int, default=100, help="the fine-tuning's episodes")
    ap.add_argument("--iterations", type=int, default=300)
    args = ap.parse_args(argv)
    ds = load_dataset(f"{args.run}/test.npz")
    task = get_task(ds.meta["task"])
    policies, pool = policies_for(ds), start_pool(ds)
    cfg = SACConfig.fine_tuning(**{"episode_length": args.horizon, **PROFILES["cpu"]["sac"]})
    sim = load_simulator(f"{args.run}/{args.method}/checkpoints")
    p, n = args.policy, len(ds.value)
    keys = pipeline_keys(0, METHODS.index(args.method))  # `rl2s pipeline`'s, seed 0
    tuned, _ = improve_policies(sim, task, pool, policies, keys["improve"], cfg,
                                n_iterations=args.iterations, chunk_iterations=args.iterations)
    name = (ds.meta.get("policy_names") or [f"policy-{p}"] * n)[p]
    env, gamma = task.make_env(), float(ds.meta.get("gamma") or 0.999)
    for length in (int(x) for x in args.lengths.split(",")):
        r0, (r1,) = paired_episode_returns(env, policies, [tuned], keys["measure"],
                                           n_episodes=args.episodes, episode_length=length,
                                           gamma=gamma)
        c0, c1 = r0[p].mean(), r1[p].mean()
        print(f"{name} in {args.method}'s simulator, real {length}-step episodes "
              f"({args.episodes}, paired): C0 {c0:.1f}  C1 {c1:.1f}  "
              f"gain {(c1 - c0) / abs(c0):+.3f}")
    both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), policies, tuned)
    for h in sorted({args.horizon, int(ds.meta.get("episode_length") or task.episode_length)}):
        v = member_values(sim, task, both, pool, keys["guard"], n_episodes=16,
                          horizon=h, gamma=gamma)
        gain = (v[:, n + p] - v[:, p]) / np.abs(v[:, p])
        print(f"{name}: the elite members' predicted gain over {h} simulated steps: "
              f"{np.round(gain, 3).tolist()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
