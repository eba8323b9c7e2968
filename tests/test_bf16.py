"""bf16 matmuls (``TrainConfig.dynamics.matmul_dtype``, issue 40 item 3): the default is the float32
model unchanged; "bfloat16" gives what a NumPy forward pass with its matmul inputs and weights
rounded to bf16 gives (forward and gradient), is refused under other names, survives a
checkpoint, and still learns the point mass's linear dynamics.

References are NumPy in float64 on values rounded by ``ml_dtypes.bfloat16``; each tolerance is
one the float32 path (no rounding) fails, which the tests check as well.
"""
import json

import jax
import jax.numpy as jnp
import ml_dtypes
import numpy as np
import pytest

from rl2s_jax import train as T
from rl2s_jax.envs.tasks import pointmass_dynamics
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model import generator as models
from rl2s_jax.policy import policy as pol
from rl2s_jax.train import losses
from rl2s_jax.train.checkpoint import Checkpointer, load_simulator
from rl2s_jax.train.config import FLAT_NAMES, TrainConfig

FLAT = {v: k for k, v in FLAT_NAMES.items()}  # dotted name -> the flat format's

OBS, ACT = 5, 2
META = {"data": {"obs_size": 2, "action_size": 1}}


def _bf(x) -> np.ndarray:
    """x rounded to bfloat16 (round to nearest even), as float64."""
    return np.asarray(x, np.float32).astype(ml_dtypes.bfloat16).astype(np.float64)


def _f64(x) -> np.ndarray:
    return np.asarray(x, np.float64)


def _np_mlp(layers, x, act, bf16: bool):
    """The MLP in float64; ``bf16``: the hidden layers' matmul inputs and weights rounded."""
    r = _bf if bf16 else _f64
    h = _f64(x)
    for layer in layers[:-1]:
        h = act(r(h) @ r(layer["w"]) + _f64(layer["b"]))
    return h @ _f64(layers[-1]["w"]) + _f64(layers[-1]["b"])


def _np_relu(x):
    return np.maximum(x, 0.0)


def _np_silu(x):
    return x / (1.0 + np.exp(-x))


def _np_softplus(x):
    return np.logaddexp(0.0, x)


def _np_member(params, x, bf16: bool):
    """member_dist in float64: (mean, log_std) of a state-noise member."""
    act = _np_silu if "silu" in params else _np_relu
    out = _np_mlp(params["layers"], x, act, bf16)
    mean, raw = np.split(out, 2, -1)
    if "max_log_std" in params:
        lo, hi = _f64(params["min_log_std"]), _f64(params["max_log_std"])
    else:
        lo, hi = dyn.LOG_STD_MIN, dyn.LOG_STD_MAX
    return mean, lo + _np_softplus(hi - _np_softplus(hi - raw) - lo)


