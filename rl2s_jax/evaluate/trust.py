"""A value interval for every evaluated policy that covers its true value at a stated level
(issue 64), built only from what is known without the truth, calibrated by split conformal
prediction over policies.

Per policy pi (``policy_features``, ``combine_features``):

* the ensemble's disagreement on its value: each elite member alone (``member_mode``
  "fixed" on that member) simulates pi with the same key (common random numbers: same start
  states and draws), ``member_sd`` = the std over the elites of these values; with several
  checkpoints (seeds) also ``seed_sd`` = the std over the checkpoints of their simulated
  values; ``eval_se`` = the simulated value's own Monte-Carlo standard error;
* its support: ``support`` = the ensemble's one-step disagreement u(s, a)
  (``Simulator.disagreement``, the u of the MOPO penalty) averaged over the live steps of
  pi's simulated episodes, in units of its mean over the training data's (s, a) rows. About
  1 where pi's simulated visits look like the data; larger where they leave it.

The difficulty score is fixed before any test policy is seen (``difficulty``):

    sigma(pi) = sqrt(member_sd^2 + seed_sd^2 + eval_se^2) * max(1, support) + floor

floor = FLOOR_FRACTION x the range of the calibration policies' simulated values (never 0).
Calibration policies (true values known; never the test policies): score_i =
|V_sim_i - V_true_i| / sigma_i, q = the ceil((n+1) level)-th smallest of the n scores
(``conformal_quantile``; infinite when n is too small for the level), interval V_sim +-
q sigma. Exchangeable calibration and test policies -> coverage >= level.

The simulator was fitted on its training policies' data, so their errors are optimistic
(smaller than a new policy's) and an interval calibrated on them under-covers. ``calibrate``
prefers held-out calibration policies (validation policies, or ``perturbed_policies`` of the
training ones, measured in the real env and not trained on): when they are enough for a
finite q, only they are used; else every calibration policy is, and the report says
"optimistic": true.

``trusted`` is False where the interval is wide (width over the calibration policies'
true-value range above ``max_width``) or the support is beyond the largest of the
calibration policies.
"""
from __future__ import annotations

import math
from functools import partial
from statistics import NormalDist

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.data.dataset import spread_rows
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.history import logged_history, push_history
from rl2s_jax.model.simulator import (
    Simulator,
    end_key,
    ends_episode,
    simulator_returns,
    start_values,
)
from rl2s_jax.policy.policy import Params, index_params, num_policies, sample_action

DEFAULT_LEVEL = 0.9
FLOOR_FRACTION = 0.02  # sigma's floor, of the calibration policies' simulated-value range
MAX_WIDTH = 0.5  # an interval wider than this x the calibration true-value range: untrusted
SUPPORT_ROWS = 20_000  # training rows that u's unit (its mean on the data) is measured on
SUPPORT_NOTE = ("support: the ensemble's one-step disagreement u(s, a) averaged over the "
                "policy's simulated visits, in units of its mean on the training data (1: "
                "like the data; larger: off it)")


# ----------------------------------------------------------------------------- the math


def check_level(level) -> float:
    """``level`` as a float in (0, 1), or a ValueError naming it."""
    if isinstance(level, bool) or not isinstance(level, int | float) or not 0 < level < 1:
        raise ValueError(f"level: expected a coverage level in (0, 1) such as 0.9, got "
                         f"{level!r}")
    return float(level)


def conformal_quantile(scores, level: float) -> float:
    """Split conformal's quantile: the ceil((n+1) level)-th smallest of n scores [n], inf when
    that rank exceeds n (too few calibration points for this level)."""
    level = check_level(level)
    s = np.sort(np.asarray(scores, np.float64).ravel())
    if s.size == 0 or not np.all(np.isfinite(s)):
        raise ValueError(f"scores: expected finite calibration scores, got {s.size} with "
                         f"{int((~np.isfinite(s)).sum())} non-finite")
    k = math.ceil((s.size + 1) * level)
    return float(s[k - 1]) if k <= s.size else math.inf


def min_calibration(level: float) -> int:
    """The fewest calibration policies with a finite quantile at ``level``."""
    level = check_level(level)
    return next(n for n in range(1, 10**7) if math.ceil((n + 1) * level) <= n)


