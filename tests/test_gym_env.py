"""The learned simulator as a Gymnasium env and vector env: the env checker, the same
trajectory as the brax SimulatorEnv and as sampling the simulator by hand, truncation, a
vector env whose every lane follows the documented per-env schedule, auto-resets included,
the ensemble's disagreement in step info (with and without history inputs), gymnasium.make
through the registered ids, and frames of the MJX tasks drawn from observations."""
import json
import os
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
from rl2s_jax.improve.gym_env import (
    SIMULATOR_ENV_ID,
    SimulatorGymEnv,
    SimulatorVectorEnv,
    TaskGymEnv,
    register_envs,
    task_env_id,
)
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.history import push_history
from rl2s_jax.model.simulator import Simulator, start_pool
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
        # The elites' disagreement at the step's (obs, action); the reward is left as it is.
        u = float(sim.disagreement(jnp.asarray(x), jnp.asarray(a)))
        assert u > 0 and info["uncertainty"] == pytest.approx(u, rel=1e-5, abs=1e-7)
        k_dyn, key = jax.random.split(key)
        x_next = np.asarray(sim.sample(jnp.asarray(x), jnp.asarray(a), k_dyn))
        np.testing.assert_allclose(obs, x_next, rtol=1e-5, atol=1e-5)
        assert reward == pytest.approx(float(TASK.reward_fn(x, a, x_next)), rel=1e-4, abs=1e-5)
        assert terminated == bool(TASK.done_fn(x_next)) and not truncated
        x = x_next
    # Seeded resets repeat; an unseeded one continues the stream (a different episode key).
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(again, np.asarray(b_reset(jax.random.PRNGKey(7)).obs))
    # One elite has no disagreement to report (it would be 0 everywhere).
    one = SimulatorGymEnv(sim.replace(n_elites=1), ds)
    one.reset(seed=7)
    assert one.step(actions[0])[4] == {}


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
        if which == "learned simulator":  # each lane's disagreement at its step's (obs, a)
            u = np.asarray(sim.disagreement(jnp.stack([s.obs for s in lanes]), jnp.asarray(a)))
            np.testing.assert_allclose(info["uncertainty"], u, rtol=1e-5, atol=1e-7)
            assert info["_uncertainty"].all() and u.min() > 0
        else:  # a dynamics function has no ensemble
            assert "uncertainty" not in info
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


def test_disagreement_in_info_sees_the_episodes_past(sim_and_data):
    """A simulator with history inputs: info["uncertainty"] is its disagreement at (obs,
    action) with the episode's past, carried by hand (new_history, then push_history)."""
    sim, ds = sim_and_data
    spec = dyn.DynamicsSpec(hidden=(16,), obs_history=2, action_history=1)
    gen = dyn.init_ensemble(jax.random.PRNGKey(3), spec, 2, 1, 3)
    hsim = Simulator(gen=gen, norm=sim.norm, rank=jnp.asarray([1, 0, 2], jnp.int32), n_elites=2,
                     task="pointmass", obs_history=2, action_history=1)
    env = SimulatorGymEnv(hsim, ds, max_episode_steps=None)
    x, _ = env.reset(seed=2)
    hist = hsim.new_history(())
    actions = np.random.default_rng(4).uniform(-1, 1, (4, 1)).astype(np.float32)
    for t, a in enumerate(actions):
        obs, _, terminated, _, info = env.step(a)
        want = float(hsim.disagreement(jnp.asarray(x), jnp.asarray(a), hist))
        assert info["uncertainty"] == pytest.approx(want, rel=1e-5, abs=1e-7), t
        if t > 0:  # the past matters: without it the value differs
            fresh = float(hsim.disagreement(jnp.asarray(x), jnp.asarray(a), hsim.new_history(())))
            assert abs(fresh - want) > 1e-4 * abs(want)
        hist = push_history(hist, jnp.asarray(x), jnp.asarray(a))
        x = obs
        assert not terminated


