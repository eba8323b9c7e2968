"""History inputs in the simulator that users train, save, evaluate and fine-tune in
(rl2s_jax.model.history; TrainConfig.dynamics.action_history / obs_history / time_inputs)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs import base as brax_base
from test_train import BIASES, GAMMA
from test_train import _policies as _pm_policies

from rl2s_jax.data.collect import collect
from rl2s_jax.data.dataset import concat_datasets
from rl2s_jax.data.episodes import from_dataset
from rl2s_jax.diagnose.planted_mjx import make_planted_env
from rl2s_jax.envs.tasks import POINTMASS_DT, PointMass, get_task
from rl2s_jax.evaluate.scores import one_step_errors
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model import history as H
from rl2s_jax.model.simulator import simulator_returns, start_pool
from rl2s_jax.train.checkpoint import Checkpointer, load_simulator
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import heldout_mask, make_train_data
from rl2s_jax.train.step import init, simulator, train_steps

TASK = get_task("pointmass")
MARKOV = TrainConfig.small().override({"task": "pointmass", "method": "bc", "vd.horizon": 50,
                                       "vd.every": 5})
DELAYED = MARKOV.override({"dynamics.action_history": 1, "dynamics.time_inputs": ("step",)})
ORDERED = MARKOV.override({"dynamics.time_inputs": ("order",)})
DRIFT_GAINS = (0.5, 2.0)  # the actuator gain of the first and the second half of the recording
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


class GainPointMass(PointMass):
    """Pointmass whose actuator gain is ``gain`` (the task's is 1): v' gets
    (gain - 1) dt 2 clip(a) more than the task's."""

    def __init__(self, gain: float):
        super().__init__()
        self.gain = float(gain)

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        nxt = super().step(state, action)
        dv = (self.gain - 1.0) * POINTMASS_DT * 2.0 * jnp.clip(action[0], -1, 1)
        x = nxt.obs + jnp.stack([POINTMASS_DT * dv, dv])
        return nxt.replace(pipeline_state=x, obs=x)


@pytest.fixture(scope="module")
def drift():
    """A Pointmass recording whose actuator drifts: the six policies recorded at gain 0.5,
    then again at gain 2.0, one Dataset in recording order (``concat_datasets``), and
    (Markov state, order state, data of each) after 40 BC steps from the same seed."""
    policies = _pm_policies(BIASES)
    kw = dict(transitions_per_policy=300, envs_per_policy=2,
              episode_length=TASK.episode_length, task="pointmass", gamma=GAMMA,
              progress=False, value_episodes=4)
    ds = concat_datasets([collect(GainPointMass(g), policies, key=jax.random.PRNGKey(i), **kw)
                          for i, g in enumerate(DRIFT_GAINS)])
    out = {}
    for name, cfg in (("markov", MARKOV), ("order", ORDERED)):
        data = make_train_data(ds, policies, cfg)
        state, _ = _steps(_init(jax.random.PRNGKey(0), cfg, data), data, 40)
        out[name] = (state, data)
    return ds, policies, out


def test_logged_history_matches_diagnosis_and_numpy(delayed):
    """Training's logged past (``logged_history``, ``TrainData.row_history``) is the input
    diagnosis fits: the same arrays as ``Episodes.past`` and a plain loop."""
    ds, _, policies = delayed
    rows = np.r_[0, 1, 2, 57, 300, ds.n_transitions - 1]
    h = H.logged_history(ds, rows, obs_history=2, action_history=3)
    eps = from_dataset(ds, position_dims=())
    for x, k, past, valid in ((ds.action, 3, h.past_act, h.past_act_valid),
                              (ds.obs, 2, h.past_obs, h.past_obs_valid)):
        ref, ref_valid = eps.past(np.asarray(x, np.float32), k)
        np.testing.assert_array_equal(np.asarray(past), ref[rows])
        np.testing.assert_array_equal(np.asarray(valid), ref_valid[rows])
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
    data = make_train_data(ds, policies, DELAYED.override({"dynamics.action_history": 3,
                                                           "holdout_frac": 0.0}))
    # with no held-out episodes the training rows are the Dataset's, grouped by policy
    order = np.argsort(pid, kind="stable")
    idx = np.asarray([0, 5, 333, 1999])
    mine = data.row_history(jnp.asarray(idx))
    ref = H.logged_history(ds, order[idx], obs_history=0, action_history=3)
    np.testing.assert_array_equal(np.asarray(mine.past_act), np.asarray(ref.past_act))
    np.testing.assert_array_equal(np.asarray(mine.t), np.asarray(ref.t))


def test_logged_order_is_the_episodes_place_in_the_recording(drift):
    """Training's recording-order input (``dataset_episode_order``, ``logged_history``, the
    training rows' ``TrainData.order`` and the held-out rows' ``val_hist``) is diagnosis's
    ``Episodes.order``: episode index in order of appearance / (E - 1)."""
    ds, policies, _ = drift
    eps = from_dataset(ds, position_dims=())
    order = H.dataset_episode_order(ds)
    np.testing.assert_array_equal(order, eps.order)
    assert order[0] == 0.0 and order[-1] == 1.0 and eps.n_episodes > 2
    # the second half of the recording (gain 2.0) is the later half of the order
    half = ds.n_transitions // 2
    assert order[:half].max() < order[half:].min()
    rows = np.r_[0, 1, 299, 300, 1799, 1800, ds.n_transitions - 1]
    h = H.logged_history(ds, rows, obs_history=0, action_history=0, time_inputs=("order",))
    np.testing.assert_array_equal(np.asarray(h.order), eps.order[rows].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(h.times[:, 0]), np.asarray(h.order))
    assert H.logged_history(ds, rows, obs_history=0, action_history=1).order is None
    # both inputs stack in the order named: "step" is t / episode_length, "order" the place
    h2 = H.logged_history(ds, rows, obs_history=0, action_history=0,
                          time_inputs=("step", "order"), episode_length=TASK.episode_length)
    np.testing.assert_allclose(np.asarray(h2.times), np.stack(
        [np.minimum(np.asarray(ds.t)[rows] / TASK.episode_length, 1.0), eps.order[rows]], -1),
        rtol=1e-6)
    # the training rows (grouped by policy) and the held-out rows carry their episode's
    cfg = ORDERED
    data = make_train_data(ds, policies, cfg)
    held = heldout_mask(ds, cfg.holdout_frac)
    keep = np.flatnonzero(~held)
    train_rows = keep[np.argsort(np.asarray(ds.policy_id)[keep], kind="stable")]
    np.testing.assert_array_equal(np.asarray(data.order),
                                  eps.order[train_rows].astype(np.float32))
    idx = np.asarray([0, 7, 1000, len(train_rows) - 1])
    np.testing.assert_array_equal(np.asarray(data.row_history(jnp.asarray(idx)).order),
                                  eps.order[train_rows[idx]].astype(np.float32))
    val = np.flatnonzero(held)
    assert val.size <= cfg.holdout_rows  # all held-out rows score
    np.testing.assert_array_equal(np.asarray(data.val_hist.order),
                                  eps.order[val].astype(np.float32))
    assert make_train_data(ds, policies, DELAYED).order is None


def test_rollouts_run_at_the_end_of_the_recording():
    """A simulated episode's order is 1.0: from the start, after pushes, and again where an
    episode restarts (the other fields empty there, as before)."""
    h = H.empty_history((3,), 2, 1, obs_history=1, action_history=1,
                        time_inputs=("step", "order"), episode_length=10)
    np.testing.assert_array_equal(np.asarray(h.order), [1.0, 1.0, 1.0])
    h = H.push_history(h, jnp.ones((3, 2)), jnp.ones((3, 1)))
    h = H.push_history(h, jnp.ones((3, 2)), jnp.ones((3, 1)))
    np.testing.assert_array_equal(np.asarray(h.order), [1.0, 1.0, 1.0])
    np.testing.assert_allclose(np.asarray(h.times), [[0.2, 1.0]] * 3)
    # a logged past (order 0.25) resets to the end of the recording, not to 0
    h = h.replace(order=jnp.full((3,), 0.25))
    r = H.reset_history(h, jnp.asarray([True, False, True]))
    np.testing.assert_array_equal(np.asarray(r.order), [1.0, 0.25, 1.0])
    np.testing.assert_array_equal(np.asarray(r.t), [0, 2, 0])
    np.testing.assert_array_equal(np.asarray(r.past_act_valid[:, 0]), [False, True, False])
    assert H.empty_history((3,), 2, 1, obs_history=1, action_history=0,
                           time_inputs=("step",)).order is None
    assert H.reset_history(H.empty_history((2,), 2, 1, obs_history=1, action_history=0),
                           jnp.asarray([True, False])).order is None
    with pytest.raises(ValueError, match="order"):
        _ = h.replace(order=None).times


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


def test_recording_order_input_learns_a_drifting_actuator(drift):
    """On a recording whose actuator gain went from 0.5 (first half) to 2.0 (second half),
    members that see the episode's place in the recording fit the held-out episodes far
    better than Markov ones (both 40 BC steps from the same seed), the late ones above all;
    a rollout of that simulator runs at order 1 throughout, on the late dynamics."""
    ds, _, out = drift
    nll = {k: float(np.mean(np.asarray(s.heldout_nll))) for k, (s, _) in out.items()}
    data = out["order"][1]
    late = np.asarray(data.val_hist.order) >= 0.5
    assert 0 < late.sum() < late.size
    obs, act, nxt = (np.asarray(x)[late] for x in (data.val_obs, data.val_action,
                                                    data.val_next_obs))
    hist = H.take_history(data.val_hist, jnp.asarray(np.flatnonzero(late)))
    std = np.asarray(data.norm.delta_std)
    mse = {}
    for k, (state, _) in out.items():
        mean = simulator(state).mean(jnp.asarray(obs), jnp.asarray(act),
                                     hist if k == "order" else None)
        mse[k] = float(np.mean(((np.asarray(mean) - nxt) / std) ** 2))
    print("drift: held-out NLL", nll, "late held-out MSE (delta stds)", mse)
    assert nll["order"] < nll["markov"] - 1.0, nll
    assert mse["order"] < 0.25 * mse["markov"], mse
    # a rollout runs at order 1 throughout; a full push at v = 0 moves as gain 2.0 does
    sim = simulator(out["order"][0])
    env = SimulatorEnv(sim, start_pool(ds))
    s = env.reset(jax.random.PRNGKey(3))
    for a in (0.7, -0.4, 0.2):
        s = env.step(s, jnp.asarray([a]))
        assert float(s.pipeline_state[1].order) == 1.0
    assert int(s.pipeline_state[1].t) == 3
    h0 = sim.new_history(())
    x0 = jnp.asarray([0.0, 0.0])
    dv = float(sim.mean(x0, jnp.asarray([1.0]), h0)[1])
    want = {g: POINTMASS_DT * 2.0 * g for g in DRIFT_GAINS}  # 0.05 at gain 0.5, 0.2 at 2.0
    print("drift: one step from rest at full action, dv", dv, "true", want)
    assert abs(dv - want[2.0]) < abs(dv - want[0.5]), (dv, want)


def test_history_checkpoint_loads_with_its_inputs(trained, delayed, tmp_path):
    state, _ = trained["history"]
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1}})
    ck.close()
    loaded = load_simulator(tmp_path / "ck")
    assert (loaded.action_history, loaded.time_inputs) == (1, ("step",))
    _, held, _ = delayed
    assert one_step_errors(loaded, held) == one_step_errors(simulator(state), held)


