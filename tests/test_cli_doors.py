"""Errors at the door (issue 38, item 4): a command's outputs are checked right after parsing,
before it loads data, compiles or collects, with one line naming the user's path and exit
status 2; and a closed stdout (`rl2s inspect ... | head -1`) ends quietly."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from rl2s_jax import cli
from rl2s_jax.app.paths import OUTPUTS, output_error, output_problem
from rl2s_jax.data.dataset import Dataset, save_dataset


def refused(argv, capsys):
    """Run the command in-process, expecting the door's refusal: (stderr, seconds)."""
    t0 = time.time()
    with pytest.raises(SystemExit) as exit_info:
        cli.main(argv)
    seconds = time.time() - t0
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, err
    assert "Traceback" not in err and ".tmp-" not in err
    assert len(err.strip().splitlines()) == 1, err
    return err, seconds


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / "FILE"
    path.write_text("not a directory")
    return path


@pytest.fixture
def read_only_dir(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    if os.geteuid() == 0 and os.access(d, os.W_OK):
        d.chmod(0o700)
        pytest.skip("root writes into read-only directories")
    yield d
    d.chmod(0o700)


def tiny_dataset(path):
    """One policy, one 3-step episode that ends done: a valid Dataset file, task none."""
    n = 3
    arrays = dict(obs=np.zeros((n, 2), np.float32), action=np.zeros((n, 1), np.float32),
                  next_obs=np.zeros((n, 2), np.float32), reward=np.ones(n, np.float32),
                  done=np.array([False, False, True]), truncated=np.zeros(n, bool),
                  policy_id=np.zeros(n, np.int32), episode_id=np.zeros(n, np.int32),
                  t=np.arange(n, dtype=np.int32))
    meta = dict(task=None, obs_size=2, action_size=1, n_policies=1, gamma=0.99,
                episode_length=None, policy_names=["p0"], source={"made_by": __name__})
    save_dataset(str(path), Dataset.from_arrays(arrays, meta))
    return str(path)


def test_train_out_under_a_file(tmp_path, a_file, capsys):
    data = tiny_dataset(tmp_path / "d.npz")
    out = f"{a_file}/sub"
    err, seconds = refused(["train", "--data", data, "--steps", "1", "--out", out], capsys)
    assert seconds < 10
    assert err == f"rl2s train: error: --out: cannot write to '{out}': '{a_file}' is not a " \
        "directory\n"
    assert not os.path.exists(out)


def test_outputs_checked_before_the_inputs(tmp_path, a_file, capsys):
    """The door comes first: a missing --data is not reached (it would be refused later)."""
    out = f"{a_file}/x/y.npz"
    err, _ = refused(["collect", "--task", "pointmass", "--zoo", "hopper",
                      "--transitions-per-policy", "5", "--out", out], capsys)
    assert f"rl2s collect: error: --out: cannot write to '{out}'" in err
    err, _ = refused(["diagnose", "--data", str(tmp_path / "missing.npz"), "--out",
                      str(a_file)], capsys)
    assert f"--out: cannot write to '{a_file}': it exists and is not a directory" in err
    err, _ = refused(["evaluate", "--oracle", "--data", str(tmp_path / "missing.npz"),
                      "--json", str(tmp_path)], capsys)
    assert f"--json: cannot write to '{tmp_path}': it is a directory" in err


def test_evaluate_json_unwritable(tmp_path, read_only_dir, capsys):
    path = str(read_only_dir / "report.json")
    err, _ = refused(["evaluate", "--oracle", "--data", str(tmp_path / "missing.npz"),
                      "--json", path], capsys)
    assert err.startswith(f"rl2s evaluate: error: --json: cannot write to '{path}': "
                          "permission denied")


def test_collect_out_unwritable(read_only_dir, capsys):
    path = str(read_only_dir / "new" / "d.npz")   # parents created by collect: checked above
    err, _ = refused(["collect", "--task", "pointmass", "--zoo", "hopper",
                      "--transitions-per-policy", "5", "--out", path], capsys)
    assert f"--out: cannot write to '{path}': permission denied ('{read_only_dir}'" in err
    assert not os.path.exists(os.path.dirname(path))


def test_diagnose_out_unwritable(tmp_path, read_only_dir, capsys):
    for path in (str(read_only_dir), str(read_only_dir / "report")):
        err, _ = refused(["diagnose", "--data", str(tmp_path / "missing.npz"), "--out", path],
                         capsys)
        assert f"rl2s diagnose: error: --out: cannot write to '{path}': permission denied" in err


def test_output_problem_creates_nothing(tmp_path, a_file):
    deep = tmp_path / "a" / "b" / "c"
    assert output_problem(str(deep), "dir") is None
    assert output_problem(str(deep / "f.npz"), "file") is None
    assert not (tmp_path / "a").exists()
    assert output_problem(str(a_file), "file") is None          # replaced whole
    assert output_problem(str(tmp_path), "dir") is None          # written into
    assert output_problem(str(a_file / "x" / "y"), "dir") == f"'{a_file}' is not a directory"
    assert output_error("--json", str(tmp_path), "file") == \
        f"--json: cannot write to '{tmp_path}': it is a directory"
    with pytest.raises(ValueError, match="kind"):
        output_problem(str(tmp_path), "folder")


def test_every_output_option_is_checked():
    """Each subcommand's output options (by name) are in paths.OUTPUTS, with a real dest."""
    parser = cli.build_parser()
    subs = next(a for a in parser._actions if a.dest == "command").choices
    for command, p in subs.items():
        names = {s for a in p._actions for s in a.option_strings}
        outputs = {"--out", "--json", "--export", "--work", "--report"} & names
        assert outputs == {o for o, _ in OUTPUTS.get(command, ())}, command
        dests = {a.dest for a in p._actions}
        assert {o.lstrip("-").replace("-", "_") for o in outputs} <= dests


@pytest.mark.parametrize("unbuffered", [False, True], ids=["buffered", "unbuffered"])
def test_inspect_into_a_closed_pipe(tmp_path, unbuffered):
    """`rl2s inspect ... | head -1`, made certain: stdout is a pipe whose reader has already
    gone, so the first write fails (in print when unbuffered, else in the final flush)."""
    data = tiny_dataset(tmp_path / "d.npz")
    read, write = os.pipe()
    os.close(read)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    env["RL2S_COMPILATION_CACHE"] = "off"
    if unbuffered:
        env["PYTHONUNBUFFERED"] = "1"
    try:
        proc = subprocess.run([sys.executable, "-m", "rl2s_jax.cli", "inspect", "--data", data],
                              stdout=write, stderr=subprocess.PIPE, text=True, env=env,
                              timeout=60)
    finally:
        os.close(write)
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr
    assert "Exception ignored" not in proc.stderr, proc.stderr
    assert proc.returncode == 1


def test_improve_and_pipeline_both_take_a_recipe():
    """`rl2s improve` and `rl2s pipeline` both take --recipe, whose floor scale the help names
    as --guard-floor-scale's default (the pipeline once had none, yet promised it)."""
    parser = cli.build_parser()
    subs = next(a for a in parser._actions if a.dest == "command").choices
    for command in ("improve", "pipeline"):
        actions = {s: a for a in subs[command]._actions for s in a.option_strings}
        assert "default: the --recipe's, else 1;" in actions["--guard-floor-scale"].help
        assert "control" in actions["--recipe"].choices, command
