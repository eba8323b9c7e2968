"""Diagnosis end to end: hide an effect in the data, require diagnose to name it with its
details, and require the extension it picks to lower the held-out error on every seed.
Plus the statistics underneath (cross-fitting, the episode estimate) against plain NumPy
references (the sign-flip and rank-sum tests: tests/test_stats.py)."""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

from rl2s_jax.app.diagnosis import diagnose
from rl2s_jax.app.training import parse_overrides
from rl2s_jax.data.episodes import from_dataset, half_split, pool_episodes, split_episodes
from rl2s_jax.diagnose.causes import (
    CAUSES,
    MEAN_CAUSES,
    crossfit_ridge,
    diagnose_causes,
    episode_estimate,
    rivals,
    variance_from_log,
)
from rl2s_jax.diagnose.extension import extension_for, train_command, train_set
from rl2s_jax.diagnose.model import ModelSpec
from rl2s_jax.diagnose.planted import make_planted
from rl2s_jax.train.config import TrainConfig

# Small enough for CI, large enough that every planted effect is found with a wide margin.
N_EPISODES, MODEL_STEPS, SEEDS = 160, 1000, (0, 1, 2)


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    cache = {}

    def run(effect):
        if effect not in cache:
            out = str(tmp_path_factory.mktemp(effect))
            ds = make_planted(effect, n_episodes=N_EPISODES, seed=1)
            cache[effect] = (diagnose(ds, out, seeds=SEEDS, log=lambda s: None,
                                      base_spec=ModelSpec(steps=MODEL_STEPS)), out, ds)
        return cache[effect]
    return run


def _gain_on_every_seed(report, metric="heldout_nll"):
    diff = report["gain"]["difference"][metric]["per_seed"]
    return len(diff) == len(SEEDS) and all(d < 0 for d in diff)


def test_clean_data_reports_none(reports):
    report, out, _ = reports("clean")
    assert report["verdict"]["trust"] == "base"
    assert report["verdict"]["wrong"].startswith("No cause explains")
    assert report["top_cause"] == "none", [(c["name"], c["score"], c["p_value"])
                                           for c in report["causes"]]
    assert report["extension"]["changes"] == [] and report["gain"]["after"] is None
    assert report["causes"][0]["name"] == "none"


def test_finds_actuation_delay_with_lag_and_actuator(reports):
    report, _, ds = reports("delay")
    truth = ds.meta["source"]["planted"]
    assert report["top_cause"] == "actuation_delay"
    top = report["causes"][0]
    assert top["details"]["lag"] == truth["lag"] == 2
    assert top["details"]["actuators"] == truth["actuators"] == [0]
    assert top["p_value"] < 1e-4
    assert report["extension"]["extended"]["action_history"] >= 2
    assert _gain_on_every_seed(report) and _gain_on_every_seed(report, "heldout_mse")


def test_finds_hidden_episode_parameter(reports):
    report, _, _ = reports("episode_param")
    assert report["top_cause"] == "hidden_episode_parameter"
    assert set(report["causes"][0]["details"]["dims"]) <= {0, 1}  # body 1 only
    assert report["extension"]["extended"]["context_dim"] > 0
    assert _gain_on_every_seed(report)


def test_finds_noise_and_its_dims(reports):
    report, _, ds = reports("noise")
    truth = ds.meta["source"]["planted"]["dims"]
    assert report["top_cause"] == "stochastic_noise"
    dims = report["causes"][0]["details"]["dims"]
    assert set(truth) <= set(dims) <= {2, 3}  # v2 and, through p' = p + dt v', p2
    assert report["extension"]["extended"]["noise"] == "state"
    assert _gain_on_every_seed(report)


def test_finds_unobserved_state(reports):
    report, _, _ = reports("unobserved")
    assert report["top_cause"] == "unobserved_state"
    assert report["extension"]["extended"]["obs_history"] >= 2
    assert _gain_on_every_seed(report)


