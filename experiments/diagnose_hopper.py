"""Diagnosis on MJX Hopper with planted effects: collect data from the shipped zoo's training
policies in a Hopper with one planted effect (clean, actuation delay, per-episode mass,
signal-dependent noise, hidden joint velocities, actuator gain drifting over the recording
order), run `diagnose` on each, and tabulate what it found against the truth.

    python experiments/diagnose_hopper.py --out DIR [--effects clean delay episode_param noise
        unobserved drift] [--reference] [--transitions-per-policy 5000] [--seeds 3]
        [--model-steps N] [--value-episodes 0] [--sim-episodes 8] [--save-data] [--load-data DIR]

``--reference``: also record a clean Hopper with another seed and diagnose differentially
against it (``diagnose(reference=...)``); "unobserved" is diagnosed without it, since a
reference with the same observation hides the same state.
Writes DIR/<effect>/report.{json,md} + plots, and DIR/summary.{json,md}. ``--save-data``
also writes each recording (DIR/<effect>/data.npz, DIR/reference.npz); ``--load-data DIR2``
diagnoses the recordings saved there instead of collecting (for example GPU-collected data
re-diagnosed on a CPU).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax
import numpy as np

from rl2s_jax._files import write_text
from rl2s_jax.app.diagnosis import diagnose
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.diagnose.model import ModelSpec
from rl2s_jax.diagnose.planted_mjx import EFFECTS, collect_planted
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

ZOO = "hopper"


def record(effect: str, transitions_per_policy: int, value_episodes: int, seed: int,
           episode_length: int | None = None):
    """The Hopper dataset of ``effect`` from the zoo's training policies."""
    zoo = load_zoo("hopper")
    ids = zoo.split_ids("train")
    return collect_planted(
        "hopper", effect, index_params(zoo.params, ids), key=jax.random.PRNGKey(seed),
        transitions_per_policy=transitions_per_policy,
        episode_length=episode_length or get_task("hopper").episode_length,
        policy_names=zoo.policy_names(ids), gamma=0.999, value_episodes=value_episodes,
        progress=False, source={"zoo": ZOO, "split": "train", "zoo_ids": ids, "seed": seed})


def expected_cause(truth: dict) -> str:
    return "none" if truth["effect"] == "none" else truth["effect"]


