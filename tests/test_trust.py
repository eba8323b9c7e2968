"""Value intervals (issue 64, evaluate/trust.py): the conformal math against plain NumPy and
its finite-sample coverage on synthetic exchangeable data; the flags; perturbed calibration
policies; the plumbing of `rl2s evaluate --level` on the tiny pointmass fixtures."""

import json
import math
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from rl2s_jax.evaluate import trust as tr


def _ref_quantile(scores, level):
    """Plain NumPy: the ceil((n+1) level)-th smallest score."""
    s = np.sort(scores)
    k = int(np.ceil((len(s) + 1) * level))
    return np.inf if k > len(s) else s[k - 1]


def _features(v, member_sd, support=None, seed_sd=None, eval_se=None):
    n = len(v)
    z = np.zeros(n)
    return {"sim_value": np.asarray(v, float), "member_sd": np.asarray(member_sd, float),
            "seed_sd": z if seed_sd is None else np.asarray(seed_sd, float),
            "eval_se": z if eval_se is None else np.asarray(eval_se, float),
            "support": np.ones(n) if support is None else np.asarray(support, float)}


def test_conformal_quantile_matches_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 5, 9, 10, 37):
        s = rng.exponential(size=n)
        for level in (0.5, 0.8, 0.9, 0.95):
            assert tr.conformal_quantile(s, level) == _ref_quantile(s, level)
    assert tr.conformal_quantile([1.0] * 8, 0.9) == math.inf  # ceil(9 * 0.9) = 9 > 8
    assert tr.min_calibration(0.9) == 9 and tr.min_calibration(0.5) == 1
    with pytest.raises(ValueError, match="level"):
        tr.conformal_quantile([1.0], 1.0)
    with pytest.raises(ValueError, match="scores"):
        tr.conformal_quantile([1.0, np.nan], 0.5)


def test_difficulty_is_the_stated_form():
    sd, seed, se, sup = np.array([1.0, 2.0]), np.array([2.0, 0.0]), np.array([2.0, 0.0]), \
        np.array([0.5, 3.0])
    want = np.sqrt(sd ** 2 + seed ** 2 + se ** 2) * np.maximum(1, sup) + 0.1
    np.testing.assert_allclose(tr.difficulty(sd, seed, se, sup, 0.1), want)
    with pytest.raises(ValueError, match="floor"):
        tr.difficulty(sd, seed, se, sup, 0.0)


@pytest.mark.parametrize("level", [0.8, 0.9])
def test_coverage_on_exchangeable_policies(level):
    """Calibration and test policies drawn alike (errors ~ sigma x t-noise, sigma known up to
    a scale): over many draws the test coverage is in [level, level + 1/(n+1)] (conformal's
    guarantee), up to Monte-Carlo error."""
    rng = np.random.default_rng(1)
    n_cal, n_test, draws = 19, 20, 400
    covered = []
    for _ in range(draws):
        m = n_cal + n_test
        spread = rng.uniform(0.1, 2.0, m)
        support = rng.uniform(0.5, 2.0, m)
        v = rng.normal(0, 10, m)
        truth = v + 1.7 * spread * np.maximum(1, support) * rng.standard_t(4, m)
        f = _features(v, spread, support)
        cal_f = {k: x[:n_cal] for k, x in f.items()}
        test_f = {k: x[n_cal:] for k, x in f.items()}
        cal = tr.calibrate(cal_f, truth[:n_cal], ["heldout"] * n_cal, level)
        iv = tr.intervals(test_f, cal)
        t = truth[n_cal:]
        covered.append(np.mean((t >= np.array(iv["lo"])) & (t <= np.array(iv["hi"]))))
    cov = float(np.mean(covered))
    mc = 3 * np.std(covered) / np.sqrt(draws)
    assert level - mc <= cov <= level + 1 / (n_cal + 1) + mc, cov


