"""Policy improvement: the simulator as a brax Env, SAC fine-tuning, improvement metrics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs import training as brax_training

from rl2s_jax import policies as pol
from rl2s_jax.improve import improve_policies, improvement_metrics, measure_improvement
from rl2s_jax.models import Normalizer, init_generator
from rl2s_jax.sac import Buffer, SACConfig, make_sac
from rl2s_jax.sim_env import SimulatorEnv
from rl2s_jax.simulate import Simulator
from rl2s_jax.tasks import PointMass, get_task, pointmass_dynamics

TASK = get_task("pointmass")


def _true_dynamics(obs, action, key):
    del key
    return pointmass_dynamics(obs, action)


def _pool(n=16, seed=0):
    return np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 2)).astype(np.float32)


def _policies(biases, hidden=(8,)):
    """Policies whose pre-tanh mean is pushed by a constant bias (as in test_collect)."""
    ps = []
    for i, b in enumerate(biases):
        p = pol.init_policy(jax.random.PRNGKey(i), 2, 1, hidden=hidden)
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:1].set(b)
        ps.append(p)
    return pol.stack_params(ps)


def test_sim_env_true_dynamics_matches_direct_rollout():
    pool = _pool()
    env = SimulatorEnv(_true_dynamics, pool, "pointmass")
    assert (env.observation_size, env.action_size, env.backend) == (2, 1, "jax")
    B, T = 4, 50
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), B))
    assert state.obs.shape == (B, 2) and state.obs.dtype == jnp.float32
    assert all(any(np.array_equal(o, s) for s in pool) for o in np.asarray(state.obs))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (T, B, 1), minval=-1.5, maxval=1.5)
    actions = actions.at[:, 0].set(1.0)  # env 0 is pushed off the edge: done fires

    def body(s, a):
        nxt = jax.vmap(env.step)(s, a)
        return nxt, (s.obs, nxt.obs, nxt.reward, nxt.done)

    _, (obs, next_obs, reward, done) = jax.jit(lambda s: jax.lax.scan(body, s, actions))(state)
    # the same rollout applying the task's functions directly
    o = np.asarray(state.obs)
    for t in range(T):
        np.testing.assert_allclose(obs[t], o, rtol=1e-5, atol=1e-6)  # jit may fuse (FMA)
        o2 = np.asarray(pointmass_dynamics(jnp.asarray(o), actions[t]))
        np.testing.assert_allclose(next_obs[t], o2, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(reward[t], TASK.reward_fn(o, actions[t], o2), atol=1e-5)
        np.testing.assert_array_equal(done[t], np.asarray(TASK.done_fn(next_obs[t]), np.float32))
        o = o2
    assert done[:, 0].max() == 1.0 and reward.dtype == done.dtype == jnp.float32


def test_sim_env_under_brax_training_wrap():
    # one start close to the right edge: pushing right ends the episode on the first step
    pool = np.array([[1.99, 0.2]], np.float32)
    L, B = 5, 2
    env = brax_training.wrap(SimulatorEnv(_true_dynamics, pool, TASK), episode_length=L,
                             action_repeat=1)
    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), B))
    step = jax.jit(env.step)
    action = jnp.array([[1.0], [-1.0]])  # env 0 terminates at once, env 1 runs to the limit
    dones, truncs, obs = [], [], []
    for _ in range(2 * L):
        state = step(state, action)
        dones.append(np.asarray(state.done))
        truncs.append(np.asarray(state.info["truncation"]))
        obs.append(np.asarray(state.obs))
    dones, truncs, obs = np.array(dones), np.array(truncs), np.array(obs)
    np.testing.assert_array_equal(dones[:, 0], 1.0)  # every step of env 0 terminates
    np.testing.assert_array_equal(truncs[:, 0], 0.0)
    np.testing.assert_allclose(obs[:, 0], np.broadcast_to(pool[0], (2 * L, 2)))  # auto-reset
    assert dones[:, 1].tolist() == [0, 0, 0, 0, 1] * 2  # the time limit, then again
    assert truncs[:, 1].tolist() == [0, 0, 0, 0, 1] * 2
    np.testing.assert_allclose(obs[L - 1, 1], pool[0])  # reset to its start after the limit
    assert not np.allclose(obs[L - 2, 1], pool[0])


def _learned_simulator():
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, (256, 2)).astype(np.float32)
    action = rng.uniform(-1, 1, (256, 1)).astype(np.float32)
    nxt = np.asarray(pointmass_dynamics(obs, action))
    gen = init_generator(jax.random.PRNGKey(0), 2, 1, hidden=(16, 16))
    gen[-1]["w"] = gen[-1]["w"] * 100.0  # a visible log-std, so sample != mean
    return Simulator(gen=gen, norm=Normalizer.from_data(obs, action, nxt), task="pointmass")


def test_sim_env_with_learned_simulator():
    sim = _learned_simulator()
    pool = _pool()
    B = 3
    keys = jax.random.split(jax.random.PRNGKey(3), B)
    action = jnp.full((B, 1), 0.5)
    stoch, det = SimulatorEnv(sim, pool), SimulatorEnv(sim, pool, deterministic=True)
    assert stoch.task.name == "pointmass"  # from sim.task
    out = {}
    for name, env in (("stoch", stoch), ("det", det)):
        s0 = jax.vmap(env.reset)(keys)
        s1 = jax.jit(jax.vmap(env.step))(s0, action)
        s2 = jax.jit(jax.vmap(env.step))(s1, action)
        for s in (s1, s2):
            assert s.obs.shape == (B, 2) and s.obs.dtype == jnp.float32
            assert s.pipeline_state.shape == (B, 2)
            assert s.reward.shape == s.done.shape == (B,)
            assert s.reward.dtype == s.done.dtype == jnp.float32
            assert s.info["rng"].shape == s0.info["rng"].shape
        assert not np.array_equal(s1.info["rng"], s0.info["rng"])  # the key moves on
        np.testing.assert_allclose(s1.reward, TASK.reward_fn(s0.obs, action, s1.obs), rtol=1e-5)
        out[name] = (s0, s1)
    s0, s1 = out["det"]
    np.testing.assert_allclose(s1.obs, sim.mean(s0.obs, action), rtol=1e-6)
    s0, s1 = out["stoch"]
    np.testing.assert_array_equal(s0.obs, out["det"][0].obs)  # same keys, same starts
    k_dyn = jax.vmap(lambda k: jax.random.split(k)[0])(s0.info["rng"])
    np.testing.assert_allclose(s1.obs, jax.vmap(sim.sample)(s0.obs, action, k_dyn), rtol=1e-6)
    assert not np.allclose(s1.obs, sim.mean(s0.obs, action))


def test_sim_env_bad_input():
    sim = _learned_simulator()
    with pytest.raises(ValueError, match="start_pool"):
        SimulatorEnv(sim, np.zeros((4, 3)))
    with pytest.raises(ValueError, match="start_pool"):
        SimulatorEnv(sim, np.zeros((0, 2)))
    with pytest.raises(ValueError, match="start_pool"):
        SimulatorEnv(sim, np.full((2, 2), np.nan))
    with pytest.raises(ValueError, match="task"):
        SimulatorEnv(_true_dynamics, _pool())
    with pytest.raises(ValueError, match="deterministic"):
        SimulatorEnv(_true_dynamics, _pool(), TASK, deterministic=True)
    with pytest.raises(ValueError, match="unknown task"):
        SimulatorEnv(_true_dynamics, _pool(), "nope")


def test_buffer_is_a_ring():
    buf = Buffer.create(5, 2, 1)
    for i in range(3):  # 9 rows into 5 slots: rows 4..8 remain
        rows = jnp.arange(3 * i, 3 * i + 3, dtype=jnp.float32)
        buf = buf.add(jnp.stack([rows, rows], -1), rows[:, None], rows, jnp.stack([rows, rows], -1),
                      jnp.zeros(3))
    assert int(buf.size) == 5 and int(buf.ptr) == 4
    assert sorted(np.asarray(buf.reward).tolist()) == [4, 5, 6, 7, 8]
    obs, action, reward, _, _ = buf.sample(jax.random.PRNGKey(0), 64)
    assert set(np.asarray(reward).tolist()) <= {4, 5, 6, 7, 8}
    np.testing.assert_array_equal(obs[:, 0], reward)
    np.testing.assert_array_equal(action[:, 0], reward)


def test_sac_config_and_actor_checked():
    env = SimulatorEnv(_true_dynamics, _pool(), TASK)
    with pytest.raises(ValueError, match="tau"):
        make_sac(env, SACConfig(tau=0.0))
    with pytest.raises(ValueError, match="buffer_size"):
        make_sac(env, SACConfig(buffer_size=100, n_envs=16, warmup_steps=64))
    with pytest.raises(ValueError, match="warmup_steps"):
        make_sac(env, SACConfig(warmup_steps=0))
    with pytest.raises(ValueError, match="AutoResetWrapper"):
        make_sac(brax_training.AutoResetWrapper(env), SACConfig())
    sac = make_sac(env, SACConfig(n_envs=2, warmup_steps=2, buffer_size=64, hidden=(4,)))
    with pytest.raises(ValueError, match="actor_params"):
        sac.init(jax.random.PRNGKey(0), _policies([0.0, 0.0]))  # a stack, not one policy


def test_sac_fine_tuning_improves_poor_policies():
    """Two policies that push the mass off either edge (real return < 0) learn to hold it near
    the centre (about +45 of the 50 possible) by SAC in the true-dynamics SimulatorEnv."""
    before = _policies([3.0, -3.0])
    cfg = SACConfig(n_envs=8, batch_size=64, hidden=(32, 32), warmup_steps=16,
                    buffer_size=10_000, episode_length=TASK.episode_length, updates_per_step=2,
                    learning_rate=1e-3)
    after, metrics = improve_policies(_true_dynamics, TASK, _pool(64), before,
                                      jax.random.PRNGKey(0), cfg, n_iterations=2000,
                                      chunk_iterations=1000)
    assert metrics["q_loss"].shape == (2, 2000)
    assert np.all(np.isfinite(np.asarray(metrics["q_loss"])))
    # the result is a policy of the same layout, its frozen normaliser untouched
    assert jax.tree_util.tree_structure(after) == jax.tree_util.tree_structure(before)
    np.testing.assert_array_equal(after["obs_std"], before["obs_std"])
    res = measure_improvement(PointMass(), before, after, jax.random.PRNGKey(1), n_episodes=16,
                              episode_length=TASK.episode_length, gamma=0.99)
    assert np.all(res["c0"] < 0), res
    assert np.all(res["c1"] > 30.0), res  # seeds 0-3 give 45-49
    assert np.all(res["c1"] - res["c0"] > 25.0), res
    assert res["mpi"] > 1.0 and res["api"] >= res["mpi"]


def test_improvement_metrics_hand_computed():
    m = improvement_metrics([10.0, -20.0, 4.0], [15.0, -10.0, 3.0])
    np.testing.assert_allclose(m["I"], [0.5, 0.5, -0.25])  # |c0|: -20 -> -10 is +50%
    assert m["mpi"] == pytest.approx(-0.25)
    assert m["api"] == pytest.approx(0.25)
    m = improvement_metrics(np.array([2.0]), np.array([2.0]))
    assert m["mpi"] == m["api"] == 0.0


def test_improvement_metrics_bad_input():
    with pytest.raises(ValueError, match="c0"):
        improvement_metrics([1.0, 0.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="c1"):
        improvement_metrics([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="c1"):
        improvement_metrics([1.0], [np.nan])
    with pytest.raises(ValueError, match="c0"):
        improvement_metrics(np.ones((2, 2)), np.ones((2, 2)))
    with pytest.raises(ValueError, match="c0"):
        improvement_metrics([], [])
    with pytest.raises(ValueError, match="n_iterations"):
        improve_policies(_true_dynamics, TASK, _pool(), _policies([0.0]), jax.random.PRNGKey(0),
                         SACConfig(), n_iterations=0)
