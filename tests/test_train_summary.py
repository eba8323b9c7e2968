"""One meaning per number in `rl2s train` / `rl2s inspect` (issue 38, item 3): a run that ends
inside pre-training says so; test-data results reach summary.json and the table with how they
were measured; inspect tells the logged return from the true discounted value."""
import json

from rl2s_jax.app.train import format_summary, run_training
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.data.summary import dataset_summary

SMALL = {"vd_horizon": 50, "vd_episodes": 2, "updates_per_step": 2, "gen_hidden": [32],
         "disc_hidden": [32], "hazard_steps": 0}


def test_a_run_inside_pretraining_warns_and_says_how_far(pm_files, tmp_path):
    logs = []
    s = run_training(pm_files["train"], "rl2s", 3, str(tmp_path / "run"), profile="cpu",
                     overrides=SMALL, progress=False, log=logs.append)
    warning = [line for line in logs if "warning" in line]
    assert warning and "--steps 3" in warning[0] and "98 more step(s)" in warning[0], logs
    assert s["pretrain_steps_left"] == 98
    assert "still pre-training" in format_summary(s)
    with open(tmp_path / "run" / "summary.json") as f:
        saved = json.load(f)
    assert saved["vd_measured_by"]["horizon"] == 50 and saved["vd_measured_by"]["episodes"] == 2


def test_eval_data_results_reach_the_summary_with_their_settings(pm_files, tmp_path):
    logs = []
    s = run_training(pm_files["train"], "bc", 4, str(tmp_path / "run"), profile="cpu",
                     overrides=SMALL, progress=False, log=logs.append,
                     eval_data=pm_files["test"], eval_every=2, eval_episodes=3)
    assert not [line for line in logs if "warning" in line]  # bc: no pre-training
    assert s["pretrain_steps_left"] == 0 and s["step_test"] == 4
    for k in ("avd_test", "mvd_test", "kendall_tau_test"):
        assert isinstance(s[k], float), k
    with open(tmp_path / "run" / "eval.jsonl") as f:
        last = [json.loads(line) for line in f][-1]
    assert last["step"] == 4 and last["avd"] == s["avd_test"]
    assert s["measured_by_test"] == {"source": "simulated vs the eval data's true values",
                                     "episodes": 3, "horizon": 50, "gamma": s["config"]["gamma"]}
    table = format_summary(s)
    assert "test policies" in table and "3 episodes x 50 steps" in table


def test_inspect_names_return_and_discounted_value_apart(pm_files):
    text = dataset_summary(load_dataset(pm_files["test"]))
    assert "logged return" in text and "true disc. value" in text and "true return" in text
    assert "undiscounted" in text and "discounted at gamma" in text
    assert "measured on 8 real episodes per policy" in text
