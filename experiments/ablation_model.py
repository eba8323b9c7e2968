"""Ablation of the dynamics model on one task (issue 10, items 2-4): the single generator trained
from scratch that preceded the model family ("legacy", RL2S) vs the ensemble trained by maximum
likelihood ("bc") vs RL2S started from the MLE-pretrained ensemble ("rl2s") vs the same run
evaluated with the moving average of its weights ("rl2s+ema"). Judged on the held-out TEST
policies by Kendall tau, nDCG@1, AVD and MVD, at the last step ("final") and at the
evaluation point chosen WITHOUT the test policies ("selected": highest Kendall tau of the
TRAINING policies' simulated values, started from the start states of their held-out
episodes, against their true values; ties to the lower training AVD).

    python experiments/ablation_model.py --task hopper --out DIR [--data-dir DIR]
        [--variants legacy,bc,rl2s] [--seeds 3] [--steps 1200] [--eval-every 200]
        [--eval-episodes 16] [--ema-decay 0.99] [--profile auto|cpu|gpu] [--set key=value ...]
        [--rollouts random:1,mean:0,...]
    python experiments/ablation_model.py --summarize DIR [DIR ...]

Every variant is one vmapped program over the seeds (``paper.train_lanes``: the MLE
pre-training and the adversarial phase are separate compiled pieces) and writes
OUT/ablation_<task>_<variant>.json after every evaluation (a run cut off by a time limit keeps
what it finished); ``--rollouts MODE:NOISE[:TERMINATION],...`` also evaluates each variant's
simulator with other rollout settings (member mode random / mean / fixed, noise scale, and for
a variant trained with a learned hazard, ``termination`` rule / hazard / both; rows
"<variant>@<mode>:<noise>[:<termination>]"), which costs no training. A variant may carry its
own settings, "bc:multistep_steps=5+multistep_weight=0.5" (its row is that whole name). The
last variant also writes OUT/ablation_<task>.json and .md, the table of
every variant's JSON found in OUT. ``--summarize`` rebuilds that table from the JSONs of
several directories (variants run in separate device calls). Data: the zoo's train / test split
as experiments/paper.py collects it (``paper.load_or_collect``, reused from --data-dir).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paper import (  # noqa: E402
    TASK_SIZES,
    load_or_collect,
    log,
    positive_int,
    profile_sizes,
)

from rl2s_jax.app.train import (
    make_config,
    parse_overrides,  # noqa: E402
)
from rl2s_jax.data.summary import episode_lengths
from rl2s_jax.data.values import true_values
from rl2s_jax.envs.tasks import _LOCO, get_task, task_names  # noqa: E402
from rl2s_jax.evaluate.lanes import lane_returns
from rl2s_jax.evaluate.metrics import ranking_metrics  # noqa: E402
from rl2s_jax.model.dynamics import MEMBER_MODES  # noqa: E402
from rl2s_jax.model.simulator import advance_values, start_pool, start_values  # noqa: E402
from rl2s_jax.model.termination import LEARNED, TERMINATIONS  # noqa: E402
from rl2s_jax.train.config import LEGACY_MODEL, TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.lanes import heldout_start_pool, select_point, train_lanes
from rl2s_jax.train.step import init, simulator
from rl2s_jax.zoo.zoo import policies_for  # noqa: E402

# variant -> (config method, config overrides); "rl2s" keeps the EMA and is evaluated twice.
VARIANTS = {
    "legacy": ("rl2s", dict(LEGACY_MODEL)),
    "legacy-bc": ("bc", dict(LEGACY_MODEL)),
    "bc": ("bc", {}),
    "rl2s": ("rl2s", {}),
}
ROWS = ("legacy", "legacy-bc", "bc", "rl2s", "rl2s+ema")
METRICS = ("kendall_tau", "ndcg@1", "avd", "mvd", "spearman")
SIZES = {"gpu": dict(seeds=3, steps=1200, eval_every=200, eval_episodes=16),
         "cpu": dict(seeds=2, steps=40, eval_every=20, eval_episodes=4)}


def _metrics(truth, values) -> dict | None:
    try:
        r = ranking_metrics(np.asarray(truth, np.float64), np.asarray(values, np.float64),
                            ks=(1,))
    except ValueError:  # non-finite simulated values: the lane diverged
        return None
    return {k: float(r[k]) for k in METRICS}


def parse_rollouts(text: str | None) -> list[tuple]:
    """--rollouts 'random:1,mean:0,random:0:both' -> [("random", 1.0), ("mean", 0.0),
    ("random", 0.0, "both")]: member mode, noise scale and optionally the termination."""
    out = []
    for item in (x.strip() for x in (text or "").split(",") if x.strip()):
        mode, _, rest = item.partition(":")
        noise, _, term = rest.partition(":")
        try:
            scale = float(noise)
        except ValueError:
            scale = -1.0
        if (mode not in MEMBER_MODES or not (np.isfinite(scale) and scale >= 0)
                or (term and term not in TERMINATIONS)):
            raise SystemExit(f"rollouts: expected MODE:NOISE[:TERMINATION] items with MODE in "
                             f"{', '.join(MEMBER_MODES)}, NOISE >= 0 and TERMINATION in "
                             f"{', '.join(TERMINATIONS)}, got {item!r}")
        out.append((mode, scale, term) if term else (mode, scale))
    return out


def rollout_row(variant: str, rollout: tuple) -> str:
    return f"{variant}@{rollout[0]}:{rollout[1]:g}" + (f":{rollout[2]}" if len(rollout) > 2
                                                         else "")


def evaluate(states, seeds, weights: bool, *, test, select, cfg, n_episodes,
             rollout: tuple[str, float] | None = None, validation=None) -> list[dict]:
    """Test and selection metrics of every lane, with the moving average (weights=True) or the
    trained weights, rolled out with the config's settings or ``rollout`` (member mode, noise
    scale). test / select / validation (optional): (policies, start pool, true values)."""
    sims = simulator(states, average=weights)
    if rollout is not None:
        sims = sims.replace(member_mode=rollout[0], noise_scale=rollout[1],
                            termination=rollout[2] if len(rollout) > 2 else sims.termination)
    out = [{} for _ in seeds]
    sets = [("test", test, 1000), ("select", select, 2000)]
    if validation is not None:
        sets.append(("validation", validation, 3000))
    for name, (pols, pool, truth), base in sets:
        keys = jnp.stack([jax.random.PRNGKey(base + s) for s in seeds])
        returns, lengths = lane_returns(sims, pols, pool, keys, n_episodes=n_episodes,
                                        horizon=cfg.vd_horizon, gamma=cfg.gamma)
        lengths = np.asarray(lengths, np.float64).mean(-1)
        for i, v in enumerate(np.asarray(returns, np.float64).mean(-1)):
            out[i][name] = _metrics(truth, v)
            if name == "test":  # per policy: what the simulator got wrong, and how long it ran
                out[i]["test_values"] = [round(float(x), 2) for x in v]
                out[i]["test_lengths"] = [round(float(x), 1) for x in lengths[i]]
    return out


# What ends an episode, per task: (name, test on the terminal observation [..., o]); the
# conditions of tasks.<task>_done, split up (docs/EVALUATION.md).
TERMINATION_RULES = {
    "hopper": (("z <= 0.7", lambda o: o[..., 1] <= 0.7),
               ("|angle| >= 0.2", lambda o: jnp.abs(o[..., 2]) >= 0.2),
               ("|q[2:], qd| >= 100", lambda o: jnp.any(jnp.abs(o[..., 2:]) >= 100.0, -1))),
    "walker2d": (("z <= 0.8", lambda o: o[..., 1] <= 0.8),
                 ("z >= 2", lambda o: o[..., 1] >= 2.0),
                 ("|angle| >= 1", lambda o: jnp.abs(o[..., 2]) >= 1.0)),
    "ant": (("z < 0.2", lambda o: _ant_z(o) < 0.2),
            ("z > 1", lambda o: _ant_z(o) > 1.0)),
}  # an ended episode that breaks none was ended by a learned hazard (termination "hazard")


def _ant_z(o):
    """The torso height ``tasks.ant_done`` tests (one physics substep behind)."""
    spec = _LOCO["ant"]
    return o[..., 2] - spec.substep * o[..., spec.vx_idx + 2]


def terminal_states(sims, policies, pool, keys, *, task, n_episodes, horizon):
    """Each lane's simulated episodes, run as ``evaluate.lanes.lane_returns`` runs them
    (``simulate.start_values`` + ``advance_values``, whose frozen state of an ended episode is
    the one it terminated in). -> (terminal obs [L, P, n, o] (the last state where none),
    ended [L, P, n])"""
    n_pol = jax.tree_util.tree_leaves(policies)[0].shape[0]

    def one(sim, key):
        k_start, k_run = jax.random.split(key)
        done_fn, hazard_fn = sim.terminations(task.done_fn)
        roll = advance_values(start_values(pool, n_pol, n_episodes, k_start), policies,
                              sim.dynamics, task.reward_fn, done_fn, k_run,
                              n_steps=horizon, horizon=horizon, gamma=1.0, hazard_fn=hazard_fn)
        return roll.obs, ~roll.alive

    return jax.jit(jax.vmap(one))(sims, keys)


def hazard_check(states, ds) -> dict:
    """How the learned per-step hazard of each lane predicts the logged terminations of a
    Dataset's rows: the summed h(s, a) against the count of done rows, and its mean
    cross-entropy against the base rate's. A diagnosis of the test policies' data (never used
    to select)."""
    from rl2s_jax.model.termination import hazard_prob

    obs, act = jnp.asarray(ds.obs), jnp.asarray(ds.action)
    done = np.asarray(ds.done, np.float64)
    window = states.config.hazard_window
    h = np.asarray(jax.jit(jax.vmap(lambda p, n: hazard_prob(p, n, obs, act, window)))(
        states.hazard, states.norm), np.float64)

    def xent(p):
        p = np.clip(p, 1e-7, 1 - 1e-7)
        return float(-np.mean(done * np.log(p) + (1 - done) * np.log1p(-p)))

    return {"rows": int(done.size), "done": int(done.sum()),
            "predicted": [round(float(x), 1) for x in h.sum(-1)],
            "bce": [round(xent(x), 5) for x in h],
            "base_rate_bce": round(xent(np.full(done.shape, done.mean())), 5)}


def open_loop_check(states, ds, task, *, ks=(1, 10, 50), n_windows: int = 256) -> dict:
    """Each lane's simulator rolled from the test policies' logged states under their LOGGED
    actions for k steps (``simulate.open_loop_returns``), against what the logged episodes
    earned in the same windows: per k, the Kendall tau of the policies' mean k-step returns,
    the spread ratio (std over policies, model / real: below 1 the model compresses the
    policies), the mean relative error, the fraction of windows that end, and the per-policy
    means at the largest k. A diagnosis of the test data (never used to select): if the
    model ranks the policies' windows well here but not in closed loop, the error is in how
    the policies react to the model's states, not in the dynamics under their actions."""
    from rl2s_jax.model.simulator import open_loop_returns

    k_max = max(ks)
    rows, steps, real_r, real_end, obs, act, n_steps = open_loop_inputs(ds, task, k_max,
                                                                        n_windows, seed=7)
    sims = simulator(states, average=False)

    def one(sim, key):
        done_fn, hazard_fn = sim.terminations(task.done_fn)
        r, _, ended = open_loop_returns(sim.dynamics, task.reward_fn, done_fn, obs, act,
                                        n_steps, key, hazard_fn=hazard_fn)
        return r, ended

    n_lanes = int(states.step.shape[0])
    keys = jnp.stack([jax.random.PRNGKey(4000 + i) for i in range(n_lanes)])
    sim_r, sim_end = (np.asarray(x) for x in jax.jit(jax.vmap(one))(sims, keys))
    sim_r = sim_r.reshape(n_lanes, *rows.shape, k_max).astype(np.float64)
    sim_end = sim_end.reshape(n_lanes, *rows.shape, k_max)
    return {"windows_per_policy": n_windows,
            **open_loop_summary(real_r, real_end, steps, sim_r, sim_end, ks)}


