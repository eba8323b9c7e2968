"""Your own policies: the policy file (save_policies / load_policies), `rl2s evaluate` and
`rl2s improve` with --policy-file or with a Dataset whose meta.source names one, `rl2s train
--eval-data TEST --eval-policies FILE`, and the settings `rl2s evaluate` uses by default (the
checkpoint's, said in the report)."""
import json
import os
import re

import jax
import numpy as np
import pytest

from rl2s_jax import cli
from rl2s_jax.app.evaluation import checkpoint_setting
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.evaluate.setting import EVAL_EPISODES, EvalSetting
from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo import zoo as zoo_mod

ODD_NAMES = ["pol/ä ü", "  spaced  ", "line\nbreak \"q\"", "🦘\x00"]  # the fixture's 4 policies
QUICK = ["--episodes", "2", "--horizon", "10", "--bootstrap", "0"]
SMALL_SAC = ["--set", "n_envs=4", "--set", "hidden=[32,32]", "--set", "batch_size=32",
             "--set", "warmup_steps=8", "--set", "buffer_size=2000"]


@pytest.fixture(scope="module")
def run(pointmass_checkpoint):
    """The conftest run plus its 4 policies (the data's, in policy_id order) and the same
    data with an empty meta.source (only a given policy file can supply its policies)."""
    out = dict(pointmass_checkpoint)
    out["params"] = zoo_mod.load_zoo(out["zoo"]).params
    ds = load_dataset(out["data"])
    out["bare"] = os.path.join(os.path.dirname(out["data"]), "bare.npz")
    save_dataset(out["bare"], ds.replace(meta={**ds.meta, "source": {}}))
    return out


@pytest.fixture(scope="module")
def zoo_report(run, tmp_path_factory):
    """`rl2s evaluate` of the run's data, its policies from the zoo that meta.source names."""
    path = tmp_path_factory.mktemp("zoo_eval") / "eval.json"
    assert cli.main(["evaluate", "--ckpt", run["ckpt"], "--data", run["data"], *QUICK,
                     "--json", str(path)]) == 0
    return json.loads(path.read_text())


def _evaluate(run, data, tmp_path, *extra) -> dict:
    path = tmp_path / "eval.json"
    assert cli.main(["evaluate", "--ckpt", run["ckpt"], "--data", data, *QUICK, *extra,
                     "--json", str(path)]) == 0
    return json.loads(path.read_text())


def test_policy_file_round_trip_with_odd_names(run, tmp_path):
    path = tmp_path / "mine.policies"  # any name: no suffix is added
    pol.save_policies(path, run["params"], ODD_NAMES)
    assert sorted(os.listdir(tmp_path)) == ["mine.policies"]
    params, names = pol.load_policies(path)
    assert names == ODD_NAMES
    assert (jax.tree_util.tree_structure(params)
            == jax.tree_util.tree_structure(run["params"]))
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(run["params"]),
                    strict=True):
        assert a.dtype == np.float32
        np.testing.assert_array_equal(a, b)


def _write(path, flat: dict, meta) -> str:
    with open(path, "wb") as f:
        np.savez(f, **flat, **({} if meta is None else {"meta": np.array(json.dumps(meta))}))
    return str(path)


