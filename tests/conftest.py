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