def _rel(a, b) -> float:
    a, b = _f64(a), _f64(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


def _member(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


# ----------------------------------------------------------------------- the forward pass


def test_default_is_the_float32_model_unchanged():
    """Default spec and config: no marker in the parameters (the checkpoints' trees are those
    of before), no bf16 anywhere in the program, and member_dist equals, bit for bit, the
    plain float32 MLP ``x @ w + b`` it computed before the option."""
    assert TrainConfig().dynamics.matmul_dtype == "float32"
    assert TrainConfig.small().dynamics.matmul_dtype == "float32"
    spec = TrainConfig.small().override({"dynamics.hidden": (16, 16)}).dynamics
    p = dyn.init_member(jax.random.PRNGKey(0), spec, OBS, ACT)
    assert "bf16" not in p
    x = jax.random.normal(jax.random.PRNGKey(1), (32, OBS + ACT))

    def previous(p, x):
        h = x
        for layer in p["layers"][:-1]:
            h = jax.nn.relu(h @ layer["w"] + layer["b"])
        out = h @ p["layers"][-1]["w"] + p["layers"][-1]["b"]
        mean, raw = jnp.split(out, 2, -1)
        return mean, dyn.bounded_log_std(raw, p)

    for got, want in zip(dyn.member_dist(p, x), previous(p, x), strict=True):
        assert got.dtype == jnp.float32
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    assert "bf16" not in str(jax.make_jaxpr(dyn.member_dist)(p, x))
    disc, us = models.init_discriminator(jax.random.PRNGKey(2), OBS, ACT, (16, 16))
    norm = dyn.Normalizer.from_data(np.zeros((2, OBS)), np.zeros((2, ACT)), np.ones((2, OBS)))
    s = jnp.ones((4, OBS))
    d_jaxpr = jax.make_jaxpr(lambda d: models.discriminator(d, us, norm, s, s[:, :ACT], s))(disc)
    assert "bf16" not in str(d_jaxpr)


@pytest.mark.parametrize("activation", ["relu", "silu"])
def test_bf16_member_matches_numpy_with_rounded_inputs_and_weights(activation):
    """A bfloat16 member (one, and each of an ensemble through the vmapped path) gives the
    NumPy member with bf16-rounded hidden-layer inputs and weights (output layer float64) to
    2e-5 of the output's scale; float32 outputs. The same parameters without the marker (the
    float32 path) are 1e-3 or more off that reference, and off the bf16 outputs by a small
    relative amount (< 1e-2)."""
    cfg = TrainConfig.small(gen_hidden=(32, 32), gen_activation=activation,
                            gen_log_std_bounds="learned", matmul_dtype="bfloat16")
    spec = cfg.dynamics
    assert spec.matmul_dtype == "bfloat16"
    ens = dyn.init_ensemble(jax.random.PRNGKey(0), spec, OBS, ACT, 3)
    assert set(ens) == {"layers", "bf16", "max_log_std", "min_log_std",
                        *(("silu",) if activation == "silu" else ())}
    assert ens["bf16"].shape == (3,) and ens["bf16"].dtype == jnp.float32
    assert not dyn.weight_mask(ens)["bf16"]
    # the last layer's default scale (0.01) would leave the head near 0: a full-size one
    ens["layers"][-1]["w"] = ens["layers"][-1]["w"] * 100.0
    x = jax.random.normal(jax.random.PRNGKey(1), (64, OBS + ACT)) * 2.0
    means, log_stds = dyn.ensemble_dist(ens, x)
    assert means.dtype == log_stds.dtype == jnp.float32
    for i in range(3):
        p = _member(ens, i)
        ref_mean, ref_ls = _np_member(p, x, bf16=True)
        one = dyn.member_dist(p, x)
        for got, ref in ((means[i], ref_mean), (log_stds[i], ref_ls), (one[0], ref_mean),
                         (one[1], ref_ls)):
            assert _rel(got, ref) < 2e-5, _rel(got, ref)
        f32 = {k: v for k, v in p.items() if k != "bf16"}
        f32_mean = dyn.member_dist(f32, x)[0]
        assert _rel(f32_mean, ref_mean) > 1e-3          # the tolerance tells the paths apart
        assert 0 < _rel(one[0], f32_mean) < 1e-2        # bf16 is a small change
        np.testing.assert_allclose(_f64(f32_mean), _np_member(f32, x, bf16=False)[0],
                                   rtol=1e-4, atol=1e-5 * np.abs(ref_mean).max())


def test_bf16_matmul_gradient_matches_numpy():
    """dynamics.matmul(x, w, "bfloat16") [B, T, i] @ [i, j]: value and both gradients (under
    a cotangent c) are NumPy's on bf16-rounded operands (the cotangent rounded too), float32;
    the float32 matmul is 1e-3 or more off each."""
    x = jax.random.normal(jax.random.PRNGKey(0), (3, 7, 24))
    w = jax.random.normal(jax.random.PRNGKey(1), (24, 9))
    c = jax.random.normal(jax.random.PRNGKey(2), (3, 7, 9))

    def loss(dtype):
        return lambda x, w: jnp.sum(dyn.matmul(x, w, dtype) * c)

    y = dyn.matmul(x, w, "bfloat16")
    dx, dw = jax.jit(jax.grad(loss("bfloat16"), (0, 1)))(x, w)
    refs = (_bf(x) @ _bf(w), _bf(c) @ _bf(w).T, np.einsum("bti,btj->ij", _bf(x), _bf(c)))
    for got, ref in zip((y, dx, dw), refs, strict=True):
        assert got.dtype == jnp.float32
        assert _rel(got, ref) < 1e-5, _rel(got, ref)
    f32 = (x @ w, *jax.grad(loss("float32"), (0, 1))(x, w))
    for got, ref in zip(f32, refs, strict=True):
        assert _rel(got, ref) > 1e-3
    # vmapped over members, as map_members runs it
    ws = jnp.stack([w, -0.5 * w])
    dws = jax.vmap(lambda w: jax.grad(loss("bfloat16"), 1)(x, w))(ws)
    assert _rel(dws[1], np.einsum("bti,btj->ij", _bf(x), _bf(c))) < 1e-5


def _dots(jaxpr) -> list:
    """The dot_general equations of a jaxpr, its sub-jaxprs included."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            out.append(eqn)
        for v in eqn.params.values():
            for sub in v if isinstance(v, list | tuple) else (v,):
                sub = getattr(sub, "jaxpr", sub)  # a ClosedJaxpr's Jaxpr
                if hasattr(sub, "eqns"):
                    out += _dots(sub)
    return out


def test_off_the_cpu_the_three_dots_take_bf16_operands(monkeypatch):
    """The program a GPU gets (traced only): the forward matmul and both gradient matmuls are
    dots of bf16 operands with float32 results (the CPU takes them up to float32 first,
    since its runtime refuses some bf16 dots); the float32 path has no bf16 dot."""
    x, w = jnp.ones((4, 6, 8)), jnp.ones((8, 3))

    def grads(dtype):
        return jax.make_jaxpr(jax.grad(lambda x, w: jnp.sum(jnp.sin(dyn.matmul(x, w, dtype))),
                                       (0, 1)))(x, w).jaxpr

    def kinds(dtype):
        return [(tuple(str(v.aval.dtype) for v in e.invars), str(e.outvars[0].aval.dtype))
                for e in _dots(grads(dtype))]

    assert all(k[0] == ("float32", "float32") for k in kinds("bfloat16"))  # the CPU's
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert kinds("bfloat16") == [(("bfloat16", "bfloat16"), "float32")] * 3
    assert kinds("float32") and all("bfloat16" not in k[0] for k in kinds("float32"))


def test_bf16_discriminator_matches_numpy():
    """The critic with matmul_dtype "bfloat16": NumPy's spectrally normalised ReLU MLP with
    the hidden layers' inputs and normalised weights rounded to bf16; float32 output. The
    default is 1e-3 or more off that reference."""
    rng = np.random.default_rng(0)
    disc, us = models.init_discriminator(jax.random.PRNGKey(0), OBS, ACT, (32, 32))
    obs, nxt = rng.normal(size=(64, OBS)), rng.normal(size=(64, OBS))
    act = rng.normal(size=(64, ACT))
    norm = dyn.Normalizer.from_data(obs, act, nxt)
    d, new_us = models.discriminator(disc, us, norm, jnp.asarray(obs, jnp.float32),
                                     jnp.asarray(act, jnp.float32),
                                     jnp.asarray(nxt, jnp.float32), matmul_dtype="bfloat16")
    d32, _ = models.discriminator(disc, us, norm, jnp.asarray(obs, jnp.float32),
                                  jnp.asarray(act, jnp.float32), jnp.asarray(nxt, jnp.float32))
    assert d.dtype == jnp.float32
    for u, u_new in zip(us, new_us, strict=True):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(u_new))  # update_us False

    def sn(w, u):  # one power-iteration read-out, no update (spectral_normalize, update False)
        w, u = _f64(w), _f64(u)
        v = w @ u / np.linalg.norm(w @ u)
        return w / (v @ w @ u)

    mask = _f64(norm.obs_input_mask)
    x = np.concatenate([(obs - _f64(norm.obs_mean)) / _f64(norm.obs_std) * mask,
                        (act - _f64(norm.act_mean)) / _f64(norm.act_std),
                        (nxt - obs - _f64(norm.delta_mean)) / _f64(norm.delta_std)], -1)
    for layer, u in zip(disc[:-1], us[:-1], strict=True):
        x = np.maximum(_bf(x) @ _bf(sn(layer["w"], u)) + _f64(layer["b"]), 0.0)
    ref = (x @ sn(disc[-1]["w"], us[-1]) + _f64(disc[-1]["b"]))[:, 0]
    assert _rel(d, ref) < 2e-5, _rel(d, ref)
    assert _rel(d32, ref) > 1e-3


# ------------------------------------------------------------------------ the config


@pytest.mark.parametrize("value", ["float16", "bf16", "fp32", None, 16])
def test_a_bad_matmul_dtype_is_refused_by_name(value):
    with pytest.raises(ValueError, match=r"matmul_dtype: expected one of 'float32', "
                                         r"'bfloat16'"):
        TrainConfig.small(matmul_dtype=value).validate()
    with pytest.raises(ValueError, match="matmul_dtype"):
        dyn.DynamicsSpec(matmul_dtype=value).validate()
    with pytest.raises(ValueError, match="matmul_dtype"):
        dyn.matmul(jnp.ones((2, 3)), jnp.ones((3, 4)), value)
    with pytest.raises(ValueError, match="matmul_dtype"):  # init checks before any work
        T.init(jax.random.PRNGKey(0), TrainConfig.small(matmul_dtype=value), None)


def test_the_field_round_trips_and_old_configs_are_float32():
    cfg = TrainConfig.small(matmul_dtype="bfloat16")
    d = json.loads(json.dumps(cfg.to_dict()))
    assert d["dynamics"]["matmul_dtype"] == "bfloat16"
    assert TrainConfig.from_saved(d) == cfg == TrainConfig.from_dict(d)
    flat = {FLAT.get(k, k): v for k, v in cfg.to_dotted().items()}  # the flat format of before
    del flat["matmul_dtype"]  # a config saved before the field
    assert TrainConfig.from_saved(flat).dynamics.matmul_dtype == "float32"
    assert TrainConfig.from_saved(flat) == TrainConfig.small()


# ------------------------------------------------------------------ training and checkpoints


def _linear_data(seed: int = 0, n_policies: int = 2, rows: int = 1000, val: int = 256
                 ) -> T.TrainData:
    """Point-mass rows: (p, v), a uniform in [-1, 1]; next states from the true dynamics
    (deterministic, linear in (v, a)). Held-out rows drawn the same way."""
    rng = np.random.default_rng(seed)
    n = n_policies * rows + val
    obs = rng.uniform(-1.0, 1.0, size=(n, 2)).astype(np.float32)
    act = rng.uniform(-1.0, 1.0, size=(n, 1)).astype(np.float32)
    nxt = np.asarray(pointmass_dynamics(jnp.asarray(obs), jnp.asarray(act)))
    m = n_policies * rows
    keys = jax.random.split(jax.random.PRNGKey(seed), n_policies)
    policies = pol.stack_params([pol.init_policy(k, 2, 1, hidden=(8,)) for k in keys])
    return T.TrainData(
        obs=jnp.asarray(obs[:m]), action=jnp.asarray(act[:m]), next_obs=jnp.asarray(nxt[:m]),
        policy_start=jnp.arange(n_policies, dtype=jnp.int32) * rows,
        policy_count=jnp.full((n_policies,), rows, jnp.int32),
        start_pool=jnp.asarray(0.3 * obs[:256]), true_value=jnp.zeros((n_policies,)),
        policies=policies, norm=dyn.Normalizer.from_data(obs[:m], act[:m], nxt[:m]),
        val_obs=jnp.asarray(obs[m:]), val_action=jnp.asarray(act[m:]),
        val_next_obs=jnp.asarray(nxt[m:]))


def test_bf16_bc_learns_the_pointmass_dynamics():
    """BC with bf16 matmuls on deterministic linear dynamics: finite, float32 parameters that
    keep their marker, the loss falls, and every member's mean next state on held-out rows
    comes within 10% of the delta's std (untrained: ~100%)."""
    data = _linear_data()
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_every=0, updates_per_step=20,
                            matmul_dtype="bfloat16")
    obs, act = data.val_obs, data.val_action
    true_next, delta_std = _f64(data.val_next_obs), _f64(data.val_next_obs - obs).std(0)

    def rel_rmse(state):
        pred = _f64(T.simulator(state).member_dists(obs, act)[0])
        pred = _f64(obs)[None] + _f64(data.norm.delta_mean) + _f64(data.norm.delta_std) * pred
        return np.sqrt(np.mean((pred - true_next) ** 2, 1)) / delta_std

    state = jax.jit(T.init, static_argnums=1)(jax.random.PRNGKey(0), cfg, data)
    before = rel_rmse(state)
    state, m = jax.jit(T.train_steps, static_argnums=2)(state, data, 25)  # 500 updates
    after = rel_rmse(state)
    assert bool(np.all(m["finite"]))
    assert "bf16" in state.gen and "bf16" in T.simulator(state).gen
    for leaf in jax.tree_util.tree_leaves((state.gen, state.gen_opt)):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(leaf)))
    assert np.all(before > 0.5), before
    assert np.all(after < 0.1), after
    first, last = float(m["nll"][:3].mean()), float(m["nll"][-3:].mean())
    assert last < 0.25 * first, (first, last)


