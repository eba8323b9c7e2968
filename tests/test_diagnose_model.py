"""Diagnosis's models, fitted through train_step (rl2s_jax.diagnose.model): each extension
fixes the effect it is built for, on a tiny synthetic system with one planted effect per obs
dim; predictions, k-step errors and policy rollouts agree with direct computations."""
import dataclasses
import json

import jax
import numpy as np
import pytest

from rl2s_jax.data.dataset import Dataset
from rl2s_jax.data.episodes import from_dataset, split_episodes
from rl2s_jax.diagnose import model as M
from rl2s_jax.model.dynamics import Normalizer, beta_nll
from rl2s_jax.model.history import step_inputs
from rl2s_jax.policy.policy import init_policy, stack_params

LENGTH = 40
N_POLICIES = 4
SEEDS = (0, 1)
DECAY = 0.8  # x' = DECAY x + ...: episodes share one state region (not told apart by it)
TINY = dict(hidden=(64, 64), steps=400, batch_size=256, lr=3e-3, context_hidden=(32, 32),
            updates_per_step=50)


def make_system(n_episodes=200, length=LENGTH, seed=0):
    """Episodes of a 5-d system driven by 4 iid uniform actions, one effect per dim:

    0: delayed action   x0' = 0.8 x0 + 0.1 a0[t-2]                      (+ 0.005 noise)
    1: episode gain     x1' = 0.8 x1 + g a1, g in {0.2, 1.0} per episode (+ 0.005 noise)
    2: heteroscedastic  x2' = 0.8 x2 + 0.5 a2 + 0.3 |a2| noise
    3: drifting gain    x3' = 0.8 x3 + (0.2 + order) a3                  (+ 0.005 noise)
    4: clock            x4' = x4 + 1 (a position dim, x4 = t; noise 0.01, 0.1 for the last
                        policy, whose rows the model therefore fits worst)
    """
    rng = np.random.default_rng(seed)
    e = n_episodes
    pol = np.arange(e) % N_POLICIES
    order = np.arange(e) / (e - 1)
    gain = rng.choice([0.2, 1.0], e)
    act = rng.uniform(-1, 1, (e, length, 4))
    obs = np.zeros((e, length + 1, 5))
    obs[:, 0, :4] = rng.normal(size=(e, 4))
    noise = rng.normal(size=(e, length, 5))
    clock_sd = np.where(pol == N_POLICIES - 1, 0.1, 0.01)
    for t in range(length):
        x, a, z = obs[:, t], act[:, t], noise[:, t]
        lag2 = act[:, t - 2, 0] if t >= 2 else 0.0
        obs[:, t + 1] = np.stack([
            DECAY * x[:, 0] + 0.1 * lag2 + 0.005 * z[:, 0],
            DECAY * x[:, 1] + gain * a[:, 1] + 0.005 * z[:, 1],
            DECAY * x[:, 2] + 0.5 * a[:, 2] + 0.3 * np.abs(a[:, 2]) * z[:, 2],
            DECAY * x[:, 3] + (0.2 + order) * a[:, 3] + 0.005 * z[:, 3],
            x[:, 4] + 1.0 + clock_sd * z[:, 4]], -1)
    n = e * length
    f32 = np.float32
    truncated = np.zeros(n, bool)
    truncated[length - 1::length] = True
    arrays = dict(obs=obs[:, :-1].reshape(n, 5).astype(f32),
                  action=act.reshape(n, 4).astype(f32),
                  next_obs=obs[:, 1:].reshape(n, 5).astype(f32), reward=np.zeros(n, f32),
                  done=np.zeros(n, bool), truncated=truncated,
                  policy_id=np.repeat(pol, length).astype(np.int32),
                  episode_id=np.repeat(np.arange(e), length).astype(np.int32),
                  t=np.tile(np.arange(length), e).astype(np.int32))
    meta = dict(task=None, obs_size=5, action_size=4, n_policies=N_POLICIES, gamma=None,
                episode_length=length, policy_names=[f"pi{p}" for p in range(N_POLICIES)],
                source={"kind": "synthetic test system"})
    return from_dataset(Dataset.from_arrays(arrays, meta), position_dims=(4,))


