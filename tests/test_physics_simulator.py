"""The calibrated physics as a simulator (issue 62, item 3): its JAX dynamics is the MJX step
with the actions delayed, its C-MuJoCo values equal the JAX path's on a short horizon, and on
a tiny planted Hopper case the calibrated physics values the test policies closer to the truth
than the nominal physics."""

import numpy as np
import pytest

DELAYS = [0, 2, 0]


@pytest.fixture(scope="module")
def pm():
    from rl2s_jax.physics.mjx_model import physics_model

    return physics_model("hopper")


@pytest.fixture(scope="module")
def zoo():
    from rl2s_jax.zoo.zoo import load_zoo

    return load_zoo("hopper")


def _theta(pm, name="body_mass", element="torso", factor=1.3):
    theta = np.zeros(len(pm.candidates))
    theta[pm.index(name, element)] = np.log(factor)
    return theta


def test_bad_theta_and_delays_fail_fast(pm):
    from rl2s_jax.physics.calibrated import c_values, physics_dynamics

    with pytest.raises(ValueError, match="theta: expected shape"):
        physics_dynamics(pm, np.zeros(3))
    with pytest.raises(ValueError, match="delays: expected 3 non-negative ints"):
        physics_dynamics(pm, None, [0, -1, 0])
    with pytest.raises(ValueError, match="bias: expected shape"):
        c_values(pm, pm.mj, None, None, None, None, None, n_episodes=1, horizon=1, gamma=1.0,
                 bias=np.zeros(2))


@pytest.mark.slow
def test_dynamics_is_the_mjx_step_with_delayed_actions(pm):
    import jax
    import jax.numpy as jnp

    from rl2s_jax.model.history import push_history
    from rl2s_jax.physics.calibrated import physics_dynamics

    theta = _theta(pm)
    dynamics, new_history = physics_dynamics(pm, theta, DELAYS)
    step = jax.vmap(lambda o, a: pm.step(jnp.asarray(theta, jnp.float32), o, a))
    both = jax.jit(lambda o, a, h, late: (dynamics(o, a, jax.random.PRNGKey(0), h),
                                          step(o, late)))
    rng = np.random.default_rng(0)
    obs = jnp.asarray(np.asarray(pm.state_to_obs_np(pm.mj.qpos0, np.zeros(pm.nv)))
                      + rng.uniform(-0.01, 0.01, (2, pm.obs_size)), jnp.float32)
    a0, a1, a2 = (jnp.asarray(rng.uniform(-1, 1, (2, 3)), jnp.float32) for _ in range(3))
    # a fresh episode: the delayed actuator gets 0 (nothing 2 steps back yet)
    got, want = both(obs, a2, new_history((2,)), a2.at[:, 1].set(0.0))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-6)
    # two steps in: actuator 1 gets the action of 2 steps back, the others today's
    hist = push_history(push_history(new_history((2,)), obs, a0), obs, a1)
    got, want = both(obs, a2, hist, a2.at[:, 1].set(a0[:, 1]))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-6)
    assert np.abs(np.asarray(got) - np.asarray(step(obs, a2))).max() > 1e-4  # the delay acts


@pytest.mark.slow
def test_c_values_equal_the_jax_values(pm, zoo):
    import jax

    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.physics.calibrated import c_values, calibrated_mj, physics_values
    from rl2s_jax.policy.policy import index_params

    params = index_params(zoo.params, [4, 7])
    pool = np.asarray(pm.state_to_obs_np(pm.mj.qpos0, np.zeros(pm.nv)))[None] + \
        np.random.default_rng(1).uniform(-5e-3, 5e-3, (3, pm.obs_size))
    theta, task = _theta(pm), get_task("hopper")
    theta[pm.index("geom_margin", "floor")] = 0.2  # additive, m: the foot 0.2 m off pushes
    kw = dict(n_episodes=2, horizon=4, gamma=0.99)
    key = jax.random.PRNGKey(3)
    v_jax, len_jax = physics_values(pm, theta, DELAYS, params, task, pool, key, **kw)
    v_c, len_c = c_values(pm, calibrated_mj(pm, theta), DELAYS, params, task, pool, key, **kw)
    np.testing.assert_allclose(v_c, np.asarray(v_jax), rtol=1e-4)
    np.testing.assert_array_equal(len_c, np.asarray(len_jax))


def test_calibrated_values_are_closer_to_the_planted_truth(pm, zoo):
    """A tiny planted gear change: identify on training policies' data, then the test
    policies' values (C MuJoCo, common start states and draws) in the planted, nominal and
    calibrated models."""
    import jax

    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.evaluate.metrics import value_differences
    from rl2s_jax.model.simulator import start_pool
    from rl2s_jax.physics.calibrated import c_values, calibrated_mj
    from rl2s_jax.physics.identify import FitConfig, identify
    from rl2s_jax.physics.measured import Planted, collect_measured, plant
    from rl2s_jax.policy.policy import index_params

    changes = [Planted("actuator_gear", "leg_joint", 0.7)]
    ds = collect_measured(pm, index_params(zoo.params, [4, 7, 16, 21]), changes=changes,
                          transitions_per_policy=200, episode_length=100, seed=2)
    found = identify(pm, ds, FitConfig(rows=128, bootstrap=20))
    test_p, task = index_params(zoo.params, zoo.test_ids[:5]), get_task("hopper")
    kw = dict(n_episodes=2, horizon=50, gamma=0.99)
    args = (test_p, task, start_pool(ds), jax.random.PRNGKey(0))
    mj_true, d_true, _ = plant(pm, changes)
    true, _ = c_values(pm, mj_true, d_true, *args, **kw)
    nominal, _ = c_values(pm, pm.mj, None, *args, **kw)
    calibrated, _ = c_values(pm, calibrated_mj(pm, found["theta"]), found["delays"], *args,
                             **kw)
    avd_nominal = value_differences(true, nominal)["avd"]
    avd_calibrated = value_differences(true, calibrated)["avd"]
    assert avd_nominal > 0.1
    assert avd_calibrated < 0.1 * avd_nominal
