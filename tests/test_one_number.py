"""One number per quantity (issue 65, item 2): one evaluation setting (evaluate/setting.py) for
`rl2s train`'s test numbers, `rl2s evaluate` and the pipeline's evaluation, so one checkpoint
gets identical numbers through each; the oracle's default horizon is the simulator's; the
progress bar shows the evaluation of the step it reports, not the one before."""
import dataclasses
import json
import types

import numpy as np
import pytest

from rl2s_jax.evaluate.setting import EVAL_EPISODES, EvalSetting, profile_horizon


def test_the_setting_checks_its_fields_and_fills_its_horizon_in_one_place():
    s = EvalSetting()
    assert (s.episodes, s.horizon, s.seed, s.truth) == (EVAL_EPISODES, None, 0, "auto")
    for bad, field in ((dict(episodes=0), "episodes"), (dict(horizon=-1), "horizon"),
                       (dict(seed=1.5), "seed"), (dict(truth="true"), "truth")):
        with pytest.raises(ValueError, match=f"^{field}: expected"):
            EvalSetting(**bad)
    assert EvalSetting.from_flags(None, None, None, None) == s
    assert EvalSetting.from_flags(3, None, 2, "logged") == EvalSetting(3, None, 2, "logged")
    # given > the checkpoint's vd_horizon > the profile's; each at most the data's episodes
    assert s.resolve(1000, 200).horizon == 200
    assert s.resolve(50, 200).horizon == 50
    assert s.resolve(50, 200).horizon_source.startswith("the data's episode_length")
    assert s.resolve(1000, None, "cpu").horizon == profile_horizon("cpu", 1000) == 100
    assert s.resolve(1000, None, "gpu").horizon == profile_horizon("gpu", 1000) == 1000
    assert EvalSetting(horizon=7).resolve(1000, 200).horizon == 7
    line = s.resolve(1000, 200).describe("measured")
    assert line.startswith(f"{EVAL_EPISODES} episodes x 200 steps") and "seed 0" in line
    assert "true values: auto (measured)" in line


def test_the_training_profile_takes_its_horizon_from_the_setting_module(pm_files):
    """The oracle's default horizon and a trained checkpoint's vd_horizon are one rule
    (``profile_horizon``), so `--oracle` and a simulator trained here score one horizon."""
    from rl2s_jax.app.training import make_config
    from rl2s_jax.data.dataset import load_dataset

    ds = load_dataset(pm_files["test"])
    ds.meta["episode_length"] = 300
    for profile in ("cpu", "gpu"):
        cfg = make_config(ds, "bc", profile)
        assert cfg.vd.horizon == profile_horizon(profile, 300)
        assert EvalSetting().resolve(300, None, profile).horizon == cfg.vd.horizon


def test_which_true_value_is_chosen_and_refused_before_any_work(pm_files):
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.data.values import data_values, true_values, truth_used

    ds = load_dataset(pm_files["test"])
    ep, gamma = ds.meta["episode_length"], float(ds.meta["gamma"])
    assert truth_used(ds, ep, gamma) == "measured"
    assert truth_used(ds, ep - 1, gamma) == "logged"  # the measured values are whole episodes
    np.testing.assert_array_equal(true_values(ds, ep, gamma, truth="measured"),
                                  np.asarray(ds.value_discounted, np.float32))
    ended = np.asarray(ds.done) | np.asarray(ds.truncated)
    logged, _ = data_values(np.asarray(ds.reward), ended, np.asarray(ds.policy_id),
                            np.asarray(ds.episode_id), np.asarray(ds.t), ds.n_policies,
                            horizon=ep, gamma=gamma)
    np.testing.assert_allclose(true_values(ds, ep, gamma, truth="logged"), logged, rtol=1e-6)
    with pytest.raises(ValueError, match="^truth: 'measured' values are of whole episodes"):
        truth_used(ds, ep - 1, gamma, "measured")


