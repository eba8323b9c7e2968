"""History inputs in the simulator that users train, save, evaluate and fine-tune in
(rl2s_jax.model.history; TrainConfig.action_history / obs_history / time_inputs)."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_train import BIASES, GAMMA
from test_train import _policies as _pm_policies

from rl2s_jax.data.collect import collect
from rl2s_jax.data.episodes import from_dataset
from rl2s_jax.diagnose.model import history as diagnosis_history
from rl2s_jax.diagnose.planted_mjx import make_planted_env
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.simulator import one_step_errors
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model import history as H
from rl2s_jax.model.simulator import simulator_returns, start_pool
from rl2s_jax.train.checkpoint import Checkpointer, load_simulator
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.step import init, simulator, train_steps

TASK = get_task("pointmass")
MARKOV = TrainConfig.small(task="pointmass", method="bc", vd_horizon=50, vd_every=5)
DELAYED = dataclasses.replace(MARKOV, action_history=1, time_inputs=("step",))
_init = jax.jit(init, static_argnums=1)
_steps = jax.jit(train_steps, static_argnums=2)


@pytest.fixture(scope="module")
def delayed():
    """Pointmass whose actuator applies the previous step's action (a planted 1-step delay):
    training and held-out recordings of the same six policies."""
    policies = _pm_policies(BIASES)
    env = make_planted_env("pointmass", "delay", lag=1)
    kw = dict(transitions_per_policy=600, envs_per_policy=4,
              episode_length=TASK.episode_length, task="pointmass", gamma=GAMMA,
              progress=False)
    train = collect(env, policies, key=jax.random.PRNGKey(0), value_episodes=4, **kw)
    held = collect(env, policies, key=jax.random.PRNGKey(1), value_episodes=0, **kw)
    return train, held, policies


@pytest.fixture(scope="module")
def trained(delayed):
    """(Markov state, delayed-input state, data) after 40 steps of BC each."""
    ds, _, policies = delayed
    out = {}
    for name, cfg in (("markov", MARKOV), ("history", DELAYED)):
        data = make_train_data(ds, policies, cfg)
        state, _ = _steps(_init(jax.random.PRNGKey(0), cfg, data), data, 40)
        out[name] = (state, data)
    return out


def test_logged_history_matches_diagnosis_and_numpy(delayed):
    """Training's logged past (``logged_history``, ``TrainData.row_history``) is the input
    diagnosis fits: the same arrays as ``diagnose.model.history`` and a plain loop."""
    ds, _, policies = delayed
    rows = np.r_[0, 1, 2, 57, 300, ds.n_transitions - 1]
    h = H.logged_history(ds, rows, obs_history=2, action_history=3)
    eps = from_dataset(ds, position_dims=())
    for x, k, past, valid in ((ds.action, 3, h.past_act, h.past_act_valid),
                              (ds.obs, 2, h.past_obs, h.past_obs_valid)):
        ref, ref_valid = diagnosis_history(eps, np.asarray(x, np.float32), k, rows)
        np.testing.assert_array_equal(np.asarray(past), ref)
        np.testing.assert_array_equal(np.asarray(valid), ref_valid)
    t, pid, eid = (np.asarray(v) for v in (ds.t, ds.policy_id, ds.episode_id))
    for i, r in enumerate(rows):  # the loop: walk back while the episode goes on
        for j in range(3):
            src = r - 1 - j
            ok = (src >= 0 and pid[src] == pid[r] and eid[src] == eid[r]
                  and t[src] == t[r] - 1 - j)
            assert bool(h.past_act_valid[i, j]) == ok
            want = np.asarray(ds.action)[src] if ok else 0.0
            np.testing.assert_array_equal(np.asarray(h.past_act[i, j]), want)
    np.testing.assert_array_equal(np.asarray(h.t), t[rows])
    data = make_train_data(ds, policies, dataclasses.replace(DELAYED, action_history=3,
                                                            holdout_frac=0.0))
    # with no held-out episodes the training rows are the Dataset's, grouped by policy
    order = np.argsort(pid, kind="stable")
    idx = np.asarray([0, 5, 333, 1999])
    mine = data.row_history(jnp.asarray(idx))
    ref = H.logged_history(ds, order[idx], obs_history=0, action_history=3)
    np.testing.assert_array_equal(np.asarray(mine.past_act), np.asarray(ref.past_act))
    np.testing.assert_array_equal(np.asarray(mine.t), np.asarray(ref.t))


def test_push_and_reset_keep_newest_first():
    h = H.empty_history((2,), 3, 1, obs_history=2, action_history=2)
    h = H.push_history(h, jnp.ones((2, 3)), jnp.full((2, 1), 1.0))
    h = H.push_history(h, 2 * jnp.ones((2, 3)), jnp.full((2, 1), 2.0))
    h = H.push_history(h, 3 * jnp.ones((2, 3)), jnp.full((2, 1), 3.0))
    np.testing.assert_array_equal(np.asarray(h.past_act[0, :, 0]), [3.0, 2.0])
    np.testing.assert_array_equal(np.asarray(h.t), [3, 3])
    r = H.reset_history(h, jnp.asarray([True, False]))
    assert not bool(r.past_act_valid[0].any()) and int(r.t[0]) == 0
    np.testing.assert_array_equal(np.asarray(r.past_obs[1, :, 0]), [3.0, 2.0])


def test_past_action_input_learns_the_planted_delay(trained):
    """On a 1-step actuation delay, members that see the previous action fit held-out
    episodes far better than Markov ones (both trained 40 BC steps from the same seed); the
    score of ``rl2s evaluate`` (``one_step_errors``) on fresh episodes says the same."""
    nll = {k: float(np.mean(np.asarray(s.heldout_nll))) for k, (s, _) in trained.items()}
    assert nll["history"] < nll["markov"] - 1.0, nll


def test_one_step_errors_rank_the_delay_model_first(trained, delayed):
    _, held, _ = delayed
    err = {k: one_step_errors(simulator(s), held) for k, (s, _) in trained.items()}
    assert err["history"]["heldout_nll"] < err["markov"]["heldout_nll"] - 1.0, err
    assert err["history"]["heldout_mse"] < err["markov"]["heldout_mse"], err
    assert err["history"]["one_step_rows"] == held.n_transitions


def test_history_simulator_needs_its_past_and_carries_it(trained, delayed):
    ds, _, policies = delayed
    sim = simulator(trained["history"][0])
    obs, act = jnp.zeros((4, 2)), jnp.zeros((4, 1))
    with pytest.raises(ValueError, match="hist"):
        sim.sample(obs, act, jax.random.PRNGKey(0))
    env = SimulatorEnv(sim, start_pool(ds))
    s0 = env.reset(jax.random.PRNGKey(3))
    s1 = env.step(s0, jnp.asarray([0.7]))
    s2 = env.step(s1, jnp.asarray([-0.4]))
    hist = s2.pipeline_state[1]
    np.testing.assert_allclose(np.asarray(hist.past_act[0]), [-0.4])
    assert int(hist.t) == 2
    # the env's step is the simulator's step with that past
    k_dyn, _ = jax.random.split(s1.info["rng"])
    want = sim.sample(s1.obs, jnp.asarray([-0.4]), k_dyn, s1.pipeline_state[1])
    np.testing.assert_allclose(np.asarray(s2.obs), np.asarray(want), rtol=1e-6)
    # value rollouts feed the past: zeroing the members' weights on the past action changes
    # the simulated returns (a rollout that never pushed its past would feed zeros there)
    ret, _ = simulator_returns(sim, TASK, policies, start_pool(ds), jax.random.PRNGKey(5),
                               n_episodes=4, horizon=20, gamma=GAMMA)
    o, a = 2, 1
    past_rows = slice(o + a, o + a + a)  # inputs: obs o, action a, past action a, ...

    def zero_past(gen):
        w = gen["layers"][0]["w"]
        return {**gen, "layers": [{**gen["layers"][0], "w": w.at[:, past_rows, :].set(0.0)},
                                  *gen["layers"][1:]]}
    blind = sim.replace(gen=zero_past(sim.gen))
    ret_blind, _ = simulator_returns(blind, TASK, policies, start_pool(ds),
                                     jax.random.PRNGKey(5), n_episodes=4, horizon=20,
                                     gamma=GAMMA)
    assert np.abs(np.asarray(ret) - np.asarray(ret_blind)).max() > 1e-3


def test_history_checkpoint_loads_with_its_inputs(trained, delayed, tmp_path):
    state, _ = trained["history"]
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1}})
    ck.close()
    loaded = load_simulator(tmp_path / "ck")
    assert (loaded.action_history, loaded.time_inputs) == (1, ("step",))
    _, held, _ = delayed
    assert one_step_errors(loaded, held) == one_step_errors(simulator(state), held)


def test_adversarial_step_trains_a_history_simulator(delayed):
    """WGAIL with history inputs: the simulated envs, the buffer and both losses carry the
    past; a few steps stay finite and the buffer's past is a pushed one (gail, no VD: the
    CVaR measurement's rollouts carry the past as rl2s's do, tested above)."""
    ds, _, policies = delayed
    cfg = dataclasses.replace(DELAYED, method="gail", vd_every=0, updates_per_step=1,
                              disc_updates=1, sim_envs=8, sim_steps=2, buffer_size=256)
    data = make_train_data(ds, policies, cfg)
    state, m = _steps(_init(jax.random.PRNGKey(0), cfg, data), data, 4)
    assert bool(np.all(np.asarray(m["finite"])))
    assert state.buffer_hist.past_act.shape == (cfg.buffer_size, 1, 1)
    assert int(state.sim.hist.t.max()) >= 1


def test_bad_history_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="time_inputs"):
        TrainConfig.small(time_inputs=("order",)).validate()
    with pytest.raises(ValueError, match="action_history"):
        TrainConfig.small(action_history=-1).validate()
    with pytest.raises(ValueError, match="termination"):
        TrainConfig.small(action_history=2, termination="predictive").validate()
