"""Forking adversarial lanes off one pre-trained trunk (issue 40, item 3): ``train.lanes.fork``
gives the state a separate run of the other eps has at the same step, bit for bit, and the
protocol's ``train_family`` with the fork reports what it reports without it; the likelihood
family's BC lanes join from the same pre-training (``paper.fork.join_trunk``), with the same
result as BC trained from step 0."""

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
    steps as an adversarial lane's pre-training: every field the pre-training writes
    (paper.fork.JOINED: the members, their optimiser, best weights and moving average, held-out
    scores and early-stopping bookkeeping, the value measurement, the key and step) is bitwise
    equal after PRE steps, so ``join_trunk`` (the BC init with those fields of the trunk) is
    leaf for leaf the BC lane's own state, and so are the BC steps after it."""
    from rl2s_jax.paper.fork import JOINED, join_trunk

    ds, policies = pm_small
    cfg = _cfg()
    data = T.make_train_data(ds, policies, cfg)
    key = jax.random.PRNGKey(5)
    trunk, _ = _steps(_init(key, cfg, data, 0.25), data, PRE, "pretrain")
    start = _init(key, _cfg(method="rl2s-bc"), data, 1.0)
    bc, _ = _steps(start, data, PRE, None)
    for name in JOINED:
        _assert_equal(getattr(bc, name), getattr(trunk, name))
    assert bc.best_gen is not None and bc.ema_gen is not None  # early stopping, EMA on
    joined = jax.jit(join_trunk)({name: getattr(trunk, name) for name in JOINED}, start)
    _assert_equal(joined, bc)
    assert int(joined.selected.sum()) == 4 and int(trunk.selected.sum()) == 2
    a, ma = _steps(joined, data, 2, None)
    b, mb = _steps(bc, data, 2, None)
    _assert_equal(a, b)
    _assert_equal(ma, mb)


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
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.paper.protocol import METRICS, train_family
    from rl2s_jax.zoo.zoo import policies_for

    train_ds, test_ds = load_dataset(pm_files["train"]), load_dataset(pm_files["test"])
    cfg = _cfg(vd_horizon=10)
    sizes = dict(steps=4, eval_every=2, eval_episodes=2, bootstrap=0)
    out = {}
    for fork_on in (True, False):
        methods = ("rl2s", "rl2s@0.5", "gail")  # with an eps lane (paper.py --eps-lanes 0.5)
        result = {"per_seed": {m: {k: [] for k in METRICS} for m in methods}, "curves": [],
                  "lanes": {}, "timings": {}}
        lanes, states = train_family(
            result, "adversarial", cfg, methods, train_ds=train_ds, test_ds=test_ds,
            train_pols=policies_for(train_ds), test_pols=policies_for(test_ds), seeds=[0, 1],
            sizes=sizes, fork=fork_on)
        assert lanes == [("rl2s", 0), ("rl2s", 1), ("rl2s@0.5", 0), ("rl2s@0.5", 1),
                         ("gail", 0), ("gail", 1)]
        np.testing.assert_array_equal(np.asarray(states.step), [4] * 6)
        np.testing.assert_allclose(np.asarray(states.eps), [0.25, 0.25, 0.5, 0.5, 1, 1])
        assert result["lanes"]["rl2s@0.5/1"]["eps"] == 0.5
        out[fork_on] = result, states
    (forked, fs), (separate, ss) = out[True], out[False]
    assert forked.pop("fork") == {"adversarial": {"trunk": "rl2s", "at_step": PRE,
                                                  "steps_saved_per_seed": 2 * PRE}}
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


