"""The paper's protocol on one task: RL2S, GAIL, BC and RL2S-BC x seeds, judged on the held-out
test policies by value difference (AVD/MVD), ranking (Kendall tau, nDCG@k, Spearman, regret@1)
and policy improvement (MPI/API), written to OUT/<task>.json.

    python experiments/paper.py --task hopper [--seeds 3] [--steps N] [--eval-every N]
        [--transitions-per-policy N] [--value-episodes N] [--eval-episodes N]
        [--improve-iterations N] [--improve-policies N] [--improve-seeds 1]
        [--sac-envs N] [--sac-critic-warmup N] [--sac-updates-per-step N]
        [--sac-set field=value ...] [--control] [--control-seeds N]
        [--improve-variants full,branched,full+penalty,branched+penalty,full+stop]
        [--ablation-methods rl2s]
        [--branch-length H] [--uncertainty-penalty L] [--uncertainty-threshold U]
        [--out DIR] [--data-dir DIR] [--profile auto|cpu|gpu] [--model ensemble|legacy]
        [--set field=value ...] [--families adversarial,mle] [--first-seed K]

Phases (each prints its wall time; OUT/<task>.json is rewritten after each, so a run cut off
by a time limit still leaves what it finished, with "complete": false):

1. data: train / test Datasets from the shipped zoo: ONE ``rl2s_jax.app.pipeline.collect_dataset``
   run over all the zoo's policies (split "all": one MJX program), split into the zoo's train
   and test policies with ``Dataset.select_policies``; reused from --data-dir when the sizes
   match.
1b. oracle: the control, ``assess.evaluate_oracle`` (the real MJX dynamics stepped from each
   observation through the lanes' evaluation path: same start states, horizon, gamma and
   episodes, key PRNGKey(1000 + seed) per seed): the "oracle" row, the ceiling of any simulator
   of this observation under this protocol (--no-oracle skips it).
2. training: the four methods x S seeds as TWO vmapped programs, as experiments/eps_sweep.py:
   eps is a state leaf, so ``rl2s`` (eps 0.25) and ``gail`` (eps 1) are lanes of one
   adversarial program (config method "rl2s"), ``rl2s-bc`` (eps 0.25) and ``bc`` (eps 1)
   lanes of one likelihood program (config method "rl2s-bc"). A lane (method m, seed s) is the
   program ``rl2s train --method m --seed s`` runs: gail differs from rl2s, and bc from rl2s-bc,
   only in the initial eps (TrainConfig.initial_eps), and the key is PRNGKey(s) (checked: the
   final states are bitwise equal unvmapped; a vmapped lane matches to ~3e-8).
   ``--families adversarial`` (or ``mle``) runs one of the two, so a task's protocol can be
   split over two device calls; experiments/merge_results.py joins the two JSON files.
   ``--first-seed K`` runs seeds K..K+S-1 (keys, evaluation keys and lane names as in one
   run of K+S seeds), so more seeds can join a result later, on the same --data-dir.
   Every --eval-every steps every lane's simulator is evaluated on the test policies as
   ``assess.evaluate_simulator`` does (simulated discounted value over the config's vd_horizon
   from the test data's start states, ``evaluate.ranking_metrics`` against the true values),
   vmapped over the lanes, with key PRNGKey(1000 + seed). The last evaluation (at --steps) is
   the final one; it gets 95% bootstrap intervals over its episodes (--bootstrap N
   replicates; ``evaluate.bootstrap_intervals``), per lane in "lane_intervals" and averaged
   over seeds in "intervals".
3. improvement: for the first --improve-seeds seeds, SAC fine-tunes --improve-policies test
   policies (spread evenly over their true returns; 0: all) inside each method's
   simulator (all methods x seeds x policies as one vmapped program), then the fine-tuned
   policies' real return C1 is measured in MJX with the test data's protocol (--value-episodes
   fresh episodes of the full episode length); C0 is the data's measured ``value``.
   I = (C1 - C0) / |C0|, MPI = min I, API = mean I (``improve.improvement_metrics``).
   ``--improve-variants`` runs this once per variant of the simulated env (each a '+' list
   of ``full`` (whole episodes from the data's start states), ``branched`` (MBPO:
   ``--branch-length`` steps from every real state of the test data), ``penalty`` (MOPO:
   r - ``--uncertainty-penalty`` * u) and ``stop`` (MOReL: end when u >
   ``--uncertainty-threshold``), u being the ensemble's disagreement
   (``sim_env.simulator_uncertainty``; needs >= 2 elites, so not --model legacy) in units of
   its mean on the test data): the first variant fills MPI/API (Table 2) from every lane, the
   others run in the lanes of ``--ablation-methods`` only; every variant goes to
   ``ablation``. ``--control`` runs the same fine-tuning (same policies, budget and SAC
   settings) in the real env, ``--control-seeds`` times, with real returns before and after
   (``improve.improve_in_real_env``): the ``control`` entry, the ceiling of improvement for
   that budget. ``--guard-margin M`` adds, per variant, the deployed policies' MPI / API
   when each lane keeps a fine-tuned policy only where every elite member of its simulator
   predicts a gain above M x |start value| (``improve.deployment_guard``; a kept start
   policy has I = 0): ablation entry ``<variant>+guard``. ``--guard-snapshots`` applies
   that guard to the actor after every ``--sac-chunk`` iterations as well
   (``improve.select_by_members``: early stopping by the simulator alone) and measures the
   chosen snapshots in the real env: ablation entry ``<variant>+guard-snapshots``.
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

from rl2s_jax.app.improve import fine_tuning_overrides
from rl2s_jax.app.pipeline import collect_dataset
from rl2s_jax.app.train import make_config, parse_overrides
from rl2s_jax.data.collect import measure_values
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.data.summary import episode_lengths
from rl2s_jax.data.values import true_values, true_values_se
from rl2s_jax.envs.tasks import get_task, task_names
from rl2s_jax.evaluate.lanes import (
    EVAL_METRICS,
    evaluate_lanes,
    intervals_over_seeds,
    oracle_noise_ceiling,
    oracle_rows,
)
from rl2s_jax.evaluate.metrics import bootstrap_intervals
from rl2s_jax.improve.finetune import (
    deployment_guard,
    improve_in_real_env,
    improvement_metrics,
    member_values,
    paired_returns,
    select_by_members,
)
from rl2s_jax.improve.sim_env import SimulatorEnv, branch_pool, real_rows, scaled_env_options
from rl2s_jax.model.simulator import Simulator, start_pool
from rl2s_jax.policy.policy import index_params
from rl2s_jax.policy.sac import SACConfig, episode_returns, make_sac
from rl2s_jax.sharding import initialize_distributed, is_writer, lane_mesh, replicate, shard_lanes
from rl2s_jax.train.config import DEFAULT_EPS, LEGACY_MODEL
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.lanes import heldout_start_pool, select_point, train_lanes
from rl2s_jax.train.loop import worst_vd_jumps
from rl2s_jax.train.step import init, simulator
from rl2s_jax.zoo.zoo import policies_for

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
# (family, config method, its lanes' methods): one vmapped program per family.
FAMILIES = (("adversarial", "rl2s", ("rl2s", "gail")), ("mle", "rl2s-bc", ("rl2s-bc", "bc")))
# mpi/api: C0 from the data's true values, C1 measured apart; *_paired: C0 and C1 measured
# paired (the same starts and noise draws, --improve-episodes each)
IMPROVE_METRICS = ("mpi", "api", "mpi_paired", "api_paired")
METRICS = EVAL_METRICS + IMPROVE_METRICS
VARIANT_PARTS = ("full", "branched", "penalty", "stop")

# Sizes per profile. gpu: 3 seeds, 1200 steps (the 1000 pre-training steps of the fitted
# model family, then 200 WGAIL; RESULTS@bf0c7b2, "Ant and Hopper: the likelihood model was
# underfit"), every test policy fine-tuned in the simulators of 2 seeds, SAC's KL weight 0.1.
# Measured on one H100 (RESULTS@bf0c7b2, "The protocol on the new model family"), per task,
# each family alone: data 83-97 s, the adversarial program (6 lanes) 355-375 s, the
# likelihood program 190-210 s, SAC 18-22 s, the real measurement of the fine-tuned policies
# 38 s (Hopper; more with 43 test policies), Hopper's oracle at 128 / 128 episodes 261 s.
# Two processes sharing the GPU run no faster than one after the other. cpu: small, for a
# 2-core machine.
PROFILES = {
    "gpu": dict(seeds=3, transitions_per_policy=20_000, value_episodes=16, steps=1200,
                eval_every=600, eval_episodes=32, improve_policies=0, improve_seeds=2,
                improve_episodes=32,
                improve_iterations=2000, sac_envs=16, sac=dict(kl_weight=0.1)),
    "cpu": dict(seeds=3, transitions_per_policy=2000, value_episodes=4, steps=300,
                eval_every=100, eval_episodes=8, improve_policies=10, improve_seeds=1,
                improve_episodes=4,
                improve_iterations=300, sac_envs=4, sac=dict(hidden=(64, 64), batch_size=128)),
}

# Per-task changes to a profile. Ant's returns spread so widely between episodes (per-episode
# sd ~830 against ~90 between neighbouring test policies) that with 16 truth / 32 simulated
# episodes even the real dynamics rank at tau 0.78; with 256 / 256 the oracle reaches 0.88
# (docs/RESULTS.md, "Many episodes on Ant and Hopper"); Hopper's oracle reaches 0.99 at
# 128 / 128 (0.96 at 32), and 16 episodes leave Walker2d an evaluation-noise tau std of 0.038
# ("The oracle"), so it gets 64 / 64.
TASK_SIZES = {"gpu": {"ant": dict(value_episodes=256, eval_episodes=256),
                      "hopper": dict(value_episodes=128, eval_episodes=128),
                      "walker2d": dict(value_episodes=64, eval_episodes=64)}}


def profile_sizes(profile: str, task: str) -> dict:
    """A profile's sizes with the task's changes (TASK_SIZES) applied."""
    return {**PROFILES[profile], **TASK_SIZES.get(profile, {}).get(task, {})}


def log(msg: str) -> None:
    print(msg, flush=True)


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def _take(tree, idx):
    idx = jnp.asarray(idx)
    return jax.tree_util.tree_map(lambda x: x[idx], tree)


def _finite_mean(x) -> str:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return f"{x.mean():.1f}" if x.size else "n/a (no episode ended)"


def _none_if_nan(x):
    x = float(x)
    return x if np.isfinite(x) else None


# ------------------------------------------------------------------ data


def load_or_collect(task: str, sizes: dict, data_dir: str, seed: int,
                    episode_length: int | None, progress: bool):
    """The train and test Datasets of the zoo's split: reused from data_dir when collected with
    the same sizes, else collected as ONE ``collect_dataset(task, "all", ...)`` run (one MJX
    program for all the zoo's policies) and split with ``Dataset.select_policies``.
    -> ({"train": Dataset, "test": Dataset}, reused)"""
    from rl2s_jax.zoo.zoo import load_zoo

    paths = {split: os.path.join(data_dir, f"{task}_{split}.npz") for split in ("train", "test")}
    key_path = os.path.join(data_dir, f"{task}_data.json")
    data_key = {"task": task, "seed": seed, "episode_length": episode_length,
                "transitions_per_policy": sizes["transitions_per_policy"],
                "value_episodes": sizes["value_episodes"]}
    if all(os.path.exists(p) for p in paths.values()) and os.path.exists(key_path):
        with open(key_path) as f:
            if json.load(f) == data_key:
                return {split: load_dataset(p) for split, p in paths.items()}, True
    everything = collect_dataset(task, "all", sizes["transitions_per_policy"], seed=seed,
                                 value_episodes=sizes["value_episodes"],
                                 episode_length=episode_length, progress=progress)
    zoo = load_zoo(task)
    all_ids = list(everything.meta["source"]["zoo_ids"])
    os.makedirs(data_dir, exist_ok=True)
    out = {}
    for split, path in paths.items():
        ids = zoo.split_ids(split)
        part = everything.select_policies([all_ids.index(i) for i in ids])
        # policies_for() finds a Dataset's policies through meta.source.zoo_ids.
        part.meta["source"] = {**part.meta["source"], "split": split,
                               "zoo_ids": [int(i) for i in ids]}
        save_dataset(path, part)
        out[split] = part
    with open(key_path, "w") as f:
        json.dump(data_key, f)
    return out, False


# ------------------------------------------------------------------ improvement


def _sac_for(sim: Simulator, pool, task, cfg: SACConfig, env_options=None):
    """SAC in ``sim``'s SimulatorEnv; env_options(sim) -> SimulatorEnv keywords."""
    opts = env_options(sim) if env_options is not None else {}
    return make_sac(SimulatorEnv(sim, pool, task, **opts), cfg)


def parse_variants(text: str) -> list[str]:
    """--improve-variants: comma list of '+'-joined parts of VARIANT_PARTS, each with exactly
    one of full / branched (e.g. 'full,branched+penalty')."""
    out = []
    for v in (x.strip() for x in text.split(",") if x.strip()):
        parts = v.split("+")
        bad = [p for p in parts if p not in VARIANT_PARTS]
        if bad or len(set(parts)) != len(parts) or sum(p in ("full", "branched")
                                                       for p in parts) != 1:
            raise SystemExit(f"improve-variants: {v!r} must join with '+' one of full / "
                             f"branched and optionally penalty, stop (known parts: "
                             f"{', '.join(VARIANT_PARTS)})")
        out.append(v)
    if not out or len(set(out)) != len(out):
        raise SystemExit(f"improve-variants: expected distinct variants, got {text!r}")
    return out


def variant_settings(variant: str, args) -> dict:
    """The SimulatorEnv settings of one --improve-variants entry (JSON-able)."""
    parts = variant.split("+")
    return {"rollout_length": args.branch_length if "branched" in parts else None,
            "uncertainty_penalty": args.uncertainty_penalty if "penalty" in parts else 0.0,
            "uncertainty_threshold": args.uncertainty_threshold if "stop" in parts else None,
            "halt_penalty": args.halt_penalty if "stop" in parts else 0.0}


def improve_in_lanes(sims: Simulator, task, pool, policies, keys, cfg: SACConfig, *,
                     n_iterations: int, chunk: int, log=log, env_options=None,
                     snapshots: bool = False):
    """SAC fine-tuning of the stacked ``policies`` [P] inside each of the stacked simulators
    ``sims`` [L] (improve.improve_policies for every simulator at once: one program, vmapped
    over simulators and policies). keys [L, P]. ``env_options(sim)``: SimulatorEnv keywords
    for one (traced) simulator. -> (actors [L, P, ...], simulated training return [L, P] of
    the episodes that ended in the last chunk (NaN if none)); ``snapshots``: the actors after
    every chunk instead, [C, L, P, ...] (the last is the final one)."""
    pool = jnp.asarray(pool)

    def init_one(sim, ks, pols):
        return jax.vmap(_sac_for(sim, pool, task, cfg, env_options).init)(ks, pols)

    states = jax.jit(jax.vmap(init_one, in_axes=(0, 0, None)))(sims, keys, policies)
    compiled, done, sim_return, kept = {}, 0, None, []
    while done < n_iterations:
        n = min(chunk, n_iterations - done)
        if n not in compiled:
            def train_one(sim, st, n=n):
                sac = _sac_for(sim, pool, task, cfg, env_options)
                return jax.vmap(lambda s: sac.train(s, n))(st)
            compiled[n] = jax.jit(jax.vmap(train_one))
        t0 = time.perf_counter()
        states, metrics = compiled[n](sims, states)
        if snapshots:
            kept.append(states.actor)
        sim_return = np.asarray(episode_returns(metrics))
        done += n
        log(f"[paper]   SAC {done}/{n_iterations} iterations ({time.perf_counter() - t0:.1f}s"
            f"); mean simulated training return {_finite_mean(sim_return)}")
    if snapshots:
        return _stack(kept), sim_return
    return states.actor, sim_return


def pick_policies(c0: np.ndarray, n: int | None) -> list[int]:
    """n test policies spread evenly over their true returns (all when n is None or >= P)."""
    order = np.argsort(c0, kind="stable")
    P = len(order)
    if n is None or n >= P:
        return sorted(order.tolist())
    pos = np.unique(np.round(np.linspace(0, P - 1, n)).astype(int))
    return sorted(order[pos].tolist())


# ------------------------------------------------------------------ results


def _mean_or_none(vals):
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else None


def _method_means(per_method: dict) -> dict:
    """{method: {"mpi": [per lane], "api": [...], ...}} -> their means, for methods that have
    any."""
    return {m: {k: _mean_or_none(vals) for k, vals in v.items()}
            for m, v in per_method.items() if v["mpi"]}


def _fmt_ms(mean, std):
    return "n/a" if mean is None else f"{mean:.3f}" + ("" if std is None else f" ±{std:.2g}")


def control_entry(res: dict, ids: list[int], c0_data: np.ndarray, n_seeds: int,
                  train_return: np.ndarray) -> dict:
    """The JSON 'control' entry from measure_improvement over R seeds x P policies (seed-major
    [R * P]): per seed MPI/API and per-policy C0/C1 with standard errors; their mean and
    sample std over seeds."""
    P = len(ids)
    shape = lambda k: np.asarray(res[k], np.float64).reshape(n_seeds, P)
    c0, c0_se, c1, c1_se = shape("c0"), shape("c0_se"), shape("c1"), shape("c1_se")
    diff_se = shape("diff_se")  # measure_improvement measures C0 and C1 paired
    per = [improvement_metrics(c0[r], c1[r]) for r in range(n_seeds)]
    mpi, api = [p["mpi"] for p in per], [p["api"] for p in per]
    std = lambda x: float(np.std(x, ddof=1)) if len(x) > 1 else None
    return {"policy_ids": ids, "seeds": n_seeds, "c0_data": np.asarray(c0_data).tolist(),
            "c0": c0.tolist(), "c0_se": c0_se.tolist(), "c1": c1.tolist(),
            "c1_se": c1_se.tolist(), "diff_se": diff_se.tolist(), "paired": True,
            "I": [p["I"].tolist() for p in per],
            "train_return": [_none_if_nan(x) for x in np.asarray(train_return).reshape(-1)],
            "mpi_per_seed": mpi, "api_per_seed": api, "mpi": float(np.mean(mpi)),
            "api": float(np.mean(api)), "mpi_std": std(mpi), "api_std": std(api)}


def summarise(result: dict) -> None:
    """Fill result["methods"] (mean over seeds), ["std"] (sample std, None for one value) and
    ["n"] (values averaged) from result["per_seed"]."""
    for m, per in result["per_seed"].items():  # the methods and "oracle"
        mean, std, n = {}, {}, {}
        for k in METRICS:
            vals = [v for v in per.get(k, []) if v is not None]
            n[k] = len(vals)
            mean[k] = float(np.mean(vals)) if vals else None
            std[k] = float(np.std(vals, ddof=1)) if len(vals) > 1 else None
        result["methods"][m], result["std"][m], result["n"][m] = mean, std, n
    for m, per in result.get("selected", {}).items():  # the test metrics at the chosen steps
        result.setdefault("methods_selected", {})[m] = {
            k: (float(np.mean([v for v in vals if v is not None]))
                if any(v is not None for v in vals) else None)
            for k, vals in per.items() if k != "step"}


# entries keyed by method, lane or family: a part adds its own keys (the first part's oracle
# stays when both ran one)
MERGED_BY_METHOD = ("per_seed", "selected", "lane_intervals", "intervals", "lanes",
                    "train_config", "improvement")
SAME_IN_PARTS = ("task", "model", "profile", "zoo_sha256", "true_value")


def seed_ids_of(result: dict) -> list[int]:
    """The seeds a paper.py result ran (``seed_ids``; results older than --first-seed ran
    0 .. seeds - 1)."""
    return [int(s) for s in result.get("seed_ids") or range(int(result["seeds"]))]


def _join_seeds(merged: dict, part: dict, methods: set, has: dict, ids: list[int]) -> None:
    """Append ``part``'s seeds of ``methods`` (run by ``merged`` on other seeds) to merged's
    per-seed lists, in place; ``has`` maps each method to the seeds merged holds."""
    twice = {m: sorted(set(has[m]) & set(ids)) for m in sorted(methods)}
    twice = {m: v for m, v in twice.items() if v}
    if twice:
        raise ValueError(f"per_seed: method(s) and seed(s) {twice} in more than one run")
    for m in sorted(methods):
        if merged["per_seed"][m].get("mpi") and part["per_seed"][m].get("mpi"):
            raise ValueError(f"improvement: method {m!r} was fine-tuned in two seed-split "
                             f"runs; fine-tune in one of them only")
        for k, vals in part["per_seed"][m].items():
            merged["per_seed"][m].setdefault(k, []).extend(vals)
        for k, vals in part.get("selected", {}).get(m, {}).items():
            merged.setdefault("selected", {}).setdefault(m, {}).setdefault(k, []).extend(vals)
        merged.setdefault("lane_intervals", {}).setdefault(m, []).extend(
            part.get("lane_intervals", {}).get(m, []))
        has[m] = has[m] + ids
    for family, cfg in part.get("train_config", {}).items():
        if merged.get("train_config", {}).get(family, cfg) != cfg:
            raise ValueError(f"train_config.{family}: the runs trained with different "
                             f"settings")


def _order_by_seed(merged: dict, has: dict) -> None:
    """Sort each method's per-seed lists by seed (in place)."""
    for m, ids in has.items():
        order = np.argsort(ids, kind="stable")
        take = lambda v, order=order: [v[i] for i in order] if len(v) == len(order) else v
        merged["per_seed"][m] = {k: take(v) for k, v in merged["per_seed"][m].items()}
        if m in merged.get("selected", {}):
            merged["selected"][m] = {k: take(v) for k, v in merged["selected"][m].items()}
        if m in merged.get("lane_intervals", {}):
            merged["lane_intervals"][m] = take(merged["lane_intervals"][m])
            merged.setdefault("intervals", {})[m] = intervals_over_seeds(
                merged["lane_intervals"][m])


def merge_runs(parts: list[dict]) -> dict:
    """One result from runs of the same protocol split over calls: runs that trained
    different families (``--families``) and runs of other seeds (``--first-seed``) on the
    same data. The per-method entries joined (a method's seeds in seed order, its intervals
    over seeds recomputed), curves concatenated, timings summed, complete when every part is.
    Raises ValueError naming the field where the runs differ (task, sizes of the data, zoo,
    training settings, ...), when two of them ran the same method and seed, or when the
    methods do not end up with the same seeds."""
    if not parts:
        raise ValueError("parts: expected at least one result")
    merged = json.loads(json.dumps(parts[0]))
    has = {m: seed_ids_of(merged) for m in merged["per_seed"] if m != "oracle"}
    for part in parts[1:]:
        for k in SAME_IN_PARTS:
            if part.get(k) != merged.get(k):
                raise ValueError(f"{k}: the runs differ ({merged.get(k)!r} vs {part.get(k)!r})")
        for k in ("train_policies", "test_policies", "transitions_per_policy", "steps",
                  "eval_every", "eval_episodes", "episode_length"):
            if part["sizes"].get(k) != merged["sizes"].get(k):
                raise ValueError(f"sizes.{k}: the runs differ ({merged['sizes'].get(k)!r} vs "
                                 f"{part['sizes'].get(k)!r})")
        part = json.loads(json.dumps(part))
        ids = seed_ids_of(part)
        methods = set(part["per_seed"]) - {"oracle"}
        _join_seeds(merged, part, methods & set(has), has, ids)
        for m in methods - set(has):
            has[m] = ids
        for k in MERGED_BY_METHOD:
            into = merged.setdefault(k, {})
            into.update({m: v for m, v in part.get(k, {}).items() if m not in into})
        for variant, entry in part.get("ablation", {}).items():  # {variant: {settings,
            into = merged.setdefault("ablation", {}).setdefault(variant, {})  # lanes, methods}}
            if "settings" in into and into["settings"] != entry.get("settings"):
                raise ValueError(f"ablation.{variant}.settings: the runs differ "
                                 f"({into['settings']!r} vs {entry.get('settings')!r})")
            for k, v in entry.items():
                if isinstance(v, dict) and k != "settings":
                    into.setdefault(k, {}).update({m: x for m, x in v.items()
                                                   if m not in into[k]})
                else:
                    into.setdefault(k, v)
        if part.get("sac_config") and merged.get("sac_config") not in (None,
                                                                         part["sac_config"]):
            raise ValueError("sac_config: the runs fine-tuned with different SAC settings")
        merged.setdefault("sac_config", part.get("sac_config"))
        merged["curves"] = merged.get("curves", []) + part.get("curves", [])
        merged["families"] = merged.get("families", []) + [
            f for f in part.get("families", []) if f not in merged.get("families", [])]
        t = merged["timings"]
        for k, v in part.get("timings", {}).items():
            t[k] = round(t.get(k, 0.0) + v, 1)
        merged["complete"] = bool(merged.get("complete")) and bool(part.get("complete"))
        merged["command"] = f"{merged['command']} && {part['command']}"
    seed_sets = {m: sorted(ids) for m, ids in has.items()}
    if len({tuple(v) for v in seed_sets.values()}) > 1:
        raise ValueError(f"seeds: the methods ran different seeds {seed_sets}")
    _order_by_seed(merged, has)
    ids = next(iter(seed_sets.values()), seed_ids_of(merged))
    merged["seeds"], merged["seed_ids"] = len(ids), ids
    merged.setdefault("sizes", {})["seeds"] = len(ids)
    merged["methods"], merged["std"], merged["n"] = {}, {}, {}
    merged.pop("methods_selected", None)
    summarise(merged)
    return merged


def write(path: str, result: dict) -> None:
    """Summarise ``result`` and write it atomically (on the writing process only)."""
    summarise(result)
    if not is_writer():
        return
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(result, f, indent=1)
    os.replace(tmp, path)


def zoo_sha256(task: str) -> str | None:
    """sha256 of rl2s_jax/zoo/shipped/<task>/zoo.npz, the zoo the result was measured on."""
    import hashlib

    from rl2s_jax.zoo.zoo import zoo_dir

    path = os.path.join(zoo_dir(task), "zoo.npz")
    if not os.path.exists(path):
        return None
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def table(result: dict) -> str:
    cols = ("kendall_tau", "ndcg@1", "ndcg@5", "spearman", "avd", "mvd", "mpi", "api")
    lines = [f"{'method':<9}" + "".join(f"{c:>16}" for c in cols)]
    for m in [m for m in METHODS + ("oracle",) if m in result["methods"]]:
        cells = []
        for c in cols:
            v, s = result["methods"][m].get(c), result["std"][m].get(c)
            cells.append("n/a" if v is None else f"{v:.3g}" + ("" if s is None else
                                                                f" ±{s:.2g}"))
        lines.append(f"{m:<9}" + "".join(f"{c:>16}" for c in cells))
    return "\n".join(lines)


# ------------------------------------------------------------------ main


def positive_int(text: str) -> int:
    """argparse type: an int >= 1, else an error naming what was expected."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an int >= 1, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    pos = positive_int
    ap.add_argument("--task", required=True, choices=task_names())
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--seeds", type=pos)
    ap.add_argument("--first-seed", type=int, default=0, help="the seeds are first-seed ... "
                    "first-seed + seeds - 1, so more seeds of one protocol can run in another "
                    "call on the same data (merge_results.py joins them)")
    ap.add_argument("--steps", type=pos, help="train_steps per lane")
    ap.add_argument("--eval-every", type=pos, help="steps between test evaluations "
                    "(divides --steps)")
    ap.add_argument("--eval-episodes", type=pos, help="simulated episodes per test policy")
    ap.add_argument("--transitions-per-policy", type=pos)
    ap.add_argument("--value-episodes", type=pos, help="real episodes per policy for true "
                    "values (C0) and for C1")
    ap.add_argument("--episode-length", type=pos, help="shorter episodes than the task's "
                    "(smoke runs)")
    ap.add_argument("--data-seed", type=int, default=0)
    ap.add_argument("--improve-iterations", type=int, help="SAC iterations (0: skip)")
    ap.add_argument("--improve-policies", type=int, help="test policies fine-tuned, spread "
                    "evenly over their true returns (0 or more than there are: all)")
    ap.add_argument("--improve-seeds", type=int, help="seeds whose simulators are used")
    ap.add_argument("--improve-episodes", type=pos, help="real episodes per policy for the "
                    "paired measurement of C0 and C1 (start and fine-tuned policies from the "
                    "same starts and noise draws)")
    ap.add_argument("--sac-envs", type=pos, help="SAC envs per fine-tuned policy")
    ap.add_argument("--sac-critic-warmup", type=int, help="updates training only the critics "
                    "(default: a quarter of --improve-iterations)")
    ap.add_argument("--sac-updates-per-step", type=pos, default=1)
    ap.add_argument("--sac-chunk", type=pos, default=1000, help="SAC iterations per compiled "
                    "call")
    ap.add_argument("--sac-set", action="append", metavar="KEY=VALUE",
                    help="SACConfig override for every fine-tuning (methods and control)")
    ap.add_argument("--control", action="store_true", help="also fine-tune the same test "
                    "policies with the same SAC in the real env (the 'control' entry)")
    ap.add_argument("--control-seeds", type=pos, default=1, help="SAC seeds of the control")
    ap.add_argument("--improve-variants", default="full", help="comma list of simulated-env "
                    "variants, each '+'-joined: full|branched [+penalty] [+stop]; the first "
                    "gives MPI/API, all go to 'ablation'")
    ap.add_argument("--ablation-methods", default="rl2s", help="comma list of methods whose "
                    "lanes run the variants after the first (the first runs in all lanes)")
    ap.add_argument("--branch-length", type=pos, default=100, help="steps of a branched "
                    "rollout (variant 'branched')")
    ap.add_argument("--uncertainty-penalty", type=float, default=1.0, help="lambda of the "
                    "penalty r - lambda * u, u in units of its mean on the test data "
                    "(variant 'penalty')")
    ap.add_argument("--uncertainty-threshold", type=float, default=3.0, help="end a rollout "
                    "when u exceeds this, same units (variant 'stop')")
    ap.add_argument("--halt-penalty", type=float, default=0.0, help="reward subtracted when "
                    "the stop rule ends a rollout (variant 'stop')")
    ap.add_argument("--model", choices=("ensemble", "legacy"), default="ensemble",
                    help="the generator: the ensemble model family with MLE pre-training "
                    "(TrainConfig's defaults) or the single generator trained from scratch "
                    "that preceded it (train.LEGACY_MODEL); --set overrides either")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="TrainConfig override for all lanes; eps=X sets the robust lanes' eps")
    ap.add_argument("--guard-margin", type=float, help="also report MPI / API of the deployed "
                    "policies when a fine-tuned policy is kept only where every elite member of "
                    "its simulator predicts a gain above this fraction (improve."
                    "deployment_guard): the ablation entry '<variant>+guard'")
    ap.add_argument("--guard-snapshots", action="store_true", help="with --guard-margin: "
                    "also apply the guard to the actor after every --sac-chunk iterations and "
                    "deploy the snapshot with the largest smallest predicted gain "
                    "(improve.select_by_members), measured in the real env: the ablation "
                    "entry '<variant>+guard-snapshots'")
    ap.add_argument("--families", default="adversarial,mle", help="comma list of the training "
                    "programs to run: adversarial (rl2s, gail) and / or mle (rl2s-bc, bc); one "
                    "of them splits the protocol over two calls (merge_results.py joins them)")
    ap.add_argument("--bootstrap", type=int, default=1000, help="bootstrap replicates for the "
                    "95%% intervals over evaluation episodes (0: none)")
    ap.add_argument("--no-oracle", dest="oracle", action="store_false", help="skip the control "
                    "(the real dynamics through the same evaluation path)")
    ap.add_argument("--out", default="results/paper")
    ap.add_argument("--data-dir", help="where train/test .npz live (default: --out)")
    ap.add_argument("--check-eval", action="store_true", help="also run "
                    "assess.evaluate_simulator on one lane and record the largest difference "
                    "from the vmapped evaluation (tests)")
    ap.add_argument("--progress", action="store_true", help="progress bars while collecting")
    return ap


def _sac_overrides(items) -> dict:
    """--sac-set KEY=VALUE pairs, checked against SACConfig's fields before any work."""
    try:
        out = fine_tuning_overrides(parse_overrides(items), flag="sac-set")
    except ValueError as err:
        raise SystemExit(str(err)) from None
    try:
        SACConfig.fine_tuning(**out).validate()
    except (TypeError, ValueError) as err:
        raise SystemExit(f"sac-set: {err}") from None
    return out


def parse_families(text: str) -> tuple:
    """--families: a comma list of FAMILIES' names -> their FAMILIES rows, in FAMILIES' order."""
    names = {f for f in (x.strip() for x in text.split(",")) if f}
    known = [f for f, _, _ in FAMILIES]
    if not names or names - set(known):
        raise SystemExit(f"families: expected a comma list of {', '.join(known)}, got {text!r}")
    return tuple(row for row in FAMILIES if row[0] in names)


def resolve_sizes(args, profile: str) -> dict:
    sizes = {k: v for k, v in profile_sizes(profile, args.task).items() if k != "sac"}
    for k in list(sizes):
        if getattr(args, k, None) is not None:
            sizes[k] = getattr(args, k)
    if sizes["steps"] % sizes["eval_every"]:
        raise SystemExit(f"steps: expected a multiple of --eval-every ({sizes['eval_every']})")
    sizes["improve_seeds"] = max(0, min(sizes["improve_seeds"], sizes["seeds"]))
    if sizes["improve_policies"] is not None and sizes["improve_policies"] <= 0:
        sizes["improve_policies"] = None
    it = max(0, sizes["improve_iterations"])
    sizes["improve_iterations"] = it
    sizes["sac_critic_warmup"] = (args.sac_critic_warmup if args.sac_critic_warmup is not None
                                  else it // 4)
    sizes["sac_updates_per_step"] = args.sac_updates_per_step
    sizes["sac_chunk"] = args.sac_chunk
    sizes["episode_length"] = args.episode_length
    sizes["bootstrap"] = max(0, args.bootstrap)
    sizes["oracle"] = args.oracle
    return sizes


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    t_start = time.perf_counter()
    initialize_distributed()  # multi-host, when the coordinator variables are set
    backend = jax.default_backend()
    profile = args.profile if args.profile != "auto" else ("gpu" if backend == "gpu" else "cpu")
    sizes = resolve_sizes(args, profile)
    variants = parse_variants(args.improve_variants)
    ablation_methods = [m.strip() for m in args.ablation_methods.split(",") if m.strip()]
    if not ablation_methods or set(ablation_methods) - set(METHODS):
        raise SystemExit(f"ablation-methods: expected a comma list of {', '.join(METHODS)}, "
                         f"got {args.ablation_methods!r}")
    sac_overrides = _sac_overrides(args.sac_set)
    families = parse_families(args.families)
    if args.guard_margin is not None and not (np.isfinite(args.guard_margin)
                                              and args.guard_margin >= 0):
        raise SystemExit(f"guard-margin: expected a finite float >= 0, got {args.guard_margin}")
    if args.guard_snapshots and args.guard_margin is None:
        raise SystemExit("guard-snapshots: needs --guard-margin (the guard's margin)")
    S = sizes["seeds"]
    if args.first_seed < 0:
        raise SystemExit(f"first-seed: expected an int >= 0, got {args.first_seed}")
    seed_ids = list(range(args.first_seed, args.first_seed + S))
    out, data_dir = args.out, args.data_dir or args.out
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{args.task}.json")
    device = jax.devices()[0].device_kind
    timings: dict[str, float] = {}

    def phase(name, t0):
        timings[name] = round(time.perf_counter() - t0, 1)
        log(f"[paper] {name}: {timings[name]:.1f}s (elapsed "
            f"{time.perf_counter() - t_start:.0f}s)")

    log(f"[paper] task {args.task} on {device} ({backend}, jax {jax.__version__}), profile "
        f"{profile}, {S} seeds ({seed_ids[0]}..{seed_ids[-1]}) -> {path}\n[paper] sizes {sizes}")
    result = {"task": args.task, "model": args.model, "methods": {}, "std": {}, "n": {},
              "seeds": S, "seed_ids": seed_ids,
              "improve_seeds": sizes["improve_seeds"], "hardware": device, "backend": backend,
              "jax_version": jax.__version__, "profile": profile, "sizes": sizes,
              "command": " ".join(["python", "experiments/paper.py", *argv]),
              "families": [f for f, _, _ in families],
              "timings": timings, "complete": False,
              "per_seed": {m: {k: [] for k in METRICS}
                           for _, _, methods in families for m in methods},
              "curves": [], "lanes": {}}

    # ---- 1. data
    t0 = time.perf_counter()
    datasets, reused = load_or_collect(args.task, sizes, data_dir, args.data_seed,
                                       args.episode_length, args.progress)
    for split, ds in datasets.items():
        log(f"[paper] {split} data: {ds.n_policies} policies x "
            f"{ds.n_transitions // ds.n_policies} transitions"
            f"{' (reused from ' + data_dir + ')' if reused else ''}")
    phase("data", t0)
    train_ds, test_ds = datasets["train"], datasets["test"]
    result["sizes"].update(train_policies=train_ds.n_policies, test_policies=test_ds.n_policies)
    train_pols, test_pols = policies_for(train_ds), policies_for(test_ds)
    result["test_policy_names"] = list(test_ds.meta.get("policy_names") or [])
    result["true_value_undiscounted"] = np.asarray(test_ds.value, np.float64).tolist()
    result["true_length"] = np.round(episode_lengths(test_ds), 1).tolist()  # logged episodes
    result["zoo_sha256"] = zoo_sha256(args.task)

    # ---- 1b. the control: the real dynamics through the same evaluation path
    if sizes["oracle"]:
        t0 = time.perf_counter()
        cfg = make_config(train_ds, "rl2s", profile, overrides=parse_overrides(args.set))
        orc = oracle_rows(args.task, test_ds, test_pols, seed_ids,
                          n_episodes=sizes["eval_episodes"], horizon=cfg.vd_horizon,
                          gamma=cfg.gamma, n_boot=sizes["bootstrap"])
        result["per_seed"]["oracle"] = {**orc["per_seed"], "mpi": [], "api": []}
        result["lane_intervals"] = {"oracle": orc["intervals"]}
        result["intervals"] = {"oracle": intervals_over_seeds(orc["intervals"])}
        result["oracle_sim_value"] = orc["sim_value"]
        result["oracle_sim_length"] = orc["sim_length"]
        result["noise_ceiling"] = oracle_noise_ceiling(
            test_ds, true_values(test_ds, cfg.vd_horizon, cfg.gamma), orc["sim_return_sd"],
            n_sim=sizes["eval_episodes"], horizon=cfg.vd_horizon, gamma=cfg.gamma)
        phase("oracle", t0)
        write(path, result)
        log(f"[paper] oracle (real dynamics, horizon {cfg.vd_horizon}): "
            + "  ".join(f"{k} {np.mean(v):.3f}" for k, v in orc["per_seed"].items()
                        if k in ("kendall_tau", "ndcg@1", "spearman", "avd", "mvd")))
        nc = result["noise_ceiling"]
        log(f"[paper] noise ceiling (an exact simulator, {nc['n_truth']} truth / "
            f"{nc['n_sim']} simulated episodes): kendall_tau {nc['kendall_tau']['mean']:.3f} "
            f"[{nc['kendall_tau']['lo']:.2f}, {nc['kendall_tau']['hi']:.2f}]  ndcg@1 "
            f"{nc['ndcg@1']['mean']:.3f}")

    # ---- 2. training, one vmapped program per family
    overrides = {**(LEGACY_MODEL if args.model == "legacy" else {}), **parse_overrides(args.set)}
    robust_eps = overrides.pop("eps", None)
    finals, configs = {}, {}
    for family, cfg_method, methods in families:
        t0 = time.perf_counter()
        cfg = make_config(train_ds, cfg_method, profile, overrides=overrides)
        configs[family] = cfg
        uses_u = [v for v in variants if {"penalty", "stop"} & set(v.split("+"))]
        if (uses_u and sizes["improve_iterations"] and sizes["improve_seeds"]
                and min(cfg.ensemble_size, cfg.n_elites) < 2):
            raise SystemExit(f"improve-variants: {', '.join(uses_u)} need u = the ensemble's "
                             f"disagreement, i.e. >= 2 elites; the {family} model has "
                             f"ensemble_size {cfg.ensemble_size}, n_elites {cfg.n_elites} "
                             f"(--model legacy has one member)")
        data = make_train_data(train_ds, train_pols, cfg)
        truth = true_values(test_ds, cfg.vd_horizon, cfg.gamma)
        test_pool = start_pool(test_ds)
        select_pool, select_truth = heldout_start_pool(train_ds), np.asarray(data.true_value)
        lanes = [(m, s) for m in methods for s in seed_ids]
        points = [[] for _ in lanes]  # per lane: {"step", "select", "test"} (model selection)
        eps = [float(robust_eps) if robust_eps is not None and DEFAULT_EPS[m] < 1
               else DEFAULT_EPS[m] for m, _ in lanes]
        keys = jnp.stack([jax.random.PRNGKey(s) for _, s in lanes])
        states = jax.jit(jax.vmap(lambda k, e, d, cfg=cfg: init(k, cfg, d, eps=e),
                                  in_axes=(0, 0, None)))(keys, jnp.asarray(eps, jnp.float32),
                                                         data)
        mesh = lane_mesh(len(lanes))  # lanes over the local devices (one: unchanged)
        states = jax.block_until_ready(shard_lanes(states, mesh))
        data = replicate(data, mesh)
        log(f"[paper] {family}: {len(lanes)} lanes over {mesh.size} device(s) "
            f"{', '.join(f'{m}/{s} (eps {e:g})' for (m, s), e in zip(lanes, eps, strict=True))}"
            f", config method {cfg_method}; init {time.perf_counter() - t0:.1f}s")
        n = sizes["eval_every"]

        compiled = {}
        evals = None
        t_eval = 0.0
        worst = [None] * len(lanes)  # each lane's worst training VD at its last evaluation
        for _ in range(sizes["steps"] // n):
            t1 = time.perf_counter()
            states, m = jax.block_until_ready(train_lanes(states, data, n, cfg, compiled))
            seconds = time.perf_counter() - t1
            t1 = time.perf_counter()
            roll = dict(n_episodes=sizes["eval_episodes"], horizon=cfg.vd_horizon,
                        gamma=cfg.gamma)
            seeds = [s for _, s in lanes]
            sims = simulator(states)
            evals, _values, _returns, _lengths = evaluate_lanes(
                sims, seeds, test_pols, test_pool, truth, key_base=1000, **roll)
            selects = evaluate_lanes(sims, seeds, data.policies, select_pool, select_truth,
                                     key_base=2000, **roll)[0]
            t_eval += time.perf_counter() - t1
            step = int(states.step[0])
            for i, (meth, s) in enumerate(lanes):
                points[i].append({"step": step, "select": selects[i], "test": evals[i]})
                jumps, worst[i] = worst_vd_jumps(np.asarray(m["mvd_train"])[i:i + 1],
                                                 np.ones(1, bool), worst[i])
                for _, before, after in jumps:  # per lane, between evaluations
                    log(f"[paper] warning: {meth} seed {s}: the worst training-policy VD rose "
                        f"from {before:.4g} to {after:.4g} by step {step}")
                    result.setdefault("worst_vd_jumps", {}).setdefault(meth, []).append(
                        {"seed": s, "step": step, "before": before, "after": after})
            log(f"[paper] {family} step {step}: {n} steps of {len(lanes)} lanes in "
                f"{seconds:.1f}s; test evaluation {time.perf_counter() - t1:.1f}s")
            for i, (meth, s) in enumerate(lanes):
                r = evals[i] or {}
                row = {"step": step, "lane": f"{meth}/{s}", "method": meth, "seed": s,
                       "avd": r.get("avd"), "mvd": r.get("mvd"), "tau": r.get("kendall_tau"),
                       "ndcg@1": r.get("ndcg@1"),
                       "select_tau": (selects[i] or {}).get("kendall_tau"),
                       "select_avd": (selects[i] or {}).get("avd"),
                       "avd_train": _none_if_nan(m["avd_train"][i]),
                       "mvd_train": _none_if_nan(m["mvd_train"][i]),
                       "finite": bool(m["finite"][i])}
                result["curves"].append(row)
                fmt = lambda x, f: "n/a" if x is None else format(x, f)
                log(f"  {meth:<8} seed {s}  AVD {fmt(row['avd'], '8.1f')}  MVD "
                    f"{fmt(row['mvd'], '8.1f')}  tau {fmt(row['tau'], '6.3f')}  nDCG@1 "
                    f"{fmt(row['ndcg@1'], '.3f')}  train AVD {fmt(row['avd_train'], '.1f')}"
                    f"  selected {int(m['n_selected'][i])}"
                    f"{'' if row['finite'] else '  NON-FINITE'}")
        truth_se = true_values_se(test_ds, cfg.vd_horizon, cfg.gamma)
        for i, (meth, s) in enumerate(lanes):
            chosen = select_point(points[i])
            sel = result.setdefault("selected", {}).setdefault(
                meth, {"step": [], **{k: [] for k in EVAL_METRICS}})
            sel["step"].append(None if chosen is None else chosen["step"])
            for k in EVAL_METRICS:
                sel[k].append(None if chosen is None else chosen["test"][k])
            r = evals[i]
            for k in EVAL_METRICS:
                result["per_seed"][meth][k].append(None if r is None else r[k])
            iv = None
            if r is not None and sizes["bootstrap"] and np.all(np.isfinite(_returns[i])):
                iv = bootstrap_intervals(truth, _returns[i], truth_se, n_boot=sizes["bootstrap"],
                                         seed=s, ks=(1, 3, 5, 10))["metrics"]
            result.setdefault("lane_intervals", {}).setdefault(meth, []).append(iv)
            result.setdefault("intervals", {})[meth] = intervals_over_seeds(
                result["lane_intervals"][meth])
            result["lanes"][f"{meth}/{s}"] = {
                "family": family, "eps": eps[i], "seed": s,
                "sim_value": np.asarray(_values[i]).tolist(),
                "sim_length": np.round(_lengths[i], 1).tolist(),
                "finite": all(row["finite"] for row in result["curves"]
                              if row["lane"] == f"{meth}/{s}")}
        result["true_value"] = np.asarray(truth).tolist()
        result.setdefault("train_config", {})[family] = cfg.to_dict()
        timings[f"eval_{family}"] = round(t_eval, 1)
        if args.check_eval:
            from rl2s_jax.evaluate.simulator import evaluate_simulator
            r = evaluate_simulator(simulator(_take(states, 0)), test_ds, test_pols,
                                   key=jax.random.PRNGKey(1000 + lanes[0][1]),
                                   n_episodes=sizes["eval_episodes"], horizon=cfg.vd_horizon,
                                   gamma=cfg.gamma)
            diff = float(np.max(np.abs(np.asarray(r["sim_value"]) - _values[0])))
            result.setdefault("eval_check", {})[family] = {
                "lane": f"{lanes[0][0]}/{lanes[0][1]}", "max_abs_diff": diff,
                "metrics": r["metrics"]}
            log(f"[paper] check: evaluate_simulator on lane {lanes[0]} differs from the "
                f"vmapped evaluation by at most {diff:.3g}")
        finals[family] = (lanes, states)
        phase(f"train_{family}", t0)
        write(path, result)

    # ---- 3. improvement
    it = sizes["improve_iterations"]
    if it and (sizes["improve_seeds"] or args.control):
        task = get_task(args.task)
        c0_all = np.asarray(test_ds.value, np.float64)
        ids = [i for i in pick_policies(c0_all, sizes["improve_policies"]) if c0_all[i] != 0]
        c0 = c0_all[ids]
        pols = index_params(test_pols, np.asarray(ids))
        horizon = next(iter(configs.values())).vd_horizon
        n_envs = sizes["sac_envs"]
        sac_cfg = SACConfig.fine_tuning(**{**dict(episode_length=horizon, n_envs=n_envs,
                                      critic_warmup_updates=sizes["sac_critic_warmup"],
                                      updates_per_step=sizes["sac_updates_per_step"],
                                      buffer_size=min(100_000, n_envs * (64 + it))),
                               **PROFILES[profile]["sac"], **sac_overrides})
        result["sac_config"] = {k: (list(v) if isinstance(v, tuple) else v)
                                for k, v in dataclasses.asdict(sac_cfg).items()}
        if sac_cfg.critic_warmup_updates >= it * sac_cfg.updates_per_step:
            log("[paper] note: the critic warm-up covers every SAC update, so the actors stay "
                "as they were")
        ep_len = int(test_ds.meta.get("episode_length") or task.episode_length)
        gamma_data = float(test_ds.meta.get("gamma") or 0.999)
    if it and sizes["improve_seeds"]:
        lanes, sims = [], []
        for family, _, _ in families:
            fam_lanes, states = finals[family]
            idx = [i for i, (_, s) in enumerate(fam_lanes)
                   if s < seed_ids[0] + sizes["improve_seeds"]]
            lanes += [fam_lanes[i] for i in idx]
            sims.append(_take(simulator(states), idx))
        statics = {(s.task, s.obs_clip, s.noise_scale, s.n_elites, s.member_mode, s.uncertainty)
                   for s in sims}
        if len(statics) != 1:
            raise SystemExit(f"set: the families' simulators differ in {statics}; they must "
                             f"share task, obs_clip, sim_noise and the ensemble's rollout settings "
                             f"to be fine-tuned together")
        sims = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *sims)
        keys = jnp.stack([jax.random.split(jax.random.fold_in(jax.random.PRNGKey(10 + s),
                                                              METHODS.index(m)), len(ids))
                          for m, s in lanes])
        u_rows = real_rows(test_ds)
        result["ablation"] = {}
        for vi, variant in enumerate(variants):
            t0 = time.perf_counter()
            # the first variant runs in every lane (Table 2), the others in the lanes of
            # --ablation-methods only
            v_idx = [i for i, (m, _) in enumerate(lanes) if vi == 0 or m in ablation_methods]
            if not v_idx:
                continue
            v_lanes, v_sims, v_keys = [lanes[i] for i in v_idx], _take(sims, v_idx), keys[
                jnp.asarray(v_idx)]
            settings = variant_settings(variant, args)
            pool = (branch_pool(test_ds, max_states=100_000) if settings["rollout_length"]
                    else start_pool(test_ds))

            def env_options(sim, settings=settings):
                return scaled_env_options(sim, *u_rows, **settings)

            log(f"[paper] improvement ({variant}: {settings}): SAC x {it} iterations "
                f"({n_envs} envs, {sac_cfg.updates_per_step} update(s) per iteration, critic "
                f"warm-up {sac_cfg.critic_warmup_updates} updates, episodes of {horizon} "
                f"steps) for {len(ids)} test policies in {len(v_lanes)} simulators "
                f"({', '.join(f'{m}/{s}' for m, s in v_lanes)}) as one program")
            actors, sim_return = improve_in_lanes(v_sims, task, pool, pols, v_keys, sac_cfg,
                                                  n_iterations=it,
                                                  chunk=min(sizes["sac_chunk"], it),
                                                  env_options=env_options,
                                                  snapshots=args.guard_snapshots)
            snaps = None
            if args.guard_snapshots:  # [C, L, P, ...]; the final actors are the last
                snaps, actors = actors, jax.tree_util.tree_map(lambda x: x[-1], actors)
            name = "improve_sac" if vi == 0 else f"improve_sac[{variant}]"
            phase(name, t0)
            L, P = len(v_lanes), len(ids)
            accepted, chosen_index, chosen = None, None, []
            if args.guard_margin is not None:  # each simulator's own verdict per policy
                t0 = time.perf_counter()
                accepted, starts = [], start_pool(test_ds)
                chosen_index = [] if snaps is not None else None
                for i in range(L):  # the elites differ per lane (chosen on the host)
                    lane = jax.tree_util.tree_map(lambda x, i=i: x[i], (v_sims, actors))
                    if snaps is None:
                        both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]),
                                                      pols, lane[1])
                        v = member_values(lane[0], task, both, starts,
                                          jax.random.PRNGKey(40 + i), n_episodes=16,
                                          horizon=horizon, gamma=gamma_data)
                        accepted.append(deployment_guard(v[:, :P], v[:, P:], args.guard_margin))
                        continue
                    # the start and every snapshot [C + 1, P, ...], valued once: the guard on
                    # the final actors reads the first and last rows of the same values
                    cands = jax.tree_util.tree_map(
                        lambda p0, x, i=i: jnp.concatenate([p0[None], x[:, i]]), pols, snaps)
                    pick, info = select_by_members(
                        lane[0], task, cands, starts, jax.random.PRNGKey(40 + i),
                        n_episodes=16, horizon=horizon, gamma=gamma_data,
                        margin=args.guard_margin)
                    accepted.append(deployment_guard(info["values"][0], info["values"][-1],
                                                     args.guard_margin))
                    chosen_index.append(info["index"])
                    chosen.append(pick)
                phase("improve_guard" if vi == 0 else f"improve_guard[{variant}]", t0)
            t0 = time.perf_counter()
            flat = jax.tree_util.tree_map(lambda x, n=L * P: x.reshape((n,) + x.shape[2:]),
                                          actors)
            # paired: the start policies, every lane's fine-tuned ones (and the snapshots the
            # guard chose) from common starts and noise draws (measure_values'
            # common_groups), C0 measured alongside
            groups = [pols, flat, *chosen]
            with_start = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *groups)
            G = 1 + L + len(chosen)
            real = measure_values(task.make_env(), with_start, key=jax.random.PRNGKey(20),
                                  n_episodes=sizes["improve_episodes"], episode_length=ep_len,
                                  gamma=gamma_data, common_groups=G, per_episode=True)
            r = np.asarray(real["returns"], np.float64).reshape(G, P, -1)
            paired = [paired_returns(r[0], r[1 + i]) for i in range(L)]
            c1 = np.stack([pr["c1"] for pr in paired])
            se = np.stack([pr["c1_se"] for pr in paired])
            phase("improve_measure" if vi == 0 else f"improve_measure[{variant}]", t0)
            improvement, per_method = {}, {m: {k: [] for k in IMPROVE_METRICS}
                                           for m in result["per_seed"] if m in METHODS}
            guarded_method = {m: {"mpi": [], "api": []} for m in per_method}
            snapshot_method = {m: {"mpi": [], "api": [], "mpi_paired": [], "api_paired": []}
                               for m in per_method}
            for i, (m, s) in enumerate(v_lanes):
                try:
                    imp = improvement_metrics(c0, c1[i])
                except ValueError as err:  # a non-finite real return
                    log(f"  {m:<8} seed {s}  no MPI/API: {err}")
                    imp = {"I": np.full(len(ids), np.nan), "mpi": None, "api": None}
                per_method[m]["mpi"].append(imp["mpi"])
                per_method[m]["api"].append(imp["api"])
                pr = paired[i]
                improvement[f"{m}/{s}"] = {
                    "method": m, "seed": s, "policy_ids": ids, "c0": c0.tolist(),
                    "c1": [_none_if_nan(x) for x in c1[i]], "c1_se": se[i].tolist(),
                    "I": [_none_if_nan(x) for x in imp["I"]],
                    "sim_return": [_none_if_nan(x) for x in sim_return[i]],
                    "mpi": imp["mpi"], "api": imp["api"],
                    # C0 re-measured on the episodes of C1 (paired), I from the pair
                    "paired_episodes": int(r.shape[-1]),
                    "c0_paired": pr["c0"].tolist(), "c0_paired_se": pr["c0_se"].tolist(),
                    "diff_se": pr["diff_se"].tolist(), "I_paired": pr["I"].tolist(),
                    "mpi_paired": pr["mpi"], "api_paired": pr["api"]}
                per_method[m]["mpi_paired"].append(pr["mpi"])
                per_method[m]["api_paired"].append(pr["api"])
                if accepted is not None and imp["mpi"] is not None:
                    # a kept start policy earns its C0: I = 0
                    dep = improvement_metrics(c0, np.where(accepted[i], c1[i], c0))
                    improvement[f"{m}/{s}"].update(
                        guard_accepted=accepted[i].tolist(), I_deployed=dep["I"].tolist(),
                        mpi_deployed=dep["mpi"], api_deployed=dep["api"])
                    guarded_method[m]["mpi"].append(dep["mpi"])
                    guarded_method[m]["api"].append(dep["api"])
                if chosen_index is not None and imp["mpi"] is not None:
                    idx = chosen_index[i]
                    c1_snap = paired_returns(r[0], r[1 + L + i])
                    dep = improvement_metrics(c0, np.where(idx > 0, c1_snap["c1"], c0))
                    i_paired = np.where(idx > 0, c1_snap["I"], 0.0)  # a kept start: I = 0
                    improvement[f"{m}/{s}"].update(
                        guard_snapshot=idx.tolist(), I_snapshot=dep["I"].tolist(),
                        mpi_snapshot=dep["mpi"], api_snapshot=dep["api"],
                        I_snapshot_paired=i_paired.tolist())
                    snapshot_method[m]["mpi"].append(dep["mpi"])
                    snapshot_method[m]["api"].append(dep["api"])
                    snapshot_method[m]["mpi_paired"].append(float(i_paired.min()))
                    snapshot_method[m]["api_paired"].append(float(i_paired.mean()))
                if imp["mpi"] is not None:
                    log(f"  {m:<8} seed {s}  MPI {imp['mpi']:8.3f}  API {imp['api']:8.3f}  "
                        f"(C1 - C0 mean {np.mean(c1[i] - c0):.1f}, simulated training return "
                        f"{_finite_mean(sim_return[i])})")
            if vi == 0:
                for m in per_method:
                    for k in IMPROVE_METRICS:
                        result["per_seed"][m].setdefault(k, [])
                        result["per_seed"][m][k] += per_method[m][k]
                result["improvement"] = improvement
                result["improve_variant"] = variant
            result["ablation"][variant] = {
                "settings": settings, "lanes": improvement,
                "methods": _method_means(per_method)}
            if accepted is not None:
                result["ablation"][f"{variant}+guard"] = {
                    "settings": {**settings, "guard_margin": args.guard_margin},
                    "methods": _method_means(guarded_method)}
            if chosen_index is not None:
                result["ablation"][f"{variant}+guard-snapshots"] = {
                    "settings": {**settings, "guard_margin": args.guard_margin,
                                 "snapshot_every": min(sizes["sac_chunk"], it)},
                    "methods": _method_means(snapshot_method)}
            write(path, result)
    if it and args.control:
        t0 = time.perf_counter()
        R = args.control_seeds
        log(f"[paper] control: the same SAC x {it} iterations in the real env for {len(ids)} "
            f"test policies x {R} seed(s)")
        tiled = jax.tree_util.tree_map(lambda x: jnp.concatenate([x] * R), pols)
        _, ctrl_metrics, ctrl = improve_in_real_env(
            task, tiled, jax.random.PRNGKey(30), sac_cfg, n_iterations=it,
            n_episodes=sizes["improve_episodes"], episode_length=ep_len, gamma=gamma_data,
            chunk_iterations=min(sizes["sac_chunk"], it))
        last = min(sizes["sac_chunk"], it)  # the training return of the last chunk
        result["control"] = control_entry(ctrl, ids, c0, R, np.asarray(episode_returns(
            jax.tree_util.tree_map(lambda x: x[:, -last:], ctrl_metrics))))
        phase("control", t0)
        cc = result["control"]
        log(f"[paper] control (real env): MPI {_fmt_ms(cc['mpi'], cc['mpi_std'])}  API "
            f"{_fmt_ms(cc['api'], cc['api_std'])} over {R} seed(s)")
    timings["total"] = round(time.perf_counter() - t_start, 1)
    result["complete"] = True
    write(path, result)
    log(f"\n[paper] {args.task}: {S} seeds on {device}, {timings['total']:.0f}s in all; "
        f"timings {timings}\n{table(result)}\n-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
