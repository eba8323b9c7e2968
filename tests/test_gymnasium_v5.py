"""Gymnasium v5 data (physics/gymnasium_v5.py): the observation convention, the Dataset, the
values, the model-difference table. C MuJoCo only, except the one MJX step test (slow)."""

import mujoco
import numpy as np
import pytest

from rl2s_jax.data.dataset import load_dataset, save_dataset, validate_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.physics import gymnasium_v5 as g5
from rl2s_jax.physics.mjx_model import load_mj, physics_model, task_xml
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

TASKS = ("hopper", "walker2d", "halfcheetah", "ant")


def _one_policy(task, zoo_id):
    return index_params(load_zoo(task).params, np.array([zoo_id]))


@pytest.mark.parametrize("task", TASKS)
def test_observation_is_the_mjx_tasks_convention(task):
    """From a v5 state after a few steps, the observation's qpos puts every body of the MJX
    task's model where v5's model has it, qvel is v5's, and hopper's / walker2d's obs[1] is
    the torso height less h * vz (the lagged height)."""
    pm = physics_model(task)
    env = g5.make_v5(task)
    env.reset(seed=3)
    for _ in range(20):
        env.step(env.action_space.sample())
    v5 = env.unwrapped
    obs = g5.obs_map(pm, v5.model)(v5.data.qpos, v5.data.qvel)
    assert obs.shape == (get_task(task).obs_size,)
    here = mujoco.MjData(v5.model)
    here.qpos[:] = v5.data.qpos
    mujoco.mj_kinematics(v5.model, here)
    theirs = mujoco.MjData(pm.mj)
    theirs.qpos[:] = obs[: pm.nq]
    if task in ("hopper", "walker2d"):
        torso_z = here.xpos[1, 2]
        assert obs[1] == pytest.approx(torso_z - pm.substep * v5.data.qvel[1], abs=1e-12)
        theirs.qpos[1] = torso_z - pm.mj.body_pos[1, 2]  # the brax model's rootz
    mujoco.mj_kinematics(pm.mj, theirs)
    np.testing.assert_allclose(theirs.xpos, here.xpos[: pm.mj.nbody], atol=1e-12)
    np.testing.assert_allclose(obs[pm.nq:], v5.data.qvel, atol=0)
    env.close()


@pytest.fixture(scope="module")
def hopper_v5():
    """One Hopper zoo policy in Hopper-v5: 60 transitions (30-step episodes), 3 value
    episodes."""
    ds = g5.collect_gymnasium("hopper", _one_policy("hopper", 9), transitions_per_policy=60,
                              episode_length=30, value_episodes=3, gamma=0.9, seed=1,
                              policy_names=["hopper-009"],
                              source={"zoo": "hopper", "zoo_ids": [9]})
    return ds


def test_dataset_validates_and_says_where_it_came_from(hopper_v5, tmp_path):
    ds = hopper_v5
    validate_dataset(ds)
    back = load_dataset(save_dataset(tmp_path / "v5.npz", ds))
    np.testing.assert_array_equal(back.next_obs, ds.next_obs)
    src = ds.meta["source"]
    assert (ds.meta["task"], src["engine"], src["env_id"]) == ("hopper", "gymnasium-v5",
                                                               "Hopper-v5")
    assert src["mujoco"] == mujoco.__version__ and src["zoo_ids"] == [9]
    assert len(src["gymnasium_value"]) == 1 and len(src["gymnasium_reward_gap"]) == 1
    task = get_task("hopper")
    np.testing.assert_allclose(ds.reward, task.reward_fn(ds.obs, ds.action, ds.next_obs),
                               rtol=1e-6)
    np.testing.assert_array_equal(ds.done, task.done_fn(ds.next_obs))
    # Each episode ends at done, at the 30-step limit (truncated) or at the data's end.
    ends = np.flatnonzero(np.diff(ds.episode_id) != 0)
    assert all(ds.done[i] or (ds.truncated[i] and ds.t[i] == 29) for i in ends)
    assert not ds.done[:-1][~np.isin(np.arange(len(ds.t) - 1), ends)].any()
    assert np.all(ds.t[1:][np.diff(ds.episode_id) == 0] == ds.t[:-1][np.diff(ds.episode_id)
                                                                      == 0] + 1)


