"""Grow a policy zoo: PPO over several seeds, snapshots along training, measured returns, split.

The paper samples policies of every quality from P(pi); we do it the usual way: train PPO from
several seeds and keep snapshots from the random initial policy to the final one. Every
snapshot's real return is then measured with fresh episodes in the env, and a fixed split picks
train policies spread evenly over the range of returns, the rest being test policies.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from rl2s_jax.collect import measure_values
from rl2s_jax.policies import Zoo
from rl2s_jax.ppo import PPOConfig, make_train
from rl2s_jax.tasks import get_task

# Per-task PPO settings, close to brax's published PPO settings for these envs; sized so that
# one zoo trains in a few minutes on one H100 with 4 seeds vmapped.
ZOO_PPO = {
    "pointmass": PPOConfig(num_envs=64, unroll_length=16, num_minibatches=4,
                           iterations_per_snapshot=10, n_snapshots=10, episode_length=50,
                           gamma=0.95, learning_rate=1e-3),
    "hopper": PPOConfig(num_envs=2048, unroll_length=10, num_minibatches=32,
                        iterations_per_snapshot=40, n_snapshots=14),
    "walker2d": PPOConfig(num_envs=2048, unroll_length=10, num_minibatches=32,
                          iterations_per_snapshot=40, n_snapshots=14),
    "halfcheetah": PPOConfig(num_envs=2048, unroll_length=20, num_minibatches=32,
                             update_epochs=8, iterations_per_snapshot=20, n_snapshots=14,
                             gamma=0.95, entropy_cost=1e-3),
    "ant": PPOConfig(num_envs=2048, unroll_length=5, num_minibatches=32,
                     iterations_per_snapshot=50, n_snapshots=14, reward_scaling=10.0),
}
SPLIT_SIZES = {"ant": 32}   # train-split size; 17 for every other task (the paper's)
MIN_TEST = 20


def spread_subset(returns: np.ndarray, size: int) -> list[int]:
    """Indices of ``size`` policies whose returns cover [min, max] as evenly as possible.

    Greedy: for each of ``size`` evenly spaced target returns, the closest policy not yet taken.
    Snapshots crowd where training plateaus; this keeps the zoo's quality spread even.
    """
    if size > len(returns):
        raise ValueError(f"zoo_size: expected at most {len(returns)} (snapshots), got {size}")
    free = np.ones(len(returns), bool)
    picks = []
    for target in np.linspace(returns.min(), returns.max(), size):
        i = int(np.argmin(np.where(free, np.abs(returns - target), np.inf)))
        free[i] = False
        picks.append(i)
    return sorted(picks)


def choose_split(returns: np.ndarray, n_train: int, min_test: int = MIN_TEST
                 ) -> tuple[list[int], list[int]]:
    """Train ids spread evenly over the sorted returns; every other policy is a test policy."""
    P = len(returns)
    if P < n_train + min_test:
        raise ValueError(f"zoo: {P} policies cannot give {n_train} train + {min_test} test")
    order = np.argsort(returns, kind="stable")
    picks = np.unique(np.round(np.linspace(0, P - 1, n_train)).astype(int))
    train = sorted(int(order[i]) for i in picks)
    test = sorted(set(range(P)) - set(train))
    return train, test


def build_zoo(task_name: str, *, seeds: int = 4, key: jax.Array | None = None,
              cfg: PPOConfig | None = None, value_episodes: int = 16,
              n_train: int | None = None, zoo_size: int = 60, min_test: int = MIN_TEST,
              log=print) -> Zoo:
    """Train ``seeds`` PPO runs (one vmapped program), measure every snapshot, keep
    ``zoo_size`` of them spread evenly over the returns, split into train and test."""
    task = get_task(task_name)
    env = task.make_env()
    cfg = cfg or ZOO_PPO[task_name]
    cfg = dataclasses.replace(cfg, episode_length=task.episode_length)
    key = jax.random.PRNGKey(0) if key is None else key
    k_train, k_eval = jax.random.split(key)
    log(f"[zoo] {task_name}: PPO x {seeds} seeds, {cfg.total_env_steps:,} env steps each")
    t0 = time.time()
    train = jax.jit(jax.vmap(make_train(env, cfg)))
    _, snaps = train(jax.random.split(k_train, seeds))
    jax.block_until_ready(snaps)
    train_s = time.time() - t0
    n_snap = cfg.n_snapshots + 1
    params = jax.tree_util.tree_map(lambda x: x.reshape((seeds * n_snap,) + x.shape[2:]),
                                    snaps["params"])
    train_ret = np.asarray(snaps["episode_return"]).reshape(-1)
    env_steps = np.asarray(snaps["env_steps"]).reshape(-1)
    log(f"[zoo] trained in {train_s:.0f}s; final training returns per seed: "
        f"{np.asarray(snaps['episode_return'])[:, -1].round(1).tolist()}")
    t1 = time.time()
    values = measure_values(env, params, key=k_eval, n_episodes=value_episodes,
                            episode_length=task.episode_length, gamma=0.999)
    log(f"[zoo] measured {seeds * n_snap} policies x {value_episodes} episodes in "
        f"{time.time() - t1:.0f}s; returns {values['value'].min():.1f} .. "
        f"{values['value'].max():.1f}")
    keep = spread_subset(values["value"], min(zoo_size, seeds * n_snap))
    params = jax.tree_util.tree_map(lambda x: x[np.asarray(keep)], params)
    values = {k: v[keep] for k, v in values.items()}
    origins = [{"seed": j // n_snap, "snapshot": j % n_snap, "env_steps": int(env_steps[j]),
                "training_return": None if np.isnan(train_ret[j]) else float(train_ret[j])}
               for j in keep]
    train_ids, test_ids = choose_split(values["value"], n_train or SPLIT_SIZES.get(task_name, 17),
                                       min_test)
    info = {"ppo": dataclasses.asdict(cfg), "seeds": seeds, "value_episodes": value_episodes,
            "snapshots_measured": seeds * n_snap,
            "train_seconds": round(train_s, 1), "device": str(jax.devices()[0]),
            "jax": jax.__version__}
    return Zoo(task=task_name, params=params, returns=values["value"],
               return_se=values["value_se"], origins=origins, train_ids=train_ids,
               test_ids=test_ids, info=info)


__all__ = ["ZOO_PPO", "build_zoo", "choose_split"]