def test_policy_file_refuses_bad_input_naming_the_field(run, tmp_path):
    params = run["params"]
    with pytest.raises(ValueError, match="names: expected unique names, got 'a' more"):
        pol.save_policies(tmp_path / "x", params, ["a", "b", "a", "c"])
    with pytest.raises(ValueError, match="names: expected 4 names"):
        pol.save_policies(tmp_path / "x", params, ["a", "b", "c"])
    with pytest.raises(ValueError, match="names: expected strings, got 3"):
        pol.save_policies(tmp_path / "x", params, ["a", "b", "c", 3])
    with pytest.raises(ValueError, match="params: expected a dict with keys"):
        pol.save_policies(tmp_path / "x", {"w": params["obs_mean"]}, ["a"] * 4)
    wide = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), params)
    with pytest.raises(ValueError, match="params: obs_mean: expected float32, got float64"):
        pol.save_policies(tmp_path / "x", wide, list("abcd"))
    assert not os.path.exists(tmp_path / "x")

    flat = pol.flatten_params(params)
    meta = {"format_version": 1, "policy_names": list("abcd")}
    cases = {
        "no 'meta' entry": (flat, None),
        "meta.format_version: expected 1, got 2": (flat, {**meta, "format_version": 2}),
        r"missing \['layers/0/b'\]": ({k: v for k, v in flat.items() if k != "layers/0/b"},
                                      meta),
        r"unknown \['extra'\]": ({**flat, "extra": flat["obs_std"]}, meta),
        r"layers/1/w: expected shape \[4, 8, 2\], got \[4, 7, 2\]":
            ({**flat, "layers/1/w": flat["layers/1/w"][:, :7]}, meta),
        "layers/1/b: expected finite values":
            ({**flat, "layers/1/b": np.full_like(flat["layers/1/b"], np.nan)}, meta),
        "obs_std: expected values > 0": ({**flat, "obs_std": 0 * flat["obs_std"]}, meta),
        "meta.policy_names: expected 4 names": (flat, {**meta, "policy_names": ["a"]}),
    }
    for i, (message, (arrays, m)) in enumerate(cases.items()):
        path = _write(tmp_path / f"bad{i}.npz", arrays, m)
        with pytest.raises(ValueError, match=re.escape(f"policy file {path}: ") + f".*{message}"):
            pol.load_policies(path)
    text = tmp_path / "text.npz"
    text.write_text("obs,action\n")
    with pytest.raises(ValueError, match="expected an .npz archive written by save_policies"):
        pol.load_policies(text)
    with pytest.raises(FileNotFoundError, match="no such file"):
        pol.load_policies(tmp_path / "missing.npz")


def test_evaluate_with_a_policy_file_scores_as_with_the_zoo(run, zoo_report, tmp_path,
                                                            capsys):
    """The bare data (no zoo named) with the same policies from a policy file: the same
    report; without the file its policies are unknown, and the error says what to pass."""
    pf = str(tmp_path / "p.npz")
    pol.save_policies(pf, run["params"], ODD_NAMES)
    r = _evaluate(run, run["bare"], tmp_path, "--policy-file", pf)
    for key in ("sim_value", "true_value", "vd", "metrics", "horizon", "n_episodes"):
        assert r[key] == zoo_report[key], key
    assert cli.main(["evaluate", "--ckpt", run["ckpt"], "--data", run["bare"], *QUICK]) == 2
    assert "--policy-file FILE" in capsys.readouterr().err


def test_data_naming_a_relative_policy_file_evaluates_from_elsewhere(run, zoo_report,
                                                                     tmp_path, monkeypatch):
    """meta.source.policy_file is resolved against the data file's directory, not the
    working directory."""
    data_dir = tmp_path / "shared" / "data"
    pol.save_policies(data_dir / "pols" / "mine.npz", run["params"], list("abcd"))
    ds = load_dataset(run["data"])
    save_dataset(str(data_dir / "test.npz"),
                 ds.replace(meta={**ds.meta, "source": {"policy_file": "pols/mine.npz"}}))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    r = _evaluate(run, os.path.join("..", "shared", "data", "test.npz"), tmp_path)
    assert r["sim_value"] == zoo_report["sim_value"]
    assert r["metrics"] == zoo_report["metrics"]
    # the source's file, not a zoo: a wrong file there is named by its field
    pol.save_policies(data_dir / "pols" / "mine.npz",
                      pol.index_params(run["params"], np.array([0, 1])), ["a", "b"])
    with pytest.raises(ValueError, match="meta.source.policy_file: .* holds 2 policies, but "
                       "the Dataset holds 4"):
        zoo_mod.policies_for(load_dataset(str(data_dir / "test.npz")),
                             data_path=str(data_dir / "test.npz"))
    with pytest.raises(ValueError, match="meta.source.policy_file: 'pols/mine.npz' is "
                       "relative .* \\(pass data_path=\\)"):
        zoo_mod.policies_for(load_dataset(str(data_dir / "test.npz")))


