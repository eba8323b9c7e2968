"""`rl2s improve` end to end on pointmass: fine-tuned policies written as a zoo that
load_zoo, collect and measure_values take; real returns, plots and summary; bad input refused
before any work."""
import json
import os

import jax
import numpy as np
import pytest

from rl2s_jax import cli
from rl2s_jax.app.value_intervals import NO_INTERVAL
from rl2s_jax.data.collect import measure_values
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.envs.tasks import PointMass
from rl2s_jax.policy import policy as pol
from rl2s_jax.policy.sac import SACConfig
from rl2s_jax.zoo import zoo as zoo_mod
from rl2s_jax.zoo.build import fine_tuning_recipe
from rl2s_jax.zoo.zoo import policies_for

SMALL = ["--set", "n_envs=4", "--set", "hidden=[32,32]", "--set", "batch_size=32",
         "--set", "warmup_steps=8", "--set", "buffer_size=2000"]


def test_improve_end_to_end(pointmass_checkpoint, tmp_path, capsys):
    """--no-guard: raw fine-tuning, every fine-tuned policy deployed."""
    run = pointmass_checkpoint
    out = tmp_path / "improved"
    rc = cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--policies",
                   "0,2", "--out", str(out), "--iterations", "40", "--episodes", "4",
                   "--quiet", "--no-guard", *SMALL, "--set", "kl_weight=0.02"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "pointmass-000" in printed and "pointmass-002" in printed and "MPI" in printed
    assert "No deployment guard (--no-guard)" in printed
    zoo = zoo_mod.load_zoo(str(out))
    assert zoo.task == "pointmass" and zoo.size == 2 and zoo.test_ids == [0, 1]
    before = pol.index_params(policies_for(load_dataset(run["data"])), np.array([0, 2]))
    assert jax.tree_util.tree_structure(zoo.params) == jax.tree_util.tree_structure(before)
    np.testing.assert_array_equal(zoo.params["obs_std"], before["obs_std"])
    moved = [not np.allclose(a, b) for a, b in zip(jax.tree_util.tree_leaves(
        zoo.params["layers"]), jax.tree_util.tree_leaves(before["layers"]), strict=True)]
    assert any(moved)  # SAC changed the actors
    assert [o["zoo_id"] for o in zoo.origins] == [0, 2]
    assert zoo.info["sac"]["kl_weight"] == 0.02 and zoo.info["sac"]["n_envs"] == 4
    assert zoo.info["sac"]["critic_warmup_updates"] == 10  # a quarter of 40 x 1 updates
    s = json.loads((out / "summary.json").read_text())
    assert s["guard"] is None and "deployed" not in zoo.origins[0]
    assert [r["policy"] for r in s["policies"]] == ["pointmass-000", "pointmass-002"]
    for r, c1 in zip(s["policies"], zoo.returns, strict=True):
        assert r["c1"] == pytest.approx(float(c1), rel=1e-5)  # the zoo records C1
        assert r["I"] == pytest.approx((r["c1"] - r["c0"]) / abs(r["c0"]), rel=1e-5)
        assert r["c0_se"] >= 0 and r["c1_se"] >= 0 and r["real_gain"] == r["I"]
        assert len(r["sim_return_curve"]) == len(s["curve_iterations"]) > 1
    assert s["mpi"] == pytest.approx(min(r["I"] for r in s["policies"]))
    assert s["api"] == pytest.approx(np.mean([r["I"] for r in s["policies"]]))
    for name in ("policy_pointmass-000.png", "policy_pointmass-002.png"):
        assert (out / name).stat().st_size > 1000
    assert "| pointmass-000 |" in (out / "summary.md").read_text()
    # the zoo is usable as any other: measure_values and `rl2s collect --zoo`
    v = measure_values(PointMass(), zoo.params, key=jax.random.PRNGKey(0), n_episodes=2,
                       episode_length=10)
    assert v["value"].shape == (2,)
    coll = tmp_path / "again.npz"
    assert cli.main(["collect", "--task", "pointmass", "--split", "test", "--zoo", str(out),
                     "--transitions-per-policy", "20", "--value-episodes", "2",
                     "--out", str(coll)]) == 0
    assert load_dataset(str(coll)).n_policies == 2


