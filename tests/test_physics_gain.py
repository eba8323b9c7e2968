"""Issue 62 item 4's table: any one-step model's errors on the physics' rows and windows, the
learned simulators scored beside the physics, intervals over seeds, and the generated
"Physics diagnosis" block of docs/RESULTS.md (fast, but for the one slow training test)."""

import json
import types

import numpy as np
import pytest
from experiment_scripts import load_script
from scipy import stats

from rl2s_jax.paper import physics_tables as pt
from rl2s_jax.paper import simulator_gain as sg
from rl2s_jax.physics.residuals import prediction_errors


def _episodes(n_ep=2, length=8, seed=0):
    """A Dataset-like recording: obs [N, 2], action [N, 2], next_obs = obs + action + noise."""
    rng = np.random.default_rng(seed)
    rows = {k: [] for k in ("obs", "action", "next_obs", "episode_id", "t")}
    for e in range(n_ep):
        o = rng.normal(size=2)
        for t in range(length):
            a = rng.normal(size=2)
            nxt = o + a + 0.1 * rng.normal(size=2)
            for k, v in zip(rows, (o, a, nxt, e, t), strict=True):
                rows[k].append(v)
            o = nxt
    return types.SimpleNamespace(**{k: np.asarray(v) for k, v in rows.items()})


def test_prediction_errors_match_numpy():
    ds = _episodes()
    step = lambda o, a: 0.9 * o + a  # noqa: E731
    k = 4
    got = prediction_errors(step, ds, k=k, max_rows=100, max_windows=100)
    scale = np.std(ds.next_obs - ds.obs, axis=0)
    z = (0.9 * ds.obs + ds.action - ds.next_obs) / scale
    assert got["one_step"] == pytest.approx(np.sqrt(np.mean(z ** 2)))
    # windows start where t % k == 0 and the episode lasts k more rows, before row N - k
    # (physics_errors' rule: the last window, at row 12, is left out)
    starts = [0, 4, 8]
    sq = []
    for s in starts:
        o = ds.obs[s]
        for j in range(k):
            o = 0.9 * o + ds.action[s + j]
        sq.append(((o - ds.next_obs[s + k - 1]) / scale) ** 2)
    assert len(got["kstep"]) == k
    assert got["kstep"][-1] == pytest.approx(np.sqrt(np.mean(sq)))
    # other actions (e.g. the physics' delayed ones) are what the model is fed
    zero = prediction_errors(step, ds, action=np.zeros_like(ds.action), k=k)
    assert zero["one_step"] == pytest.approx(
        np.sqrt(np.mean(((0.9 * ds.obs - ds.next_obs) / scale) ** 2)))
    with pytest.raises(ValueError, match="action: expected shape"):
        prediction_errors(step, ds, action=np.zeros((3, 2)))
    # with_rows: the model is told which logged rows it steps (where it reads their past)
    seen = []

    def by_rows(o, a, rows):
        seen.append(np.asarray(rows))
        return 0.9 * o + ds.action[rows]
    again = prediction_errors(by_rows, ds, k=k, with_rows=True)
    assert again["one_step"] == pytest.approx(got["one_step"])
    assert again["kstep"] == pytest.approx(got["kstep"])
    np.testing.assert_array_equal(seen[0], np.arange(16))  # one-step: every row
    for j in range(k):  # window step j: the rows starts + j
        np.testing.assert_array_equal(seen[1 + j], np.array(starts) + j)


