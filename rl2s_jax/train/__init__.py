"""Training the simulator: the config, losses, the CVaR selection, the pure ``train_step``,
the host loop (chunks, resume, NaN stop) and checkpoints.

The names below are re-exported so that ``from rl2s_jax.train import TrainConfig, init``
keeps working; the modules are ``config``, ``losses``, ``cvar``, ``data``, ``step``,
``loop`` and ``checkpoint``.
"""
from rl2s_jax.data.values import true_values, true_values_se
from rl2s_jax.train.config import DEFAULT_EPS, LEGACY_MODEL, METHODS, TrainConfig
from rl2s_jax.train.cvar import n_worst, select_worst
from rl2s_jax.train.data import TrainData, episode_steps_left, heldout_mask, make_train_data
from rl2s_jax.train.losses import multistep_error
from rl2s_jax.train.step import (
    TrainState,
    init,
    member_mle_updates,
    simulator,
    track_best,
    train_step,
    train_steps,
)

__all__ = ["DEFAULT_EPS", "LEGACY_MODEL", "METHODS", "TrainConfig", "TrainData", "TrainState",
           "episode_steps_left", "heldout_mask", "init", "make_train_data",
           "member_mle_updates", "multistep_error", "n_worst", "select_worst", "simulator",
           "track_best", "train_step", "train_steps", "true_values", "true_values_se"]
