"""Benchmarks, measured side by side in one run (`make bench`).

Collection throughput (transitions/s, policy inference, fresh resets and the copy to the host
included) next to raw MJX stepping (vmap(env.step) in a scan, random actions, no resets) for
the same env and batch, and their ratio; collection with a batched reset every step
(refresh_every=1), to show what resetting rarely buys. With --breakdown also the pieces: raw
stepping with the policies' actions, raw stepping where ended envs go back to a stored start
(the state distribution of collection without its machinery), collection without the copy to
the host, and with a reset every 32 steps.

    python experiments/bench.py [--task hopper] [--batch 1024 8192 ...] [--breakdown]
        [--refresh-every K ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import sys
import time

import jax

from rl2s_jax._files import write_json
from rl2s_jax.data.collect import make_rollout_step
from rl2s_jax.envs.checks import tree_where
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy.policy import init_policy, sample_action, stack_params


def timed(fn, *args, repeats: int = 3):
    """Best wall time of fn(*args) over repeats, after one warm-up (compile) call."""
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def bench_batch(env, n_policies: int, batch: int, steps: int, reset_every_step: bool,
                breakdown: bool = False, refresh_every: tuple[int, ...] = ()) -> dict:
    """Transitions/s of raw stepping and of collection variants at one batch size.

    ``breakdown`` adds the pieces: raw stepping with the policies' actions instead of random
    ones ("policy"); raw stepping in which an env that is done goes back to its stored first
    state by a select ("raw_autoreset": no reset computed, no records); collection without
    the copy of its records to the host ("collect_no_copy"); collection resetting used starts
    every 32 steps instead of 8 ("collect_refresh_every_32"). ``refresh_every``: more
    collection variants, one per period ("collect_refresh_every_K")."""
    E = batch // n_policies
    B = n_policies * E
    keys = jax.random.split(jax.random.PRNGKey(0), n_policies)
    params = stack_params([init_policy(k, env.observation_size, env.action_size)
                           for k in keys])
    state0 = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), B))
    v_step, act = jax.vmap(env.step), jax.vmap(sample_action)

    def raw_with(actions, autoreset: bool = False):
        @jax.jit
        def raw(state, key):
            def body(c, _):
                s, k = c
                k, ka = jax.random.split(k)
                nxt = v_step(s, actions(s, ka))
                if autoreset:
                    nxt = tree_where(nxt.done > 0.5, state, nxt)
                return (nxt, k), None
            return jax.lax.scan(body, (state, key), None, length=steps)[0][0].obs
        return raw

    def random_actions(s, k):
        return jax.random.uniform(k, (B, env.action_size), minval=-1.0, maxval=1.0)

    def policy_actions(s, k):
        a, _, _ = act(params, s.obs.reshape(n_policies, E, -1), jax.random.split(k, n_policies))
        return a.reshape(B, -1)

    raw_s = timed(raw_with(random_actions), state0, jax.random.PRNGKey(2))
    row = {"batch": B, "policies": n_policies, "envs_per_policy": E, "steps": steps,
           "raw_steps_per_s": B * steps / raw_s}
    variants = [("collect", 8, True)]
    if reset_every_step:
        variants.append(("collect_reset_every_step", 1, True))
    if breakdown:
        for label, actions, autoreset in (("policy", policy_actions, False),
                                          ("raw_autoreset", random_actions, True)):
            row[f"{label}_steps_per_s"] = B * steps / timed(
                raw_with(actions, autoreset), state0, jax.random.PRNGKey(2))
            row[f"{label}_ratio"] = row[f"{label}_steps_per_s"] / row["raw_steps_per_s"]
            _progress(B, label, row)
        variants += [("collect_no_copy", 8, False), ("collect_refresh_every_32", 32, True)]
    variants += [(f"collect_refresh_every_{k}", k, True) for k in refresh_every
                 if f"collect_refresh_every_{k}" not in [v[0] for v in variants]]
    for label, every, copy in variants:
        init, step = make_rollout_step(env, n_policies, E, episode_length=1000,
                                       refresh_every=every)
        carry = jax.jit(init)(jax.random.PRNGKey(3))
        chunk = jax.jit(lambda c, step=step: jax.lax.scan(
            lambda x, _: step(params, x), c, None, length=steps))

        def run(c, chunk=chunk, copy=copy):
            # as collect() does: one jitted scanned chunk, its records copied to the host
            c, records = chunk(c)
            if copy:
                jax.device_get(records)
            else:
                jax.block_until_ready(records)
            return c.t
        row[f"{label}_steps_per_s"] = B * steps / timed(run, carry)
        row[f"{label}_ratio"] = row[f"{label}_steps_per_s"] / row["raw_steps_per_s"]
        _progress(B, label, row)
        if copy:  # how often envs end (two ends in one refresh period force a reset)
            _, records = chunk(carry)
            ends = records["done"] | records["truncated"]
            row[f"{label}_end_rate"] = float(ends.mean())
    return row


def _progress(batch: int, label: str, row: dict) -> None:
    print(f"#   batch {batch} {label}: {row[f'{label}_steps_per_s']:,.0f}/s, ratio "
          f"{row[f'{label}_ratio']:.3f}", file=sys.stderr, flush=True)


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
    parser.add_argument("--breakdown", action="store_true",
                        help="also time the pieces: policy actions, no copy to the host")
    parser.add_argument("--refresh-every", type=int, nargs="*", default=[],
                        help="also time collection with a reset of used starts every K steps")
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    env = get_task(args.task).make_env()
    device = str(jax.devices()[0].device_kind)
    print(f"# collection vs raw MJX stepping: {args.task}, {device}, jax {jax.__version__}, "
          f"{args.steps} steps per timed run, best of 3")
    cols = [("collect", "collect"), ("collect_reset_every_step", "reset every step")]
    if args.breakdown:
        cols += [("policy", "raw + policy actions"), ("raw_autoreset", "raw + autoreset"),
                 ("collect_no_copy", "collect, no host copy"),
                 ("collect_refresh_every_32", "collect, reset every 32 steps")]
    cols += [(f"collect_refresh_every_{k}", f"collect, reset every {k} steps")
             for k in args.refresh_every if f"collect_refresh_every_{k}" not in dict(cols)]
    print("| batch | raw MJX steps/s | " + " | ".join(f"{c} /s | ratio" for _, c in cols) + " |")
    print("|---:|---:|" + "---:|---:|" * len(cols))
    rows = []
    for b in args.batch:
        r = bench_batch(env, args.policies, b, args.steps, b in args.reset_every_step_batch,
                        args.breakdown, tuple(args.refresh_every))
        rows.append(r)
        cells = [f"{r[k + '_steps_per_s']:,.0f} | {r[k + '_ratio']:.2f}"
                 if k + "_ratio" in r else "- | -" for k, _ in cols]
        print(f"| {r['batch']} | {r['raw_steps_per_s']:,.0f} | " + " | ".join(cells) + " |",
              flush=True)
    if args.json:
        write_json(args.json, {"task": args.task, "device": device, "jax": jax.__version__,
                               "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
