"""Evaluate a learned simulator on a set of policies (usually the held-out test policies):
simulate each policy's value in p_phi, compare with its true value, rank.

    report = evaluate_checkpoint("runs/rl2s/checkpoints", "results/hopper/test.npz")
    report["metrics"]  # avd, mvd, kendall_tau, spearman, ndcg@k, regret@k
"""
from __future__ import annotations

from functools import partial

import jax
import numpy as np

from rl2s_jax.data.values import true_values, true_values_se
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.metrics import bootstrap_intervals, ranking_metrics
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.model.simulator import Simulator, simulated_returns, simulator_returns, start_pool
from rl2s_jax.policy.policy import Params, num_policies


@partial(jax.jit, static_argnames=("n_episodes", "horizon", "gamma"))
def _sim_returns(sim: Simulator, policies, pool, key, *, n_episodes, horizon, gamma):
    return simulator_returns(sim, get_task(sim.task), policies, pool, key,
                             n_episodes=n_episodes, horizon=horizon, gamma=gamma)


def _protocol(ds, policies, n_episodes, horizon, gamma) -> tuple[int, float]:
    if num_policies(policies) != ds.n_policies:
        raise ValueError(f"policies: expected {ds.n_policies} (the data's), got "
                         f"{num_policies(policies)}")
    if not isinstance(n_episodes, int) or n_episodes < 1:
        raise ValueError(f"episodes: expected an int >= 1, got {n_episodes!r}")
    return (int(horizon or ds.meta.get("episode_length") or 1000),
            float(gamma or ds.meta.get("gamma") or 0.999))


def value_report(ds, returns, lengths, *, horizon: int, gamma: float, ks=(1, 3, 5, 10),
                 n_boot: int = 0, boot_seed: int = 0) -> dict:
    """The report of simulated episodes against the data's true values.

    returns, lengths: [P, n] each simulated episode's discounted return and length
    ("sim_return_sd": [P] the spread of one episode's return, the evaluation noise). n_boot > 0
    adds "intervals" (``evaluate.bootstrap_intervals`` over the episodes, with the true values'
    standard errors when the data measured them).
    """
    truth = true_values(ds, horizon, gamma)
    returns = np.asarray(returns, np.float64)
    sim_value = returns.mean(1)
    out = {"true_value": truth.tolist(), "sim_value": sim_value.tolist(),
           "sim_length": np.asarray(lengths, np.float64).mean(1).tolist(),
           "sim_return_sd": (returns.std(1, ddof=1) if returns.shape[1] > 1
                             else np.zeros(returns.shape[0])).tolist(),
           "vd": np.abs(truth - sim_value).tolist(), "horizon": horizon, "gamma": gamma,
           "n_episodes": int(returns.shape[1]),
           "policy_names": list(ds.meta.get("policy_names") or range(ds.n_policies))}
    if ds.n_policies >= 2:
        out["metrics"] = ranking_metrics(truth, sim_value, ks=ks)
        if n_boot and np.all(np.isfinite(returns)):
            out["intervals"] = bootstrap_intervals(truth, returns,
                                                   true_values_se(ds, horizon, gamma),
                                                   n_boot=n_boot, seed=boot_seed, ks=ks)
    else:
        vd = float(abs(truth[0] - sim_value[0]))
        out["metrics"] = {"avd": vd, "mvd": vd}
    return out


def evaluate_simulator(sim: Simulator, ds, policies: Params, *, key: jax.Array,
                       n_episodes: int = 16, horizon: int | None = None,
                       gamma: float | None = None, ks=(1, 3, 5, 10), n_boot: int = 0) -> dict:
    """Simulated vs true discounted value of every policy of ``ds`` (stacked ``policies``).

    horizon: steps per simulated episode (default: the data's episode_length); gamma: default
    the data's. -> {"true_value", "sim_value", "sim_length", "vd" (lists [P]), "metrics": {avd,
    mvd, kendall_tau, spearman, ndcg@k, regret@k}, "horizon", "gamma", "n_episodes"} and, with
    n_boot > 0, "intervals" (``value_report``).
    """
    if sim.task is None:
        raise ValueError("ckpt: the simulator names no task, so there is no reward_fn/done_fn")
    horizon, gamma = _protocol(ds, policies, n_episodes, horizon, gamma)
    returns, lengths = _sim_returns(sim, policies, start_pool(ds), key, n_episodes=n_episodes,
                                    horizon=horizon, gamma=gamma)
    return value_report(ds, returns, lengths, horizon=horizon, gamma=gamma, ks=ks,
                        n_boot=n_boot)


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
                    n_boot: int = 0, env=None) -> dict:
    """``evaluate_simulator`` with the real dynamics in place of a learned simulator: the
    ceiling of any simulator of this observation under this protocol (same start states,
    horizon, gamma, reward_fn / done_fn and number of episodes)."""
    horizon, gamma = _protocol(ds, policies, n_episodes, horizon, gamma)
    returns, lengths = oracle_returns(task, env)(policies, start_pool=start_pool(ds), key=key,
                                                 n_episodes=n_episodes, horizon=horizon,
                                                 gamma=gamma)
    return value_report(ds, returns, lengths, horizon=horizon, gamma=gamma, ks=ks,
                        n_boot=n_boot)