def _close(a, b, where="result"):
    """Two results' values equal, floats to round-off (vmap over other lane counts)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and not isinstance(b, bool):
        assert a == pytest.approx(b, rel=1e-3, abs=1e-4, nan_ok=True), where
    else:
        assert a == b, where


def _mle_run(pm_files, steps=4, eval_every=2):
    """Inputs of a train_family run on pm_files' data (the same objects for every family, as
    paper.py passes them) and a fresh result for some methods."""
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.paper.protocol import METRICS
    from rl2s_jax.zoo.zoo import policies_for

    train_ds, test_ds = load_dataset(pm_files["train"]), load_dataset(pm_files["test"])
    inputs = dict(train_ds=train_ds, test_ds=test_ds, train_pols=policies_for(train_ds),
                  test_pols=policies_for(test_ds), seeds=[0, 1],
                  sizes=dict(steps=steps, eval_every=eval_every, eval_episodes=2,
                             bootstrap=0))

    def fresh(methods):
        return {"per_seed": {m: {k: [] for k in METRICS} for m in methods}, "curves": [],
                "lanes": {}, "timings": {}}
    return inputs, fresh


@pytest.mark.heavy
@pytest.mark.parametrize("steps,every", [(4, 2), (6, 3)], ids=["in-chunk", "at-evaluation"])
def test_bc_lanes_join_from_the_adversarial_trunk(pm_files, steps, every):
    """The adversarial family (forked) then the likelihood family with a share: the bc lanes
    join the rl2s-bc lanes at step PRE (inside the second evaluation chunk as on the gpu
    profile, or at an evaluation as on the cpu one) from the rl2s lanes' pre-training, their
    evaluations until then are the trunk's, and the family's result is the one of bc trained
    from step 0 (no share): the same structure, the same numbers to round-off (vmap over 2 vs
    4 lanes), "fork" saying where it joined. Heavy: ~15 s each with the compilation cache."""
    from rl2s_jax.paper.protocol import train_family

    inputs, fresh = _mle_run(pm_files, steps=steps, eval_every=every)
    share = {}
    adv = fresh(("rl2s", "gail"))
    train_family(adv, "adversarial", _cfg(vd_horizon=10), ("rl2s", "gail"), share=share,
                 **inputs)
    assert share["trunk"]["fields"]["step"].tolist() == [PRE, PRE]
    before = list(range(every, PRE + 1, every))  # the trunk's evaluations before the fork
    assert sorted(share["trunk"]["points"]) == before
    mle_cfg = _cfg(vd_horizon=10, method="rl2s-bc")
    out = {}
    for joined in (True, False):
        result = fresh(("rl2s-bc", "bc"))
        lanes, states = train_family(result, "mle", mle_cfg, ("rl2s-bc", "bc"),
                                     share=share if joined else None, **inputs)
        assert lanes == [("rl2s-bc", 0), ("rl2s-bc", 1), ("bc", 0), ("bc", 1)]
        np.testing.assert_array_equal(np.asarray(states.step), [steps] * 4)
        out[joined] = result, states
    assert "trunk" not in share  # taken by the family that joined
    (joined, js), (separate, ss) = out[True], out[False]
    assert joined.pop("fork") == {"mle": {"trunk": "rl2s", "trunk_family": "adversarial",
                                          "joined": ["bc"], "at_step": PRE,
                                          "steps_saved_per_seed": PRE}}
    assert separate.pop("fork") == {"mle": None}
    for r in (joined, separate):
        r["timings"].clear()
    assert _shape(joined) == _shape(separate)
    _close(joined, separate)
    # the bc lanes' rows before the join are the rl2s lanes' (the trunk's) of their seed
    rows = {(r["lane"], r["step"]): r for r in adv["curves"]}
    bc = [r for r in joined["curves"] if r["method"] == "bc" and r["step"] in before]
    assert len(bc) == 2 * len(before)
    for r in bc:
        t = rows[f"rl2s/{r['seed']}", r["step"]]
        assert (r["avd"], r["tau"], r["avd_train"]) == (t["avd"], t["tau"], t["avd_train"])
    np.testing.assert_array_equal(np.asarray(js.eps), np.asarray(ss.eps))
    np.testing.assert_array_equal(np.asarray(js.selected), np.asarray(ss.selected))
    for a, b in zip(jax.tree_util.tree_leaves(js.gen), jax.tree_util.tree_leaves(ss.gen),
                    strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-3, atol=1e-5)


def test_incompatible_trunk_is_refused(pm_files, capsys):
    """A shared trunk that differs from the likelihood family (another config field, other
    seeds, evaluation sizes or data, training that ended before the fork) is refused with the
    reason; the family then trains its bc lanes from step 0 and records no join."""

    from rl2s_jax.paper.fork import join_refusal
    from rl2s_jax.paper.protocol import train_family

    inputs, fresh = _mle_run(pm_files)
    cfg = _cfg(vd_horizon=10, method="rl2s-bc")
    lanes = [(m, s) for m in ("rl2s-bc", "bc") for s in (0, 1)]
    ins = tuple(inputs[k] for k in ("train_ds", "test_ds", "train_pols", "test_pols"))
    ok = {"family": "adversarial", "method": "rl2s", "config": cfg.override(
        {"method": "rl2s"}), "seeds": [0, 1], "at_step": PRE,
        "sizes": {"eval_every": 2, "eval_episodes": 2}, "inputs": ins, "points": {},
        "fields": {}, "finite_before": None}
    eps = [0.25, 0.25, 1.0, 1.0]

    def why(trunk, **kw):
        args = dict(lanes=lanes, joining=[2, 3], eps=eps, seeds=[0, 1],
                    sizes=inputs["sizes"], inputs=ins)
        args.update(kw)
        return join_refusal(trunk, cfg, **args)

    assert why(ok) is None
    assert "no adversarial trunk" in why(None)
    assert "differs in vd.episodes" in why({**ok, "config": ok["config"].override(
        {"vd.episodes": 3})})
    assert "seeds" in why({**ok, "seeds": [0, 2]})
    assert "ended before step" in why({**ok, "fields": None})
    assert "evaluated with" in why({**ok, "sizes": {"eval_every": 1, "eval_episodes": 2}})
    assert "other data" in why({**ok, "inputs": (*ins[:3], list(ins[3]))})
    assert "eps < 1" in why(ok, eps=[0.25, 0.25, 0.5, 1.0])
    assert "no other lanes" in why(ok, lanes=lanes[2:], joining=[0, 1], eps=eps[2:])
    assert "fewer than" in why(ok, sizes={**inputs["sizes"], "steps": 2})
    # refused in train_family: bc trains from step 0 beside rl2s-bc, no join recorded
    share = {"trunk": {**ok, "config": ok["config"].override({"vd.episodes": 3})}}
    result = fresh(("rl2s-bc", "bc"))
    _, states = train_family(result, "mle", cfg, ("rl2s-bc", "bc"), share=share,
                             **{**inputs, "sizes": {**inputs["sizes"], "steps": 2}})
    assert "the bc lanes train from step 0" in capsys.readouterr().out
    assert result["fork"] == {"mle": None} and "trunk" not in share
    np.testing.assert_array_equal(np.asarray(states.step), [2] * 4)
    assert [r["lane"] for r in result["curves"]] == [f"{m}/{s}" for m, s in lanes]