def test_training_policies_only_when_heldout_are_too_few():
    rng = np.random.default_rng(2)
    v = rng.normal(size=12)
    truth = v + rng.normal(size=12)
    f = _features(v, np.ones(12))
    kinds = ["heldout"] * 9 + ["train"] * 3
    cal = tr.calibrate(f, truth, kinds, 0.9)
    assert (cal["used"], cal["n"], cal["optimistic"]) == ("heldout", 9, False)
    sigma = tr.difficulty(f["member_sd"], 0, 0, 1, cal["floor"])
    assert cal["q"] == _ref_quantile((np.abs(v - truth) / sigma)[:9], 0.9)
    cal = tr.calibrate(f, truth, ["heldout"] * 8 + ["train"] * 4, 0.9)
    assert (cal["used"], cal["n"], cal["optimistic"]) == ("all", 12, True)
    with pytest.raises(ValueError, match="kinds"):
        tr.calibrate(f, truth, ["test"] * 12, 0.9)
    with pytest.raises(ValueError, match="truth"):
        tr.calibrate(f, truth[:3], kinds, 0.9)


def test_flags_wide_and_off_support():
    cal_f = _features(np.linspace(0, 10, 9), np.full(9, 0.5), np.linspace(0.8, 1.2, 9))
    cal = tr.calibrate(cal_f, np.linspace(0, 10, 9) + 0.3, ["heldout"] * 9, 0.9)
    test_f = _features([5.0, 5.0, 5.0], [0.5, 50.0, 0.5], [1.0, 1.0, 1.5])
    iv = tr.intervals(test_f, cal)
    assert iv["trusted"] == [True, False, False]
    assert iv["why"] == ["", "wide", "off support"]


def test_stats_and_spread_interval_against_numpy():
    v, s, t = np.array([0.0, 1.0, 2.0, 3.0]), np.array([1.0, 0.5, 2.0, 1.0]), \
        np.array([0.5, 2.5, 2.0, 6.0])
    st = tr.interval_stats(v - s, v + s, t)
    assert st["coverage"] == 0.5 and st["mean_width"] == pytest.approx(2 * s.mean())
    assert st["width_over_range"] == pytest.approx(2 * s.mean() / 5.5)
    si = tr.spread_interval(v, s, t, 0.9, target=0.75)
    assert si["z"] == pytest.approx(1.6449, abs=1e-4)
    # the factor that covers 3 of 4: sorted |v - t| / s = 0, 0.5, 3, 3 -> 3
    assert si["scaled_mean_width"] == pytest.approx(2 * 3 * s.mean())


