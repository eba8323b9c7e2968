"""Checkpoints, exact resume, the stop on divergence, loading in a fresh process, `rl2s train`."""
import json
import os
import re
import shutil
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_train import _policies as _pm_policies  # biased pointmass policies

from rl2s_jax.cli import main
from rl2s_jax.data.collect import collect
from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.train.checkpoint import (
    Checkpointer,
    CheckpointError,
    CheckpointWarning,
    load_checkpoint,
    load_meta,
    load_simulator,
)
from rl2s_jax.train.config import FLAT_NAMES, TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.loop import TrainingDiverged, fit
from rl2s_jax.train.step import init, simulator

CFG = TrainConfig.small(task="pointmass", method="rl2s", vd_horizon=50, vd_every=3)
META = {"data": {"obs_size": 2, "action_size": 1}}


@pytest.fixture(scope="module")
def pm():
    task = get_task("pointmass")
    params = _pm_policies([-2.0, 0.0, 1.0, 2.0])
    ds = collect(task.make_env(), params, key=jax.random.PRNGKey(0), transitions_per_policy=500,
                 envs_per_policy=2, episode_length=task.episode_length, task="pointmass",
                 value_episodes=8, progress=False)
    return ds, params, make_train_data(ds, params, CFG)


def _leaves_equal(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_resume_is_bit_identical(pm, tmp_path):
    _, _, data = pm
    state0 = init(jax.random.PRNGKey(3), CFG, data)
    straight, _ = fit(state0, data, 8, chunk=4, progress=False)

    ck = Checkpointer(tmp_path / "ck")
    half, _ = fit(state0, data, 4, chunk=2, checkpointer=ck, save_every=4, meta=META,
                  progress=False)
    ck.close()
    assert Checkpointer(tmp_path / "ck").steps() == [4]
    ck = Checkpointer(tmp_path / "ck")
    resumed = ck.restore(jax.eval_shape(lambda: init(jax.random.PRNGKey(0), CFG, data)))
    assert int(resumed.step) == 4
    _leaves_equal(resumed, half)
    resumed, _ = fit(resumed, data, 8, chunk=2, checkpointer=ck, save_every=4, meta=META,
                     progress=False)
    ck.close()
    _leaves_equal(resumed, straight)
    assert int(straight.step) == 8 and np.isfinite(np.asarray(straight.vd)).all()


def test_pretrained_then_adversarial_run_resumes_exactly(pm, tmp_path):
    """rl2s with 3 MLE pre-training steps, a critic warm-up step, early stopping and the EMA:
    resumed from a checkpoint inside pre-training (step 2) and from one after the switch
    (step 4), it ends bit-identical to the run that never stopped. (chunk=1: two compiled
    programs, one per phase.)"""
    _, _, data = pm
    cfg = TrainConfig.small(task="pointmass", method="rl2s", vd_horizon=50, vd_every=3,
                            pretrain_steps=3, disc_warmup_steps=1, ema_decay=0.9)
    template = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), cfg, data))
    state0 = init(jax.random.PRNGKey(4), cfg, data)
    straight, m = fit(state0, data, 6, chunk=1, progress=False)
    np.testing.assert_array_equal(np.asarray(m["phase"]), [0, 0, 0, 1, 1, 1])

    ck = Checkpointer(tmp_path / "ck")
    fit(state0, data, 2, chunk=1, checkpointer=ck, save_every=2, meta=META, progress=False)
    resumed = ck.restore(template)
    assert int(resumed.step) == 2
    resumed, _ = fit(resumed, data, 6, chunk=1, checkpointer=ck, save_every=4, meta=META,
                     progress=False)
    _leaves_equal(resumed, straight)
    assert ck.steps() == [2, 4, 6]
    after_switch = ck.restore(template, step=4)
    again, _ = fit(after_switch, data, 6, chunk=1, progress=False)
    ck.close()
    _leaves_equal(again, straight)
    # the saved simulator is the moving average of the members
    _leaves_equal(load_simulator(tmp_path / "ck").gen, straight.ema_gen)


