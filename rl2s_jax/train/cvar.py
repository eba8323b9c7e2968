"""The CVaR selection: the worst eps-fraction of the training policies by value difference."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def n_worst(eps: jax.Array | float, n_policies: int) -> jax.Array:
    """max(2, ceil(eps * P)) capped at P. A slack of a few float32 ulps keeps rounding error
    from rounding up (0.15 * 20 is 3, not 4; 0.6 * 205 is 123). -> [] int32"""
    x = jnp.asarray(eps, jnp.float32) * n_policies
    k = jnp.ceil(x - 3e-7 * jnp.maximum(x, 1.0)).astype(jnp.int32)
    return jnp.minimum(jnp.maximum(k, 2), n_policies)


def select_worst(vd: jax.Array, n_select: jax.Array) -> jax.Array:
    """Mask [P] of the n_select largest VDs; ties go to the lower index; NaN counts as worst."""
    vd = jnp.where(jnp.isnan(vd), jnp.inf, vd)
    order = jnp.argsort(-vd, stable=True)
    rank = jnp.zeros_like(order).at[order].set(jnp.arange(vd.shape[0], dtype=order.dtype))
    return rank < n_select
