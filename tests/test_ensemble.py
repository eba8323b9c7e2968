"""The dynamics-model family and its ensemble (rl2s_jax.model.dynamics, Simulator, train.py):
members against NumPy, rollout modes and disagreement, one member = the single generator, an
ensemble = its members trained separately, elites and early stopping against NumPy
references, the moving average, pre-training then adversarial steps.

Every check is against plain NumPy / SciPy or a hand-run of the same single-member code."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from scipy import stats
from test_train import _policies as _pm_policies  # biased pointmass policies

from rl2s_jax import train as T
from rl2s_jax.data.collect import collect
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model import generator as models
from rl2s_jax.model.simulator import Simulator

TASK = get_task("pointmass")
BIASES = [-2.0, 0.0, 1.0, 2.0]


@pytest.fixture(scope="module")
def pm():
    """A point-mass Dataset of 4 biased policies (600 transitions each: 12 episodes)."""
    policies = _pm_policies(BIASES)
    ds = collect(TASK.make_env(), policies, key=jax.random.PRNGKey(0), transitions_per_policy=600,
                 envs_per_policy=2, episode_length=TASK.episode_length, task="pointmass",
                 value_episodes=4, progress=False)
    return ds, policies


def _np_mlp(layers, x, silu=False):
    x = np.asarray(x, np.float64)
    act = (lambda v: v / (1.0 + np.exp(-v))) if silu else (lambda v: np.maximum(v, 0.0))
    for layer in layers[:-1]:
        x = act(x @ np.asarray(layer["w"], np.float64) + np.asarray(layer["b"]))
    return x @ np.asarray(layers[-1]["w"], np.float64) + np.asarray(layers[-1]["b"])


def _np_bound(raw, lo, hi):
    sp = lambda v: np.logaddexp(0.0, v)
    return lo + sp(hi - sp(hi - raw) - lo)


def _np_member(params, x):
    """(mean, log_std) of one member in NumPy (state or global noise, fixed or learned bounds)."""
    out = _np_mlp(params["layers"], x, silu="silu" in params)
    lo, hi = dyn.LOG_STD_MIN, dyn.LOG_STD_MAX
    if "max_log_std" in params:
        lo, hi = (np.asarray(params[k], np.float64) for k in ("min_log_std", "max_log_std"))
    if "log_std" in params:
        return out, np.broadcast_to(_np_bound(np.asarray(params["log_std"], np.float64), lo, hi),
                                    out.shape)
    o = out.shape[-1] // 2
    return out[..., :o], _np_bound(out[..., o:], lo, hi)


def _member(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _norm(rng, o, a):
    return models.Normalizer(
        obs_mean=jnp.asarray(rng.normal(size=o), jnp.float32),
        obs_std=jnp.asarray(rng.uniform(0.5, 2, size=o), jnp.float32),
        act_mean=jnp.zeros(a), act_std=jnp.ones(a),
        delta_mean=jnp.asarray(rng.normal(size=o) * 0.01, jnp.float32),
        delta_std=jnp.asarray(rng.uniform(0.05, 0.1, size=o), jnp.float32))


# ------------------------------------------------------------------------- one member


@pytest.mark.parametrize("noise", ["state", "global"])
def test_member_with_learned_bounds_matches_numpy(noise):
    o, a, n = 3, 2, 200
    rng = np.random.default_rng(0)
    spec = dyn.DynamicsSpec(hidden=(16,), noise=noise, log_std_bounds="learned")
    p = dyn.init_member(jax.random.PRNGKey(0), spec, o, a)
    assert set(p) == {"layers", "max_log_std", "min_log_std"} | ({"log_std"} if noise ==
                                                                   "global" else set())
    p["layers"][-1]["w"] = p["layers"][-1]["w"] * 300.0                # outputs far out
    p["max_log_std"] = jnp.asarray([0.5, -1.0, 2.0])
    p["min_log_std"] = jnp.asarray([-3.0, -4.0, -0.5])
    if noise == "global":
        p["log_std"] = jnp.asarray([5.0, -9.0, 0.3])
    x = rng.normal(size=(n, o + a)).astype(np.float32)
    mean, log_std = (np.asarray(v, np.float64) for v in dyn.member_dist(p, jnp.asarray(x)))
    ref_mean, ref_ls = _np_member(p, x)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(log_std, ref_ls, rtol=1e-4, atol=1e-4)
    # within each dim's learned bounds (the top overshoots by at most log(1 + e^(lo - hi)))
    hi, lo = np.asarray(p["max_log_std"]), np.asarray(p["min_log_std"])
    assert np.all(log_std >= lo - 1e-6) and np.all(log_std <= hi + np.log1p(np.exp(lo - hi)))
    assert float(dyn.bound_penalty(p)) == pytest.approx(hi.sum() - lo.sum())
    # the NLL is SciPy's
    y = rng.normal(size=(n, o))
    np.testing.assert_allclose(np.asarray(dyn.gaussian_nll(mean, log_std, y)),
                               -stats.norm.logpdf(y, mean, np.exp(log_std)).sum(-1), rtol=1e-5)
    # weight decay touches the weight matrices only
    mask = dyn.weight_mask(p)
    assert all(mask["layers"][i]["w"] and not mask["layers"][i]["b"] for i in range(2))
    assert not mask["max_log_std"] and not mask["min_log_std"]


def test_silu_member_matches_numpy_and_its_parameters_name_the_activation():
    """activation="silu": the hidden layers apply x sigmoid(x); the member's parameters carry
    the marker (a scalar that no computation reads) so that every apply path, and a member
    loaded from a checkpoint, takes it; the ReLU member of the same weights differs."""
    o, a, n = 3, 2, 100
    spec = dyn.DynamicsSpec(hidden=(16, 16), activation="silu")
    p = dyn.init_member(jax.random.PRNGKey(1), spec, o, a)
    assert set(p) == {"layers", "silu"} and p["silu"].shape == ()
    assert not dyn.weight_mask(p)["silu"]
    p["layers"][-1]["w"] = p["layers"][-1]["w"] * 100.0
    x = np.random.default_rng(1).normal(size=(n, o + a)).astype(np.float32)
    mean, log_std = (np.asarray(v, np.float64) for v in dyn.member_dist(p, jnp.asarray(x)))
    ref_mean, ref_ls = _np_member(p, x)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(log_std, ref_ls, rtol=1e-4, atol=1e-4)
    relu = {"layers": p["layers"]}
    assert np.abs(np.asarray(dyn.member_dist(relu, jnp.asarray(x))[0]) - mean).max() > 1e-2
    # an ensemble of SiLU members keeps the marker per member, and the numpy init matches
    ens = dyn.init_ensemble(jax.random.PRNGKey(2), spec, o, a, 3)
    assert ens["silu"].shape == (3,)
    assert set(dyn.init_member_numpy(0, spec, o, a)) == {"layers", "silu"}
    with pytest.raises(ValueError, match="activation"):
        dyn.DynamicsSpec(activation="tanh").validate()
    with pytest.raises(ValueError, match="dynamics.activation"):
        T.TrainConfig().override({"gen_activation": "gelu"}).validate()


def test_rank_members_matches_numpy():
    rng = np.random.default_rng(1)
    f = jax.jit(dyn.rank_members)
    for trial in range(20):
        nll = np.round(rng.normal(size=7), 1 if trial % 2 else 3).astype(np.float32)
        nll[rng.random(7) < 0.2] = np.nan
        order = np.argsort(np.where(np.isnan(nll), np.inf, nll), kind="stable")
        want = np.empty(7, int)
        want[order] = np.arange(7)
        np.testing.assert_array_equal(np.asarray(f(jnp.asarray(nll))), want, err_msg=str(nll))


# ------------------------------------------------------------------------ the ensemble


@pytest.fixture(scope="module")
def ens():
    """An ensemble of 4 members with visible, different outputs, ranked [2, 0, 3, 1]."""
    o, a = 3, 2
    spec = dyn.DynamicsSpec(hidden=(16,))
    gen = dyn.init_ensemble(jax.random.PRNGKey(0), spec, o, a, 4)
    gen["layers"][-1]["w"] = gen["layers"][-1]["w"] * 100.0
    gen["layers"][-1]["b"] = gen["layers"][-1]["b"].at[:, o:].set(-1.0)
    norm = _norm(np.random.default_rng(2), o, a)
    return gen, norm, jnp.asarray([2, 0, 3, 1], jnp.int32)


def _sim(ens, mode, noise_scale=1.0, uncertainty="std"):
    gen, norm, rank = ens
    return Simulator(gen=gen, norm=norm, rank=rank, n_elites=2, member_mode=mode,
                     noise_scale=noise_scale, obs_clip=None, uncertainty=uncertainty)


def _np_members(ens, obs, act):
    gen, norm, _ = ens
    x = np.concatenate([np.asarray(norm.input_obs(obs)), np.asarray(norm.norm_act(act))], -1)
    ms, ls = zip(*[_np_member(_member(gen, i), x) for i in range(4)], strict=True)
    return np.stack(ms), np.stack(ls)                                   # [E, n, o]


def test_rollout_modes_log_prob_and_disagreement_match_numpy(ens):
    gen, norm, rank = ens
    rng = np.random.default_rng(3)
    n = 400
    obs = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    act = jnp.asarray(rng.uniform(-1, 1, size=(n, 2)), jnp.float32)
    means, log_stds = _np_members(ens, obs, act)
    elites = [1, 3]                                    # rank 0 and 1
    d_mean, d_std = np.asarray(norm.delta_mean), np.asarray(norm.delta_std)
    to_next = lambda m: np.asarray(obs) + d_mean + d_std * m
    key = jax.random.PRNGKey(4)

    # "random": with no noise every row is one elite's mean, both elites in use
    s = np.asarray(_sim(ens, "random", noise_scale=0.0).sample(obs, act, key))
    err = np.abs(s[None] - to_next(means)).max(-1)                       # [E, n]
    which = err.argmin(0)
    assert np.all(err.min(0) < 1e-4) and set(which) == set(elites)
    assert 0.4 < np.mean(which == elites[0]) < 0.6
    # ... and its density is the elites' uniform mixture
    y = rng.normal(size=(n, 3)) * 0.5
    nxt = jnp.asarray(np.asarray(obs) + d_mean + d_std * y, jnp.float32)
    dens = np.mean([stats.norm.pdf(y, means[e], np.exp(log_stds[e])).prod(-1) for e in elites], 0)
    np.testing.assert_allclose(np.asarray(_sim(ens, "random").log_prob(obs, act, nxt)),
                               np.log(dens), rtol=1e-4, atol=1e-4)
    # "mean": the elites' average mean, std sqrt(mean variance)
    m_avg = means[elites].mean(0)
    sd_avg = np.sqrt(np.exp(2 * log_stds[elites]).mean(0))
    np.testing.assert_allclose(np.asarray(_sim(ens, "mean", 0.0).sample(obs, act, key)),
                               to_next(m_avg), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(_sim(ens, "mean").log_prob(obs, act, nxt)),
                               stats.norm.logpdf(y, m_avg, sd_avg).sum(-1), rtol=1e-4, atol=1e-4)
    # "fixed": the best-ranked member (index 1)
    np.testing.assert_allclose(np.asarray(_sim(ens, "fixed", 0.0).sample(obs, act, key)),
                               to_next(means[1]), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(_sim(ens, "fixed").mean(obs, act)), to_next(means[1]),
                               rtol=1e-4, atol=1e-4)
    # predictive (what diagnosis reads): the mixture's mean and std
    pm_, ps_ = (np.asarray(v) for v in _sim(ens, "random").predictive(obs, act))
    np.testing.assert_allclose(pm_, m_avg, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(ps_, np.sqrt(sd_avg**2 + means[elites].var(0)), rtol=1e-4)
    # disagreement: the elites' std (over members, rms over dims) / largest pairwise distance
    std_ref = np.sqrt(means[elites].var(0).mean(-1))
    np.testing.assert_allclose(np.asarray(_sim(ens, "random").uncertainty_fn(obs, act)), std_ref,
                               rtol=1e-4)
    pair_ref = np.sqrt(((means[1] - means[3]) ** 2).mean(-1))
    np.testing.assert_allclose(np.asarray(_sim(ens, "random", uncertainty="max_pairwise")
                                          .disagreement(obs, act)), pair_ref, rtol=1e-4)
    # step: the sample and the disagreement from one pass
    sim = _sim(ens, "random")
    nxt_s, u = sim.step(obs, act, key)
    np.testing.assert_array_equal(np.asarray(nxt_s), np.asarray(sim.sample(obs, act, key)))
    np.testing.assert_allclose(np.asarray(u), std_ref, rtol=1e-4)
    # transition: the elites' mean next state, the same sample, the disagreement
    t_mean, t_next, t_u = (np.asarray(v) for v in sim.transition(obs, act, key))
    np.testing.assert_allclose(t_mean, to_next(m_avg), rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(t_next, np.asarray(nxt_s))
    np.testing.assert_allclose(t_u, std_ref, rtol=1e-4)
    # with noise (same key: same members), the normalised residual is standard normal
    s = np.asarray(sim.sample(obs, act, key))
    pick = lambda x: np.take_along_axis(x, which[None, :, None], 0)[0]
    z = ((s - np.asarray(obs) - d_mean) / d_std - pick(means)) / np.exp(pick(log_stds))
    assert abs(z.mean()) < 0.1 and abs(z.std() - 1) < 0.1


def test_one_member_simulator_is_the_single_generator(ens):
    _, norm, _ = ens
    gen = models.init_generator(jax.random.PRNGKey(5), 3, 2, (16,))
    gen[-1]["w"] = gen[-1]["w"] * 50.0
    sim = Simulator(gen=gen, norm=norm, obs_clip=None)
    assert sim.n_members == 1
    rng = np.random.default_rng(6)
    obs = jnp.asarray(rng.normal(size=(50, 3)), jnp.float32)
    act = jnp.asarray(rng.normal(size=(50, 2)), jnp.float32)
    key = jax.random.PRNGKey(7)
    np.testing.assert_array_equal(np.asarray(sim.sample(obs, act, key)),
                                  np.asarray(models.generator_sample(gen, norm, obs, act, key)))
    np.testing.assert_array_equal(np.asarray(sim.mean(obs, act)),
                                  np.asarray(models.generator_mean(gen, norm, obs, act)))
    nxt = obs + 0.01
    np.testing.assert_array_equal(np.asarray(sim.log_prob(obs, act, nxt)),
                                  np.asarray(models.generator_log_prob(gen, norm, obs, act, nxt)))
    np.testing.assert_array_equal(np.asarray(sim.disagreement(obs, act)), np.zeros(50))
    # a one-member ensemble made by the family's init is the generator made by init_generator
    one = dyn.init_ensemble(jax.random.PRNGKey(5), dyn.DynamicsSpec(hidden=(16,)), 3, 2, 1)
    ref = models.init_generator(jax.random.PRNGKey(5), 3, 2, (16,))
    for layer, r in zip(one["layers"], ref, strict=True):
        np.testing.assert_array_equal(np.asarray(layer["w"][0]), np.asarray(r["w"]))


# ------------------------------------------------------------------------- training

_init = jax.jit(T.init, static_argnums=1)
_steps = jax.jit(T.train_steps, static_argnames=("n_steps", "phase"))
_step = jax.jit(T.train_step, static_argnames="phase")


def test_one_member_training_reproduces_the_single_generator(pm):
    """E = 1 with LEGACY_MODEL: bc's train_step is the single generator's likelihood loop
    (init_generator, clip + Adam, the same keys and batches), run here by hand."""
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="bc", vd_every=0, vd_horizon=50,
                              **T.LEGACY_MODEL)
    data = T.make_train_data(ds, policies, cfg)
    state, _ = _steps(_init(jax.random.PRNGKey(3), cfg, data), data, n_steps=3)

    key = jax.random.PRNGKey(3)
    k_gen, *_, key = jax.random.split(key, 7)
    gen = models.init_generator(k_gen, 2, 1, cfg.dynamics.hidden)
    tx = optax.chain(optax.clip(cfg.grad_clip), optax.adam(cfg.bc_lr))
    opt = tx.init(gen)
    everyone = jnp.ones((len(BIASES),), bool)

    @jax.jit
    def updates(gen, opt, k_upd):
        def one(carry, k):
            gen, opt = carry
            batch = T.data._real_batch(k, data, everyone, cfg.batch_size)
            loss, g = jax.value_and_grad(
                lambda p: -jnp.mean(models.generator_log_prob(p, data.norm, *batch)))(gen)
            u, opt = tx.update(g, opt, gen)
            return (optax.apply_updates(gen, u), opt), loss
        return jax.lax.scan(one, (gen, opt), jax.random.split(k_upd, cfg.updates_per_step))[0]

    for _ in range(3):
        key, _, k_upd, _ = jax.random.split(key, 4)
        gen, opt = updates(gen, opt, k_upd)
    for layer, ref in zip(state.gen["layers"], gen, strict=True):
        np.testing.assert_allclose(np.asarray(layer["w"][0]), np.asarray(ref["w"]), rtol=1e-6,
                                   atol=1e-7)
        np.testing.assert_allclose(np.asarray(layer["b"][0]), np.asarray(ref["b"]), rtol=1e-6,
                                   atol=1e-7)


def _np_heldout_nll(gen, data):
    """Every member's mean held-out NLL [E], NumPy."""
    norm = data.norm
    x = np.concatenate([np.asarray(norm.input_obs(data.val_obs)),
                        np.asarray(norm.norm_act(data.val_action))], -1)
    y = np.asarray(norm.norm_delta(data.val_obs, data.val_next_obs), np.float64)
    out = []
    for i in range(dyn.n_members(gen)):
        m, ls = _np_member(_member(gen, i), x)
        out.append((0.5 * ((y - m) / np.exp(ls)) ** 2 + ls + 0.5 * np.log(2 * np.pi)).sum(-1)
                   .mean())
    return np.asarray(out)