def test_improve_branched_with_penalty_runs(pointmass_checkpoint, tmp_path):
    run = pointmass_checkpoint
    out = tmp_path / "branched"
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--policies",
                     "1", "--out", str(out), "--iterations", "12", "--no-measure", "--quiet",
                     "--branch-length", "5", "--uncertainty-penalty", "0.5",
                     "--uncertainty-threshold", "4", *SMALL]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["env_options"] == {"rollout_length": 5, "uncertainty_penalty": 0.5,
                                "uncertainty_threshold": 4.0, "halt_penalty": 0.0}
    assert s["mpi"] is None and not list(out.glob("*.png"))
    zoo = zoo_mod.load_zoo(str(out))
    assert zoo.size == 1 and np.isnan(zoo.returns[0])


def test_improve_recipe_gives_the_defaults_and_flags_given_win(pointmass_checkpoint, tmp_path,
                                                               capsys):
    """--recipe control: the measured recipe's branches, penalty, KL, SAC sizes and the zoo
    learner's discount where no flag is given; --iterations, --set, --branch-length and
    --uncertainty-penalty given win; a simulator the recipe cannot run in is refused."""
    run = pointmass_checkpoint
    out = tmp_path / "recipe"
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--policies",
                     "1", "--out", str(out), "--recipe", "control", "--iterations", "6",
                     "--no-measure", "--quiet", "--no-guard", *SMALL, "--set",
                     "updates_per_step=1", "--set", "critic_warmup_updates=3"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["recipe"] == "control" and s["iterations"] == 6
    assert s["env_options"]["rollout_length"] == 100
    assert s["env_options"]["uncertainty_penalty"] == 1.0
    sac = zoo_mod.load_zoo(str(out)).info["sac"]
    assert sac["kl_weight"] == 0.01 and sac["n_envs"] == 4 and sac["updates_per_step"] == 1
    assert sac["critic_warmup_updates"] == 3 and sac["buffer_size"] == 2000
    assert sac["gamma"] == fine_tuning_recipe("pointmass")["gamma"] != SACConfig.fine_tuning(
        ).gamma and sac["learn_alpha"] is False
    assert "(recipe control)" in (out / "summary.md").read_text()
    out2 = tmp_path / "recipe_penalty"
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--policies",
                     "1", "--out", str(out2), "--recipe", "control", "--iterations", "2",
                     "--no-measure", "--quiet", "--no-guard", "--uncertainty-penalty", "0",
                     "--branch-length", "5", *SMALL, "--set", "critic_warmup_updates=1",
                     "--set", "updates_per_step=1"]) == 0
    env = json.loads((out2 / "summary.json").read_text())["env_options"]
    assert env["rollout_length"] == 5 and env.get("uncertainty_penalty", 0.0) == 0.0  # off
    # a simulator with history inputs cannot start the recipe's branches: refused, named,
    # before any SAC (a step-0 checkpoint of such a model will do)
    hist = _history_checkpoint(run["data"], tmp_path / "hist")
    assert cli.main(["improve", "--ckpt", hist, "--data", run["data"], "--out",
                     str(tmp_path / "h"), "--recipe", "control", "--quiet"]) == 2
    assert "recipe: control fine-tunes in branches" in capsys.readouterr().err
    assert not (tmp_path / "h").exists()
    with pytest.raises(SystemExit):  # an unknown recipe: refused by the parser
        cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--out",
                  str(tmp_path / "x"), "--recipe", "nope"])


def _history_checkpoint(data_path, root) -> str:
    """A step-0 checkpoint of a pointmass BC model with history inputs (obs_history 1)."""
    from rl2s_jax.train.checkpoint import Checkpointer
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init

    ds = load_dataset(data_path)
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=20, obs_history=1)
    ck = Checkpointer(root / "checkpoints")
    ck.save(init(jax.random.PRNGKey(0), cfg, make_train_data(ds, policies_for(ds), cfg)),
            {"data": {"obs_size": ds.obs_size, "action_size": ds.action_size}})
    ck.close()
    return str(root / "checkpoints")


