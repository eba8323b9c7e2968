"""The learned simulator as a Gymnasium env and vector env: the env checker, the same
trajectory as the brax SimulatorEnv and as sampling the simulator by hand, truncation, and a
vector env whose every lane follows the documented per-env schedule, auto-resets included."""
import subprocess
import sys
import warnings

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import get_task, pointmass_dynamics
from rl2s_jax.improve.gym_env import SimulatorGymEnv, SimulatorVectorEnv
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.train.checkpoint import load_simulator

TASK = get_task("pointmass")


def true_dynamics(obs, action, key):
    del key
    return pointmass_dynamics(obs, action)


@pytest.fixture(scope="module")
def sim_and_data(pm_checkpoint, pm_files):
    return load_simulator(pm_checkpoint), load_dataset(pm_files["test"])


def test_passes_the_gymnasium_env_checker(pm_checkpoint, pm_files):
    env = SimulatorGymEnv.from_checkpoint(pm_checkpoint, pm_files["test"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    notes = {str(w.message) for w in caught if "gymnasium" in str(w.filename)}
    # Only notes: learned states have no a-priori bounds; no spec to make other render modes.
    assert all("infinity" in m or "render modes" in m for m in notes), notes
    obs, info = env.reset(seed=1)
    assert obs.dtype == np.float32 and obs in env.observation_space and info == {}


def test_same_seed_same_trajectory_as_brax_env_and_by_hand(sim_and_data):
    sim, ds = sim_and_data
    env = SimulatorGymEnv(sim, ds, max_episode_steps=None)
    brax_env = SimulatorEnv(sim, start_pool(ds))
    b_reset, b_step = jax.jit(brax_env.reset), jax.jit(brax_env.step)
    pool = np.asarray(start_pool(ds))
    actions = np.random.default_rng(0).uniform(-1, 1, (15, 1)).astype(np.float32)

    obs, _ = env.reset(seed=7)
    state = b_reset(jax.random.PRNGKey(7))
    # By hand: SimulatorEnv's key schedule, the simulator's sample, the task's functions.
    k_idx, key = jax.random.split(jax.random.PRNGKey(7))
    x = pool[int(jax.random.randint(k_idx, (), 0, pool.shape[0]))]
    np.testing.assert_array_equal(obs, np.asarray(state.obs))
    np.testing.assert_array_equal(obs, x)
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        state = b_step(state, jnp.asarray(a))
        np.testing.assert_array_equal(obs, np.asarray(state.obs))
        assert reward == float(state.reward) and terminated == bool(state.done)
        k_dyn, key = jax.random.split(key)
        x_next = np.asarray(sim.sample(jnp.asarray(x), jnp.asarray(a), k_dyn))
        np.testing.assert_allclose(obs, x_next, rtol=1e-5, atol=1e-5)
        assert reward == pytest.approx(float(TASK.reward_fn(x, a, x_next)), rel=1e-4, abs=1e-5)
        assert terminated == bool(TASK.done_fn(x_next)) and not truncated
        x = x_next
    # Seeded resets repeat; an unseeded one continues the stream (a different episode key).
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(again, np.asarray(b_reset(jax.random.PRNGKey(7)).obs))


def test_truncation_and_termination():
    still = SimulatorGymEnv(true_dynamics, np.zeros((1, 2), np.float32), "pointmass",
                            max_episode_steps=5)
    still.reset(seed=0)
    flags = [still.step(np.zeros(1, np.float32))[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(False, True)]
    edge = SimulatorGymEnv(true_dynamics, np.array([[1.99, 1.0]], np.float32), "pointmass",
                           max_episode_steps=1)
    edge.reset(seed=0)
    _, _, terminated, truncated, _ = edge.step(np.ones(1, np.float32))
    assert terminated and not truncated  # a termination is not also a time-limit truncation
    with pytest.raises(ValueError, match=r"action: expected shape \(1,\)"):
        edge.step(np.zeros(2, np.float32))
    with pytest.raises(gym.error.ResetNeeded):
        SimulatorGymEnv(true_dynamics, np.zeros((1, 2)), "pointmass").step(np.zeros(1))
    with pytest.raises(ValueError, match="max_episode_steps"):
        SimulatorGymEnv(true_dynamics, np.zeros((1, 2)), "pointmass", max_episode_steps=0)


@pytest.mark.parametrize("which", ["true dynamics near the edge", "learned simulator"])
def test_vector_env_lanes_follow_the_single_env_schedule(sim_and_data, which):
    """Every lane of one jitted batched step equals the brax env stepped alone with the keys
    vec_reset / vec_step document, auto-resets and final_obs included."""
    sim, ds = sim_and_data
    if which == "learned simulator":
        dyn, pool = sim, np.asarray(start_pool(ds))
    else:  # half the starts terminate at once when pushed: resets mid-run
        dyn, pool = true_dynamics, np.array([[0.0, 0.0], [1.95, 1.0]], np.float32)
    n, limit = 5, 4
    venv = SimulatorVectorEnv(dyn, pool, n, "pointmass", max_episode_steps=limit)
    single = SimulatorEnv(dyn, pool, "pointmass")
    reset, step = jax.jit(single.reset), jax.jit(single.step)

    obs, info = venv.reset(seed=3)
    key, k = jax.random.split(jax.random.PRNGKey(3))
    lanes = [reset(kk) for kk in jax.random.split(k, n)]
    t = np.zeros(n, int)
    assert obs.shape == (n, 2) and obs in venv.observation_space and info == {}
    np.testing.assert_array_equal(obs, np.stack([s.obs for s in lanes]))
    actions = np.random.default_rng(1).uniform(0.5, 1, (9, n, 1)).astype(np.float32)
    seen = {"terminated": 0, "truncated": 0}
    for a in actions:
        obs, reward, terminated, truncated, info = venv.step(a)
        key, k = jax.random.split(key)
        restarts = jax.random.split(k, n)
        for i in range(n):
            nxt = step(lanes[i], jnp.asarray(a[i]))
            t[i] += 1
            term = bool(nxt.done > 0.5)
            trunc = not term and t[i] >= limit
            assert (terminated[i], truncated[i]) == (term, trunc), (i, t[i])
            assert reward[i] == pytest.approx(float(nxt.reward), rel=1e-5, abs=1e-6)
            if term or trunc:
                np.testing.assert_allclose(info["final_obs"][i], nxt.obs, rtol=1e-5, atol=1e-6)
                lanes[i], t[i] = reset(restarts[i]), 0
            else:
                assert "final_obs" not in info or not info["_final_obs"][i]
                lanes[i] = nxt
            np.testing.assert_allclose(obs[i], lanes[i].obs, rtol=1e-5, atol=1e-6)
        seen["terminated"] += int(terminated.sum())
        seen["truncated"] += int(truncated.sum())
    assert seen["truncated"] > 0
    if which != "learned simulator":
        assert seen["terminated"] > 0


def test_example_rolls_a_policy(pm_checkpoint, pm_files):
    proc = subprocess.run([sys.executable, "examples/gym_rollout.py", "--ckpt", pm_checkpoint,
                           "--data", pm_files["test"]], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "one episode in the learned simulator: return" in proc.stdout
    assert "16 episodes in the vector env: mean return" in proc.stdout
