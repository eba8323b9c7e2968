"""The protocol's value intervals (issue 64 item 1, paper/trust_phase.py): per lane the
conformal interval of every test policy, calibrated on perturbed training policies measured
here (never the test policies), the per-method "trust" block checked against plain NumPy,
JSON without bare Infinity, on untrained pointmass lanes (pm_files)."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.evaluate import trust as tr

LEVEL = 0.8  # min_calibration(0.8) == 4


@pytest.fixture(scope="module")
def pm_lanes(pm_files):
    """Two untrained rl2s lanes (seeds 0, 1) of pm_files' train data and the inputs of
    run_trust: any simulator will do for the plumbing and the arithmetic."""
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.data.values import true_values
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.lanes import init_lanes
    from rl2s_jax.zoo.zoo import policies_for

    train_ds, test_ds = load_dataset(pm_files["train"]), load_dataset(pm_files["test"])
    cfg = TrainConfig.small(task="pointmass", method="rl2s", **{"vd.horizon": 20})
    assert cfg.n_elites >= 2
    data = make_train_data(train_ds, policies_for(train_ds), cfg)
    lanes = [("rl2s", 0), ("rl2s", 1)]
    states = init_lanes(jnp.stack([jax.random.PRNGKey(s) for _, s in lanes]), cfg, data,
                        eps=jnp.asarray([0.25, 0.25], jnp.float32))
    kw = dict(task="pointmass", train_ds=train_ds, train_pols=policies_for(train_ds),
              test_ds=test_ds, test_pols=policies_for(test_ds),
              truth=true_values(test_ds, cfg.vd.horizon, cfg.gamma), horizon=cfg.vd.horizon,
              gamma=cfg.gamma, sizes={"value_episodes": 4, "eval_episodes": 4}, seed=0,
              level=LEVEL)
    return {"adversarial": (lanes, states)}, kw


def _run(pm_lanes, n, level=LEVEL, n_evaluated=0):
    from rl2s_jax.paper.trust_phase import run_trust

    finals, kw = pm_lanes
    result = {"lanes": {"rl2s/0": {}, "rl2s/1": {}}, "timings": {}, "command": "cmd"}
    run_trust(result, finals, n_calibration=n, **{**kw, "level": level},
              **({"n_evaluated": n_evaluated} if n_evaluated else {}))
    return result


@pytest.mark.slow
def test_protocol_trust_block_by_hand(pm_lanes):
    """The block's numbers from the lanes' stored intervals with NumPy; the seed-spread
    interval scaled to the same coverage by hand; the JSON is strict (no Infinity)."""
    r = _run(pm_lanes, 6)
    truth = np.asarray(pm_lanes[1]["truth"], np.float64)
    json.dumps(r, allow_nan=False)
    b = r["trust"]["rl2s"]
    assert {"level", "coverage", "width_over_range", "worst_flagged", "runs",
            "command"} <= set(b) and b["runs"] == 2 and b["command"] == "cmd"
    assert b["level"] == LEVEL and r["trust_calibration"]["n"] == 6
    covs, wors, flagged, values = [], [], [], []
    for lane in ("rl2s/0", "rl2s/1"):
        t = r["lanes"][lane]["trust"]
        lo, hi = np.asarray(t["interval"], np.float64).T
        assert not t["q_infinite"] and np.all(hi > lo)
        np.testing.assert_allclose((lo + hi) / 2, t["sim_value"], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(hi - lo, 2 * t["q"] * np.asarray(t["sigma"]), rtol=1e-6)
        covs.append(np.mean((truth >= lo) & (truth <= hi)))
        wors.append(np.mean(hi - lo) / np.ptp(truth))
        worst = int(np.argmax(np.abs(np.asarray(t["sim_value"]) - truth)))
        flagged.append(not t["trusted"][worst])
        values.append(t["sim_value"])
    assert b["coverage"] == pytest.approx(np.mean(covs))
    assert b["width_over_range"] == pytest.approx(np.mean(wors))
    assert b["worst_flagged"] == pytest.approx(np.mean(flagged))
    v = np.asarray(values)
    sd = v.std(0, ddof=1)
    need = np.sort((np.abs(v - truth) / sd).ravel())[math.ceil(b["coverage"] * v.size) - 1]
    assert b["seed_spread"]["scaled_width_over_range"] == pytest.approx(
        np.mean(2 * need * sd) / np.ptp(truth))
    assert b["narrower_than_seed_spread"] == (
        b["width_over_range"] < b["seed_spread"]["scaled_width_over_range"])
    # the seeds as one estimate: centred on their mean, the seed spread inside sigma
    c = b["seeds_combined"]
    lo, hi = np.asarray(c["interval"], np.float64).T
    np.testing.assert_allclose((lo + hi) / 2, v.mean(0), rtol=1e-6, atol=1e-9)
    assert np.all(hi - lo >= 2 * c["q"] * v.std(0, ddof=1) - 1e-9) and c["seeds"] == 2
    assert c["coverage"] == pytest.approx(np.mean((truth >= lo) & (truth <= hi)))
    assert c["width_over_range"] == pytest.approx(np.mean(hi - lo) / np.ptp(truth))


@pytest.mark.slow
def test_protocol_trust_too_few_calibration_policies_is_valid_json(pm_lanes):
    """Fewer calibration policies than the level needs: q infinite, flagged, the intervals'
    ends null (read back as -inf, inf by interval_from_json), never a bare Infinity."""
    r = _run(pm_lanes, 6, level=0.95)  # the other test's programs; 0.95 needs 19
    assert tr.min_calibration(0.95) > 6
    text = json.dumps(r, allow_nan=False)
    assert "Infinity" not in text
    t = r["lanes"]["rl2s/0"]["trust"]
    assert t["q_infinite"] and t["q"] is None and all(t["unbounded"])
    assert tr.interval_from_json(t["interval"][0]) == (-math.inf, math.inf)
    b = r["trust"]["rl2s"]
    assert b["coverage"] == 1.0 and b["width_over_range"] is None and b["unbounded_runs"] == 2


@pytest.mark.slow
def test_lane_features_equal_the_single_simulator_ones(pm_lanes):
    """lane_features (one program over lanes and elites) gives each lane what
    policy_features gives its simulator alone with the same key."""
    from rl2s_jax.model.simulator import start_pool
    from rl2s_jax.paper.fork import take_lanes
    from rl2s_jax.train.step import simulator

    finals, kw = pm_lanes
    sims = simulator(finals["adversarial"][1])
    pool = start_pool(kw["test_ds"])
    keys = jnp.stack([jax.random.PRNGKey(7), jax.random.PRNGKey(8)])
    units = tr.lane_data_disagreement(sims, kw["train_ds"])
    roll = dict(n_episodes=3, horizon=10, gamma=kw["gamma"])
    lanes = tr.lane_features(sims, kw["test_pols"], pool, keys, units, **roll)
    for i in range(2):
        one = simulator(take_lanes(finals["adversarial"][1], i))
        assert units[i] == pytest.approx(tr.data_disagreement(one, kw["train_ds"]), rel=1e-5)
        ref = tr.policy_features(one, pool, kw["test_pols"], key=keys[i], u_unit=units[i],
                                 **roll)
        assert lanes[i]["member_values"].shape == ref["member_values"].shape
        for k in ref:
            np.testing.assert_allclose(lanes[i][k], ref[k], rtol=1e-4, atol=1e-5, err_msg=k)
    # the elites alone from fewer episodes: their values are policy_features' at that many
    few = tr.lane_features(sims, kw["test_pols"], pool, keys, units, member_episodes=2, **roll)
    for i in range(2):
        one = simulator(take_lanes(finals["adversarial"][1], i))
        ref = tr.policy_features(one, pool, kw["test_pols"], key=keys[i], u_unit=units[i],
                                 **dict(roll, n_episodes=2))
        np.testing.assert_allclose(few[i]["member_values"], ref["member_values"], rtol=1e-4,
                                   atol=1e-5)
        np.testing.assert_allclose(few[i]["sim_value"], lanes[i]["sim_value"], rtol=1e-6)


def test_json_safe_and_interval_from_json():
    x = {"a": [1.0, math.inf, np.float32(2.5)], "b": np.array([-np.inf, 3.0]), "c": math.nan}
    assert tr.json_safe(x) == {"a": [1.0, None, 2.5], "b": [None, 3.0], "c": None}
    assert tr.interval_from_json([None, 2.0]) == (-math.inf, 2.0)
    assert tr.interval_from_json([1.0, None]) == (1.0, math.inf)
    with pytest.raises(ValueError, match="interval: expected"):
        tr.interval_from_json([1.0])


def test_lane_intervals_never_see_the_test_truth():
    """lane_trust: the intervals and flags depend on the calibration policies only; the test
    truth changes the measured coverage, nothing else."""
    from rl2s_jax.paper.trust_phase import lane_trust

    rng = np.random.default_rng(0)
    feats = {k: rng.uniform(1, 2, 5) for k in ("sim_value", "member_sd", "eval_se", "support")}
    feats["seed_sd"] = np.zeros(5)
    cal = {k: rng.uniform(1, 2, 8) for k in feats}
    cal_truth = cal["sim_value"] + rng.normal(0, 0.3, 8)
    a = lane_trust(feats, cal, cal_truth, list("abcde"), feats["sim_value"], LEVEL)
    b = lane_trust(feats, cal, cal_truth, list("abcde"), feats["sim_value"] + 50.0, LEVEL)
    assert a["interval"] == b["interval"] and a["trusted"] == b["trusted"]
    assert a["coverage"] == 1.0 and b["coverage"] == 0.0
    sigma = tr.difficulty(cal["member_sd"], cal["seed_sd"], cal["eval_se"], cal["support"],
                          tr.sigma_floor(cal["sim_value"]))
    q = _ref_q(np.abs(cal["sim_value"] - cal_truth) / sigma)
    assert a["q"] == pytest.approx(q)


def _ref_q(scores, level=LEVEL):
    s = np.sort(scores)
    return s[math.ceil((len(s) + 1) * level) - 1]


def test_seed_spread_scaled_to_a_coverage_by_hand():
    """seed_spread: run s's value +- k sd_over_seeds, k the smallest reaching the coverage
    (pooled over runs), width over the truth's range; one seed: skipped."""
    from rl2s_jax.paper.trust_phase import seed_spread

    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 10, 6)
    v = truth + rng.normal(0, 1, (3, 6))
    sd = v.std(0, ddof=1)
    for cov in (0.5, 0.75):
        k = np.sort((np.abs(v - truth) / sd).ravel())[math.ceil(cov * v.size) - 1]
        s = seed_spread(v, truth, 0.9, cov)
        assert s["scaled_width_over_range"] == pytest.approx(2 * k * sd.mean() / np.ptp(truth))
        inside = np.abs(v - truth) <= 1.6448536 * sd
        assert s["coverage"] == pytest.approx(inside.mean())
    assert "skipped" in seed_spread(v[:1], truth, 0.9, 0.5)


