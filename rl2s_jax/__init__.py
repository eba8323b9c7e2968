"""rl2s_jax: Robust Learning to Simulate in JAX.

The public API: build ``TrainData`` from a Dataset and its policies, ``init`` a ``TrainState``,
call the pure ``train_step(state, data) -> (state, metrics)`` (jit / scan / vmap it freely),
checkpoint with ``Checkpointer`` and load a trained ``Simulator`` with ``load_simulator``;
``SimulatorGymEnv`` / ``SimulatorVectorEnv`` put it behind the Gymnasium API. Your own
policies: ``save_policies`` / ``load_policies``; your own system's rules: ``register``.
"""
# First: imports mujoco.mjx without its lines about the optional Warp backend (rl2s_jax/_quiet.py).
import rl2s_jax._quiet  # noqa: F401
from rl2s_jax.app.train import run_training
from rl2s_jax.data.dataset import Dataset, load_dataset, save_dataset
from rl2s_jax.envs.tasks import register
from rl2s_jax.improve.finetune import improve_policies, improvement_metrics, measure_improvement
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model.simulator import Simulator, simulated_values
from rl2s_jax.policy.policy import load_policies, save_policies
from rl2s_jax.policy.sac import SACConfig, make_sac
from rl2s_jax.train.checkpoint import (
    Checkpointer,
    CheckpointError,
    CheckpointWarning,
    load_checkpoint,
    load_meta,
    load_simulator,
)
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.cvar import n_worst, select_worst
from rl2s_jax.train.data import TrainData, make_train_data
from rl2s_jax.train.loop import TrainingDiverged, fit
from rl2s_jax.train.step import TrainState, init, simulator, train_step, train_steps
from rl2s_jax.zoo.zoo import load_zoo, policies_for

__all__ = [
    "CheckpointError", "CheckpointWarning", "Checkpointer", "Dataset", "SACConfig", "Simulator",
    "SimulatorEnv", "SimulatorGymEnv", "SimulatorVectorEnv", "TrainConfig", "TrainData",
    "TrainState", "TrainingDiverged", "fit", "improve_policies", "improvement_metrics", "init",
    "load_checkpoint", "load_dataset", "load_meta", "load_policies", "load_simulator",
    "load_zoo", "make_sac", "make_train_data", "measure_improvement", "n_worst",
    "policies_for", "register", "run_training", "save_dataset", "save_policies",
    "select_worst", "simulated_values", "simulator", "train_step", "train_steps",
]


def __getattr__(name: str):
    """The Gymnasium envs, imported on first use (gymnasium is not needed otherwise)."""
    if name in ("SimulatorGymEnv", "SimulatorVectorEnv"):
        from rl2s_jax.improve import gym_env

        return getattr(gym_env, name)
    raise AttributeError(f"module 'rl2s_jax' has no attribute {name!r}")
