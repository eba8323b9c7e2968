"""Planted-effect generators: each effect is really in the data, checked against the known
physics with plain NumPy least squares; the brax wrappers on PointMass (fast) and one MJX
Hopper test (one jit compile)."""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.data.dataset import validate_dataset
from rl2s_jax.diagnose.planted import EFFECTS, TWOMASS, make_planted, twomass_dynamics
from rl2s_jax.diagnose.planted_mjx import (
    DelayedActions,
    EpisodeMass,
    ProcessNoise,
    make_planted_env,
    planted_truth,
)
from rl2s_jax.envs.checks import check_env
from rl2s_jax.envs.tasks import PointMass, pointmass_dynamics

DT, DECAY, GAIN = TWOMASS["dt"], TWOMASS["decay"], TWOMASS["gain"]


def _arrays(ds):
    """obs, action, next_obs as float64 [E, L, ...] (fixed-length episodes)."""
    e, L = ds.n_transitions // ds.meta["episode_length"], ds.meta["episode_length"]
    return tuple(np.asarray(x, np.float64).reshape(e, L, -1)
                 for x in (ds.obs, ds.action, ds.next_obs))


def _lagged(x, lag):
    """x [E, L, ...] shifted by lag steps within each episode, zeros before its start."""
    out = np.zeros_like(x)
    out[:, lag:] = x[:, :-lag]
    return out


def _lstsq_rms(features, target):
    """RMS residual of the least-squares fit target [n] ~ features [n, k]."""
    coef = np.linalg.lstsq(features, target, rcond=None)[0]
    return float(np.sqrt(np.mean((target - features @ coef) ** 2)))


def _per_episode_fit(features, target):
    """Least squares per episode: features [E, L, k], target [E, L] -> coef [E, k]."""
    xtx = np.einsum("elk,elj->ekj", features, features)
    xty = np.einsum("elk,el->ek", features, target)
    return np.linalg.solve(xtx, xty[..., None])[..., 0]


def _body1_features(obs, a0):
    """The regressors of v1' in the known physics: v1, p1 - p2, a_0. -> [E, L, 3]"""
    return np.stack([obs[..., 1], obs[..., 0] - obs[..., 2], a0], axis=-1)


# --------------------------------------------------------------------------- twomass


def test_clean_is_exactly_the_deterministic_model_and_valid():
    t0 = time.perf_counter()
    ds = make_planted("clean")
    assert time.perf_counter() - t0 < 1.0
    validate_dataset(ds)
    assert ds.n_transitions == 240 * 60 and not ds.has_values
    meta = ds.meta
    assert (meta["task"], meta["obs_size"], meta["action_size"], meta["gamma"]) == (
        None, 4, 2, None)
    assert meta["episode_length"] == 60 and len(meta["policy_names"]) == meta["n_policies"] == 6
    assert meta["source"]["generator"] == "planted.twomass"
    assert meta["source"]["planted"] == {"effect": "none"}
    np.testing.assert_array_equal(twomass_dynamics(ds.obs, ds.action).astype(np.float32),
                                  ds.next_obs)
    obs, action, next_obs = _arrays(ds)
    np.testing.assert_array_equal(obs[:, 1:], next_obs[:, :-1])
    assert np.all(np.diff(ds.episode_id) >= 0) and ds.truncated.sum() == 240
    assert not ds.done.any() and np.abs(ds.action).max() <= 1.0
    # varied behaviour: every policy acts, actions are spread and autocorrelated
    assert np.bincount(ds.policy_id).min() == 40 * 60
    assert 0.2 < np.abs(action).mean() < 0.6
    a0 = action[..., 0]
    assert 0.2 < np.corrcoef(a0[:, 1:].ravel(), a0[:, :-1].ravel())[0, 1] < 0.95


