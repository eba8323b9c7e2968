"""Checks and helpers for batched brax envs: the wrappers collection refuses, a per-env select."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from brax.envs.base import Env, Wrapper
from brax.envs.wrappers import training as brax_training

FORBIDDEN_WRAPPERS = (brax_training.AutoResetWrapper, brax_training.EpisodeWrapper,
                      brax_training.VmapWrapper, brax_training.DomainRandomizationVmapWrapper)


def check_env(env: Env) -> None:
    """Refuse envs whose wrappers reset, time-limit or batch on their own."""
    if not isinstance(env, Env):
        raise TypeError(f"env: expected a brax.envs.base.Env, got {type(env).__name__}")
    e = env
    while isinstance(e, Wrapper):
        if isinstance(e, FORBIDDEN_WRAPPERS):
            raise ValueError(
                f"env: {type(e).__name__} found in the wrapper chain; pass an env without "
                "auto-reset, episode or vmap wrappers (collection does its own resets, time "
                "limit and batching)")
        e = e.env


def tree_where(mask: jax.Array, a: Any, b: Any) -> Any:
    """Per-env select between two batched pytrees. mask: [B]; leaves: [B, ...]."""
    def sel(x, y):
        return jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y)
    return jax.tree_util.tree_map(sel, a, b)
