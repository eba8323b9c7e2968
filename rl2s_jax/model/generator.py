"""The simulator's networks: the generator (one member of the dynamics-model family of
``rl2s_jax.model.dynamics``) and a spectrally normalised discriminator.

Everything is a plain pytree and a pure function, written for one example and batched by the
caller (any leading axes work). Shapes use o = obs size, a = action size.

- ``Normalizer`` (defined in ``rl2s_jax.model.dynamics``): fixed statistics of obs, action and
  delta = s' - s, computed once from data. It is part of the simulator, so a checkpoint is
  usable without the training data.
- Generator p_phi(s'|s,a): MLP over normalised (s, a) -> mean and log-std of the normalised
  delta; s' = s + delta_mean + delta_std * delta_n. The ``generator_*`` functions here take ONE
  member: a family member dict (``dynamics.init_member``) or a bare list of MLP layers (the
  generator before the family, ``init_generator``). Ensembles: ``rl2s_jax.model.dynamics`` and
  ``rl2s_jax.simulate.Simulator``.
- Discriminator D_psi(s, a, s'): MLP over normalised (s, a, delta), every layer spectrally
  normalised (one power-iteration step per discriminator update, as torch's spectral_norm).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.model.dynamics import (
    LOG_STD_MAX,
    LOG_STD_MIN,
    Normalizer,
    bounded_log_std,
    gaussian_nll,
    matmul,
    relu_mlp,
)
from rl2s_jax.model.history import History, member_step_dist
from rl2s_jax.policy.policy import init_mlp

__all__ = ["LOG_STD_MAX", "LOG_STD_MIN", "Normalizer", "count_params", "discriminator",
           "generator_dist", "generator_log_prob", "generator_mean", "generator_sample",
           "init_discriminator", "init_generator", "spectral_normalize"]

_relu_mlp = relu_mlp
_bounded_log_std = bounded_log_std


# ---------------------------------------------------------------- generator


def init_generator(key: jax.Array, obs_size: int, action_size: int,
                   hidden: Sequence[int] = (512, 512, 512, 512)) -> list[dict]:
    """MLP [o + a] -> hidden -> [2 o] (mean and raw log-std of the normalised delta): the layers
    of a default family member (``dynamics.init_member(key, DynamicsSpec(hidden), o, a)``)."""
    return init_mlp(key, [obs_size + action_size, *hidden, 2 * obs_size], last_scale=0.01)


def _member(gen) -> dict:
    return {"layers": gen} if isinstance(gen, list | tuple) else gen


def generator_dist(gen, norm: Normalizer, obs: jax.Array, action: jax.Array,
                   hist: History | None = None) -> tuple[jax.Array, jax.Array]:
    """Gaussian over the normalised delta.

    obs [..., o], action [..., a], hist: the steps' past for a member with history inputs
    (``rl2s_jax.model.history``; None: Markov) -> (mean, log_std), each [..., o].
    """
    return member_step_dist(_member(gen), norm, obs, action, hist)


def generator_sample(gen, norm: Normalizer, obs: jax.Array, action: jax.Array,
                     key: jax.Array, obs_clip: float | None = None,
                     noise_scale: float = 1.0, hist: History | None = None) -> jax.Array:
    """A reparameterised next-state sample s' ~ p_phi(.|s, a). -> [..., o]

    ``obs_clip`` bounds the normalised next state to [-obs_clip, obs_clip] so long simulated
    rollouts stay finite; leave it None where gradients must flow (the generator loss).
    ``noise_scale`` multiplies the std (0: the mean, for deterministic real systems).
    """
    mean, log_std = generator_dist(gen, norm, obs, action, hist)
    return sample_next(norm, obs, mean, log_std, key, obs_clip, noise_scale)


def sample_next(norm: Normalizer, obs, mean, log_std, key, obs_clip: float | None = None,
                noise_scale: float = 1.0):
    """s' = s + delta from N(mean, exp(log_std) * noise_scale) over the normalised delta,
    clipped to +-obs_clip data stds (None: not clipped). -> [..., o]"""
    noise = jax.random.normal(key, mean.shape, mean.dtype)
    delta_n = mean + noise_scale * jnp.exp(log_std) * noise
    return norm.clip_obs(norm.next_from_delta(obs, delta_n), obs_clip)


def generator_mean(gen, norm: Normalizer, obs: jax.Array, action: jax.Array,
                   hist: History | None = None) -> jax.Array:
    """The generator's mean next state (no noise). -> [..., o]"""
    mean, _ = generator_dist(gen, norm, obs, action, hist)
    return norm.next_from_delta(obs, mean)


def generator_log_prob(gen, norm: Normalizer, obs: jax.Array, action: jax.Array,
                       next_obs: jax.Array, hist: History | None = None) -> jax.Array:
    """log p_phi(s'|s,a) of the normalised delta, summed over dims. -> [...]

    It is the density of delta_n, not of s' (they differ by the constant sum(log delta_std)).
    """
    mean, log_std = generator_dist(gen, norm, obs, action, hist)
    return -gaussian_nll(mean, log_std, norm.norm_delta(obs, next_obs))


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
                  action: jax.Array, next_obs: jax.Array, update_us: bool = False,
                  matmul_dtype: str = "float32") -> tuple[jax.Array, list[jax.Array]]:
    """D_psi(s, a, s'): obs [..., o], action [..., a], next_obs [..., o] -> ([...], new us).
    ``matmul_dtype`` "bfloat16": the hidden layers' matmuls in bf16 with float32 accumulation
    (``dynamics.matmul``; the spectral normalisation and the output layer stay float32)."""
    x = jnp.concatenate([norm.input_obs(obs), norm.norm_act(action),
                         norm.norm_delta(obs, next_obs)], -1)
    new_us = []
    for i, (layer, u) in enumerate(zip(disc, us, strict=True)):
        w, u = spectral_normalize(layer["w"], u, update_us)
        new_us.append(u)
        if i < len(disc) - 1:
            x = jax.nn.relu(matmul(x, w, matmul_dtype) + layer["b"])
        else:
            x = x @ w + layer["b"]
    return x[..., 0], new_us


def count_params(tree: Any) -> int:
    return int(sum(np.prod(x.shape) for x in jax.tree_util.tree_leaves(tree)))