def difficulty(member_sd, seed_sd, eval_se, support, floor: float) -> np.ndarray:
    """sigma(pi) [P]: the value spread (member, seed, Monte-Carlo, in value units) inflated by
    the support beyond the data's (max(1, support)), plus ``floor`` > 0."""
    if not floor > 0:
        raise ValueError(f"floor: expected > 0, got {floor!r}")
    spread = np.sqrt(np.square(member_sd) + np.square(seed_sd) + np.square(eval_se))
    return spread * np.maximum(1.0, np.asarray(support, np.float64)) + floor


def sigma_floor(cal_sim_value) -> float:
    """FLOOR_FRACTION x the calibration policies' simulated-value range (1e-6 if constant)."""
    v = np.asarray(cal_sim_value, np.float64)
    return FLOOR_FRACTION * float(max(np.ptp(v), 1e-6 / FLOOR_FRACTION))


def interval_stats(lo, hi, truth) -> dict:
    """{"coverage": share of truth [P] in [lo, hi], "mean_width", "width_over_range" (mean
    width over the range of the true values; None for one value)}."""
    lo, hi, truth = (np.asarray(x, np.float64) for x in (lo, hi, truth))
    width = float(np.mean(hi - lo))
    rng = float(np.ptp(truth))
    return {"coverage": float(np.mean((truth >= lo) & (truth <= hi))), "mean_width": width,
            "width_over_range": width / rng if rng > 0 else None}


def spread_interval(sim_value, spread, truth, level: float, target: float | None) -> dict:
    """The plain spread interval V_sim +- z spread (z: the normal quantile of ``level``) with
    ``interval_stats``, and "scaled_mean_width": the mean width once its half-width factor is
    chosen WITH the truth to reach coverage ``target`` (the comparison for a calibrated
    interval of that coverage; None without a target)."""
    z = NormalDist().inv_cdf(0.5 + check_level(level) / 2)
    v, s, t = (np.asarray(x, np.float64) for x in (sim_value, spread, truth))
    out = interval_stats(v - z * s, v + z * s, t)
    out["z"] = z
    out["scaled_mean_width"] = None
    if target is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.where(s > 0, np.abs(v - t) / s, np.where(v == t, 0.0, np.inf))
        k = np.sort(need)[max(math.ceil(target * need.size) - 1, 0)]
        out["scaled_mean_width"] = float(np.mean(2 * k * s)) if np.isfinite(k) else math.inf
    return out


# ----------------------------------------------------------------------------- calibration

def calibrate(features: dict, truth, kinds, level: float = DEFAULT_LEVEL) -> dict:
    """The calibration of ``intervals`` from policies whose truth is known (never the test
    policies). features: ``combine_features`` of them; truth [n]; kinds [n]: "train" (the
    simulator's own training policies: optimistic errors) or "heldout". Held-out policies
    only when there are ``min_calibration(level)`` of them, else all (then "optimistic").
    -> {"level", "q", "floor", "n", "n_heldout", "n_train", "used", "optimistic",
    "value_range", "max_support"}."""
    level = check_level(level)
    truth = np.asarray(truth, np.float64)
    kinds = np.asarray(list(kinds))
    v = np.asarray(features["sim_value"], np.float64)
    if truth.shape != v.shape or kinds.shape != v.shape:
        raise ValueError(f"truth / kinds: expected shape {v.shape} (the calibration policies'),"
                         f" got {truth.shape} / {kinds.shape}")
    bad = set(kinds.tolist()) - {"train", "heldout"}
    if bad:
        raise ValueError(f"kinds: expected 'train' or 'heldout', got {sorted(bad)}")
    if not np.all(np.isfinite(truth)):
        raise ValueError("truth: the calibration policies need finite true values")
    heldout = kinds == "heldout"
    only_heldout = heldout.sum() >= min_calibration(level)
    use = heldout if only_heldout else np.ones_like(heldout)
    floor = sigma_floor(v[use])
    sigma = _sigma(features, floor)
    scores = np.abs(v - truth) / sigma
    return {"level": level, "q": conformal_quantile(scores[use], level), "floor": floor,
            "n": int(use.sum()), "n_heldout": int(heldout.sum()),
            "n_train": int((~heldout).sum()), "used": "heldout" if only_heldout else "all",
            "optimistic": bool((use & ~heldout).any()),
            "value_range": float(np.ptp(truth[use])),
            "max_support": float(np.max(np.asarray(features["support"])[use]))}