def test_finds_drift_over_recording_order(reports):
    report, _, _ = reports("drift")
    assert report["top_cause"] == "time_drift"
    assert report["causes"][0]["details"]["over"] == "episode_order"
    assert "order" in report["extension"]["extended"]["time_inputs"]
    assert _gain_on_every_seed(report)


def test_report_files_and_schema(reports):
    report, out, _ = reports("delay")
    with open(os.path.join(out, "report.json")) as f:
        saved = json.load(f)
    for key in ("gaps", "causes", "top_cause", "extension", "gain"):
        assert key in saved
    for c in saved["causes"]:
        assert {"name", "score", "p_value", "details"} <= set(c)
    for side in ("before", "after"):
        assert {"heldout_nll", "heldout_mse"} <= set(saved["gain"][side])
    assert {"lag", "actuators"} <= set(saved["causes"][0]["details"])
    md = open(os.path.join(out, "report.md")).read()
    assert "actuation_delay" in md and "| heldout_nll |" in md
    # the report opens with its verdict: what is wrong, why, the gain, whether to trust it
    assert saved["verdict"]["trust"] == "extended"
    first = md.split("\n")[2]
    assert first.startswith("**The simulator misses an actuation delay")
    assert "lag 2 steps on actuator(s) [0]" in first and "lower on 3 of 3 seeds" in first
    for png in saved["plots"]:
        assert os.path.getsize(os.path.join(out, png)) > 1000


# ------------------------------------------------------------------ the statistics underneath


def test_crossfit_ridge_matches_numpy_solve():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(200, 5)), rng.normal(size=(200, 2))
    folds = np.arange(200) % 4
    pred = crossfit_ridge(x, y, folds, {"m": np.array([0, 2, 3])}, ridge=0.01)["m"]
    tr, te = folds != 1, folds == 1
    xs = x[:, [0, 2, 3]]
    mu, sd = xs[tr].mean(0), xs[tr].std(0)
    z = (xs - mu) / sd
    w = np.linalg.solve(z[tr].T @ z[tr] + 0.01 * tr.sum() * np.eye(3),
                        z[tr].T @ (y[tr] - y[tr].mean(0)))
    np.testing.assert_allclose(pred[te], y[tr].mean(0) + z[te] @ w, rtol=1e-10)


def test_episode_estimate_never_sees_its_own_half():
    ds = make_planted("episode_param", n_episodes=12, seed=3)
    eps = from_dataset(ds)
    rows = np.arange(eps.n)
    rng = np.random.default_rng(0)
    target, x = rng.normal(size=(eps.n, 4)), eps.action
    before = episode_estimate(eps, rows, target, x)
    changed = target.copy()
    first = half_split(eps) == 0
    changed[first] += 5.0  # only first-half rows change: their own estimates must not
    after = episode_estimate(eps, rows, changed, x)
    np.testing.assert_allclose(after[first], before[first])
    assert not np.allclose(after[~first], before[~first])


def test_split_episodes_leaves_short_episodes_out_of_both_sides():
    eps = from_dataset(make_planted("clean", n_episodes=12, episode_length=5, seed=0))
    length = eps.length.copy()
    length[[0, 7]] = 1  # as if two recordings were cut right after a reset
    short = dataclasses.replace(eps, length=length)
    fit, held = split_episodes(short, 0.3, 0, min_length=2)
    assert not {0, 7} & (set(fit.tolist()) | set(held.tolist()))
    assert sorted(np.r_[fit, held].tolist()) == [e for e in range(12) if e not in (0, 7)]
    fit1, held1 = split_episodes(short, 0.3, 0)  # default: every episode is used
    assert len(fit1) + len(held1) == 12