def open_loop_inputs(ds, task, k_max: int, n_windows: int, seed: int):
    """The logged windows of every policy (``simulate.open_loop_windows``), what the logged
    episodes earned in them (``logged_window_returns``), and the flat inputs of
    ``open_loop_returns``. -> (rows, steps [P, n], real reward [P, n, k_max], real end [P, n],
    start obs [P * n, o], actions [P * n, k_max, a], steps [P * n])"""
    from rl2s_jax.model.simulator import logged_window_returns, open_loop_windows

    rows, steps = open_loop_windows(ds, k_max, n_windows, seed=seed)
    real_r, real_end = logged_window_returns(ds, rows, steps, k_max, task.reward_fn)
    idx = rows[..., None] + np.minimum(np.arange(k_max), steps[..., None] - 1)
    obs = jnp.asarray(np.asarray(ds.obs)[rows.ravel()])
    act = jnp.asarray(np.asarray(ds.action)[idx.reshape(-1, k_max)])
    return rows, steps, real_r, real_end, obs, act, jnp.asarray(steps.ravel())


def open_loop_summary(real_r, real_end, steps, sim_r, sim_end, ks) -> dict:
    """Per k of ``ks``: the simulators' mean k-step returns per policy against the logged ones.
    real_r [P, n, K] logged rewards, real_end [P, n], steps [P, n] (``logged_window_returns``,
    ``open_loop_windows``); sim_r [L, P, n, K], sim_end [L, P, n, K] of L simulators. -> {k:
    {tau, spread_ratio (std over policies, model / real), relative_error, real_end, model_end:
    lists over L; at the largest k also real_per_policy, model_per_policy}}"""
    from rl2s_jax.evaluate.metrics import kendall_tau

    out = {}
    for k in ks:
        real = real_r[..., :k].sum(-1).mean(-1)  # [P]
        model = sim_r[..., :k].sum(-1).mean(-1)  # [L, P]
        out[str(k)] = {
            "tau": [round(kendall_tau(real, m), 3) for m in model],
            "spread_ratio": [round(float(np.std(m) / np.std(real)), 3) for m in model],
            "relative_error": [round(float(np.mean(np.abs(m - real)) / np.mean(np.abs(real))),
                                     3) for m in model],
            "real_end": round(float((real_end & (steps <= k)).mean()), 4),
            "model_end": [round(float(e[..., :k].any(-1).mean()), 4) for e in sim_end]}
        if k == max(ks):
            out[str(k)]["real_per_policy"] = [round(float(x), 2) for x in real]
            out[str(k)]["model_per_policy"] = [[round(float(x), 2) for x in m] for m in model]
    return out


