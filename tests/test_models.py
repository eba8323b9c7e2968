"""Model inputs: position dims left out of the networks' inputs."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.model import generator as models
from rl2s_jax.train.config import TrainConfig


def test_ignored_position_dims_do_not_change_predictions():
    rng = np.random.default_rng(0)
    obs, act = rng.normal(size=(64, 4)), rng.normal(size=(64, 2))
    nxt = obs + 0.1 * rng.normal(size=(64, 4))
    gen = models.init_generator(jax.random.PRNGKey(0), 4, 2, (16,))
    disc, us = models.init_discriminator(jax.random.PRNGKey(1), 4, 2, (16,))
    o, a, n = (jnp.asarray(x, jnp.float32) for x in (obs, act, nxt))
    shifted = o.at[:, 0].add(100.0)
    masked = models.Normalizer.from_data(obs, act, nxt, ignore_dims=(0,))
    full = models.Normalizer.from_data(obs, act, nxt)
    # shifting x moves the predicted next x by the same amount and nothing else
    m0 = models.generator_mean(gen, masked, o, a)
    m1 = models.generator_mean(gen, masked, shifted, a)
    np.testing.assert_allclose(m1 - m0, np.tile([100.0, 0, 0, 0], (64, 1)), atol=1e-4)
    d0, _ = models.discriminator(disc, us, masked, o, a, n)
    d1, _ = models.discriminator(disc, us, masked, shifted, a, n.at[:, 0].add(100.0))
    np.testing.assert_allclose(d0, d1, atol=1e-4)  # float32 rounding of x + 100
    # without the mask the same shift changes the prediction
    f0, f1 = models.generator_mean(gen, full, o, a), models.generator_mean(gen, full, shifted, a)
    assert np.abs(np.asarray(f1 - f0)[:, 1:]).max() > 1e-3
    with pytest.raises(ValueError, match="ignore_dims"):
        models.Normalizer.from_data(obs, act, nxt, ignore_dims=(4,))


def test_config_takes_the_task_position_dims():
    assert TrainConfig(task="hopper").ignore_dims == (0,)
    assert TrainConfig(task="ant").ignore_dims == (0, 1)
    assert TrainConfig(task="pointmass").ignore_dims == ()
    assert TrainConfig(task="hopper", input_ignore_dims=()).ignore_dims == ()


def test_noise_scale_zero_gives_the_mean_and_scales_the_spread():
    rng = np.random.default_rng(1)
    obs, act = rng.normal(size=(256, 3)), rng.normal(size=(256, 2))
    norm = models.Normalizer.from_data(obs, act, obs + rng.normal(size=(256, 3)))
    gen = models.init_generator(jax.random.PRNGKey(0), 3, 2, (8,))
    o, a = jnp.asarray(obs, jnp.float32), jnp.asarray(act, jnp.float32)
    key = jax.random.PRNGKey(2)
    mean = models.generator_mean(gen, norm, o, a)
    np.testing.assert_allclose(models.generator_sample(gen, norm, o, a, key, noise_scale=0.0),
                               mean, atol=1e-6)
    full = models.generator_sample(gen, norm, o, a, key) - mean
    half = models.generator_sample(gen, norm, o, a, key, noise_scale=0.5) - mean
    np.testing.assert_allclose(half, 0.5 * full, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="sim_noise"):
        TrainConfig(sim_noise=-1.0).validate()