def test_the_progress_bar_shows_the_evaluation_of_its_step(monkeypatch):
    """fit's last progress-bar numbers are the last evaluation's (they lagged one behind)."""
    from rl2s_jax.train import loop

    posted = []

    class Bar:
        def __init__(self, *a, **k):
            pass

        def update(self, n):
            pass

        def set_postfix(self, d, refresh=True):
            posted.append(dict(d))

        def close(self):
            pass

    def chunk(state, data, n_steps, phase):  # a chunk of n_steps without any training
        m = {"finite": np.ones(n_steps, bool), "avd_train": np.ones(n_steps),
             "mvd_train": np.ones(n_steps), "vd_refreshed": np.zeros(n_steps, bool)}
        return dataclasses.replace(state, step=state.step + n_steps), m

    @dataclasses.dataclass
    class State:
        step: int
        vd: np.ndarray
        config: types.SimpleNamespace

    monkeypatch.setattr(loop, "tqdm", Bar)
    monkeypatch.setattr(loop, "_train_chunk", chunk)
    cfg = types.SimpleNamespace(method="bc", phase=lambda step: "main")  # one phase
    state = State(0, np.zeros(2), cfg)
    loop.fit(state, None, 6, chunk=2, eval_every=2,
             on_eval=lambda s: {"avd_test": float(s.step)})
    assert [p["avd_test"] for p in posted] == ["2", "4", "6"]


@pytest.mark.slow
def test_one_checkpoint_gets_one_number_through_every_front_end(pm_files, tmp_path, capsys):
    """`rl2s train`'s summary and eval.jsonl, `rl2s evaluate` and the pipeline's evaluation of
    one run's final checkpoint: identical numbers, each stored with its setting; a run whose
    last step is no multiple of --eval-every is evaluated at its last step too."""
    from rl2s_jax import cli
    from rl2s_jax.app.pipeline import evaluate_run

    run = tmp_path / "run"
    train = ["train", "--data", pm_files["train"], "--method", "bc", "--steps", "3", "--out",
             str(run), "--profile", "cpu", "--quiet", "--eval-data", pm_files["test"],
             "--eval-every", "2", "--set", "vd_horizon=30", "--set", "updates_per_step=2",
             "--set", "gen_hidden=[32]"]
    assert cli.main(train) == 0
    printed = capsys.readouterr().out
    summary = json.loads((run / "summary.json").read_text())
    rows = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
    assert summary["step_test"] == rows[-1]["step"] == 3 and [r["step"] for r in rows] == [2, 3]
    setting = EvalSetting(horizon=30, horizon_source="the checkpoint's vd_horizon")
    assert summary["setting_test"] == rows[-1]["setting"] == setting.to_dict()
    assert f"{EVAL_EPISODES} episodes x 30 steps" in printed and "seed 0" in printed

    out = tmp_path / "eval.json"
    assert cli.main(["evaluate", "--ckpt", str(run / "checkpoints"), "--data",
                     pm_files["test"], "--bootstrap", "0", "--json", str(out)]) == 0
    assert "seed 0, true values: logged" in capsys.readouterr().out
    evaluated = json.loads(out.read_text())
    piped = evaluate_run(str(run), pm_files["test"], EvalSetting())
    for r in (evaluated, piped):
        assert r["setting"] == setting.to_dict() and r["step"] == 3
        assert r["metrics"] == {k: summary[f"{k}_test"] for k in r["metrics"]}
        assert r["vd"] == rows[-1]["vd"]
    assert piped["sim_value"] == evaluated["sim_value"]
    # a rerun of the finished run scores its last step anew: the same numbers, no second row
    assert cli.main(train) == 0
    again = json.loads((run / "summary.json").read_text())
    assert [json.loads(line)["step"] for line in
            (run / "eval.jsonl").read_text().splitlines()] == [2, 3]
    assert again["avd_test"] == summary["avd_test"] and again["step_test"] == 3


def test_the_oracle_scores_the_horizon_a_simulator_trained_here_does(pm_files, monkeypatch):
    """`rl2s evaluate --oracle` on 300-step episodes: the cpu profile's 100 steps, the
    vd_horizon `rl2s train` gives a checkpoint of this data on this backend (it took the
    data's 300 before)."""
    from rl2s_jax.app import evaluation as ev
    from rl2s_jax.app.training import make_config
    from rl2s_jax.data.dataset import load_dataset

    ds = load_dataset(pm_files["test"])
    ds = ds.replace(meta={**ds.meta, "episode_length": 300})
    seen = {}

    def oracle(task, data, policies, *, key, n_episodes, horizon, n_boot, truth):
        seen.update(horizon=horizon, episodes=n_episodes, truth=truth)
        return {}
    monkeypatch.setattr(ev, "load_dataset", lambda path: ds)
    monkeypatch.setattr(ev, "evaluate_oracle", oracle)
    r = ev.evaluate_oracle_data(pm_files["test"])
    assert seen == {"horizon": make_config(ds, "bc", "cpu").vd.horizon, "episodes": 16,
                    "truth": "auto"} and seen["horizon"] == 100
    assert r["setting"]["horizon"] == 100 and r["horizon_source"].startswith("the cpu profile")
