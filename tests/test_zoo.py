"""Zoo building (issue 15): SAC from scratch, resumable zoo training, the spread rule, the CLI.

The zoo runs here are tiny pointmass runs of SAC and PPO; they share one set of programs, and
a module-wide persistent compilation cache lets the repeated runs (stop, resume, import) skip
recompiling them.
"""

import dataclasses
import json
import os
import time

import jax
import numpy as np
import pytest

from rl2s_jax import cli
from rl2s_jax.data.collect import measure_values
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy import policy as pol
from rl2s_jax.policy.sac import make_sac
from rl2s_jax.zoo import zoo as zoo_mod
from rl2s_jax.zoo.build import (
    ZOO_SAC,
    build_zoo,
    choose_split,
    extend_zoo,
    fill_gaps,
    learner_plans,
    spread_check,
    spread_subset,
)
from rl2s_jax.zoo.store import load_runs, read_export, write_export

TINY = {"sac": {"hidden": [16], "n_envs": 8, "batch_size": 32, "warmup_steps": 4,
                "buffer_size": 2000},
        "ppo": {"num_envs": 16, "unroll_length": 8, "value_hidden": [16]}}
TINY_STEPS, TINY_SNAPSHOTS = 768, 6   # per seed: 6 intervals of 16 SAC / 1 PPO iterations


@pytest.fixture(scope="module", autouse=True)
def compilation_cache(tmp_path_factory):
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes")
    old = {n: getattr(jax.config, n) for n in names}
    jax.config.update(names[0], str(tmp_path_factory.mktemp("jax_cache")))
    jax.config.update(names[1], 0)
    jax.config.update(names[2], 0)
    yield
    for n, v in old.items():
        jax.config.update(n, v)


def _tiny_zoo(work, **kw):
    plans = learner_plans("pointmass", "both", TINY_STEPS, TINY_SNAPSHOTS, TINY)
    kw = {"n_train": 5, "min_test": 4, **kw}
    return build_zoo("pointmass", algo="both", seeds=2, plans=plans, work_dir=str(work),
                     value_episodes=2, progress=False, log=lambda *_: None, **kw)


@pytest.fixture(scope="module")
def full_zoo(tmp_path_factory):
    """The tiny uninterrupted run (both learners) that stopped/resumed/imported runs match."""
    return _tiny_zoo(tmp_path_factory.mktemp("full"))


def _same_snapshots(a, b):
    for name in ("sac", "ppo"):
        sa, sb = a["runs"][name].snapshots, b["runs"][name].snapshots
        la, lb = jax.tree_util.tree_leaves(sa), jax.tree_util.tree_leaves(sb)
        assert len(la) == len(lb)
        for x, y in zip(la, lb, strict=True):
            np.testing.assert_array_equal(x, y)


# ---------------------------------------------------------------------------------------------
# The spread rule and the split.

def test_spread_check_reports_a_hole():
    zoo = np.r_[np.linspace(0.0, 30.0, 10), np.linspace(70.0, 100.0, 10)]   # nothing in 30..70
    split = zoo[::2]
    chk = spread_check(split, zoo)
    s = np.sort(split)
    assert chk["largest_gap"] == pytest.approx(np.max(np.diff(s)) / 100.0)   # NumPy reference
    assert chk["gap_between"] == pytest.approx([s[4], s[5]]) and s[4] <= 30 and s[5] >= 70
    assert not chk["pass"] and "gap" in chk["failures"][0]
    assert chk["lowest_at"] == 0.0 and chk["highest_at"] == pytest.approx(s[-1] / 100.0)

    even = np.linspace(-50.0, 50.0, 11)
    ok = spread_check(even, even)
    assert ok["pass"] and ok["largest_gap"] == pytest.approx(0.1) and not ok["failures"]
    # both ends are checked against the zoo's range, not the split's own
    low = spread_check(np.linspace(0.0, 75.0, 20), np.linspace(0.0, 100.0, 5))
    assert not low["pass"] and low["highest_at"] == pytest.approx(0.75)
    assert any("highest" in f for f in low["failures"])
    high = spread_check(np.linspace(15.0, 100.0, 20), np.linspace(0.0, 100.0, 5))
    assert not high["pass"] and any("lowest" in f for f in high["failures"])
    with pytest.raises(ValueError, match="no range"):
        spread_check([1.0], [1.0, 1.0])