def _sigma(features: dict, floor: float) -> np.ndarray:
    return difficulty(features["member_sd"], features["seed_sd"], features["eval_se"],
                      features["support"], floor)


def intervals(features: dict, cal: dict, *, max_width: float = MAX_WIDTH) -> dict:
    """Each policy's interval and flag from ``calibrate``'s ``cal``.
    -> {"lo", "hi", "sigma", "trusted" (lists [P]), "why" ([P] reasons, "" when trusted)}."""
    v = np.asarray(features["sim_value"], np.float64)
    sigma = _sigma(features, cal["floor"])
    half = cal["q"] * sigma
    lo, hi = v - half, v + half
    support = np.asarray(features["support"], np.float64)
    why = []
    for w, s in zip(hi - lo, support, strict=True):
        r = []
        if not np.isfinite(w) or w > max_width * max(cal["value_range"], 1e-12):
            r.append("wide")
        if s > cal["max_support"]:
            r.append("off support")
        why.append(", ".join(r))
    return {"lo": lo.tolist(), "hi": hi.tolist(), "sigma": sigma.tolist(),
            "trusted": [not r for r in why], "why": why}


def trust_report(features: dict, cal: dict, names, truth=None) -> dict:
    """The "trust" block of an evaluation: the calibration, every policy's interval and flag,
    and where ``truth`` [P] is given the measured coverage (``interval_stats``), the plain
    spread interval's ("spread_interval"), and whether the largest-error policy is flagged."""
    iv = intervals(features, cal)
    spread = np.sqrt(np.square(features["member_sd"]) + np.square(features["seed_sd"]))
    out = {"level": cal["level"], "calibration": cal, "support_measure": SUPPORT_NOTE,
           "policies": [
               {"name": str(n), "sim_value": float(v), "interval": [lo, hi], "trusted": t,
                "why": w, "sigma": s, "support": float(u), "member_sd": float(m),
                "seed_sd": float(d)}
               for n, v, lo, hi, t, w, s, u, m, d in zip(
                   names, features["sim_value"], iv["lo"], iv["hi"], iv["trusted"], iv["why"],
                   iv["sigma"], features["support"], features["member_sd"],
                   features["seed_sd"], strict=True)]}
    if truth is None:
        return out
    truth = np.asarray(truth, np.float64)
    out.update(interval_stats(iv["lo"], iv["hi"], truth))
    out["spread_interval"] = dict(
        spread_interval(features["sim_value"], spread, truth, cal["level"], out["coverage"]),
        what="seed and member spread" if np.any(features["seed_sd"]) else "member spread")
    worst = int(np.argmax(np.abs(np.asarray(features["sim_value"]) - truth)))
    out["worst"] = {"name": str(names[worst]), "flagged": not iv["trusted"][worst]}
    return out


