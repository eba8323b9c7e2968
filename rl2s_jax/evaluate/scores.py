"""Evaluate a learned simulator on a set of policies (usually the held-out test policies):
simulate each policy's value in p_phi, compare with its true value, rank.

    report = evaluate_checkpoint("runs/rl2s/checkpoints", "results/hopper/test.npz")
    report["metrics"]  # avd, mvd, kendall_tau, spearman, ndcg@k, regret@k
"""
from __future__ import annotations

from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.data.dataset import spread_rows
from rl2s_jax.data.values import true_values, true_values_se, truth_used
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.metrics import ranking_metrics
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.history import logged_history
from rl2s_jax.model.simulator import Simulator, simulated_returns, simulator_returns, start_pool
from rl2s_jax.policy.policy import Params, num_policies
from rl2s_jax.stats import bootstrap_intervals


@partial(jax.jit, static_argnames=("n_episodes", "horizon", "gamma", "policy_fn"))
def _sim_returns(sim: Simulator, policies, pool, key, *, n_episodes, horizon, gamma,
                 policy_fn=None):
    return simulator_returns(sim, None, policies, pool, key,  # the simulator's task_fns
                             n_episodes=n_episodes, horizon=horizon, gamma=gamma,
                             policy_fn=policy_fn)


def _protocol(ds, policies, n_episodes, horizon, gamma) -> tuple[int, float]:
    if num_policies(policies) != ds.n_policies:
        raise ValueError(f"policies: expected {ds.n_policies} (the data's), got "
                         f"{num_policies(policies)}")
    if not isinstance(n_episodes, int) or n_episodes < 1:
        raise ValueError(f"episodes: expected an int >= 1, got {n_episodes!r}")
    return (int(horizon or ds.meta.get("episode_length") or 1000),
            float(gamma or ds.meta.get("gamma") or 0.999))


def value_report(ds, returns, lengths, *, horizon: int, gamma: float, ks=(1, 3, 5, 10),
                 n_boot: int = 0, boot_seed: int = 0, truth: str = "auto") -> dict:
    """The report of simulated episodes against the data's true values.

    returns, lengths: [P, n] each simulated episode's discounted return and length
    ("sim_return_sd": [P] the spread of one episode's return, the evaluation noise). n_boot > 0
    adds "intervals" (``stats.bootstrap_intervals`` of ``ranking_metrics`` over the episodes,
    with the true values' standard errors when the data measured them). ``truth``: which true value
    (``data.values.truth_used``; the one used is "true_value_source").
    """
    source = truth_used(ds, horizon, gamma, truth)
    se = true_values_se(ds, horizon, gamma, truth)
    truth = true_values(ds, horizon, gamma, truth=truth)
    returns = np.asarray(returns, np.float64)
    sim_value = returns.mean(1)
    out = {"true_value": truth.tolist(), "sim_value": sim_value.tolist(),
           "sim_length": np.asarray(lengths, np.float64).mean(1).tolist(),
           "sim_return_sd": (returns.std(1, ddof=1) if returns.shape[1] > 1
                             else np.zeros(returns.shape[0])).tolist(),
           "vd": np.abs(truth - sim_value).tolist(), "horizon": horizon, "gamma": gamma,
           "n_episodes": int(returns.shape[1]), "true_value_source": source,
           "policy_names": list(ds.meta.get("policy_names") or range(ds.n_policies))}
    if ds.n_policies >= 2:
        out["metrics"] = ranking_metrics(truth, sim_value, ks=ks)
        if n_boot and np.all(np.isfinite(returns)):
            out["intervals"] = bootstrap_intervals(
                truth, returns, partial(ranking_metrics, ks=ks), se, n_boot=n_boot,
                seed=boot_seed)
    else:
        vd = float(abs(truth[0] - sim_value[0]))
        out["metrics"] = {"avd": vd, "mvd": vd}
    return out


def evaluate_simulator(sim: Simulator, ds, policies: Params, *, key: jax.Array,
                       n_episodes: int = 16, horizon: int | None = None,
                       gamma: float | None = None, ks=(1, 3, 5, 10), n_boot: int = 0,
                       policy_fn: Callable | None = None, truth: str = "auto") -> dict:
    """Simulated vs true discounted value of every policy of ``ds`` (stacked ``policies``;
    ``policy_fn(params, obs [n, o], key) -> action [n, a]`` applies one policy's params when
    they are not the project's policy format: any JAX function, e.g. your own network).

    horizon: steps per simulated episode (default: the data's episode_length); gamma: default
    the data's. -> {"true_value", "sim_value", "sim_length", "vd" (lists [P]), "metrics": {avd,
    mvd, kendall_tau, spearman, ndcg@k, regret@k}, "horizon", "gamma", "n_episodes"} and, with
    n_boot > 0, "intervals" (``value_report``; ``truth`` as there). The one-step errors are
    ``one_step_errors``.
    Rewards and terminations: the simulator's ``task_fns`` (its registered task's, or its
    learned reward and hazard).
    """
    sim.task_fns()  # a simulator of no registered task without a learned reward: refused here
    horizon, gamma = _protocol(ds, policies, n_episodes, horizon, gamma)
    truth_used(ds, horizon, gamma, truth)  # a true value it cannot give: refused first
    returns, lengths = _sim_returns(sim, policies, start_pool(ds), key, n_episodes=n_episodes,
                                    horizon=horizon, gamma=gamma, policy_fn=policy_fn)
    return value_report(ds, returns, lengths, horizon=horizon, gamma=gamma, ks=ks,
                        n_boot=n_boot, truth=truth)