@pytest.mark.slow
def test_simulated_values_with_intervals(pm_files, pm_checkpoint):
    """The Python API: values as simulated_values gives them (the same key), intervals
    value +- q sigma with q the conformal quantile of the calibration policies' scores by
    hand; bad input named before any work."""
    import rl2s_jax as rl2s
    from rl2s_jax.data.values import true_values
    from rl2s_jax.model.simulator import simulator_returns, start_pool

    sim = rl2s.load_simulator(pm_checkpoint)
    train, test = rl2s.load_dataset(pm_files["train"]), rl2s.load_dataset(pm_files["test"])
    key, pool, roll = jax.random.PRNGKey(3), start_pool(test), dict(n_episodes=4, horizon=20,
                                                                   gamma=0.99)
    cal = (rl2s.policies_for(train), true_values(train, 20, 0.99))
    r = rl2s.simulated_values_with_intervals(sim, rl2s.policies_for(test), pool, key,
                                             calibration=cal, data=train, level=0.5, **roll)
    ret, _ = simulator_returns(sim, None, rl2s.policies_for(test), pool, key, **roll)
    np.testing.assert_allclose(r["value"], np.asarray(ret).mean(1), rtol=1e-5)
    cf = tr.combine_features([tr.policy_features(
        sim, pool, cal[0], key=key, u_unit=tr.data_disagreement(sim, train), **roll)])
    sigma = tr.difficulty(cf["member_sd"], cf["seed_sd"], cf["eval_se"], cf["support"],
                          tr.sigma_floor(cf["sim_value"]))
    q = _ref_q(np.abs(cf["sim_value"] - np.asarray(cal[1])) / sigma, 0.5)
    assert r["calibration"]["q"] == pytest.approx(q, rel=1e-6)
    np.testing.assert_allclose(r["hi"] - r["value"], q * r["sigma"], rtol=1e-6)
    np.testing.assert_allclose(r["value"] - r["lo"], q * r["sigma"], rtol=1e-6)
    assert r["trusted"].shape == (3,) and r["calibration"]["n_heldout"] == 3
    with pytest.raises(ValueError, match="calibration: 3 policies but 2 true values"):
        rl2s.simulated_values_with_intervals(sim, cal[0], pool, key, level=0.5, **roll,
                                             calibration=(cal[0], cal[1][:2]))
    with pytest.raises(ValueError, match="sims: expected a Simulator"):
        rl2s.simulated_values_with_intervals("x", cal[0], pool, key, calibration=cal, **roll)


