"""Tests for rl2s_jax.envs.tasks: reward_fn/done_fn reproduce the envs' own reward and done."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.envs import tasks

MUJOCO = ("hopper", "walker2d", "halfcheetah", "ant")
N_ENVS = 8
N_STEPS = 40
EPS32 = float(np.finfo(np.float32).eps)


def _rollout(env, keys, actions):
    """Rolls ``env`` (unwrapped) from reset with fixed actions, in one jitted scan.

    keys [B], actions [B, T, A] -> obs, next_obs [B, T, O]; reward, done [B, T].
    """

    def one(key, acts):
        def body(state, action):
            nxt = env.step(state, action)
            return nxt, (state.obs, nxt.obs, nxt.reward, nxt.done)

        _, out = jax.lax.scan(body, env.reset(key), acts)
        return out

    return jax.tree.map(np.asarray, jax.jit(jax.vmap(one))(keys, actions))


def _actions(key, action_size, n_steps=N_STEPS):
    """[N_ENVS, T, A]: half uniform random in [-1, 1], half constant +-1 patterns (to fall)."""
    n_rand = N_ENVS // 2
    rand = jax.random.uniform(key, (n_rand, n_steps, action_size), minval=-1.0, maxval=1.0)
    signs = np.ones((N_ENVS - n_rand, action_size), np.float32)
    signs[1] = -1.0
    signs[2, ::2] = -1.0
    signs[3, 1::2] = -1.0
    const = np.broadcast_to(signs[:, None, :], (N_ENVS - n_rand, n_steps, action_size))
    return jnp.concatenate([rand, jnp.asarray(const)], axis=0)


def _valid_steps(done):
    """[B, T] bool: steps up to and including each env's first termination."""
    return (np.cumsum(done, axis=1) - done) == 0


# --------------------------------------------------------------------------------------------
# MuJoCo tasks: one env and one rollout per task, shared by the tests of that task.


@pytest.fixture(scope="module", params=MUJOCO)
def mjx_case(request, env_cache):
    task = tasks.get_task(request.param)
    env = env_cache(request.param)
    keys = jax.random.split(jax.random.PRNGKey(0), N_ENVS)
    actions = _actions(jax.random.PRNGKey(1), task.action_size)
    obs, next_obs, reward, done = _rollout(env, keys, actions)
    return dict(
        task=task,
        env=env,
        actions=np.asarray(actions),
        obs=obs,
        next_obs=next_obs,
        reward=reward,
        done=done,
    )


@pytest.mark.slow
def test_mujoco_reward_matches_env(mjx_case):
    task, env = mjx_case["task"], mjx_case["env"]
    spec = tasks._LOCO[task.name]
    obs, act, nobs = mjx_case["obs"], mjx_case["actions"], mjx_case["next_obs"]
    valid = _valid_steps(mjx_case["done"])

    pred = np.array(task.reward_fn(obs, act, nobs))
    # First step of an episode: reset ran mjx.forward, so brax's first x.pos is not one substep
    # behind q and brax's reward is lower by v0 / n_frames (see the tasks module docstring).
    pred[:, 0] -= obs[:, 0, spec.vx_idx] / spec.n_frames
    # The documented clipped-velocity case (|v_x| > 10) does not occur in this rollout.
    assert np.all(np.abs(obs[..., spec.vx_idx][valid]) < 10.0)
    assert np.all(np.abs(nobs[..., spec.vx_idx][valid]) < 10.0)

    # Forward velocity is a difference of float32 positions divided by dt: brax's own value and
    # ours each carry a rounding error of ~ulp(|x|) / dt (1.5e-5 at |x| = 1 for dt = 0.008), so
    # the tolerance is 1e-5 absolute plus 2 ulps of |x| over dt (<= 1e-5 more while |x| < 0.33;
    # observed errors are ~1e-6).
    x_scale = np.maximum(np.abs(obs[..., spec.x_idx]), np.abs(nobs[..., spec.x_idx]))
    tol = 1e-5 + 2 * EPS32 * x_scale / float(env.dt)
    err = np.abs(pred - mjx_case["reward"])
    assert np.all(err[valid] <= tol[valid]), (task.name, err[valid].max(), tol[valid].min())


@pytest.mark.slow
def test_mujoco_done_matches_env(mjx_case):
    task = mjx_case["task"]
    valid = _valid_steps(mjx_case["done"])
    pred = np.asarray(task.done_fn(mjx_case["next_obs"]))
    assert pred.dtype == np.bool_
    np.testing.assert_array_equal(pred[valid], mjx_case["done"][valid] > 0.5)
    if task.name in ("hopper", "walker2d"):
        # The constant +-1 actions make the robots fall: the check above is not vacuous.
        assert mjx_case["done"].any(), f"no termination observed for {task.name}"
        assert not mjx_case["done"].all()


@pytest.mark.slow
def test_mujoco_dt_and_sizes(mjx_case):
    task, env = mjx_case["task"], mjx_case["env"]
    assert task.dt == pytest.approx(float(env.dt), rel=1e-6)
    assert tasks._LOCO[task.name].dt == pytest.approx(float(env.dt), rel=1e-6)
    assert task.obs_size == mjx_case["obs"].shape[-1]
    assert task.action_size == env.action_size
    assert task.episode_length == 1000
    assert env.unwrapped is env  # no wrappers

    # reward_fn divides by env.dt: moving x by dx at equal velocities adds dx / env.dt.
    obs = mjx_case["obs"][0, 0]
    act = np.zeros(task.action_size, np.float32)
    moved = obs.copy()
    moved[0] += 0.01
    diff = task.reward_fn(obs, act, moved) - task.reward_fn(obs, act, obs)
    np.testing.assert_allclose(diff, 0.01 / float(env.dt), rtol=1e-4)


