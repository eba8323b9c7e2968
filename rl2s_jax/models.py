"""The simulator's networks: a Gaussian generator over normalised state changes and a
spectrally normalised discriminator.

Everything is a plain pytree and a pure function, written for one example and batched by the
caller (any leading axes work). Shapes use o = obs size, a = action size.

- ``Normalizer``: fixed statistics of obs, action and delta = s' - s, computed once from data.
  It is part of the simulator, so a checkpoint is usable without the training data.
- Generator p_phi(s'|s,a): MLP over normalised (s, a) -> mean and log-std of the normalised
  delta; s' = s + delta_mean + delta_std * delta_n.
- Discriminator D_psi(s, a, s'): MLP over normalised (s, a, delta), every layer spectrally
  normalised (one power-iteration step per discriminator update, as torch's spectral_norm).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rl2s_jax.policies import init_mlp

LOG_STD_MIN = -5.0  # std >= 0.7% of the data's delta std: sharper made BC collapse on Hopper
LOG_STD_MAX = 1.0


@struct.dataclass
class Normalizer:
    """Per-dimension mean/std of obs [o], action [a] and delta = next_obs - obs [o], and
    obs_input_mask [o]: 1 for the obs dims the networks see, 0 for those left out (absolute
    positions, which the dynamics do not depend on)."""

    obs_mean: jax.Array
    obs_std: jax.Array
    act_mean: jax.Array
    act_std: jax.Array
    delta_mean: jax.Array
    delta_std: jax.Array
    obs_input_mask: jax.Array | None = None  # None: every dim

    @classmethod
    def from_data(cls, obs, action, next_obs, min_std: float = 1e-6,
                  ignore_dims: tuple[int, ...] = ()) -> Normalizer:
        """Statistics of transitions obs [N, o], action [N, a], next_obs [N, o] (NumPy, float64);
        ``ignore_dims``: obs dims to leave out of the networks' inputs."""
        obs, action, next_obs = (np.asarray(x, np.float64) for x in (obs, action, next_obs))
        delta = next_obs - obs

        def stats(x):
            return (jnp.asarray(x.mean(0), jnp.float32),
                    jnp.asarray(np.maximum(x.std(0), min_std), jnp.float32))

        (om, os_), (am, as_), (dm, ds) = stats(obs), stats(action), stats(delta)
        mask = np.ones(obs.shape[1], np.float32)
        for d in ignore_dims:
            if not 0 <= d < obs.shape[1]:
                raise ValueError(f"ignore_dims: expected obs dims in [0, {obs.shape[1]}), got {d}")
            mask[d] = 0.0
        return cls(om, os_, am, as_, dm, ds, jnp.asarray(mask))

    def norm_obs(self, obs):
        return (obs - self.obs_mean) / self.obs_std

    def input_obs(self, obs):
        """The normalised obs as the networks see it (left-out dims zeroed)."""
        x = self.norm_obs(obs)
        return x if self.obs_input_mask is None else x * self.obs_input_mask

    def norm_act(self, action):
        return (action - self.act_mean) / self.act_std

    def norm_delta(self, obs, next_obs):
        return (next_obs - obs - self.delta_mean) / self.delta_std

    def next_from_delta(self, obs, delta_n):
        return obs + self.delta_mean + self.delta_std * delta_n


# ---------------------------------------------------------------- generator


def init_generator(key: jax.Array, obs_size: int, action_size: int,
                   hidden: Sequence[int] = (512, 512, 512, 512)) -> list[dict]:
    """MLP [o + a] -> hidden -> [2 o] (mean and raw log-std of the normalised delta)."""
    return init_mlp(key, [obs_size + action_size, *hidden, 2 * obs_size], last_scale=0.01)


def _relu_mlp(layers: list[dict], x: jax.Array) -> jax.Array:
    for layer in layers[:-1]:
        x = jax.nn.relu(x @ layer["w"] + layer["b"])
    return x @ layers[-1]["w"] + layers[-1]["b"]


def _bounded_log_std(raw: jax.Array) -> jax.Array:
    """Smoothly bound log-std to about [LOG_STD_MIN, LOG_STD_MAX] (it can exceed the top by
    log(1 + e^(MIN - MAX)), 0.0025 here; gradients never vanish outright)."""
    x = LOG_STD_MAX - jax.nn.softplus(LOG_STD_MAX - raw)
    return LOG_STD_MIN + jax.nn.softplus(x - LOG_STD_MIN)


def generator_dist(gen: list[dict], norm: Normalizer, obs: jax.Array, action: jax.Array
                   ) -> tuple[jax.Array, jax.Array]:
    """Gaussian over the normalised delta.

    obs [..., o], action [..., a] -> (mean, log_std), each [..., o].
    """
    x = jnp.concatenate([norm.input_obs(obs), norm.norm_act(action)], -1)
    out = _relu_mlp(gen, x)
    mean, raw_log_std = jnp.split(out, 2, axis=-1)
    return mean, _bounded_log_std(raw_log_std)