def format_trust(t: dict) -> str:
    """The lines a command prints under its table about the intervals."""
    c = t["calibration"]
    lines = [f"{t['level']:.0%} value intervals, split conformal over {c['n']} calibration "
             f"policies ({c['n_heldout']} held out, {c['n_train']} training; used: {c['used']}"
             f"{', OPTIMISTIC: training policies included' if c['optimistic'] else ''}), "
             f"q {c['q']:.3g}"]
    if "coverage" in t:
        si = t["spread_interval"]
        wor = t["width_over_range"]
        lines.append(f"coverage {t['coverage']:.2f}, mean width {t['mean_width']:.3g}"
                     f" (width/range {'n/a' if wor is None else f'{wor:.3f}'}); plain "
                     f"{si['what']} interval (+-{si['z']:.2f} sd): coverage "
                     f"{si['coverage']:.2f}, mean width {si['mean_width']:.3g}, scaled to the "
                     f"same coverage {si['scaled_mean_width']:.3g}; largest error: "
                     f"{t['worst']['name']} "
                     f"({'flagged' if t['worst']['flagged'] else 'NOT flagged'})")
    untrusted = [f"{p['name']} ({p['why']})" for p in t["policies"] if not p["trusted"]]
    lines.append(f"untrusted: {', '.join(untrusted) if untrusted else 'none'}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- perturbed policies

def perturbed_policies(params: Params, key: jax.Array, n: int, *, noise: float = 0.1
                       ) -> tuple[Params, list[dict]]:
    """``n`` new policies made from stacked ``params`` [P >= 1, ...]: each interpolates two
    of them, theta = (1 - alpha) theta_i + alpha theta_j (i, j drawn, alpha ~ U(0, 1)), plus
    Gaussian noise of std ``noise`` x each leaf's std over the P policies (the observation
    normaliser is interpolated, never perturbed). Held-out calibration points near the
    training policies. -> (stacked [n, ...], n origins {"i", "j", "alpha", "noise"})."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n: expected an int >= 1, got {n!r}")
    if not noise >= 0:
        raise ValueError(f"noise: expected >= 0, got {noise!r}")
    P = num_policies(params)
    k_pair, k_alpha, k_noise = jax.random.split(key, 3)
    pair = np.asarray(jax.random.randint(k_pair, (n, 2), 0, P))
    alpha = np.asarray(jax.random.uniform(k_alpha, (n,)), np.float32)
    a, b = index_params(params, pair[:, 0]), index_params(params, pair[:, 1])
    leaves, tree = jax.tree_util.tree_flatten_with_path(params)
    keys = jax.random.split(k_noise, len(leaves))

    def mix(path, x, y, full, k):
        w = alpha.reshape((n,) + (1,) * (x.ndim - 1))
        out = (1 - w) * x + w * y
        if "obs_" in jax.tree_util.keystr(path) or noise == 0:
            return out
        sd = jnp.std(full, 0) if P > 1 else jnp.std(full)
        return out + noise * sd * jax.random.normal(k, out.shape, out.dtype)

    mixed = [mix(p, x, y, f, k) for (p, f), x, y, k in zip(
        leaves, jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), keys, strict=True)]
    origins = [{"i": int(i), "j": int(j), "alpha": float(al), "noise": float(noise)}
               for (i, j), al in zip(pair, alpha, strict=True)]
    return jax.tree_util.tree_unflatten(tree, mixed), origins


# ----------------------------------------------------------------------------- rollouts

@partial(jax.jit, static_argnames=("n_episodes", "horizon", "gamma"))
def _returns(sim: Simulator, policies, pool, key, *, n_episodes, horizon, gamma):
    return simulator_returns(sim, None, policies, pool, key, n_episodes=n_episodes,
                             horizon=horizon, gamma=gamma)


@partial(jax.jit, static_argnames=("n_episodes", "horizon"))
def visited_disagreement(sim: Simulator, policies: Params, pool: jax.Array, key: jax.Array,
                         *, n_episodes: int, horizon: int) -> jax.Array:
    """The ensemble's disagreement u(s, a) averaged over the live steps of each policy's
    simulated episodes (as ``simulated_returns`` runs them: same starts and termination).
    policies [P, ...], pool [S, o] -> [P]."""
    return returns_and_support(sim, policies, pool, key, n_episodes=n_episodes,
                               horizon=horizon, gamma=1.0)[1]


def returns_and_support(sim: Simulator, policies: Params, pool: jax.Array, key: jax.Array,
                        *, n_episodes: int, horizon: int, gamma: float):
    """One rollout of the ensemble: each episode's discounted return (``simulator_returns``'
    episodes, the same key: the same draws) and u averaged over each policy's live steps.
    -> (returns [P, n], u [P])"""
    task = sim.task_fns()
    done_fn, hazard_fn = sim.terminations(task.done_fn)
    n_pol = num_policies(policies)
    k_start, k_run = jax.random.split(key)
    roll = start_values(pool, n_pol, n_episodes, k_start, sim.new_history)
    act = jax.vmap(lambda p, o, k: sample_action(p, o, k)[0])

    def step(carry, xs):
        obs, hist, alive, ret, total, count = carry
        key, discount = xs
        k_act, k_dyn = jax.random.split(key)
        action = act(policies, obs, jax.random.split(k_act, n_pol))
        k_dyn, k_end = end_key(k_dyn, hazard_fn)
        nxt, u = sim.step(obs, action, k_dyn, hist)
        reward = task.reward_fn(obs, action, nxt)
        hist = None if hist is None else push_history(hist, obs, action)
        w = alive.astype(jnp.float32)
        done = ends_episode(obs, action, nxt, k_end, done_fn, hazard_fn)
        return (jnp.where(alive[..., None], nxt, obs), hist, alive & ~done,
                ret + jnp.where(alive, discount * reward, 0.0), total + w * u, count + w), None

    zeros = jnp.zeros(roll.alive.shape, jnp.float32)
    discounts = jnp.asarray(gamma, jnp.float32) ** jnp.arange(horizon, dtype=jnp.float32)
    carry = (roll.obs, roll.hist, roll.alive, zeros, zeros, zeros)
    (_, _, _, ret, total, count), _ = jax.lax.scan(
        step, carry, (jax.random.split(k_run, horizon), discounts))
    return ret, total.sum(1) / jnp.maximum(count.sum(1), 1.0)


def _data_rows(sim: Simulator, ds, max_rows: int):
    """(obs [R, O], action [R, A], the rows' logged History or None) of up to ``max_rows``
    evenly spread rows of ``ds``, as ``sim`` (one simulator or lanes stacked) reads them."""
    rows = spread_rows(ds.n_transitions, max_rows)
    obs, action = (jnp.asarray(np.asarray(x, np.float32)[rows]) for x in (ds.obs, ds.action))
    hist = None if sim.markov else logged_history(
        ds, rows, obs_history=sim.obs_history, action_history=sim.action_history,
        time_inputs=sim.time_inputs, episode_length=sim.episode_length)
    return obs, action, hist


def data_disagreement(sim: Simulator, ds, max_rows: int = SUPPORT_ROWS) -> float:
    """The mean of u(s, a) over (up to ``max_rows``, evenly spread) rows of ``ds``."""
    obs, action, hist = _data_rows(sim, ds, max_rows)
    return float(jnp.mean(jax.jit(Simulator.disagreement)(sim, obs, action, hist)))


def elites(sim: Simulator) -> np.ndarray:
    """The elite members' indices."""
    return np.flatnonzero(np.asarray(dyn.elite_mask(sim.rank, sim.n_elites, sim.n_members)))


def policy_features(sim: Simulator, pool: jax.Array, policies: Params, *, key: jax.Array,
                    n_episodes: int, horizon: int, gamma: float, u_unit: float | None) -> dict:
    """What one simulator knows of each policy without its truth. pool [S, o]: start states;
    u_unit: ``data_disagreement`` on the training data (None or 0: one elite, no support
    measure, support 1). -> {"sim_value" [P], "eval_se" [P], "member_values" [E_elite, P],
    "support" [P]} (NumPy)."""
    ret, _ = _returns(sim, policies, pool, key, n_episodes=n_episodes, horizon=horizon,
                      gamma=gamma)
    ret = np.asarray(ret, np.float64)
    members = []
    rank = np.arange(sim.n_members) if sim.rank is None else np.asarray(sim.rank)
    for e in elites(sim):  # each elite alone, the same key: only the model differs
        alone = sim.replace(member_mode="fixed", rank=jnp.asarray(
            np.where(np.arange(rank.size) == e, -1, rank), jnp.int32))
        members.append(np.asarray(_returns(alone, policies, pool, key, n_episodes=n_episodes,
                                           horizon=horizon, gamma=gamma)[0]).mean(1))
    if u_unit:
        support = np.asarray(visited_disagreement(sim, policies, pool, key,
                                                  n_episodes=n_episodes, horizon=horizon),
                             np.float64) / u_unit
    else:
        support = np.ones(ret.shape[0])
    se = ret.std(1, ddof=1) / np.sqrt(ret.shape[1]) if ret.shape[1] > 1 else np.zeros(
        ret.shape[0])
    return {"sim_value": ret.mean(1), "eval_se": se, "member_values": np.asarray(members),
            "support": support}


def combine_features(per_sim: list[dict]) -> dict:
    """``policy_features`` of S >= 1 simulators (seeds) of one data set, combined:
    sim_value and support their means, member_sd the root mean over simulators of the
    elites' variance (0 for one elite), seed_sd the std over simulators (0 for one),
    eval_se the root mean square over S divided by sqrt(S). -> dict of [P]."""
    if not per_sim:
        raise ValueError("per_sim: expected the features of 1 or more simulators")
    v = np.stack([f["sim_value"] for f in per_sim])  # [S, P]
    var = np.stack([f["member_values"].var(0, ddof=1) if f["member_values"].shape[0] > 1
                    else np.zeros(v.shape[1]) for f in per_sim])
    se = np.stack([f["eval_se"] for f in per_sim])
    return {"sim_value": v.mean(0), "member_sd": np.sqrt(var.mean(0)),
            "seed_sd": v.std(0, ddof=1) if v.shape[0] > 1 else np.zeros(v.shape[1]),
            "eval_se": np.sqrt(np.mean(se ** 2, 0) / v.shape[0]),
            "support": np.stack([f["support"] for f in per_sim]).mean(0)}


# ----------------------------------------------------------------------------- lanes (protocol)

def _member_values(sim: Simulator, policies, pool, key, **roll) -> jax.Array:
    """Each elite alone (``member_mode`` "fixed" on it), the same key: values [n_elites, P];
    [0, P] for a simulator without ranked members."""
    if sim.rank is None or sim.n_members < 2 or (sim.n_elites or sim.n_members) < 2:
        return jnp.zeros((0, num_policies(policies)), jnp.float32)
    n_el = min(sim.n_elites or sim.n_members, sim.n_members)
    best = jnp.nonzero(sim.rank < n_el, size=n_el)[0]  # the elites, as ``elites`` lists them
    members = jnp.arange(sim.n_members)

    def alone(e):
        rank = jnp.where(members == e, -1, sim.rank).astype(jnp.int32)
        ret, _ = simulator_returns(sim.replace(member_mode="fixed", rank=rank), None,
                                   policies, pool, key, **roll)
        return ret.mean(-1)
    return jax.vmap(alone)(best)


@partial(jax.jit, static_argnames=("n_episodes", "horizon", "gamma", "member_episodes"))
def lane_feature_arrays(sims: Simulator, policies: Params, pool: jax.Array, keys: jax.Array,
                        *, n_episodes: int, horizon: int, gamma: float,
                        member_episodes: int | None = None):
    """``policy_features``' rollouts for every lane of ``sims`` (a Simulator with a leading
    lane axis L) in one program: one rollout of the ensemble gives each lane's returns
    [L, P, n] and the disagreement along its simulated visits [L, P] (raw, not in data
    units; ``returns_and_support``), and the elites alone, vmapped over them, their values
    [L, n_elites, P] (0 elites without ranked members) from ``member_episodes`` episodes
    each (None: n; common random numbers make few enough for their spread). keys [L, 2];
    pool [S, o]."""
    roll = dict(n_episodes=n_episodes, horizon=horizon, gamma=gamma)
    members = dict(roll, n_episodes=member_episodes or n_episodes)

    def one(sim, key):
        ret, u = returns_and_support(sim, policies, pool, key, **roll)
        return ret, _member_values(sim, policies, pool, key, **members), u
    return jax.vmap(one)(sims, keys)


def lane_data_disagreement(sims: Simulator, ds, max_rows: int = SUPPORT_ROWS) -> np.ndarray:
    """``data_disagreement`` of every lane of ``sims`` [L] on the rows of ``ds`` (u's unit)."""
    obs, action, hist = _data_rows(sims, ds, max_rows)
    u = jax.jit(jax.vmap(Simulator.disagreement, in_axes=(0, None, None, None)))(
        sims, obs, action, hist)
    return np.asarray(jnp.mean(u, -1), np.float64)


def lane_features(sims: Simulator, policies: Params, pool: jax.Array, keys: jax.Array,
                  u_units, **roll) -> list[dict]:
    """``policy_features`` of every lane (``lane_feature_arrays``), u in units of
    ``u_units`` [L] (each lane's ``lane_data_disagreement``; support 1 where a lane has fewer
    than 2 elites). -> L dicts as ``policy_features`` returns."""
    ret, members, u = (np.asarray(x, np.float64) for x in lane_feature_arrays(
        sims, policies, pool, keys, **roll))
    out = []
    for i in range(ret.shape[0]):
        n = ret.shape[2]
        se = ret[i].std(1, ddof=1) / np.sqrt(n) if n > 1 else np.zeros(ret.shape[1])
        ok = members.shape[1] > 1 and u_units[i] > 0
        out.append({"sim_value": ret[i].mean(1), "eval_se": se, "member_values": members[i],
                    "support": u[i] / u_units[i] if ok else np.ones(ret.shape[1])})
    return out


# ----------------------------------------------------------------------------- JSON

def json_safe(x):
    """``x`` (dicts, lists, NumPy) with every non-finite float as None: JSON without the
    non-standard Infinity / NaN. Where an infinity means something (an unbounded interval,
    an infinite quantile) the caller records a flag beside it."""
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple | np.ndarray):
        return [json_safe(v) for v in (x.tolist() if isinstance(x, np.ndarray) else x)]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def interval_from_json(pair) -> tuple[float, float]:
    """An interval as ``json_safe`` wrote it ([lo, hi], None for an unbounded end) -> (lo,
    hi) floats, -inf / +inf for the unbounded ends."""
    if not isinstance(pair, list | tuple) or len(pair) != 2:
        raise ValueError(f"interval: expected [lo, hi] (None for an unbounded end), got "
                         f"{pair!r}")
    lo, hi = pair
    return (-math.inf if lo is None else float(lo)), (math.inf if hi is None else float(hi))