def test_values_are_the_mean_returns_of_fresh_episodes():
    """_values: per policy, the mean (discounted from t = 0) task return of episodes ended by
    done_fn or the length, its standard error, and v5's own reward summed over the same steps
    (the same episodes replayed from the same seed)."""
    import jax

    task = get_task("hopper")
    pm = physics_model("hopper")
    env = g5.make_v5("hopper")
    omap = g5.obs_map(pm, env.unwrapped.model)
    params = _one_policy("hopper", 0)  # the random initial policy: it falls within 40 steps
    one = jax.tree_util.tree_map(lambda x: np.asarray(x[0]), params)
    gamma, length = 0.9, 40
    values, gym = g5._values(env, omap, task, task.done_fn, lambda p: one, 1, 3, length,
                             gamma, np.random.default_rng(7))
    rng = np.random.default_rng(7)
    ret, dret, gret = [], [], []
    for _ in range(3):
        rec = g5._episode(env, omap, one, rng, length, task.done_fn)
        r = np.asarray(task.reward_fn(np.float32(rec["obs"]), np.float32(rec["action"]),
                                      np.float32(rec["next_obs"])), np.float64)
        assert rec["done"][-1] or len(r) == length
        ret.append(r.sum())
        dret.append(sum(x * gamma ** i for i, x in enumerate(r)))
        gret.append(sum(rec["gym_reward"]))
    assert values["value"][0] == pytest.approx(np.mean(ret), rel=1e-6)
    assert values["value_se"][0] == pytest.approx(np.std(ret, ddof=1) / np.sqrt(3), rel=1e-5)
    assert values["value_discounted"][0] == pytest.approx(np.mean(dret), rel=1e-6)
    assert gym["gymnasium_value"][0] == pytest.approx(np.mean(gret), rel=1e-9)
    env.close()


def test_bad_input_is_named():
    params = _one_policy("hopper", 9)
    with pytest.raises(ValueError, match="task_name"):
        g5.collect_gymnasium("pointmass", params, transitions_per_policy=5)
    with pytest.raises(ValueError, match="episode_length"):
        g5.collect_gymnasium("hopper", params, transitions_per_policy=5, episode_length=1001)
    with pytest.raises(ValueError, match="policy_names"):
        g5.collect_gymnasium("hopper", params, transitions_per_policy=5, policy_names=["a", "b"])


def test_model_differences_are_facts():
    """The table names what the XMLs set differently and nothing for an identical model."""
    rows = {(r["quantity"], r["element"]): (r["mjx"], r["v5"])
            for r in g5.model_differences("hopper")}
    assert rows[("opt.integrator", "")] == ("mjINT_EULER", "mjINT_RK4")
    assert rows[("opt.iterations", "")] == ("4", "100")
    assert rows[("qpos0", "rootz")] == ("0", "1.25")
    walker = {(r["quantity"], r["element"]): r for r in g5.model_differences("walker2d")}
    assert walker[("geom_friction", "foot_geom")]["v5"].startswith("1.9")
    assert ("geom_friction", "foot_left_geom") not in walker
    same = g5.model_differences("hopper", v5_model=load_mj("hopper"))
    assert [r["quantity"] for r in same] == ["precision"]
    assert "opt.integrator" in g5.print_differences("hopper", g5.model_differences("hopper"))


