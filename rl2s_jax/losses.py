"""Simulator losses: pure functions returning ``(loss, aux)``.

Batches are (obs [B, o], action [B, a], next_obs [B, o]) in raw units; the models normalise.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from rl2s_jax.dynamics import beta_nll
from rl2s_jax.models import (
    Normalizer,
    discriminator,
    generator_dist,
    generator_log_prob,
    generator_sample,
)


def discriminator_loss(disc, us, norm: Normalizer, real: tuple, fake: tuple):
    """Wasserstein critic loss  E_fake[D] - E_real[D]  (lower is better for D).

    One forward pass over real and fake together updates the spectral-norm vectors once.
    -> (loss, (new us, {"d_real", "d_fake"})).
    """
    n = real[0].shape[0]
    both = [jnp.concatenate([r, f], 0) for r, f in zip(real, fake, strict=True)]
    d, new_us = discriminator(disc, us, norm, *both, update_us=True)
    d_real, d_fake = jnp.mean(d[:n]), jnp.mean(d[n:])
    return d_fake - d_real, (new_us, {"d_real": d_real, "d_fake": d_fake})


def generator_adversarial_loss(gen, disc, us, norm: Normalizer, obs, action, key):
    """-E[D(s, a, s')] with s' ~ p_phi(.|s, a) reparameterised, so the gradient flows through D
    into the generator (the official RL2S one-step update). -> (loss, {})."""
    next_obs = generator_sample(gen, norm, obs, action, key)
    d, _ = discriminator(disc, us, norm, obs, action, next_obs, update_us=False)
    return -jnp.mean(d), {}


def generator_nll_loss(gen, norm: Normalizer, obs, action, next_obs):
    """Maximum likelihood (BC): -E[log p_phi(s'|s, a)] of the normalised delta. -> (loss, {})."""
    return -jnp.mean(generator_log_prob(gen, norm, obs, action, next_obs)), {}


def generator_beta_nll_loss(gen, norm: Normalizer, obs, action, next_obs, beta: float):
    """beta-NLL (Seitzer et al. 2022): each dimension's Gaussian NLL weighted by
    stop_gradient(std^(2 beta)), averaged over rows, summed over dims. beta = 0 is
    ``generator_nll_loss``; beta = 1 gives the mean the gradient of the squared error, so
    rows the model finds hard (contacts) still pull its mean instead of only widening its
    std. -> (loss, {})"""
    if not beta:
        return generator_nll_loss(gen, norm, obs, action, next_obs)
    mean, log_std = generator_dist(gen, norm, obs, action)
    return jnp.mean(beta_nll(mean, log_std, norm.norm_delta(obs, next_obs), beta)), {}


def tree_all_finite(tree) -> jax.Array:
    """True when every leaf of ``tree`` is finite everywhere. -> [] bool"""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.bool_(True)