# ----------------------------------------------------------------------------- the Python API

def simulated_values_with_intervals(sims, policies: Params, start_pool: jax.Array,
                                    key: jax.Array, *, calibration: tuple, n_episodes: int,
                                    horizon: int, gamma: float, level: float = DEFAULT_LEVEL,
                                    data=None, calibration_kind: str = "heldout") -> dict:
    """``simulated_values`` with each policy's conformal interval for its true value at
    ``level`` (the module docstring's method).

    sims: a ``Simulator`` or a list of them (seeds of one data set: their mean value, and
    their spread joins the difficulty); policies: stacked [P, ...]; start_pool [S, o];
    calibration: (stacked params [n, ...], true discounted values [n] over ``horizon`` at
    ``gamma``) of policies whose truth is known -- never the evaluated ones;
    calibration_kind "heldout" (the simulators never saw their data) or "train" (their own
    training policies: optimistic); data: the training Dataset, u's unit for the support
    (None: support 1). Every policy runs with ``key`` (common random numbers).
    -> {"value" [P], "lo" [P], "hi" [P], "trusted" [P] bool, "why" [P], "sigma" [P],
    "support" [P], "calibration": ``calibrate``'s dict} (NumPy; lo / hi infinite when n is
    below ``min_calibration(level)``)."""
    sims = list(sims) if isinstance(sims, list | tuple) else [sims]
    if not sims or not all(isinstance(s, Simulator) for s in sims):
        raise ValueError(f"sims: expected a Simulator or a non-empty list of them, got "
                         f"{type(sims[0]).__name__ if sims else 'an empty list'}")
    if not isinstance(calibration, tuple) or len(calibration) != 2:
        raise ValueError("calibration: expected (stacked policy params [n], true values [n])")
    cal_params, cal_truth = calibration
    cal_truth = np.asarray(cal_truth, np.float64).ravel()
    if num_policies(cal_params) != cal_truth.size:
        raise ValueError(f"calibration: {num_policies(cal_params)} policies but "
                         f"{cal_truth.size} true values")
    if calibration_kind not in ("heldout", "train"):
        raise ValueError(f"calibration_kind: expected 'heldout' or 'train', got "
                         f"{calibration_kind!r}")
    level = check_level(level)
    kw = dict(key=key, n_episodes=n_episodes, horizon=horizon, gamma=gamma)
    units = [data_disagreement(s, data) if data is not None and elites(s).size > 1 else None
             for s in sims]

    def features(params):
        return combine_features([policy_features(s, start_pool, params, u_unit=u, **kw)
                                 for s, u in zip(sims, units, strict=True)])

    cal = calibrate(features(cal_params), cal_truth, [calibration_kind] * cal_truth.size,
                    level)
    feats = features(policies)
    iv = intervals(feats, cal)
    return {"value": feats["sim_value"], "lo": np.asarray(iv["lo"]),
            "hi": np.asarray(iv["hi"]), "trusted": np.asarray(iv["trusted"]),
            "why": iv["why"], "sigma": np.asarray(iv["sigma"]), "support": feats["support"],
            "calibration": cal}
