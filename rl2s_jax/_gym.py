"""``gymnasium.make("rl2s/Simulator-v0", ckpt=..., data=...)`` after ``import rl2s_jax``, in
either import order, without importing JAX or gymnasium itself.

Gymnasium 1.x loads no plugin entry points (its ``gymnasium.envs`` group was dropped in 1.0),
so the id is registered by the package: at once when gymnasium is loaded already, else right
after gymnasium's own import finishes (a one-shot import hook). The entry points are strings,
so registering loads nothing of ours; ``improve/gym_env.py`` registers the task ids.
Standard library only."""

from __future__ import annotations

import importlib.abc
import sys

SIMULATOR_ENV_ID = "rl2s/Simulator-v0"
_GYM_ENV = "rl2s_jax.improve.gym_env"


def register_simulator_env() -> None:
    """Register ``"rl2s/Simulator-v0"`` with the loaded gymnasium (no-op if it is there)."""
    gym = sys.modules["gymnasium"]
    if SIMULATOR_ENV_ID not in gym.registry:
        gym.register(SIMULATOR_ENV_ID, entry_point=f"{_GYM_ENV}:make_simulator_env",
                     vector_entry_point=f"{_GYM_ENV}:make_simulator_vector_env")


class _AfterGymnasium(importlib.abc.MetaPathFinder):
    """Finds nothing itself; wraps gymnasium's loader to register once it has run."""

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        sys.meta_path.remove(self)
        # local: the real spec, from the finders after this one
        from importlib.util import find_spec

        spec = find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_and_register(module):
            exec_module(module)
            register_simulator_env()

        spec.loader.exec_module = exec_and_register
        return spec


def install() -> None:
    """Register now if gymnasium is loaded, else when it is imported."""
    if "gymnasium" in sys.modules:
        register_simulator_env()
    elif not any(isinstance(f, _AfterGymnasium) for f in sys.meta_path):
        sys.meta_path.insert(0, _AfterGymnasium())
