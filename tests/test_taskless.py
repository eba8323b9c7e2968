"""Data of a system that no registered task describes (``meta.task`` null): the learned reward
head (rl2s_jax.model.reward) and the learned termination stand in for the task's rules,
chosen by `rl2s train`, reported with their held-out errors, kept by checkpoints, and used by
`rl2s evaluate`, `rl2s improve` and the simulator envs (``Simulator.task_fns``)."""
import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from rl2s_jax import cli
from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.improve.gym_env import SimulatorGymEnv
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.policy import policy as pol
from rl2s_jax.train.checkpoint import Checkpointer, load_simulator
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.learned import heldout_errors
from rl2s_jax.train.loop import fit
from rl2s_jax.train.step import init, simulator

SMALL = dict(gen_hidden=(64, 64), hazard_steps=1500, hazard_hidden=(64, 64), reward_steps=800,
             reward_hidden=(64, 64))
CFG = TrainConfig.small(task=None, method="bc", vd_horizon=50, vd_every=3, reward="learned",
                        termination="hazard", **SMALL)
SETS = ["--set", "gen_hidden=[64,64]", "--set", "updates_per_step=5", "--set",
        "hazard_steps=1500", "--set", "hazard_hidden=[64,64]", "--set", "reward_steps=800",
        "--set", "reward_hidden=[64,64]", "--set", "vd_horizon=50"]
SMALL_SAC = ["--set", "n_envs=4", "--set", "hidden=[32,32]", "--set", "batch_size=32",
             "--set", "warmup_steps=8", "--set", "buffer_size=2000"]


@pytest.fixture(scope="module")
def taskless(pm_falls, tmp_path_factory):
    """Pointmass data (two of four policies push the mass out) with meta.task null and no
    meta.source, its policies in a policy file, and `rl2s train --method bc` of it (6 steps):
    {"data", "policies", "out", "summary", "printed", "params", "ds"}."""
    ds, params = pm_falls
    root = tmp_path_factory.mktemp("taskless")
    data, pfile, out = str(root / "d.npz"), str(root / "p.npz"), str(root / "run")
    ds = ds.replace(meta={**ds.meta, "task": None, "source": {}})
    save_dataset(data, ds)
    pol.save_policies(pfile, params, [f"pm{i}" for i in range(4)])
    return {"data": data, "policies": pfile, "out": out, "params": params, "ds": ds}


@pytest.fixture(scope="module")
def trained(taskless):
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = cli.main(["train", "--data", taskless["data"], "--method", "bc", "--steps", "6",
                       "--out", taskless["out"], "--policy-file", taskless["policies"],
                       "--profile", "cpu", "--quiet", *SETS])
    assert rc == 0, buf.getvalue()
    with open(os.path.join(taskless["out"], "summary.json")) as f:
        summary = json.load(f)
    return {**taskless, "summary": summary, "printed": buf.getvalue(),
            "ckpt": os.path.join(taskless["out"], "checkpoints")}


def test_learned_reward_matches_a_known_reward(pm_falls):
    """On pointmass the head r(s, a, s') learns the task's 1 - p'^2 - 0.1 a^2 from the logged
    rewards: R^2 > 0.9 on the held-out episodes' rows, and the task's own reward_fn scores 1."""
    ds, params = pm_falls
    cfg = dataclasses.replace(CFG, task="pointmass")  # registered: learned beside the rule
    data = make_train_data(ds, params, cfg)
    state = jax.jit(init, static_argnums=1)(jax.random.PRNGKey(0), cfg, data)
    errs = heldout_errors(simulator(state), data)
    assert errs["reward"]["source"] == "learned"
    assert errs["reward"]["heldout_r2"] > 0.9, errs
    term = errs["termination"]
    assert term["source"] == "hazard" and term["heldout_logloss"] < 0.5, term
    rule = heldout_errors(simulator(state).replace(reward=None, termination="rule"), data)
    assert rule["reward"]["source"] == "task pointmass"
    assert rule["reward"]["heldout_r2"] > 0.999 and rule["termination"]["heldout_agreement"] == 1


