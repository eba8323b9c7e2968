"""The hybrid (issue 62 item 3): calibrated physics plus a residual learned through train_step.

Measured data: C-MuJoCo Hopper under gravity tilted forward by GX m/s^2 (a constant push on
every body in proportion to its mass, as a slope or a steady wind would give): a force the
physics candidates have no parameter for. The physics is calibrated on it (``identify``), the
hybrid trained through the door (``train_hybrid``, i.e. `rl2s train --physics --method bc`)
and loaded back from its checkpoint alone (``load_hybrid``)."""

import copy
import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

GX = 2.0
TRAIN_IDS = [4, 7, 16, 21]


@pytest.fixture(scope="module")
def pm():
    from rl2s_jax.physics.mjx_model import physics_model

    return physics_model("hopper")


def _tilted(pm, seed: int, per_policy: int):
    from rl2s_jax.physics.measured import collect_measured
    from rl2s_jax.policy.policy import index_params
    from rl2s_jax.zoo.zoo import load_zoo

    mj = copy.deepcopy(pm.mj)
    mj.opt.gravity[0] = GX
    zoo = load_zoo("hopper")
    return collect_measured(dataclasses.replace(pm, mj=mj),
                            index_params(zoo.params, TRAIN_IDS), transitions_per_policy=per_policy,
                            episode_length=100, seed=seed, policy_names=zoo.policy_names(TRAIN_IDS),
                            source={"zoo": "hopper", "zoo_ids": TRAIN_IDS})


@pytest.fixture(scope="module")
def files(pm, tmp_path_factory):
    """Training and held-out data (other episodes of the same policies), calibrated.json."""
    from rl2s_jax.data.dataset import save_dataset
    from rl2s_jax.physics.identify import FitConfig, identify

    root = tmp_path_factory.mktemp("hybrid")
    train, held = _tilted(pm, 2, 300), _tilted(pm, 5, 100)
    paths = {"train": str(root / "train.npz"), "held": str(root / "held.npz"),
             "calibrated": str(root / "calibrated.json"), "out": str(root / "run")}
    save_dataset(paths["train"], train)
    save_dataset(paths["held"], held)
    found = identify(pm, train, FitConfig(rows=128, bootstrap=20))
    with open(paths["calibrated"], "w") as f:
        json.dump({"task": "hopper", "xml": pm.xml_path, "n_frames": pm.n_frames,
                   "theta": [float(x) for x in found["theta"]],
                   "delays": [int(d) for d in found["delays"]],
                   "labels": [c.label for c in pm.candidates]}, f)
    return paths


