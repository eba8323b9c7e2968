"""The names the ``rl2s`` parser offers as choices, without importing what defines them (the
tasks and the recipes load JAX, brax and MuJoCo: seconds that ``rl2s --help`` and an argument
error should not wait for). Standard library only; tests/test_front_door.py checks these
against ``envs.tasks.BUILT_IN`` and ``improve.recipes.IMPROVE_RECIPES``."""

from __future__ import annotations

import sys

BUILT_IN_TASKS = ("hopper", "walker2d", "halfcheetah", "ant", "pointmass")
IMPROVE_RECIPE_NAMES = ("control",)


def task_names() -> tuple[str, ...]:
    """The registered task names: the built-in ones, and those ``register``ed in this process
    (registering imports ``rl2s_jax.envs.tasks``, so its registry is asked when loaded)."""
    tasks = sys.modules.get("rl2s_jax.envs.tasks")
    return tasks.task_names() if tasks is not None else BUILT_IN_TASKS