def test_restore_refuses_another_config(pm, tmp_path):
    _, _, data = pm
    ck = Checkpointer(tmp_path / "ck")
    ck.save(init(jax.random.PRNGKey(0), CFG, data), META)
    other = TrainConfig.small(task="pointmass", method="rl2s", vd_horizon=50, batch_size=32)
    with pytest.raises(ValueError, match="batch_size"):
        ck.restore(jax.eval_shape(lambda: init(jax.random.PRNGKey(0), other, data)))
    ck.close()


def test_nan_stops_training_and_keeps_last_good(pm, tmp_path):
    _, _, data = pm
    ck = Checkpointer(tmp_path / "ck")
    state, _ = fit(init(jax.random.PRNGKey(0), CFG, data), data, 4, chunk=2, checkpointer=ck,
                   save_every=100, meta=META, progress=False)
    assert ck.steps() == [4]
    # A corrupt row in every policy's data poisons the next losses.
    bad = data.replace(next_obs=data.next_obs.at[data.policy_start].set(jnp.nan))
    with pytest.raises(TrainingDiverged) as err:
        fit(state, bad, 20, chunk=4, checkpointer=ck, save_every=100, meta=META,
            progress=False)
    e = err.value
    assert 5 <= e.step <= 8, "the first bad step is named (it lies in the first chunk after 4)"
    assert any(q in ("disc_loss", "gen_loss", "d_real", "params") for q in e.quantities)
    assert f"step {e.step}" in str(e) and "non-finite" in str(e)
    assert int(e.last_good.step) == 4 and ck.steps() == [4]
    kept = ck.restore(jax.eval_shape(lambda: init(jax.random.PRNGKey(0), CFG, data)))
    ck.close()
    _leaves_equal(kept, state)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(kept.gen))


def test_checkpoint_loads_in_fresh_process(pm, tmp_path):
    _, _, data = pm
    state, _ = fit(init(jax.random.PRNGKey(1), CFG, data), data, 2, chunk=2, progress=False)
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, META)
    ck.close()
    obs, act = np.array([[0.3, -0.2], [1.0, 0.5]], np.float32), np.array([[0.5], [-1.0]],
                                                                          np.float32)
    here = np.asarray(simulator(state).mean(jnp.asarray(obs), jnp.asarray(act)))
    code = (
        "import json, sys, numpy as np, jax.numpy as jnp\n"
        "from rl2s_jax import load_simulator\n"
        f"sim = load_simulator({str(tmp_path / 'ck')!r})\n"
        f"obs, act = jnp.asarray({obs.tolist()}), jnp.asarray({act.tolist()})\n"
        "print(json.dumps({'task': sim.task, 'mean': np.asarray(sim.mean(obs, act)).tolist(),"
        " 'sample': np.asarray(sim.sample(obs, act, __import__('jax').random.PRNGKey(0)))"
        ".shape}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["task"] == "pointmass" and got["sample"] == [2, 2]
    np.testing.assert_allclose(np.asarray(got["mean"]), here, rtol=1e-6, atol=1e-6)
    assert load_meta(tmp_path / "ck")["config"]["method"] == "rl2s"


def test_a_silu_simulator_loads_as_silu(pm, tmp_path):
    """dynamics.activation "silu" survives save and load: the loaded simulator's means are the
    trained one's (a load that fell back to ReLU would differ)."""
    _, _, data = pm
    cfg = CFG.override({"dynamics.activation": "silu", "vd.every": 0, "method": "bc"})
    state, _ = fit(init(jax.random.PRNGKey(1), cfg, data), data, 2, chunk=2, progress=False)
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, META)
    ck.close()
    obs, act = jnp.asarray([[0.3, -0.2], [1.0, 0.5]]), jnp.asarray([[0.5], [-1.0]])
    loaded = load_simulator(tmp_path / "ck")
    assert "silu" in loaded.gen
    np.testing.assert_allclose(np.asarray(loaded.mean(obs, act)),
                               np.asarray(simulator(state).mean(obs, act)), rtol=1e-6)
    relu = loaded.replace(gen={k: v for k, v in loaded.gen.items() if k != "silu"})
    assert np.abs(np.asarray(relu.mean(obs, act) - loaded.mean(obs, act))).max() > 1e-4



