"""rl2s_jax: Robust Learning to Simulate in JAX.

The public API: build ``TrainData`` from a Dataset and its policies, ``init`` a ``TrainState``,
call the pure ``train_step(state, data) -> (state, metrics)`` (jit / scan / vmap it freely),
checkpoint with ``Checkpointer`` and load a trained ``Simulator`` with ``load_simulator``;
``SimulatorGymEnv`` / ``SimulatorVectorEnv`` put it behind the Gymnasium API. Your own
policies: ``save_policies`` / ``load_policies``; your own system's rules: ``register``.
Importing the package registers ``gymnasium.make("rl2s/Simulator-v0", ckpt=..., data=...)``
(rl2s_jax/_gym.py).

The names load on first use (module ``__getattr__``): ``import rl2s_jax`` and the ``rl2s``
command's parser load no JAX, brax or MuJoCo (seconds on a small CPU).
"""
from __future__ import annotations

import importlib

from rl2s_jax import _gym, _xla_cpu

_xla_cpu.avoid_cholesky_deadlock()  # before any JAX backend starts: rl2s_jax/_xla_cpu.py

_gym.install()

# public name -> the module that defines it
_PUBLIC = {
    "run_training": "rl2s_jax.app.training",
    "TrainSpec": "rl2s_jax.app.specs",
    **dict.fromkeys(("Dataset", "load_dataset", "save_dataset"), "rl2s_jax.data.dataset"),
    "register": "rl2s_jax.envs.tasks",
    **dict.fromkeys(("improve_policies", "improvement_metrics", "measure_improvement"),
                    "rl2s_jax.improve.finetune"),
    "SimulatorEnv": "rl2s_jax.improve.sim_env",
    **dict.fromkeys(("SimulatorGymEnv", "SimulatorVectorEnv"), "rl2s_jax.improve.gym_env"),
    **dict.fromkeys(("Simulator", "simulated_values"), "rl2s_jax.model.simulator"),
    **dict.fromkeys(("load_policies", "save_policies"), "rl2s_jax.policy.policy"),
    **dict.fromkeys(("SACConfig", "make_sac"), "rl2s_jax.policy.sac"),
    **dict.fromkeys(("Checkpointer", "CheckpointError", "CheckpointWarning", "load_checkpoint",
                     "load_meta", "load_simulator"), "rl2s_jax.train.checkpoint"),
    "simulated_values_with_intervals": "rl2s_jax.evaluate.trust",
    "TrainConfig": "rl2s_jax.train.config",
    **dict.fromkeys(("n_worst", "select_worst"), "rl2s_jax.train.cvar"),
    **dict.fromkeys(("TrainData", "make_train_data"), "rl2s_jax.train.data"),
    **dict.fromkeys(("TrainingDiverged", "fit"), "rl2s_jax.train.loop"),
    **dict.fromkeys(("TrainState", "init", "simulator", "train_step", "train_steps"),
                    "rl2s_jax.train.step"),
    **dict.fromkeys(("load_zoo", "policies_for"), "rl2s_jax.zoo.zoo"),
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    """A public name, imported from its module on first use (then cached in this module)."""
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'rl2s_jax' has no attribute {name!r}")
    importlib.import_module("rl2s_jax._quiet")  # first: MJX without its Warp lines
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
