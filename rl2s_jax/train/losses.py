"""Simulator losses: pure functions returning ``(loss, aux)``.

Batches are (obs [B, o], action [B, a], next_obs [B, o]) in raw units; the models normalise.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from rl2s_jax.model.dynamics import Normalizer, beta_nll
from rl2s_jax.model.generator import (
    discriminator,
    generator_dist,
    generator_log_prob,
    generator_sample,
)
from rl2s_jax.model.history import member_step_dist, push_history


def discriminator_loss(disc, us, norm: Normalizer, real: tuple, fake: tuple,
                       matmul_dtype: str = "float32"):
    """Wasserstein critic loss  E_fake[D] - E_real[D]  (lower is better for D).

    One forward pass over real and fake together updates the spectral-norm vectors once.
    ``matmul_dtype``: the critic's hidden matmuls (``discriminator``).
    -> (loss, (new us, {"d_real", "d_fake"})).
    """
    n = real[0].shape[0]
    both = [jnp.concatenate([r, f], 0) for r, f in zip(real, fake, strict=True)]
    d, new_us = discriminator(disc, us, norm, *both, update_us=True, matmul_dtype=matmul_dtype)
    d_real, d_fake = jnp.mean(d[:n]), jnp.mean(d[n:])
    return d_fake - d_real, (new_us, {"d_real": d_real, "d_fake": d_fake})


def generator_adversarial_loss(gen, disc, us, norm: Normalizer, obs, action, key, hist=None,
                               matmul_dtype: str = "float32"):
    """-E[D(s, a, s')] with s' ~ p_phi(.|s, a) reparameterised, so the gradient flows through D
    into the generator (the official RL2S one-step update). ``hist``: the rows' past for a
    member with history inputs (None: Markov); ``matmul_dtype``: the critic's hidden matmuls
    (the member's follow its parameters). -> (loss, {})."""
    next_obs = generator_sample(gen, norm, obs, action, key, hist=hist)
    d, _ = discriminator(disc, us, norm, obs, action, next_obs, update_us=False,
                         matmul_dtype=matmul_dtype)
    return -jnp.mean(d), {}


def generator_nll_loss(gen, norm: Normalizer, obs, action, next_obs, hist=None):
    """Maximum likelihood (BC): -E[log p_phi(s'|s, a)] of the normalised delta. -> (loss, {})."""
    return -jnp.mean(generator_log_prob(gen, norm, obs, action, next_obs, hist)), {}


def generator_beta_nll_loss(gen, norm: Normalizer, obs, action, next_obs, beta: float,
                            hist=None):
    """beta-NLL (Seitzer et al. 2022): each dimension's Gaussian NLL weighted by
    stop_gradient(std^(2 beta)), averaged over rows, summed over dims. beta = 0 is
    ``generator_nll_loss``; beta = 1 gives the mean the gradient of the squared error, so
    rows the model finds hard (contacts) still pull its mean instead of only widening its
    std. -> (loss, {})"""
    if not beta:
        return generator_nll_loss(gen, norm, obs, action, next_obs, hist)
    mean, log_std = generator_dist(gen, norm, obs, action, hist)
    return jnp.mean(beta_nll(mean, log_std, norm.norm_delta(obs, next_obs), beta)), {}


def tree_all_finite(tree) -> jax.Array:
    """True when every leaf of ``tree`` is finite everywhere. -> [] bool"""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.bool_(True)


def multistep_error(gen, norm: Normalizer, obs, action, next_obs, valid, obs_clip: float,
                    hist=None):
    """The member's mean prediction rolled k steps from the real obs [B, o] under the logged
    actions [B, k, a], against the logged next states [B, k, o]: the squared error in data
    stds, averaged over the seen obs dims (those of ``norm.obs_input_mask``) and over the valid
    steps j >= 1 [B, k] (step 0 is the one-step likelihood's). Gradients flow through the whole
    chain; ``hist`` (the start rows' past, None: Markov) is pushed along it. -> []"""
    mask = (jnp.ones_like(norm.obs_std) if norm.obs_input_mask is None
            else norm.obs_input_mask)

    def step(carry, xs):
        s, h = carry
        a, target = xs
        mean, _ = member_step_dist(gen, norm, s, a, h)
        nxt = norm.clip_obs(norm.next_from_delta(s, mean), obs_clip)
        err = jnp.sum(mask * ((nxt - target) / norm.obs_std) ** 2, -1) / jnp.sum(mask)
        return (nxt, None if h is None else push_history(h, s, a)), err

    _, err = jax.lax.scan(step, (obs, hist),
                          (jnp.swapaxes(action, 0, 1), jnp.swapaxes(next_obs, 0, 1)))
    w = jnp.swapaxes(valid, 0, 1)[1:].astype(jnp.float32)  # [k - 1, B]
    return jnp.sum(w * err[1:]) / jnp.maximum(jnp.sum(w), 1.0)