def test_bf16_gail_steps_are_finite_and_the_critic_gets_the_dtype(monkeypatch):
    """The adversarial step passes the config's matmul_dtype to the critic in both of its
    losses (the default passes float32), and a few bf16 GAIL steps stay finite."""
    data = _linear_data(rows=300, val=128)
    seen = []
    original = models.discriminator

    def recording(*args, matmul_dtype="float32", **kw):
        seen.append(matmul_dtype)
        return original(*args, matmul_dtype=matmul_dtype, **kw)

    monkeypatch.setattr(losses, "discriminator", recording)
    base = dict(task="pointmass", method="gail", vd_every=0, gen_hidden=(16,),
                disc_hidden=(16,), batch_size=16, updates_per_step=2, disc_updates=2,
                sim_envs=8, sim_steps=2, buffer_size=32)
    f32 = TrainConfig.small(**base)
    jax.eval_shape(T.train_step, jax.eval_shape(lambda: T.init(jax.random.PRNGKey(0), f32,
                                                               data)), data)
    assert set(seen) == {"float32"} and len(seen) >= 2
    seen.clear()
    cfg = TrainConfig.small(**base, matmul_dtype="bfloat16")
    state = T.init(jax.random.PRNGKey(0), cfg, data)
    state, m = jax.jit(T.train_steps, static_argnums=2)(state, data, 3)
    assert set(seen) == {"bfloat16"} and len(seen) >= 2
    assert bool(np.all(m["finite"])), {k: np.asarray(v) for k, v in m.items()}
    assert np.all(np.isfinite(np.asarray(m["disc_loss"])))
    for leaf in jax.tree_util.tree_leaves((state.gen, state.disc, state.disc_opt)):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == jnp.float32