@pytest.fixture(scope="module")
def bc3(pm):
    """bc with 3 members (learned bounds, weight decay, no early stopping): init and 3 steps."""
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="bc", vd_every=0, vd_horizon=50,
                              early_stop_patience=0, gen_weight_decay=1e-3)
    data = T.make_train_data(ds, policies, cfg)
    state0 = _init(jax.random.PRNGKey(3), cfg, data)
    state, metrics = _steps(state0, data, n_steps=3)
    return cfg, data, state0, state, metrics


def test_ensemble_equals_its_members_trained_separately(bc3):
    """One vmapped program of 3 members = each member's own likelihood loop
    (``member_mle_updates``) with the member's keys (``dynamics.member_keys``)."""
    cfg, data, state0, state, _ = bc3
    everyone = jnp.ones((data.n_policies,), bool)
    one = jax.jit(lambda g, o, k: T.member_mle_updates(g, o, k, data, everyone, data.norm, cfg))
    key = state0.key
    members = [(_member(state0.gen, i), _member(state0.gen_opt, i)) for i in range(3)]
    for _ in range(3):
        key, _, k_upd, _ = jax.random.split(key, 4)
        keys = dyn.member_keys(k_upd, 3)
        members = [one(g, o, keys[i])[:2] for i, (g, o) in enumerate(members)]
    for i, (g, _) in enumerate(members):
        for got, want in zip(jax.tree_util.tree_leaves(_member(state.gen, i)),
                             jax.tree_util.tree_leaves(g), strict=True):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-6)
    w = np.asarray(state.gen["layers"][0]["w"])
    assert not np.allclose(w[0], w[1]) and not np.allclose(w[1], w[2])  # different members


