"""The paper's eps sweep (Fig. 5) as one vmapped program: every (eps, seed) pair is one lane of
``jax.vmap(train_steps)``; test-policy VD and ranking are measured for every lane every
``--eval-every`` steps.

    python experiments/eps_sweep.py --train train.npz --test test.npz [--method rl2s]
        [--eps 0.05 0.1 0.25 0.5 1.0] [--seeds 1] [--steps 1000] [--eval-every 250]
        [--profile auto|cpu|gpu] [--set field=value ...] [--json out.json]
"""
from __future__ import annotations

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.app.training import make_config, parse_overrides
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.evaluate.scores import evaluate_simulator
from rl2s_jax.sharding import initialize_distributed, is_writer, lane_mesh, shard_lanes
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.step import init, simulator, train_steps
from rl2s_jax.zoo.zoo import policies_for


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train", required=True)
    ap.add_argument("--test", required=True)
    ap.add_argument("--method", default="rl2s", choices=("rl2s", "rl2s-bc"))
    ap.add_argument("--eps", type=float, nargs="+", default=[0.05, 0.1, 0.25, 0.5, 1.0])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--eval-episodes", type=int, default=16)
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    if args.steps % args.eval_every:
        raise SystemExit("steps: expected a multiple of --eval-every")
    initialize_distributed()  # multi-host, when the coordinator variables are set
    profile = args.profile if args.profile != "auto" else (
        "gpu" if jax.default_backend() == "gpu" else "cpu")
    train_ds, test_ds = load_dataset(args.train), load_dataset(args.test)
    cfg = make_config(train_ds, args.method, profile, overrides=parse_overrides(args.set))
    data = make_train_data(train_ds, policies_for(train_ds), cfg)
    test_pols = policies_for(test_ds)
    lanes = [(e, s) for e in args.eps for s in range(args.seeds)]
    eps = jnp.asarray([e for e, _ in lanes], jnp.float32)
    keys = jnp.stack([jax.random.PRNGKey(s) for _, s in lanes])
    t0 = time.perf_counter()
    states = jax.jit(jax.vmap(lambda k, e: init(k, cfg, data, eps=e)))(keys, eps)
    mesh = lane_mesh(len(lanes))  # lanes over the local devices (one: unchanged)
    states = shard_lanes(states, mesh)
    run = jax.jit(jax.vmap(lambda s: train_steps(s, data, args.eval_every)[0]))
    print(f"{len(lanes)} lanes over {mesh.size} device(s) ({args.method}, profile {profile}, "
          f"{jax.devices()[0].device_kind})"
          f"; init {time.perf_counter() - t0:.1f}s", flush=True)
    rows = []
    for _ in range(args.steps // args.eval_every):
        t0 = time.perf_counter()
        states = jax.block_until_ready(run(states))
        seconds = time.perf_counter() - t0
        step = int(states.step[0])
        for i, (e, s) in enumerate(lanes):
            one = jax.tree_util.tree_map(lambda x, i=i: x[i], states)
            r = evaluate_simulator(simulator(one), test_ds, test_pols,
                                   key=jax.random.PRNGKey(1000 + s),
                                   n_episodes=args.eval_episodes, horizon=cfg.vd.horizon,
                                   gamma=cfg.gamma)
            rows.append({"step": step, "eps": e, "seed": s, **r["metrics"],
                         "n_selected": int(np.asarray(one.selected).sum())})
        print(f"step {step}: {args.eval_every} steps of {len(lanes)} lanes in {seconds:.1f}s",
              flush=True)
        for row in rows[-len(lanes):]:
            print(f"  eps {row['eps']:<5} seed {row['seed']}  AVD {row['avd']:8.1f}  MVD "
                  f"{row['mvd']:8.1f}  tau {row['kendall_tau']:6.3f}  nDCG@1 "
                  f"{row['ndcg@1']:.3f}  selected {row['n_selected']}", flush=True)
    if args.json and is_writer():
        write_json(args.json, {"method": args.method, "profile": profile,
                               "config": cfg.to_dict(),
                               "device": jax.devices()[0].device_kind, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