def test_perturbed_policies_interpolate_and_perturb():
    from rl2s_jax.policy import policy as pol

    ps = pol.stack_params([pol.init_policy(jax.random.PRNGKey(i), 3, 2, hidden=(8,))
                           for i in range(3)])
    ps["obs_mean"] = ps["obs_mean"] + np.arange(3)[:, None]
    new, origins = tr.perturbed_policies(ps, jax.random.PRNGKey(0), 5, noise=0.0)
    assert pol.num_policies(new) == 5 and len(origins) == 5
    for k, o in enumerate(origins):
        a = o["alpha"]
        want = (1 - a) * np.asarray(ps["layers"][0]["w"][o["i"]]) + a * np.asarray(
            ps["layers"][0]["w"][o["j"]])
        np.testing.assert_allclose(new["layers"][0]["w"][k], want, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(new["obs_mean"][k], (1 - a) * o["i"] + a * o["j"],
                                   rtol=1e-5)
    noisy, _ = tr.perturbed_policies(ps, jax.random.PRNGKey(0), 5, noise=0.5)
    assert not np.allclose(noisy["layers"][0]["w"], new["layers"][0]["w"])
    np.testing.assert_allclose(noisy["obs_mean"], new["obs_mean"])  # never perturbed
    again, _ = tr.perturbed_policies(ps, jax.random.PRNGKey(0), 5, noise=0.5)
    np.testing.assert_array_equal(again["layers"][0]["w"], noisy["layers"][0]["w"])
    with pytest.raises(ValueError, match="n: expected"):
        tr.perturbed_policies(ps, jax.random.PRNGKey(0), 0)


@pytest.mark.slow
def test_evaluate_level_on_pointmass(pm_files, pm_checkpoint, tmp_path):
    """The plumbing: evaluate_checkpoint(level=) gives each policy an interval around its
    simulated value, features of the right shapes, calibration on the given file only; the
    evaluated data as calibration is refused; the CLI prints the interval column."""
    from rl2s_jax.app.evaluation import evaluate_checkpoint, format_report

    r = evaluate_checkpoint(pm_checkpoint, pm_files["test"], level=0.5, n_episodes=4,
                            horizon=20, calibration=[pm_files["train"]])
    t = r["trust"]
    assert t["calibration"]["n"] == 3 and t["calibration"]["sources"] == [pm_files["train"]]
    assert len(r["interval"]) == 3 and len(r["trusted"]) == 3
    for (lo, hi), p, v in zip(r["interval"], t["policies"], r["sim_value"], strict=True):
        assert p["sim_value"] == pytest.approx(v, rel=1e-5, abs=1e-5)  # the report's value
        assert lo <= v <= hi
        assert hi - lo == pytest.approx(2 * t["calibration"]["q"] * p["sigma"], rel=1e-6)
        assert p["support"] > 0 and p["member_sd"] >= 0
    assert {"coverage", "mean_width", "spread_interval", "worst"} <= set(t)
    assert "interval" in format_report(r) and "calibration policies" in format_report(r)
    with pytest.raises(ValueError, match="calibration: .* the evaluated data"):
        evaluate_checkpoint(pm_checkpoint, pm_files["test"], level=0.5, n_episodes=4,
                            horizon=20, calibration=[pm_files["test"]])
    out = tmp_path / "r.json"
    res = subprocess.run([sys.executable, "-m", "rl2s_jax.cli", "evaluate", "--ckpt",
                          pm_checkpoint, "--data", pm_files["test"], "--episodes", "4",
                          "--horizon", "20", "--bootstrap", "0", "--level", "0.5",
                          "--calibration", pm_files["train"], "--json", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "50% interval" in res.stdout
    assert json.loads(out.read_text())["trust"]["level"] == 0.5


@pytest.mark.slow
def test_calibration_data_of_perturbed_policies(pm_files, tmp_path):
    """calibration_data writes a Dataset of perturbed zoo policies with true values whose
    policies policies_for finds through its policy file."""
    from rl2s_jax.app.value_intervals import calibration_data
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.policy.policy import num_policies
    from rl2s_jax.zoo.zoo import policies_for

    src = load_dataset(pm_files["train"]).meta["source"]["zoo"]
    path = calibration_data(src, str(tmp_path / "cal.npz"), n=4, transitions_per_policy=100,
                            value_episodes=4)
    ds = load_dataset(path)
    assert ds.n_policies == 4 and np.all(np.isfinite(ds.value_discounted))
    assert num_policies(policies_for(ds, data_path=path)) == 4
    assert ds.meta["source"]["perturbed_from"]["zoo_ids"] == [0, 1, 2]


def test_level_flag_refused_at_parsing(capsys):
    from rl2s_jax.cli import build_parser

    p = build_parser()
    assert p.parse_args(["evaluate", "--data", "d.npz", "--oracle"]).level == 0.9
    assert p.parse_args(["evaluate", "--data", "d.npz", "--level", "0"]).level == 0.0
    for bad in ("1", "-0.1", "ninety"):
        with pytest.raises(SystemExit):
            p.parse_args(["evaluate", "--data", "d.npz", "--level", bad])
        assert "level: expected a coverage level in [0, 1)" in capsys.readouterr().err


def test_pipeline_report_lines():
    from rl2s_jax.app.report import trust_lines

    f = _features([0.0, 5.0, 9.0], [0.5, 0.5, 10.0], [1.0, 1.0, 1.0])
    cal = tr.calibrate(_features(np.arange(9.0), np.full(9, 0.5)), np.arange(9.0) + 0.2,
                       ["train"] * 9, 0.9)
    t = tr.trust_report(f, cal, ["a", "b", "c"], truth=[0.1, 5.1, 1.0])
    assert t["worst"] == {"name": "c", "flagged": True}  # |9 - 1| is the largest error
    (line, skipped, blank) = trust_lines({"bc": {"trust": t}, "gail": {"trust": {"skipped": "x"}}})
    assert skipped == "- gail: value intervals skipped: x"  # why it has none, said
    assert line.startswith("- bc: 90% value intervals cover 67% of the test policies")
    assert "1 untrusted" in line and "c flagged" in line and "training (optimistic)" in line
    assert blank == "" and trust_lines({"bc": {}}) == []


def test_true_vs_sim_plot_draws_each_interval_and_flag():
    """The report's true-vs-simulated panel: a vertical bar per policy from its interval's ends
    (an unbounded end drawn to the axes' edge), trusted and untrusted policies apart (the
    untrusted in red), the coverage in the title; a report without intervals: plain points."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rl2s_jax.app.report import plot_true_vs_sim, value_interval_bars

    f = _features([0.0, 5.0, 9.0], [0.5, 0.5, 10.0], [1.0, 1.0, 1.0])
    cal = tr.calibrate(_features(np.arange(9.0), np.full(9, 0.5)), np.arange(9.0) + 0.2,
                       ["train"] * 9, 0.9)
    truth = np.array([0.1, 5.1, 1.0])
    t = tr.json_safe(tr.trust_report(f, cal, ["a", "b", "c"], truth=truth))
    t["policies"][2]["interval"] = [None, None]  # as json_safe writes an unbounded one
    r = {"true_value": truth, "sim_value": [0.0, 5.0, 9.0], "metrics": {"kendall_tau": 0.33},
         "trust": t}
    lo, hi, trusted = value_interval_bars(r)
    want = np.array([p["interval"][0] for p in t["policies"][:2]])
    np.testing.assert_allclose(lo[:2], want)
    assert np.isnan(lo[2]) and np.isnan(hi[2]) and trusted.tolist() == [True, True, False]
    fig, ax = plt.subplots()
    plot_true_vs_sim(ax, "bc", r)
    bars = {c.get_label(): c for c in ax.containers}
    assert set(bars) == {"trusted", "untrusted"}
    seg = bars["trusted"].lines[2][0].get_segments()  # the vertical bars: [(x, lo), (x, hi)]
    np.testing.assert_allclose([s_[:, 1] for s_ in seg], np.stack([lo[:2], hi[:2]], 1))
    (red,) = bars["untrusted"].lines[2][0].get_segments()
    y0, y1 = ax.get_ylim()
    assert red[0, 1] == pytest.approx(y0) and red[1, 1] == pytest.approx(y1)
    assert matplotlib.colors.to_hex(bars["untrusted"].lines[0].get_color()) == \
        matplotlib.colors.to_hex("C3")
    assert "intervals cover 67%" in ax.get_title()
    plt.close(fig)
    assert value_interval_bars({**r, "trust": {"skipped": "x"}}) is None
    fig, ax = plt.subplots()
    plot_true_vs_sim(ax, "bc", {**r, "trust": {"skipped": "x"}})
    assert not ax.containers and len(ax.collections) == 1 and "cover" not in ax.get_title()
    plt.close(fig)


def test_plot_intervals_script_draws_a_protocol_lane(tmp_path):
    """experiments/plot_intervals.py: a paper.py lane's trust entry becomes the panel's
    evaluation (intervals and flags by test policy, the lane's tau); a file without the lane
    or without intervals is refused naming the field before anything is drawn."""
    sys.path.insert(0, os.path.dirname(__file__))
    from experiment_scripts import load_script

    mod = load_script("plot_intervals")
    trust = {"level": 0.9, "coverage": 0.5, "sim_value": [1.0, 4.0],
             "interval": [[0.0, 2.0], [None, None]], "trusted": [True, False]}
    result = {"task": "pointmass", "true_value": [1.5, 2.0], "test_policy_names": ["a", "b"],
              "seed_ids": [3, 4], "per_seed": {"rl2s": {"kendall_tau": [0.2, 1.0]}},
              "lanes": {"rl2s/4": {"trust": trust}, "bc/4": {"trust": {"skipped": "why"}}}}
    r = mod.lane_panel(result, "rl2s", 4)
    assert r["metrics"]["kendall_tau"] == 1.0 and r["sim_value"] == [1.0, 4.0]
    assert [p["name"] for p in r["trust"]["policies"]] == ["a", "b"]
    from rl2s_jax.app.report import value_interval_bars
    lo, hi, ok = value_interval_bars(r)
    assert lo[0] == 0.0 and hi[0] == 2.0 and np.isnan(lo[1]) and ok.tolist() == [True, False]
    with pytest.raises(ValueError, match="lanes: no lane 'rl2s/0'"):
        mod.lane_panel(result, "rl2s", 0)
    with pytest.raises(ValueError, match=r"lanes\['bc/4'\].trust: no intervals \(why\)"):
        mod.lane_panel(result, "bc", 4)
    with pytest.raises(ValueError, match="true_value: missing"):
        mod.lane_panel({k: v for k, v in result.items() if k != "true_value"}, "rl2s", 4)
    path = tmp_path / "r.json"
    path.write_text(json.dumps(result))
    out = tmp_path / "fig.png"
    assert mod.main([str(path), "--seed", "4", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000


@pytest.mark.slow
def test_default_calibration_is_the_training_data(pm_files, tmp_path):
    """Without --calibration: the checkpoint's training data (3 policies: too few for a finite
    q at 0.9, so every interval is infinite and untrusted, and the report says optimistic);
    evaluating that training data itself skips the intervals with the reason."""
    import os

    from rl2s_jax.app.evaluation import evaluate_checkpoint
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.train.checkpoint import Checkpointer
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init
    from rl2s_jax.zoo.zoo import policies_for

    ds = load_dataset(pm_files["train"])
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=20)
    for seed in (0, 1):
        ck = Checkpointer(tmp_path / f"s{seed}" / "checkpoints")
        ck.save(init(jax.random.PRNGKey(seed), cfg, make_train_data(ds, policies_for(ds), cfg)),
                {"data": {"obs_size": ds.obs_size, "action_size": ds.action_size,
                          "path": os.path.abspath(pm_files["train"])}})
        ck.close()
    ckpt, ckpt1 = (str(tmp_path / f"s{seed}" / "checkpoints") for seed in (0, 1))
    r = evaluate_checkpoint(ckpt, pm_files["test"], level=0.9, n_episodes=4)
    c = r["trust"]["calibration"]
    assert (c["n"], c["n_train"], c["used"], c["optimistic"]) == (3, 3, "all", True)
    assert c["q"] == math.inf and r["trusted"] == [False] * 3
    assert all(p["why"].startswith("wide") for p in r["trust"]["policies"])
    own = evaluate_checkpoint(ckpt, pm_files["train"], level=0.9, n_episodes=4)
    assert "training data" in own["trust"]["skipped"] and "interval" not in own
    # two seeds: one interval per policy around their mean, with the seeds' spread in sigma
    from rl2s_jax.app.evaluation import evaluate_checkpoints, format_agreement

    two = evaluate_checkpoints([ckpt, ckpt1], pm_files["test"], level=0.5, n_episodes=4,
                               calibration=[pm_files["train"]])
    sims = np.array([c["sim_value"] for c in two["checkpoints"]])
    for p, v, sd in zip(two["trust"]["policies"], sims.mean(0), sims.std(0, ddof=1),
                        strict=True):
        assert p["sim_value"] == pytest.approx(v, rel=1e-5) and p["seed_sd"] == pytest.approx(sd)
    assert "50% interval" in format_agreement(two)


def test_evaluate_says_why_a_value_has_no_interval(pm_files, pm_checkpoint, capsys):
    """Issue 64's audit: `rl2s evaluate --oracle` and `--level 0` print values without an
    interval, each with the reason (NO_INTERVAL), in the printed report and the JSON."""
    from rl2s_jax.app.evaluation import run_evaluate
    from rl2s_jax.app.specs import EvaluateSpec
    from rl2s_jax.app.value_intervals import NO_INTERVAL

    kw = dict(data=pm_files["test"], episodes=2, horizon=10, bootstrap=0)
    assert run_evaluate(EvaluateSpec(oracle=True, **kw)) == 0
    assert f"value intervals skipped: {NO_INTERVAL['oracle']}" in capsys.readouterr().out
    assert run_evaluate(EvaluateSpec(ckpt=[pm_checkpoint], level=0, **kw)) == 0
    assert f"value intervals skipped: {NO_INTERVAL['level_0']}" in capsys.readouterr().out