def test_elites_are_the_lowest_heldout_nll(bc3):
    """The state's held-out NLL per member is NumPy's on the held-out rows, the ranks its
    stable argsort, the elites (n_elites = 2) the two lowest; the metric averages them."""
    cfg, data, _, state, metrics = bc3
    nll = _np_heldout_nll(state.gen, data)
    np.testing.assert_allclose(np.asarray(state.heldout_nll), nll, rtol=1e-4, atol=1e-4)
    want = np.empty(3, int)
    want[np.argsort(nll, kind="stable")] = np.arange(3)
    np.testing.assert_array_equal(np.asarray(state.rank), want)
    np.testing.assert_allclose(float(metrics["heldout_nll"][-1]), np.sort(nll)[:2].mean(),
                               rtol=1e-4)
    sim = T.simulator(state)
    assert sim.n_elites == cfg.n_elites == 2
    np.testing.assert_array_equal(np.asarray(dyn.elite_mask(sim.rank, 2, 3)), want < 2)
    assert np.all(np.asarray(state.best_nll) <= nll + 1e-4)  # tracked even without stopping


def test_track_best_matches_numpy():
    rng = np.random.default_rng(8)
    E, T_, patience, min_delta = 5, 30, 3, 0.05
    seqs = np.cumsum(rng.normal(-0.02, 0.1, size=(T_, E)), 0).astype(np.float32)
    seqs[rng.random((T_, E)) < 0.05] = np.nan
    f = jax.jit(lambda n, b, s, st: T.track_best(n, b, s, st, min_delta=min_delta,
                                                 patience=patience))
    best, since, stopped = (jnp.full(E, jnp.inf), jnp.zeros(E, jnp.int32), jnp.zeros(E, bool))
    r_best, r_since, r_stopped = np.full(E, np.inf), np.zeros(E, int), np.zeros(E, bool)
    for t in range(T_):
        improved, best, since, stop_now = f(jnp.asarray(seqs[t]), best, since, stopped)
        stopped = stopped | stop_now
        for e in range(E):
            if r_stopped[e]:
                continue
            if seqs[t, e] < r_best[e] - min_delta:
                r_best[e], r_since[e] = seqs[t, e], 0
            else:
                r_since[e] += 1
            r_stopped[e] = r_since[e] >= patience
        np.testing.assert_array_equal(np.asarray(best), r_best.astype(np.float32))
        np.testing.assert_array_equal(np.asarray(since), r_since)
        np.testing.assert_array_equal(np.asarray(stopped), r_stopped)
    assert r_stopped.any()


