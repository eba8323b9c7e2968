"""The real-env control of policy improvement (issue 11): SAC fine-tuning of a zoo's test
policies inside the real MJX env, with the same settings as experiments/paper.py's
improvement phase, and their real returns before and after. No simulator is needed.

    python experiments/improve_control.py --tasks hopper,walker2d,halfcheetah,ant --out DIR
        [--policies 0] [--seeds 2] [--iterations 2000] [--episodes 16] [--sac-envs 16]
        [--critic-warmup 500] [--updates-per-step 1] [--sac-set KEY=VALUE ...] [--plain]
        [--select-episodes 0] [--select-every 400] [--select-z 2] [--zoo-recipe] [--ids ID ...]

For each task: C0 and C1 of every chosen test policy (``--policies`` N spread over their
returns, 0 = all) over ``--episodes`` fresh real episodes, for ``--seeds`` SAC seeds (one
vmapped program over seeds x policies; ``improve.improve_in_real_env``); per seed
MPI = min I and API = mean I, their mean over seeds and 95% bootstrap intervals
(``stats.improvement_intervals``: policies resampled, returns redrawn from their standard
errors). ``--plain`` also runs plain SAC (``SACConfig()``'s from-scratch defaults: alpha from
1, target entropy -action_size, no KL anchor) with the same budget, for comparison.
``--select-episodes E`` (> 0): early stopping on real validation returns: the actor is kept
every ``--select-every`` iterations and each policy deploys the snapshot with a significant
paired gain over its start on E further real episodes (``improve.select_by_validation``), else
its start; the JSON then also holds the undeployed final snapshot's MPI / API ("final_*").
``--zoo-recipe``: the discount, reward scaling and batch size of the SAC that trained the
task's zoo (``zoo.build.ZOO_SAC``) and a 2^19-row buffer, under the fine-tuning settings
(``--sac-set`` still wins). Fine-tuning at the zoo's discount and reward scale is what made the
control gain (docs/RESULTS.md, "Policy improvement: the real-env control").
Writes OUT/control_<task>.json after each task and prints a table.

    python experiments/improve_control.py --describe docs/results/control_zoo_recipe/*.json
    python experiments/improve_control.py --combine A.json B.json --out DIR

The first reads such files instead (``describe``): per task and config, of the policies below
the zoo's top quartile, where they start (fraction of the zoo's top), how far the final actors
moved (KL from the start), their median gain, final and deployed, and how many stayed at the
start.
``--first-seed K`` runs seeds K .. K + seeds - 1 (a control split over GPUs); ``--combine``
joins such runs' seeds into one control_<task>.json (``combine``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from rl2s_jax._files import write_json  # noqa: E402
from rl2s_jax.app.report import machine_info  # noqa: E402
from rl2s_jax.app.training import parse_overrides  # noqa: E402
from rl2s_jax.envs.tasks import get_task, task_names  # noqa: E402
from rl2s_jax.improve.finetune import (
    improve_in_real_env,
    improvement_metrics,
    median_gain,
)
from rl2s_jax.policy.policy import index_params
from rl2s_jax.policy.sac import SACConfig  # noqa: E402
from rl2s_jax.stats import improvement_intervals  # noqa: E402
from rl2s_jax.zoo.build import fine_tuning_recipe  # noqa: E402
from rl2s_jax.zoo.zoo import load_zoo  # noqa: E402


def log(msg: str) -> None:
    print(msg, flush=True)


def pick(returns: np.ndarray, n: int) -> list[int]:
    """n indices spread evenly over the sorted returns (all when n <= 0 or n >= len)."""
    order = np.argsort(returns, kind="stable")
    if n <= 0 or n >= len(order):
        return sorted(order.tolist())
    return sorted(order[np.unique(np.round(np.linspace(0, len(order) - 1, n)).astype(int))]
                  .tolist())


def sac_configs(args, episode_length: int, task_name: str | None = None
                ) -> dict[str, SACConfig]:
    fields = {f.name for f in dataclasses.fields(SACConfig)}
    over = parse_overrides(args.sac_set)
    unknown = sorted(set(over) - fields)
    if unknown:
        raise SystemExit(f"sac-set: unknown SACConfig field(s) {unknown}")
    for k in ("hidden", "actor_hidden"):
        if k in over:
            over[k] = tuple(over[k])
    sizes = dict(episode_length=episode_length, n_envs=args.sac_envs,
                 critic_warmup_updates=args.critic_warmup,
                 updates_per_step=args.updates_per_step,
                 buffer_size=min(100_000, args.sac_envs * (64 + args.iterations)))
    if getattr(args, "zoo_recipe", False) and task_name is not None:
        sizes.update(fine_tuning_recipe(task_name))
    out = {"fine_tuning": SACConfig.fine_tuning(**{**sizes, **over})}
    if args.plain:
        out["plain"] = SACConfig(**{**sizes, "critic_warmup_updates": 0, **over})
    for c in out.values():
        c.validate()
    return out


def summarise(res: dict, R: int, P: int) -> dict:
    """MPI / API per seed, their means and 95% bootstrap intervals from one paired
    measurement (``measure_improvement``'s fields, [R * P] as seeds x policies)."""
    c0, s0, c1, s1, sd = (np.asarray(res[k], np.float64).reshape(R, P)
                          for k in ("c0", "c0_se", "c1", "c1_se", "diff_se"))
    per = [improvement_metrics(c0[r], c1[r]) for r in range(R)]
    ci = improvement_intervals(c0, s0, c1, s1, diff_se=sd)  # C0, C1 measured paired
    return {"I": [p["I"].tolist() for p in per],
            "mpi_per_seed": [p["mpi"] for p in per], "api_per_seed": [p["api"] for p in per],
            "mpi": float(np.mean([p["mpi"] for p in per])),
            "api": float(np.mean([p["api"] for p in per])),
            "mpi_ci95": ci["mpi"], "api_ci95": ci["api"]}


def describe(ctl: dict, zoo_returns: np.ndarray) -> dict:
    """Per config of a control JSON, over its policies below the zoo's top quartile (all
    seeds): n, start / zoo top (min, median, max), the final actors' KL from their start
    (median, 10% and 90% quantiles; None where not measured: kl_weight 0 before SAC measured
    it there, all zeros), the median gain of the final actor and of the deployed one
    (``median_gain``), and how many (seed, policy) were kept at the start."""
    start = zoo_returns[ctl["zoo_ids"]]
    out = {}
    for name, c in ctl["configs"].items():
        deployed = median_gain(c["c0"], c["c1"], start, zoo_returns)
        below = np.asarray(deployed["below"])  # median_gain's rule: below the top quartile
        kl = np.asarray(c["final_kl"], np.float64).reshape(-1, len(start))[:, below]
        frac = start[below] / zoo_returns.max()
        # at kl_weight 0 SAC measured no KL before 2026-11-27 (it read 0); since, it does
        measured = c.get("sac", {}).get("kl_weight", 1.0) > 0 or bool(np.any(kl > 0))
        row = {"n_below": deployed["n_below"],
               "start_of_top": [float(frac.min()), float(np.median(frac)), float(frac.max())],
               "final_kl": ([float(np.median(kl)), *map(float, np.quantile(kl, [0.1, 0.9]))]
                            if measured else None),
               "median_gain": deployed["median_gain"]}
        if "final_c1" in c:
            row["median_gain_final"] = median_gain(c["c0"], c["final_c1"], start,
                                                   zoo_returns)["median_gain"]
            row["kept_at_start"] = int((np.asarray(c["selected"])[:, below] == 0).sum())
        out[name] = row
    return out


def run_task(task_name: str, args) -> dict:
    task = get_task(task_name)
    zoo = load_zoo(task_name)
    split_ids = zoo.split_ids(args.split)
    chosen = (sorted(args.ids) if args.ids else
              [split_ids[i] for i in pick(np.asarray(zoo.returns)[split_ids], args.policies)])
    pols = index_params(zoo.params, np.asarray(chosen))
    R, P = args.seeds, len(chosen)
    tiled = jax.tree_util.tree_map(lambda x: jnp.concatenate([x] * R), pols)
    K = args.first_seed
    result = {"task": task_name, "split": args.split, "zoo_ids": chosen, "seeds": R,
              "first_seed": K,
              "seed_ids": list(range(K, K + R)), "iterations": args.iterations,
              "n_episodes": args.episodes, "backend": jax.default_backend(),
              "device": str(jax.devices()[0]), "machine": machine_info(), "configs": {}}
    # --first-seed 0 keeps the key of the runs before it; K > 0 folds K in: other draws
    key = jax.random.PRNGKey(30) if K == 0 else jax.random.fold_in(jax.random.PRNGKey(30), K)
    result["zoo_recipe"] = fine_tuning_recipe(task_name) if args.zoo_recipe else None
    for name, cfg in sac_configs(args, task.episode_length, task_name).items():
        t0 = time.perf_counter()
        log(f"[control] {task_name} {name}: SAC x {args.iterations} iterations in the real env "
            f"for {P} {args.split} policies x {R} seed(s)")
        select = args.select_episodes > 0
        _, metrics, res = improve_in_real_env(
            task, tiled, key, cfg, n_iterations=args.iterations,
            n_episodes=args.episodes,
            chunk_iterations=min(args.select_every if select else 1000, args.iterations),
            select_episodes=args.select_episodes, select_z=args.select_z)
        c0, s0, c1, s1, sd = (np.asarray(res[k], np.float64).reshape(R, P)
                              for k in ("c0", "c0_se", "c1", "c1_se", "diff_se"))
        summary = summarise(res, R, P)
        entry = {"sac": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in dataclasses.asdict(cfg).items()},
                 "c0": c0.tolist(), "c0_se": s0.tolist(), "c1": c1.tolist(),
                 "c1_se": s1.tolist(), "diff_se": sd.tolist(), "paired": True,
                 **summary,
                 "final_alpha": np.asarray(metrics["alpha"][:, -1]).tolist(),
                 "final_kl": np.asarray(metrics["kl"][:, -1]).tolist(),
                 "seconds": round(time.perf_counter() - t0, 1)}
        if select:
            fin = summarise(res["final"], R, P)
            entry.update(
                select={"episodes": args.select_episodes, "every": args.select_every,
                        "z": args.select_z},
                selected=np.asarray(res["selected"]).reshape(R, P).tolist(),
                validation_mean=np.asarray(res["validation_mean"]).reshape(-1, R, P).tolist(),
                validation_gain_se=np.asarray(res["validation_gain_se"]).reshape(-1, R, P)
                .tolist(),
                **{f"final_{k}": np.asarray(res["final"][k]).reshape(R, P).tolist()
                   for k in ("c1", "c1_se", "diff_se")},
                **{f"final_{k}": fin[k] for k in ("I", "mpi", "api", "mpi_ci95", "api_ci95")})
            log(f"  {name:<12} without the selection (final snapshot): MPI "
                f"{entry['final_mpi']:+.3f}  API {entry['final_api']:+.3f}; "
                f"deployed a fine-tuned snapshot for "
                f"{int((np.asarray(res['selected']) > 0).sum())} of {R * P}")
        result["configs"][name] = entry
        (m0, m1), (a0, a1) = entry["mpi_ci95"], entry["api_ci95"]
        log(f"  {name:<12} MPI {entry['mpi']:+.3f} [{m0:+.3f}, {m1:+.3f}]  "
            f"API {entry['api']:+.3f} [{a0:+.3f}, {a1:+.3f}]  "
            f"mean C0 {c0.mean():.1f} -> C1 {c1.mean():.1f}  ({entry['seconds']:.0f}s)")
    return result