def test_test_causes_rejects_bad_shapes():
    ds = make_planted("clean", n_episodes=8, seed=0)
    eps = from_dataset(ds)
    fit, held = split_episodes(eps, 0.5, 0)
    rows = eps.rows(held)
    with pytest.raises(ValueError, match="resid, std"):
        diagnose_causes(eps, rows, np.zeros((len(rows), 3)), np.ones((len(rows), 3)),
                    eps.rows(fit))
    with pytest.raises(ValueError, match="finite"):
        bad = np.zeros((len(rows), 4))
        bad[0, 0] = np.nan
        diagnose_causes(eps, rows, bad, np.ones_like(bad), eps.rows(fit))


def test_extension_for_maps_every_cause():
    def causes(name, details, score=1.0):
        return {"top_cause": name, "causes": [{"name": name, "score": score, "significant": True,
                                               "details": details}]}
    base = ModelSpec()
    assert extension_for(causes("actuation_delay", {"lag": 3}), base)[0].action_history == 3
    assert extension_for(causes("unobserved_state", {"lags": [1, 4]}), base)[0].obs_history == 4
    ctx = extension_for(causes("hidden_episode_parameter", {}), base)[0]
    assert (ctx.context_dim, ctx.obs_history, ctx.action_history, ctx.noise) == (
        2, 4, 4, "state")
    noisy = extension_for(causes("stochastic_noise", {}), base)[0]
    assert noisy.noise == "state" and noisy.nll_beta == 0.5
    assert extension_for(causes("time_drift", {"over": "step"}), base)[0].time_inputs == ("step",)
    # weighting the worst policies is how `rl2s train --method rl2s-bc` trains, not a model
    # input: recorded, the fitted spec unchanged
    assert extension_for(causes("coverage_gap", {}), base) == (
        base, [{"cause": "coverage_gap", "change": {"policy_cvar_eps": 0.25}}])
    assert extension_for({"top_cause": "none", "causes": []}, base) == (base, [])


def test_train_set_builds_what_the_trained_simulator_lacks():
    """The extension as `rl2s train --set` items: the history inputs as TrainConfig fields,
    nothing the trained simulator already has (its noise head and beta 1), nll_beta raised
    only over a config below diagnosis's 0.5, the context with the past it is inferred from,
    and both time inputs (the recording order too: rollouts run at its end). Every item parses
    through --set into a valid TrainConfig."""
    change = lambda name, **c: {"cause": name, "change": c}
    items, skipped, already = train_set([
        change("actuation_delay", action_history=2),
        change("stochastic_noise", noise="state", nll_beta=0.5),
        change("hidden_episode_parameter", context_dim=2),
        change("time_drift", time_inputs=["order", "step"])])
    assert items == ["dynamics.action_history=4", "dynamics.context_dim=2",
                     "dynamics.obs_history=4", 'dynamics.time_inputs=["order", "step"]'], items
    assert already == ['dynamics.noise="state"', "nll_beta=1.0"], already
    assert skipped == []
    cfg = TrainConfig().override(parse_overrides(items), what="set").validate()
    d = cfg.dynamics
    assert (d.action_history, d.context_dim, d.time_inputs) == (4, 2, ("order", "step"))
    items, skipped, _ = train_set([change("time_drift", time_inputs=["order"])])
    assert (items, skipped) == (['dynamics.time_inputs=["order"]'], []), items
    _, _, already = train_set([change("time_drift", time_inputs=["order"])],
                              TrainConfig().override({"dynamics.time_inputs": ("step", "order")}))
    assert already == ['dynamics.time_inputs=["order", "step"]'], already
    legacy = TrainConfig().override({"nll_beta": 0.0, "dynamics.noise": "global",
                                     "dynamics.action_history": 3})
    items, _, _ = train_set([change("stochastic_noise", noise="state", nll_beta=0.5),
                             change("actuation_delay", action_history=2)], legacy)
    assert items == ['dynamics.noise="state"', "nll_beta=0.5"], items  # history 3 >= 2
    report = {"extension": {"train_set": ["dynamics.action_history=2"], "method": "bc"}}
    assert train_command(report, "d.npz", "out", steps=7) == (
        "rl2s train --data d.npz --method bc --steps 7 --out out --set "
        "dynamics.action_history=2")
    assert train_command({"extension": {"train_set": []}}, "d.npz", "out") is None


