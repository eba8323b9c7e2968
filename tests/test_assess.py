"""`rl2s evaluate` (fresh process) and test-policy evaluation during `rl2s train`."""
import json
import subprocess
import sys

import numpy as np
import pytest

from rl2s_jax.cli import main
from rl2s_jax.evaluate.metrics import kendall_tau


def test_train_with_test_evaluation_then_evaluate_in_fresh_process(pm_files, tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["train", "--data", pm_files["train"], "--method", "bc", "--steps", "6",
               "--out", str(out), "--profile", "cpu", "--quiet", "--eval-data",
               pm_files["test"], "--eval-every", "3", "--set", "vd_horizon=50"])
    assert rc == 0, capsys.readouterr().err
    rows = [json.loads(x) for x in (out / "eval.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [3, 6]
    for r in rows:
        assert len(r["vd"]) == 3 and r["avd"] == pytest.approx(np.mean(r["vd"]))
        assert r["mvd"] == pytest.approx(np.max(r["vd"]))

    report = tmp_path / "eval.json"
    proc = subprocess.run([sys.executable, "-m", "rl2s_jax.cli", "evaluate", "--ckpt",
                           str(out / "checkpoints"), "--data", pm_files["test"], "--episodes",
                           "8", "--json", str(report)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "kendall_tau" in proc.stdout
    # Quiet start: MJX's lines about its absent optional Warp backend do not reach the terminal.
    assert "Failed to import" not in proc.stdout + proc.stderr
    r = json.loads(report.read_text())
    assert r["step"] == 6 and r["method"] == "bc" and r["horizon"] == 50
    true, sim = np.asarray(r["true_value"]), np.asarray(r["sim_value"])
    np.testing.assert_allclose(r["vd"], np.abs(true - sim), rtol=1e-6)
    assert r["metrics"]["avd"] == pytest.approx(np.mean(np.abs(true - sim)))
    assert r["metrics"]["kendall_tau"] == pytest.approx(kendall_tau(true, sim))
    from rl2s_jax.data.dataset import load_dataset
    np.testing.assert_allclose(true, load_dataset(pm_files["test"]).value_discounted, rtol=1e-6)
    assert all(0 < n <= 50 for n in r["sim_length"])


def test_value_report_states_the_spread_of_one_episode(pm_files):
    """value_report's sim_return_sd is each policy's sample std over its episodes (the noise
    that noise_ceiling needs), 0 with one episode."""
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.evaluate.scores import value_report
    ds = load_dataset(pm_files["test"])
    rng = np.random.default_rng(0)
    returns = rng.normal(10.0, 3.0, size=(ds.n_policies, 7))
    r = value_report(ds, returns, np.full_like(returns, 50.0), horizon=50, gamma=0.99)
    np.testing.assert_allclose(r["sim_return_sd"], np.std(returns, axis=1, ddof=1))
    np.testing.assert_allclose(r["sim_value"], returns.mean(1))
    one = value_report(ds, returns[:, :1], np.ones_like(returns[:, :1]), horizon=50,
                       gamma=0.99)
    assert one["sim_return_sd"] == [0.0] * ds.n_policies


def test_evaluate_bad_input(pm_files, tmp_path, capsys):
    rc = main(["evaluate", "--ckpt", str(tmp_path / "none"), "--data", pm_files["test"]])
    assert rc == 2 and "ckpt" in capsys.readouterr().err
    rc = main(["evaluate", "--ckpt", str(tmp_path), "--data", str(tmp_path / "missing.npz")])
    assert rc == 2 and "data" in capsys.readouterr().err


def test_broken_latest_checkpoint_evaluate_and_resume_fall_back(pm_files, tmp_path, capsys):
    """The issue's case: a corrupt newest checkpoint. `rl2s evaluate` and the resume of
    `rl2s train` both warn naming the step and the damage, then use the newest intact step;
    `--step` of the broken one is an error saying what is wrong."""
    out = tmp_path / "run"
    train = ["train", "--data", pm_files["train"], "--method", "bc", "--steps", "4",
             "--save-every", "2", "--out", str(out), "--profile", "cpu", "--quiet", "--set",
             "vd_horizon=20", "--set", "vd_every=2"]
    assert main(train) == 0, capsys.readouterr().err
    capsys.readouterr()
    with open(out / "checkpoints" / "4" / "meta" / "metadata", "r+b") as f:
        f.truncate(20)
    evaluate = ["evaluate", "--ckpt", str(out / "checkpoints"), "--data", pm_files["test"],
                "--episodes", "2", "--horizon", "20"]
    report = tmp_path / "eval.json"
    assert main(evaluate + ["--json", str(report)]) == 0
    err = capsys.readouterr().err
    assert ("rl2s evaluate: warning: checkpoint" in err and "broken step 4 skipped (step 4: "
            "meta/metadata is not valid JSON" in err and "using step 2" in err), err
    assert json.loads(report.read_text())["step"] == 2

    assert main(evaluate + ["--step", "4"]) == 2
    err = capsys.readouterr().err
    assert "rl2s evaluate: error:" in err and "step 4 is broken: meta/metadata is not valid" in err

    assert main(train) == 0
    captured = capsys.readouterr()
    assert "rl2s train: warning:" in captured.err and "broken step 4" in captured.err
    assert "resuming" in captured.out and "from step 2" in captured.out
    assert "moved corrupt step(s) [4]" in captured.out
    assert (out / "checkpoints" / "corrupt" / "4").is_dir()
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4]
    assert main(evaluate + ["--json", str(report), "--force"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert json.loads(report.read_text())["step"] == 4