def test_value_scores_and_seed_intervals():
    true, sim = np.array([1.0, 2.0, 3.0, 4.0]), np.array([2.1, 1.8, 3.5, 3.9])
    s = sg.value_scores(true, sim)
    assert s["avd"] == pytest.approx(np.mean(np.abs(true - sim)))
    assert s["mvd"] == pytest.approx(1.1)
    assert s["tau"] == pytest.approx((5 - 1) / 6)  # one discordant pair (0, 1)
    runs = [{"nominal": dict(one_step=x, kstep=2 * x, avd=1.0, mvd=2.0, tau=0.5), "bc": None}
            for x in (0.1, 0.2, 0.4)]
    out = sg.seed_summary(runs, ["nominal", "bc", "rl2s"])
    assert set(out) == {"nominal"}  # bc skipped on every seed, rl2s absent
    x = np.array([0.1, 0.2, 0.4])
    half = stats.t.ppf(0.975, 2) * x.std(ddof=1) / np.sqrt(3)
    cell = out["nominal"]["one_step"]
    assert cell["mean"] == pytest.approx(x.mean()) and cell["n"] == 3
    assert [cell["lo"], cell["hi"]] == pytest.approx([x.mean() - half, x.mean() + half])
    one = sg.seed_summary(runs[:1], ["nominal"])["nominal"]["kstep"]
    assert one["lo"] is None and one["mean"] == pytest.approx(0.2)
    rows = sg.gain_rows({"mass": out})
    assert rows[0].startswith("| case | simulator | seeds | one-step RMSE")
    assert rows[2].startswith(f"| mass | nominal | 3 | {x.mean():.3g} [{x.mean() - half:.3g}, ")


def _v5_record():
    return {"task": "halfcheetah",
            "v5": {"one_step_mean": 0.01, "one_step_in_contact": 0.02,
                   "one_step_no_contact": 0.001, "k_step_mean": 0.05},
            "values": {"kendall_tau": 0.8, "avd": 10.0, "mvd": 30.0},
            "mjx_remeasured_vs_zoo_tau": 0.9,
            "physics_diagnosis": {"top_cause": None, "unexplained": 1.0}}


def test_v5_rows_merge_by_task_command_and_hardware(tmp_path):
    path = str(tmp_path / "gymnasium_v5.json")
    row = pt.v5_row(_v5_record(), "python experiments/gymnasium_v5.py --tasks halfcheetah",
                    "one H200")
    assert (row["one_step"], row["kstep"], row["tau"], row["tau_floor"]) == (0.01, 0.05, 0.8, 0.9)
    assert row["diagnosis"] == "nothing named (unexplained 1.000)"
    pt.merge_v5_row(path, row)
    pt.merge_v5_row(path, {**row, "tau": 0.7})  # the same run again: replaced
    pt.merge_v5_row(path, {**row, "hardware": "CPU"})  # another run: kept beside it
    with open(path) as f:
        rows = json.load(f)["rows"]
    assert [(r["hardware"], r["tau"]) for r in rows] == [("one H200", 0.7), ("CPU", 0.8)]


def test_v5_row_names_every_kept_quantity():
    q = lambda name, el, nominal, value, kept: {  # noqa: E731
        "name": name, "element": el, "nominal": nominal, "value": value, "interval": None,
        "significant": kept}
    params = [q("integrator", "opt", "Euler", "RK4", True),
              q("geom_friction", "foot_geom", 0.9, 1.9, True),
              q("geom_friction", "foot_left_geom", 1.9, 1.878, False)]
    rec = {**_v5_record(), "physics_diagnosis": {"top_cause": params[0], "parameters": params,
                                                 "unexplained": 0.009}}
    assert pt.v5_row(rec, "cmd", "CPU")["diagnosis"] == (
        "integrator[opt] Euler -> RK4; geom_friction[foot_geom] 0.9 -> 1.9 (unexplained 0.009)")
    rec["physics_diagnosis"]["parameters"] = None  # an older record: its top cause alone
    assert pt.v5_row(rec, "cmd", "CPU")["diagnosis"] == (
        "integrator[opt] Euler -> RK4 (unexplained 0.009)")