def test_policy_file_mismatch_is_refused_naming_the_flag(run, tmp_path, capsys):
    three = str(tmp_path / "three.npz")
    pol.save_policies(three, pol.index_params(run["params"], np.array([0, 1, 2])),
                      list("abc"))
    shuffled = str(tmp_path / "shuffled.npz")
    pol.save_policies(shuffled, run["params"], [f"pointmass-{i:03d}" for i in (1, 0, 2, 3)])
    wide = str(tmp_path / "wide.npz")
    pol.save_policies(wide, pol.stack_params([pol.init_policy(jax.random.PRNGKey(i), 3, 1)
                                              for i in range(4)]), list("abcd"))
    out = tmp_path / "never"
    for extra, parts in (
            (["--policy-file", three], [f"policy-file: {three} holds 3 policies, but the "
                                        "Dataset holds 4 (its n_policies)"]),
            (["--policy-file", shuffled], [f"policy-file: {shuffled} names the Dataset's "
                                           "policies in another order"]),
            (["--policy-file", wide], [f"policy-file: the policies of {wide} take "
                                       "observations of size 3 and act in 1 dims, the "
                                       "Dataset's obs_size / action_size are 2 / 1"]),
            (["--policy-file", three, "--zoo", run["zoo"]],
             ["policy-file: give the data's policies by --zoo DIR or by --policy-file FILE, "
              "not both"]),
            (["--policy-file", str(tmp_path / "missing.npz")],
             ["policy-file: policy file ", "missing.npz: no such file"])):
        for command in (["evaluate", *QUICK], ["improve", "--out", str(out), "--quiet"]):
            rc = cli.main([*command, "--ckpt", run["ckpt"], "--data", run["data"], *extra])
            err = capsys.readouterr().err
            assert rc == 2 and err.startswith(f"rl2s {command[0]}: error: "), err
            assert all(part in err for part in parts), (parts, err)
    assert not out.exists()  # refused before any work


def test_improve_takes_the_policies_of_a_policy_file(run, tmp_path):
    """The file's policy 1 (its normaliser marked) is the one fine-tuned; the zoo written
    records the file as the policies' origin."""
    params = jax.tree_util.tree_map(np.array, run["params"])
    params["obs_mean"][1] = [0.125, -0.25]  # a frozen normaliser: fine-tuning keeps it
    pf = tmp_path / "mine.npz"
    pol.save_policies(pf, params, list("abcd"))
    out = tmp_path / "improved"
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["bare"], "--policy-file",
                     str(pf), "--policies", "1", "--out", str(out), "--iterations", "4",
                     "--no-measure", "--quiet", *SMALL_SAC]) == 0
    zoo = zoo_mod.load_zoo(str(out))
    np.testing.assert_array_equal(zoo.params["obs_mean"], [[0.125, -0.25]])
    assert zoo.origins[0]["policy_file"] == str(pf) and zoo.origins[0]["zoo"] is None
    assert zoo.origins[0]["data_index"] == 1


@pytest.fixture(scope="module")
def short_checkpoint(run, tmp_path_factory):
    """A pointmass checkpoint (initialised, untrained) whose training evaluated 3 episodes of
    20 steps per policy, shorter than the data's 50-step episodes."""
    from rl2s_jax.train.checkpoint import Checkpointer
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init

    ds = load_dataset(run["data"])
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=20, vd_episodes=3)
    state = init(jax.random.PRNGKey(0), cfg, make_train_data(ds, run["params"], cfg))
    path = str(tmp_path_factory.mktemp("short") / "checkpoints")
    ck = Checkpointer(path)
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1, "task": "pointmass"}})
    ck.close()
    return path


def test_evaluate_defaults_to_the_checkpoints_horizon_and_says_so(run, short_checkpoint,
                                                                  tmp_path, capsys):
    path = tmp_path / "eval.json"
    base = ["evaluate", "--ckpt", short_checkpoint, "--data", run["data"], "--bootstrap", "0",
            "--json", str(path)]
    assert cli.main(base) == 0
    printed = capsys.readouterr().out
    r = json.loads(path.read_text())
    # the data's episodes last 50 steps; the episodes are the one setting's, not vd_episodes
    assert (r["horizon"], r["n_episodes"]) == (20, EVAL_EPISODES)
    assert r["horizon_source"] == "the checkpoint's vd_horizon"
    assert r["episodes_source"] == f"the default {EVAL_EPISODES}"
    assert r["setting"] == {"episodes": EVAL_EPISODES, "horizon": 20, "seed": 0,
                            "truth": "auto", "horizon_source": "the checkpoint's vd_horizon"}
    assert max(r["sim_length"]) <= 20  # simulated so, not only reported
    assert (f"horizon 20 (the checkpoint's vd_horizon), {EVAL_EPISODES} episodes (the default "
            f"{EVAL_EPISODES})") in printed and "seed 0, true values: logged" in printed
    assert cli.main(base + ["--horizon", "10", "--episodes", "2", "--force"]) == 0
    r = json.loads(path.read_text())
    assert (r["horizon"], r["horizon_source"], r["n_episodes"], r["episodes_source"]) == (
        10, "--horizon", 2, "--episodes")
    assert "horizon 10 (--horizon), 2 episodes (--episodes)" in capsys.readouterr().out