def test_extension_joins_mechanisms_before_symptoms():
    # A significant noise score under a delay is a symptom of the delay (the linear mean model
    # left part of it): it neither joins the extension nor competes for the top.
    def causes(*entries):
        return {"top_cause": entries[0][0], "causes": [
            {"name": n, "score": sc, "significant": True,
             "details": {"lag": 2} if n == "actuation_delay" else {}} for n, sc in entries]}
    base = ModelSpec()
    spec, changes = extension_for(causes(("actuation_delay", 1.0), ("stochastic_noise", 0.9)),
                                  base)
    assert spec.action_history == 2 and spec.noise == base.noise
    assert [c["cause"] for c in changes] == ["actuation_delay"]
    # Under a symptom at the top, a mechanism scoring enough joins.
    spec, changes = extension_for(causes(("stochastic_noise", 1.0), ("actuation_delay", 0.5)),
                                  base)
    assert spec.noise == "state" and spec.action_history == 2
    assert rivals("actuation_delay") == tuple(MEAN_CAUSES) and rivals("coverage_gap") == CAUSES


def test_cli_diagnose_bad_input_names_the_field(tmp_path, capsys):
    from rl2s_jax.cli import main
    from rl2s_jax.data.dataset import save_dataset

    path = str(tmp_path / "d.npz")
    save_dataset(path, make_planted("clean", n_episodes=8, seed=0))
    assert main(["diagnose", "--data", path, "--out", str(tmp_path / "o"),
                 "--heldout", "1.5"]) == 2
    assert "heldout" in capsys.readouterr().err
    assert main(["diagnose", "--data", path, "--out", str(tmp_path / "o"),
                 "--ckpt", str(tmp_path / "missing")]) == 2
    assert "ckpt" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "o")


# ------------------------------------------------------------------ differential mode


def _quick(target, reference, seed_ref=2):
    ds = make_planted(target, n_episodes=N_EPISODES, seed=1)
    ref = None if reference is None else make_planted(reference, n_episodes=N_EPISODES,
                                                      seed=seed_ref)
    return diagnose(ds, None, seeds=(0,), base_spec=ModelSpec(steps=MODEL_STEPS),
                    reference=ref, plots=False, log=lambda s: None)


def test_reference_separates_a_new_effect_from_one_both_datasets_show():
    """Delay in both datasets, noise only in the target: alone, the delay wins; against
    the reference, only the noise (on v2) is named."""
    plain = _quick("delay+noise", None)
    assert plain["top_cause"] == "actuation_delay"
    diff = _quick("delay+noise", "delay")
    assert diff["top_cause"] == "stochastic_noise"
    top = diff["causes"][0]
    assert 3 in top["details"]["dims"] and set(top["details"]["dims"]) <= {2, 3}
    delay = next(c for c in diff["causes"] if c["name"] == "actuation_delay")
    assert not delay["significant"] and delay["score"] < 0.05
    assert diff["reference"]["episodes"] == N_EPISODES
    assert diff["extension"]["extended"]["noise"] == "state"
    assert "beyond what the reference data shows" in diff["verdict"]["wrong"]


def test_reference_showing_the_same_effect_leaves_none():
    report = _quick("delay", "delay")
    assert report["top_cause"] == "none", [(c["name"], c["score"], c["p_value"])
                                           for c in report["causes"]]
    assert report["cause_settings"]["differential"]


def test_clean_against_clean_leaves_none():
    """Two recordings of one system with other seeds: nothing is new in the target."""
    report = _quick("clean", "clean")
    assert report["top_cause"] == "none", [(c["name"], c["score"], c["p_value"])
                                           for c in report["causes"]]


