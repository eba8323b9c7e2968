"""Benchmarks, measured side by side in one run (`make bench`).

Collection throughput (transitions/s, policy inference, fresh resets and the copy to the host
included) next to raw MJX stepping (vmap(env.step) in a scan, random actions, no resets) for
the same env and batch, and their ratio. Also collection with a full reset every step
(refresh_fraction=1), to show what the pooled fresh starts buy.

    python experiments/bench.py [--task hopper] [--batch 1024 8192 ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax

from rl2s_jax.collect import make_rollout_step
from rl2s_jax.policies import init_policy, stack_params
from rl2s_jax.tasks import get_task


def timed(fn, *args, repeats: int = 3):
    """Best wall time of fn(*args) over repeats, after one warm-up (compile) call."""
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def bench_batch(env, n_policies: int, batch: int, steps: int, reset_every_step: bool) -> dict:
    E = batch // n_policies
    B = n_policies * E
    keys = jax.random.split(jax.random.PRNGKey(0), n_policies)
    params = stack_params([init_policy(k, env.observation_size, env.action_size)
                           for k in keys])
    state0 = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), B))

    @jax.jit
    def raw(state, key):
        def body(c, _):
            s, k = c
            k, ka = jax.random.split(k)
            a = jax.random.uniform(ka, (B, env.action_size), minval=-1.0, maxval=1.0)
            return (jax.vmap(env.step)(s, a), k), None
        return jax.lax.scan(body, (state, key), None, length=steps)[0][0].obs

    raw_s = timed(raw, state0, jax.random.PRNGKey(2))
    row = {"batch": B, "policies": n_policies, "envs_per_policy": E, "steps": steps,
           "raw_steps_per_s": B * steps / raw_s}
    variants = [("collect", 0.125)] + ([("collect_reset_every_step", 1.0)]
                                       if reset_every_step else [])
    for label, frac in variants:
        init, step = make_rollout_step(env, n_policies, E, episode_length=1000,
                                       refresh_fraction=frac)
        carry = jax.jit(init)(jax.random.PRNGKey(3))
        chunk = jax.jit(lambda c, step=step: jax.lax.scan(
            lambda x, _: step(params, x), c, None, length=steps))

        def run(c, chunk=chunk):
            # as collect() does: one jitted scanned chunk, its records copied to the host
            c, records = chunk(c)
            jax.device_get(records)
            return c.t
        row[f"{label}_steps_per_s"] = B * steps / timed(run, carry)
        row[f"{label}_ratio"] = row[f"{label}_steps_per_s"] / row["raw_steps_per_s"]
    return row


def main(argv=None) -> int:
    on_gpu = jax.default_backend() == "gpu"
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="hopper")
    parser.add_argument("--batch", type=int, nargs="+",
                        default=[1024, 2048, 4096, 8192, 16384, 32768] if on_gpu else [64, 256])
    parser.add_argument("--policies", type=int, default=16)
    parser.add_argument("--steps", type=int, default=200 if on_gpu else 20)
    parser.add_argument("--reset-every-step-batch", type=int, nargs="*", default=[8192, 64],
                        help="batch sizes at which to also time a full reset every step")
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    env = get_task(args.task).make_env()
    device = str(jax.devices()[0].device_kind)
    print(f"# collection vs raw MJX stepping: {args.task}, {device}, jax {jax.__version__}, "
          f"{args.steps} steps per timed run, best of 3")
    print("| batch | raw MJX steps/s | collect transitions/s | ratio | reset-every-step "
          "transitions/s | ratio |")
    print("|---:|---:|---:|---:|---:|---:|")
    rows = []
    for b in args.batch:
        r = bench_batch(env, args.policies, b, args.steps, b in args.reset_every_step_batch)
        rows.append(r)
        full = (f"{r['collect_reset_every_step_steps_per_s']:,.0f} | "
                f"{r['collect_reset_every_step_ratio']:.2f}"
                if "collect_reset_every_step_ratio" in r else "- | -")
        print(f"| {r['batch']} | {r['raw_steps_per_s']:,.0f} | {r['collect_steps_per_s']:,.0f} "
              f"| {r['collect_ratio']:.2f} | {full} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"task": args.task, "device": device, "jax": jax.__version__,
                       "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