def test_merge_results_recomputes_the_trust_block_over_joined_seeds():
    """Two runs of other seeds (paper.py --first-seed): carry_trust's "trust" block is the one
    of all the method's lanes together (method_block on the four runs, by seed), the
    calibration the runs share; runs calibrated on other policies are refused; the guard
    blocks join per method."""
    from experiment_scripts import load_script

    from rl2s_jax.paper.trust_phase import lane_trust, method_block

    mr = load_script("merge_results")
    rng = np.random.default_rng(2)
    truth = rng.uniform(0, 10, 5)
    cal = {k: rng.uniform(1, 2, 8) for k in ("sim_value", "member_sd", "eval_se", "support",
                                              "seed_sd")}
    reps, parts = [], []
    for ids in ([0, 1], [2, 3]):
        lanes = {}
        for s in ids:
            f = {k: rng.uniform(0.5, 1.5, 5) for k in ("member_sd", "eval_se", "support")}
            f.update(sim_value=truth + rng.normal(0, 1, 5), seed_sd=np.zeros(5))
            reps.append(lane_trust(f, cal, cal["sim_value"] + rng.normal(0, .3, 8),
                                   list("abcde"), truth, LEVEL))
            lanes[f"rl2s/{s}"] = {"seed": s, "trust": tr.json_safe(reps[-1])}
        parts.append({"lanes": lanes, "true_value": truth.tolist(), "command": "c",
                      "trust_calibration": {"true_value": [1.0 + ids[0] / 1e4],
                                            "origins": [{"i": 0}]},
                      "guard": {"chosen": "floor", "floor": {f"m{ids[0]}": 1},
                                "interval": {f"m{ids[0]}": 2}}})
    merged = {"lanes": {**parts[0]["lanes"], **parts[1]["lanes"]},
              "true_value": truth.tolist(), "command": "c && c"}
    parts[0]["trust"] = {"rl2s": {"runs": 2, "seeds_combined": {"seeds": 2}}}
    mr.carry_trust(merged, parts)
    assert "seeds_combined" not in merged["trust"]["rl2s"]  # no part had all four seeds
    parts[0]["trust"] = {"rl2s": {"runs": 4, "seeds_combined": {"seeds": 4}}}
    mr.carry_trust(merged, parts)
    assert merged["trust"]["rl2s"].pop("seeds_combined") == {"seeds": 4}
    ref = tr.json_safe(method_block(reps, [r["sim_value"] for r in reps], truth, LEVEL,
                                    "c && c"))
    assert merged["trust"]["rl2s"] == ref and ref["runs"] == 4
    assert merged["guard"]["floor"] == {"m0": 1, "m2": 1} and merged["guard"]["chosen"] == "floor"
    assert merged["trust_calibration"]["truth_differs_by"] == pytest.approx(2e-4)
    parts[1]["trust_calibration"] = {"true_value": [1.0], "origins": [{"i": 1}]}
    with pytest.raises(ValueError, match="trust_calibration: the runs calibrated"):
        mr.carry_trust(merged, parts)