def test_effects_share_policies_and_starts_for_a_seed():
    clean, drift = make_planted("clean", seed=3), make_planted("drift", seed=3)
    np.testing.assert_array_equal(clean.obs[clean.t == 0], drift.obs[drift.t == 0])
    np.testing.assert_array_equal(clean.action[0], drift.action[0])
    assert not np.array_equal(clean.obs[clean.t == 0], make_planted(seed=4).obs[clean.t == 0])


def test_delay_actuator_0_applies_the_action_of_two_steps_ago():
    ds = make_planted("delay")
    validate_dataset(ds)
    assert ds.meta["source"]["planted"] == {"effect": "actuation_delay", "lag": 2,
                                            "actuators": [0]}
    obs, action, next_obs = _arrays(ds)
    dv1 = (next_obs[..., 1] - obs[..., 1]).ravel()
    dv2 = (next_obs[..., 3] - obs[..., 3]).ravel()
    x = obs.reshape(-1, 4)

    def fit(target, a):
        return _lstsq_rms(np.column_stack([x, a.reshape(-1)]), target)

    a0, a1 = action[..., 0], action[..., 1]
    assert fit(dv1, _lagged(a0, 2)) < 1e-5 < 0.02 < fit(dv1, a0)
    assert fit(dv1, _lagged(a0, 2)) < 0.2 * fit(dv1, _lagged(a0, 1))
    assert fit(dv2, a1) < 1e-5 < 0.02 < fit(dv2, _lagged(a1, 2))

    both = make_planted("delay", lag=1, actuators=(0, 1), n_episodes=30)
    obs, action, next_obs = _arrays(both)
    for j in (0, 1):
        dv = (next_obs[..., 2 * j + 1] - obs[..., 2 * j + 1]).ravel()
        x = obs.reshape(-1, 4)
        assert _lstsq_rms(np.column_stack([x, _lagged(action[..., j], 1).ravel()]), dv) < 1e-5


def test_episode_param_mass1_varies_per_episode():
    ds = make_planted("episode_param")
    truth = ds.meta["source"]["planted"]
    assert truth["effect"] == "hidden_episode_parameter" and truth["parameter"] == "mass1"
    obs, action, next_obs = _arrays(ds)
    coef = _per_episode_fit(_body1_features(obs, action[..., 0]), next_obs[..., 1])
    np.testing.assert_allclose(coef[:, 0], DECAY, atol=1e-4)  # damping: not mass-dependent
    mass1 = DT * GAIN / coef[:, 2]
    np.testing.assert_allclose(mass1, truth["values"], rtol=2e-3)
    assert mass1.min() < 0.6 and mass1.max() > 1.8
    assert np.all((mass1 > 0.5 * 0.99) & (mass1 < 2.0 * 1.01))
    # body 2 is untouched; a pooled fit of body 1 is poor
    assert _lstsq_rms(np.column_stack([obs.reshape(-1, 4), action.reshape(-1, 2)]),
                      (next_obs[..., 3] - obs[..., 3]).ravel()) < 1e-5
    assert _lstsq_rms(np.column_stack([obs.reshape(-1, 4), action.reshape(-1, 2)]),
                      (next_obs[..., 1] - obs[..., 1]).ravel()) > 0.01


