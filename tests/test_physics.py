"""Physics diagnosis (issue 62): the MJX step against the task env, the C-MuJoCo collector,
and planted changes in C-MuJoCo Hopper data named with their element and value.

The planted amounts live only here; the library sees the data, and the tests compare its
answer with the truth the collector recorded in meta (``source.planted``)."""

import json

import numpy as np
import pytest

from rl2s_jax.physics.mjx_model import delayed_actions

CASES = {
    "clean": [],
    "mass": [("body_mass", "torso", 1.3)],
    "friction": [("geom_friction", "foot_geom", 0.6)],
    "gear": [("actuator_gear", "leg_joint", 0.7)],
    "damping": [("dof_damping", "foot_joint", 3.0)],
    "delay": [("action_delay", "thigh_joint", 2)],
    # the contact margin (m; planted as its value): the floor and the foot share one contact
    # pair, whose margin is the sum of theirs, so naming either with 0.01 is right
    "margin": [("geom_margin", "floor", 0.01)],
    "integrator": [("integrator", "RK4", 1)],  # data stepped with RK4, the model with Euler
}
POLICIES = [4, 7, 16, 21]  # shipped Hopper zoo: training policies that hop for 100 steps


def test_delayed_actions_shift_within_episodes():
    action = np.arange(12, dtype=np.float32).reshape(6, 2)
    episode = np.array([0, 0, 0, 1, 1, 1])
    t = np.array([0, 1, 2, 0, 1, 2])
    out = delayed_actions(action, episode, t, [0, 2])
    expect = action.copy()
    expect[:, 1] = [0, 0, action[0, 1], 0, 0, action[3, 1]]
    np.testing.assert_array_equal(out, expect)
    with pytest.raises(ValueError, match="delays"):
        delayed_actions(action, episode, t, [0, -1])


@pytest.fixture(scope="module")
def pm():
    from rl2s_jax.physics.mjx_model import physics_model

    return physics_model("hopper")


@pytest.fixture(scope="module")
def zoo_params():
    from rl2s_jax.policy import policy as pol
    from rl2s_jax.zoo import zoo as zoo_mod

    return pol.index_params(zoo_mod.load_zoo("hopper").params, POLICIES)


def test_candidates_carry_mujoco_names(pm):
    labels = {c.label for c in pm.candidates}
    for want in ("body_mass[torso]", "geom_friction[foot_geom]", "dof_damping[foot_joint]",
                 "actuator_gear[leg_joint]", "dof_armature[thigh_joint]", "obs_bias[obs[3]]"):
        assert want in labels
    # root joints (rootx/z/y) have no damping in hopper.xml: not a candidate
    assert not any(c.element.startswith("root") for c in pm.candidates)
    c = pm.candidates[pm.index("body_mass", "torso")]
    assert c.nominal == pytest.approx(float(pm.mj.body_mass[1]))


def test_obs_state_round_trip(pm):
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    obs = rng.normal(size=pm.obs_size)
    q, v = pm.obs_to_state_np(obs)
    # the lagged torso height: q[1] = obs[1] - z0 + h qd[1] (mjx_model's docstring)
    assert q[1] == pytest.approx(obs[1] - pm.mj.body_pos[1, 2] + pm.substep * obs[7])
    np.testing.assert_allclose(pm.state_to_obs_np(q, v), obs, atol=1e-12)
    qj, vj = pm.obs_to_state(jnp.asarray(obs, jnp.float32))
    np.testing.assert_allclose(np.asarray(qj), q, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pm.state_to_obs(qj, vj)), obs, atol=1e-6)


def _dataset(pm, zoo_params, case, seed=1):
    from rl2s_jax.physics.measured import Planted, collect_measured

    return collect_measured(pm, zoo_params, transitions_per_policy=300, episode_length=100,
                            changes=[Planted(*c) for c in CASES[case]], seed=seed)