def test_variance_from_log_keeps_one_extreme_prediction_from_flooring_the_rest():
    """A log-variance prediction far beyond any error seen (one extreme input row) is
    clipped to the observed range, so the other rows keep their relative sizes."""
    rng = np.random.default_rng(0)
    u2 = rng.chisquare(1, (200, 2)) * np.array([1.0, 4.0])
    log_u2 = np.log(u2)
    pred = np.tile(np.log([1.0, 4.0]) - 1.27, (200, 1))
    pred[7] = 60.0  # the extrapolated row
    v = variance_from_log(pred, log_u2, u2)
    np.testing.assert_allclose(v.mean(0), u2.mean(0))
    rest = np.delete(v, 7, axis=0)
    expect = np.exp(np.clip(60.0, log_u2.min(0), log_u2.max(0)) - np.log([1.0, 4.0]) + 1.27)
    # every other row gets the same share of the per-dim mean, as in plain NumPy
    np.testing.assert_allclose(rest, np.broadcast_to(u2.mean(0) * 200 / (199 + expect),
                                                     rest.shape), rtol=1e-10)
    assert (rest > 0.1 * u2.mean(0)).all()


def test_pool_episodes_renumbers_the_reference_and_checks_sizes():
    a = from_dataset(make_planted("clean", n_episodes=6, seed=0))
    b = from_dataset(make_planted("delay", n_episodes=4, seed=1))
    pooled, in_target = pool_episodes(a, b)
    assert pooled.n == a.n + b.n and in_target.sum() == a.n
    assert pooled.n_episodes == 10 and pooled.n_policies == a.n_policies + b.n_policies
    np.testing.assert_array_equal(pooled.episode[~in_target], b.episode + 6)
    np.testing.assert_array_equal(pooled.rows(np.arange(6, 10)), np.flatnonzero(~in_target))
    np.testing.assert_array_equal(pooled.order[~in_target], b.order)
    small = dataclasses.replace(b, obs=b.obs[:, :3], next_obs=b.next_obs[:, :3])
    with pytest.raises(ValueError, match="reference: its obs size 3"):
        pool_episodes(a, small)


def test_cli_diagnose_reference_of_another_system_is_refused(tmp_path, capsys):
    from rl2s_jax.cli import main
    from rl2s_jax.data.dataset import Dataset, save_dataset

    data, ref = str(tmp_path / "d.npz"), str(tmp_path / "r.npz")
    ds = make_planted("clean", n_episodes=8, seed=0)
    save_dataset(data, ds)
    arrays = {k: np.asarray(getattr(ds, k)) for k in ("obs", "action", "next_obs", "reward",
                                                      "done", "truncated", "policy_id",
                                                      "episode_id", "t")}
    arrays["action"] = arrays["action"][:, :1]
    save_dataset(ref, Dataset.from_arrays(arrays, {**ds.meta, "action_size": 1}))
    assert main(["diagnose", "--data", data, "--out", str(tmp_path / "o"),
                 "--reference", ref]) == 2
    assert "reference: its action_size 1" in capsys.readouterr().err
    assert main(["diagnose", "--data", data, "--out", str(tmp_path / "o"),
                 "--reference", str(tmp_path / "missing.npz")]) == 2
    assert "reference" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "o")


def test_printed_train_command_runs_as_printed(pm_files, tmp_path):
    """The `rl2s train` command diagnosis prints (extension.train_command) runs through the
    CLI exactly as printed, and builds the extension it names (here a 2-step action history)."""
    import shlex

    from rl2s_jax.cli import main
    from rl2s_jax.train.checkpoint import load_meta

    report = {"extension": {"train_set": ['time_inputs=["step"]', "action_history=2"],
                            "method": "bc"}}
    out = str(tmp_path / "extended dir")  # a space: the printed paths must be quoted
    command = train_command(report, pm_files["train"], out, steps=2)
    argv = shlex.split(command)
    assert argv[0] == "rl2s", command
    assert main(argv[1:]) == 0
    cfg = load_meta(os.path.join(out, "checkpoints"))["config"]
    assert (cfg["dynamics"]["action_history"], list(cfg["dynamics"]["time_inputs"])) == (
        2, ["step"]), cfg