def test_improve_guard_keeps_the_start_where_the_simulator_sees_no_gain(pointmass_checkpoint,
                                                                        tmp_path):
    """--guard-margin: each fine-tuned policy is deployed only if every elite member predicts
    a gain above the margin; a margin no policy can clear keeps every start policy (the zoo
    holds them unchanged, their improvement is 0); the decisions follow the recorded
    simulated values."""
    run = pointmass_checkpoint
    before = pol.index_params(policies_for(load_dataset(run["data"])), np.array([0, 3]))
    for margin, name in ((1e6, "strict"),):
        out = tmp_path / name
        assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--policies",
                         "0,3", "--out", str(out), "--iterations", "20", "--episodes", "2",
                         "--quiet", "--guard-margin", str(margin), "--guard-episodes", "4",
                         *SMALL]) == 0
        s = json.loads((out / "summary.json").read_text())
        g = s["guard"]
        v0, v1 = np.asarray(g["sim_value_start"]), np.asarray(g["sim_value_tuned"])
        assert v0.shape == v1.shape and v0.shape[1] == 2
        assert g["accepted"] == np.all(v1 - v0 > margin * np.abs(v0), axis=0).tolist()
        i_all = np.asarray([r["I"] for r in s["policies"]])
        assert g["I"] == pytest.approx(np.where(g["accepted"], i_all, 0.0).tolist())
        assert g["mpi"] == pytest.approx(min(g["I"])) and g["api"] == pytest.approx(
            np.mean(g["I"]))
        zoo = zoo_mod.load_zoo(str(out))
        for j, keep in enumerate(g["accepted"]):
            assert zoo.origins[j]["deployed"].startswith("fine-tuned" if keep else "start")
            r = s["policies"][j]
            assert zoo.returns[j] == pytest.approx(r["c1"] if keep else r["c0"], rel=1e-5)
        if name == "strict":
            assert g["accepted"] == [False, False] and g["mpi"] == 0.0
            for a, b in zip(jax.tree_util.tree_leaves(zoo.params),
                            jax.tree_util.tree_leaves(before), strict=True):
                np.testing.assert_array_equal(a, b)
            assert "0 of 2 fine-tuned policies deployed" in (out / "summary.md").read_text()


def test_improve_uses_the_guard_by_default(pointmass_checkpoint, tmp_path, capsys):
    """Without guard options `rl2s improve` deploys through the guard at margin 0.02 and
    prints, per policy, deployed or kept, the members' predicted gain and the real gain."""
    run = pointmass_checkpoint
    out = tmp_path / "default"
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--policies",
                     "0,3", "--out", str(out), "--iterations", "20", "--episodes", "2",
                     "--quiet", "--guard-episodes", "4", *SMALL]) == 0
    printed = capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    g = s["guard"]
    assert g is not None and g["margin"] == 0.02 and "snapshot" not in g
    v0, v1 = np.asarray(g["sim_value_start"]), np.asarray(g["sim_value_tuned"])
    gain = (v1 - v0) / np.abs(v0)
    assert g["accepted"] == np.all(gain > 0.02, axis=0).tolist()
    assert "| policy | deployed | predicted gain (every member at least) |" in printed
    # the floor guard's block and rows as before the interval guard existed (--guard floor)
    assert set(g) == {"margin", "floor", "episodes", "accepted", "sim_value_start",
                      "sim_value_tuned", "predicted_gain", "predicted_gain_mean",
                      "floor_source", "floor_scale", "c1", "c1_se", "I", "mpi", "api"}
    assert "predicted relative gain G" not in printed and not any(
        {"predicted_relative_gain", "gain_lower"} & set(r) for r in s["policies"])
    # issue 64: each simulated value printed without an interval says why
    assert f"Why no interval: {NO_INTERVAL['sim_return']}." in printed
    assert f"Why no interval: {NO_INTERVAL['floor_guard']}." in printed
    for j, r in enumerate(s["policies"]):
        assert r["deployed_fine_tuned"] == g["accepted"][j]
        assert r["predicted_gain"] == pytest.approx(gain[:, j].min())
        assert r["predicted_gain_mean"] == pytest.approx(gain[:, j].mean())
        assert r["real_gain"] == (r["I"] if g["accepted"][j] else 0.0)
        what = "deployed" if g["accepted"][j] else "kept (start)"
        assert f"| {r['policy']} | {what} | {r['predicted_gain']:+.3f} |" in printed