def test_taskless_data_trains_with_a_learned_reward_and_hazard(trained):
    s = trained["summary"]
    assert s["config"]["task"] is None
    assert (s["config"]["outcome"]["reward"], s["config"]["outcome"]["termination"]) == (
        "learned", "hazard")
    assert s["config"]["data_episode_length"] == 50
    assert "data of no registered task (meta.task None): reward 'learned', termination " \
        "'hazard'" in trained["printed"]
    r, t = s["learned"]["reward"], s["learned"]["termination"]
    assert r["heldout_r2"] > 0.9 and r["heldout_rows"] > 0, r
    assert t["heldout_logloss"] < t["constant_logloss"] and t["heldout_ends"] > 0, t
    assert "reward (learned) on" in trained["printed"]
    assert "termination (hazard) on" in trained["printed"]
    assert np.isfinite(s["avd_train"])


def test_a_taskless_checkpoint_evaluates_the_policies_of_a_policy_file(trained, tmp_path):
    path = tmp_path / "eval.json"
    assert cli.main(["evaluate", "--ckpt", trained["ckpt"], "--data", trained["data"],
                     "--policy-file", trained["policies"], "--bootstrap", "0", "--json",
                     str(path)]) == 0
    r = json.loads(path.read_text())
    assert r["horizon"] == 50 and len(r["sim_value"]) == 4
    assert np.isfinite(r["metrics"]["kendall_tau"]) and np.all(np.isfinite(r["sim_value"]))


def test_a_taskless_simulator_rolls_out_with_its_learned_rules(trained):
    """The checkpoint's Simulator: its task_fns give the learned reward and a rule that never
    fires, episodes ending by the learned hazard; the brax and Gymnasium envs step with them."""
    sim = load_simulator(trained["ckpt"])
    assert sim.task is None and sim.reward is not None and sim.hazard is not None
    task = sim.task_fns()
    assert task.name == "unregistered" and task.episode_length == 50
    assert (task.obs_size, task.action_size) == (2, 1)
    ds = trained["ds"]
    obs, act, nxt = (jnp.asarray(np.asarray(x)) for x in (ds.obs, ds.action, ds.next_obs))
    assert not np.asarray(task.done_fn(nxt)).any()
    assert sim.terminations(task.done_fn)[0] is None  # the hazard alone ends episodes
    r = np.asarray(task.reward_fn(obs, act, nxt))
    truth = np.asarray(get_task("pointmass").reward_fn(obs, act, nxt))
    assert 1 - np.mean((r - truth) ** 2) / np.var(truth) > 0.9
    done = np.asarray(ds.done, bool)
    h = np.asarray(sim.hazard_prob(obs, act))
    assert h[done].mean() > 5 * h[~done].mean(), (h[done].mean(), h[~done].mean())
    env = SimulatorEnv(sim, start_pool(ds), deterministic=True)
    state = env.step(env.reset(jax.random.PRNGKey(0)), jnp.array([0.5]))
    expect = sim.predict_reward(env.reset(jax.random.PRNGKey(0)).obs, jnp.array([0.5]),
                                state.obs)
    np.testing.assert_allclose(float(state.reward), float(expect), rtol=1e-5)
    gym_env = SimulatorGymEnv(sim, ds)
    assert gym_env.max_episode_steps == 50
    gym_env.reset(seed=0)
    _, reward, *_ = gym_env.step(np.array([0.5], np.float32))
    assert np.isfinite(reward)