def test_gymnasium_make_and_the_registered_ids(pm_checkpoint, pm_files):
    """gymnasium.make("rl2s/Simulator-v0", ckpt=..., data=...) passes the env checker; the
    registration runs once (calling it again does not warn); the vector entry point and a
    task's real env ("rl2s/pointmass-v0") come through gymnasium too."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        register_envs()  # what importing the module again does: no re-registration warning
    env = gym.make(SIMULATOR_ENV_ID, ckpt=pm_checkpoint, data=pm_files["test"])
    assert isinstance(env.unwrapped, SimulatorGymEnv)
    check_env(env.unwrapped)
    obs, _ = env.reset(seed=0)
    assert "uncertainty" in env.step(env.action_space.sample())[4]
    venv = gym.make_vec(SIMULATOR_ENV_ID, num_envs=3, ckpt=pm_checkpoint, data=pm_files["test"])
    assert isinstance(venv, SimulatorVectorEnv) and venv.reset(seed=0)[0].shape == (3, 2)

    real = gym.make(task_env_id("pointmass"))
    assert isinstance(real.unwrapped, TaskGymEnv)
    assert real.spec.max_episode_steps == TASK.episode_length
    check_env(real.unwrapped)
    obs, _ = real.reset(seed=5)
    state = jax.jit(TASK.make_env().reset)(jax.random.PRNGKey(5))
    np.testing.assert_array_equal(obs, np.asarray(state.obs))
    nxt, reward, *_ = real.step(np.ones(1, np.float32))
    np.testing.assert_allclose(nxt, pointmass_dynamics(obs, np.ones(1, np.float32)), rtol=1e-6)
    assert reward == pytest.approx(float(TASK.reward_fn(obs, np.ones(1), nxt)), rel=1e-5)


def test_render_refuses_a_task_without_a_model():
    with pytest.raises(NotImplementedError, match="task 'pointmass' has no MuJoCo model"):
        SimulatorGymEnv(true_dynamics, np.zeros((1, 2)), "pointmass", render_mode="rgb_array")
    env = SimulatorGymEnv(true_dynamics, np.zeros((1, 2)), "pointmass")
    env.reset(seed=0)
    with pytest.raises(NotImplementedError, match="'pointmass'"):
        env.render()
    with pytest.raises(ValueError, match="render_mode: expected None or 'rgb_array'"):
        SimulatorGymEnv(true_dynamics, np.zeros((1, 2)), "pointmass", render_mode="human")
    with pytest.raises(NotImplementedError, match="'pointmass'"):
        TaskGymEnv("pointmass", render_mode="rgb_array")


# Run in a fresh process: MuJoCo picks its GL backend (MUJOCO_GL) when it is first imported.
# A pose (qpos, qvel) observed as the task observes it (envs/tasks.py): qpos, hopper's torso
# height lagged one physics substep, then qvel. The env's frame at that observation must be
# MuJoCo's own frame of the pose through the model's "track" camera.
_RENDER_SCRIPT = r"""
import json, sys
import numpy as np, mujoco
from etils import epath
try:
    mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8).close()
except Exception as e:  # no GL backend here
    print(json.dumps({"skip": f"{type(e).__name__}: {e}"})); sys.exit(0)
from rl2s_jax.improve.gym_env import SimulatorGymEnv

out = {}
for task, xml in (("hopper", "hopper.xml"), ("halfcheetah", "half_cheetah.xml")):
    model = mujoco.MjModel.from_xml_path(str(epath.resource_path("brax") / "envs" / "assets"
                                             / xml))
    data = mujoco.MjData(model)
    frames, diffs = [], []
    for pose in range(2):  # the model's qpos0 at rest, then a pose of its own
        rng = np.random.default_rng(pose)
        qpos = (model.qpos0 + pose * rng.uniform(-0.3, 0.3, model.nq)).astype(np.float32)
        qvel = (pose * rng.uniform(-2, 2, model.nv)).astype(np.float32)
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)
        obs = np.concatenate([qpos, qvel])
        if task == "hopper":
            obs[1] = data.xpos[1, 2] - model.opt.timestep * qvel[1]
        with mujoco.Renderer(model) as r:
            r.update_scene(data, camera="track")
            want = r.render()
        env = SimulatorGymEnv(lambda o, a, k: o, obs[None], task, render_mode="rgb_array")
        env.reset(seed=0)
        frames.append(env.render())
        env.close()
        diffs.append(float(np.abs(frames[-1].astype(int) - want).mean()))
    out[task] = {"shape": list(frames[0].shape), "dtype": str(frames[0].dtype),
                 "mean_diff_to_mujoco": diffs,
                 "poses_differ": float(np.abs(frames[0].astype(int) - frames[1]).mean())}
print(json.dumps(out))
"""


def test_render_draws_the_observed_pose_headless():
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL") or "egl"}
    proc = subprocess.run([sys.executable, "-c", _RENDER_SCRIPT], capture_output=True,
                          text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    if "skip" in result:
        pytest.skip(f"no GL backend for MuJoCo's renderer (MUJOCO_GL={env['MUJOCO_GL']}): "
                    f"{result['skip']}")
    for task, r in result.items():
        assert r["shape"] == [240, 320, 3] and r["dtype"] == "uint8", task
        assert max(r["mean_diff_to_mujoco"]) < 0.05, (task, r)  # the observed pose
        assert r["poses_differ"] > 1.0, (task, r)  # a frame shows its observation