@pytest.mark.slow
def test_mjx_step_from_v5_states():
    """The MJX task's physics stepped from v5's states under the logged actions: with v5 run
    on the MJX task's own XML (the models agree; C float64 vs MJX float32) it lands on v5's
    next observation; on v5's own model (RK4, 100 solver iterations, every geom colliding)
    it misses by far more."""
    pm = physics_model("hopper")
    step = pm.batch_step()
    theta = np.zeros(len(pm.candidates), np.float32)
    errors = {}
    for name, kwargs in (("same", {"xml_file": task_xml("hopper")}), ("v5", {})):
        ds = g5.collect_gymnasium("hopper", _one_policy("hopper", 9), transitions_per_policy=40,
                                  value_episodes=0, seed=2, env_kwargs=kwargs)
        pred = np.asarray(step(theta, ds.obs, ds.action))
        errors[name] = np.abs(pred - ds.next_obs).max(axis=0)
        scale = np.abs(ds.next_obs - ds.obs).max(axis=0)
    # Measured: same <= 1e-6 (float32 round-off), v5 up to 0.19 (a joint velocity).
    assert np.all(errors["same"] <= 1e-5 + 1e-5 * scale), errors["same"]
    assert errors["v5"].max() > 100 * errors["same"].max(), errors


class _LinearPhysics:
    """A stand-in for PhysicsModel: next = 0.9 obs + action (obs and action of size 2), in
    contact where obs[0] > 0."""

    candidates = ()

    def step(self, theta, obs, action):
        return 0.9 * obs + action

    def step_with_contact(self, theta, obs, action):
        return self.step(theta, obs, action), obs[0] > 0


def test_script_errors_are_rmse_over_the_datas_change():
    """experiments/gymnasium_v5.py: the one-step and k-step errors against plain NumPy, on
    data whose next observation is the stand-in's plus a known offset."""
    from experiment_scripts import load_script

    from rl2s_jax.data.dataset import Dataset

    script = load_script("gymnasium_v5")
    rng = np.random.default_rng(0)
    n, bias = 30, np.array([0.1, -0.2])
    obs, act = np.zeros((n, 2)), rng.normal(size=(n, 2))
    obs[0] = rng.normal(size=2)
    for i in range(n - 1):  # one episode of true dynamics 0.9 o + a + bias
        obs[i + 1] = 0.9 * obs[i] + act[i] + bias
    nxt = 0.9 * obs + act + bias
    ds = Dataset.from_arrays({
        "obs": obs.astype(np.float32), "action": act.astype(np.float32),
        "next_obs": nxt.astype(np.float32), "reward": np.zeros(n, np.float32),
        "done": np.zeros(n, bool), "truncated": np.zeros(n, bool),
        "policy_id": np.zeros(n, np.int32), "episode_id": np.zeros(n, np.int32),
        "t": np.arange(n, dtype=np.int32)},
        {"task": None, "obs_size": 2, "action_size": 2, "n_policies": 1, "gamma": None,
         "episode_length": None, "policy_names": ["p"], "source": {}})
    k = 3
    got = script.physics_errors(_LinearPhysics(), ds, k, stride=4)
    change = np.sqrt(((nxt - obs) ** 2).mean(0))
    np.testing.assert_allclose(got["one_step"], np.abs(bias) / change, rtol=1e-4)
    contact = obs[:, 0] > 0
    err_in = np.sqrt(np.tile(bias ** 2, (contact.sum(), 1)).mean(0))
    change_in = np.sqrt(((nxt - obs)[contact] ** 2).mean(0))
    assert got["one_step_in_contact"] == pytest.approx(np.mean(err_in / change_in), rel=1e-4)
    starts = np.arange(0, n - k + 1, 4)
    # Open loop, the model misses the bias every step: after k steps by sum 0.9^j bias.
    miss = np.abs(bias) * sum(0.9 ** j for j in range(k))
    change_k = np.sqrt(((nxt[starts + k - 1] - obs[starts]) ** 2).mean(0))
    np.testing.assert_allclose(got["k_step"], miss / change_k, rtol=1e-4)
    assert got["windows"] == len(starts)