RP_FIELDS = ("c0", "c0_se", "c1", "c1_se", "diff_se", "I", "selected", "final_c1",
             "final_c1_se", "final_diff_se", "final_I")  # [R, P] lists, joined over seeds


def combine(controls: list[dict]) -> dict:
    """One control of the seeds of several runs of one task (``--first-seed``, e.g. one GPU
    each): the same policies, iterations, episodes, configs and SAC / selection settings,
    disjoint seeds. Per config the [R, P] fields and validation [S, R, P] are joined in seed
    order and MPI / API and their intervals recomputed over all seeds (``summarise``; the
    final snapshot's where its SEs were kept). ValueError naming what differs."""
    if len(controls) < 2:
        raise ValueError("combine: expected at least two control files")
    runs = sorted(controls, key=lambda c: c.get("first_seed", 0))
    first = runs[0]
    for key in ("task", "zoo_ids", "iterations", "n_episodes", "zoo_recipe"):
        bad = [c.get(key) for c in runs if c.get(key) != first.get(key)]
        if bad:
            raise ValueError(f"combine: {key} differs ({first.get(key)!r} vs {bad[0]!r})")
    seeds = [s for c in runs for s in c.get("seed_ids", range(c["seeds"]))]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"combine: a seed in two files (seed ids {seeds})")
    if any(set(c["configs"]) != set(first["configs"]) for c in runs):
        raise ValueError("combine: the files ran different configs")
    P, R = len(first["zoo_ids"]), len(seeds)
    out = {**first, "seeds": R, "seed_ids": seeds, "first_seed": None, "configs": {},
           "seconds": [c.get("seconds") for c in runs], "command": [c.get("command")
                                                                     for c in runs]}
    for name, e0 in first["configs"].items():
        es = [c["configs"][name] for c in runs]
        for key in ("sac", "select"):
            if any(e.get(key) != e0.get(key) for e in es):
                raise ValueError(f"combine: {name}'s {key} settings differ")
        entry = {"sac": e0["sac"], "paired": e0.get("paired"),
                 "seconds": [e.get("seconds") for e in es]}
        for key in RP_FIELDS:
            if all(key in e for e in es):
                entry[key] = [row for e in es for row in np.reshape(e[key], (-1, P)).tolist()]
        for key in ("final_alpha", "final_kl"):  # flat [R * P], as a run writes them
            if all(key in e for e in es):
                entry[key] = [x for e in es for x in np.ravel(e[key]).tolist()]
        flat = {k: np.ravel(entry[k]) for k in ("c0", "c0_se", "c1", "c1_se", "diff_se")}
        entry.update(summarise(flat, R, P))
        if "select" in e0:
            entry["select"] = e0["select"]
            for key in ("validation_mean", "validation_gain_se"):
                entry[key] = np.concatenate([np.asarray(e[key]) for e in es], 1).tolist()
            if "final_c1_se" in entry:
                fin = summarise({"c0": flat["c0"], "c0_se": flat["c0_se"],
                                 **{k: np.ravel(entry[f"final_{k}"])
                                    for k in ("c1", "c1_se", "diff_se")}}, R, P)
                entry.update({f"final_{k}": fin[k]
                              for k in ("I", "mpi", "api", "mpi_ci95", "api_ci95")})
            elif "final_I" in entry:  # older files: no SEs kept, so no intervals
                fi = np.asarray(entry["final_I"], np.float64)
                entry.update(final_mpi=float(fi.min(1).mean()), final_api=float(fi.mean()))
        out["configs"][name] = entry
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", default="hopper,walker2d,halfcheetah,ant")
    ap.add_argument("--out", help="where control_<task>.json go (required unless --describe)")
    ap.add_argument("--describe", nargs="+", metavar="CONTROL_JSON",
                    help="describe these control JSONs (docstring) instead of running")
    ap.add_argument("--policies", type=int, default=0, help="test policies (0: all)")
    ap.add_argument("--ids", type=int, nargs="+", metavar="ZOO_ID",
                    help="these test policies (zoo ids; one task) instead of --policies")
    ap.add_argument("--split", choices=("test", "train", "validation"), default="test",
                    help="whose policies (train, validation: to choose a recipe without the "
                    "test policies; validation: paper.py --policy-split validation's)")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds K .. K + seeds - 1 "
                    "(split a control over GPUs; --combine joins the files)")
    ap.add_argument("--combine", nargs="+", metavar="CONTROL_JSON", help="join these runs' "
                    "seeds into OUT/control_<task>.json (combine) instead of running")
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--sac-envs", type=int, default=16)
    ap.add_argument("--critic-warmup", type=int, default=500)
    ap.add_argument("--updates-per-step", type=int, default=1)
    ap.add_argument("--sac-set", action="append", metavar="KEY=VALUE")
    ap.add_argument("--plain", action="store_true", help="also run plain SAC")
    ap.add_argument("--select-episodes", type=int, default=0,
                    help="validation episodes for early stopping (0: off)")
    ap.add_argument("--select-every", type=int, default=400,
                    help="iterations between the snapshots offered to the selection")
    ap.add_argument("--select-z", type=float, default=2.0,
                    help="standard errors of paired gain a snapshot needs to be deployed")
    ap.add_argument("--zoo-recipe", action="store_true",
                    help="the zoo learner's discount, reward scale and batch size (docstring)")
    args = ap.parse_args(argv)
    if args.describe:
        for path in args.describe:
            with open(path) as f:
                ctl = json.load(f)
            zret = np.asarray(load_zoo(ctl["task"]).returns, np.float64)
            for name, r in describe(ctl, zret).items():
                log(f"{path}: {ctl['task']} {name}: {r['n_below']} "
                    f"{ctl.get('split', 'test')} policies below the top quartile, "
                    "start at {:.2f} / {:.2f} / {:.2f} of the top; ".format(*r["start_of_top"])
                    + ("final KL from the start {:.4f} [{:.4f}, {:.4f}]; ".format(*r["final_kl"])
                       if r["final_kl"] else "final KL not measured (kl_weight 0); ")
                    + f"median gain deployed {r['median_gain']:+.3f}"
                    + (f", final {r['median_gain_final']:+.3f}, kept at the start "
                       f"{r['kept_at_start']}" if "kept_at_start" in r else ""))
        return 0
    if not args.out:
        ap.error("--out is required (unless --describe)")
    if args.combine:
        parts = []
        for path in args.combine:
            with open(path) as f:
                parts.append(json.load(f))
        try:
            joined = combine(parts)
        except ValueError as err:
            raise SystemExit(str(err)) from None
        os.makedirs(args.out, exist_ok=True)
        path = os.path.join(args.out, f"control_{joined['task']}.json")
        write_json(path, joined)
        log(f"[control] seeds {joined['seed_ids']} of {joined['task']} -> {path}")
        return 0
    if args.first_seed < 0:
        raise SystemExit(f"first-seed: expected >= 0, got {args.first_seed}")
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    bad = [t for t in tasks if t not in task_names()]
    if bad:
        raise SystemExit(f"tasks: unknown {bad}; known: {task_names()}")
    if args.ids:
        own = set(load_zoo(tasks[0]).split_ids(args.split)) if len(tasks) == 1 else None
        if own is None or not set(args.ids) <= own:
            raise SystemExit(f"ids: expected {args.split}-policy zoo ids of one task; got "
                             f"{args.ids} for tasks {tasks}" + (
                                 f" ({args.split} ids: {sorted(own)})" if own else ""))
    for name in ("seeds", "iterations", "episodes", "sac_envs"):
        if getattr(args, name) < 1:
            raise SystemExit(f"{name.replace('_', '-')}: expected >= 1")
    if args.episodes < 2:
        raise SystemExit("episodes: expected >= 2 (for standard errors)")
    if args.select_episodes < 0 or args.select_episodes == 1:
        raise SystemExit("select-episodes: expected 0 (off) or >= 2")
    if args.select_every < 1 or not (args.select_z >= 0):
        raise SystemExit("select-every: expected >= 1; select-z: expected >= 0")
    sac_configs(args, 1000)  # bad --sac-set fails before any work
    os.makedirs(args.out, exist_ok=True)
    for t in tasks:
        t0 = time.perf_counter()
        res = run_task(t, args)
        res["seconds"] = round(time.perf_counter() - t0, 1)
        res["command"] = " ".join(["python experiments/improve_control.py",
                                   *(sys.argv[1:] if argv is None else argv)])
        write_json(os.path.join(args.out, f"control_{t}.json"), res)
        log(f"[control] {t} done in {res['seconds']:.0f}s -> {args.out}/control_{t}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