def test_improve_guard_over_snapshots_deploys_the_members_choice(pointmass_checkpoint,
                                                                 tmp_path):
    """--guard-snapshots: the actor is kept every tenth of the iterations; per policy the
    snapshot choose_by_members picks from the recorded member values deploys (the start
    where none is eligible), and the zoo holds it with its own paired real return."""
    from rl2s_jax.improve.finetune import choose_by_members, member_values
    from rl2s_jax.model.simulator import start_pool
    from rl2s_jax.train.checkpoint import load_simulator

    run = pointmass_checkpoint
    before = pol.index_params(policies_for(load_dataset(run["data"])), np.array([0, 1, 2, 3]))
    out = tmp_path / "snapshots"
    margin = 0.0
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--out",
                     str(out), "--iterations", "20", "--episodes", "2", "--quiet",
                     "--guard-margin", str(margin), "--guard-snapshots", "--guard-episodes",
                     "2", *SMALL]) == 0
    s = json.loads((out / "summary.json").read_text())
    g = s["guard"]
    values = np.asarray(g["sim_value_snapshots"])
    assert values.shape[0] == 11 and values.shape[2] == 4 and g["snapshot_every"] == 2
    index = np.asarray(g["snapshot"])
    assert index.tolist() == choose_by_members(values, margin).tolist()
    assert 0 < index.max() and index.min() < 10, "expected a mix of snapshots and starts"
    assert g["accepted"] == (index > 0).tolist()
    assert g["snapshot_iteration"] == (2 * index).tolist()
    zoo = zoo_mod.load_zoo(str(out))
    for j, k in enumerate(index):
        same = [np.array_equal(a[j], b[j]) for a, b in zip(
            jax.tree_util.tree_leaves(zoo.params), jax.tree_util.tree_leaves(before),
            strict=True)]
        assert all(same) == (k == 0)  # the start kept, or a fine-tuned snapshot
        r = s["policies"][j]
        assert zoo.returns[j] == pytest.approx(g["c1"][j], rel=1e-6)
        if k == 0:
            assert g["c1"][j] == r["c0"] and g["I"][j] == 0.0
        shown = values[max(k, 1) if k else 10]  # the deployed snapshot's, else the final's
        assert r["predicted_gain"] == pytest.approx(
            np.min((shown[:, j] - values[0, :, j]) / np.abs(values[0, :, j])))
        if k == 10:  # the final actor: the same paired episodes as the final's C1
            assert g["c1"][j] == pytest.approx(r["c1"], rel=1e-4)
        assert zoo.origins[j]["deployed"] == (
            "start (the guard kept it)" if k == 0
            else f"fine-tuned (snapshot after {2 * k} iterations)")
    assert g["mpi"] == pytest.approx(min(g["I"]))
    assert "over snapshots every 2 iterations" in (out / "summary.md").read_text()
    # the zoo holds the chosen snapshots: valued again as the guard valued them (each policy
    # as if alone, the guard's key: run_improve's measurement key folded with 1), each gives
    # the members' values recorded for its chosen snapshot
    ds = load_dataset(run["data"])
    key = jax.random.fold_in(jax.random.split(jax.random.PRNGKey(0))[1], 1)
    again = member_values(load_simulator(run["ckpt"]), "pointmass", zoo.params, start_pool(ds),
                          key, n_episodes=2, horizon=ds.meta["episode_length"],
                          gamma=ds.meta["gamma"])
    np.testing.assert_allclose(again, values[index, :, np.arange(4)].T, rtol=1e-4, atol=1e-4)