def test_adversarial_step_trains_a_history_simulator(delayed, tmp_path):
    """WGAIL with history inputs: the simulated envs, the buffer and both losses carry the
    past; a few steps stay finite and the buffer's past is a pushed one (gail, no VD: the
    CVaR measurement's rollouts carry the past as rl2s's do, tested above)."""
    ds, _, policies = delayed
    cfg = DELAYED.override({
        "method": "gail", "vd.every": 0, "updates_per_step": 1, "adversarial": {
            "disc_updates": 1, "sim_envs": 8, "sim_steps": 2, "buffer_size": 256},
        "dynamics.time_inputs": ("step", "order")})
    data = make_train_data(ds, policies, cfg)
    state, m = _steps(_init(jax.random.PRNGKey(0), cfg, data), data, 4)
    assert bool(np.all(np.asarray(m["finite"])))
    assert state.buffer_hist.past_act.shape == (cfg.adversarial.buffer_size, 1, 1)
    assert int(state.sim.hist.t.max()) >= 1
    # the recording order rides along: the buffer's and the simulated envs' (restarted from
    # real rows, with their logged past) are logged episodes' places in [0, 1]
    for h in (state.buffer_hist, state.sim.hist):
        o = np.asarray(h.order)
        assert o.shape == h.t.shape and o.min() >= 0.0 and o.max() <= 1.0
    assert np.unique(np.asarray(state.buffer_hist.order)).size > 1
    # a checkpoint holds the state with those histories and restores it exactly
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1}})
    back = ck.restore(state)
    ck.close()
    for a, b in zip(jax.tree_util.tree_leaves((state.buffer_hist, state.sim.hist)),
                    jax.tree_util.tree_leaves((back.buffer_hist, back.sim.hist)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert load_simulator(tmp_path / "ck").time_inputs == ("step", "order")


def test_bad_history_settings_are_refused_by_name():
    for ok in (("order",), ("step",), ("order", "step"), ("step", "order")):
        assert TrainConfig.small(time_inputs=ok).validate().dynamics.time_inputs == ok
    for bad in (("hour",), ("order", "order")):
        with pytest.raises(ValueError, match="dynamics.time_inputs"):
            TrainConfig.small(time_inputs=bad).validate()
    as_list = dataclasses.replace(MARKOV.dynamics, time_inputs=["order"])  # not via override,
    with pytest.raises(ValueError, match="dynamics.time_inputs"):  # which makes lists tuples
        dataclasses.replace(MARKOV, dynamics=as_list).validate()
    with pytest.raises(ValueError, match="action_history"):
        TrainConfig.small(action_history=-1).validate()
    with pytest.raises(ValueError, match="termination"):
        TrainConfig.small(action_history=2, termination="predictive").validate()