@pytest.mark.parametrize("dims", [(3,), (1, 3)])
def test_noise_grows_with_the_action_on_chosen_dims_only(dims):
    ds = make_planted("noise", dims=dims)
    truth = ds.meta["source"]["planted"]
    assert truth["effect"] == "stochastic_noise" and truth["dims"] == list(dims)
    model = twomass_dynamics(ds.obs, ds.action).astype(np.float32)  # exact where clean
    resid = ds.next_obs.astype(np.float64) - model
    scale, base = EFFECTS["noise"]["scale"], EFFECTS["noise"]["base"]
    for d in range(4):
        if d not in dims:
            assert np.all(resid[:, d] == 0.0), d
            continue
        r = resid[:, d]
        a = np.abs(ds.action[:, (d - 1) // 2]).astype(np.float64)
        assert r[a > 0.8].std() > 3.0 * r[a < 0.1].std()
        est = np.sqrt(np.mean(r ** 2 / (base + a) ** 2))
        assert est == pytest.approx(scale, rel=0.05)


def test_unobserved_body_makes_v1_depend_on_history():
    ds = make_planted("unobserved")
    truth = ds.meta["source"]["planted"]
    assert truth["effect"] == "unobserved_state" and truth["dims"] == [0, 1]
    resid = (ds.next_obs - twomass_dynamics(ds.obs, ds.action).astype(np.float32))
    assert np.all(resid[:, 2:] == 0.0) and np.sqrt(np.mean(resid[:, 1] ** 2)) > 0.02

    obs, action, next_obs = _arrays(ds)
    dv1 = next_obs[..., 1] - obs[..., 1]
    now = np.concatenate([obs, action, np.ones_like(obs[..., :1])], axis=-1)
    k = 3  # the hidden body is 2-dim linear: 3 past steps pin it down
    past = [_lagged(np.concatenate([obs, action, dv1[..., None]], axis=-1), j)
            for j in range(1, k + 1)]
    rows = slice(k, None)
    markov = _lstsq_rms(now[:, rows].reshape(-1, now.shape[-1]), dv1[:, rows].ravel())
    with_history = np.concatenate([now] + past, axis=-1)[:, rows]
    history = _lstsq_rms(with_history.reshape(-1, with_history.shape[-1]), dv1[:, rows].ravel())
    assert markov > 0.02 and history < 0.05 * markov
    # the Markov residual is slow within an episode: a hidden state, not noise
    coef = np.linalg.lstsq(now.reshape(-1, now.shape[-1]), dv1.ravel(), rcond=None)[0]
    r = dv1 - now @ coef
    assert np.corrcoef(r[:, 1:].ravel(), r[:, :-1].ravel())[0, 1] > 0.8


def test_drift_gain_falls_with_recording_order():
    ds = make_planted("drift")
    assert ds.meta["source"]["planted"]["over"] == "episode_order"
    obs, action, next_obs = _arrays(ds)
    coef = _per_episode_fit(_body1_features(obs, action[..., 0]), next_obs[..., 1])
    gain = coef[:, 2] / (DT * GAIN)
    order = np.arange(len(gain)) / (len(gain) - 1)
    np.testing.assert_allclose(gain, 1.0 - 0.4 * order, rtol=1e-3)
    feats2 = np.stack([obs[..., 3], obs[..., 2] - obs[..., 0], action[..., 1]], axis=-1)
    gain2 = _per_episode_fit(feats2, next_obs[..., 3])[:, 2] / (DT * GAIN)
    assert np.corrcoef(gain2, order)[0, 1] < -0.999


def test_bad_arguments_are_refused_with_the_accepted_values():
    with pytest.raises(ValueError, match=r"effect: expected one of .*'delay'.*got 'typo'"):
        make_planted("typo")
    with pytest.raises(ValueError, match=r"unknown argument\(s\) lags; accepted: lag, actuators"):
        make_planted("delay", lags=3)
    with pytest.raises(ValueError, match="dims"):
        make_planted("noise", dims=(0,))
    with pytest.raises(ValueError, match="lag"):
        make_planted("delay", lag=0)
    with pytest.raises(ValueError, match="mass_range"):
        make_planted("episode_param", mass_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="n_episodes"):
        make_planted(n_episodes=0)
    with pytest.raises(ValueError, match=r"effect: expected one of .*'drift'.*got 'wind'"):
        planted_truth("wind")
    with pytest.raises(ValueError, match="unknown argument"):
        make_planted_env("hopper", "noise", sigma=1.0)
    with pytest.raises(ValueError, match="EpisodeMass needs a brax PipelineEnv"):
        EpisodeMass(PointMass())
    with pytest.raises(ValueError, match="actuators"):
        DelayedActions(PointMass(), lag=1, actuators=(1,))


# --------------------------------------------------------------------------- wrappers


def _rollout(env, actions, key, n_envs):
    """jit(vmap) reset + scan of env.step over actions [T, B, A] -> (obs, next_obs) [T, B, O]."""
    def run(key):
        state = jax.vmap(env.reset)(jax.random.split(key, n_envs))

        def step(s, a):
            nxt = jax.vmap(env.step)(s, a)
            return nxt, (s.obs, nxt.obs)
        return jax.lax.scan(step, state, actions)[1]
    return jax.tree_util.tree_map(np.asarray, jax.jit(run)(key))


def test_process_noise_on_pointmass_only_on_chosen_dims():
    env = ProcessNoise(PointMass(), dims=(0,), scale=0.2, base=0.1)
    assert env.obs_dims == (1,)
    actions = jnp.concatenate([jnp.zeros((10, 200, 1)), jnp.ones((10, 200, 1))], axis=1)
    obs, next_obs = _rollout(env, actions, jax.random.PRNGKey(0), 400)
    resid = next_obs - np.asarray(pointmass_dynamics(obs, np.asarray(actions)))
    np.testing.assert_allclose(resid[..., 0], 0.0, atol=1e-6)  # position: clean this step
    # velocity: std = scale * (base + |a|) = 0.02 at a = 0, 0.22 at a = 1
    assert resid[:, :200, 1].std() == pytest.approx(0.02, rel=0.1)
    assert resid[:, 200:, 1].std() == pytest.approx(0.22, rel=0.1)


def test_delayed_actions_on_pointmass_through_collect():
    from rl2s_jax.data.collect import collect
    from rl2s_jax.policy import policy as pol

    env = DelayedActions(PointMass(), lag=2, actuators=(0,))
    check_env(env)
    params = pol.stack_params([pol.init_policy(jax.random.PRNGKey(i), 2, 1, hidden=(4,))
                               for i in range(2)])
    ds = collect(env, params, key=jax.random.PRNGKey(0), transitions_per_policy=40,
                 envs_per_policy=2, episode_length=10, value_episodes=0, progress=False)
    validate_dataset(ds)
    rows = np.arange(ds.n_transitions)
    applied = np.where((ds.t >= 2)[:, None], ds.action[np.maximum(rows - 2, 0)], 0.0)
    np.testing.assert_allclose(ds.next_obs, pointmass_dynamics(ds.obs, applied), atol=1e-6)
    assert np.abs(ds.next_obs - pointmass_dynamics(ds.obs, ds.action)).max() > 0.02


def test_episode_mass_on_mjx_hopper(env_cache):
    """One jit compile: masses drawn per reset; one start, three masses, the same actions."""
    env = env_cache("hopper")
    nominal = np.asarray(env.sys.body_mass)
    wrapped = EpisodeMass(env, scale_range=(0.5, 2.0))
    check_env(wrapped)
    assert wrapped.bodies == (1, 2, 3, 4)
    assert ProcessNoise(env).obs_dims == (9,) and planted_truth("noise")["dims"] == [9]
    actions = jnp.ones((3, 3, 3))

    def run(key):
        states = jax.vmap(wrapped.reset)(jax.random.split(key, 3))
        same = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x[:1], x.shape), states)
        same = same.replace(info={**same.info, "mass_scale": jnp.array([0.5, 1.0, 2.0])})
        final = jax.lax.scan(lambda s, a: (jax.vmap(wrapped.step)(s, a), None), same,
                             actions)[0]
        return states.info["mass_scale"], same.obs, final.obs

    compiled = jax.jit(run).lower(jax.random.PRNGKey(0)).compile(
        compiler_options={"xla_backend_optimization_level": 0,
                          "xla_llvm_disable_expensive_passes": True})
    scales, start, final = (np.asarray(x) for x in compiled(jax.random.PRNGKey(0)))
    assert len(np.unique(scales)) == 3 and np.all((scales > 0.5) & (scales < 2.0))
    assert np.all(np.isfinite(final))
    # same start and actions: the lighter the hopper, the faster its actuated joints spin up
    joint_speed = np.abs(final[:, 9:12] - start[:, 9:12]).sum(axis=1)
    assert joint_speed[0] > joint_speed[1] > joint_speed[2]
    np.testing.assert_array_equal(np.asarray(env.sys.body_mass), nominal)  # env untouched


