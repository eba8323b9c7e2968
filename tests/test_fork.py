"""Forking adversarial lanes off one pre-trained trunk (issue 40, item 3): ``train.lanes.fork``
gives the state a separate run of the other eps has at the same step, bit for bit, and the
protocol's ``train_family`` with the fork reports what it reports without it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_train import _policies

from rl2s_jax import train as T
from rl2s_jax.data.collect import collect
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.train.lanes import FORK_REDRAWN, fork, fork_lanes, init_lanes

PRE = 3  # pre-training steps


def _cfg(**kw):
    base = dict(task="pointmass", method="rl2s", vd_horizon=4, vd_every=2, vd_episodes=2,
                gen_hidden=(16,), disc_hidden=(16,), batch_size=16, updates_per_step=2,
                disc_updates=2, sim_envs=16, sim_steps=2, buffer_size=32, pretrain_steps=PRE,
                disc_warmup_steps=1, ema_decay=0.5)
    base.update(kw)
    return T.TrainConfig.small(**base)


@pytest.fixture(scope="module")
def pm_small():
    """Point-mass data of 4 biased policies (200 transitions, 8 value episodes each)."""
    policies = _policies([-2.0, 0.0, 1.0, 2.0])
    task = get_task("pointmass")
    ds = collect(task.make_env(), policies, key=jax.random.PRNGKey(0),
                 transitions_per_policy=200, envs_per_policy=2,
                 episode_length=task.episode_length, task="pointmass", value_episodes=8,
                 progress=False)
    return ds, policies


_init = jax.jit(T.init, static_argnums=1)
_steps = jax.jit(T.train_steps, static_argnums=(2, 3))


def _leaves(tree):
    return {jax.tree_util.keystr(p): np.asarray(x)
            for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _assert_equal(a, b):
    """Leaf for leaf bitwise equal (NaN == NaN), the same structure and static config."""
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    la, lb = _leaves(a), _leaves(b)
    for name in la:
        np.testing.assert_array_equal(la[name], lb[name], err_msg=name, strict=True)


def test_fork_equals_the_separate_run_bit_for_bit(pm_small):
    """(a) the trunk (rl2s, eps 0.25) pre-trained, forked to eps 1 (gail) with a start drawn by
    init from the same key, is bitwise the gail lane pre-trained on its own; (b) both then run
    the adversarial phase to the same bits (critic warm-up, a CVaR refresh: the states and the
    metrics). From a start of another key the critic, envs and buffer are that start's."""
    ds, policies = pm_small
    cfg = _cfg()
    data = T.make_train_data(ds, policies, cfg)
    key = jax.random.PRNGKey(5)
    trunk, _ = _steps(_init(key, cfg, data, 0.25), data, PRE, "pretrain")
    start = _init(key, cfg, data, 1.0)
    separate, _ = _steps(start, data, PRE, "pretrain")
    forked = fork(trunk, start)
    _assert_equal(forked, separate)
    assert int(forked.selected.sum()) == 4 and int(trunk.selected.sum()) == 2
    a, ma = _steps(forked, data, 4, "main")
    b, mb = _steps(separate, data, 4, "main")
    _assert_equal(a, b)
    _assert_equal(ma, mb)
    assert bool(np.all(ma["finite"])) and int(a.step) == PRE + 4
    assert np.asarray(ma["vd_refreshed"]).any()
    # a start of another key: its re-drawn parts, the trunk's pre-trained ones
    other = _init(jax.random.PRNGKey(6), cfg, data, 1.0)
    f2 = fork(trunk, other)
    l2, lt, lo = _leaves(f2), _leaves(trunk), _leaves(other)
    for name, x in l2.items():
        field = name.split(".")[1].split("[")[0]
        if field == "selected":
            continue
        ref = lo if field in FORK_REDRAWN else lt
        np.testing.assert_array_equal(x, ref[name], err_msg=name, strict=True)
    disc = [n for n in l2 if n.startswith(".disc")]
    assert disc and not all(np.array_equal(l2[n], _leaves(start)[n]) for n in disc)
    np.testing.assert_array_equal(np.asarray(f2.selected), np.ones(4, bool))


