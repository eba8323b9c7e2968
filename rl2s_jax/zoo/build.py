"""Grow a policy zoo: SAC and/or PPO over seeds, snapshots along training, measured returns,
a zoo spread evenly over the returns, and a train/test split that spans the range.

The paper samples policies of every quality from P(pi); we train learners from several seeds
(``zoo_train.train_learner``: resumable, time-limited, seeds vmapped) and keep snapshots from
the random initial policy to the final one. Every snapshot's real return is then measured with
fresh episodes (``collect.measure_values``), ``spread_subset`` keeps ``zoo_size`` of them
spread evenly over the range of returns, and ``choose_split`` picks train policies spread the
same way, the rest being test policies. ``spread_check`` reports, per split, the largest gap
between neighbouring returns and whether the split reaches both ends of the zoo's range.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time

import jax
import numpy as np

from rl2s_jax._files import atomic_open, save_figure, write_text
from rl2s_jax.data.collect import measure_values
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy.ppo import PPOConfig
from rl2s_jax.policy.sac import SACConfig
from rl2s_jax.zoo.learners import LEARNERS, LearnerPlan, LearnerRun, make_learner, train_learner
from rl2s_jax.zoo.zoo import Zoo, load_zoo, save_zoo, zoo_dir

# Per-task learner settings (per seed). SAC follows brax's published MJX Hopper/Walker2d SAC
# (normalised observations, discount 0.997, lr 6e-4, batch 512, reward scaling, target entropy
# -action_size / 2, a 2^20-row buffer) with 256 envs per seed and 64 updates per env step (an
# update-to-data ratio of 1/4): SAC's speed on the GPU is bound by the number of sequential
# updates, so many envs add data at almost no cost. PPO follows brax's Ant settings. Zoo
# policies are 64x64 tanh-Gaussian MLPs for both learners (so --algo both can pool them);
# critics are 256x256. The env-step budgets are upper bounds for one GPU call: a run with
# --time-limit --final stops there and builds the zoo from the snapshots so far.
# See docs/EVALUATION.md ("Policy zoos").
_SAC_MJX = dict(n_envs=256, batch_size=512, updates_per_step=64, learning_rate=6e-4,
                gamma=0.997, normalize_observations=True, warmup_steps=64,
                buffer_size=1 << 20, hidden=(256, 256), actor_hidden=(64, 64))
ZOO_SAC = {
    "pointmass": LearnerPlan(SACConfig(
        n_envs=16, batch_size=128, warmup_steps=16, buffer_size=20_000, hidden=(64, 64),
        actor_hidden=(64, 64), learning_rate=1e-3, gamma=0.95, normalize_observations=True,
        init_alpha=0.1), env_steps=48_000, snapshots=10),
    "hopper": LearnerPlan(SACConfig(**_SAC_MJX, reward_scaling=30.0, target_entropy=-1.5),
                          env_steps=6_000_000),
    "walker2d": LearnerPlan(SACConfig(**_SAC_MJX, reward_scaling=5.0, target_entropy=-3.0),
                            env_steps=6_000_000),
    "halfcheetah": LearnerPlan(SACConfig(**{**_SAC_MJX, "gamma": 0.99}, target_entropy=-3.0),
                               env_steps=6_000_000),
    "ant": LearnerPlan(SACConfig(**{**_SAC_MJX, "gamma": 0.99}, target_entropy=-4.0),
                       env_steps=6_000_000),
}
ZOO_PPO = {
    "pointmass": LearnerPlan(PPOConfig(num_envs=64, unroll_length=16, num_minibatches=4,
                                       episode_length=50, gamma=0.95, learning_rate=1e-3),
                             env_steps=102_400, snapshots=10),
    "hopper": LearnerPlan(PPOConfig(num_envs=4096, unroll_length=20, num_minibatches=32,
                                    gamma=0.995, entropy_cost=1e-3), env_steps=60_000_000),
    "walker2d": LearnerPlan(PPOConfig(num_envs=4096, unroll_length=20, num_minibatches=32,
                                      gamma=0.99, entropy_cost=1e-3), env_steps=60_000_000),
    # brax's HalfCheetah PPO: discount 0.95, 8 epochs, unroll 20
    "halfcheetah": LearnerPlan(PPOConfig(num_envs=4096, unroll_length=20, num_minibatches=32,
                                         update_epochs=8, gamma=0.95, entropy_cost=1e-3),
                               env_steps=60_000_000),
    # brax's Ant PPO: 4096 envs, unroll 5, discount 0.97, entropy 1e-2, reward scaling 10
    "ant": LearnerPlan(PPOConfig(num_envs=4096, unroll_length=5, num_minibatches=32,
                                 reward_scaling=10.0), env_steps=60_000_000),
}
PLANS = {"sac": ZOO_SAC, "ppo": ZOO_PPO}

# SAC for the tasks where it is known to need far fewer env steps than PPO (expected to matter
# in a GPU call of minutes; not yet measured here); PPO for Ant, brax's choice there.
DEFAULT_ALGO = {"pointmass": "sac", "hopper": "sac", "walker2d": "sac",
                "halfcheetah": "sac", "ant": "ppo"}

SPLIT_SIZES = {"ant": 32}   # train-split size; 17 for every other task (the paper's)
MIN_TEST = {"ant": 14}      # smallest test split; 8 for every other task
EXPERT_BARS = {"hopper": 2500.0, "walker2d": 3500.0, "halfcheetah": 6000.0, "ant": 3500.0}
# The spread rule (issue 15), per split, as fractions of the zoo's return range.
MAX_GAP, BOTTOM, TOP = 0.2, 0.1, 0.2
# The zoo learner's SAC fields that fine-tuning takes over (fine_tuning_recipe).
RECIPE_FIELDS = ("gamma", "reward_scaling", "batch_size")


def fine_tuning_recipe(task_name: str) -> dict:
    """SACConfig fields for fine-tuning a zoo policy of ``task_name`` at its learner's
    discount, reward scale and batch size (``ZOO_SAC``) with a 2^19-row buffer and alpha held
    at its start (``learn_alpha=False``): the recipe under which the real-env control gains
    (docs/RESULTS.md, "Policy improvement: the real-env control (issue 39)"; a learned alpha
    ran away from 0.01 to 0.3-98 and lost 0.1-0.2 of median gain on every task).
    KeyError-free: a task without a SAC plan gets {}. Ant's shipped zoo was trained by PPO
    (gamma 0.97, reward scaling 10), so Ant gets its SAC plan's settings, not its learner's;
    a CPU probe on two training policies found PPO's worse for fine-tuning
    (docs/results/control_zoo_recipe/cpu_probe/ant_train_*.json)."""
    plan = ZOO_SAC.get(task_name)
    if plan is None:
        return {}
    return {**{k: getattr(plan.config, k) for k in RECIPE_FIELDS}, "buffer_size": 1 << 19,
            "learn_alpha": False}


def spread_subset(returns: np.ndarray, size: int) -> list[int]:
    """Indices of ``size`` policies whose returns cover [min, max] as evenly as possible.

    Greedy: for each of ``size`` evenly spaced target returns, the closest policy not yet taken.
    Snapshots crowd where training plateaus; this keeps the zoo's quality spread even.
    """
    returns = np.asarray(returns, np.float64)
    if size > len(returns):
        raise ValueError(f"zoo_size: expected at most {len(returns)} (snapshots), got {size}")
    free = np.ones(len(returns), bool)
    picks = []
    for target in np.linspace(returns.min(), returns.max(), size):
        i = int(np.argmin(np.where(free, np.abs(returns - target), np.inf)))
        free[i] = False
        picks.append(i)
    return sorted(picks)


def choose_split(returns: np.ndarray, n_train: int, min_test: int = 8
                 ) -> tuple[list[int], list[int]]:
    """Train and test ids interleaved by rank, so both splits follow the zoo's distribution of
    returns: with the policies sorted by return, train takes ``n_train`` ranks evenly spaced
    from the lowest to the highest (both ends), test every other policy.

    (Choosing train by ``spread_subset`` over the returns, the earlier rule, left the test split
    whatever lay between the train picks; choosing test first left the train split without
    the sparse middle of a fast-rising learning curve: gaps of 40-70% of the range on the
    first GPU zoos.) Where the zoo itself has a hole, no split can close it: spread_check
    reports it."""
    returns = np.asarray(returns, np.float64)
    P = len(returns)
    if P < n_train + min_test:
        raise ValueError(f"zoo: {P} policies cannot give {n_train} train + {min_test} test")
    order = np.argsort(returns, kind="stable")
    train = sorted(int(i) for i in order[np.round(np.linspace(0, P - 1, n_train)).astype(int)])
    return train, sorted(set(range(P)) - set(train))


def extend_zoo(base: Zoo, params, values: dict, origins: list[dict], min_test: int,
               run: dict | None = None) -> tuple[Zoo, list[int]]:
    """``base`` with test policies added from new snapshots (``params`` [C, ...], measured
    ``values`` {"value", "value_se"} [C], ``origins`` C dicts) by ``fill_gaps`` until its test
    split holds at least ``min_test`` and has no fillable hole. Policy ids and the training
    split stay as they were, so a dataset collected from the base zoo's training policies is
    the dataset of the extended zoo too; added policies take ids base.size, base.size + 1, ...

    -> (the extended Zoo, the candidate indices added, in id order)."""
    ret = np.asarray(base.returns, np.float64)
    lo, hi = float(ret.min()), float(ret.max())
    picks = sorted(fill_gaps(ret[base.test_ids], values["value"], lo, hi, min_test))
    if len(base.test_ids) + len(picks) < min_test:
        raise ValueError(
            f"min_test: the {len(origins)} new snapshots hold {len(picks)} returns inside the "
            f"zoo's range [{lo:.1f}, {hi:.1f}]; the test split would have "
            f"{len(base.test_ids) + len(picks)} < {min_test} policies. Train more seeds "
            "(--seeds) or more snapshots (--snapshots)")
    added = jax.tree_util.tree_map(lambda x: np.asarray(x)[np.asarray(picks, int)], params)
    new_params = jax.tree_util.tree_map(lambda a, b: np.concatenate([np.asarray(a), b]),
                                        base.params, added)
    new_ret = np.concatenate([ret, values["value"][picks]]).astype(np.float32)
    new_se = np.concatenate([np.asarray(base.return_se, np.float64),
                             values["value_se"][picks]]).astype(np.float32)
    test_ids = sorted(list(base.test_ids) + list(range(base.size, base.size + len(picks))))
    info = dict(base.info or {})
    info["spread"] = {"train": spread_check(new_ret[base.train_ids], new_ret),
                      "test": spread_check(new_ret[test_ids], new_ret)}
    info["extensions"] = list(info.get("extensions", [])) + [
        {**(run or {}), "candidates": len(origins), "added": len(picks),
         "ids": list(range(base.size, base.size + len(picks)))}]
    zoo = dataclasses.replace(base, params=new_params, returns=new_ret, return_se=new_se,
                              origins=list(base.origins) + [origins[i] for i in picks],
                              test_ids=test_ids, info=info)
    return zoo, picks


def zoo_with_log(task_or_dir: str) -> tuple[Zoo, list[dict]]:
    """A zoo (``load_zoo``) and the rows of its train_log.jsonl ([] when it has none)."""
    directory = task_or_dir if os.path.isdir(task_or_dir) else zoo_dir(task_or_dir)
    path = os.path.join(directory, "train_log.jsonl")
    rows = []
    if os.path.exists(path):
        with open(path) as f:
            rows = [json.loads(line) for line in f if line.strip()]
    return load_zoo(task_or_dir), rows


def resplit(zoo: Zoo, n_train: int, min_test: int = 8) -> Zoo:
    """``zoo`` with its train/test split chosen again by ``choose_split`` and the spread check
    of ``info`` updated (for zoos built with an earlier split rule)."""
    ret = np.asarray(zoo.returns, np.float64)
    train_ids, test_ids = choose_split(ret, n_train, min_test)
    info = dict(zoo.info or {})
    info["spread"] = {"train": spread_check(ret[train_ids], ret),
                      "test": spread_check(ret[test_ids], ret)}
    return dataclasses.replace(zoo, train_ids=train_ids, test_ids=test_ids, info=info)


def fill_gaps(split_returns, candidate_returns, lo: float, hi: float, min_count: int,
              max_gap: float = MAX_GAP) -> list[int]:
    """Indices into ``candidate_returns`` to add to a split so that it holds at least
    ``min_count`` policies and no gap wider than ``max_gap`` of the range [lo, hi] that a
    candidate could fill remains.

    Greedy: while more are needed, the widest gap between neighbouring returns of the split
    (the ends lo and hi count as neighbours) that holds a free candidate strictly inside takes
    the candidate closest to its middle. Candidates outside [lo, hi] are never taken: added
    policies fill holes, they do not stretch the range the training split was chosen over."""
    split = [float(r) for r in np.asarray(split_returns, np.float64)]
    cand = np.asarray(candidate_returns, np.float64)
    span = hi - lo
    if span <= 0:
        raise ValueError("fill_gaps: expected lo < hi (the zoo's return range)")
    free = np.isfinite(cand) & (cand >= lo) & (cand <= hi)
    picks: list[int] = []
    while True:
        edges = np.array(sorted(split + [float(cand[i]) for i in picks] + [lo, hi]))
        n_now = len(split) + len(picks)
        order = np.argsort(-np.diff(edges), kind="stable")
        pick = None
        for g in order:
            a, b = edges[g], edges[g + 1]
            if n_now >= min_count and (b - a) / span <= max_gap:
                break                      # enough policies and the widest fillable gap is fine
            inside = free & (cand > a) & (cand < b)
            if inside.any():
                mid = (a + b) / 2
                pick = int(np.argmin(np.where(inside, np.abs(cand - mid), np.inf)))
                break
        if pick is None:
            return picks
        free[pick] = False
        picks.append(pick)


def spread_check(split_returns, zoo_returns, max_gap: float = MAX_GAP, bottom: float = BOTTOM,
                 top: float = TOP) -> dict:
    """Does a split span the zoo's return range evenly?

    With the split's returns sorted: the largest gap between neighbours as a fraction of the
    zoo's range (max - min of ``zoo_returns``) must not exceed ``max_gap``, the lowest return
    must lie in the bottom ``bottom`` fraction of the range and the highest in the top ``top``.
    -> {"n", "largest_gap" (fraction), "gap_between" [low, high], "lowest_at", "highest_at"
    (fractions of the range from the zoo's min), "pass", "failures" (what failed, in words)}.
    """
    r = np.sort(np.asarray(split_returns, np.float64))
    z = np.asarray(zoo_returns, np.float64)
    if r.size == 0 or not np.all(np.isfinite(r)) or not np.all(np.isfinite(z)):
        raise ValueError("returns: expected a non-empty split of finite returns")
    lo, span = z.min(), z.max() - z.min()
    if span <= 0:
        raise ValueError("zoo_returns: the zoo's returns have no range (all equal)")
    gaps = np.diff(r) / span
    i = int(np.argmax(gaps)) if gaps.size else 0
    out = {"n": int(r.size), "largest_gap": float(gaps[i]) if gaps.size else 0.0,
           "gap_between": [float(r[i]), float(r[i + 1])] if gaps.size else [float(r[0])] * 2,
           "lowest_at": float((r[0] - lo) / span), "highest_at": float((r[-1] - lo) / span),
           "rule": {"max_gap": max_gap, "bottom": bottom, "top": top}}
    failures = []
    if out["largest_gap"] > max_gap:
        failures.append(f"gap of {out['largest_gap']:.0%} of the range between returns "
                        f"{out['gap_between'][0]:.1f} and {out['gap_between'][1]:.1f} "
                        f"(max {max_gap:.0%})")
    if out["lowest_at"] > bottom:
        failures.append(f"lowest return at {out['lowest_at']:.0%} of the range "
                        f"(must be in the bottom {bottom:.0%})")
    if out["highest_at"] < 1 - top:
        failures.append(f"highest return at {out['highest_at']:.0%} of the range "
                        f"(must be in the top {top:.0%})")
    out["pass"], out["failures"] = not failures, failures
    return out


def format_spread(name: str, check: dict) -> str:
    verdict = "PASS" if check["pass"] else "FAIL: " + "; ".join(check["failures"])
    return (f"{name:<5} n={check['n']:<3} largest gap {check['largest_gap']:.1%}, lowest at "
            f"{check['lowest_at']:.1%}, highest at {check['highest_at']:.1%} -> {verdict}")


def _override(cfg, overrides: dict, what: str):
    """``cfg`` with fields replaced from ``overrides`` (lists become tuples)."""
    fields = {f.name for f in dataclasses.fields(cfg)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"set: {what} has no field(s) {bad}; fields: {sorted(fields)}")
    fix = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    return dataclasses.replace(cfg, **fix)


def learner_plans(task_name: str, algo: str, env_steps: int | None = None,
                  snapshots: int | None = None, overrides: dict | None = None
                  ) -> dict[str, LearnerPlan]:
    """The plans of the learners of ``algo`` ('sac' | 'ppo' | 'both') for a task, with the
    task's episode length and absolute-position dims filled in and ``overrides``
    ({'sac': {field: value}, 'ppo': {...}}) applied."""
    task = get_task(task_name)
    names = LEARNERS if algo == "both" else (algo,)
    if algo != "both" and algo not in LEARNERS:
        raise ValueError(f"algo: expected sac, ppo or both, got {algo!r}")
    overrides = overrides or {}
    bad = sorted(set(overrides) - set(LEARNERS))
    if bad:
        raise ValueError(f"set: expected keys sac.FIELD or ppo.FIELD, got {bad}")
    plans = {}
    for name in names:
        plan = PLANS[name].get(task_name)
        if plan is None:
            raise ValueError(f"task: no {name} zoo settings for {task_name!r}")
        cfg = dataclasses.replace(plan.config, episode_length=task.episode_length,
                                  ignore_obs_dims=tuple(task.position_dims))
        cfg = _override(cfg, overrides.get(name, {}), name)
        plans[name] = LearnerPlan(cfg, int(env_steps or plan.env_steps),
                                  int(snapshots or plan.snapshots))
    return plans


def _leaf_shapes(tree, lead: int = 0) -> list[tuple[str, tuple]]:
    """[(keystr path, shape without its ``lead`` leading axes)] of a pytree's leaves."""
    return [(jax.tree_util.keystr(p), tuple(x.shape[lead:])) for p, x in
            jax.tree_util.tree_flatten_with_path(tree)[0]]


def _policy_spec(learner) -> list:
    return _leaf_shapes(jax.eval_shape(lambda k: learner.policy(learner.init(k)),
                                       jax.random.PRNGKey(0)))


def build_zoo(task_name: str, *, algo: str | None = None, seeds: int = 4, seed: int = 0,
              plans: dict[str, LearnerPlan] | None = None, work_dir: str | None = None,
              deadline: float | None = None, imported: dict | None = None,
              value_episodes: int = 16, n_train: int | None = None, zoo_size: int = 60,
              min_test: int | None = None, checkpoint_every_s: float = 120.0,
              final: bool = False, extend: Zoo | None = None, progress: bool = True,
              log=print) -> tuple[Zoo | None, dict]:
    """Train the learners of ``algo`` (default: the task's ``DEFAULT_ALGO``) over ``seeds``
    seeds, measure every snapshot, keep ``zoo_size`` spread evenly over the returns, split.

    plans: {learner: LearnerPlan} (default ``learner_plans(task, algo)``); work_dir: where the
    runs checkpoint and resume (default: a fresh temporary directory); deadline: stop training
    (after a checkpoint) at this ``time.time()`` (the first learner not yet done trains at least
    one snapshot interval per call); imported: ``zoo_train.read_export``'s runs,
    used for learners with no checkpoint in work_dir; final: when the deadline stops training,
    build the zoo from the snapshots trained so far instead of returning None (the last call
    of a run; a later call with a larger budget still continues it); extend: a zoo whose test
    split the new snapshots grow to ``min_test`` policies (``extend_zoo``: its training split
    and ids kept; zoo_size and n_train unused); run it with another ``seed`` than the zoo's.

    -> (the Zoo, or None when the time limit stopped training first; extras: {"runs":
    {learner: LearnerRun}, "log": training-log rows with measured returns}).
    """
    task = get_task(task_name)
    env = task.make_env()
    algo = algo or DEFAULT_ALGO.get(task_name, "sac")
    plans = plans or learner_plans(task_name, algo)
    n_train = n_train or SPLIT_SIZES.get(task_name, 17)
    min_test = MIN_TEST.get(task_name, 8) if min_test is None else min_test
    if value_episodes < 1:
        raise ValueError(f"value_episodes: expected >= 1, got {value_episodes}")
    learners = {name: make_learner(name, env, plan.config) for name, plan in plans.items()}
    specs = {name: _policy_spec(lr) for name, lr in learners.items()}
    if len({json.dumps(s, default=list) for s in specs.values()}) > 1:
        raise ValueError("algo both: the learners' policies differ in shape "
                         f"({ {n: [s[1] for s in v] for n, v in specs.items()} }); the zoo "
                         "stacks them, so set sac.actor_hidden equal to ppo.hidden")
    if extend is not None:
        if extend.task != task_name:
            raise ValueError(f"extend: a {extend.task} zoo cannot take {task_name} policies")
        base_spec = _leaf_shapes(extend.params, lead=1)   # the zoo's params are stacked
        for name, spec in specs.items():
            if spec != base_spec:
                raise ValueError(f"extend: the {name} learner's policy {spec} differs in shape "
                                 f"from the zoo's {base_spec}; use the zoo's learner settings")
        seeds_used = {(o.get("learner"), o.get("run_seed", extend.info.get("seed", 0)))
                      for o in extend.origins}
        clash = [n for n in learners if (n, seed) in seeds_used]
        if clash:
            raise ValueError(f"seed: the zoo's {clash} snapshots already come from --seed "
                             f"{seed}; extend it from another seed")
    n_candidates = sum(seeds * (p.snapshots + 1) for p in plans.values())
    if extend is None and n_candidates < n_train + min_test:
        raise ValueError(f"snapshots: {n_candidates} snapshots cannot give {n_train} train + "
                         f"{min_test} test policies; raise --snapshots or --seeds")
    work_dir = work_dir or tempfile.mkdtemp(prefix=f"zoo_{task_name}_")
    runs: dict[str, LearnerRun] = {}
    ran = 0  # snapshot intervals trained in this call: the first learner always makes progress
    for name, learner in learners.items():
        plan = plans[name]
        runs[name] = train_learner(learner, task=task_name, seeds=seeds, seed=seed,
                                   env_steps=plan.env_steps, snapshots=plan.snapshots,
                                   work_dir=work_dir, deadline=deadline,
                                   imported=(imported or {}).get(name),
                                   checkpoint_every_s=checkpoint_every_s,
                                   min_intervals=0 if ran else 1, progress=progress, log=log)
        ran += runs[name].intervals
        if not runs[name].complete:
            if not final:
                return None, {"runs": runs, "log": []}
            log(f"[zoo] {name}: time limit reached with --final: building the zoo from the "
                f"{runs[name].meta['snapshots_done']} snapshot intervals trained so far"
                + (f"; {', '.join(n for n in learners if n not in runs)} not trained"
                   if len(runs) < len(learners) else ""))
            break

    # Pool every snapshot: [learner][seed][snapshot] flattened in that order.
    params, origins = [], []
    for name, run in runs.items():
        S, n1 = run.snapshots["training_return"].shape
        params.append(jax.tree_util.tree_map(lambda x, S=S, n1=n1: x.reshape(
            (S * n1,) + x.shape[2:]), run.snapshots["params"]))
        for s in range(S):
            for k in range(n1):
                r = float(run.snapshots["training_return"][s, k])
                origins.append({"learner": name, "seed": s, "snapshot": k,
                                "env_steps": int(run.snapshots["env_steps"][k]),
                                "training_return": r if np.isfinite(r) else None})
    params = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *params)
    values, measure_s = _measure(env, params, origins, task, seed, value_episodes, work_dir,
                                 log)
    if extend is not None:
        offset = {n: 1 + max((o["seed"] for o in extend.origins if o.get("learner") == n),
                             default=-1) for n in learners}
        rows = [{**r, "seed": r["seed"] + offset[r["learner"]], "run_seed": seed}
                for r in _log_rows(runs, origins, values, {})]
        origins = [{**o, "seed": o["seed"] + offset[o["learner"]], "run_seed": seed}
                   for o in origins]
        run = {"seed": seed, "seeds": seeds, "value_episodes": value_episodes,
               "learners": {n: {"env_steps_per_seed": int(r.snapshots["env_steps"][-1]),
                                "snapshots_per_seed": int(r.meta["snapshots_done"]),
                                "train_seconds": r.meta["train_seconds"]}
                            for n, r in runs.items()}, "measure_seconds": measure_s}
        zoo, picks = extend_zoo(extend, params, values, origins, min_test, run)
        for j in picks:
            rows[j]["zoo"] = "test"
        return zoo, {"runs": runs, "log": rows, "added": picks}

    keep = spread_subset(values["value"], min(zoo_size, len(origins)))
    zoo_params = jax.tree_util.tree_map(lambda x: x[np.asarray(keep)], params)
    zoo_values = {k: v[keep] for k, v in values.items()}
    train_ids, test_ids = choose_split(zoo_values["value"], n_train, min_test)
    ret = zoo_values["value"]
    spread = {"train": spread_check(ret[train_ids], ret),
              "test": spread_check(ret[test_ids], ret)}
    bar = EXPERT_BARS.get(task_name)
    info = {"algo": algo, "seeds": seeds, "seed": seed, "value_episodes": value_episodes,
            "learners": {name: {"config": run.meta["run"]["config"],
                                "env_steps_per_seed": int(run.snapshots["env_steps"][-1]),
                                "env_steps_target": plans[name].env_steps,
                                "complete": run.complete,
                                "snapshots_per_seed": int(run.meta["snapshots_done"]),
                                "iterations_per_snapshot": run.meta["iterations_per_snapshot"],
                                "train_seconds": run.meta["train_seconds"]}
                         for name, run in runs.items()},
            "snapshots_measured": len(origins), "measure_seconds": measure_s,
            "best_return": float(ret.max()), "expert_bar": bar,
            "expert_bar_met": None if bar is None else bool(ret.max() >= bar),
            "spread": spread, "device": str(jax.devices()[0]), "jax": jax.__version__}
    zoo = Zoo(task=task_name, params=zoo_params, returns=ret, return_se=zoo_values["value_se"],
              origins=[origins[i] for i in keep], train_ids=train_ids, test_ids=test_ids,
              info=info)
    split_of = {keep[i]: ("train" if i in set(train_ids) else "test") for i in range(len(keep))}
    rows = _log_rows(runs, origins, values, split_of)
    return zoo, {"runs": runs, "log": rows}


def _measure(env, params, origins, task, seed, value_episodes, work_dir, log):
    """measure_values of every snapshot, cached in work_dir/measured.npz for these snapshots."""
    path = os.path.join(work_dir, "measured.npz")
    finger = json.dumps({"origins": [(o["learner"], o["seed"], o["snapshot"]) for o in origins],
                         "value_episodes": value_episodes, "seed": seed})
    if os.path.exists(path):
        with np.load(path) as z:
            if str(z["fingerprint"]) == finger:
                log(f"[zoo] measured returns of {len(origins)} snapshots: reusing {path}")
                return {k: z[k] for k in z.files if k not in ("fingerprint", "seconds")}, \
                    float(z["seconds"])
    t0 = time.time()
    values = measure_values(env, params, key=jax.random.fold_in(jax.random.PRNGKey(seed), 99),
                            n_episodes=value_episodes, episode_length=task.episode_length,
                            gamma=0.999)
    seconds = round(time.time() - t0, 1)
    with atomic_open(path, "wb") as f:  # a file object: savez adds no .npz suffix
        np.savez(f, fingerprint=finger, seconds=seconds, **values)
    log(f"[zoo] measured {len(origins)} snapshots x {value_episodes} episodes in {seconds:.0f}s;"
        f" returns {values['value'].min():.1f} .. {values['value'].max():.1f}")
    return values, seconds


def _log_rows(runs, origins, values, split_of) -> list[dict]:
    """The training log of every learner and seed, one row per snapshot (snapshot 0: the
    initial policy), with the snapshot's measured return and its split in the zoo (or None)."""
    logged = {(r["learner"], r["seed"], r["snapshot"]): r for run in runs.values()
              for r in run.meta["log"]}
    rows = []
    for j, o in enumerate(origins):
        row = dict(logged.get((o["learner"], o["seed"], o["snapshot"]),
                              {k: o[k] for k in ("learner", "seed", "snapshot", "env_steps")}))
        row.update(measured_return=float(values["value"][j]),
                   measured_return_se=float(values["value_se"][j]), zoo=split_of.get(j))
        rows.append(row)
    return rows


def write_zoo_outputs(zoo: Zoo, rows: list[dict], directory: str) -> list[str]:
    """zoo.npz + zoo.json (policies.save_zoo), train_log.jsonl and the two plots."""

    save_zoo(zoo, directory)
    write_text(os.path.join(directory, "train_log.jsonl"),
               "".join(json.dumps(row) + "\n" for row in rows))
    return ["zoo.npz", "zoo.json", "train_log.jsonl"] + write_zoo_plots(directory)


def write_zoo_plots(directory: str) -> list[str]:
    """curves.png (measured return of every snapshot vs env steps, one line per learner and
    seed; training returns dotted) and returns_hist.png (the zoo's returns by split), from
    zoo.json and train_log.jsonl in ``directory``."""
    # Imported here to keep start-up fast: matplotlib loads in about a second, and only
    # the plots need it.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(os.path.join(directory, "zoo.json")) as f:
        meta = json.load(f)
    with open(os.path.join(directory, "train_log.jsonl")) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    learners = sorted({r["learner"] for r in rows})
    fig, axes = plt.subplots(1, len(learners), figsize=(6 * len(learners), 4), squeeze=False)
    bar = meta["info"].get("expert_bar")
    for ax, name in zip(axes[0], learners, strict=True):
        for s in sorted({r["seed"] for r in rows if r["learner"] == name}):
            rs = sorted((r for r in rows if r["learner"] == name and r["seed"] == s),
                        key=lambda r: r["env_steps"])
            x = np.array([r["env_steps"] for r in rs], float)
            line, = ax.plot(x, [r["measured_return"] for r in rs], "o-", ms=3,
                            label=f"seed {s}")
            tr = [np.nan if r.get("training_return") is None else r["training_return"]
                  for r in rs]
            ax.plot(x, tr, ":", color=line.get_color(), lw=1)
            picked = [(xi, r["measured_return"]) for xi, r in zip(x, rs, strict=True)
                      if r.get("zoo")]
            if picked:
                ax.plot(*zip(*picked, strict=True), "s", mfc="none", color="k", ms=6)
        if bar is not None:
            ax.axhline(bar, color="grey", ls="--", lw=1, label=f"bar {bar:g}")
        ax.set(title=f"{meta['task']}: {name} (squares: in the zoo; dotted: training return)",
               xlabel="env steps per seed",
               ylabel=f"return ({meta['info'].get('value_episodes', '?')} fresh episodes)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, os.path.join(directory, "curves.png"), dpi=110)
    plt.close(fig)

    ret = np.asarray(meta["returns"])
    fig, ax = plt.subplots(figsize=(6, 3.5))
    bins = np.linspace(ret.min(), ret.max(), 21)
    ax.hist([ret[meta["train_ids"]], ret[meta["test_ids"]]], bins=bins, stacked=True,
            label=[f"train ({len(meta['train_ids'])})", f"test ({len(meta['test_ids'])})"])
    ax.set(title=f"{meta['task']} zoo: {meta['size']} policies", xlabel="measured return",
           ylabel="policies")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, os.path.join(directory, "returns_hist.png"), dpi=110)
    plt.close(fig)
    return ["curves.png", "returns_hist.png"]


__all__ = ["DEFAULT_ALGO", "EXPERT_BARS", "ZOO_PPO", "ZOO_SAC", "build_zoo", "choose_split",
           "extend_zoo", "fill_gaps", "fine_tuning_recipe", "learner_plans", "spread_check",
           "spread_subset", "write_zoo_outputs", "write_zoo_plots", "zoo_with_log"]