def flat_config(cfg: TrainConfig) -> dict:
    """``cfg`` in the flat saved format of before the groups (no "version")."""
    flat = {v: k for k, v in FLAT_NAMES.items()}
    return {flat.get(k, k): list(v) if isinstance(v, tuple) else v
            for k, v in cfg.to_dotted().items()}

def test_a_checkpoint_saved_before_gen_activation_loads_as_relu(pm, tmp_path):
    """A saved config without gen_activation (checkpoints from before the field) is a ReLU
    run: it loads and gives the saved means, although today's default is SiLU."""
    _, _, data = pm
    assert CFG.dynamics.activation == "relu" and TrainConfig().dynamics.activation == "silu"
    state = init(jax.random.PRNGKey(1), CFG, data)
    ck = Checkpointer(tmp_path / "ck")
    step = ck.save(state, META)
    ck.close()
    path = tmp_path / "ck" / str(step) / "meta" / "metadata"
    meta = json.loads(path.read_text())
    meta["config"] = flat_config(CFG)  # the flat format of before, without the field
    del meta["config"]["gen_activation"]
    path.write_text(json.dumps(meta))
    loaded = load_simulator(tmp_path / "ck")
    assert "silu" not in loaded.gen
    obs, act = jnp.asarray([[0.3, -0.2]]), jnp.asarray([[0.5]])
    np.testing.assert_allclose(np.asarray(loaded.mean(obs, act)),
                               np.asarray(simulator(state).mean(obs, act)), rtol=1e-6)
    ck = Checkpointer(tmp_path / "ck")  # and training resumes it under the ReLU config
    _leaves_equal(ck.restore(state).gen, state.gen)
    ck.close()


def test_load_simulator_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="ckpt"):
        load_simulator(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no saved step"):
        load_simulator(tmp_path / "empty")


# ------------------------------------------------------------------ the CLI on Hopper data


@pytest.fixture(scope="module")
def hopper_train_npz(tmp_path_factory, hopper_train_ds):
    path = tmp_path_factory.mktemp("hopper") / "train.npz"
    save_dataset(path, hopper_train_ds)
    return str(path)


@pytest.mark.parametrize("method", ["rl2s", "gail", "bc", "rl2s-bc"])
def test_cli_train_each_method_on_hopper(hopper_train_npz, tmp_path, method, capsys):
    out = tmp_path / method
    rc = main(["train", "--data", hopper_train_npz, "--method", method, "--steps", "2",
               "--out", str(out), "--profile", "cpu", "--quiet", "--set", "vd_horizon=20",
               "--set", "vd_every=2"])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 2 and summary["method"] == method
    assert len(summary["policies"]) == 17
    n_sel = 17 if method in ("gail", "bc") else 5  # max(2, ceil(0.25 * 17))
    assert len(summary["selected"]) == n_sel
    assert np.isfinite(summary["avd_train"]) and summary["mvd_train"] >= summary["avd_train"]
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    assert "AVD" in capsys.readouterr().out
    assert load_simulator(out / "checkpoints").task == "hopper"
    if method == "bc":  # resume: the same directory continues to the new total
        rc = main(["train", "--data", hopper_train_npz, "--method", method, "--steps", "3",
                   "--out", str(out), "--profile", "cpu", "--quiet", "--set",
                   "vd_horizon=20", "--set", "vd_every=2"])
        assert rc == 0
        rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
        assert [r["step"] for r in rows] == [1, 2, 3]
        assert "resuming" in capsys.readouterr().out


def test_cli_train_bad_input(hopper_train_npz, tmp_path, capsys):
    rc = main(["train", "--data", str(tmp_path / "missing.npz"), "--steps", "1", "--out",
               str(tmp_path / "o")])
    assert rc == 2 and "data" in capsys.readouterr().err
    rc = main(["train", "--data", hopper_train_npz, "--steps", "1", "--out",
               str(tmp_path / "o"), "--set", "hidden=3"])
    err = capsys.readouterr().err
    assert rc == 2 and "hidden" in err and "unknown config field" in err
    rc = main(["train", "--data", hopper_train_npz, "--steps", "1", "--out",
               str(tmp_path / "o"), "--eps", "1.5"])
    assert rc == 2 and "eps" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "o" / "checkpoints" / "1")