def test_improve_refuses_bad_input_before_work(pointmass_checkpoint, tmp_path, capsys):
    run = pointmass_checkpoint
    out = tmp_path / "never"

    def refused(*extra, data=run["data"], ckpt=run["ckpt"]):
        rc = cli.main(["improve", "--ckpt", ckpt, "--data", data, "--out", str(out),
                       "--iterations", "5", "--quiet", *extra])
        return rc, capsys.readouterr().err

    rc, err = refused(ckpt=str(tmp_path / "missing"))
    assert rc == 2 and "ckpt" in err and "missing" in err
    rc, err = refused(data=str(tmp_path / "missing.npz"))
    assert rc == 2 and "data" in err
    rc, err = refused("--policies", "0,4")
    assert rc == 2 and "policies: index 4 out of range" in err and "0..3" in err
    rc, err = refused("--policies", "1,1")
    assert rc == 2 and "distinct" in err
    rc, err = refused("--set", "nope=3")
    assert rc == 2 and "nope" in err and "kl_weight" in err
    rc, err = refused("--set", "kl_weight=-1")
    assert rc == 2 and "kl_weight" in err
    rc, err = refused("--guard-margin", "-0.5")
    assert rc == 2 and "guard-margin" in err
    rc, err = refused("--no-guard", "--guard-snapshots")
    assert rc == 2 and "no-guard: turns the deployment guard off; drop --guard-snapshots" in err
    rc, err = refused("--no-guard", "--guard-margin", "0.1")
    assert rc == 2 and "drop --guard-margin" in err
    rc, err = refused("--no-guard", "--guard-floor-scale", "0.5")
    assert rc == 2 and "drop --guard-floor-scale" in err
    rc, err = refused("--guard-floor-scale", "-1")
    assert rc == 2 and "guard-floor-scale: expected a finite float >= 0" in err
    # data of another task
    ds = load_dataset(run["data"])
    other = ds.replace(meta={**ds.meta, "task": "twomass"})
    path = tmp_path / "other.npz"
    save_dataset(str(path), other)
    rc, err = refused(data=str(path))
    assert rc == 2 and "twomass" in err and "pointmass" in err
    with pytest.raises(SystemExit):
        cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--out", str(out),
                  "--policies", "a,b"])
    assert not os.path.exists(out)


def test_improve_guard_floor_comes_from_the_training_summary(pointmass_checkpoint, tmp_path,
                                                             monkeypatch):
    """`rl2s improve` takes the guard's floor from the summary.json `rl2s train` wrote beside
    the checkpoint: the training MVD, where measured at the guard's horizon and gamma. A floor
    no predicted gain can clear keeps every start; one measured at another horizon is not
    used (floor 0, the margin's decisions). --guard-floor-scale K (or the --recipe's) scales
    the MVD: K 1e-6 gives floor 1 and the decisions of margin and floor 1."""
    import shutil

    from rl2s_jax.improve import recipes

    run = pointmass_checkpoint
    ds = load_dataset(run["data"])
    horizon = int(ds.meta.get("episode_length") or PointMass().episode_length)
    gamma = float(ds.meta.get("gamma") or 0.999)
    decisions = {}
    # the recipe's scale where no flag is given (a task's change, as a calibration would add)
    monkeypatch.setitem(recipes.IMPROVE_RECIPE_TASKS["control"], "pointmass",
                        {"guard_floor_scale": 1e-6})
    recipe = ["--recipe", "control", "--branch-length", "5", "--uncertainty-penalty", "0",
              "--no-measure"]
    for name, h, extra in (("comparable", horizon, []), ("other_horizon", horizon + 7, []),
                           ("scaled", horizon, ["--guard-floor-scale", "1e-6"]),
                           ("recipe", horizon, recipe)):
        run_dir = tmp_path / name
        shutil.copytree(run["ckpt"], run_dir / "checkpoints")
        (run_dir / "summary.json").write_text(json.dumps(
            {"mvd_train": 1e6, "steps": None,
             "vd_measured_by": {"horizon": h, "gamma": gamma}}))
        out = tmp_path / f"out_{name}"
        assert cli.main(["improve", "--ckpt", str(run_dir / "checkpoints"), "--data",
                         run["data"], "--policies", "0,3", "--out", str(out), "--iterations",
                         "20", "--episodes", "2", "--quiet", "--guard-episodes", "4",
                         *SMALL, *extra]) == 0
        g = json.loads((out / "summary.json").read_text())["guard"]
        v0, v1 = np.asarray(g["sim_value_start"]), np.asarray(g["sim_value_tuned"])
        floor = 1.0 if name in ("scaled", "recipe") else 0.0
        decisions[name] = (g, np.all(v1 - v0 > np.maximum(0.02 * np.abs(v0), floor),
                                     axis=0).tolist())
    g, _ = decisions["comparable"]
    assert g["floor"] == 1e6 and "summary.json" in g["floor_source"]
    assert g["accepted"] == [False, False]
    g, by_margin = decisions["other_horizon"]
    assert g["floor"] == 0.0 and "horizon" in g["floor_source"]
    assert g["accepted"] == by_margin
    md = (tmp_path / "out_scaled" / "summary.md").read_text()  # what the user reads
    assert "Deployment guard (margin 0.02, floor 1: 1e-06 x the training MVD in" in md
    for name in ("scaled", "recipe"):
        g, by_floor = decisions[name]
        assert g["floor_scale"] == 1e-6 and g["floor"] == pytest.approx(1.0), name
        assert g["floor_source"].startswith("1e-06 x the training MVD"), name
        assert g["accepted"] == by_floor, name


