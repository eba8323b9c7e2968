"""Where the time of `rl2s diagnose` goes (issue 62, "Diagnosis fast"): record a task with a
planted actuation delay from its zoo's training policies (and a clean reference with another
seed), then run ``diagnose`` on it with its phase timings, every compiled program logged with
the time it took (``--log-compiles``), and the Python stacks dumped every ``--stack-every``
seconds, so that a run that stalls says where.

    python experiments/diagnose_timing.py --out DIR [--task walker2d] [--lag 3]
        [--transitions-per-policy 5000] [--value-episodes 16] [--seeds 3] [--no-reference]
        [--no-values] [--load-data DIR2] [--stack-every 60]

Writes DIR/timing.json (phases, seconds, the device, the command) and, with --save-data,
DIR/data.npz and DIR/reference.npz.
"""
from __future__ import annotations

import argparse
import faulthandler
import json
import logging
import os
import sys
import time

import jax

from rl2s_jax._files import write_json
from rl2s_jax.app.diagnosis import diagnose
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.diagnose.planted_mjx import collect_planted
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo


def record(task: str, effect: str, effect_kwargs: dict, n: int, value_episodes: int,
           seed: int):
    """The task's dataset with one planted effect, from its shipped zoo's training policies."""
    zoo = load_zoo(task)
    ids = zoo.split_ids("train")
    return collect_planted(
        task, effect, index_params(zoo.params, ids), key=jax.random.PRNGKey(seed),
        transitions_per_policy=n, effect_kwargs=effect_kwargs,
        episode_length=get_task(task).episode_length, policy_names=zoo.policy_names(ids),
        gamma=0.999, value_episodes=value_episodes, progress=False,
        source={"zoo": task, "split": "train", "zoo_ids": ids, "seed": seed})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--task", default="walker2d")
    ap.add_argument("--lag", type=int, default=3)
    ap.add_argument("--transitions-per-policy", type=int, default=5000)
    ap.add_argument("--value-episodes", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--no-values", action="store_true", help="value views off (zoo=None and "
                    "the recorded values dropped)")
    ap.add_argument("--save-data", action="store_true")
    ap.add_argument("--collect-only", action="store_true", help="record (and save), no diagnosis")
    ap.add_argument("--load-data", metavar="DIR2")
    ap.add_argument("--log-compiles", action="store_true")
    ap.add_argument("--stack-every", type=float, default=60.0)
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    if args.log_compiles:
        jax.config.update("jax_log_compiles", True)
        logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                            format="%(relativeCreated)9.0fms %(message)s", force=True)
    faulthandler.dump_traceback_later(args.stack_every, repeat=True, file=sys.stderr)
    t0 = time.perf_counter()
    if args.load_data:
        ds = load_dataset(os.path.join(args.load_data, "data.npz"))
        ref = (None if args.no_reference
               else load_dataset(os.path.join(args.load_data, "reference.npz")))
    else:
        kw = {"lag": args.lag, "actuators": (0,)}
        ds = record(args.task, "delay", kw, args.transitions_per_policy,
                    0 if args.no_values else args.value_episodes, 0)
        ref = (None if args.no_reference else
               record(args.task, "clean", {}, args.transitions_per_policy, 0, 1000))
        if args.save_data:
            save_dataset(os.path.join(args.out, "data.npz"), ds)
            if ref is not None:
                save_dataset(os.path.join(args.out, "reference.npz"), ref)
    collect_s = time.perf_counter() - t0
    if args.no_values and ds.has_values:  # the recorded values would switch the views on
        ds = ds.replace(value=None, value_se=None, value_discounted=None,
                        value_discounted_se=None)
    print(f"[timing] data: {ds.n_transitions} transitions, {ds.n_policies} policies "
          f"({collect_s:.1f}s)", flush=True)
    if args.collect_only:
        faulthandler.cancel_dump_traceback_later()
        return 0
    t0 = time.perf_counter()
    report = diagnose(ds, os.path.join(args.out, "diagnosis"), seeds=tuple(range(args.seeds)),
                      reference=ref, zoo=None if args.no_values else args.task,
                      progress=False, log=lambda s: print(s, flush=True))
    seconds = time.perf_counter() - t0
    faulthandler.cancel_dump_traceback_later()
    out = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
           "transitions": ds.n_transitions, "policies": ds.n_policies,
           "collect_s": round(collect_s, 1), "diagnose_s": round(seconds, 1),
           "phases": report["timings"], "top_cause": report["top_cause"],
           "value_views": report["value_views"],
           "command": "python experiments/diagnose_timing.py " + " ".join(argv or sys.argv[1:])}
    write_json(os.path.join(args.out, "timing.json"), out)
    print(json.dumps(out, indent=1), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
