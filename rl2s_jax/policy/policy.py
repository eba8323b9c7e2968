"""The one policy architecture of the project, and the policy zoo.

A policy is a tanh-squashed Gaussian MLP with a frozen observation normaliser. Its parameters
are a plain pytree (dict of arrays), so a zoo of P policies is the same pytree with a leading
axis [P, ...] and anything written for one policy runs over a zoo with ``jax.vmap``.

Params layout (one policy)::

    {"obs_mean": [obs], "obs_std": [obs],
     "layers": [{"w": [in, out], "b": [out]}, ...]}   # last layer out = 2 * action_size

The last layer's output is split into the pre-tanh mean ``loc`` and a raw scale; the scale is
``softplus(raw) + MIN_SCALE`` (as brax's NormalTanhDistribution), so the policy is state
dependent, differentiable, and fine to fine-tune with SAC.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

Params = dict[str, Any]
MIN_SCALE = 1e-3
DEFAULT_HIDDEN = (64, 64)


def init_mlp(key: jax.Array, sizes: Sequence[int], last_scale: float = 1.0) -> list[dict]:
    """MLP layers for ``mlp``: lecun-normal weights (last layer scaled), zero biases."""
    keys = jax.random.split(key, len(sizes) - 1)
    init = jax.nn.initializers.lecun_normal()
    layers = [{"w": init(k, (a, b), jnp.float32), "b": jnp.zeros((b,), jnp.float32)}
              for k, a, b in zip(keys, sizes[:-1], sizes[1:], strict=True)]
    layers[-1]["w"] = layers[-1]["w"] * last_scale
    return layers


def init_policy(key: jax.Array, obs_size: int, action_size: int,
                hidden: Sequence[int] = DEFAULT_HIDDEN) -> Params:
    """Fresh policy parameters with an identity normaliser.

    A small last layer keeps the initial policy near zero mean with a moderate spread.
    """
    return {"obs_mean": jnp.zeros((obs_size,), jnp.float32),
            "obs_std": jnp.ones((obs_size,), jnp.float32),
            "layers": init_mlp(key, [obs_size, *hidden, 2 * action_size], last_scale=0.01)}


def mlp(layers: list[dict[str, jax.Array]], x: jax.Array) -> jax.Array:
    """A swish MLP; no activation after the last layer. x: [..., in] -> [..., out]."""
    for layer in layers[:-1]:
        x = jax.nn.swish(x @ layer["w"] + layer["b"])
    return x @ layers[-1]["w"] + layers[-1]["b"]


def normalize_obs(params: Params, obs: jax.Array) -> jax.Array:
    """Observation normalised by the policy's frozen statistics, clipped to [-10, 10]."""
    return jnp.clip((obs - params["obs_mean"]) / params["obs_std"], -10.0, 10.0)


def policy_dist(params: Params, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Pre-tanh Gaussian of one policy. obs: [..., obs] -> (loc, scale), each [..., act]."""
    out = mlp(params["layers"], normalize_obs(params, obs))
    loc, raw_scale = jnp.split(out, 2, axis=-1)
    return loc, jax.nn.softplus(raw_scale) + MIN_SCALE


def gaussian_log_prob(loc: jax.Array, scale: jax.Array, raw: jax.Array) -> jax.Array:
    """log N(raw; loc, scale) summed over the last axis. -> [...]"""
    z = (raw - loc) / scale
    return jnp.sum(-0.5 * z**2 - jnp.log(scale) - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def tanh_log_det(raw: jax.Array) -> jax.Array:
    """log |d tanh(raw) / d raw| summed over the last axis (numerically stable form)."""
    return jnp.sum(2.0 * (jnp.log(2.0) - raw - jax.nn.softplus(-2.0 * raw)), axis=-1)


def sample_action(params: Params, obs: jax.Array, key: jax.Array
                  ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Stochastic action of one policy.

    obs: [..., obs] -> (action [..., act] in (-1, 1), raw pre-tanh action [..., act],
    log-prob of the squashed action [...]).
    """
    loc, scale = policy_dist(params, obs)
    raw = loc + scale * jax.random.normal(key, loc.shape, loc.dtype)
    logp = gaussian_log_prob(loc, scale, raw) - tanh_log_det(raw)
    return jnp.tanh(raw), raw, logp


def mode_action(params: Params, obs: jax.Array) -> jax.Array:
    """Deterministic action tanh(loc). obs: [..., obs] -> [..., act]."""
    return jnp.tanh(policy_dist(params, obs)[0])


# Observation dims a policy should not see (absolute positions) get this std and mean 0, so
# their normalised value is ~0 for any reachable position: the policy ignores them.
IGNORED_OBS_STD = 1e6


def mask_obs_stats(mean: jax.Array, std: jax.Array, ignore_dims: Sequence[int] = ()
                   ) -> tuple[jax.Array, jax.Array]:
    """(mean, std) [obs] with the ``ignore_dims`` set to (0, IGNORED_OBS_STD)."""
    if len(ignore_dims):
        idx = jnp.asarray(tuple(ignore_dims), jnp.int32)
        mean, std = mean.at[idx].set(0.0), std.at[idx].set(IGNORED_OBS_STD)
    return mean, std


class RunningNorm(NamedTuple):
    """Running observation mean and variance (parallel-algorithm update), the source of a
    trained policy's ``obs_mean`` / ``obs_std``."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @staticmethod
    def create(size: int) -> RunningNorm:
        return RunningNorm(jnp.zeros(size), jnp.ones(size), jnp.array(1e-4))

    def update(self, x: jax.Array) -> RunningNorm:
        """Fold in a batch x [..., obs]."""
        x = x.reshape(-1, x.shape[-1])
        b_mean, b_var, b_n = x.mean(0), x.var(0), x.shape[0]
        delta, total = b_mean - self.mean, self.count + b_n
        mean = self.mean + delta * b_n / total
        m2 = self.var * self.count + b_var * b_n + delta**2 * self.count * b_n / total
        return RunningNorm(mean, m2 / total, total)

    def std(self) -> jax.Array:
        return jnp.sqrt(self.var + 1e-6)

    def stats(self, ignore_dims: Sequence[int] = ()) -> tuple[jax.Array, jax.Array]:
        """(obs_mean, obs_std) [obs] float32 for a policy, ``ignore_dims`` masked out."""
        return mask_obs_stats(self.mean.astype(jnp.float32), self.std().astype(jnp.float32),
                              ignore_dims)


def stack_params(params_list: Sequence[Params]) -> Params:
    """[policy_0, policy_1, ...] -> one pytree with a leading policy axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *params_list)


def index_params(stacked: Params, ids) -> Params:
    """Policies ``ids`` (int or int array) of a stacked pytree."""
    ids = jnp.asarray(ids)
    return jax.tree_util.tree_map(lambda x: x[ids], stacked)


def num_policies(stacked: Params) -> int:
    return int(jax.tree_util.tree_leaves(stacked)[0].shape[0])