def test_diagnose_a_saved_simulator(pm, tmp_path):
    """`diagnose(ckpt=...)` tests the causes on the checkpoint's residuals, not the base model's."""
    from rl2s_jax.app.diagnosis import diagnose
    from rl2s_jax.diagnose.model import ModelSpec

    ds, _, data = pm
    ck = Checkpointer(tmp_path / "ck")
    fit(init(jax.random.PRNGKey(0), CFG, data), data, 2, chunk=2, checkpointer=ck,
        save_every=2, meta=META, progress=False)
    ck.close()
    kw = dict(seeds=(0,), base_spec=ModelSpec(steps=100), plots=False, log=lambda s: None)
    from_ckpt = diagnose(ds, ckpt=str(tmp_path / "ck"), **kw)
    own = diagnose(ds, **kw)
    assert from_ckpt["residuals_from"].startswith("checkpoint")
    assert "policies are not available" in from_ckpt["value_views"]  # no zoo in meta.source
    # A 2-step simulator is far worse than the base model fitted for 100 updates.
    assert from_ckpt["gaps"]["overall"]["rmse"] > own["gaps"]["overall"]["rmse"]
    # The per-dim error is exactly the checkpoint's on the held-out rows.
    from rl2s_jax.data.episodes import from_dataset, split_episodes

    eps = from_dataset(ds)
    fit_eps, held_eps = split_episodes(eps, 0.3, 0)
    held = eps.rows(held_eps)
    sim = load_simulator(str(tmp_path / "ck"))
    pred = np.asarray(sim.mean(eps.obs[held].astype(np.float32),
                               eps.action[held].astype(np.float32)), np.float64)
    resid = (eps.next_obs[held] - pred) / eps.delta[eps.rows(fit_eps)].std(0)
    np.testing.assert_allclose([d["rmse"] for d in from_ckpt["gaps"]["by_dim"]],
                               np.sqrt((resid ** 2).mean(0)), rtol=1e-3)
    # The gain is also stated against the saved simulator itself, and the extension is
    # trained by the checkpoint's method.
    np.testing.assert_allclose(from_ckpt["gain"]["saved"]["heldout_mse"], (resid ** 2).mean(),
                               rtol=2e-3)
    assert CFG.method in from_ckpt["extension"]["trained_by"]
    assert "saved" not in own["gain"]


# ------------------------------------------------------------------ broken checkpoints


@pytest.fixture(scope="module")
def saved_steps(pm, tmp_path_factory):
    """A checkpoint directory with steps 2 and 4, and the TrainStates saved there."""
    _, _, data = pm
    root = tmp_path_factory.mktemp("steps") / "ck"
    ck = Checkpointer(root)
    s2, _ = fit(init(jax.random.PRNGKey(5), CFG, data), data, 2, chunk=2, checkpointer=ck,
                save_every=2, meta=META, progress=False)
    s4, _ = fit(s2, data, 4, chunk=2, checkpointer=ck, save_every=2, meta=META,
                progress=False)
    ck.close()
    return root, {2: s2, 4: s4}


def _truncate(path, size=10):
    with open(path, "r+b") as f:
        f.truncate(size)


def _array_files(step_dir, item):
    """The data files of one item's arrays (orbax OCDBT layout), largest first.

    Damage all of them, never one: which files the merged manifest still references varies
    from save to save (a per-process B-tree node superseded by the merge can be the largest)."""
    files = [os.path.join(d, f) for d, _, fs in os.walk(step_dir / item) for f in fs
             if os.path.basename(d) == "d"]
    assert files, f"no array data files under {step_dir / item}"
    return sorted(files, key=os.path.getsize, reverse=True)


CORRUPTIONS = {
    # name: (damage(step_dir), what the message must say)
    "meta JSON truncated": (lambda d: _truncate(d / "meta" / "metadata"),
                            "meta/metadata is not valid JSON"),
    "simulator array files deleted": (lambda d: [os.remove(f)
                                                 for f in _array_files(d, "simulator")],
                                      "simulator cannot be read"),
    "simulator array files truncated": (lambda d: [_truncate(f, 7)
                                                   for f in _array_files(d, "simulator")],
                                        "simulator cannot be read"),
    "simulator _METADATA truncated": (lambda d: _truncate(d / "simulator" / "_METADATA"),
                                      "simulator/_METADATA is not valid JSON"),
    "simulator item deleted": (lambda d: shutil.rmtree(d / "simulator"), "simulator/ is missing"),
}