def visited_error_check(states, test_ds, test, task, *, n_episodes: int, horizon: int,
                        rows_per_policy: int = 2048, train_ds=None) -> dict:
    """Each lane's one-step error against the real dynamics (``oracle.oracle_dynamics``) on the
    states its own closed-loop episodes of the test policies visit
    (``simulate.visited_step_errors``), on logged states of the same policies (a random
    ``rows_per_policy`` of each) and, with ``train_ds``, on logged states of the training
    policies (the model's own data: an error as large there is underfitting, not a shift), in
    units of the data's one-step change std per dim, with the reward difference per step. A
    diagnosis of the test policies (never used to select): an error that grows from the logged
    states to the visited ones is the model taking the policies where it was not fitted; a
    reward bias per step times the episode length is the value error it makes.
    -> {"visited" | "logged" [| "train_logged"]: {"rmse" | "reward_bias" | "reward_abs": [L][P],
    "rmse_per_dim": [L][o] (mean over the policies' squared errors)}, "visited_steps": [L][P]}"""
    from rl2s_jax.evaluate.oracle import oracle_dynamics
    from rl2s_jax.model.simulator import mean_square, step_errors, visited_step_errors

    reference = oracle_dynamics(task)
    policies, pool = test[0], test[1]
    rng = np.random.default_rng(11)

    def rows_of(ds):  # [P, R] obs and actions
        pid = np.asarray(ds.policy_id)
        idx = np.stack([rng.choice(np.flatnonzero(pid == p), rows_per_policy)
                        for p in range(ds.n_policies)])
        return jnp.asarray(np.asarray(ds.obs)[idx]), jnp.asarray(np.asarray(ds.action)[idx])

    logged_sets = {"logged": rows_of(test_ds)}
    if train_ds is not None:
        logged_sets["train_logged"] = rows_of(train_ds)

    def on_rows(sim, obs, act, key):
        k_model, k_ref = jax.random.split(key)
        nxt, ref = sim.dynamics(obs, act, k_model), reference(obs, act, k_ref)
        z, dr = step_errors(nxt, ref, obs, act, task.reward_fn, sim.norm.delta_std)  # [P, R]
        return {"rmse": jnp.sqrt(mean_square(z, sim.norm.delta_std).mean(-1)),
                "reward_bias": dr.mean(-1), "reward_abs": jnp.abs(dr).mean(-1),
                "rmse_per_dim": jnp.sqrt((z ** 2).mean((0, 1)))}

    def visited_of(sim, key):
        done_fn, hazard_fn = sim.terminations(task.done_fn)
        visited = visited_step_errors(policies, sim.dynamics, reference, task.reward_fn,
                                      done_fn, pool, key, n_episodes=n_episodes,
                                      horizon=horizon, scale=sim.norm.delta_std,
                                      hazard_fn=hazard_fn)
        steps = visited["steps"]
        per_dim = jnp.sqrt(jnp.sum(visited["rmse_per_dim"] ** 2 * steps[:, None], 0)
                           / jnp.maximum(steps.sum(), 1.0))  # over every visited step
        return {**visited, "rmse_per_dim": per_dim}

    # one compiled program per piece: XLA's CPU runtime hung (every thread in a futex wait)
    # running the visited rollout and both logged sets as one program
    sims = simulator(states, average=False)
    n_lanes = int(states.step.shape[0])
    keys = jnp.stack([jax.random.PRNGKey(5000 + i) for i in range(n_lanes)])
    res = {"visited": jax.block_until_ready(jax.jit(jax.vmap(visited_of))(sims, keys))}
    for i, (name, (obs, act)) in enumerate(logged_sets.items()):
        lane_keys = jax.vmap(lambda k, i=i: jax.random.fold_in(k, i + 1))(keys)
        res[name] = jax.block_until_ready(jax.jit(jax.vmap(
            lambda sim, k, o=obs, a=act: on_rows(sim, o, a, k)))(sims, lane_keys))
    rnd = lambda x: np.round(np.asarray(x, np.float64), 4).tolist()
    keep = ("rmse", "reward_bias", "reward_abs", "rmse_per_dim")
    return {**{side: {k: rnd(v[k]) for k in keep} for side, v in res.items()},
            "visited_steps": rnd(res["visited"]["steps"]), "rows_per_policy": rows_per_policy,
            "episodes_per_policy": n_episodes}