def test_checkpoint_setting_stops_at_the_datas_episode_length(run):
    ds = run["dataset"]
    s = checkpoint_setting({"vd_horizon": 80, "vd_episodes": 5}, ds, EvalSetting(episodes=5))
    assert (s.horizon, s.episodes) == (ds.meta["episode_length"], 5)
    assert s.horizon_source == ("the data's episode_length; the checkpoint's vd_horizon 80 "
                                "is longer")
    with pytest.raises(ValueError, match="horizon: expected an int >= 1"):
        EvalSetting(horizon=0)


def test_oracle_takes_a_policy_file_and_names_its_defaults(run, tmp_path, capsys):
    """--oracle (no checkpoint): the policies from --policy-file, the one setting's 16
    episodes of the horizon training on this backend uses (the cpu profile's here: the data's
    50-step episodes, under its 100), said in the report."""
    pf = tmp_path / "p.npz"
    pol.save_policies(pf, run["params"], list("abcd"))
    path = tmp_path / "oracle.json"
    assert cli.main(["evaluate", "--oracle", "--data", run["bare"], "--policy-file", str(pf),
                     "--bootstrap", "0", "--json", str(path)]) == 0
    r = json.loads(path.read_text())
    assert (r["method"], r["horizon"], r["n_episodes"]) == ("oracle", 50, 16)
    assert (r["horizon_source"], r["episodes_source"]) == (
        "the cpu profile's: at most 100 steps of the data's episodes", "the default 16")
    assert "the real dynamics (oracle) on " in capsys.readouterr().out
    # the exact dynamics: the simulated values meet the measured ones within their noise
    true_se = np.asarray(run["dataset"].value_discounted_se)
    sim_se = np.asarray(r["sim_return_sd"]) / np.sqrt(r["n_episodes"])
    assert np.all(np.asarray(r["vd"]) < 4 * np.hypot(true_se, sim_se))


def test_any_jax_policy_function_is_evaluated_from_python(run):
    """``evaluate_simulator(..., policy_fn=)``: any JAX function (params, obs, key) -> action
    with a stacked params pytree. The project's own policy, wrapped as such a function, scores
    exactly as the default path; a foreign params layout (a linear policy) runs and its
    values follow what its actions do."""
    import jax.numpy as jnp

    from rl2s_jax.evaluate.scores import evaluate_simulator
    from rl2s_jax.train.checkpoint import load_simulator

    sim, ds = load_simulator(run["ckpt"]), load_dataset(run["data"])
    kw = dict(key=jax.random.PRNGKey(3), n_episodes=4, horizon=20)
    plain = evaluate_simulator(sim, ds, run["params"], **kw)
    wrapped = evaluate_simulator(sim, ds, run["params"], **kw,
                                 policy_fn=lambda p, o, k: pol.sample_action(p, o, k)[0])
    assert wrapped["sim_value"] == plain["sim_value"]

    def linear(p, obs, key):  # deterministic: tanh(obs @ w + b), one policy's params
        del key
        return jnp.tanh(obs @ p["w"] + p["b"])
    P = ds.n_policies
    pushes = jnp.asarray([[-3.0], [0.0], [0.0], [3.0]])[:P]  # full throttle either way, or none
    foreign = {"w": jnp.zeros((P, 2, 1)), "b": pushes}
    res = evaluate_simulator(sim, ds, foreign, **kw, policy_fn=linear)
    v = np.asarray(res["sim_value"])
    assert np.isfinite(v).all() and v.shape == (P,)
    # reward 1 - p'^2: full throttle either way drives the mass off the origin, costing
    # value (measured 16.5 and 12.0 against 17.8 and 18.1 for no push, listed twice)
    assert max(v[0], v[3]) < min(v[1], v[2]), v


# `rl2s train` of pm_files' train data (3 policies), 2 bc steps, tiny networks, one test
# evaluation at the end (2 episodes of 50 steps per test policy)
TRAIN_QUICK = ["--method", "bc", "--steps", "2", "--eval-every", "2", "--profile", "cpu",
               "--quiet", "--set", "vd_horizon=50", "--set", "vd_episodes=2", "--set",
               "updates_per_step=2", "--set", "gen_hidden=[32]", "--set", "hazard_steps=0"]