def test_fork_lanes_checks_and_vmaps(pm_small):
    """fork_lanes: vmapped fork of every lane (a trunk lane repeated for each method); refuses
    starts past step 0, a trunk past its pre-training and a config without pre-training."""
    ds, policies = pm_small
    cfg = _cfg()
    data = T.make_train_data(ds, policies, cfg)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (1, 2, 1, 2)])
    starts = init_lanes(keys, cfg, data, eps=jnp.asarray([0.25, 0.25, 1.0, 1.0]))
    trunk, _ = jax.jit(jax.vmap(lambda s: T.train_steps(s, data, PRE, "pretrain")))(
        jax.tree_util.tree_map(lambda x: x[:2], starts))
    both = jax.tree_util.tree_map(lambda x: x[jnp.asarray([0, 1, 0, 1])], trunk)
    forked = fork_lanes(both, starts)
    np.testing.assert_array_equal(np.asarray(forked.eps), [0.25, 0.25, 1.0, 1.0])
    np.testing.assert_array_equal(np.asarray(forked.selected.sum(1)), [2, 2, 4, 4])
    for i, j in ((0, 2), (1, 3)):  # the methods of a seed share the pre-trained members
        np.testing.assert_array_equal(np.asarray(forked.gen["layers"][0]["w"][i]),
                                      np.asarray(forked.gen["layers"][0]["w"][j]))
        np.testing.assert_array_equal(np.asarray(forked.sim.obs[j]),
                                      np.asarray(starts.sim.obs[j]))
    with pytest.raises(ValueError, match="step 0"):
        fork_lanes(both, both)
    with pytest.raises(ValueError, match="pre-training"):
        fork_lanes(both.replace(step=both.step + 1), starts)
    with pytest.raises(ValueError, match="different configs"):
        fork(both, starts.replace(config=_cfg(sim_steps=3)))
    flat = _cfg(pretrain_steps=0)
    with pytest.raises(ValueError, match="pretrain_steps > 0"):
        fork(both.replace(config=flat), starts.replace(config=flat))


def test_bc_lane_runs_the_trunks_pre_training(pm_small):
    """BC (eps 1, the likelihood family's config) from the same key takes the same likelihood
    steps as an adversarial lane's pre-training: the members, their optimiser, the value
    measurement and the key are bitwise equal after PRE steps (docs/SCALING.md: BC could
    continue from the trunk; the protocol does not do it)."""
    ds, policies = pm_small
    cfg = _cfg()
    data = T.make_train_data(ds, policies, cfg)
    key = jax.random.PRNGKey(5)
    trunk, _ = _steps(_init(key, cfg, data, 0.25), data, PRE, "pretrain")
    bc, _ = _steps(_init(key, _cfg(method="rl2s-bc"), data, 1.0), data, PRE, None)
    for name in ("gen", "gen_opt", "best_gen", "ema_gen", "heldout_nll", "best_nll", "vd",
                 "vd_roll", "key", "step"):
        _assert_equal(getattr(bc, name), getattr(trunk, name))


def _shape(x):
    """A result's structure: dict keys all the way down, list lengths, leaf types."""
    if isinstance(x, dict):
        return {k: _shape(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_shape(v) for v in x]
    return type(x).__name__ if x is not None else None


@pytest.mark.heavy
def test_protocol_forked_family_reports_as_the_separate_one(pm_files):
    """(c) train_family with the fork (the rl2s lanes pre-train for gail too; fork inside the
    second evaluation chunk) writes the result of the separate lanes: the same structure and
    the same numbers to round-off (vmap over 2 vs 4 lanes), "fork" saying where it forked.
    Heavy: ~25 s with the compilation cache, ~2 min without (five lane programs)."""
    from rl2s_jax.app.protocol import METRICS, train_family
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.zoo.zoo import policies_for

    train_ds, test_ds = load_dataset(pm_files["train"]), load_dataset(pm_files["test"])
    cfg = _cfg(vd_horizon=10)
    sizes = dict(steps=4, eval_every=2, eval_episodes=2, bootstrap=0)
    out = {}
    for fork_on in (True, False):
        methods = ("rl2s", "gail")
        result = {"per_seed": {m: {k: [] for k in METRICS} for m in methods}, "curves": [],
                  "lanes": {}, "timings": {}}
        lanes, states = train_family(
            result, "adversarial", cfg, methods, train_ds=train_ds, test_ds=test_ds,
            train_pols=policies_for(train_ds), test_pols=policies_for(test_ds), seeds=[0, 1],
            sizes=sizes, fork=fork_on)
        assert lanes == [("rl2s", 0), ("rl2s", 1), ("gail", 0), ("gail", 1)]
        np.testing.assert_array_equal(np.asarray(states.step), [4] * 4)
        out[fork_on] = result, states
    (forked, fs), (separate, ss) = out[True], out[False]
    assert forked.pop("fork") == {"adversarial": {"trunk": "rl2s", "at_step": PRE,
                                                  "steps_saved_per_seed": PRE}}
    assert separate.pop("fork") == {"adversarial": None}
    for r in (forked, separate):
        r["timings"].clear()
    assert _shape(forked) == _shape(separate)
    np.testing.assert_array_equal(np.asarray(fs.eps), np.asarray(ss.eps))
    np.testing.assert_array_equal(np.asarray(fs.selected), np.asarray(ss.selected))
    for a, b in zip(forked["curves"], separate["curves"], strict=True):
        assert a["lane"] == b["lane"] and a["step"] == b["step"]
        for k in ("avd", "mvd", "tau", "avd_train", "mvd_train"):
            assert a[k] == pytest.approx(b[k], rel=1e-3, abs=1e-4), (a["lane"], k)