def test_fill_gaps_by_hand():
    # worked by hand: [0, 10] is halved (5), the lower half halved (2), the widest gap left
    # (5..10, half the range) takes 7.5, then 7.5..10 (25% > 20%) takes 9.9; 2..5 (30%) has no
    # candidate and 11 lies outside the range
    cand = [5.0, 2.0, 9.9, 11.0, 7.5]
    assert fill_gaps([0.0, 10.0], cand, 0.0, 10.0, min_count=4, max_gap=0.2) == [0, 1, 4, 2]
    assert fill_gaps([0.0, 10.0], cand, 0.0, 10.0, min_count=3, max_gap=1.0) == [0]
    assert fill_gaps([0.0, 10.0], [11.0, np.nan], 0.0, 10.0, min_count=5) == []


def test_extend_zoo_keeps_ids_and_training_split():
    P = 10
    base = zoo_mod.Zoo(task="pointmass", params={"w": np.arange(P * 2.0).reshape(P, 2)},
                       returns=np.linspace(0, 90, P).astype(np.float32),
                       return_se=np.ones(P, np.float32), origins=[{"seed": 0}] * P,
                       train_ids=[0, 2, 4, 6, 9], test_ids=[1, 3, 5, 7, 8])
    cand = np.array([95.0, 44.0, 46.0, 12.0, -5.0])
    values = {"value": cand, "value_se": np.full(5, 2.0)}
    new = {"w": np.arange(10.0).reshape(5, 2) + 100}
    zoo, picks = extend_zoo(base, new, values, [{"seed": 1, "k": i} for i in range(5)], 7)
    assert picks == [1, 3]          # inside the range, nearest the middles of the widest gaps
    assert zoo.train_ids == base.train_ids and zoo.test_ids == [1, 3, 5, 7, 8, 10, 11]
    np.testing.assert_array_equal(zoo.params["w"][10:], new["w"][[1, 3]])
    np.testing.assert_array_equal(zoo.returns[10:], [44.0, 12.0])
    assert zoo.origins[10]["k"] == 1 and zoo.info["extensions"][0]["ids"] == [10, 11]
    assert zoo.info["spread"]["test"]["n"] == 7
    with pytest.raises(ValueError, match="min_test"):
        extend_zoo(base, new, values, [{}] * 5, 9)


def test_names_to_zoo_ids_inverts_policy_names():
    """names_to_zoo_ids reads back the ids Zoo.policy_names wrote, a task with a dash too."""
    from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids

    zoo = load_zoo("hopper")
    ids = [0, 7, 35]
    assert names_to_zoo_ids(zoo.policy_names(ids)) == ids
    assert names_to_zoo_ids(["my-robot-012"]) == [12]


def test_validation_split_holds_out_every_fourth_training_policy_by_return():
    """split_ids("validation"): every VALIDATION_EVERY-th training policy by return, from the
    middle of each group; "fit": the rest; together the training policies, no test policy;
    an unknown split names the known ones."""
    from rl2s_jax.zoo.zoo import VALIDATION_EVERY, load_zoo

    for task in ("hopper", "ant"):
        zoo = load_zoo(task)
        fit, held = zoo.split_ids("fit"), zoo.split_ids("validation")
        assert sorted(fit + held) == sorted(zoo.train_ids) and not set(held) & set(fit)
        by_return = sorted(zoo.train_ids, key=lambda i: zoo.returns[i])
        want = [by_return[k] for k in range(len(by_return)) if k % VALIDATION_EVERY == 2]
        assert sorted(held) == sorted(want) and len(held) == len(zoo.train_ids) // 4
    with pytest.raises(ValueError, match="'fit', 'validation', 'lineage-fit', "
                       "'lineage-validation', got 'val'"):
        load_zoo("hopper").split_ids("val")


def test_spread_subset_and_split_span_the_range():
    returns = np.array([0.0, 1.0, 1.1, 1.2, 1.3, 5.0, 9.0, 9.1, 10.0])
    assert spread_subset(returns, 4) == [0, 5, 6, 8]  # targets 0, 3.33, 6.67, 10
    rng = np.random.default_rng(0)
    # a crowded plateau near the top, as training curves give
    returns = np.r_[rng.uniform(0, 3000, 40), rng.uniform(2800, 3000, 80)]
    zoo = np.asarray(returns)[spread_subset(returns, 60)]
    train, test = choose_split(zoo, n_train=17, min_test=8)
    assert len(train) == 17 and len(test) == 43 and not set(train) & set(test)
    assert np.argmin(zoo) in train and np.argmax(zoo) in train
    for ids in (train, test):
        assert spread_check(zoo[ids], zoo)["pass"], spread_check(zoo[ids], zoo)
    with pytest.raises(ValueError, match="cannot give"):
        choose_split(np.arange(20.0), n_train=17, min_test=8)