@pytest.fixture(scope="module")
def datasets(pm, zoo_params):
    return {}


def _get(datasets, pm, zoo_params, case):
    if case not in datasets:
        datasets[case] = _dataset(pm, zoo_params, case)
    return datasets[case]


def test_collector_records_planted_truth(pm, zoo_params, datasets):
    ds = _get(datasets, pm, zoo_params, "mass")
    truth = ds.meta["source"]["planted"]
    assert truth[0]["name"] == "body_mass" and truth[0]["element"] == "torso"
    assert truth[0]["value"] == pytest.approx(1.3 * truth[0]["nominal"])
    assert ds.n_transitions == 300 * len(POLICIES)
    # the recorded next obs is the next row's obs within an episode
    same = ds.episode_id[1:] == ds.episode_id[:-1]
    np.testing.assert_array_equal(ds.next_obs[:-1][same], ds.obs[1:][same])


@pytest.mark.slow
def test_step_reproduces_the_task_env(pm, env_cache):
    import jax

    from rl2s_jax.physics.residuals import predict

    env = env_cache("hopper")
    step = jax.jit(env.step)
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    rng = np.random.default_rng(0)
    obs, act, nxt = [], [], []
    for _ in range(20):
        a = rng.uniform(-1, 1, 3).astype(np.float32)
        new = step(state, a)
        obs.append(np.asarray(state.obs))
        act.append(a)
        nxt.append(np.asarray(new.obs))
        state = new
    pred = predict(pm, np.zeros(len(pm.candidates)), np.array(obs), np.array(act),
                   backend="mjx")
    # row 0 is excluded: brax's reset height is not lagged (tasks.py's docstring)
    np.testing.assert_allclose(pred[1:], np.array(nxt)[1:], atol=2e-5, rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_planted_change_is_named_with_its_value(pm, zoo_params, datasets, case):
    from rl2s_jax.physics.identify import FitConfig, identify

    ds = _get(datasets, pm, zoo_params, case)
    found = identify(pm, ds, FitConfig(rows=256))
    truth = ds.meta["source"]["planted"]
    top = found["top_cause"]
    if not truth:
        assert top is None, f"clean data, named {top}"
        assert found["unexplained"] == pytest.approx(1.0)
        return
    assert top is not None, f"nothing named; screened {found['parameters']}"
    pair = {"floor", "foot_geom"} if truth[0]["name"] == "geom_margin" else {truth[0]["element"]}
    assert top["name"] == truth[0]["name"] and top["element"] in pair, top
    if top["name"] in ("action_delay", "integrator"):
        assert top["value"] == truth[0]["value"]
        assert found["integrator"] == (truth[0]["value"] if top["name"] == "integrator"
                                       else "Euler")
    else:
        assert top["value"] == pytest.approx(truth[0]["value"], rel=0.1)
        lo, hi = top["interval"]
        assert lo <= top["value"] <= hi
    assert found["unexplained"] < 0.5


@pytest.mark.slow
def test_mjx_backend_gradients_and_answer_match_the_c_engine(pm, zoo_params, datasets):
    """The MJX backend (``jax.jacfwd`` through MJX's float32 step) against the C backend's
    float64 forward differences on the same rows, then its identification of the planted
    mass: the element and the value (one compile of 64-row chunks serves both)."""
    from rl2s_jax.physics.identify import JAC_ROWS, FitConfig, c_backend, compiled, identify

    ds = _get(datasets, pm, zoo_params, "mass")
    rows = slice(1, 1 + JAC_ROWS)  # row 0 of an episode: brax's unlagged reset height
    obs, act = ds.obs[rows], ds.action[rows]
    theta = np.zeros(len(pm.candidates))
    theta[pm.index("body_mass", "torso")] = np.log(1.3)
    pred, jac = compiled(pm)[1](theta, obs, act)
    pred_c, jac_c = c_backend(pm)[1](theta, obs.astype(np.float64), act.astype(np.float64))
    np.testing.assert_allclose(pred, pred_c, atol=1e-4)
    err = np.abs(jac - jac_c) / (np.abs(jac_c).max(axis=(0, 1)) + 1e-3)  # per candidate
    margin = np.array([c.name == "geom_margin" for c in pm.candidates])
    # measured: 99.9% of the entries within 1.3e-5; 0.02% (two rows' obs_bias columns, a
    # contact beside a finite difference's step) up to 0.036
    assert np.quantile(err[..., ~margin], 0.999) < 1e-4
    assert (err[..., ~margin] > 1e-2).mean() < 1e-3
    # a margin's derivative is the steepest (a contact's push as it nears): 0.5% of its
    # entries beyond 1e-2, none beyond 0.037
    assert (err[..., margin] > 1e-2).mean() < 0.02 and err[..., margin].max() < 0.1
    found = identify(pm, ds, FitConfig(rows=256, backend="mjx"))
    top, truth = found["top_cause"], ds.meta["source"]["planted"][0]
    assert (top["name"], top["element"]) == ("body_mass", "torso")
    assert top["value"] == pytest.approx(truth["value"], rel=0.02)


def test_no_physics_model_fails_fast(tmp_path, pm_files):
    from rl2s_jax.app.physics_diagnosis import PhysicsSpec, diagnose_physics

    with pytest.raises(ValueError, match="no physics model.*--sim-xml"):
        diagnose_physics(PhysicsSpec(data=pm_files["train"], out=str(tmp_path / "o")))
    assert not (tmp_path / "o").exists()
    from rl2s_jax.physics.mjx_model import task_xml

    with pytest.raises(ValueError, match="obs_size 12"):  # a user's model of other sizes
        diagnose_physics(PhysicsSpec(data=pm_files["train"], out=str(tmp_path / "o"),
                                     sim_xml=task_xml("hopper")))


def _diagnose_cli(tmp_path, ds):
    """`rl2s diagnose --physics` on ``ds`` as a user runs it -> (its out dir, report.json)."""
    from rl2s_jax.cli import main
    from rl2s_jax.data.dataset import save_dataset

    path = str(tmp_path / "data.npz")
    save_dataset(path, ds)
    out = tmp_path / "report"
    assert main(["diagnose", "--data", path, "--physics", "--out", str(out), "--quiet",
                 "--k-max", "3"]) == 0
    return out, json.loads((out / "report.json").read_text())


@pytest.mark.slow
def test_cli_writes_the_physics_report(tmp_path, pm, zoo_params, datasets):
    out, report = _diagnose_cli(tmp_path, _get(datasets, pm, zoo_params, "gear"))
    ph = report["physics"]
    assert set(ph) >= {"top_cause", "parameters", "unexplained", "seconds", "command"}
    assert ph["top_cause"]["element"] == "leg_joint"
    assert all("significant" in p for p in ph["parameters"])
    assert (out / "physics_one_step.png").exists() and (out / "report.md").exists()
    err = report["errors"]
    assert err["calibrated"]["kstep"][-1] < err["nominal"]["kstep"][-1]
    # the calibrated simulator the report's command loads carries the identified gear
    from rl2s_jax.app.physics_diagnosis import load_calibrated

    pm2, theta, delays = load_calibrated(str(out / "calibrated.json"))
    k = pm2.index("actuator_gear", "leg_joint")
    assert pm2.candidates[k].value(theta[k]) == pytest.approx(ph["top_cause"]["value"])
    assert ph["command"].startswith("rl2s evaluate --physics ")
    assert str(out / "calibrated.json") in ph["command"] and delays.tolist() == [0, 0, 0]


@pytest.mark.slow
def test_cli_calibrates_the_integrator_it_names(tmp_path, pm, zoo_params, datasets):
    """Data stepped with RK4, the model with Euler: the report names the integrator (no
    interval: a choice among names), report.md prints it, calibrated.json carries it, and the
    model it loads steps with it (the calibrated one-step error near 0)."""
    import mujoco

    from rl2s_jax.app.physics_diagnosis import load_calibrated

    out, report = _diagnose_cli(tmp_path, _get(datasets, pm, zoo_params, "integrator"))
    top = report["physics"]["top_cause"]
    assert top == {"name": "integrator", "element": "opt", "nominal": "Euler", "value": "RK4",
                   "interval": None}
    assert "integrator[opt] Euler -> RK4" in (out / "report.md").read_text()
    assert json.loads((out / "calibrated.json").read_text())["integrator"] == "RK4"
    pm2, _, _ = load_calibrated(str(out / "calibrated.json"))
    assert pm2.mj.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert pm.mj.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER  # the nominal untouched
    err = report["errors"]
    assert err["calibrated"]["one_step"]["rmse"] < 0.01 * err["nominal"]["one_step"]["rmse"]


def test_sysid_path_fits_the_chosen_quantity(pm, zoo_params, datasets):
    from rl2s_jax.physics.identify import fit_sysid

    ds = _get(datasets, pm, zoo_params, "gear")
    truth = ds.meta["source"]["planted"][0]
    out = fit_sysid(pm, ds, [(truth["name"], truth["element"])])
    value = out["values"][f"{truth['name']}[{truth['element']}]"]
    assert value == pytest.approx(truth["value"], rel=0.1)
    assert out["seconds"] > 0


@pytest.mark.slow
def test_clean_mjx_data_names_nothing(pm, zoo_params, env_cache):
    """Data from the MJX env itself (float32, brax's stepping) against the C-MuJoCo float64
    model: the engines' differences must not be named as a physical cause."""
    import jax

    from rl2s_jax.data.collect import collect
    from rl2s_jax.physics.identify import FitConfig, identify

    ds = collect(env_cache("hopper"), zoo_params, key=jax.random.PRNGKey(0),
                 transitions_per_policy=300, envs_per_policy=3, episode_length=100,
                 task="hopper", value_episodes=0, progress=False)
    found = identify(pm, ds, FitConfig(rows=256))
    assert found["top_cause"] is None, f"named {found['top_cause']}"
    assert 0 < found["error_nominal"] < 1e-4  # float32 round-off, not a physical change


def test_split_tests_on_every_second_episode_even_with_one_per_policy():
    """Held-out episodes alternate within each policy; where policies have one episode each
    (HalfCheetah never terminates: one per policy in a short recording) they alternate over
    all episodes instead of leaving too few to test on (Gymnasium-v5 HalfCheetah found it)."""
    from types import SimpleNamespace

    from rl2s_jax.physics.identify import split_rows

    def data(policy_of_episode, rows_per_episode=4):
        episode = np.repeat(np.arange(len(policy_of_episode)), rows_per_episode)
        n = episode.size
        return SimpleNamespace(episode_id=episode,
                               policy_id=np.repeat(policy_of_episode, rows_per_episode),
                               obs=np.zeros((n, 2)), next_obs=np.zeros((n, 2)),
                               action=np.zeros((n, 1)), t=np.tile(np.arange(rows_per_episode),
                                                                   len(policy_of_episode)))

    fit, test = split_rows(data(np.arange(8)), rows=32, seed=0)  # one episode per policy
    tested = set(test.episode[test.episode >= 0].tolist())
    assert tested == {1, 3, 5, 7}, tested
    assert set(fit.episode[fit.episode >= 0].tolist()) == {0, 2, 4, 6}
    fit, test = split_rows(data(np.repeat(np.arange(3), 2)), rows=32, seed=0)  # two each
    assert set(test.episode[test.episode >= 0].tolist()) == {1, 3, 5}
    with pytest.raises(ValueError, match="at least 6 episodes"):
        split_rows(data(np.arange(4)), rows=32, seed=0)