def termination_causes(task_name: str, terminal, ended) -> dict | None:
    """{rule: share of the ended episodes whose terminal state breaks it (rules can overlap)},
    plus "ended": share of episodes that ended; None for a task without rules."""
    rules = TERMINATION_RULES.get(task_name)
    if rules is None:
        return None
    ended = np.asarray(ended, bool)
    n = max(int(ended.sum()), 1)
    out = {name: float(np.asarray(rule(jnp.asarray(terminal)))[ended].sum() / n)
           for name, rule in rules}
    return {"ended": float(ended.mean()), **out}


_select = select_point  # the rule lives in train/lanes.py; tests call it by this name


def tau_swing(points: list[dict], from_step: int = 0) -> float | None:
    """Mean |change of test Kendall tau| between consecutive evaluations of one lane, over the
    evaluations at steps >= from_step (the adversarial phase of a pre-trained run); None with
    fewer than two finite points. How much a lane's ranking moves from one checkpoint to the
    next: what a moving average of the weights should damp."""
    taus = [p["test"]["kendall_tau"] for p in points
            if p["step"] >= from_step and p["test"] is not None]
    taus = np.asarray(taus, np.float64)
    taus = taus[np.isfinite(taus)]
    return float(np.mean(np.abs(np.diff(taus)))) if taus.size > 1 else None