ONE_STEP_ROWS = 20_000  # rows that one-step errors are measured on (evenly spread)


@jax.jit
def _one_step(sim: Simulator, obs, action, next_obs, hist, scale):
    means, log_stds = sim.member_dists(obs, action, hist)                  # [E, n, o]
    start = sim.anchor(obs, action, hist)  # obs, or a hybrid's physics step
    y = sim.norm.norm_delta(start, next_obs)
    nll = jnp.mean(dyn.gaussian_nll(means, log_stds, y[None]), 1)          # [E]
    nll = nll + jnp.sum(jnp.log(sim.norm.delta_std))  # nats of s' - s in the data's units
    mean_next = sim.mean_of(start, means, log_stds)  # the same pass as the NLL's
    mse = jnp.mean(((mean_next - next_obs) / scale) ** 2)
    return nll, mse


def one_step_errors(sim: Simulator, ds, max_rows: int = ONE_STEP_ROWS) -> dict:
    """The simulator's one-step error on the transitions of ``ds`` (for a fair score, data the
    simulator never trained on: held-out episodes of the same system). Up to ``max_rows``
    rows, evenly spread; a simulator with history inputs sees each row's logged past.

    -> {"heldout_nll": mean over the elites of each member's Gaussian NLL of s' - s, in nats
    per transition of the data's raw units (comparable across simulators and normalisers, the
    quantity training's ``heldout_nll`` reports up to the constant sum(log delta_std)),
    "heldout_mse": the mean squared error of the mean next state (``Simulator.mean``), per dim
    in units of this data's own std of s' - s, averaged over dims; "one_step_rows": n}."""
    rows = spread_rows(ds.n_transitions, max_rows)
    obs, action, next_obs = (jnp.asarray(np.asarray(x, np.float32)[rows])
                             for x in (ds.obs, ds.action, ds.next_obs))
    if obs.shape[-1] != sim.norm.obs_mean.shape[-1] or (
            action.shape[-1] != sim.norm.act_mean.shape[-1]):
        raise ValueError(f"data: obs / action sizes {obs.shape[-1]} / {action.shape[-1]} do "
                         f"not match the simulator's {sim.norm.obs_mean.shape[-1]} / "
                         f"{sim.norm.act_mean.shape[-1]}")
    hist = None if sim.markov else logged_history(
        ds, rows, obs_history=sim.obs_history, action_history=sim.action_history,
        time_inputs=sim.time_inputs, episode_length=sim.episode_length)
    delta = np.asarray(ds.next_obs, np.float64) - np.asarray(ds.obs, np.float64)
    scale = jnp.asarray(np.maximum(delta.std(0), 1e-6), jnp.float32)
    nll, mse = _one_step(sim, obs, action, next_obs, hist, scale)
    E = nll.shape[0]
    elite = np.asarray(dyn.elite_mask(sim.rank, sim.n_elites, E))
    return {"heldout_nll": float(np.asarray(nll)[elite].mean()), "heldout_mse": float(mse),
            "one_step_rows": int(rows.size)}


def oracle_returns(task: str, env=None):
    """A jitted ``f(policies, pool, key, *, n_episodes, horizon, gamma) -> (returns, lengths)
    [P, n]``: ``simulate.simulated_returns`` with the task's real dynamics
    (``oracle.oracle_dynamics``), i.e. the evaluation path of a learned simulator."""
    t = get_task(task)
    dyn = oracle_dynamics(t, env)
    return jax.jit(partial(simulated_returns, dynamics=dyn, reward_fn=t.reward_fn,
                           done_fn=t.done_fn),
                   static_argnames=("n_episodes", "horizon", "gamma"))


def evaluate_oracle(task: str, ds, policies: Params, *, key: jax.Array, n_episodes: int = 16,
                    horizon: int | None = None, gamma: float | None = None, ks=(1, 3, 5, 10),
                    n_boot: int = 0, env=None, truth: str = "auto") -> dict:
    """``evaluate_simulator`` with the real dynamics in place of a learned simulator: the
    ceiling of any simulator of this observation under this protocol (same start states,
    horizon, gamma, reward_fn / done_fn and number of episodes)."""
    horizon, gamma = _protocol(ds, policies, n_episodes, horizon, gamma)
    truth_used(ds, horizon, gamma, truth)  # a true value it cannot give: refused first
    returns, lengths = oracle_returns(task, env)(policies, start_pool=start_pool(ds), key=key,
                                                 n_episodes=n_episodes, horizon=horizon,
                                                 gamma=gamma)
    return value_report(ds, returns, lengths, horizon=horizon, gamma=gamma, ks=ks,
                        n_boot=n_boot, truth=truth)