def test_checkpoints_keep_the_dtype(tmp_path):
    """A bfloat16 simulator loads as bfloat16 (its means are the saved state's; without the
    marker they differ), and a checkpoint whose config predates the field loads as float32."""
    data = _linear_data(rows=300, val=128)
    obs, act = jnp.asarray([[0.3, -0.2], [0.9, 0.5]]), jnp.asarray([[0.5], [-1.0]])
    for dtype in ("bfloat16", "float32"):
        cfg = TrainConfig.small(task="pointmass", method="bc", vd_every=0, matmul_dtype=dtype)
        state = T.init(jax.random.PRNGKey(1), cfg, data)
        state = state.replace(gen={**state.gen, "layers": [
            {**layer, "w": layer["w"] * 100.0} if i == len(state.gen["layers"]) - 1 else layer
            for i, layer in enumerate(state.gen["layers"])]})  # a head far from 0
        ck = Checkpointer(tmp_path / dtype)
        step = ck.save(state, META)
        ck.close()
        if dtype == "float32":  # as saved before the field existed
            path = tmp_path / dtype / str(step) / "meta" / "metadata"
            meta = json.loads(path.read_text())
            meta["config"] = {FLAT.get(k, k): v for k, v in  # the flat format of before
                              TrainConfig.from_dict(meta["config"]).to_dotted().items()}
            del meta["config"]["matmul_dtype"]
            path.write_text(json.dumps(meta))
        loaded = load_simulator(tmp_path / dtype)
        assert ("bf16" in loaded.gen) == (dtype == "bfloat16")
        np.testing.assert_allclose(np.asarray(loaded.mean(obs, act)),
                                   np.asarray(T.simulator(state).mean(obs, act)), rtol=1e-6)
        if dtype == "bfloat16":
            plain = loaded.replace(gen={k: v for k, v in loaded.gen.items() if k != "bf16"})
            assert np.abs(np.asarray(plain.mean(obs, act) - loaded.mean(obs, act))).max() > 0
        ck = Checkpointer(tmp_path / dtype)  # and a run of the same config resumes it
        restored = ck.restore(state)
        ck.close()
        for a, b in zip(jax.tree_util.tree_leaves(restored.gen),
                        jax.tree_util.tree_leaves(state.gen), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