@pytest.mark.slow
def _diverge_lane_part(monkeypatch, tp, part: int) -> None:
    """``family_trust`` with the second lane's features of one policy set (0: test, 1:
    calibration, 2: evaluated) made non-finite, as a diverged lane's would be."""
    real = tp.family_trust

    def diverged(*a, **kw):
        out = real(*a, **kw)
        out[1][part]["sim_value"] = np.full_like(out[1][part]["sim_value"], np.nan)
        return out
    monkeypatch.setattr(tp, "family_trust", diverged)


def test_a_diverged_lane_is_skipped_and_a_failure_spares_the_run(pm_lanes, monkeypatch):
    """A lane whose features are not finite gets no interval and leaves its method's block
    (the other seed's alone, no seeds_combined); an error in the phase is recorded and
    logged, the protocol goes on."""
    import argparse
    import types

    from rl2s_jax.paper import trust_phase as tp

    _diverge_lane_part(monkeypatch, tp, part=0)
    r = _run(pm_lanes, 6)
    assert r["lanes"]["rl2s/1"]["trust"] == {"skipped": "non-finite simulated values or support"}
    b = r["trust"]["rl2s"]
    assert b["runs"] == 1 and "seeds_combined" not in b and "skipped" in b["seed_spread"]
    assert tp.trust_from_lanes({**r, "true_value": pm_lanes[1]["truth"].tolist()})["rl2s"][
        "runs"] == 1

    def broken(*a, **kw):
        raise RuntimeError("boom")
    monkeypatch.setattr(tp, "run_trust", broken)
    monkeypatch.setattr(tp, "policies_for", lambda ds: None)
    result, phases = {"true_value": [1.0]}, []
    args = argparse.Namespace(trust_calibration=3, task="pointmass", data_seed=0,
                              trust_evaluated=0, trust_level=0.9, trust_episodes=None,
                              trust_member_episodes=16, episode_length=None)
    tp.trust_phase(args, result, {}, {"train": None, "test": None},
                   {"f": types.SimpleNamespace(vd=types.SimpleNamespace(horizon=5), gamma=0.9)}, {},
                   phase=lambda name, t0: phases.append(name), save=lambda: None)
    assert result["trust"] == {"error": "RuntimeError: boom"} and phases == ["trust"]


