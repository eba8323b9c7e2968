"""How much an unbiased step error alone moves a task's closed-loop values and ranking: the
REAL dynamics (``oracle.oracle_dynamics``) with sigma x N(0, 1) x the data's one-step change std
added to every next state (``evaluate.errors.noisy``), the test policies acting on the states
they see, through the evaluation path of every simulator (``simulate.simulated_returns``:
start states from the data, 1000 steps, gamma, the task's reward and termination).

Every scale runs on the same keys as the exact oracle (the same start states and action
draws), so the comparison is paired; a second exact run on other keys gives the evaluation
noise of that many episodes (tau between two exact runs). A learned simulator whose step error
is of a scale that keeps the ranking here, yet ranks worse, is held back by its bias, not by
the size of its error.

    python experiments/closed_loop_control.py --task ant [--transitions-per-policy 2000]
        [--episodes 32] [--noise 0.003,0.01,0.03] [--data test.npz] [--out DIR]

CPU: Ant, 19 test policies x 32 episodes x 1000 steps, about 2 minutes per scale on 2 cores.
Writes OUT/closed_loop_control_<task>.json and prints a table.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.envs.tasks import get_task, task_names
from rl2s_jax.evaluate.errors import noisy, one_step_std
from rl2s_jax.evaluate.metrics import kendall_tau
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.model.simulator import simulated_returns, start_pool
from rl2s_jax.paper.ablation import load_test_split, parse_noise


def run(ds, task, policies, *, scales, n_episodes: int, horizon: int, gamma: float,
        dynamics=None) -> dict:
    """Per noise scale: each policy's mean return and episode length over n_episodes paired
    episodes, against the exact dynamics on the same keys. dynamics: the exact dynamics
    (default the task's oracle). -> {"exact": {...}, "exact_other_keys": {...},
    "scales": {scale: {"value", "length", "tau_vs_exact", "relative_change"}}}"""
    pool = start_pool(ds)
    noise_std = jnp.asarray(one_step_std(ds, task.position_dims))
    real_dyn = dynamics if dynamics is not None else oracle_dynamics(task)

    @jax.jit
    def values(scale, key):
        ret, length = simulated_returns(policies, noisy(real_dyn, scale, noise_std),
                                        task.reward_fn, task.done_fn, pool, key,
                                        n_episodes=n_episodes, horizon=horizon, gamma=gamma)
        return ret.mean(-1), length.astype(jnp.float32).mean(-1)

    def measure(scale, seed):
        t0 = time.perf_counter()
        v, n = (np.asarray(x, np.float64) for x in values(jnp.float32(scale),
                                                          jax.random.PRNGKey(seed)))
        print(f"[closed-loop control] scale {scale} key {seed}: {time.perf_counter() - t0:.1f}s",
              flush=True)
        return v, n

    exact, exact_len = measure(0.0, 0)
    rnd = lambda xs: [round(float(x), 2) for x in xs]

    def against_exact(v, n):
        return {"value": rnd(v), "length": rnd(n), "tau_vs_exact": round(kendall_tau(exact, v), 3),
                "spread_ratio": round(float(np.std(v) / np.std(exact)), 3),
                "relative_change": round(float(np.mean(np.abs(v - exact))
                                               / np.mean(np.abs(exact))), 3)}

    out = {"episodes": n_episodes, "horizon": horizon, "gamma": gamma,
           "exact": {"value": rnd(exact), "length": rnd(exact_len)},
           "exact_other_keys": against_exact(*measure(0.0, 1)), "scales": {}}
    for scale in scales:
        out["scales"][str(scale)] = against_exact(*measure(scale, 0))
    return out


def table(res: dict) -> str:
    lines = ["| real dynamics, closed loop | tau vs exact (same keys) | value spread vs exact | "
             "mean relative value change | mean episode length |", "|---|---:|---:|---:|---:|",
             f"| exact | 1 | 1 | 0 | {np.mean(res['exact']['length']):.0f} |"]
    rows = [("exact, other keys (evaluation noise)", res["exact_other_keys"])]
    rows += [(f"noise {scale}", r) for scale, r in res["scales"].items()]
    for name, r in rows:
        lines.append(f"| {name} | {r['tau_vs_exact']} | {r['spread_ratio']} | "
                     f"{r['relative_change']} | {np.mean(r['length']):.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", choices=[t for t in task_names() if t != "pointmass"],
                    default="ant")
    ap.add_argument("--transitions-per-policy", type=int, default=2000)
    ap.add_argument("--episodes", type=int, default=32)
    ap.add_argument("--horizon", type=int, default=1000)
    ap.add_argument("--gamma", type=float, default=0.999)
    ap.add_argument("--noise", default="0.003,0.01,0.03")
    ap.add_argument("--data", help="a Dataset .npz of the zoo's test split (default: collect)")
    ap.add_argument("--out", default="results/closed_loop_control")
    args = ap.parse_args(argv)
    scales = parse_noise(args.noise, zero_ok=False)  # 0 is the exact run, always made
    for name in ("transitions_per_policy", "episodes", "horizon"):
        if getattr(args, name) < 1:
            raise SystemExit(f"{name.replace('_', '-')}: expected an int >= 1, got "
                             f"{getattr(args, name)}")
    if not 0 < args.gamma <= 1:
        raise SystemExit(f"gamma: expected a float in (0, 1], got {args.gamma}")
    from rl2s_jax.policy.policy import index_params
    from rl2s_jax.zoo.zoo import load_zoo

    os.makedirs(args.out, exist_ok=True)
    task = get_task(args.task)
    zoo = load_zoo(args.task)
    policies = index_params(zoo.params, zoo.test_ids)
    t0 = time.perf_counter()
    ds = load_test_split(args.task, args.data, args.transitions_per_policy)
    if ds.n_policies != len(zoo.test_ids):
        raise SystemExit(f"data: expected the {len(zoo.test_ids)} test policies of the "
                         f"{args.task} zoo, got {ds.n_policies}")
    res = run(ds, task, policies, scales=scales, n_episodes=args.episodes,
              horizon=args.horizon, gamma=args.gamma)
    res.update(task=args.task, command=" ".join(["python", "experiments/closed_loop_control.py",
                                                 *(argv if argv is not None else sys.argv[1:])]),
               hardware=jax.devices()[0].device_kind, jax_version=jax.__version__,
               wall_s=round(time.perf_counter() - t0, 1))
    path = os.path.join(args.out, f"closed_loop_control_{args.task}.json")
    write_json(path, res)
    print(table(res))
    print(f"[closed-loop control] wrote {path} ({res['wall_s']}s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