# ---------------------------------------------------------------------------------------------
# SAC from scratch.

def _lqr_optimal_pointmass_return(T=50) -> float:
    """Upper bound on any policy's expected pointmass return: finite-horizon LQR of the linear
    dynamics with the quadratic costs (actions unconstrained), starts ~ U[-0.5, 0.5]^2."""
    A = np.array([[1.0, 0.05 * 0.95], [0.0, 0.95]])
    B = np.array([[0.05 * 0.05 * 2.0], [0.05 * 2.0]])
    Q, R, P = np.diag([1.0, 0.0]), 0.1, np.zeros((2, 2))
    for _ in range(T):   # cost of the step: x'^T Q x' + R a^2, x' = A x + B a
        M = Q + P
        K = np.linalg.solve(B.T @ M @ B + R, B.T @ M @ A)
        Acl = A - B @ K
        P = Acl.T @ M @ Acl + R * K.T @ K
    return T - float(np.trace(P @ (np.eye(2) / 12.0)))


def test_sac_from_scratch_reaches_near_optimal_pointmass():
    plan = ZOO_SAC["pointmass"]
    cfg = dataclasses.replace(plan.config, episode_length=50)
    env = get_task("pointmass").make_env()
    sac = make_sac(env, cfg)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    state = jax.jit(jax.vmap(lambda k: sac.init(k)))(keys)
    initial = state.actor
    n_iterations = plan.env_steps // cfg.n_envs
    state, metrics = jax.jit(jax.vmap(lambda s: sac.train(s, n_iterations)))(state)
    assert np.all(np.isfinite(np.asarray(metrics["q_loss"])))
    # the running normaliser's statistics are the actor's, so the actor is a zoo policy
    np.testing.assert_allclose(state.actor["obs_mean"], state.obs_norm.mean, rtol=1e-6)
    np.testing.assert_allclose(state.actor["obs_std"], state.obs_norm.std(), rtol=1e-6)
    assert np.all(np.asarray(state.actor["obs_std"]) < 0.9)  # real statistics, not the init
    both = jax.tree_util.tree_map(lambda a, b: np.concatenate([a, b]), initial, state.actor)
    v = measure_values(env, both, key=jax.random.PRNGKey(1), n_episodes=64, episode_length=50)
    random_ret, final = v["value"][:2], v["value"][2:]
    optimal = _lqr_optimal_pointmass_return()
    assert 48.9 < optimal < 49.1 and np.all(random_ret < 44.0), (optimal, random_ret)
    # near-optimal: at least 85% of the way from the random policy to the optimum
    assert np.all(final >= optimal - 0.15 * (optimal - random_ret)), (final, optimal, random_ret)
    assert np.all(final <= optimal + 3 * v["value_se"][2:] + 0.05), (final, optimal)


def test_sac_from_scratch_options_checked():
    env = get_task("pointmass").make_env()
    cfg = dataclasses.replace(ZOO_SAC["pointmass"].config, n_envs=2, warmup_steps=2)
    with pytest.raises(ValueError, match="ignore_obs_dims"):
        make_sac(env, dataclasses.replace(cfg, ignore_obs_dims=(2,)))
    sac = make_sac(env, cfg)
    with pytest.raises(ValueError, match="normalize_observations"):
        sac.init(jax.random.PRNGKey(0), pol.init_policy(jax.random.PRNGKey(1), 2, 1))
    # an ignored dim is invisible to a fresh actor and its critics: std 1e6, mean 0
    sac = make_sac(env, dataclasses.replace(cfg, ignore_obs_dims=(0,)))
    state = sac.init(jax.random.PRNGKey(0))
    assert float(state.actor["obs_std"][0]) == pol.IGNORED_OBS_STD
    assert float(state.actor["obs_mean"][0]) == 0.0 and float(state.actor["obs_std"][1]) < 1


# ---------------------------------------------------------------------------------------------
# Resumable zoo training.

