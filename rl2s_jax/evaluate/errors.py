"""Where a simulator's error starts: diagnostics of trained lanes on the test policies' data
(never used to select a model) and the controls of those diagnostics (docs/EVALUATION.md,
"Where the error starts, and the controls of those diagnostics").

Each check takes the lanes' simulators as one ``Simulator`` whose array leaves carry a leading
lane axis L (``train.simulator(states, average=False)`` of vmapped training states):
``open_loop_check`` (the policies' logged actions replayed, k-step returns per policy),
``visited_error_check`` (one-step error against the real dynamics on the states the
simulator's own episodes visit, and on logged ones), ``hazard_check`` (a learned termination
against the logged ends), ``terminal_states`` / ``termination_causes`` (which of the task's
done conditions the simulated episodes end on). ``noisy`` and ``one_step_std`` build the
controls: the real dynamics with an unbiased step error of a known size.
``experiments/ablation_model.py`` and the control scripts use these."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.envs.tasks import _LOCO
from rl2s_jax.evaluate.metrics import kendall_tau
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.model.simulator import (
    Simulator,
    advance_values,
    logged_window_returns,
    mean_square,
    open_loop_returns,
    open_loop_windows,
    start_values,
    step_errors,
    visited_step_errors,
)


def _n_lanes(sims: Simulator) -> int:
    return int(jax.tree_util.tree_leaves(sims)[0].shape[0])


def noisy(dynamics, scale: jax.Array, noise_std: jax.Array):
    """``dynamics`` with scale x N(0, 1) x noise_std [o] added to every next state."""
    def step(obs, action, key):
        nxt = dynamics(obs, action, key)
        return nxt + scale * noise_std * jax.random.normal(key, nxt.shape, nxt.dtype)
    return step


def one_step_std(ds, position_dims) -> np.ndarray:
    """The std of the logged one-step change per obs dim [o], 0 on the absolute positions."""
    std = np.std(np.asarray(ds.next_obs, np.float64) - np.asarray(ds.obs, np.float64), 0)
    std[list(position_dims)] = 0.0
    return std.astype(np.float32)


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


def terminal_states(sims: Simulator, policies, pool, keys, *, task, n_episodes, horizon):
    """Each lane's simulated episodes (sims: leading lane axis L, keys [L, 2]; the stacked
    ``policies`` [P] from ``pool`` [S, o]), run as ``evaluate.lane_scores.lane_returns`` runs them
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


def termination_causes(task_name: str, terminal, ended) -> dict | None:
    """terminal [..., o] episodes' last states, ended [...] whether each ended ->
    {rule of TERMINATION_RULES[task_name]: share of the ended episodes whose terminal state
    breaks it (rules can overlap)}, plus "ended": share of episodes that ended; None for a
    task without rules."""
    rules = TERMINATION_RULES.get(task_name)
    if rules is None:
        return None
    ended = np.asarray(ended, bool)
    n = max(int(ended.sum()), 1)
    out = {name: float(np.asarray(rule(jnp.asarray(terminal)))[ended].sum() / n)
           for name, rule in rules}
    return {"ended": float(ended.mean()), **out}


def hazard_check(sims: Simulator, ds) -> dict:
    """How the learned per-step hazard of each lane (sims: leading lane axis L, trained with
    a learned termination) predicts the logged terminations of a Dataset's N rows: the summed
    h(s, a) against the count of done rows, and its mean cross-entropy against the base
    rate's. A diagnosis of the test policies' data (never used to select).
    -> {"rows", "done", "predicted": [L], "bce": [L], "base_rate_bce"}"""
    obs, act = jnp.asarray(ds.obs), jnp.asarray(ds.action)
    done = np.asarray(ds.done, np.float64)
    h = np.asarray(jax.jit(jax.vmap(lambda sim: sim.hazard_prob(obs, act)))(sims),
                   np.float64)  # [L, N]

    def xent(p):
        p = np.clip(p, 1e-7, 1 - 1e-7)
        return float(-np.mean(done * np.log(p) + (1 - done) * np.log1p(-p)))

    return {"rows": int(done.size), "done": int(done.sum()),
            "predicted": [round(float(x), 1) for x in h.sum(-1)],
            "bce": [round(xent(x), 5) for x in h],
            "base_rate_bce": round(xent(np.full(done.shape, done.mean())), 5)}


def open_loop_inputs(ds, task, k_max: int, n_windows: int, seed: int):
    """The logged windows of every policy (``simulate.open_loop_windows``), what the logged
    episodes earned in them (``logged_window_returns``), and the flat inputs of
    ``open_loop_returns``. -> (rows, steps [P, n], real reward [P, n, k_max], real end [P, n],
    start obs [P * n, o], actions [P * n, k_max, a], steps [P * n])"""
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


def open_loop_check(sims: Simulator, ds, task, *, ks=(1, 10, 50), n_windows: int = 256
                    ) -> dict:
    """Each lane's simulator (sims: leading lane axis L) rolled from the test policies'
    logged states under their LOGGED actions for k steps (``simulate.open_loop_returns``),
    against what the logged episodes earned in the same windows: per k, the Kendall tau of
    the policies' mean k-step returns,
    the spread ratio (std over policies, model / real: below 1 the model compresses the
    policies), the mean relative error, the fraction of windows that end, and the per-policy
    means at the largest k. A diagnosis of the test data (never used to select): if the
    model ranks the policies' windows well here but not in closed loop, the error is in how
    the policies react to the model's states, not in the dynamics under their actions.
    -> {"windows_per_policy", **``open_loop_summary``}"""
    k_max = max(ks)
    rows, steps, real_r, real_end, obs, act, n_steps = open_loop_inputs(ds, task, k_max,
                                                                        n_windows, seed=7)

    def one(sim, key):
        done_fn, hazard_fn = sim.terminations(task.done_fn)
        r, _, ended = open_loop_returns(sim.dynamics, task.reward_fn, done_fn, obs, act,
                                        n_steps, key, hazard_fn=hazard_fn)
        return r, ended

    n_lanes = _n_lanes(sims)
    keys = jnp.stack([jax.random.PRNGKey(4000 + i) for i in range(n_lanes)])
    sim_r, sim_end = (np.asarray(x) for x in jax.jit(jax.vmap(one))(sims, keys))
    sim_r = sim_r.reshape(n_lanes, *rows.shape, k_max).astype(np.float64)
    sim_end = sim_end.reshape(n_lanes, *rows.shape, k_max)
    return {"windows_per_policy": n_windows,
            **open_loop_summary(real_r, real_end, steps, sim_r, sim_end, ks)}


def visited_error_check(sims: Simulator, test_ds, test, task, *, n_episodes: int, horizon: int,
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
    n_lanes = _n_lanes(sims)
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