def summarize_rows(results: list[dict]) -> dict:
    """{row: {"final" | "selected": {metric: (mean, std, n)}, "selected_steps": [...],
    "tau_swing": (mean, std, n)}} over the seeds of every variant result; the swing is taken
    from the first evaluation at or after the pre-training steps (config.pretrain_steps of an
    adversarial variant, else from the start)."""
    table = {}
    for res in results:
        cfg = res.get("config") or {}
        adversarial = cfg.get("method") in ("rl2s", "gail")
        from_step = int(cfg.get("pretrain_steps") or 0) if adversarial else 0
        for row, lanes in res["curves"].items():
            finals, chosen, steps, swings, valids = [], [], [], [], []
            for points in lanes.values():
                sw = tau_swing(points, from_step)
                if sw is not None:
                    swings.append(sw)
                if points and points[-1]["test"] is not None:
                    finals.append(points[-1]["test"])
                if points and points[-1].get("validation") is not None:
                    valids.append(points[-1]["validation"])
                sel = _select(points)
                if sel is not None:
                    chosen.append(sel["test"])
                    steps.append(sel["step"])
            entry = {}
            for what, rs in (("final", finals), ("selected", chosen), ("validation", valids)):
                entry[what] = {}
                for k in METRICS:
                    v = np.asarray([r[k] for r in rs], np.float64)
                    entry[what][k] = (float(v.mean()) if v.size else None,
                                      float(v.std(ddof=1)) if v.size > 1 else None, int(v.size))
            entry["selected_steps"] = steps
            v = np.asarray(swings, np.float64)
            entry["tau_swing"] = (float(v.mean()) if v.size else None,
                                  float(v.std(ddof=1)) if v.size > 1 else None, int(v.size))
            entry["seeds"] = len(lanes)
            table[row] = entry
    return table


def markdown(table: dict, task: str) -> str:
    cols = ("kendall_tau", "ndcg@1", "avd", "mvd")
    vcols = ("kendall_tau", "avd") if any(e.get("validation", {}).get("avd", (None,))[0]
                                          is not None for e in table.values()) else ()
    head = (f"| {task} | " + " | ".join(f"{c} final" for c in cols) + " | "
            + " | ".join(f"{c} selected" for c in cols) + " | tau swing | selected steps |"
            + "".join(f" validation {c} |" for c in vcols))
    lines = [head, "|" + "---|" * (2 * len(cols) + 3 + len(vcols))]
    fmt = lambda c: "n/a" if c[0] is None else (f"{c[0]:.3g}" + ("" if c[1] is None
                                                                  else f" ± {c[1]:.2g}"))
    for row in [r for r in ROWS if r in table] + sorted(set(table) - set(ROWS)):
        e = table[row]
        cells = ([fmt(e["final"][c]) for c in cols] + [fmt(e["selected"][c]) for c in cols]
                 + [fmt(e.get("tau_swing", (None, None, 0)))])
        lines.append(f"| {row} | " + " | ".join(cells) + f" | {e['selected_steps']} |"
                     + "".join(f" {fmt(e['validation'][c])} |" for c in vcols))
    return "\n".join(lines)


def write_summary(out: str, task: str, paths: list[str]) -> str:
    results = []
    for p in paths:
        with open(p) as f:
            results.append(json.load(f))
    table = summarize_rows(results)
    md = markdown(table, task)
    with open(os.path.join(out, f"ablation_{task}.json"), "w") as f:
        json.dump({"task": task, "rows": table, "sources": paths,
                   "runs": [{k: r[k] for k in ("variant", "hardware", "jax_version", "command",
                                               "timings", "complete")} for r in results]},
                  f, indent=1)
    with open(os.path.join(out, f"ablation_{task}.md"), "w") as f:
        f.write(md + "\n")
    return md


def split_validation(train_ds, n: int):
    """Leave-policies-out validation inside the training zoo: ``n`` training policies spread
    over its value ranking (the middle of n equal slices) are held out whole, the model is
    fitted on the rest, and the held-out ones are ranked like test policies. A choice made on
    them (e.g. the termination) never sees the test policies, and unlike the training
    policies' held-out episodes it measures generalisation to policies the model has not seen.
    -> (fit Dataset, validation Dataset)"""
    p = train_ds.n_policies
    if not 2 <= n <= p - 2:
        raise SystemExit(f"validation-policies: expected 2 ... {p - 2} (the training split "
                         f"has {p} policies), got {n}")
    order = np.argsort(np.asarray(train_ds.value_discounted, np.float64))
    held = sorted(int(order[int((i + 0.5) * p / n)]) for i in range(n))
    rest = [i for i in range(p) if i not in held]
    zoo_ids = list(train_ds.meta["source"]["zoo_ids"])
    out = []
    for ids in (rest, held):
        part = train_ds.select_policies(ids)
        part.meta["source"] = {**part.meta["source"], "zoo_ids": [int(zoo_ids[i]) for i in ids]}
        out.append(part)
    return tuple(out)