@pytest.mark.slow
def test_protocol_trust_evaluated_set(pm_lanes, monkeypatch):
    """--trust-evaluated 4: perturbed TEST policies (their own key) measured in the real env
    as the calibration set is, rolled out on their own; each lane's intervals on them
    calibrated on the calibration set alone (the test policies' reports exactly as
    without the flag), coverage and width by NumPy; trust_from_lanes gives the same block; without
    the flag no new key; a lane diverged on the evaluated set alone keeps its test report."""
    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.paper import trust_phase as tp

    finals, kw = pm_lanes
    plain, r = _run(pm_lanes, 6), _run(pm_lanes, 6, n_evaluated=4)
    assert "trust_evaluated" not in plain and "trust_evaluated" not in plain["timings"]
    assert not any("evaluated" in plain["lanes"][k]["trust"] for k in plain["lanes"])
    assert "evaluated" not in plain["trust"]["rl2s"]
    assert "evaluated" not in tp.trust_from_lanes({**plain, "true_value": kw["truth"].tolist()})[
        "rl2s"]
    json.dumps(r, allow_nan=False)
    assert r["trust_calibration"] == plain["trust_calibration"]
    ev = r["trust_evaluated"]
    assert ev["n"] == 4 and ev["origins"] != r["trust_calibration"]["origins"]
    _, truth, origins = tp.calibration_policies(
        "pointmass", kw["test_pols"], n=4, seed=kw["seed"] + 5000,
        n_episodes=kw["sizes"]["value_episodes"], horizon=kw["horizon"], gamma=kw["gamma"],
        episode_length=get_task("pointmass").episode_length)
    np.testing.assert_array_equal(ev["true_value"], truth)
    assert ev["origins"] == origins and "trust_evaluated" in r["timings"]
    truth = np.asarray(truth, np.float64)
    covs, wors, flagged = [], [], []
    for lane in ("rl2s/0", "rl2s/1"):
        t, t0 = r["lanes"][lane]["trust"], plain["lanes"][lane]["trust"]
        # the evaluated set rolls out on its own keys: the test report is unchanged, bit for bit
        assert {k: v for k, v in t.items() if k != "evaluated"} == t0
        e = t["evaluated"]
        assert e["n"] == 4 and e["q"] == pytest.approx(t["q"], rel=1e-12)
        lo, hi = np.asarray(e["interval"], np.float64).T
        np.testing.assert_allclose((lo + hi) / 2, e["sim_value"], rtol=1e-6, atol=1e-9)
        covs.append(np.mean((truth >= lo) & (truth <= hi)))
        assert e["coverage"] == pytest.approx(covs[-1])
        wors.append(np.mean(hi - lo) / np.ptp(truth))
        assert e["width_over_range"] == pytest.approx(wors[-1])
        worst = int(np.argmax(np.abs(np.asarray(e["sim_value"]) - truth)))
        flagged.append(not e["trusted"][worst])
        assert e["worst"] == {"name": f"evaluated-{worst}", "flagged": flagged[-1]}
    b = r["trust"]["rl2s"]["evaluated"]
    assert b["n"] == 4 and b["runs"] == 2 and "4 perturbed/interpolated test" in b["what"]
    assert b["coverage"] == pytest.approx(np.mean(covs))
    assert b["width_over_range"] == pytest.approx(np.mean(wors))
    assert b["worst_flagged"] == pytest.approx(np.mean(flagged))
    assert tp.trust_from_lanes({**r, "true_value": kw["truth"].tolist()})["rl2s"][
        "evaluated"] == b

    _diverge_lane_part(monkeypatch, tp, part=2)
    d = _run(pm_lanes, 6, n_evaluated=4)
    assert d["lanes"]["rl2s/1"]["trust"]["evaluated"] == {
        "skipped": "non-finite simulated values or support"}
    assert d["lanes"]["rl2s/1"]["trust"]["interval"] == r["lanes"]["rl2s/1"]["trust"]["interval"]
    assert d["trust"]["rl2s"]["evaluated"]["runs"] == 1 and d["trust"]["rl2s"]["runs"] == 2