def generator_sample(gen: list[dict], norm: Normalizer, obs: jax.Array, action: jax.Array,
                     key: jax.Array, obs_clip: float | None = None,
                     noise_scale: float = 1.0) -> jax.Array:
    """A reparameterised next-state sample s' ~ p_phi(.|s, a). -> [..., o]

    ``obs_clip`` bounds the normalised next state to [-obs_clip, obs_clip] so long simulated
    rollouts stay finite; leave it None where gradients must flow (the generator loss).
    ``noise_scale`` multiplies the std (0: the mean, for deterministic real systems).
    """
    mean, log_std = generator_dist(gen, norm, obs, action)
    noise = jax.random.normal(key, mean.shape, mean.dtype)
    delta_n = mean + noise_scale * jnp.exp(log_std) * noise
    next_obs = norm.next_from_delta(obs, delta_n)
    if obs_clip is not None:
        lo = norm.obs_mean - obs_clip * norm.obs_std
        hi = norm.obs_mean + obs_clip * norm.obs_std
        next_obs = jnp.clip(next_obs, lo, hi)
    return next_obs


def generator_mean(gen: list[dict], norm: Normalizer, obs: jax.Array, action: jax.Array
                   ) -> jax.Array:
    """The generator's mean next state (no noise). -> [..., o]"""
    mean, _ = generator_dist(gen, norm, obs, action)
    return norm.next_from_delta(obs, mean)


def generator_log_prob(gen: list[dict], norm: Normalizer, obs: jax.Array, action: jax.Array,
                       next_obs: jax.Array) -> jax.Array:
    """log p_phi(s'|s,a) of the normalised delta, summed over dims. -> [...]

    It is the density of delta_n, not of s' (they differ by the constant sum(log delta_std)).
    """
    mean, log_std = generator_dist(gen, norm, obs, action)
    z = (norm.norm_delta(obs, next_obs) - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * jnp.log(2 * jnp.pi), -1)


# ------------------------------------------------------------ discriminator


def init_discriminator(key: jax.Array, obs_size: int, action_size: int,
                       hidden: Sequence[int] = (512, 512, 512, 512)
                       ) -> tuple[list[dict], list[jax.Array]]:
    """Parameters [2 o + a] -> hidden -> [1] and the power-iteration vectors u (one per layer)."""
    k_w, k_u = jax.random.split(key)
    layers = init_mlp(k_w, [2 * obs_size + action_size, *hidden, 1])
    keys = jax.random.split(k_u, len(layers))
    us = [_l2_normalize(jax.random.normal(k, (layer["w"].shape[1],)))
          for k, layer in zip(keys, layers, strict=True)]
    return layers, us


def _l2_normalize(x: jax.Array, eps: float = 1e-12) -> jax.Array:
    return x / (jnp.linalg.norm(x) + eps)


def spectral_normalize(w: jax.Array, u: jax.Array, update: bool = True
                       ) -> tuple[jax.Array, jax.Array]:
    """w [in, out] / its largest singular value, estimated by power iteration from u [out].

    One power-iteration step when ``update``; u and v carry no gradient (as torch's
    spectral_norm). Returns (normalised w, the new u).
    """
    u = jax.lax.stop_gradient(u)
    w_sg = jax.lax.stop_gradient(w)
    v = _l2_normalize(w_sg @ u)
    if update:
        u = _l2_normalize(w_sg.T @ v)
        v = _l2_normalize(w_sg @ u)
    sigma = v @ w @ u
    return w / sigma, u


def discriminator(disc: list[dict], us: list[jax.Array], norm: Normalizer, obs: jax.Array,
                  action: jax.Array, next_obs: jax.Array, update_us: bool = False
                  ) -> tuple[jax.Array, list[jax.Array]]:
    """D_psi(s, a, s'): obs [..., o], action [..., a], next_obs [..., o] -> ([...], new us)."""
    x = jnp.concatenate([norm.input_obs(obs), norm.norm_act(action),
                         norm.norm_delta(obs, next_obs)], -1)
    new_us = []
    for i, (layer, u) in enumerate(zip(disc, us, strict=True)):
        w, u = spectral_normalize(layer["w"], u, update_us)
        new_us.append(u)
        x = x @ w + layer["b"]
        if i < len(disc) - 1:
            x = jax.nn.relu(x)
    return x[..., 0], new_us


def count_params(tree: Any) -> int:
    return int(sum(np.prod(x.shape) for x in jax.tree_util.tree_leaves(tree)))