def test_checkpoint_floor_reads_the_summary_beside_the_checkpoint(tmp_path):
    from rl2s_jax.app.improvement import checkpoint_floor

    ckpt = tmp_path / "run" / "checkpoints"
    ckpt.mkdir(parents=True)
    assert checkpoint_floor(str(ckpt), None, 100, 0.999)[0] == 0.0  # no summary
    (tmp_path / "run" / "summary.json").write_text(json.dumps(
        {"mvd_train": 12.5, "steps": 300, "vd_measured_by": {"horizon": 100, "gamma": 0.999}}))
    assert checkpoint_floor(str(ckpt) + "/", None, 100, 0.999)[0] == 12.5
    assert checkpoint_floor(str(ckpt), 300, 100, 0.999)[0] == 12.5
    value, why = checkpoint_floor(str(ckpt), 200, 100, 0.999)  # an earlier step: not its MVD
    assert value == 0.0 and "step 300" in why
    assert checkpoint_floor(str(ckpt), None, 1000, 0.999)[0] == 0.0
    assert checkpoint_floor(str(ckpt), None, 100, 0.99)[0] == 0.0


def _calibration_file(path, **fields):
    cal = {"task": "pointmass", "level": 0.9, "q": 1.0, "floor": 0.01, "n": 20, **fields}
    path.write_text(json.dumps(cal))
    return str(path)