def test_evaluated_set_leaves_the_test_rollout_program_as_it_was(pm_lanes, monkeypatch):
    """The evaluated set rolls out in a call of its own (other keys): the test and calibration
    policies' rollout gets exactly the policies it gets without the flag, so it is the same
    XLA program (on the GPU one stacked rollout of more policies rounded HalfCheetah's
    elites-alone values differently, moving member_sd by a median 6-37% per lane)."""
    from rl2s_jax.policy.policy import num_policies

    calls = []
    real = tr.lane_features

    def counting(sims, policies, *a, **kw):
        calls.append(num_policies(policies))
        return real(sims, policies, *a, **kw)
    monkeypatch.setattr(tr, "lane_features", counting)
    _run(pm_lanes, 6)
    plain, calls[:] = list(calls), []
    _run(pm_lanes, 6, n_evaluated=4)
    assert calls == [*plain, 4] and len(plain) == 1


def test_trust_evaluated_flag_refused_before_any_work(tmp_path):
    """--trust-evaluated below 0, or without calibration policies, names the flag."""
    from experiment_scripts import load_script

    paper = load_script("paper")
    base = ["--task", "hopper", "--out", str(tmp_path)]
    for extra, msg in ((["--trust-evaluated", "-1"], "trust-evaluated: expected an int >= 0"),
                       (["--trust-evaluated", "4", "--trust-calibration", "0"],
                        "trust-evaluated: needs --trust-calibration")):
        with pytest.raises(SystemExit, match=msg):
            paper.check_arguments(paper.parse_args(base + extra))
    assert paper.parse_args(base).trust_evaluated == 0


