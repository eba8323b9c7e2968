"""Shared fixtures: MJX envs are slow to build on the CPU (~30 s), so each is built once."""

import functools

import pytest


@functools.cache
def cached_env(name: str):
    from rl2s_jax.tasks import get_task

    return get_task(name).make_env()


@pytest.fixture(scope="session")
def env_cache():
    return cached_env


@pytest.fixture(scope="session")
def hopper_train_ds(env_cache):
    """A small Hopper Dataset of the shipped zoo's 17 training policies (40-step episodes,
    2 true-value episodes each); meta.source names the zoo so `rl2s train` finds the policies."""
    import jax

    from rl2s_jax import policies as pol
    from rl2s_jax.collect import collect

    zoo = pol.load_zoo("hopper")
    ids = list(zoo.train_ids)
    return collect(env_cache("hopper"), pol.index_params(zoo.params, ids),
                   key=jax.random.PRNGKey(0), transitions_per_policy=80, envs_per_policy=2,
                   episode_length=40, task="hopper", value_episodes=2, progress=False,
                   policy_names=zoo.policy_names(ids),
                   source={"zoo": "experiments/zoo/hopper", "zoo_ids": ids})