def test_bad_physics_is_refused_at_the_door(files, tmp_path, capsys):
    """Missing calibrated.json, another task's, an adversarial method, a learned reward, test
    evaluation during training: each one line naming the field, before any training work."""
    from rl2s_jax import cli
    from rl2s_jax.app.specs import TrainSpec
    from rl2s_jax.app.training import run_training, train_hybrid

    out = str(tmp_path / "run")
    rc = cli.main(["train", "--data", files["train"], "--physics", str(tmp_path / "none.json"),
                   "--method", "bc", "--steps", "1", "--out", out, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("rl2s train: error: physics: no such file")
    with pytest.raises(FileNotFoundError, match="physics: no such file .*calibrated.json"):
        train_hybrid(files["train"], str(tmp_path / "none.json"), 1, out)
    other = tmp_path / "walker.json"
    content = json.load(open(files["calibrated"]))
    other.write_text(json.dumps({**content, "task": "walker2d"}))
    with pytest.raises(ValueError, match="physics: .* calibrates task 'walker2d' but the data "
                                         "is task 'hopper'"):
        train_hybrid(files["train"], str(other), 1, out)
    for method in ("rl2s", "gail", "rl2s-bc"):
        with pytest.raises(ValueError, match=f"method: a hybrid .* '{method}' rolls"):
            run_training(TrainSpec(data=files["train"], method=method, steps=1, out=out,
                                   set={"physics": files["calibrated"]}))
    with pytest.raises(ValueError, match="reward: a hybrid takes the task's reward_fn"):
        train_hybrid(files["train"], files["calibrated"], 1, out,
                     overrides={"reward": "learned"})
    with pytest.raises(ValueError, match="eval_data: training's evaluation would roll the "
                                         "residual model alone"):
        train_hybrid(files["train"], files["calibrated"], 1, out, eval_data=files["held"])
    assert not (tmp_path / "run" / "checkpoints").exists()  # refused before any work


def test_hybrid_config_carries_the_delays_and_turns_vd_off(files, tmp_path):
    """A calibrated delay needs the actions that far back in the rollouts' history: the
    members see at least max(delays) past actions; the VD measurement is off."""
    from rl2s_jax.app.training import make_config
    from rl2s_jax.data.dataset import load_dataset

    ds = load_dataset(files["train"])
    delayed = tmp_path / "delayed.json"
    content = json.load(open(files["calibrated"]))
    delayed.write_text(json.dumps({**content, "delays": [0, 2, 0]}))
    cfg = make_config(ds, "bc", "cpu", overrides={"physics": str(delayed)})
    assert (cfg.dynamics.action_history, cfg.vd.every, cfg.physics) == (2, 0, str(delayed))
    cfg = make_config(ds, "bc", "cpu", overrides={"physics": str(delayed), "action_history": 3})
    assert cfg.dynamics.action_history == 3
    assert make_config(ds, "bc", "cpu").physics is None
    delayed.write_text(json.dumps({**content, "delays": [0, 2]}))
    with pytest.raises(ValueError, match=r"physics: .* has delays \[0, 2\]; the data has 3"):
        make_config(ds, "bc", "cpu", overrides={"physics": str(delayed)})


@pytest.fixture(scope="module")
def hybrid(files):
    """The hybrid trained through the door and loaded back from its checkpoint alone."""
    from rl2s_jax.app.training import train_hybrid
    from rl2s_jax.physics.hybrid import load_hybrid

    summary = train_hybrid(files["train"], files["calibrated"], 40, files["out"],
                           profile="cpu", quiet=True, log=lambda *_: None)
    sim, meta = load_hybrid(summary["checkpoint"])
    return {"sim": sim, "meta": meta, "summary": summary}


@pytest.fixture(scope="module")
def stepped(files, hybrid):
    """The held-out rows stepped by the hybrid and by its members alone (base None), means
    and noise-scale-1 samples: one compiled program."""
    import jax
    import jax.numpy as jnp

    from rl2s_jax.data.dataset import load_dataset

    held = load_dataset(files["held"])
    sim = hybrid["sim"].replace(noise_scale=1.0, obs_clip=1e3)  # no clip: a plain composition
    plain = sim.replace(base=None)
    key = jax.random.PRNGKey(0)
    out = jax.jit(lambda s, p, o, a, k: (s.mean(o, a), p.mean(o, a), s.dynamics(o, a, k),
                                         p.dynamics(o, a, k)))(
        sim, plain, *(jnp.asarray(np.asarray(x), jnp.float32) for x in (held.obs, held.action)),
        key)
    return held, dict(zip(("mean", "plain_mean", "sample", "plain_sample"),
                          (np.asarray(x, np.float64) for x in out), strict=True))


def _physics(pm, files, ds):
    """The calibrated physics' next states of a Dataset's rows: C MuJoCo, float64."""
    from rl2s_jax.physics.hybrid import calibrated_model
    from rl2s_jax.physics.mjx_model import delayed_actions
    from rl2s_jax.physics.residuals import predict

    _, theta, delays = calibrated_model(json.load(open(files["calibrated"])))
    action = delayed_actions(np.asarray(ds.action), np.asarray(ds.episode_id),
                             np.asarray(ds.t), delays)
    return predict(pm, theta, np.asarray(ds.obs, np.float64), action)


@pytest.mark.slow
def test_hybrid_step_is_physics_plus_residual(pm, files, stepped):
    """mean and sample: C-MuJoCo physics + (the members' own step - obs), in NumPy; the MJX
    physics it steps agrees with the C engine to float32 round-off."""
    held, out = stepped
    physics, obs = _physics(pm, files, held), np.asarray(held.obs, np.float64)
    np.testing.assert_allclose(out["mean"], physics + out["plain_mean"] - obs, atol=2e-4)
    np.testing.assert_allclose(out["sample"], physics + out["plain_sample"] - obs, atol=2e-4)
    assert np.abs(out["sample"] - out["mean"]).max() > 1e-3  # the sample is not the mean


@pytest.mark.slow
def test_hybrid_beats_the_calibrated_physics_on_held_out_episodes(pm, files, stepped):
    """The planted push is beyond the candidates: the calibrated physics keeps a one-step
    error that the residual takes most of (per dim in the data's std of next_obs - obs)."""
    from rl2s_jax.data.dataset import load_dataset

    held, out = stepped
    train = load_dataset(files["train"])
    scale = np.std(np.asarray(train.next_obs, np.float64) - np.asarray(train.obs), 0)
    nxt = np.asarray(held.next_obs, np.float64)
    rmse = lambda pred: float(np.sqrt(np.mean(((pred - nxt) / scale) ** 2)))
    physics, hybrid = rmse(_physics(pm, files, held)), rmse(out["mean"])
    assert physics > 0.02  # the push shows in the calibrated physics
    assert hybrid < 0.6 * physics, (hybrid, physics)


@pytest.mark.slow
def test_checkpoint_round_trips_as_the_hybrid(files, hybrid):
    """The checkpoint holds the calibrated.json (meta) and its path (config); it loads as the
    hybrid with load_hybrid and is refused by the plain loaders (its members alone are only the
    residual)."""
    from rl2s_jax.train.checkpoint import (
        CheckpointError,
        load_checkpoint,
        load_meta,
        load_simulator,
    )

    sim, meta, summary = hybrid["sim"], hybrid["meta"], hybrid["summary"]
    assert meta["physics"] == json.load(open(files["calibrated"]))
    assert meta["config"]["physics"] == files["calibrated"]
    assert summary["config"]["physics"] == files["calibrated"] and summary["method"] == "bc"
    assert sim.base is not None and sim.task == "hopper"
    for load in (load_checkpoint, load_simulator):
        with pytest.raises(CheckpointError, match="is a hybrid .*physics.hybrid.load_hybrid"):
            load(summary["checkpoint"])
    assert load_meta(summary["checkpoint"])["physics"] == meta["physics"]


@pytest.mark.slow
def test_fit_hybrid_is_the_door_in_memory(pm, files, hybrid):
    """fit_hybrid with the door's config and seed fits the same members as `rl2s train
    --physics`; their normaliser's delta statistics are the residual's (next_obs minus the
    calibrated physics, over the training rows), not those of next_obs - obs."""
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.physics.hybrid import fit_hybrid
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import heldout_mask
    from rl2s_jax.zoo.zoo import policies_for

    ds, door = load_dataset(files["train"]), hybrid["sim"]
    cfg = TrainConfig.from_dict(hybrid["summary"]["config"])
    sim = fit_hybrid(ds, policies_for(ds), files["calibrated"], steps=40, config=cfg)
    assert sim.base is not None and sim.action_history == door.action_history
    for a, b in zip(jax_leaves(sim.gen), jax_leaves(door.gen), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    train = ~heldout_mask(ds, cfg.holdout_frac)
    resid = np.asarray(ds.next_obs, np.float64) - _physics(pm, files, ds)
    np.testing.assert_allclose(np.asarray(sim.norm.delta_mean), resid[train].mean(0),
                               atol=1e-5)
    np.testing.assert_allclose(np.asarray(sim.norm.delta_std),
                               np.maximum(resid[train].std(0), 1e-6), rtol=1e-3, atol=1e-6)


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


@pytest.mark.heavy
def test_rl2s_evaluate_scores_the_hybrid_in_a_fresh_process(files, hybrid, stepped, tmp_path):
    """`rl2s evaluate --ckpt` on the hybrid's checkpoint in a fresh process: it scores the
    hybrid, whose one-step error on the held-out rows is the one computed here (not the
    residual model's alone). Heavy: its MJX rollouts compile for minutes on the CPU."""
    report = tmp_path / "eval.json"
    out = subprocess.run([sys.executable, "-m", "rl2s_jax.cli", "evaluate", "--ckpt",
                          hybrid["summary"]["checkpoint"], "--data", files["held"],
                          "--episodes", "2", "--horizon", "5", "--bootstrap", "0", "--json",
                          str(report)], capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(report.read_text())
    held, stepped_rows = stepped
    delta = np.asarray(held.next_obs, np.float64) - np.asarray(held.obs, np.float64)
    scale = np.maximum(delta.std(0), 1e-6)
    want = np.mean(((stepped_rows["mean"] - np.asarray(held.next_obs)) / scale) ** 2)
    np.testing.assert_allclose(r["heldout_mse"], want, rtol=1e-3)
    assert r["method"] == "bc" and np.isfinite(r["sim_value"]).all()


@pytest.mark.heavy
def test_a_delayed_hybrid_steps_the_physics_with_the_late_actions(pm, files):
    """A calibrated delay (thigh actuator, 2 steps): the hybrid's members see 2 past actions,
    and its physics takes that actuator's action 2 steps back from the rollout's history (0
    before the episode's start), as the residual's targets had it. Heavy: another MJX
    program (with a history) to compile."""
    import jax
    import jax.numpy as jnp

    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.model.history import logged_history
    from rl2s_jax.physics.hybrid import fit_hybrid
    from rl2s_jax.physics.mjx_model import delayed_actions
    from rl2s_jax.physics.residuals import predict
    from rl2s_jax.zoo.zoo import policies_for

    delays = [0, 2, 0]
    content = {**json.load(open(files["calibrated"])), "delays": delays}
    ds, held = load_dataset(files["train"]), load_dataset(files["held"])
    sim = fit_hybrid(ds, policies_for(ds), content, steps=2)
    assert sim.action_history == 2 and sim.base is not None
    rows = np.r_[np.flatnonzero(np.asarray(held.t) < 2)[:8], np.arange(2, len(held.t), 13)]
    hist = logged_history(held, rows, obs_history=0, action_history=2,
                          episode_length=sim.episode_length)
    obs, act = (np.asarray(x, np.float32)[rows] for x in (held.obs, held.action))
    got, members = (np.asarray(x, np.float64) for x in jax.jit(
        lambda s, p, o, a, h: (s.mean(o, a, h), p.mean(o, a, h)))(
            sim, sim.replace(base=None), jnp.asarray(obs), jnp.asarray(act), hist))
    late = delayed_actions(np.asarray(held.action), np.asarray(held.episode_id),
                           np.asarray(held.t), delays)[rows]
    physics = predict(pm, np.asarray(content["theta"]), obs.astype(np.float64), late)
    np.testing.assert_allclose(got, physics + members - obs, atol=2e-4)
    on_time = predict(pm, np.asarray(content["theta"]), obs.astype(np.float64), act)
    assert np.abs(got - (on_time + members - obs)).max() > 1e-3  # the delay acts


def test_calibrated_json_from_before_the_margin_candidates_still_loads(pm, tmp_path):
    """A calibrated.json written before geom_margin became a candidate (its labels a subset of
    the model's): its values land on their own candidates, the new ones at their nominal
    (theta 0), through both loaders; labels of another model are still refused."""
    from rl2s_jax.physics.hybrid import calibrated_model
    from rl2s_jax.physics.physics_simulator import physics_simulator

    old = [c.label for c in pm.candidates if c.name != "geom_margin"]
    assert len(old) < len(pm.candidates)
    theta = [0.01 * (i + 1) for i in range(len(old))]
    content = {"task": "hopper", "xml": pm.xml_path, "n_frames": pm.n_frames, "theta": theta,
               "delays": [0, 0, 0], "labels": old}
    _, full, _ = calibrated_model(content)
    for c, th in zip(pm.candidates, full, strict=True):
        assert th == (theta[old.index(c.label)] if c.label in old else 0.0), c.label
    path = tmp_path / "old.json"
    path.write_text(json.dumps(content))
    assert list(physics_simulator(str(path), "hopper").theta) == list(full)
    with pytest.raises(ValueError, match="not this model's"):
        calibrated_model({**content, "labels": old[:-1] + ["body_mass[nothing]"]})
    # theta null (the nominal model) with the model's own labels still loads
    path.write_text(json.dumps({**content, "theta": None,
                                "labels": [c.label for c in pm.candidates]}))
    assert not any(physics_simulator(str(path), "hopper").theta)


def test_calibrated_model_checks_every_field_as_evaluate_does(pm):
    """hybrid.calibrated_model loads through physics_simulator.checked_model: a bad field is
    refused by name (before: a NaN theta or a bad n_frames went through to the model)."""
    from rl2s_jax.physics.hybrid import calibrated_model

    good = {"task": "hopper", "xml": pm.xml_path, "n_frames": pm.n_frames,
            "theta": [0.0] * len(pm.candidates), "delays": [0, 0, 0],
            "labels": [c.label for c in pm.candidates]}
    cal, theta, delays = calibrated_model(good)
    assert cal.n_frames == pm.n_frames and theta.shape == (len(pm.candidates),)
    assert delays.tolist() == [0, 0, 0]
    bad = {"theta": [float("nan")] * len(pm.candidates), "n_frames": 0,
           "task": "no_such_task", "collisions": ["foot"], "delays": [0, 0]}
    match = {"theta": "theta: expected finite", "n_frames": "n_frames: expected an int",
             "task": "task: expected one of", "collisions": "collisions: expected",
             "delays": "delays"}
    for field, value in bad.items():
        with pytest.raises(ValueError, match=match[field]):
            calibrated_model({**good, field: value})