@pytest.fixture(scope="module")
def system():
    eps = make_system()
    fit, held = split_episodes(eps, 0.3, seed=0)
    return eps, fit, held


@pytest.fixture(scope="module")
def fitted(system):
    """name -> FittedModels of the base model and each extension (2 seeds each), fit lazily."""
    eps, fit, _ = system
    specs = {"base": {}, "ah2": dict(action_history=2), "oh2": dict(obs_history=2, steps=100),
             "ctx": dict(context_dim=2, obs_history=4, action_history=4),
             "state": dict(noise="state"), "time": dict(time_inputs=("order", "step"))}
    cache = {}

    def get(name):
        if name not in cache:
            spec = M.ModelSpec(**{**TINY, **specs[name]})
            cache[name] = M.fit_models(eps, fit, spec, SEEDS)
        return cache[name]

    return get


def per_dim_mse(fm, eps, rows):
    mean, _ = M.predict(fm, eps, rows)
    return ((M.normalized_delta(fm, eps, rows)[None] - mean) ** 2).mean(1)  # [S, o]


# ----------------------------------------------------------------------- validation


@pytest.mark.parametrize("field,value", [
    ("action_history", -1), ("obs_history", 1.5), ("context_dim", True), ("noise", "hetero"),
    ("time_inputs", ("order", "clock")), ("time_inputs", ["order"]),
    ("time_inputs", ("step", "step")), ("context_dim", 2),
    ("hidden", ()), ("hidden", (64, 0)), ("steps", 0), ("batch_size", 0),
    ("updates_per_step", 0), ("lr", float("nan")), ("nll_beta", 1.5), ("nll_beta", -0.1),
    ("weight_decay", -1.0)])
def test_bad_spec_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        M.ModelSpec(**{field: value}).validate()


def test_spec_describe_is_json_and_names_the_extensions():
    spec = M.ModelSpec(action_history=2, time_inputs=("order",))
    d = json.loads(json.dumps(spec.describe()))
    assert d["action_history"] == 2 and d["time_inputs"] == ["order"]
    assert d["extensions"] == ["action_history=2", "time_inputs=order"]
    assert M.ModelSpec().validate().extensions == ("base",)


def test_spec_is_fitted_as_the_simulator_users_train():
    """The fit's TrainConfig: maximum likelihood of one member per seed, with the spec's
    inputs as the TrainConfig fields that `rl2s train --set` takes."""
    spec = M.ModelSpec(**{**TINY, "action_history": 2, "noise": "state", "nll_beta": 0.5})
    cfg = spec.train_config(LENGTH, (4,))
    assert (cfg.method, cfg.ensemble_size, cfg.vd.every, cfg.holdout_frac) == ("bc", 1, 0, 0.0)
    assert (cfg.dynamics.action_history, cfg.dynamics.noise, cfg.nll_beta, cfg.dynamics.hidden) == (
        2, "state", 0.5, (64, 64))
    assert (cfg.episode_length, cfg.ignore_dims, cfg.bc_lr) == (LENGTH, (4,), 3e-3)


def test_fit_rejects_bad_input_before_any_work(system):
    eps, fit, _ = system
    spec = M.ModelSpec(**TINY)
    with pytest.raises(ValueError, match="fit_episodes"):
        M.fit_models(eps, np.array([0, eps.n_episodes]), spec)
    with pytest.raises(ValueError, match="seeds"):
        M.fit_models(eps, fit, spec, seeds=())
    with pytest.raises(ValueError, match="noise"):
        M.fit_models(eps, fit, dataclasses.replace(spec, noise="none"))


# -------------------------------------------------------------------------- inputs