def test_hopper_unobserved_truth_names_the_hidden_joints_positions():
    # Hopper's obs is q (6) ++ qd (6): hiding qvel 3-5 (obs 9-11) leaves their joints'
    # angles qpos 3-5, obs 3-5, as the dims that need the lost velocities.
    from rl2s_jax.envs.tasks import _LOCO

    assert _LOCO["hopper"].x_idx == 0 and _LOCO["hopper"].vx_idx == 6
    truth = planted_truth("unobserved", task_name="hopper")
    assert truth["removed_obs_dims"] == [9, 10, 11] and truth["dims"] == [3, 4, 5]


def test_collect_planted_unobserved_and_drift_on_pointmass():
    """The two recorded effects: a hidden velocity leaves only the position in the data; the
    drift records chunks whose applied action is scaled by a falling gain, in order."""
    from rl2s_jax.diagnose.planted_mjx import collect_planted
    from rl2s_jax.policy import policy as pol

    params = pol.stack_params([pol.init_policy(jax.random.PRNGKey(i), 2, 1, hidden=(4,))
                               for i in range(2)])
    kw = dict(key=jax.random.PRNGKey(0), transitions_per_policy=40, envs_per_policy=2,
              episode_length=10, value_episodes=0, progress=False)
    clean = collect_planted("pointmass", "clean", params, **kw)
    hidden = collect_planted("pointmass", "unobserved", params, effect_kwargs={"dims": (0,)},
                             **kw)
    validate_dataset(hidden)
    assert hidden.obs_size == 1 and hidden.meta["task"] is None
    np.testing.assert_array_equal(hidden.obs[:, 0], clean.obs[:, 0])  # same key: same run
    truth = hidden.meta["source"]["planted"]
    assert truth["effect"] == "unobserved_state" and truth["removed_obs_dims"] == [1]
    assert truth["dims"] == [0] and hidden.meta["source"]["hidden_obs_dims"] == [1]

    drift = collect_planted("pointmass", "drift", params, effect_kwargs={
        "gain_start": 1.0, "gain_end": 0.5, "chunks": 2}, **kw)
    validate_dataset(drift)
    assert drift.n_transitions == 2 * 2 * 20  # 2 chunks x 2 policies x 20 each
    half = drift.n_transitions // 2
    assert drift.episode_id[half:].min() > drift.episode_id[:half].max()
    for rows, gain in ((slice(0, half), 1.0), (slice(half, None), 0.5)):
        np.testing.assert_allclose(
            drift.next_obs[rows], pointmass_dynamics(drift.obs[rows], gain * drift.action[rows]),
            atol=1e-6)
    assert drift.meta["source"]["planted"]["gains"] == [1.0, 0.5]
    # Without envs_per_policy, each chunk runs the envs of the whole recording (40 // 10 = 4
    # per policy, 5 steps each), not its own default (20 // 10 = 2, 10 steps each).
    auto = collect_planted("pointmass", "drift", params, effect_kwargs={
        "gain_start": 1.0, "gain_end": 0.5, "chunks": 2},
        **{k: v for k, v in kw.items() if k != "envs_per_policy"})
    first = slice(0, auto.n_transitions // 2)
    assert np.unique(auto.episode_id[first]).size == 2 * 4 and auto.t[first].max() == 4
    with pytest.raises(ValueError, match="chunks: expected an int >= 2"):
        collect_planted("pointmass", "drift", params, effect_kwargs={"chunks": 1}, **kw)
    with pytest.raises(ValueError, match="use collect_planted"):
        make_planted_env("pointmass", "drift")
    with pytest.raises(ValueError, match=r"dims: expected .* in \[0, 1\)"):
        planted_truth("unobserved", task_name="pointmass")  # default dims are Hopper's
