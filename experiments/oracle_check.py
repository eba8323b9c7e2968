"""The control on its own: the oracle simulator's ranking and VD on a zoo's test policies, over
horizons and episode counts, to find where evaluation is sound before any model is judged.

    python experiments/oracle_check.py --tasks hopper,walker2d,halfcheetah,ant --out DIR
        [--transitions-per-policy 20000] [--value-episodes 16] [--horizons 1000]
        [--episodes 16,64] [--bootstrap 1000] [--split test] [--data-seed D --data-dir DIR]

Per task: ONE collection of the split (``app.pipeline.collect_dataset``), then
``evaluate_oracle``
for every (horizon, episodes) pair with key PRNGKey(1000). Writes DIR/oracle_<task>.json with
the metrics, the 95% bootstrap intervals, the sim-only tau std (the evaluation noise) and the
true and oracle values per policy.

--data-seed D: the protocol's data instead (``paper.protocol.load_or_collect``: the zoo's test
split of paper.py --data-seed D at these --transitions-per-policy and --value-episodes, reused
from --data-dir where paper.py collected it there, else collected the same way), so the oracle
and its noise ceiling (``lane_scores.oracle_noise_ceiling``, per row) are measured on the
protocol run's test policies and true values: paper.py's oracle row of seed 0 (the same key),
one seed instead of paper.py's one per seed. merge_results.py --oracle puts it into that data
seed's by_data_seed entry.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.app.pipeline import collect_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.lane_scores import oracle_noise_ceiling
from rl2s_jax.evaluate.scores import evaluate_oracle
from rl2s_jax.paper.protocol import load_or_collect
from rl2s_jax.zoo.zoo import policies_for


def ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def protocol_test_data(task: str, args):
    """The test Dataset of paper.py --data-seed D at these sizes (reused from --data-dir)."""
    sizes = {"transitions_per_policy": args.transitions_per_policy,
             "value_episodes": args.value_episodes}
    data_dir = args.data_dir or os.path.join(args.out, "data")
    datasets, reused = load_or_collect(task, sizes, data_dir, args.data_seed, None, False)
    print(f"[oracle] {task} data seed {args.data_seed}: "
          f"{'reused from' if reused else 'collected into'} {data_dir}", flush=True)
    return datasets["test"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", default="hopper")
    ap.add_argument("--split", default="test")
    ap.add_argument("--transitions-per-policy", type=int, default=20_000)
    ap.add_argument("--value-episodes", type=int, default=16)
    ap.add_argument("--horizons", type=ints, default=[1000])
    ap.add_argument("--episodes", type=ints, default=[16, 64])
    ap.add_argument("--bootstrap", type=int, default=1000)
    ap.add_argument("--zoo", help="zoo directory (default: the task's shipped zoo)")
    ap.add_argument("--data-seed", type=int, help="the protocol's data of this data seed "
                    "(paper.py --data-seed; --split test only)")
    ap.add_argument("--data-dir", help="with --data-seed: where paper.py's data lies / goes")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if args.data_seed is not None and (args.split != "test" or args.zoo):
        raise SystemExit("data-seed: the protocol's test split of the shipped zoo only "
                         "(no --split, no --zoo)")
    os.makedirs(args.out, exist_ok=True)
    device = jax.devices()[0].device_kind
    for task in args.tasks.split(","):
        t0 = time.perf_counter()
        ds = protocol_test_data(task, args) if args.data_seed is not None else collect_dataset(
            task, args.split, args.transitions_per_policy, value_episodes=args.value_episodes,
            zoo_path=args.zoo, progress=False)
        t_collect = time.perf_counter() - t0
        env, pols = get_task(task).make_env(), policies_for(ds)
        rows = []
        for h in args.horizons:
            for n in args.episodes:
                t1 = time.perf_counter()
                r = evaluate_oracle(task, ds, pols, key=jax.random.PRNGKey(1000), n_episodes=n,
                                    horizon=h, n_boot=args.bootstrap, env=env)
                row = {"horizon": h, "n_episodes": n, "seconds": time.perf_counter() - t1,
                       "metrics": r["metrics"], "intervals": r.get("intervals"),
                       "true_value": r["true_value"], "oracle_value": r["sim_value"],
                       "oracle_length": r["sim_length"]}
                if args.data_seed is not None:  # the truth's SEs are the data's
                    row["noise_ceiling"] = oracle_noise_ceiling(
                        ds, r["true_value"], [r["sim_return_sd"]], n_sim=n, horizon=h,
                        gamma=float(ds.meta.get("gamma") or 0.999))
                rows.append(row)
                m = r["metrics"]
                noise = (r.get("intervals") or {}).get("sim_only", {}).get("kendall_tau", {})
                print(f"[oracle] {task} horizon {h} episodes {n}: tau {m['kendall_tau']:.3f} "
                      f"spearman {m['spearman']:.3f} nDCG@1 {m['ndcg@1']:.3f} AVD "
                      f"{m['avd']:.1f} MVD {m['mvd']:.1f}; eval-noise tau std "
                      f"{noise.get('std', float('nan')):.3f} ({row['seconds']:.0f}s)",
                      flush=True)
        out = {"task": task, "hardware": device, "jax_version": jax.__version__,
               "command": " ".join(["python", "experiments/oracle_check.py", *(argv or
                                                                               sys.argv[1:])]),
               "split": args.split, "policies": ds.n_policies,
               "policy_names": list(ds.meta.get("policy_names") or []),
               "true_value_undiscounted": np.asarray(ds.value).tolist(),
               "true_value_se": np.asarray(ds.value_discounted_se).tolist(),
               "collect_seconds": t_collect, "rows": rows,
               **({} if args.data_seed is None else {"data_seed": args.data_seed})}
        write_json(os.path.join(args.out, f"oracle_{task}.json"), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