def test_evaluated_report_and_block_by_hand():
    """evaluated_report: the lane's calibration (q as lane_trust's), intervals fixed by the
    calibration alone, coverage and width by NumPy on a set some truths miss;
    method_evaluated: means over the lanes, None where a lane's width is None, skipped lanes
    left out, sets of other sizes not pooled, no lanes with one: None."""
    from rl2s_jax.paper.trust_phase import evaluated_report, lane_trust, method_evaluated

    rng = np.random.default_rng(4)
    keys = ("sim_value", "member_sd", "eval_se", "support")
    feats = {k: rng.uniform(1, 2, 6) for k in keys} | {"seed_sd": np.zeros(6)}
    cal = {k: rng.uniform(1, 2, 8) for k in keys} | {"seed_sd": np.zeros(8)}
    cal_truth = cal["sim_value"] + rng.normal(0, 0.3, 8)
    truth = feats["sim_value"] + np.array([0.0, 0.01, -0.02, 30.0, -30.0, 0.03])
    e = evaluated_report(feats, cal, cal_truth, truth, LEVEL)
    lo, hi = np.asarray(e["interval"], np.float64).T
    inside = (truth >= lo) & (truth <= hi)
    assert 0 < inside.mean() < 1 and e["coverage"] == pytest.approx(inside.mean())
    assert e["width_over_range"] == pytest.approx(np.mean(hi - lo) / np.ptp(truth))
    assert e["q"] == lane_trust(feats, cal, cal_truth, list("abcdef"), truth, LEVEL)["q"]
    assert evaluated_report(feats, cal, cal_truth, truth + 9.0, LEVEL)["interval"] == e["interval"]
    worst = int(np.argmax(np.abs(feats["sim_value"] - truth)))
    assert e["worst"] == {"name": f"evaluated-{worst}", "flagged": not e["trusted"][worst]}
    a, b = tr.json_safe(e), tr.json_safe({**e, "coverage": 0.25, "worst": {"flagged": False}})
    block = method_evaluated([{"evaluated": a}, {"evaluated": b}, {"evaluated": {"skipped": "x"}},
                              {}])
    assert block["runs"] == 2 and block["n"] == 6
    assert block["coverage"] == pytest.approx((e["coverage"] + 0.25) / 2)
    assert block["worst_flagged"] == pytest.approx(e["worst"]["flagged"] / 2)
    med = np.median(hi - lo) / np.ptp(truth)
    assert block["median_width_over_range"] == pytest.approx(med)
    # one policy's interval 1000x wider: the mean follows it, the median does not
    wide = json.loads(json.dumps(a))
    wide["interval"][0] = [wide["interval"][0][0], wide["interval"][0][0] + 1000 * np.ptp(truth)]
    wide["mean_width"] = float(np.mean([h - lo_ for lo_, h in wide["interval"]]))
    wide["width_over_range"] = wide["mean_width"] / float(np.ptp(truth))
    out = method_evaluated([{"evaluated": wide}])
    assert out["width_over_range"] > 100 and out["median_width_over_range"] == pytest.approx(
        np.median([h - lo_ for lo_, h in wide["interval"]]) / np.ptp(truth))
    assert method_evaluated([{"evaluated": a}, {"evaluated": {**b, "width_over_range": None}}])[
        "width_over_range"] is None
    assert "skipped" in method_evaluated([{"evaluated": a}, {"evaluated": {**b, "n": 5}}])
    assert method_evaluated([{}, {"evaluated": {"skipped": "x"}}]) is None