def parse_variant(spec: str) -> tuple[str, dict]:
    """'bc' or 'bc:multistep_steps=5+multistep_weight=0.5' -> (base variant, its own config
    overrides); the row is named by the whole spec."""
    base, _, extra = spec.partition(":")
    if base not in VARIANTS:
        raise SystemExit(f"variants: expected names from {', '.join(VARIANTS)} (optionally "
                         f"':key=value+key=value'), got {spec!r}")
    try:
        own = parse_overrides([kv for kv in extra.split("+") if kv]) if extra else {}
    except (ValueError, SystemExit) as e:
        raise SystemExit(f"variants: {spec!r}: {e}") from None
    return base, own


def check_variants(task: str, text: str, parse=parse_variant) -> list[str]:
    """The comma-separated variant specs of ``text``, each parsed by ``parse`` and its config
    validated for ``task``: bad input stops here (SystemExit naming the spec), before any
    work."""
    variants = [v for v in text.split(",") if v]
    if not variants:
        raise SystemExit(f"variants: expected names from {', '.join(VARIANTS)}")
    for v in variants:
        base, own = parse(v)
        try:
            TrainConfig.from_dict({"task": task, "method": VARIANTS[base][0],
                                   **VARIANTS[base][1], **own}).validate()
        except (ValueError, TypeError) as e:
            raise SystemExit(f"variants: {v!r}: {e}") from None
    return variants