def test_history_and_inputs_match_a_loop_reference(system):
    eps, _, _ = system
    rng = np.random.default_rng(0)
    rows = np.concatenate([eps.start[:3], eps.start[:3] + 1, rng.integers(0, eps.n, 20)])
    k = 3
    ref = np.zeros((rows.size, k, eps.obs_size))
    ref_valid = np.zeros((rows.size, k), bool)
    for i, r in enumerate(rows):
        for j in range(k):
            back = r - 1 - j
            if back >= 0 and eps.episode[back] == eps.episode[r]:
                ref[i, j], ref_valid[i, j] = eps.obs[back], True
    hist = M.episode_history(eps, rows, obs_history=k, action_history=0)
    np.testing.assert_array_equal(np.asarray(hist.past_obs_valid), ref_valid)
    np.testing.assert_allclose(np.asarray(hist.past_obs), ref, rtol=1e-6, atol=1e-6)
    full, full_valid = eps.past_obs(k)
    np.testing.assert_allclose(np.asarray(hist.past_obs), full[rows], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(hist.past_obs_valid), full_valid[rows])

    # the generator inputs: normalised s (position dim zeroed), a, past a, past s, masks, time
    norm = Normalizer.from_data(eps.obs, eps.action, eps.next_obs, ignore_dims=(4,))
    hist = M.episode_history(eps, rows, obs_history=1, action_history=2,
                             time_inputs=("step", "order"), episode_length=LENGTH)
    x = np.asarray(step_inputs(norm, np.asarray(eps.obs[rows], np.float32),
                               np.asarray(eps.action[rows], np.float32), hist))
    om, osd, am, asd = (np.asarray(v, np.float64) for v in
                        (norm.obs_mean, norm.obs_std, norm.act_mean, norm.act_std))
    keep = np.array([1, 1, 1, 1, 0])
    for i, r in enumerate(rows):
        t = eps.t[r]
        s_in = lambda s: (s - om) / osd * keep
        past_s = s_in(eps.obs[r - 1]) if t >= 1 else np.zeros(5)
        past_a = [(eps.action[r - j] - am) / asd if t >= j else np.zeros(4) for j in (1, 2)]
        want = np.concatenate([s_in(eps.obs[r]), past_s, [t >= 1],
                               (eps.action[r] - am) / asd, *past_a, [t >= 1, t >= 2],
                               [2 * eps.step_frac[r] - 1, 2 * eps.order[r] - 1]])
        np.testing.assert_allclose(x[i], want, rtol=1e-4, atol=1e-4)
    spec = M.ModelSpec(action_history=2, obs_history=1, time_inputs=("step", "order"))
    assert x.shape[1] == spec.dynamics.input_size(5, 4)


# --------------------------------------------------------------------- the effects


def test_predict_shapes_and_seeds_differ_but_are_deterministic(system, fitted):
    eps, fit, held = system
    fm = fitted("base")
    rows = eps.rows(held)
    mean, std = M.predict(fm, eps, rows)
    assert mean.shape == std.shape == (len(SEEDS), rows.size, 5)
    assert (std > 0).all() and np.isfinite(mean).all()
    assert np.abs(mean[0] - mean[1]).max() > 1e-3
    again = M.fit_models(eps, fit, fm.spec, SEEDS)
    np.testing.assert_array_equal(M.predict(again, eps, rows)[0], mean)
    np.testing.assert_array_equal(again.train_loss, fm.train_loss)
    assert fm.loss_history.shape == (len(SEEDS), 8) and fm.train_loss[0] < fm.loss_history[0, 0]
    np.testing.assert_allclose(M.delta_scale(fm), eps.delta[eps.rows(fit)].std(0), rtol=1e-4)
    met = M.heldout_metrics(fm, eps, rows)
    assert met["nll"].shape == met["mse"].shape == (len(SEEDS),)
    np.testing.assert_allclose(met["mse"], per_dim_mse(fm, eps, rows).mean(1), rtol=1e-6)


def test_action_history_fixes_an_actuation_delay(system, fitted):
    eps, _, held = system
    rows = eps.rows(held)
    base, ext = per_dim_mse(fitted("base"), eps, rows), per_dim_mse(fitted("ah2"), eps, rows)
    assert (base[:, 0] > 0.4).all() and (ext[:, 0] < 0.05).all(), (base[:, 0], ext[:, 0])
    b, e = (M.heldout_metrics(fitted(n), eps, rows) for n in ("base", "ah2"))
    assert (e["mse"] < b["mse"] - 0.05).all() and (e["nll"] < b["nll"] - 0.5).all()