@pytest.mark.parametrize("damage", list(CORRUPTIONS))
def test_broken_latest_step_falls_back_to_the_newest_intact(saved_steps, tmp_path, damage):
    src, states = saved_steps
    ck_dir = tmp_path / "ck"
    shutil.copytree(src, ck_dir)
    hurt, what = CORRUPTIONS[damage]
    hurt(ck_dir / "4")
    with pytest.warns(CheckpointWarning) as caught:
        sim, meta = load_checkpoint(ck_dir)
    msg = str(caught[0].message)
    assert "broken step 4" in msg and what in msg and "using step 2" in msg, msg
    assert meta["step"] == 2
    obs, act = jnp.array([[0.3, -0.2], [1.0, 0.5]]), jnp.array([[0.5], [-1.0]])
    np.testing.assert_array_equal(np.asarray(sim.mean(obs, act)),
                                  np.asarray(simulator(states[2]).mean(obs, act)))
    with pytest.warns(CheckpointWarning, match="broken step 4"):
        assert load_meta(ck_dir)["step"] == 2
    # An explicitly requested broken step is an error naming the step and the damage.
    with pytest.raises(CheckpointError, match=f"step 4 is broken: {re.escape(what)}"):
        load_simulator(ck_dir, step=4)
    assert load_checkpoint(ck_dir, step=2)[1]["step"] == 2


def test_no_intact_step_is_a_clear_error(saved_steps, tmp_path):
    src, _ = saved_steps
    shutil.copytree(src, tmp_path / "ck")
    _truncate(tmp_path / "ck" / "4" / "meta" / "metadata")
    for f in _array_files(tmp_path / "ck" / "2", "simulator"):
        os.remove(f)
    with pytest.raises(CheckpointError) as err:
        load_simulator(tmp_path / "ck")
    msg = str(err.value)
    assert "no intact step" in msg
    assert "step 4: meta/metadata is not valid JSON" in msg
    assert "step 2: simulator cannot be read" in msg


def test_resume_skips_a_broken_state_and_replays_it(pm, saved_steps, tmp_path):
    """A broken state item stops neither evaluation (it needs only the simulator) nor the resume:
    training restarts from step 2, sets step 4 aside and saves it again, bit-identical."""
    _, _, data = pm
    src, states = saved_steps
    ck_dir = tmp_path / "ck"
    shutil.copytree(src, ck_dir)
    for f in _array_files(ck_dir / "4", "state"):
        os.remove(f)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointWarning)
        assert load_meta(ck_dir)["step"] == 4  # the simulator of step 4 is intact
    template = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), CFG, data))
    ck = Checkpointer(ck_dir)
    with pytest.warns(CheckpointWarning, match=r"broken step 4 skipped \(step 4: state cannot "
                      r"be read.*using step 2"):
        resumed = ck.restore(template)
    _leaves_equal(resumed, states[2])
    assert ck.set_aside_after(2) == {"corrupt": [4], "superseded": []}
    assert ck.steps() == [2] and (ck_dir / "corrupt" / "4" / "meta").is_dir()
    again, _ = fit(resumed, data, 4, chunk=2, checkpointer=ck, save_every=2, meta=META,
                   progress=False)
    assert ck.steps() == [2, 4]
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointWarning)
        _leaves_equal(ck.restore(template), states[4])
    ck.close()
    _leaves_equal(again, states[4])


def test_restore_a_chosen_step_sets_newer_ones_aside(pm, saved_steps, tmp_path):
    _, _, data = pm
    src, states = saved_steps
    shutil.copytree(src, tmp_path / "ck")
    ck = Checkpointer(tmp_path / "ck")
    template = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), CFG, data))
    _leaves_equal(ck.restore(template, step=2), states[2])
    assert ck.set_aside_after(2) == {"corrupt": [], "superseded": [4]}
    assert ck.steps() == [2] and (tmp_path / "ck" / "superseded" / "4").is_dir()
    with pytest.raises(FileNotFoundError, match="step 4 not in"):
        ck.restore(template, step=4)
    ck.close()