# --------------------------------------------------------------------------------------------
# Point mass.


@pytest.fixture(scope="module")
def pm():
    task = tasks.get_task("pointmass")
    env = task.make_env()
    keys = jax.random.split(jax.random.PRNGKey(0), N_ENVS)
    # Half the envs: random actions in [-3, 3] (exercising the clip); the other half: constant
    # pushes that cross |p| = 2 within 50 steps.
    n_steps = task.episode_length
    rand = 3.0 * jax.random.uniform(jax.random.PRNGKey(1), (N_ENVS // 2, n_steps, 1), minval=-1)
    const = jnp.ones((N_ENVS // 2, n_steps, 1)) * jnp.array([1.0, -1.0, 2.0, -5.0])[:, None, None]
    actions = jnp.concatenate([rand, const], axis=0)
    obs, next_obs, reward, done = _rollout(env, keys, actions)
    return dict(
        task=task,
        env=env,
        keys=keys,
        actions=np.asarray(actions),
        obs=obs,
        next_obs=next_obs,
        reward=reward,
        done=done,
    )


def test_pointmass_reward_done_match_env(pm):
    task = pm["task"]
    obs, act, nobs = pm["obs"], pm["actions"], pm["next_obs"]
    np.testing.assert_allclose(task.reward_fn(obs, act, nobs), pm["reward"], atol=1e-6)
    assert pm["done"].dtype == np.float32
    np.testing.assert_array_equal(task.done_fn(nobs), pm["done"] > 0.5)
    assert pm["done"][N_ENVS // 2 :].any(axis=1).all()  # every constant push terminates
    # No auto-reset: the state keeps evolving from the terminal state.
    np.testing.assert_array_equal(obs[:, 1:], nobs[:, :-1])
    np.testing.assert_allclose(nobs, tasks.pointmass_dynamics(obs, act), atol=1e-6)


def test_pointmass_dynamics_equals_env_step(pm):
    env = pm["env"]
    key_x, key_a = jax.random.split(jax.random.PRNGKey(2))
    x = jax.random.uniform(key_x, (16, 2), minval=-3.0, maxval=3.0)
    a = jax.random.uniform(key_a, (16, 1), minval=-2.0, maxval=2.0)
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), 16))
    state = state.replace(pipeline_state=x, obs=x)
    nxt = jax.jit(jax.vmap(env.step))(state, a)
    expected = tasks.pointmass_dynamics(x, a)
    np.testing.assert_allclose(nxt.obs, expected, atol=1e-6)
    np.testing.assert_allclose(nxt.pipeline_state, expected, atol=1e-6)
    # The documented closed form.
    ac = np.clip(np.asarray(a[:, 0]), -1, 1)
    v = 0.95 * np.asarray(x[:, 1]) + 0.05 * 2.0 * ac
    p = np.asarray(x[:, 0]) + 0.05 * v
    np.testing.assert_allclose(expected, np.stack([p, v], -1), atol=1e-6)


def test_pointmass_env_properties(pm):
    task, env, obs = pm["task"], pm["env"], pm["obs"]
    assert env.observation_size == task.obs_size == 2
    assert env.action_size == task.action_size == 1
    assert env.backend == "jax"
    assert env.dt == task.dt == 0.05
    assert task.episode_length == 50
    reset_obs = obs[:, 0]
    assert np.all(np.abs(reset_obs) <= 0.5) and reset_obs.std() > 0.05
    state = env.reset(jax.random.PRNGKey(0))
    assert state.done.dtype == jnp.float32 and state.reward.dtype == jnp.float32


# --------------------------------------------------------------------------------------------
# Registry and pure functions (no env needed).


def test_registry():
    assert tasks.task_names() == tuple(tasks.TASKS)
    assert set(tasks.task_names()) == {*MUJOCO, "pointmass"}
    for name in tasks.task_names():
        task = tasks.get_task(name)
        assert task.name == name
        with pytest.raises(dataclasses.FrozenInstanceError):
            task.obs_size = 0
    with pytest.raises(ValueError, match="nope") as info:
        tasks.get_task("nope")
    for name in tasks.task_names():
        assert name in str(info.value)


@pytest.mark.parametrize("name", [*MUJOCO, "pointmass"])
def test_fns_broadcast_over_batch_dims(name):
    task = tasks.get_task(name)
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(4), 3)
    obs = jax.random.normal(k1, (3, 5, task.obs_size))
    act = jax.random.uniform(k2, (3, 5, task.action_size), minval=-1)
    nobs = obs + 0.01 * jax.random.normal(k3, obs.shape)
    r = task.reward_fn(obs, act, nobs)
    d = task.done_fn(nobs)
    assert r.shape == d.shape == (3, 5)
    assert d.dtype == jnp.bool_
    np.testing.assert_allclose(r[1, 2], task.reward_fn(obs[1, 2], act[1, 2], nobs[1, 2]), rtol=1e-6)
    assert d[1, 2] == task.done_fn(nobs[1, 2])