def write_summary(args, argv, device, rows) -> None:
    """DIR/summary.json and summary.md (rewritten after every effect, so a cut-off run keeps
    what it finished)."""
    summary = {"device": device, "jax": jax.__version__, "seeds": args.seeds,
               "reference": args.reference,
               "transitions_per_policy": args.transitions_per_policy,
               "command": "python experiments/diagnose_hopper.py " + " ".join(argv or []),
               "rows": rows}
    write_text(os.path.join(args.out, "summary.json"),
               json.dumps(summary, indent=1, default=lambda x: np.asarray(x).tolist()))
    lines = ["| planted | truth | mode | top cause | planted cause found? | confidence | details "
             "| held-out NLL base -> extended (diff ± std) | MSE base -> extended "
             "| AVD base -> extended |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n, m = r["heldout_nll"], r["heldout_mse"]
        truth = {k: v for k, v in r["truth"].items() if k in ("effect", "lag", "actuators",
                                                               "dims", "over")}
        found = ("yes, top" if r["found"] else
                 f"ranked {r['rank']}" if r["rank"] else "no")
        nll = (f"{n['before']:.3f} -> {n['after']:.3f} ({n['diff']:+.3f} ± {n['diff_std']:.3f})"
               if "after" in n else f"{n['before']:.3f} (no extension)")
        mse = (f"{m['before']:.4f} -> {m['after']:.4f}" if "after" in m
               else f"{m['before']:.4f}")
        a = r.get("avd")
        avd = ("-" if a is None else
               f"{a['before']:.1f} -> {a['after']:.1f} ({a['diff']:+.1f} ± {a['diff_std']:.1f})"
               if "after" in a else f"{a['before']:.1f}")
        lines.append(f"| {r['effect']} | {truth} | {r['mode']} | **{r['top_cause']}** | "
                     f"{found} | {r['confidence']:.2f} | {r['details']} | {nll} | {mse} | {avd} |")
    with open(os.path.join(args.out, "summary.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--effects", nargs="+", default=list(EFFECTS), choices=list(EFFECTS))
    ap.add_argument("--reference", action="store_true",
                    help="diagnose differentially against a clean recording (seed + 1000)")
    ap.add_argument("--transitions-per-policy", type=int, default=5000)
    ap.add_argument("--value-episodes", type=int, default=0,
                    help="real episodes per policy for the true values (0: no value views)")
    ap.add_argument("--sim-episodes", type=int, default=8,
                    help="simulated episodes per policy and model seed for AVD")
    ap.add_argument("--episode-length", type=int)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--model-steps", type=int)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save-data", action="store_true",
                    help="write each recording to DIR/<effect>/data.npz (reference.npz)")
    ap.add_argument("--load-data", metavar="DIR2",
                    help="diagnose the recordings a --save-data run wrote to DIR2")
    ap.add_argument("--base-from-clean", action="store_true",
                    help="diagnose the planted effects against the model the clean run's "
                    "diagnosis extended (clean runs first): what is wrong beyond what clean "
                    "Hopper already shows")
    args = ap.parse_args(argv)
    if args.load_data:  # every file must be there before any work is spent
        wanted = [os.path.join(args.load_data, e, "data.npz") for e in args.effects]
        if args.reference:
            wanted.append(os.path.join(args.load_data, "reference.npz"))
        missing = [w for w in wanted if not os.path.isfile(w)]
        if missing:
            ap.error(f"--load-data: expected saved recordings, missing {missing}")
    if args.base_from_clean:
        args.effects = ["clean"] + [e for e in args.effects if e != "clean"]
    os.makedirs(args.out, exist_ok=True)
    spec = ModelSpec()
    if args.model_steps:
        spec = dataclasses.replace(spec, steps=args.model_steps)
    device = jax.devices()[0].device_kind
    rows = []
    clean_reference = None
    if args.reference:
        t0 = time.perf_counter()
        if args.load_data:
            clean_reference = load_dataset(os.path.join(args.load_data, "reference.npz"))
        else:
            clean_reference = record("clean", args.transitions_per_policy, 0,
                                     args.seed + 1000, args.episode_length)
        if args.save_data:
            save_dataset(os.path.join(args.out, "reference.npz"), clean_reference)
        print(f"[reference] clean Hopper, seed {args.seed + 1000}: "
              f"{clean_reference.n_transitions} transitions in {time.perf_counter() - t0:.0f}s",
              flush=True)
    for effect in args.effects:
        t0 = time.perf_counter()
        if args.load_data:
            ds = load_dataset(os.path.join(args.load_data, effect, "data.npz"))
        else:
            ds = record(effect, args.transitions_per_policy, args.value_episodes, args.seed,
                        args.episode_length)
        t_collect = time.perf_counter() - t0
        if args.save_data:
            os.makedirs(os.path.join(args.out, effect), exist_ok=True)
            save_dataset(os.path.join(args.out, effect, "data.npz"), ds)
        print(f"[{effect}] collected {ds.n_transitions} transitions in {t_collect:.0f}s",
              flush=True)
        truth = ds.meta["source"]["planted"]
        reference = clean_reference
        if reference is not None and "removed_obs_dims" in truth:
            # A reference recorded with the same sensors lacks the same dims, so a hidden state
            # is in both datasets and nothing is new in the target: diagnosed without one.
            reference = None
            print(f"[{effect}] diagnosed without the reference: a clean recording with the "
                  "same observation hides the same state", flush=True)
        report = diagnose(ds, os.path.join(args.out, effect), seeds=tuple(range(args.seeds)),
                          base_spec=spec, reference=reference,
                          zoo=ZOO if args.value_episodes else None,
                          value_episodes=args.sim_episodes,
                          log=lambda s, e=effect: print(f"[{e}] {s}", flush=True))
        if effect == "clean" and args.base_from_clean:
            ext = report["extension"]["extended"]
            spec = dataclasses.replace(spec, **{k: (tuple(v) if isinstance(v, list) else v)
                                                for k, v in ext.items() if k != "extensions"})
            print(f"[clean] the planted effects are diagnosed against {spec.extensions}",
                  flush=True)
        top = report["causes"][0]
        g = report["gain"]
        names = [c["name"] for c in report["causes"] if c["significant"]]
        want = expected_cause(truth)
        row = {"effect": effect, "truth": truth,
               "mode": "differential" if reference is not None else "plain",
               "top_cause": report["top_cause"], "confidence": report["confidence"],
               "found": report["top_cause"] == want,
               "rank": names.index(want) + 1 if want in names else None,
               "score": top["score"], "p_value": top["p_value"],
               "details": {k: v for k, v in top["details"].items()
                           if k in ("lag", "actuators", "dims", "over", "lags")},
               "base": report["extension"]["base"]["extensions"],
               "extension": report["extension"]["extended"]["extensions"],
               "causes": [{k: c[k] for k in ("name", "score", "p_value", "significant")}
                          for c in report["causes"]],
               "collect_seconds": round(t_collect, 1), "diagnose_seconds": report["seconds"],
               "transitions": ds.n_transitions}
        for k in ("heldout_nll", "heldout_mse", f"kstep_rmse@{g['k_max']}", "avd",
                  "kendall_tau"):
            if k not in g["before"]:
                continue
            row[k] = {"before": g["before"][k], "before_std": g["before"][f"{k}_std"]}
            if g["after"]:
                row[k].update(after=g["after"][k], after_std=g["after"][f"{k}_std"],
                              diff=g["difference"][k]["mean"],
                              diff_std=g["difference"][k]["std"])
        rows.append(row)
        print(f"[{effect}] truth {row['truth']} -> {row['top_cause']} "
              f"(confidence {row['confidence']:.2f}) {row['details']}", flush=True)
        write_summary(args, argv, device, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(__import__("sys").argv[1:]))
