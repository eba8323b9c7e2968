"""The learned termination hazard and the "predictive" termination (rl2s_jax.model.termination):
its loss against NumPy, that it learns a known hazard, that rollouts end episodes with the
chances it gives, and that it travels through training, checkpoints and the simulator env."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm as gauss
from test_train import _policies as _pm_policies

from rl2s_jax.envs.tasks import get_task, pointmass_dynamics
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.simulator import advance_values, ends_episode, simulated_returns, start_values
from rl2s_jax.model.termination import bce, fit_hazard, hazard_prob, init_hazard
from rl2s_jax.train.checkpoint import Checkpointer, load_simulator
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.step import init, simulator

CFG = TrainConfig.small(task="pointmass", method="bc", vd_horizon=50, vd_every=3,
                        termination="both", hazard_steps=1500, hazard_hidden=(64, 64))


@pytest.fixture(scope="module")
def pm(pm_falls):
    return pm_falls


def _identity_norm(o, a):
    z = lambda n: np.zeros((4, n))
    return Normalizer.from_data(z(o), z(a), z(o), min_std=1.0)


def test_bce_matches_numpy():
    rng = np.random.default_rng(0)
    logit = rng.normal(0, 4, 200).astype(np.float32)
    y = rng.random(200) < 0.3
    p = 1 / (1 + np.exp(-logit.astype(np.float64)))
    ref = -np.mean(y * np.log(p) + (1 - y) * np.log1p(-p))
    np.testing.assert_allclose(float(bce(jnp.asarray(logit), jnp.asarray(y))), ref, rtol=1e-5)


def test_fit_hazard_learns_a_known_hazard():
    """done ~ Bernoulli(0.02 + 0.4 [s_0 > 0]): the fitted h is that in each region."""
    rng = np.random.default_rng(1)
    n = 20_000
    obs = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    act = rng.uniform(-1, 1, (n, 1)).astype(np.float32)
    truth = 0.02 + 0.4 * (obs[:, 0] > 0)
    done = (rng.random(n) < truth).astype(np.float32)
    norm = _identity_norm(2, 1)
    params, losses = jax.jit(lambda k: fit_hazard(
        k, init_hazard(jax.random.PRNGKey(0), 2, 1, (32, 32)), norm, jnp.asarray(obs),
        jnp.asarray(act), jnp.asarray(done), steps=1500))(jax.random.PRNGKey(1))
    assert float(losses[-100:].mean()) < float(losses[:10].mean())
    h = np.asarray(hazard_prob(params, norm, jnp.asarray(obs), jnp.asarray(act)))
    away = np.abs(obs[:, 0]) > 0.2  # the step itself is where a smooth fit must blur
    for region, want in ((obs[:, 0] > 0, 0.42), (obs[:, 0] < 0, 0.02)):
        assert abs(h[region & away].mean() - want) < 0.04, (want, h[region & away].mean())


def _const_hazard(p: float):
    return lambda obs, action, key: jnp.full(obs.shape[:-1], p)


def test_a_constant_hazard_gives_geometric_episode_lengths():
    """Reward 1 per step, no rule, hazard p: E[length] = (1 - (1 - p)^H) / p."""
    p, horizon, n = 0.1, 30, 4000
    policies = _pm_policies([0.0])
    pool = jnp.zeros((1, 2))
    ret, length = simulated_returns(
        policies, lambda o, a, k: o, lambda o, a, o2: jnp.ones(o.shape[:-1]), None, pool,
        jax.random.PRNGKey(0), n_episodes=n, horizon=horizon, gamma=1.0,
        hazard_fn=_const_hazard(p))
    want = (1 - (1 - p) ** horizon) / p
    sd = np.asarray(length, np.float64).std() / np.sqrt(n)
    assert abs(float(length.mean()) - want) < 4 * sd, (float(length.mean()), want)
    np.testing.assert_array_equal(np.asarray(ret), np.asarray(length, np.float32))


def test_a_zero_hazard_changes_nothing_and_no_rule_never_ends():
    task = get_task("pointmass")
    policies = _pm_policies([-2.0, 2.0])
    pool = jnp.zeros((3, 2))
    dyn = lambda o, a, k: pointmass_dynamics(o, a)
    kw = dict(n_episodes=8, horizon=60, gamma=0.99)
    key = jax.random.PRNGKey(2)
    plain = simulated_returns(policies, dyn, task.reward_fn, task.done_fn, pool, key, **kw)
    zero = simulated_returns(policies, dyn, task.reward_fn, task.done_fn, pool, key, **kw,
                             hazard_fn=_const_hazard(0.0))
    for a, b in zip(plain, zero, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(plain[1].min()) < 60  # the policies do push the mass out
    _, never = simulated_returns(policies, dyn, task.reward_fn, None, pool, key, **kw)
    assert (np.asarray(never) == 60).all()
    obs = jnp.zeros((5, 2))
    assert not ends_episode(obs, None, obs, None, None, None).any()


def test_termination_settings_are_checked(pm):
    ds, params = pm
    with pytest.raises(ValueError, match="termination"):
        TrainConfig.small(termination="sometimes").validate()
    with pytest.raises(ValueError, match="hazard_steps"):
        TrainConfig.small(termination="hazard", hazard_steps=0).validate()
    with pytest.raises(ValueError, match="hazard_hidden"):
        TrainConfig.small(hazard_hidden=()).validate()
    data = make_train_data(ds, params, CFG)
    with pytest.raises(ValueError, match="TrainData.done"):
        init(jax.random.PRNGKey(0), CFG, data.replace(done=None))
    rule = simulator(init(jax.random.PRNGKey(0), CFG.override({"outcome.termination": "rule"}),
                          data))
    assert rule.hazard is None and rule.terminations(get_task("pointmass").done_fn)[1] is None
    with pytest.raises(ValueError, match="needs a learned hazard"):
        rule.replace(termination="both").terminations(get_task("pointmass").done_fn)


def test_training_fits_the_hazard_and_a_checkpoint_keeps_it(pm, tmp_path):
    """init fits h on the data's done flags (high where the mass left, ~0 well inside), the value
    measurement uses it, and a saved checkpoint loads it back in a fresh Simulator."""
    from rl2s_jax.train.loop import fit

    ds, params = pm
    data = make_train_data(ds, params, CFG)
    state = init(jax.random.PRNGKey(0), CFG, data)
    sim = simulator(state)
    assert sim.hazard is not None and sim.termination == "both"
    done = np.asarray(ds.done, bool)
    h = np.asarray(sim.hazard_prob(jnp.asarray(ds.obs), jnp.asarray(ds.action)))
    inside = np.abs(np.asarray(ds.obs)[:, 0]) < 1.0
    assert h[done].mean() > 0.3 and h[inside].mean() < 0.01, (h[done].mean(), h[inside].mean())
    state, _ = fit(state, data, 3, chunk=3, progress=False)
    assert np.isfinite(np.asarray(state.vd)).all()
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1}})
    ck.close()
    loaded = load_simulator(tmp_path / "ck")
    assert loaded.termination == "both"
    for a, b in zip(jax.tree_util.tree_leaves(loaded.hazard),
                    jax.tree_util.tree_leaves(simulator(state).hazard), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the hazard's window travels with it (a window lost on load would turn q = P(end within
    # K steps) into a per-step hazard K times too high)
    windowed = state.replace(config=state.config.override({"outcome.hazard_window": 4}))
    ck = Checkpointer(tmp_path / "ck4")
    ck.save(windowed, {"data": {"obs_size": 2, "action_size": 1}})
    ck.close()
    assert load_simulator(tmp_path / "ck4").hazard_window == 4
    assert loaded.hazard_window == 1


def test_predictive_termination_ends_with_the_models_own_chance(pm):
    """'predictive' ends a step with P(|p'| > 2) under the model's one-step Gaussian (one
    member): checked against the normal tail at a state whose mean next p is near 2."""
    ds, params = pm
    cfg = CFG.override({"outcome.termination": "predictive", "member_mode": "fixed"})
    sim = simulator(init(jax.random.PRNGKey(0), cfg, make_train_data(ds, params, cfg)))
    task = get_task("pointmass")
    done_fn, hazard_fn = sim.terminations(task.done_fn)
    assert done_fn is task.done_fn
    act = jnp.asarray([[0.5]])
    obs = jnp.asarray([[1.9, 0.5]])
    for _ in range(3):  # move p so that the mean next p sits at the boundary
        obs = obs.at[0, 0].add(2.0 - float(sim.mean(obs, act)[0, 0]) - 0.3 * float(
            sim.predictive(obs, act)[1][0, 0] * sim.norm.delta_std[0]))
    mean, std = sim.predictive(obs, act)
    m = float(sim.norm.next_from_delta(obs, mean)[0, 0])
    s = float(std[0, 0] * sim.norm.delta_std[0])
    want = gauss.sf((2.0 - m) / s) + gauss.cdf((-2.0 - m) / s)
    assert 0.1 < want < 0.9
    n = 4000
    keys = jax.random.split(jax.random.PRNGKey(5), n)
    got = np.asarray(jax.vmap(lambda k: hazard_fn(obs, act, k))(keys)).mean()
    assert abs(got - want) < 4 * np.sqrt(want * (1 - want) / n), (got, want)


def test_sim_env_ends_episodes_by_the_hazard(pm):
    ds, params = pm
    sim = simulator(init(jax.random.PRNGKey(0), CFG, make_train_data(ds, params, CFG)))
    pool = jnp.zeros((1, 2))
    for bias, ends in ((30.0, 1.0), (-30.0, 0.0)):
        layers = [dict(x) for x in sim.hazard["layers"]]
        layers[-1] = {"w": jnp.zeros_like(layers[-1]["w"]),
                      "b": jnp.full_like(layers[-1]["b"], bias)}  # h = sigmoid(bias)
        env = SimulatorEnv(sim.replace(hazard={"layers": layers}, termination="hazard"), pool)
        state = env.step(env.reset(jax.random.PRNGKey(0)), jnp.zeros((1,)))
        assert float(state.done) == ends
        done_fn, hazard_fn = env.sim.terminations(None)
        roll = advance_values(start_values(pool, 1, 4, jax.random.PRNGKey(1)),
                              jax.tree_util.tree_map(lambda x: x[:1], params), env.sim.dynamics,
                              get_task("pointmass").reward_fn, done_fn, jax.random.PRNGKey(2),
                              n_steps=5, horizon=5, gamma=1.0, hazard_fn=hazard_fn)
        assert (np.asarray(roll.length) == (1 if ends else 5)).all()


def test_window_labels_and_the_per_step_hazard_match_numpy():
    """Episodes of lengths 5 (terminated), 4 (truncated), 3 (terminated), rows in order."""
    from rl2s_jax.model.termination import window_labels
    from rl2s_jax.train.data import episode_steps_left

    ep = np.repeat([0, 1, 2], [5, 4, 3])
    t = np.concatenate([np.arange(5), np.arange(4), np.arange(3)])
    done = np.zeros(12, np.float32)
    done[[4, 11]] = 1
    left = episode_steps_left(np.zeros(12, int), ep, t)
    for k in (1, 2, 4):
        ref = np.zeros(12, np.float32)
        for start, n, ended in ((0, 5, True), (5, 4, False), (9, 3, True)):
            if ended:
                ref[start + max(n - k, 0):start + n] = 1
        got = window_labels(jnp.asarray(done), jnp.asarray(left), k)
        np.testing.assert_array_equal(np.asarray(got), ref, err_msg=f"window {k}")
    from rl2s_jax.model.termination import hazard_logit

    params = init_hazard(jax.random.PRNGKey(0), 2, 1, (8,))
    norm = _identity_norm(2, 1)
    obs = jnp.asarray(np.random.default_rng(0).normal(0, 3, (6, 2)), jnp.float32)
    act = jnp.zeros((6, 1))
    params["layers"][-1]["w"] = params["layers"][-1]["w"] * 300  # logits of several units
    q = 1 / (1 + np.exp(-np.asarray(hazard_logit(params, norm, obs, act), np.float64)))
    assert q.min() < 0.01 and q.max() > 0.3
    for k in (1, 3, 20):
        h = np.asarray(hazard_prob(params, norm, obs, act, k), np.float64)
        np.testing.assert_allclose(h, 1 - (1 - q) ** (1 / k), rtol=1e-4)


def test_the_adversarial_phase_simulated_envs_end_by_the_hazard(pm):
    """WGAIL's simulated envs (the buffer of fake (s, a)) end as the value rollouts do: a
    hazard of ~1 restarts every env at every step, one of ~0 (and no rule) lets them all run
    sim_steps steps."""
    from rl2s_jax.train.step import _advance_sim

    ds, params = pm
    cfg = CFG.override({"method": "rl2s", "outcome.termination": "hazard",
                        "outcome.hazard_steps": 1, "vd.every": 0, "eps": 1.0})
    data = make_train_data(ds, params, cfg)
    state = init(jax.random.PRNGKey(0), cfg, data)
    for bias, t_after in ((30.0, 0), (-30.0, cfg.adversarial.sim_steps)):
        layers = [dict(x) for x in state.hazard["layers"]]
        layers[-1] = {"w": jnp.zeros_like(layers[-1]["w"]),
                      "b": jnp.full_like(layers[-1]["b"], bias)}  # h = sigmoid(bias)
        moved, metrics = _advance_sim(state.replace(hazard={"layers": layers}), data,
                                      jax.random.PRNGKey(1))
        np.testing.assert_array_equal(np.asarray(moved.sim.t), t_after)
        assert float(metrics["sim_reset_rate"]) == (1.0 if t_after == 0 else 0.0)