def test_zoo_stopped_and_resumed_is_bit_identical(tmp_path, full_zoo):
    full = full_zoo
    assert full[0] is not None
    # stopped after its first checkpoint (the deadline has passed: one interval, then stop)
    zoo, extras = _tiny_zoo(tmp_path / "resumed", deadline=time.time())
    assert zoo is None and not extras["runs"]["sac"].complete
    assert extras["runs"]["sac"].meta["snapshots_done"] == 1 and "ppo" not in extras["runs"]
    assert sorted(os.listdir(tmp_path / "resumed" / "sac" / "ckpt")) == ["1"]
    # stopped again (one more interval), with final: a zoo of what was trained so far
    part, extras = _tiny_zoo(tmp_path / "resumed", deadline=time.time(), final=True,
                             n_train=2, min_test=2)
    sac = part.info["learners"]["sac"]
    assert list(part.info["learners"]) == ["sac"] and not sac["complete"]
    assert sac["env_steps_per_seed"] == 2 * TINY_STEPS // TINY_SNAPSHOTS
    assert part.size == 2 * 3 and {o["snapshot"] for o in part.origins} == {0, 1, 2}
    resumed = _tiny_zoo(tmp_path / "resumed")
    _same_snapshots(full[1], resumed[1])
    for a, b in zip(jax.tree_util.tree_leaves(full[0].params),
                    jax.tree_util.tree_leaves(resumed[0].params), strict=True):
        np.testing.assert_array_equal(a, b)
    assert full[0].origins == resumed[0].origins and full[0].train_ids == resumed[0].train_ids
    np.testing.assert_array_equal(full[0].returns, resumed[0].returns)
    # the training log is whole: one row per seed and snapshot interval, no repeats
    rows = [(r["learner"], r["seed"], r["snapshot"]) for r in resumed[1]["log"]]
    assert len(rows) == len(set(rows)) == resumed[0].info["snapshots_measured"]
    # a finished run given a larger budget goes on from where it stopped
    plans = learner_plans("pointmass", "both", 2 * TINY_STEPS, TINY_SNAPSHOTS, TINY)
    longer = build_zoo("pointmass", algo="both", seeds=2, plans=plans,
                       work_dir=str(tmp_path / "resumed"), value_episodes=2, n_train=5,
                       min_test=4, progress=False, log=lambda *_: None)
    sa, sb = full[1]["runs"]["sac"].snapshots, longer[1]["runs"]["sac"].snapshots
    assert sb["training_return"].shape == (2, 2 * TINY_SNAPSHOTS + 1)
    np.testing.assert_array_equal(sb["training_return"][:, :TINY_SNAPSHOTS + 1],
                                  sa["training_return"])
    np.testing.assert_array_equal(sb["env_steps"][:TINY_SNAPSHOTS + 1], sa["env_steps"])


def test_zoo_export_import_full_and_light(tmp_path, full_zoo):
    full = full_zoo
    assert _tiny_zoo(tmp_path / "a", deadline=time.time())[0] is None
    runs = load_runs(str(tmp_path / "a"), ["sac", "ppo"])
    assert list(runs) == ["sac"]
    # full export: small enough, one file; continuing from it elsewhere is bit-identical
    files = write_export(str(tmp_path / "x.npz"), runs, log=lambda *_: None)
    assert files == [str(tmp_path / "x.npz")]
    cont = _tiny_zoo(tmp_path / "b", imported=read_export(files[0]))
    _same_snapshots(full[1], cont[1])
    # light export: over the limit without the buffer, then split into parts; the continued
    # run keeps the snapshots so far, re-fills the buffer and still finishes
    msgs = []
    files = write_export(str(tmp_path / "y.npz"), runs, max_bytes=40_000, log=msgs.append)
    assert len(files) > 1 and all(f.startswith(str(tmp_path / "y.npz.part")) for f in files)
    assert "without replay buffers" in msgs[0]
    light = read_export(str(tmp_path / "y.npz"))
    assert light["sac"]["meta"]["export_exact"] is False
    assert len(light["sac"]["state"]) < len(runs["sac"]["state"])
    cont = _tiny_zoo(tmp_path / "c", imported=light)
    assert cont[0] is not None
    sa, sb = full[1]["runs"]["sac"].snapshots, cont[1]["runs"]["sac"].snapshots
    np.testing.assert_array_equal(sa["params"]["layers"][0]["w"][:, :2],
                                  sb["params"]["layers"][0]["w"][:, :2])
    assert sb["training_return"].shape == sa["training_return"].shape
    # every continued interval trained (reward per env step is logged each interval; the
    # training return is NaN where no 50-step episode ended inside a 16-iteration interval)
    assert np.all(np.isfinite(sb["reward_per_step"][:, 1:]))
    # other settings than the saved run's are refused, naming the field
    with pytest.raises(ValueError, match="batch_size"):
        plans = learner_plans("pointmass", "sac", TINY_STEPS, TINY_SNAPSHOTS,
                              {"sac": {**TINY["sac"], "batch_size": 64}})
        build_zoo("pointmass", algo="sac", seeds=2, plans=plans, work_dir=str(tmp_path / "a"),
                  progress=False, log=lambda *_: None, n_train=5, min_test=4)