def test_episode_context_fixes_a_hidden_episode_gain(system, fitted):
    """The gain of dim 1 is drawn per episode: a context inferred from the episode's last 4
    transitions cuts that dim's held-out error (with the same past as plain inputs only,
    ``oh2``-like models, the error stays high)."""
    eps, _, held = system
    rows = eps.rows(held)
    base, ext = per_dim_mse(fitted("base"), eps, rows), per_dim_mse(fitted("ctx"), eps, rows)
    assert (base[:, 1] > 0.12).all() and (ext[:, 1] < 0.5 * base[:, 1]).all(), (base, ext)
    assert "enc" in fitted("ctx").simulator(0).gen


def test_beta_nll_matches_numpy_and_gives_the_mean_the_squared_error_gradient():
    rng = np.random.default_rng(0)
    mean, log_std, y = (rng.normal(size=(5, 3)) for _ in range(3))
    nll = 0.5 * ((y - mean) / np.exp(log_std)) ** 2 + log_std + 0.5 * np.log(2 * np.pi)
    for beta in (0.0, 0.5, 1.0):
        w = np.exp(2 * beta * log_std)
        np.testing.assert_allclose(beta_nll(mean, log_std, y, beta), (w * nll).sum(-1),
                                   rtol=1e-5)
    g_mean, g_log_std = jax.grad(lambda m, s: beta_nll(m, s, y, 1.0).sum(),
                                 argnums=(0, 1))(mean, log_std)
    np.testing.assert_allclose(g_mean, mean - y, rtol=1e-5, atol=1e-6)
    # the std still learns its NLL gradient, only rescaled (the weight is a constant)
    np.testing.assert_allclose(g_log_std, np.exp(2 * log_std) * (1 - ((y - mean)
                               / np.exp(log_std)) ** 2), rtol=1e-4, atol=1e-6)


def test_state_noise_lowers_nll_but_not_mse(system, fitted):
    eps, _, held = system
    rows = eps.rows(held)
    b, s = (M.heldout_metrics(fitted(n), eps, rows) for n in ("base", "state"))
    assert (s["nll"] < b["nll"] - 0.1).all(), (b, s)
    base, ext = per_dim_mse(fitted("base"), eps, rows), per_dim_mse(fitted("state"), eps, rows)
    np.testing.assert_allclose(ext[:, 2], base[:, 2], atol=0.05)
    _, std = M.predict(fitted("state"), eps, rows)
    assert np.corrcoef(std[0, :, 2], np.abs(eps.action[rows, 2]))[0, 1] > 0.6


def test_time_inputs_fix_a_drifting_gain(system, fitted):
    eps, _, held = system
    rows = eps.rows(held)
    base, ext = per_dim_mse(fitted("base"), eps, rows), per_dim_mse(fitted("time"), eps, rows)
    assert (base[:, 3] > 0.08).all() and (ext[:, 3] < 0.5 * base[:, 3]).all(), (base, ext)


# -------------------------------------------------------------------- k-step errors


def test_kstep_errors_grow_and_start_at_the_one_step_error(system, fitted):
    eps, _, held = system
    k_max = 10
    for name in ("base", "ctx", "ah2"):
        fm = fitted(name)
        ks = M.kstep_errors(fm, eps, held, k_max=k_max)
        assert ks.shape == (len(SEEDS), k_max) and (ks[:, -1] > 1.5 * ks[:, 0]).all()
        rows = eps.rows(held)
        starts = rows[eps.t[rows] <= LENGTH - k_max]
        mean, _ = M.predict(fm, eps, starts)
        err = (mean - M.normalized_delta(fm, eps, starts)) * M.delta_scale(fm)
        one = np.sqrt(((err / np.asarray(fm.norm.obs_std)) ** 2).mean((1, 2)))
        np.testing.assert_allclose(ks[:, 0], one, rtol=1e-4)
    sub = M.kstep_errors(fm, eps, held, k_max=3, n_starts=50, seed=1)
    assert sub.shape == (len(SEEDS), 3)
    with pytest.raises(ValueError, match="k_max"):
        M.kstep_errors(fm, eps, held, k_max=LENGTH + 1)


