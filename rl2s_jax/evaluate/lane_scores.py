"""Evaluation of lanes: many simulators (seeds, methods) stacked on a leading axis and scored at
once, as ``evaluate_simulator`` scores one; the oracle through the same path, once per seed.

A lane's simulator is ``train.simulator(states)`` of a vmapped ``TrainState`` (``train.lanes``);
here it is a ``Simulator`` whose array leaves carry a leading lane axis L. The paper protocol
(``rl2s_jax.paper.protocol``), the ablations and the sharding tests use these."""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.data.values import true_values_se
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.metrics import noise_ceiling, ranking_metrics
from rl2s_jax.evaluate.scores import evaluate_oracle
from rl2s_jax.model.simulator import Simulator, simulator_returns

# The ranking and value metrics of a lane's evaluation (``ranking_metrics`` at ks 1, 3, 5, 10).
EVAL_METRICS = ("kendall_tau", "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10", "spearman",
                "regret@1", "avd", "mvd")


@partial(jax.jit, static_argnames=("n_episodes", "horizon", "gamma"))
def lane_returns(sims: Simulator, policies, pool, keys, *, n_episodes, horizon, gamma):
    """``evaluate_simulator``'s rollouts vmapped over lanes: sims (a Simulator with a leading
    lane axis L) and keys [L, 2]; the stacked ``policies`` [P] started from ``pool`` [S, o].
    -> (discounted returns [L, P, n], episode lengths [L, P, n])"""
    return jax.vmap(lambda sim, key: simulator_returns(  # each lane's own task_fns
        sim, None, policies, pool, key, n_episodes=n_episodes, horizon=horizon,
        gamma=gamma))(sims, keys)


def evaluate_lanes(sims: Simulator, seeds, policies, pool, truth, *, key_base: int,
                   n_episodes, horizon, gamma):
    """``evaluate_simulator``'s metrics for every lane of ``sims`` (leading lane axis L): the
    stacked ``policies`` [P] started from ``pool`` [S, o] against their true values ``truth``
    [P], keys PRNGKey(key_base + seed) for the lanes' ``seeds`` [L] (1000: the test policies,
    2000: the training policies' held-out episodes, for model selection).
    -> (list of L metric dicts (None where the simulated values are not finite), values
    [L, P], per-episode returns [L, P, n], mean simulated episode lengths [L, P])"""
    keys = jnp.stack([jax.random.PRNGKey(key_base + s) for s in seeds])
    returns, lengths = lane_returns(sims, policies, pool, keys, n_episodes=n_episodes,
                                    horizon=horizon, gamma=gamma)
    returns = np.asarray(returns, np.float64)
    values = returns.mean(-1)
    out = []
    for v in values:
        try:
            out.append(ranking_metrics(truth, v, ks=(1, 3, 5, 10)))
        except ValueError:  # non-finite simulated values: the lane diverged
            out.append(None)
    return out, values, returns, np.asarray(lengths, np.float64).mean(-1)


def intervals_over_seeds(per_seed: list[dict | None]) -> dict:
    """Each metric's mean over seeds of the per-seed bootstrap interval ends and std.
    per_seed: S entries of ``stats.bootstrap_intervals(...)["metrics"]`` ({metric: {"lo", "hi",
    "std", ...}}, None for a seed without one) -> {metric: {"lo", "hi", "std"}} (an
    episode-noise interval; the spread over seeds is a result's "std")."""
    rows = [r for r in per_seed if r is not None]
    if not rows:
        return {}
    return {k: {q: float(np.mean([r[k][q] for r in rows])) for q in ("lo", "hi", "std")}
            for k in rows[0]}


def oracle_rows(task: str, test_ds, test_pols, seeds, *, n_episodes, horizon, gamma,
                n_boot: int) -> dict:
    """The control: ``evaluate_oracle`` (the real dynamics through the lanes' evaluation path:
    same start states, horizon, gamma, episodes) once per seed with the lanes' key
    PRNGKey(1000 + seed). test_pols: the test data's P policies, stacked.
    -> {"per_seed": {metric: [S]}, "intervals": [S] (bootstrap metric intervals or None),
    "sim_value", "sim_length", "sim_return_sd": [S][P] each}"""
    env = get_task(task).make_env()
    out = {"per_seed": {k: [] for k in EVAL_METRICS}, "intervals": [], "sim_value": [],
           "sim_length": [], "sim_return_sd": []}
    for s in seeds:
        r = evaluate_oracle(task, test_ds, test_pols, key=jax.random.PRNGKey(1000 + s),
                            n_episodes=n_episodes, horizon=horizon, gamma=gamma,
                            n_boot=n_boot, env=env)
        for k in EVAL_METRICS:
            out["per_seed"][k].append(r["metrics"][k])
        out["intervals"].append(r.get("intervals", {}).get("metrics"))
        out["sim_value"].append(r["sim_value"])
        out["sim_length"].append(np.round(r["sim_length"], 1).tolist())
        out["sim_return_sd"].append(r["sim_return_sd"])
    return out


def oracle_noise_ceiling(test_ds, truth, sim_return_sd, *, n_sim: int, horizon: int,
                         gamma: float, n_rep: int = 1000) -> dict:
    """What evaluation noise alone lets an exact simulator reach on these test policies
    (``metrics.noise_ceiling``): the simulator's per-episode spread from the oracle's episodes
    (sim_return_sd [S, P], averaged over seeds), the truth's from the data's value SE x
    sqrt(its episodes) where it was measured (else the oracle's spread). truth: [P].
    -> {"n_truth", "n_sim", "kendall_tau", "ndcg@1"}: the last two {"mean", "lo", "hi"}."""
    sd = np.mean(np.asarray(sim_return_sd, np.float64), axis=0)
    n_truth = int((test_ds.meta.get("source") or {}).get("value_episodes") or 0)
    se = true_values_se(test_ds, horizon, gamma)
    if se is None or n_truth < 1:   # true values from the logged episodes: their count
        n_truth = max(int(np.unique(np.asarray(test_ds.episode_id)).size
                          // max(test_ds.n_policies, 1)), 1)
        truth_sd = None
    else:
        truth_sd = np.asarray(se, np.float64) * np.sqrt(n_truth)
    nc = noise_ceiling(truth, sd, n_truth=n_truth, n_sim=n_sim, n_rep=n_rep,
                       truth_episode_sd=truth_sd)
    return {"n_truth": n_truth, "n_sim": n_sim, "kendall_tau": nc["kendall_tau"],
            "ndcg@1": nc["ndcg@1"]}