def test_improve_interval_guard_deploys_where_the_lower_end_is_above_zero(
        pointmass_checkpoint, tmp_path, capsys):
    """--guard interval on a hand-made calibration: per policy G = mean over the elite members
    of (v1 - v0) / |mean v0|, its lower end G - q (sd + floor) (NumPy, from the recorded member
    values); exactly the policies whose lower end is above 0 deploy, the zoo holds the start
    elsewhere; the summary and the printed report state G, the lower end and the calibration."""
    run = pointmass_checkpoint
    before = pol.index_params(policies_for(load_dataset(run["data"])), np.arange(4))
    q, floor = 1.5, 0.01
    cal = _calibration_file(tmp_path / "cal.json", q=q, floor=floor)
    out = tmp_path / "interval"
    assert cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--out", str(out),
                     "--iterations", "20", "--episodes", "2", "--quiet", "--guard-episodes",
                     "4", "--guard", "interval", "--guard-calibration", cal, *SMALL]) == 0
    printed = capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    g = s["guard"]
    v0, v1 = np.asarray(g["sim_value_start"]), np.asarray(g["sim_value_tuned"])
    rel = (v1 - v0) / np.abs(v0.mean(0))
    gain, sd = rel.mean(0), rel.std(0, ddof=1)
    lower = gain - q * (sd + floor)
    # a policy with G > 0 that its interval keeps: the lower end decides, not G alone
    assert 0 < (lower > 0).sum() < 4 and ((gain > 0) & (lower <= 0)).any(), (gain, lower)
    assert g["kind"] == "interval" and g["accepted"] == (lower > 0).tolist()
    assert g["gain"] == pytest.approx(gain.tolist()) and g["gain_lower"] == pytest.approx(
        lower.tolist())
    assert g["calibration"] == {"level": 0.9, "q": q, "floor": floor, "n": 20,
                                "source": [cal], "q_infinite": False}
    zoo = zoo_mod.load_zoo(str(out))
    for j, r in enumerate(s["policies"]):
        assert r["deployed_fine_tuned"] == bool(lower[j] > 0)
        assert r["predicted_relative_gain"] == pytest.approx(gain[j])
        assert r["gain_lower"] == pytest.approx(lower[j])
        assert r["real_gain"] == (r["I"] if lower[j] > 0 else 0.0)
        same = all(np.array_equal(a[j], b[j]) for a, b in zip(
            jax.tree_util.tree_leaves(zoo.params), jax.tree_util.tree_leaves(before),
            strict=True))
        assert same == (not lower[j] > 0)
        what = "deployed" if lower[j] > 0 else "kept (start)"
        assert f"| {r['policy']} | {what} | {gain[j]:+.3f} | {lower[j]:+.3f} |" in printed
    assert "Deployment guard: interval (deploy where the lower end" in printed
    assert f"q {q:.3g}, floor {floor:.3g}, n 20 calibration policies, from {cal}" in printed
    assert NO_INTERVAL["floor_guard"] not in printed and NO_INTERVAL["sim_return"] in printed


def test_improve_interval_guard_refused_at_the_door(pointmass_checkpoint, tmp_path, capsys):
    """Each wrong use of --guard interval / --guard-calibration: status 2, one line naming
    the flag and what was expected, nothing written."""
    run = pointmass_checkpoint
    out = tmp_path / "never"
    good = _calibration_file(tmp_path / "good.json")
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    test_split = tmp_path / "test_split.json"
    test_split.write_text(json.dumps({"task": "pointmass", "policy_split": "zoo",
                                      "improvement": {}}))
    cases = (
        (["--guard", "interval"], "guard: 'interval' needs --guard-calibration FILE"),
        (["--guard", "interval", "--guard-calibration", str(tmp_path / "nope.json")],
         "guard-calibration: no such file"),
        (["--guard", "interval", "--guard-calibration", good, "--no-guard"],
         "no-guard: turns the deployment guard off; drop --guard interval"),
        (["--guard", "interval", "--guard-calibration", good, "--guard-margin", "0.1"],
         "--guard-margin is the floor guard's, drop it"),
        (["--guard-calibration", good], "guard-calibration: the interval guard's calibration; "
                                        "add --guard interval"),
        (["--guard", "interval", "--guard-calibration",
          _calibration_file(tmp_path / "hopper.json", task="hopper")],
         "guard-calibration: " + str(tmp_path / "hopper.json") + " calibrates task 'hopper', "
         "the simulator models 'pointmass'"),
        (["--guard", "interval", "--guard-calibration", str(bad_json)],
         "is not readable JSON"),
        (["--guard", "interval", "--guard-calibration",
          _calibration_file(tmp_path / "neg.json", q=-1.0)], "expected level in (0, 1), q >= 0"),
        (["--guard", "interval", "--guard-calibration", str(test_split)],
         "guard-calibration: expected a 'pointmass' run on the validation split"),
    )
    for extra, msg in cases:
        rc = cli.main(["improve", "--ckpt", run["ckpt"], "--data", run["data"], "--out",
                       str(out), "--iterations", "5", "--quiet", *extra])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and len(err.strip().splitlines()) == 1, (extra, err)
    rc = cli.main(["improve", "--physics", "nominal", "--data", run["data"], "--out", str(out),
                   "--guard", "interval", "--guard-calibration", good])
    assert rc == 2 and "guard: 'interval' is calibrated on learned" in capsys.readouterr().err
    assert not os.path.exists(out)