@pytest.fixture(scope="module")
def eval_files(pm_files, tmp_path_factory):
    """pm_files' test data without meta.source ("bare": only a given file supplies its
    policies), a file of its policies (zoo 3-5, their names) and one of others (zoo 0-2)."""
    root = tmp_path_factory.mktemp("eval_policies")
    ds = load_dataset(pm_files["test"])
    z = zoo_mod.load_zoo(ds.meta["source"]["zoo"])
    out = {"bare": str(root / "bare.npz"), "mine": str(root / "mine.npz"),
           "other": str(root / "other.npz")}
    save_dataset(out["bare"], ds.replace(meta={**ds.meta, "source": {}}))
    pol.save_policies(out["mine"], pol.index_params(z.params, np.array([3, 4, 5])),
                      z.policy_names([3, 4, 5]))
    pol.save_policies(out["other"], pol.index_params(z.params, np.array([0, 1, 2])),
                      ["x", "y", "z"])
    return out


def _train(pm_files, out, *extra) -> tuple[dict, dict]:
    """`rl2s train` -> (summary.json, the last row of eval.jsonl)."""
    assert cli.main(["train", "--data", pm_files["train"], "--out", str(out), *TRAIN_QUICK,
                     *extra]) == 0
    with open(out / "eval.jsonl") as f:
        last = [json.loads(line) for line in f][-1]
    return json.loads((out / "summary.json").read_text()), last


def test_train_evaluates_the_test_policies_of_eval_policies(pm_files, eval_files,
                                                             tmp_path, capsys):
    """The same test policies from the data's zoo or from --eval-policies (bare data): the
    same test VD; other policies in the file (over the zoo the data names): another."""
    _, by_zoo = _train(pm_files, tmp_path / "zoo", "--eval-data", pm_files["test"])
    s, by_file = _train(pm_files, tmp_path / "file", "--eval-data", eval_files["bare"],
                        "--eval-policies", eval_files["mine"])
    assert f"policies of {eval_files['mine']}" in capsys.readouterr().out
    assert s["eval_policies"] == eval_files["mine"] and s["step_test"] == 2
    assert len(by_file["vd"]) == 3 and by_file["step"] == 2
    assert by_file["vd"] == by_zoo["vd"] and by_file["avd"] == s["avd_test"]
    _, by_other = _train(pm_files, tmp_path / "other", "--eval-data", pm_files["test"],
                         "--eval-policies", eval_files["other"])
    assert len(by_other["vd"]) == 3 and by_other["vd"] != by_zoo["vd"]


def test_train_refuses_wrong_eval_policies_before_training(pm_files, eval_files,
                                                           tmp_path, capsys):
    """Refused naming --eval-policies (or what is missing), before any training work: the
    run directory is never made."""
    z = pol.load_policies(eval_files["mine"])[0]
    two = str(tmp_path / "two.npz")
    pol.save_policies(two, pol.index_params(z, np.array([0, 1])), ["a", "b"])
    wide = str(tmp_path / "wide.npz")
    pol.save_policies(wide, pol.stack_params([pol.init_policy(jax.random.PRNGKey(i), 3, 1)
                                              for i in range(3)]), list("abc"))
    out = tmp_path / "never"
    bare = ["--eval-data", eval_files["bare"]]
    for extra, parts in (
            ([*bare, "--eval-policies", two],
             [f"eval-policies: {two} holds 2 policies, but the Dataset holds 3"]),
            ([*bare, "--eval-policies", wide],
             [f"eval-policies: the policies of {wide} take observations of size 3 and act "
              "in 1 dims, the Dataset's obs_size / action_size are 2 / 1"]),
            ([*bare, "--eval-policies", str(tmp_path / "missing.npz")],
             ["eval-policies: policy file ", "missing.npz: no such file"]),
            (bare, [f"eval_data: {eval_files['bare']}: zoo: ", "--eval-policies FILE"]),
            (["--eval-policies", eval_files["mine"]],
             ["eval-policies: ", "--eval-data TEST"])):
        rc = cli.main(["train", "--data", pm_files["train"], "--out", str(out), *TRAIN_QUICK,
                       *extra])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("rl2s train: error: "), err
        assert all(part in err for part in parts), (parts, err)
        assert not out.exists()  # refused before any work