def _physics_results(folder):
    folder.mkdir()
    runs = [{"nominal": dict(one_step=x, kstep=x, avd=x, mvd=x, tau=0.9),
             "rl2s": dict(one_step=2 * x, kstep=x, avd=x, mvd=x, tau=0.5)} for x in (1.0, 2.0)]
    gain = {"command": "python experiments/physics_gain.py --profile gpu", "seconds": 400.0,
            "machine": {"backend": "gpu", "device": "NVIDIA H200", "cpu": "Xeon",
                        "cpu_count": 16, "jax": "0.11.2", "mujoco": "4.0.0"},
            "args": {"profile": "gpu"},
            "summary": {"mass": sg.seed_summary(runs, ["nominal", "rl2s"])}}
    unseen = {"command": "python experiments/physics_unseen.py", "machine": "a CPU",
              "sizes": {}, "cases": [
                  {"case": "thigh_mass", "passed": True, "command_seconds": 9.0,
                   "truth": [{"name": "body_mass", "element": "thigh", "value": 3.0}],
                   "found": {"name": "body_mass", "element": "thigh", "value": 3.01,
                             "interval": [2.9, 3.1]}},
                  {"case": "clean", "passed": False, "command_seconds": 8.0, "truth": [],
                   "found": {"name": "dof_damping", "element": "leg_joint", "value": 1.2,
                             "interval": None}}]}
    (folder / "physics_gain.json").write_text(json.dumps(gain))
    (folder / "physics_unseen.json").write_text(json.dumps(unseen))
    return gain


def test_physics_block_from_the_json(tmp_path):
    res = tmp_path / "results"
    _physics_results(res)
    block = pt.physics_block(str(res), "R")
    assert block.startswith(pt.PHYSICS_BEGIN) and block.rstrip().endswith(pt.PHYSICS_END)
    assert "NVIDIA H200, host CPU Xeon, 16 cores; jax 0.11.2, mujoco 4.0.0" in block
    assert "| mass | nominal | 2 | 1.5 [" in block and "| mass | rl2s | 2 | 3 [" in block
    assert ("| thigh_mass | body_mass[thigh] | body_mass[thigh] | 3.01 (3) | [2.9, 3.1] | yes "
            "| 9.0 |") in block
    assert "| clean | nothing | dof_damping[leg_joint] | 1.2 | - | NO | 8.0 |" in block
    assert "Not measured yet (`R/gymnasium_v5.json`)" in block and "INCOMPLETE" not in block
    gain = json.loads((res / "physics_gain.json").read_text())
    (res / "physics_gain.json").write_text(json.dumps({**gain, "complete": False,
                                                       "units_done": 1}))
    assert "INCOMPLETE run (1 case-seed units done)" in pt.physics_block(str(res), "R")
    assert "not the table" not in block
    (res / "physics_gain.json").write_text(json.dumps({**gain, "args": {"profile": "cpu"}}))
    assert "A check of the code at CPU sizes, not the table" in pt.physics_block(str(res), "R")
    (res / "physics_gain.json").write_text(json.dumps({**gain, "note": "GPU shared"}))
    assert "mujoco 4.0.0, 400 s. GPU shared; profile gpu" in pt.physics_block(str(res), "R")
    pt.merge_v5_row(str(res / "gymnasium_v5.json"),
                    pt.v5_row(_v5_record(), "python experiments/gymnasium_v5.py", "one H200"))
    block = pt.physics_block(str(res), "R")
    assert "| halfcheetah | 1 | 0.01 (0.02 / 0.001) | 0.05 | 0.800 (0.900) | 10.0 | 30.0 |" in block
    assert "1. on one H200: `python experiments/gymnasium_v5.py`" in block


def test_paper_tables_writes_and_checks_the_physics_block(tmp_path, capsys):
    tables = load_script("paper_tables")
    res, out = tmp_path / "results", tmp_path / "RESULTS.md"
    res.mkdir()
    out.write_text("# Results\n")
    assert tables.main(["--results", str(res), "--out", str(out)]) == 0
    assert pt.PHYSICS_BEGIN not in out.read_text()  # no physics JSON: no physics block
    gain = _physics_results(res / "p")
    args = ["--results", str(res / "p"), "--out", str(out)]
    assert tables.main(args) == 0
    text = out.read_text()
    assert text.count(pt.PHYSICS_BEGIN) == 1 and "| mass | rl2s | 2 |" in text
    assert tables.main([*args, "--check"]) == 0
    gain["summary"]["mass"]["rl2s"]["tau"]["mean"] = 0.25  # a stale physics cell
    (res / "p" / "physics_gain.json").write_text(json.dumps(gain))
    assert tables.main([*args, "--check"]) == 1
    assert "the generated block is not what" in capsys.readouterr().err
    assert tables.main(args) == 0 and out.read_text().count(pt.PHYSICS_BEGIN) == 1
    assert "0.25" in out.read_text()