def test_merge_results_carries_the_evaluated_block():
    """carry_trust on runs whose lanes have an evaluated report: the method's block as
    without them, plus "evaluated" pooled over the four lanes of both runs."""
    from experiment_scripts import load_script

    from rl2s_jax.paper.trust_phase import evaluated_report, lane_trust, method_evaluated

    mr = load_script("merge_results")
    rng = np.random.default_rng(5)
    keys = ("member_sd", "eval_se", "support")
    truth, ev_truth = rng.uniform(0, 10, 5), rng.uniform(0, 10, 3)
    cal = {k: rng.uniform(1, 2, 8) for k in keys + ("sim_value",)} | {"seed_sd": np.zeros(8)}
    cal_truth = cal["sim_value"] + rng.normal(0, .3, 8)
    parts, entries = [], []
    for ids in ([0, 1], [2, 3]):
        lanes = {}
        for s in ids:
            f, g = ({k: rng.uniform(0.5, 1.5, n) for k in keys} | {
                "sim_value": t + rng.normal(0, 1, n), "seed_sd": np.zeros(n)}
                for t, n in ((truth, 5), (ev_truth, 3)))
            e = tr.json_safe(lane_trust(f, cal, cal_truth, list("abcde"), truth, LEVEL))
            entries.append(dict(e, evaluated=tr.json_safe(
                evaluated_report(g, cal, cal_truth, ev_truth, LEVEL))))
            lanes[f"rl2s/{s}"] = {"seed": s, "trust": entries[-1]}
        parts.append({"lanes": lanes, "true_value": truth.tolist(), "command": "c",
                      "trust_calibration": {"true_value": [1.0], "origins": [{"i": 0}]}})
    merged = {"lanes": {**parts[0]["lanes"], **parts[1]["lanes"]},
              "true_value": truth.tolist(), "command": "c && c"}
    mr.carry_trust(merged, parts)
    assert merged["trust"]["rl2s"].pop("evaluated") == tr.json_safe(method_evaluated(entries))
    bare = {**merged, "lanes": {k: {**v, "trust": {x: y for x, y in v["trust"].items()
                                                    if x != "evaluated"}}
                                for k, v in merged["lanes"].items()}}
    mr.carry_trust(bare, parts)
    assert merged["trust"] == bare["trust"] and bare["trust"]["rl2s"]["runs"] == 4
    assert method_evaluated(entries)["runs"] == 4


def test_trust_phase_passes_the_flag_and_logs_the_evaluated_block(monkeypatch, capsys):
    """paper.py's trust step: --trust-evaluated reaches run_trust as n_evaluated, and each
    method with an "evaluated" block gets its own log line."""
    import argparse
    import types

    from rl2s_jax.paper import trust_phase as tp

    seen = {}
    block = {"level": 0.9, "coverage": 0.9, "width_over_range": 0.2, "worst_flagged": 0.5,
             "runs": 2, "unbounded_runs": 0, "seed_spread": {"skipped": "one seed"},
             "evaluated": {"n": 4, "coverage": 0.75, "width_over_range": 0.3,
                           "worst_flagged": 0.5, "runs": 2}}

    def fake(result, finals, **kw):
        seen.update(kw)
        result["trust"] = {"rl2s": block}
    monkeypatch.setattr(tp, "run_trust", fake)
    monkeypatch.setattr(tp, "policies_for", lambda ds: None)
    args = argparse.Namespace(trust_calibration=3, task="pointmass", data_seed=0,
                              trust_evaluated=4, trust_level=0.9, trust_episodes=None,
                              trust_member_episodes=16, episode_length=None)
    tp.trust_phase(args, {"true_value": [1.0]}, {}, {"train": None, "test": None},
                   {"f": types.SimpleNamespace(vd=types.SimpleNamespace(horizon=5), gamma=0.9)}, {},
                   phase=lambda name, t0: None, save=lambda: None)
    assert seen["n_evaluated"] == 4
    assert ("[paper] trust rl2s evaluated: 4 perturbed test policies: coverage 0.750, "
            "width/range 0.300, worst policy flagged in 0.500 of 2 runs") in capsys.readouterr().out