def run_variant(variant: str, args, profile: str, sizes: dict, train_ds, test_ds,
                valid_ds=None) -> dict:
    base, own = parse_variant(variant)
    method, model = VARIANTS[base]
    overrides = {**parse_overrides(args.set), **model, **own}  # a legacy variant stays legacy
    if base == "rl2s":
        overrides.setdefault("ema_decay", args.ema_decay)
    cfg = make_config(train_ds, method, profile, overrides=overrides)
    data = make_train_data(train_ds, policies_for(train_ds), cfg)
    test = (policies_for(test_ds), start_pool(test_ds),
            true_values(test_ds, cfg.vd_horizon, cfg.gamma))
    select = (data.policies, heldout_start_pool(train_ds), np.asarray(data.true_value))
    validation = None if valid_ds is None else (
        policies_for(valid_ds), start_pool(valid_ds),
        true_values(valid_ds, cfg.vd_horizon, cfg.gamma))
    rows = {(False, None): variant} | ({(True, None): f"{variant}+ema"} if cfg.ema_decay
                                       else {})
    rollouts = parse_rollouts(args.rollouts)
    if cfg.termination not in LEARNED and any(len(r) > 2 and r[2] in LEARNED
                                              for r in rollouts):
        raise SystemExit(f"rollouts: a learned termination needs a variant trained with one "
                         f"({variant!r} has termination {cfg.termination!r}; add "
                         f"':termination=both')")
    rows |= {(False, r): rollout_row(variant, r) for r in rollouts}
    seeds = list(range(sizes["seeds"]))
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", variant)  # a file name any tool copies back
    path = os.path.join(args.out, f"ablation_{args.task}_{safe}.json")
    res = {"task": args.task, "variant": variant, "config": cfg.to_dict(), "sizes": sizes,
           "hardware": jax.devices()[0].device_kind, "jax_version": jax.__version__,
           "command": " ".join(["python", "experiments/ablation_model.py", *args.argv]),
           "timings": {}, "complete": False,
           "curves": {row: {str(s): [] for s in seeds} for row in rows.values()},
           "heldout_nll": {str(s): [] for s in seeds},
           "test_true_values": [float(x) for x in test[2]],
           "test_true_lengths": [round(float(x), 1) for x in episode_lengths(test_ds)]}
    t0 = time.perf_counter()
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    states = jax.block_until_ready(jax.jit(jax.vmap(lambda k, d: init(k, cfg, d),
                                                    in_axes=(0, None)))(keys, data))
    res["timings"]["init"] = round(time.perf_counter() - t0, 1)
    log(f"[ablation] {variant}: method {method}, {len(seeds)} seeds, E={cfg.ensemble_size}, "
        f"pretrain {cfg.pretrain_steps if cfg.adversarial else '-'}, ema {cfg.ema_decay}; "
        f"init {res['timings']['init']}s")
    compiled, t_train, t_eval = {}, 0.0, 0.0
    n = sizes["eval_every"]
    for _ in range(sizes["steps"] // n):
        t1 = time.perf_counter()
        states, m = jax.block_until_ready(train_lanes(states, data, n, cfg, compiled))
        t_train += time.perf_counter() - t1
        t1 = time.perf_counter()
        step = int(states.step[0])
        for (weights, rollout), row in rows.items():
            for s, r in zip(seeds, evaluate(states, seeds, weights, test=test, select=select,
                                            cfg=cfg, n_episodes=sizes["eval_episodes"],
                                            rollout=rollout, validation=validation),
                            strict=True):
                res["curves"][row][str(s)].append({"step": step, **r,
                                                   "finite": bool(m["finite"][s])})
                t, sl = r["test"] or {}, r["select"] or {}
                f = lambda d, k: "n/a" if k not in d else f"{d[k]:.3f}"
                log(f"  {row:<9} seed {s} step {step:>5}  test tau {f(t, 'kendall_tau')}"
                    f"  nDCG@1 {f(t, 'ndcg@1')}  AVD {f(t, 'avd')}  MVD {f(t, 'mvd')}  | "
                    f"select tau {f(sl, 'kendall_tau')}  AVD {f(sl, 'avd')}"
                    + ("" if validation is None else
                       f"  | validation tau {f(r['validation'] or {}, 'kendall_tau')}  AVD "
                       f"{f(r['validation'] or {}, 'avd')}"))
        if data.n_heldout:
            elite = np.asarray(states.rank) < cfg.n_elites
            nll = np.where(elite, np.asarray(states.heldout_nll), 0).sum(1) / cfg.n_elites
            for s in seeds:
                res["heldout_nll"][str(s)].append([step, float(nll[s])])
        t_eval += time.perf_counter() - t1
        res["timings"].update(train=round(t_train, 1), eval=round(t_eval, 1))
        log(f"[ablation] {variant} step {step}: train {t_train:.1f}s, eval {t_eval:.1f}s")
        _write(path, res)
    if cfg.termination in LEARNED:  # the hazard's calibration on the test policies' rows
        res["hazard_check"] = hazard_check(states, test_ds)
        log(f"[ablation] {variant}: hazard on the test rows {res['hazard_check']}")
    if args.open_loop:
        res["open_loop"] = open_loop_check(states, test_ds, get_task(args.task),
                                           ks=args.open_loop, n_windows=256)
        log(f"[ablation] {variant}: open loop on the test policies' logged actions "
            + "; ".join(f"k={k}: tau {v['tau']} spread {v['spread_ratio']} end "
                        f"{v['real_end']} vs {v['model_end']}"
                        for k, v in res["open_loop"].items() if k != "windows_per_policy"))
    if args.visited_error:
        res["visited_error"] = v = visited_error_check(
            states, test_ds, test, get_task(args.task), n_episodes=args.visited_error,
            horizon=cfg.vd_horizon, train_ds=train_ds)
        mean = lambda d, k: [round(float(np.mean(x)), 4) for x in d[k]]
        log(f"[ablation] {variant}: one-step error against the real dynamics (per seed, mean "
            f"over the test policies): visited states rmse {mean(v['visited'], 'rmse')} "
            f"reward bias {mean(v['visited'], 'reward_bias')} | logged states rmse "
            f"{mean(v['logged'], 'rmse')} reward bias {mean(v['logged'], 'reward_bias')} | "
            f"training policies' logged states rmse {mean(v['train_logged'], 'rmse')}")
    if args.task in TERMINATION_RULES:  # why the simulated episodes end, vs the logged ones
        task = get_task(args.task)
        keys = jnp.stack([jax.random.PRNGKey(3000 + s) for s in seeds])
        terminal, ended = terminal_states(simulator(states, average=False), test[0], test[1],
                                          keys, task=task, n_episodes=sizes["eval_episodes"],
                                          horizon=cfg.vd_horizon)
        done_rows = np.asarray(test_ds.done, bool)
        res["termination"] = {
            "simulated": {str(s): termination_causes(args.task, terminal[i], ended[i])
                          for i, s in enumerate(seeds)},
            "logged": termination_causes(args.task, np.asarray(test_ds.next_obs)[done_rows],
                                         np.ones(int(done_rows.sum()), bool))}
        log(f"[ablation] {variant}: termination causes {res['termination']}")
    res["complete"] = True
    _write(path, res)
    return res


def _write(path: str, res: dict) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(res, f, indent=1)
    os.replace(tmp, path)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    pos = positive_int
    ap.add_argument("--task", choices=task_names())
    ap.add_argument("--variants", default="legacy,bc,rl2s",
                    help=f"comma-separated, from {', '.join(VARIANTS)}, each optionally with "
                    "its own settings: bc:multistep_steps=5+multistep_weight=0.5")
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--seeds", type=pos)
    ap.add_argument("--steps", type=pos)
    ap.add_argument("--eval-every", type=pos)
    ap.add_argument("--eval-episodes", type=pos)
    ap.add_argument("--transitions-per-policy", type=pos)
    ap.add_argument("--value-episodes", type=pos)
    ap.add_argument("--episode-length", type=pos)
    ap.add_argument("--ema-decay", type=float, default=0.99)
    ap.add_argument("--set", action="append", metavar="KEY=VALUE")
    ap.add_argument("--rollouts", metavar="MODE:NOISE[:TERMINATION],...",
                    help="also evaluate every variant with these rollout settings (member mode "
                    "random|mean|fixed : noise scale [: rule|hazard|both]), e.g. "
                    "random:1,mean:0,random:0:rule")
    ap.add_argument("--open-loop", metavar="K,K,...",
                    type=lambda t: tuple(sorted({pos(x) for x in t.split(",") if x})),
                    help="also roll each trained simulator from the test policies' logged "
                    "states under their logged actions for K steps and compare the K-step "
                    "returns per policy (open_loop in the JSON), e.g. 1,10,50")
    ap.add_argument("--visited-error", type=pos, metavar="N",
                    help="also measure each trained simulator's one-step error against the "
                    "real dynamics (the oracle) on the states its own N episodes per test "
                    "policy visit and on logged states (visited_error in the JSON)")
    ap.add_argument("--validation-policies", type=int, metavar="N",
                    help="hold N training policies (spread over their values) out of the "
                    "model's data and rank them as validation policies (a choice made on "
                    "them never sees the test policies); the test rows are then of a model "
                    "fitted on the other training policies")
    ap.add_argument("--out", default="results/ablation")
    ap.add_argument("--data-dir")
    ap.add_argument("--summarize", nargs="+", metavar="DIR",
                    help="only rebuild the table of the ablation JSONs in these directories "
                    "(written into --out)")
    args = ap.parse_args(argv)
    args.argv = argv
    os.makedirs(args.out, exist_ok=True)
    if args.summarize:
        paths = sorted(p for d in args.summarize
                       for p in glob.glob(os.path.join(d, "ablation_*_*.json")))
        if not paths:
            raise SystemExit(f"summarize: no ablation_<task>_<variant>.json in {args.summarize}")
        tasks = {json.load(open(p))["task"] for p in paths}
        for task in sorted(tasks):
            mine = [p for p in paths if json.load(open(p))["task"] == task]
            print(write_summary(args.out, task, mine))
        return 0
    if not args.task:
        raise SystemExit("task: required (or --summarize)")
    parse_rollouts(args.rollouts)  # bad input stops here, before any work
    variants = check_variants(args.task, args.variants)
    if args.validation_policies is not None:  # the zoo's split sizes, before any collection
        from rl2s_jax.zoo.zoo import load_zoo
        n_train = len(load_zoo(args.task).split_ids("train"))
        if not 2 <= args.validation_policies <= n_train - 2:
            raise SystemExit(f"validation-policies: expected 2 ... {n_train - 2} (the "
                             f"training split has {n_train} policies), got "
                             f"{args.validation_policies}")
    backend = jax.default_backend()
    profile = args.profile if args.profile != "auto" else ("gpu" if backend == "gpu" else "cpu")
    profile_data = profile_sizes(profile, args.task)
    # the task's evaluation episodes follow paper.py's (TASK_SIZES: Ant's 256 on the gpu
    # profile, where fewer leave its ranking at the evaluation noise's own ceiling)
    task_sizes = TASK_SIZES.get(profile, {}).get(args.task, {})
    sizes = {**SIZES[profile], **{k: v for k, v in task_sizes.items() if k in SIZES[profile]}}
    for k in sizes:
        if getattr(args, k, None) is not None:
            sizes[k] = getattr(args, k)
    if sizes["steps"] % sizes["eval_every"]:
        raise SystemExit(f"steps: expected a multiple of --eval-every ({sizes['eval_every']})")
    data_sizes = {k: profile_data[k] for k in ("transitions_per_policy", "value_episodes")}
    for k in data_sizes:
        if getattr(args, k, None) is not None:
            data_sizes[k] = getattr(args, k)
    t0 = time.perf_counter()
    datasets, reused = load_or_collect(args.task, data_sizes, args.data_dir or args.out, 0,
                                       args.episode_length, False)
    log(f"[ablation] {args.task} on {jax.devices()[0].device_kind} ({backend}, jax "
        f"{jax.__version__}), profile {profile}, sizes {sizes}, data {data_sizes} "
        f"({'reused' if reused else 'collected'} in {time.perf_counter() - t0:.1f}s)")
    train_ds, valid_ds = datasets["train"], None
    if args.validation_policies is not None:
        train_ds, valid_ds = split_validation(train_ds, args.validation_policies)
        log(f"[ablation] validation policies {valid_ds.meta['policy_names']}; fitting on "
            f"{train_ds.n_policies}")
    for v in variants:
        t1 = time.perf_counter()
        run_variant(v, args, profile, sizes, train_ds, datasets["test"], valid_ds)
        log(f"[ablation] {v}: {time.perf_counter() - t1:.1f}s")
    mine = sorted(glob.glob(os.path.join(args.out, f"ablation_{args.task}_*.json")))
    print(write_summary(args.out, args.task, mine))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