def test_improve_fine_tunes_in_a_taskless_simulator(trained, tmp_path):
    """No real system to measure in: the real returns are skipped, saying so."""
    out = tmp_path / "improved"
    assert cli.main(["improve", "--ckpt", trained["ckpt"], "--data", trained["data"],
                     "--policy-file", trained["policies"], "--policies", "1", "--out",
                     str(out), "--iterations", "4", "--quiet", *SMALL_SAC]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["mpi"] is None and s["task"] == "unregistered" and len(s["policies"]) == 1


def test_refusals_name_what_is_missing(taskless, trained, capsys):
    with pytest.raises(ValueError, match="reward: 'task' takes rewards from the registered"):
        TrainConfig.small(task=None, termination="hazard").validate()
    with pytest.raises(ValueError, match="termination: 'rule' ends episodes by the registered"):
        TrainConfig.small(task=None, reward="learned").validate()
    with pytest.raises(ValueError, match="task 'not_here' is not registered"):
        TrainConfig.small(task="not_here", termination="hazard").validate()
    with pytest.raises(ValueError, match="reward: expected one of"):
        TrainConfig.small(reward="guessed").validate()
    # no rollouts (vd_every 0, bc): nothing needs the rules, as rl2s diagnose fits its models
    TrainConfig.small(task=None, method="bc", vd_every=0).validate()
    sim = load_simulator(trained["ckpt"])
    with pytest.raises(ValueError, match="has no learned reward"):
        sim.replace(reward=None).task_fns()
    with pytest.raises(ValueError, match="termination: 'rule' ends episodes"):
        sim.replace(termination="rule").task_fns()
    data = make_train_data(taskless["ds"], taskless["params"], CFG)
    with pytest.raises(ValueError, match="TrainData.reward is None"):
        init(jax.random.PRNGKey(0), CFG, data.replace(reward=None))
    assert cli.main(["evaluate", "--oracle", "--data", taskless["data"], "--policy-file",
                     taskless["policies"]]) == 2
    assert "oracle: " in capsys.readouterr().err
    rc = cli.main(["train", "--data", taskless["data"], "--method", "bc", "--steps", "1",
                   "--out", str(os.path.dirname(taskless["out"]) + "/refused"),
                   "--policy-file", taskless["policies"], "--set", "reward=task"])
    assert rc == 2 and "reward: 'task' takes rewards" in capsys.readouterr().err


def test_a_state_saved_before_the_reward_field_resumes(pm_falls, tmp_path):
    """Checkpoints written before TrainState had ``reward`` (its state tree lacks the key)
    resume: the saved fields by name, reward None."""
    ds, params = pm_falls
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=50)
    data = make_train_data(ds, params, cfg)
    state, _ = fit(init(jax.random.PRNGKey(0), cfg, data), data, 2, chunk=2, progress=False)
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1}})
    old = {f.name: getattr(state, f.name) for f in dataclasses.fields(state)
           if f.metadata.get("pytree_node", True) and f.name != "reward"}
    meta = ck._read_meta(2)
    ck._mgr.save(3, args=ocp.args.Composite(
        state=ocp.args.StandardSave(old), simulator=ocp.args.StandardSave(
            {"gen": state.gen, "norm": state.norm, "rank": state.rank}),
        meta=ocp.args.JsonSave({**meta, "step": 3})), force=True)
    ck._mgr.wait_until_finished()
    assert ck._fields_saved_without(3, state) == {"reward"}
    back = ck.restore(jax.eval_shape(lambda: init(jax.random.PRNGKey(0), cfg, data)), 3)
    ck.close()
    assert back.reward is None and int(back.step) == 2
    for a, b in zip(jax.tree_util.tree_leaves(back.gen), jax.tree_util.tree_leaves(state.gen),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_unregistered_system_example_learns_and_ranks(monkeypatch, tmp_path):
    """examples/own_system_unregistered.py --quick (about 30 s on the CPU): no task is
    registered, and the simulator learns reward and termination and ranks unseen policies."""
    import sys

    from rl2s_jax.envs.tasks import task_names

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    monkeypatch.syspath_prepend(os.path.join(root, "examples"))
    before = task_names()
    import own_system_unregistered as example
    out = example.main(["--quick", "--out", str(tmp_path)])
    sys.modules.pop("own_system_unregistered", None)
    assert task_names() == before  # nothing registered
    s, r = out["summary"], out["report"]
    assert s["config"]["task"] is None and s["config"]["outcome"]["reward"] == "learned"
    assert s["learned"]["reward"]["heldout_r2"] > 0.95
    assert s["learned"]["termination"]["heldout_ends"] > 0
    assert r["horizon"] == example.EPISODE and len(r["true_value"]) == 6
    assert r["metrics"]["kendall_tau"] > 0.3, r["metrics"]