def test_cli_zoo_end_to_end(tmp_path, capsys):
    work, out, exp = tmp_path / "work", tmp_path / "zoo", tmp_path / "run.npz"
    sets = [f"--set={k}.{f}={json.dumps(v)}" for k, d in TINY.items() for f, v in d.items()]
    argv = ["zoo", "--task", "pointmass", "--algo", "both", "--seeds", "2", "--env-steps",
            str(TINY_STEPS), "--snapshots", str(TINY_SNAPSHOTS), "--value-episodes", "2",
            "--work", str(work), "--out", str(out), "--export", str(exp), "--quiet", *sets]
    assert cli.main(argv + ["--time-limit", "1e-6"]) == 0
    assert "stopped at the time limit" in capsys.readouterr().out and exp.exists()
    assert not (out / "zoo.json").exists()
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "spread train" in text and "spread test" in text and "-> " in text
    assert {"zoo.npz", "zoo.json", "train_log.jsonl", "curves.png",
            "returns_hist.png"} <= set(os.listdir(out))
    zoo = zoo_mod.load_zoo(str(out))
    assert zoo.size == 2 * 2 * (TINY_SNAPSHOTS + 1) and len(zoo.train_ids) == 17
    assert {o["learner"] for o in zoo.origins} == {"sac", "ppo"}
    assert set(zoo.info["spread"]) == {"train", "test"}
    for split, ids in (("train", zoo.train_ids), ("test", zoo.test_ids)):
        chk = spread_check(zoo.returns[ids], zoo.returns)
        assert zoo.info["spread"][split]["pass"] == chk["pass"]
        assert zoo.info["spread"][split]["largest_gap"] == pytest.approx(chk["largest_gap"])
    rows = [json.loads(line) for line in open(out / "train_log.jsonl")]
    assert len(rows) == zoo.size and all("measured_return" in r for r in rows)
    assert sum(r["zoo"] == "train" for r in rows) == 17
    # bad settings are refused before any work, naming the field
    assert cli.main(argv[:-len(sets)] + ["--set", "sac.nope=1", "--force"]) == 2
    assert "nope" in capsys.readouterr().err
    assert cli.main(["zoo", "--task", "pointmass", "--plots-only", "--out", str(out)]) == 0

    # --extend: new seeds add test policies; the old ids, params and training split stay
    grown = tmp_path / "grown"
    ext = [a for a in argv if a not in ("--export", str(exp))]
    ext = ext[:ext.index("--work")] + ext[ext.index("--out") + 2:]
    assert cli.main(ext + ["--work", str(tmp_path / "work2"), "--out", str(grown), "--extend",
                           str(out), "--min-test", "13"]) == 2      # same seed as the zoo's
    assert "another seed" in capsys.readouterr().err
    assert cli.main(ext + ["--work", str(tmp_path / "work2"), "--out", str(grown), "--extend",
                           str(out), "--min-test", "13", "--seed", "1"]) == 0
    assert "join the test split as ids 28.." in capsys.readouterr().out
    big = zoo_mod.load_zoo(str(grown))
    assert big.size >= zoo.size + 2 and len(big.test_ids) >= 13
    assert big.train_ids == zoo.train_ids and set(zoo.test_ids) < set(big.test_ids)
    np.testing.assert_array_equal(big.returns[:zoo.size], zoo.returns)
    for a, b in zip(jax.tree_util.tree_leaves(zoo.params), jax.tree_util.tree_leaves(big.params),
                    strict=True):
        np.testing.assert_array_equal(a, b[:zoo.size])
    assert all(o["run_seed"] == 1 for o in big.origins[zoo.size:])
    lo, hi = zoo.returns.min(), zoo.returns.max()
    assert np.all((big.returns >= lo) & (big.returns <= hi))
    rows = [json.loads(line) for line in open(grown / "train_log.jsonl")]
    assert sum(r["zoo"] == "test" for r in rows) == len(big.test_ids)
    assert len({(r["learner"], r["seed"]) for r in rows}) == 8   # 2 learners x (2 + 2) seeds