@pytest.mark.slow
def test_learned_simulator_scored_on_the_physics_rows(pm_files, tmp_path):
    """train_learned runs rl2s train's training; learned_scores gives its mean's errors on
    prediction_errors' rows and values of the same rollouts as simulator_returns."""
    import jax

    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.model.simulator import simulator_returns, start_pool
    from rl2s_jax.zoo.zoo import policies_for

    sim = sg.train_learned(pm_files["train"], "bc", str(tmp_path / "bc"), steps=2,
                           profile="cpu", seed=0, gamma=0.95, horizon=20, log=lambda s: None)
    assert (tmp_path / "bc" / "checkpoints").is_dir()
    with open(tmp_path / "bc" / "summary.json") as f:
        config = json.load(f)["config"]
    assert (config["method"], config["gamma"], config["vd"]["horizon"]) == ("bc", 0.95, 20)
    held = load_dataset(pm_files["test"])
    task, params = get_task("pointmass"), policies_for(held)
    pool, key = start_pool(held), jax.random.PRNGKey(3)
    true = np.array([1.0, 2.0, 3.0])
    got = sg.learned_scores(sim, held, task, params, pool, key, true, k=3, seed=0,
                            n_episodes=4, horizon=20, gamma=0.95)
    mean = np.asarray(sim.mean(np.asarray(held.obs, np.float32),
                               np.asarray(held.action, np.float32)))
    scale = np.std(np.asarray(held.next_obs, np.float64) - held.obs, axis=0)
    z = (mean - held.next_obs) / scale
    assert got["one_step"] == pytest.approx(np.sqrt(np.mean(z ** 2)), rel=1e-4)
    ret, _ = simulator_returns(sim, task, params, pool, key, n_episodes=4, horizon=20,
                               gamma=0.95)
    vals = np.asarray(ret.mean(1))
    assert got["avd"] == pytest.approx(np.mean(np.abs(vals - true)), rel=1e-5)


def test_unseen_check_names_element_and_value():
    """experiments/physics_unseen.py's check: quantity and element named, value within 10% (a
    delay exactly); on clean data, nothing named."""
    check = load_script("physics_unseen").check
    truth = [{"name": "body_mass", "element": "thigh", "value": 3.0}]
    top = {"name": "body_mass", "element": "thigh", "value": 3.25}
    assert check(truth, top)["passed"] and not check(truth, {**top, "value": 3.35})["passed"]
    assert check(truth, {**top, "element": "leg"}) == {"named": False, "value_ok": False,
                                                       "passed": False}
    delay = [{"name": "action_delay", "element": "foot_joint", "value": 1}]
    assert check(delay, {**delay[0]})["passed"]
    assert not check(delay, {**delay[0], "value": 2})["passed"]
    assert check([], None)["passed"] and not check([], top)["passed"]
    assert not check(truth, None)["passed"]


@pytest.mark.parametrize("script, work, args", [
    ("physics_gain", "_unit", ["--cases", "mass", "--seeds", "0", "--out"]),
    ("gymnasium_v5", "run_task", ["--tasks", "hopper", "--results"]),
])
def test_scripts_make_their_output_folder_before_any_work(tmp_path, monkeypatch, script,
                                                          work, args):
    """--out / --results into a folder that does not exist yet (both crashed on the GPU after
    their work for want of it): made before the first unit runs."""
    mod = load_script(script)
    out = tmp_path / "new" / "deeper" / "result.json"

    def first_unit(*a, **k):
        assert out.parent.is_dir()
        raise RuntimeError("stop here")

    monkeypatch.setattr(mod, work, first_unit)
    with pytest.raises(RuntimeError, match="stop here"):
        mod.main([*args, str(out)])
