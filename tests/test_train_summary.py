"""One meaning per number in `rl2s train` / `rl2s inspect` (issue 38, item 3): a run that ends
inside pre-training says so; test-data results reach summary.json and the table with how they
were measured; inspect tells the logged return from the true discounted value."""
import json

from rl2s_jax.app.specs import TrainSpec
from rl2s_jax.app.training import format_summary, run_training
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.data.summary import dataset_summary
from rl2s_jax.evaluate.setting import EvalSetting

SMALL = {"vd_horizon": 50, "vd_episodes": 2, "updates_per_step": 2, "gen_hidden": [32],
         "disc_hidden": [32], "hazard_steps": 0}


def test_a_run_inside_pretraining_warns_and_says_how_far(pm_files, tmp_path):
    logs = []
    s = run_training(TrainSpec(pm_files["train"], 3, str(tmp_path / "run"), "rl2s",
                               profile="cpu", set=SMALL, quiet=True), log=logs.append)
    warning = [line for line in logs if "warning" in line]
    assert warning and "--steps 3" in warning[0] and "98 more step(s)" in warning[0], logs
    assert s["pretrain_steps_left"] == 98
    assert "still pre-training" in format_summary(s)
    with open(tmp_path / "run" / "summary.json") as f:
        saved = json.load(f)
    assert saved["vd_measured_by"]["horizon"] == 50 and saved["vd_measured_by"]["episodes"] == 2
    assert saved["machine"]["backend"] == "cpu" and "cpu_isa" in saved["machine"]


def test_eval_data_results_reach_the_summary_with_their_settings(pm_files, tmp_path, capsys):
    logs = []
    # with the progress bar: the test results join the training VD there (make hopper crashed
    # when both named a key "avd"); chunks of 2 put an evaluation before the last bar update
    s = run_training(TrainSpec(pm_files["train"], 4, str(tmp_path / "run"), "bc",
                               profile="cpu", set=SMALL, chunk=2, eval_data=pm_files["test"],
                               eval_every=2, eval_episodes=3), log=logs.append)
    assert "avd_test=" in capsys.readouterr().err
    assert not [line for line in logs if "warning" in line]  # bc: no pre-training
    assert s["pretrain_steps_left"] == 0 and s["step_test"] == 4
    for k in ("avd_test", "mvd_test", "kendall_tau_test"):
        assert isinstance(s[k], float), k
    with open(tmp_path / "run" / "eval.jsonl") as f:
        last = [json.loads(line) for line in f][-1]
    assert last["step"] == 4 and last["avd"] == s["avd_test"]
    assert s["measured_by_test"] == {
        "source": "simulated vs the eval data's measured true values", "episodes": 3,
        "horizon": 50, "gamma": s["config"]["gamma"], "seed": 0, "truth": "auto",
        "true_value_source": "measured"}
    assert s["setting_test"] == last["setting"] == EvalSetting(
        episodes=3, horizon=50, horizon_source="the checkpoint's vd_horizon").to_dict()
    table = format_summary(s)
    assert "test policies" in table and "3 episodes x 50 steps" in table
    assert "seed 0, true values: measured" in table
    assert "why no interval: sim value: of the training policies" in table  # issue 64


def test_inspect_names_return_and_discounted_value_apart(pm_files):
    text = dataset_summary(load_dataset(pm_files["test"]))
    assert "logged return" in text and "true disc. value" in text and "true return" in text
    assert "undiscounted" in text and "discounted at gamma" in text
    assert "measured on 8 real episodes per policy" in text


def test_worst_vd_jumps_against_a_loop():
    import numpy as np

    from rl2s_jax.train.loop import worst_vd_jumps
    mvd = np.array([5.0, 5.0, 9.0, 9.0, 30.0, 30.0, np.nan, 70.0])
    refreshed = np.array([True, False, True, False, True, False, True, True])
    jumps, last = worst_vd_jumps(mvd, refreshed, previous=2.0)
    want, prev = [], 2.0  # the plain loop: each measurement against the last finite one
    for i in range(len(mvd)):
        if refreshed[i] and np.isfinite(mvd[i]):
            if mvd[i] > 2.0 * prev:
                want.append((i, prev, mvd[i]))
            prev = mvd[i]
    assert jumps == want == [(0, 2.0, 5.0), (4, 9.0, 30.0), (7, 30.0, 70.0)]
    assert last == 70.0
    assert worst_vd_jumps(mvd, refreshed, None, factor=10.0) == ([], 70.0)


def test_fit_warns_when_the_worst_training_vd_jumps(pm_files, monkeypatch):
    """fit names the step and the rise through on_warning (the chunk's metrics are faked: a
    real jump needs a long run)."""
    import jax
    import numpy as np

    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.train import loop
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init
    from rl2s_jax.zoo.zoo import policies_for

    ds = load_dataset(pm_files["train"])
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=20, vd_episodes=2)
    data = make_train_data(ds, policies_for(ds), cfg)
    state = init(jax.random.PRNGKey(0), cfg, data)
    first = float(np.max(np.asarray(state.vd)))
    series = iter([first * 1.5, first * 4.0])  # one mild rise, then a 2.7x jump

    def fake_chunk(st, d, n_steps, phase):
        mvd = np.full(n_steps, next(series))
        refreshed = np.zeros(n_steps, bool)
        refreshed[-1] = True
        return st.replace(step=st.step + n_steps), {
            "finite": np.ones(n_steps, bool), "mvd_train": mvd, "avd_train": mvd,
            "vd_refreshed": refreshed}

    monkeypatch.setattr(loop, "_train_chunk", fake_chunk)
    heard = []
    loop.fit(state, data, 10, chunk=5, progress=False, on_warning=heard.append)
    assert len(heard) == 1 and "step 10" in heard[0] and "2.7x" in heard[0], heard