def test_early_stopping_and_moving_average_in_training(pm):
    """bc, 3 members, patience 2 and min_delta 1 nat (on this data the held-out NLL falls
    about 0.3 nats a step, so only the first step counts as a gain): a member stops when its
    steps without gain reach 2, gets the weights of its best held-out
    NLL back and never changes again; best_nll is NumPy's NLL of those weights. The moving
    average (decay 0.5) is NumPy's recursion over the weights, and what simulator() returns."""
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="bc", vd_every=0, vd_horizon=50,
                              early_stop_patience=2, early_stop_min_delta=1.0, ema_decay=0.5)
    data = T.make_train_data(ds, policies, cfg)
    state = _init(jax.random.PRNGKey(1), cfg, data)
    ema = jax.tree_util.tree_map(np.asarray, state.gen)
    frozen = {}
    for _ in range(7):
        prev_since, prev_stopped = np.asarray(state.since_best), np.asarray(state.stopped)
        state, m = _step(state, data)
        since, stopped = np.asarray(state.since_best), np.asarray(state.stopped)
        nll = _np_heldout_nll(state.gen, data)
        np.testing.assert_allclose(np.asarray(state.heldout_nll), nll, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(np.asarray(state.best_nll), _np_heldout_nll(state.best_gen,
                                                                               data),
                                   rtol=1e-4, atol=1e-4)
        for e in range(3):
            if prev_stopped[e]:   # frozen: unchanged, nothing counted
                assert since[e] == prev_since[e] and stopped[e]
                for a, b in zip(jax.tree_util.tree_leaves(_member(state.gen, e)),
                                frozen[e], strict=True):
                    np.testing.assert_array_equal(np.asarray(a), b)
            elif stopped[e]:      # stops now: the count reached patience, best weights back
                assert since[e] == prev_since[e] + 1 == cfg.early_stop_patience
                for a, b in zip(jax.tree_util.tree_leaves(_member(state.gen, e)),
                                jax.tree_util.tree_leaves(_member(state.best_gen, e)),
                                strict=True):
                    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
                frozen[e] = [np.asarray(x) for x in jax.tree_util.tree_leaves(
                    _member(state.gen, e))]
            else:
                assert since[e] in (0, prev_since[e] + 1) and since[e] < cfg.early_stop_patience
        assert int(m["n_stopped"]) == stopped.sum()
        ema = jax.tree_util.tree_map(lambda e, g: 0.5 * e + 0.5 * np.asarray(g), ema, state.gen)
        for a, b in zip(jax.tree_util.tree_leaves(state.ema_gen), jax.tree_util.tree_leaves(ema),
                        strict=True):
            np.testing.assert_allclose(np.asarray(a), b, rtol=1e-5, atol=1e-6)
    assert frozen, "no member stopped: the test did not exercise early stopping"
    for a, b in zip(jax.tree_util.tree_leaves(T.simulator(state).gen),
                    jax.tree_util.tree_leaves(state.ema_gen), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(jax.tree_util.tree_leaves(T.simulator(state, average=False).gen),
                    jax.tree_util.tree_leaves(state.gen), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_adversarial_phase_starts_from_the_best_pretrained_weights(pm):
    """Pre-training then WGAIL: the phases switch at pretrain_steps (metrics say which ran),
    the first adversarial step restarts from best_gen with fresh Adam moments, the critic
    warm-up leaves the members alone, and the device-chosen phase (lax.cond) equals the
    host-chosen one."""
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="rl2s", vd_horizon=20, vd_every=2,
                              pretrain_steps=2, disc_warmup_steps=1, early_stop_patience=1,
                              early_stop_min_delta=10.0)
    data = T.make_train_data(ds, policies, cfg)
    state = _init(jax.random.PRNGKey(2), cfg, data)
    assert [cfg.phase(s) for s in range(4)] == ["pretrain", "pretrain", "main", "main"]
    pre, m_pre = _steps(state, data, n_steps=2, phase="pretrain")
    np.testing.assert_array_equal(np.asarray(m_pre["phase"]), [0, 0])
    assert np.isfinite(np.asarray(m_pre["nll"])).all() and np.isnan(m_pre["gen_loss"]).all()
    # min_delta 10: only the first step gains, so every member stopped at step 2 on its best
    assert np.asarray(pre.stopped).all()
    start = T.step._start_adversarial(pre)
    for a, b in zip(jax.tree_util.tree_leaves(start.gen), jax.tree_util.tree_leaves(pre.best_gen),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    fresh = dyn.map_members(T.step._gen_tx(cfg, cfg.gen_lr).init, start.gen)
    for a, b in zip(jax.tree_util.tree_leaves(start.gen_opt), jax.tree_util.tree_leaves(fresh),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    not_first = T.step._start_adversarial(pre.replace(step=pre.step + 1))
    for a, b in zip(jax.tree_util.tree_leaves(not_first.gen_opt),
                    jax.tree_util.tree_leaves(pre.gen_opt), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # step 2 (critic warm-up): members unchanged from best_gen; step 3 moves them
    adv, m_adv = _steps(pre, data, n_steps=1, phase="main")
    assert int(m_adv["phase"][0]) == 1 and np.isnan(m_adv["nll"]).all()
    assert np.isfinite(np.asarray(m_adv["disc_loss"])).all()
    for a, b in zip(jax.tree_util.tree_leaves(adv.gen), jax.tree_util.tree_leaves(pre.best_gen),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    adv2, _ = _steps(adv, data, n_steps=1, phase="main")
    assert not np.allclose(np.asarray(adv2.gen["layers"][0]["w"]),
                           np.asarray(adv.gen["layers"][0]["w"]))
    # the same four steps with the phase chosen on the device
    cond, m_cond = _steps(state, data, n_steps=4)
    np.testing.assert_array_equal(np.asarray(m_cond["phase"]), [0, 0, 1, 1])
    for a, b in zip(jax.tree_util.tree_leaves(cond), jax.tree_util.tree_leaves(adv2),
                    strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


# --------------------------------------------------------------- the multi-step loss


def test_episode_steps_left_matches_a_loop():
    rng = np.random.default_rng(3)
    n = 400
    pid = np.sort(rng.integers(0, 3, n))
    ep = np.cumsum(rng.random(n) < 0.08)              # episodes of random lengths
    t = np.arange(n) - np.maximum.accumulate(np.r_[0, np.flatnonzero(np.diff(ep)) + 1][
        np.searchsorted(np.r_[0, np.flatnonzero(np.diff(ep)) + 1], np.arange(n), "right") - 1])
    t[rng.random(n) < 0.03] += 5                     # gaps: held-out rows removed mid-episode
    ref = np.zeros(n, int)
    for i in range(n - 2, -1, -1):
        if pid[i + 1] == pid[i] and ep[i + 1] == ep[i] and t[i + 1] == t[i] + 1:
            ref[i] = ref[i + 1] + 1
    np.testing.assert_array_equal(T.episode_steps_left(pid, ep, t), ref)
    assert T.episode_steps_left(pid[:0], ep[:0], t[:0]).shape == (0,)


def test_train_data_steps_left_follow_the_episodes(pm):
    ds, policies = pm
    data = T.make_train_data(ds, policies, T.TrainConfig.small(task="pointmass", method="bc"))
    left = np.asarray(data.steps_left)
    obs, nxt = np.asarray(data.obs), np.asarray(data.next_obs)
    go_on = np.flatnonzero(left[:-1] >= 1)
    assert go_on.size > 0.8 * len(left)
    np.testing.assert_array_equal(nxt[go_on], obs[go_on + 1])   # row i + 1 continues row i
    np.testing.assert_array_equal(left[go_on + 1], left[go_on] - 1)
    ends = np.flatnonzero(left == 0)
    assert (len(ends) - 1) == np.sum(np.any(nxt[ends[:-1]] != obs[ends[:-1] + 1], -1))


def test_multistep_error_matches_numpy(pm):
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="bc", multistep_steps=4)
    data = T.make_train_data(ds, policies, cfg)
    norm = data.norm
    member = dyn.init_member(jax.random.PRNGKey(7), cfg.dynamics, 2, 1)
    obs, act, nxt, valid = T.data._real_windows(jax.random.PRNGKey(2), data,
                                           jnp.ones(data.n_policies, bool), 64, 4)
    assert (~np.asarray(valid)).any() and np.asarray(valid)[:, 0].all()
    got = T.multistep_error(member, norm, obs, act, nxt, valid, cfg.obs_clip)
    n = {k: np.asarray(getattr(norm, k), np.float64) for k in (
        "obs_mean", "obs_std", "act_mean", "act_std", "delta_mean", "delta_std")}
    mask = np.asarray(norm.obs_input_mask, np.float64)
    s = np.asarray(obs, np.float64)
    errs = []
    for j in range(4):
        x = np.concatenate([(s - n["obs_mean"]) / n["obs_std"] * mask,
                            (np.asarray(act[:, j]) - n["act_mean"]) / n["act_std"]], -1)
        mean, _ = _np_member(member, x)
        s = np.clip(s + n["delta_mean"] + n["delta_std"] * mean,
                    n["obs_mean"] - cfg.obs_clip * n["obs_std"],
                    n["obs_mean"] + cfg.obs_clip * n["obs_std"])
        errs.append((mask * ((s - np.asarray(nxt[:, j])) / n["obs_std"]) ** 2).sum(-1) / mask.sum())
    w = np.asarray(valid, np.float64)[:, 1:]
    ref = (w * np.stack(errs, 1)[:, 1:]).sum() / w.sum()
    np.testing.assert_allclose(float(got), ref, rtol=1e-4)


def test_multistep_training_lowers_the_k_step_error(pm):
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="bc", vd_every=0, vd_horizon=50,
                              multistep_steps=5, multistep_weight=1.0)
    data = T.make_train_data(ds, policies, cfg)
    state = T.init(jax.random.PRNGKey(0), cfg, data)
    windows = T.data._real_windows(jax.random.PRNGKey(5), data, jnp.ones(data.n_policies, bool),
                              256, 5)

    def k_step_error(st):
        best = int(np.argmin(np.asarray(st.rank)))
        member = jax.tree_util.tree_map(lambda x: x[best], st.gen)
        return float(T.multistep_error(member, st.norm, *windows, cfg.obs_clip))

    before = k_step_error(state)
    state, m = T.train_steps(state, data, 15)
    after = k_step_error(state)
    assert bool(np.all(m["finite"])) and after < 0.5 * before, (before, after)
    # the update's loss is the one-step NLL (beta 0: plain) of the window's first step plus
    # weight x the k-step error (and the log-std bound penalty), on the windows its key draws
    member = jax.tree_util.tree_map(lambda x: x[0], state.gen)
    one = dataclasses.replace(cfg, updates_per_step=1, multistep_weight=2.5, nll_beta=0.0)
    everyone = jnp.ones(data.n_policies, bool)
    key = jax.random.PRNGKey(11)
    _, _, got = T.member_mle_updates(member, T.step._gen_tx(one, one.bc_lr).init(member), key, data,
                                     everyone, state.norm, one)
    obs, act, nxt, valid = T.data._real_windows(jax.random.split(key, 1)[0], data, everyone,
                                           one.batch_size, 5)
    want = (-jnp.mean(models.generator_log_prob(member, state.norm, obs, act[:, 0], nxt[:, 0]))
            + 2.5 * T.multistep_error(member, state.norm, obs, act, nxt, valid, one.obs_clip)
            + one.log_std_bound_weight * dyn.bound_penalty(member))
    np.testing.assert_allclose(float(got), float(want), rtol=1e-5)
    with pytest.raises(ValueError, match="multistep_steps"):
        T.TrainConfig.small(task="pointmass", multistep_steps=0).validate()
    with pytest.raises(ValueError, match="multistep_weight"):
        T.TrainConfig.small(task="pointmass", multistep_weight=-1.0).validate()


# --------------------------------------------------------------- the likelihood anchor


@pytest.mark.parametrize("anchor_on", ["all", "selected", "both"])
def test_adversarial_nll_anchor_adds_weight_times_the_real_batch_nll(pm, anchor_on):
    """adv_nll_weight w: each member's adversarial loss gains w x its NLL of the anchor's batch
    (the critic updates before it do not depend on w): "selected" the real batch the update
    draws from the CVaR set, "all" its own batch of every training policy (the real batch's key
    folded with 1), "both" the mean of the two; a large w keeps the members' held-out NLL near
    the pre-trained one where pure WGAIL moves it."""
    ds, policies = pm
    cfg = T.TrainConfig.small(task="pointmass", method="gail", vd_horizon=20, vd_every=0,
                              updates_per_step=1, early_stop_patience=0, adv_nll_weight=0.0,
                              adv_nll_on=anchor_on)
    data = T.make_train_data(ds, policies, cfg)
    state = T.init(jax.random.PRNGKey(4), cfg, data)
    state = state.replace(selected=jnp.arange(state.selected.shape[0]) < 2)  # as a CVaR set
    key = jax.random.PRNGKey(9)
    w = 2.5
    _, m0 = T.step._adversarial_updates(state, data, key)
    anchored = state.replace(config=cfg.override({"adversarial.nll_weight": w}))
    _, mw = T.step._adversarial_updates(anchored, data, key)
    k_real = jax.random.split(jax.random.split(key, 1)[0], 4)[1]
    draws = {"selected": [(k_real, state.selected)],
             "all": [(jax.random.fold_in(k_real, 1), jnp.ones_like(state.selected))]}
    draws["both"] = draws["selected"] + draws["all"]

    def nll_of(k, selected):
        r_obs, r_act, r_next = T.data._real_batch(k, data, selected, cfg.batch_size)
        return np.mean([float(-jnp.mean(models.generator_log_prob(
            _member(state.gen, i), state.norm, r_obs, r_act, r_next)))
            for i in range(cfg.ensemble_size)])

    nll = np.mean([nll_of(k, sel) for k, sel in draws[anchor_on]])
    np.testing.assert_allclose(float(mw["gen_loss"]) - float(m0["gen_loss"]), w * nll,
                               rtol=1e-4, atol=1e-4)
    if anchor_on != "all":
        return  # the behaviour below does not depend on the batch's source
    # behaviour: from a likelihood-trained start, the anchor holds the held-out NLL
    bc = dataclasses.replace(cfg, method="bc", updates_per_step=20)
    start = T.train_steps(T.init(jax.random.PRNGKey(4), bc, data), data, 10)[0]
    nll0 = float(np.mean(np.asarray(T.step._heldout_nll(start.gen, start.norm, data))))
    after = {}
    for weight in (0.0, 10.0):
        adv_cfg = cfg.override({"updates_per_step": 20, "adversarial.nll_weight": weight})
        st = T.init(jax.random.PRNGKey(4), adv_cfg, data).replace(gen=start.gen)
        st = T.train_steps(st, data, 10)[0]
        after[weight] = float(np.mean(np.asarray(T.step._heldout_nll(st.gen, st.norm, data))))
    assert after[10.0] - nll0 < 0.5 * (after[0.0] - nll0), (nll0, after)
    with pytest.raises(ValueError, match="adversarial.nll_weight"):
        T.TrainConfig.small(task="pointmass", adv_nll_weight=-1.0).validate()


# --------------------------------------------------------------- beta-NLL


@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0])
def test_beta_nll_matches_numpy_and_beta_one_gives_the_mean_the_squared_error(beta):
    """generator_beta_nll_loss: SciPy's per-dim NLL weighted by std^(2 beta) (beta 0: the plain
    NLL); with beta = 1 the mean's gradient is that of half the squared error."""
    from rl2s_jax.train import losses
    o, a, n = 3, 2, 64
    rng = np.random.default_rng(1)
    norm = _norm(rng, o, a)
    spec = dyn.DynamicsSpec(hidden=(16,), noise="global", log_std_bounds="learned")
    p = dyn.init_member(jax.random.PRNGKey(3), spec, o, a)
    p["log_std"] = jnp.asarray([0.8, -1.5, 0.1])
    obs = jnp.asarray(rng.normal(size=(n, o)), jnp.float32)
    act = jnp.asarray(rng.normal(size=(n, a)), jnp.float32)
    nxt = obs + jnp.asarray(rng.normal(size=(n, o)) * 0.1, jnp.float32)
    got = float(losses.generator_beta_nll_loss(p, norm, obs, act, nxt, beta)[0])
    mean, log_std = (np.asarray(v, np.float64) for v in models.generator_dist(p, norm, obs, act))
    y = np.asarray(norm.norm_delta(obs, nxt), np.float64)
    per_dim = -stats.norm.logpdf(y, mean, np.exp(log_std))
    want = np.mean(np.sum(np.exp(2 * beta * log_std) * per_dim, -1))
    np.testing.assert_allclose(got, want, rtol=1e-4)
    if beta == 0.0:
        np.testing.assert_allclose(got, float(losses.generator_nll_loss(p, norm, obs, act,
                                                                         nxt)[0]), rtol=1e-6)
    if beta == 1.0:  # "global" noise: the layers reach the loss through the mean only
        g = jax.grad(lambda q: losses.generator_beta_nll_loss(q, norm, obs, act, nxt, 1.0)[0])(p)
        y_j = norm.norm_delta(obs, nxt)
        g_mse = jax.grad(lambda q: 0.5 * jnp.mean(jnp.sum(
            (y_j - models.generator_dist(q, norm, obs, act)[0]) ** 2, -1)))(p)
        for a_, b_ in zip(jax.tree_util.tree_leaves(g["layers"]),
                          jax.tree_util.tree_leaves(g_mse["layers"]), strict=True):
            np.testing.assert_allclose(np.asarray(a_), np.asarray(b_), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="nll_beta"):
        T.TrainConfig.small(task="pointmass", nll_beta=-0.5).validate()