def test_kstep_feeds_its_own_predictions_into_the_obs_history(system, fitted):
    """Open-loop errors of an obs-history model equal a rollout done by hand with predict on
    data whose observations after the start are replaced by the model's predictions."""
    eps, _, held = system
    fm = fitted("oh2")
    k_max, e = 3, held[1]
    ks = M.kstep_errors(fm, eps, np.array([e]), k_max=k_max)
    obs_std = np.asarray(fm.norm.obs_std, np.float64)
    sse = np.zeros((len(SEEDS), k_max))
    starts = np.arange(eps.start[e], eps.start[e] + LENGTH - k_max + 1)
    for s in range(len(SEEDS)):
        for r in starts:
            obs = eps.obs.copy()
            for j in range(k_max):
                mean, _ = M.predict(fm, dataclasses.replace(eps, obs=obs), np.array([r + j]))
                pred = obs[r + j] + np.asarray(fm.norm.delta_mean) + M.delta_scale(fm) * mean[s, 0]
                sse[s, j] += (((pred - eps.next_obs[r + j]) / obs_std) ** 2).mean()
                if j + 1 < k_max:
                    obs[r + j + 1] = pred
    np.testing.assert_allclose(ks, np.sqrt(sse / starts.size), rtol=2e-3)


# ------------------------------------------------------------------------- rollouts


@dataclasses.dataclass(frozen=True)
class _Task:
    """What a rollout needs of a task: its reward_fn and done_fn."""
    reward_fn: object
    done_fn: object


def test_rollout_values_match_hand_computed_values(system, fitted):
    eps, _, _ = system
    policies = stack_params([init_policy(jax.random.PRNGKey(i), 5, 4) for i in range(2)])
    starts = eps.obs[eps.t == 0]
    gamma, horizon = 0.9, 12
    kw = dict(horizon=horizon, n_episodes=32, gamma=gamma, key=jax.random.PRNGKey(0))
    one = lambda s, a, s2: 1.0 + 0 * s2[..., 0]
    at5 = lambda s2: s2[..., 4] >= 4.5          # the clock reaches 5 at step 4
    clock = lambda s, a, s2: s2[..., 4]
    never = lambda s2: 0 * s2[..., 0]
    fm = fitted("base")
    # reward 1 until done: 1 + gamma + ... + gamma^4, whatever the noise
    v = M.rollout_values(fm, 0, policies, starts, task=_Task(one, at5), **kw)
    np.testing.assert_allclose(v, np.sum(gamma ** np.arange(5)) * np.ones(2), rtol=1e-5)
    # reward = the clock, which the model moves by 1 a step from 0
    want = np.sum(gamma ** np.arange(horizon) * np.arange(1, horizon + 1))
    for name in ("base", "ctx", "ah2"):  # the past (and context) carried along
        for seed_index in (0, 1):
            v = M.rollout_values(fitted(name), seed_index, policies, starts,
                                 task=_Task(clock, never), **kw)
            np.testing.assert_allclose(v, want * np.ones(2), rtol=0.02)
    with pytest.raises(ValueError, match="seed_index"):
        M.rollout_values(fm, 2, policies, starts, task=_Task(one, never), **kw)
    with pytest.raises(ValueError, match="start_obs"):
        M.rollout_values(fm, 0, policies, starts[:, :3], task=_Task(one, never), **kw)


def test_fit_models_stops_on_nan_and_names_the_seed():
    from rl2s_jax.diagnose.planted import make_planted

    eps = from_dataset(make_planted("clean", n_episodes=8, seed=0))
    with pytest.raises(M.ModelDiverged, match="turned NaN/Inf") as err:  # absurd lr
        M.fit_models(eps, np.arange(eps.n_episodes), M.ModelSpec(steps=300, lr=1e30),
                     seeds=(0, 1))
    assert err.value.last_good is not None
