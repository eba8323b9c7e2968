"""The physics model as a simulator that `rl2s evaluate`, `rl2s improve` and the Gymnasium env
take (issue 62, item 3): `rl2s evaluate --physics` scores policies as ``physics_values`` does
with the same key and setting, and the nominal physics ranks policies of nominal C-MuJoCo
data nearly as their logged returns do; the Gymnasium env steps the MJX step at the file's
theta with its delays; bad input is refused, naming --physics, before anything compiles."""

import json

import numpy as np
import pytest

HORIZON = 20
THETA_CHANGE = ("body_mass", "torso", 1.3)
DELAYS = [0, 2, 0]  # hopper's actuators: thigh_joint, leg_joint, foot_joint


@pytest.fixture(scope="module")
def pm():
    from rl2s_jax.physics.mjx_model import physics_model

    return physics_model("hopper")


@pytest.fixture(scope="module")
def data_path(pm, tmp_path_factory):
    """Nominal C-MuJoCo Hopper data of six test policies of the shipped zoo (two 50-step
    episodes each), naming the zoo so that the policies load from it."""
    from rl2s_jax.data.dataset import save_dataset
    from rl2s_jax.physics.measured import collect_measured
    from rl2s_jax.policy.policy import index_params
    from rl2s_jax.zoo.zoo import load_zoo

    zoo = load_zoo("hopper")
    ids = [int(i) for i in zoo.test_ids[:6]]
    ds = collect_measured(pm, index_params(zoo.params, ids), transitions_per_policy=100,
                          episode_length=50, seed=0, policy_names=zoo.policy_names(ids),
                          source={"zoo": "hopper", "zoo_ids": ids})
    path = str(tmp_path_factory.mktemp("physics_eval") / "nominal.npz")
    save_dataset(path, ds)
    return path


def _calibrated(pm, path, **fields) -> str:
    """A calibrated.json as `rl2s diagnose --physics` writes it (THETA_CHANGE, DELAYS), with
    ``fields`` replacing its entries."""
    theta = np.zeros(len(pm.candidates))
    theta[pm.index(*THETA_CHANGE[:2])] = np.log(THETA_CHANGE[2])
    c = {"task": "hopper", "xml": pm.xml_path, "n_frames": pm.n_frames,
         "theta": theta.tolist(), "delays": DELAYS,
         "labels": [cand.label for cand in pm.candidates], **fields}
    with open(path, "w") as f:
        json.dump(c, f)
    return str(path)


@pytest.mark.slow
def test_evaluate_physics_is_physics_values_and_ranks_as_the_truth(pm, data_path, tmp_path):
    import jax

    from rl2s_jax.app.evaluation import run_evaluate
    from rl2s_jax.app.specs import EvaluateSpec
    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.model.simulator import start_pool
    from rl2s_jax.physics.calibrated import physics_values
    from rl2s_jax.zoo.zoo import policies_for

    out = tmp_path / "report.json"
    assert run_evaluate(EvaluateSpec(data=data_path, physics="nominal", episodes=2,
                                     horizon=HORIZON, seed=3, bootstrap=0, level=0.9,
                                     json=str(out))) == 0
    r = json.loads(out.read_text())
    ds = load_dataset(data_path)
    want, length = physics_values(pm, None, None, policies_for(ds), get_task("hopper"),
                                  start_pool(ds), jax.random.PRNGKey(3), n_episodes=2,
                                  horizon=HORIZON, gamma=r["gamma"])
    np.testing.assert_allclose(r["sim_value"], np.asarray(want), rtol=1e-5)
    np.testing.assert_allclose(r["sim_length"], np.asarray(length))
    assert (r["method"], r["physics"], r["horizon"], r["n_episodes"]) == (
        "physics", "nominal", HORIZON, 2)
    # the MJX model of the C model that made the data: float32 round-off, and the ranking
    # of the logged returns up to the episodes' noise
    assert r["heldout_mse"] < 1e-6 and r["one_step_rows"] == ds.n_transitions
    assert r["metrics"]["kendall_tau"] >= 0.6
    assert "skipped" in r["trust"] and "interval" not in r  # no ensemble: no intervals


@pytest.mark.slow
def test_gym_env_steps_the_calibrated_physics(pm, data_path, tmp_path):
    """Hopper with a heavier torso and the leg's action two steps late: each step of the
    Gymnasium env is ``pm.step`` at that theta with the action its actuators apply."""
    import gymnasium
    import jax
    import jax.numpy as jnp

    import rl2s_jax.improve.gym_env  # noqa: F401  (registers rl2s/Simulator-v0)

    path = _calibrated(pm, tmp_path / "calibrated.json")
    env = gymnasium.make("rl2s/Simulator-v0", physics=path, data=data_path)
    theta = jnp.asarray(json.loads(open(path).read())["theta"], jnp.float32)
    step = jax.jit(lambda o, a: pm.step(theta, o, a))
    obs, _ = env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (4, 3)).astype(np.float32)
    for t, a in enumerate(actions):
        late = a.copy()
        late[1] = actions[t - 2, 1] if t >= 2 else 0.0
        want = np.asarray(step(jnp.asarray(obs), jnp.asarray(late)))
        obs, _, terminated, _, info = env.step(a)
        np.testing.assert_allclose(obs, want, atol=1e-6)
        assert info == {} and not terminated  # deterministic: no uncertainty to report
    env.close()


def test_calibrated_json_gives_its_theta_and_delays(pm, data_path, tmp_path):
    from rl2s_jax.physics.physics_simulator import physics_simulator

    sim = physics_simulator(_calibrated(pm, tmp_path / "c.json"), "hopper", 12, 3)
    i = pm.index(*THETA_CHANGE[:2])
    assert sim.theta[i] == pytest.approx(np.log(THETA_CHANGE[2]))
    assert sum(abs(x) for x in sim.theta) == pytest.approx(np.log(THETA_CHANGE[2]))
    assert list(sim.delays) == DELAYS and not sim.markov
    nominal = physics_simulator("nominal", "hopper")
    assert nominal.markov and not any(nominal.theta) and nominal.new_history((2,)) is None


def test_one_step_error_is_that_of_the_file_s_theta_and_delays(pm, tmp_path):
    """On data of Hopper with the file's heavier torso and late leg, the calibrated physics
    steps every transition as the system did; the nominal one does not."""
    from rl2s_jax.physics.measured import Planted, collect_measured
    from rl2s_jax.physics.physics_simulator import one_step_mse, physics_simulator
    from rl2s_jax.policy.policy import index_params
    from rl2s_jax.zoo.zoo import load_zoo

    planted = [Planted(*THETA_CHANGE), Planted("action_delay", "leg_joint", DELAYS[1])]
    ds = collect_measured(pm, index_params(load_zoo("hopper").params, [4, 7]),
                          transitions_per_policy=60, episode_length=30, changes=planted)
    calibrated = one_step_mse(physics_simulator(_calibrated(pm, tmp_path / "c.json"),
                                                "hopper"), ds)
    nominal = one_step_mse(physics_simulator("nominal", "hopper"), ds)
    assert calibrated["one_step_rows"] == ds.n_transitions == 120
    assert calibrated["heldout_mse"] < 1e-8 < 1e-3 < nominal["heldout_mse"]


def test_the_calibrated_json_of_rl2s_diagnose_is_the_simulator(pm, tmp_path):
    """`rl2s diagnose --physics` on Hopper data with the leg's gear planted at 0.7 x writes a
    calibrated.json that ``physics_simulator`` takes as it is: the gear it names, and the
    planted system's one-step error (~0, where the nominal model's is not)."""
    from rl2s_jax.app.physics_diagnosis import PhysicsSpec, diagnose_physics
    from rl2s_jax.data.dataset import save_dataset
    from rl2s_jax.physics.identify import FitConfig
    from rl2s_jax.physics.measured import Planted, collect_measured
    from rl2s_jax.physics.physics_simulator import one_step_mse, physics_simulator
    from rl2s_jax.policy.policy import index_params
    from rl2s_jax.zoo.zoo import load_zoo

    ds = collect_measured(pm, index_params(load_zoo("hopper").params, [4, 7, 16, 21]),
                          transitions_per_policy=200, episode_length=100, seed=2,
                          changes=[Planted("actuator_gear", "leg_joint", 0.7)])
    save_dataset(str(tmp_path / "gear.npz"), ds)
    diagnose_physics(PhysicsSpec(data=str(tmp_path / "gear.npz"), out=str(tmp_path / "diag"),
                                 fit=FitConfig(rows=128, bootstrap=20), k=3, quiet=True))
    sim = physics_simulator(str(tmp_path / "diag" / "calibrated.json"), "hopper", 12, 3)
    assert np.exp(sim.theta[pm.index("actuator_gear", "leg_joint")]) == pytest.approx(0.7,
                                                                                     rel=0.01)
    calibrated = one_step_mse(sim, ds)["heldout_mse"]
    assert calibrated < 1e-3 * one_step_mse(physics_simulator("nominal", "hopper"),
                                            ds)["heldout_mse"]


def test_calibrated_json_gives_its_structure(pm, tmp_path):
    """The integrator and the switched contacts the diagnosis chose reach the simulator's
    model (`rl2s evaluate --physics` ran the XML's integrator before); bad ones are refused
    by field."""
    import mujoco

    from rl2s_jax.physics.physics_simulator import physics_simulator

    c = json.loads(open(_calibrated(pm, tmp_path / "c.json")).read())
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**c, "integrator": "RK4", "collisions": {"leg_geom": True}}))
    sim = physics_simulator(str(path), "hopper", 12, 3)
    leg = mujoco.mj_name2id(sim.pm.mj, mujoco.mjtObj.mjOBJ_GEOM, "leg_geom")
    assert sim.pm.mj.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert sim.pm.mj.geom_contype[leg] == 1 and pm.mj.geom_contype[leg] == 0
    assert sim.theta == physics_simulator(str(tmp_path / "c.json"), "hopper", 12, 3).theta
    for field, bad, want in (("integrator", "Verlet", "integrator: expected one of Euler"),
                             ("collisions", {"leg_geom": 1}, "collisions: expected"),
                             ("collisions", {"shin": True},
                              "collisions: expected geom names .* 'shin'")):
        path.write_text(json.dumps({**c, field: bad}))
        with pytest.raises(ValueError, match=f"physics: {path}: {want}"):
            physics_simulator(str(path), "hopper", 12, 3)


SLIDER = """<mujoco><option timestep="0.05"/><worldbody><body name="mass">
<joint name="x" type="slide" axis="1 0 0" damping="0.1"/><geom size="0.1" mass="1"/></body>
</worldbody><actuator><motor joint="x" gear="2"/></actuator></mujoco>"""


def test_a_users_mjcf_takes_the_data_s_task(tmp_path):
    """A calibrated.json of no registered task ("task": null) names the MJCF; the data's task
    (pointmass: obs (p, v), one action) gives the rewards, its sizes checked."""
    from rl2s_jax.physics.physics_simulator import physics_simulator

    xml = tmp_path / "slider.xml"
    xml.write_text(SLIDER)
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"task": None, "xml": str(xml), "n_frames": 2}))
    sim = physics_simulator(str(path), "pointmass", 2, 1)
    assert (sim.pm.task, sim.pm.n_frames, sim.task, sim.delays) == (None, 2, "pointmass", (0,))
    assert sim.theta == (0.0,) * len(sim.pm.candidates) and sim.markov
    with pytest.raises(ValueError, match=r"sizes \(2, 1\) differ from the data's \(4, 1\)"):
        physics_simulator(str(path), "pointmass", 4, 1)
    path.write_text(json.dumps({"task": None, "xml": str(tmp_path / "none.xml")}))
    with pytest.raises(ValueError, match="physics: .*xml: expected the MJCF file"):
        physics_simulator(str(path), "pointmass", 2, 1)


def test_improve_takes_the_physics_as_its_simulator(pm, data_path, tmp_path):
    """What `rl2s improve --physics` builds before SAC (nothing compiled here; the whole command
    ran by hand, docs/DIAGNOSIS.md): the physics for the data, its env carrying the delay's
    past, one member for the guard, and no disagreement to penalise."""
    import jax

    from rl2s_jax.app.improvement import simulator_of
    from rl2s_jax.app.specs import ImproveSpec
    from rl2s_jax.improve.physics_env import PhysicsEnv
    from rl2s_jax.physics.physics_simulator import PhysicsSimulator

    path = _calibrated(pm, tmp_path / "c.json")
    sim, ds, ids, inside = simulator_of(ImproveSpec(data=data_path, out=str(tmp_path / "o"),
                                                    physics=path, policies=[1, 3]))
    assert isinstance(sim, PhysicsSimulator) and list(sim.delays) == DELAYS
    assert ids == [1, 3] and ds.n_policies == 6
    assert inside == {"checkpoint": None, "physics": path}
    assert sim.n_members == 1 and sim.replace(member_mode="fixed", rank=None) is sim
    env = PhysicsEnv(sim, np.asarray(ds.obs)[:4])
    state = env.reset(jax.random.PRNGKey(0))
    assert state.pipeline_state[1].past_act.shape == (2, 3)  # max delay 2, 3 actuators
    with pytest.raises(ValueError, match="uncertainty_penalty / uncertainty_threshold: u is"):
        PhysicsEnv(sim, np.asarray(ds.obs)[:4], uncertainty_penalty=1.0)


def test_bad_physics_input_is_refused_naming_the_field(pm, data_path, tmp_path):
    from rl2s_jax.app.specs import EvaluateSpec, ImproveSpec
    from rl2s_jax.improve.gym_env import make_simulator_env
    from rl2s_jax.physics.physics_simulator import physics_simulator

    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    cases = [
        (lambda: physics_simulator(str(tmp_path / "none.json"), "hopper"),
         "physics: no such file"),
        (lambda: physics_simulator(str(bad_json), "hopper"), "is not a calibrated.json"),
        (lambda: physics_simulator(_calibrated(pm, tmp_path / "w.json", task="walker2d"),
                                   "hopper"),
         "physics: .* models task 'walker2d' but the data is task 'hopper'"),
        (lambda: physics_simulator(_calibrated(pm, tmp_path / "t.json", theta=[0.0] * 3,
                                               labels=None), "hopper"),
         rf"physics: .*theta: expected shape \({len(pm.candidates)},\)"),
        (lambda: physics_simulator(_calibrated(pm, tmp_path / "d.json", delays=[0, -1, 0]),
                                   "hopper"), "physics: .*delays: expected 3 non-negative"),
        (lambda: physics_simulator(_calibrated(pm, tmp_path / "l.json", labels=["x"]),
                                   "hopper"), "physics: .*labels: its 1 quantities"),
        (lambda: physics_simulator("nominal", "pointmass"),
         "physics: 'nominal' is the data's task's MuJoCo model, and its task 'pointmass'"),
        (lambda: EvaluateSpec(data=data_path, physics="nominal", ckpt=["c"]),
         "physics: .*drop --ckpt"),
        (lambda: EvaluateSpec(data=data_path, physics="nominal", oracle=True),
         "physics: .*drop --oracle"),
        (lambda: EvaluateSpec(data=data_path, physics="nominal", calibration=["c.npz"]),
         "physics: .*drop --calibration"),
        (lambda: ImproveSpec(data=data_path, out="o", physics="nominal", ckpt="c"),
         "physics: .*drop --ckpt"),
        (lambda: ImproveSpec(data=data_path, out="o", physics="nominal",
                             uncertainty_penalty=1.0), "physics: --uncertainty-penalty"),
        (lambda: ImproveSpec(data=data_path, out="o"), "ckpt: required"),
        (lambda: make_simulator_env(data=data_path), "physics: give ckpt= .* or physics="),
        (lambda: make_simulator_env("c", data_path, physics="nominal"),
         "physics: give ckpt= .* or physics="),
    ]
    for make, message in cases:
        with pytest.raises(ValueError, match=message):
            make()


def test_cli_refuses_physics_with_ckpt_in_one_line(data_path, capsys):
    from rl2s_jax import cli

    assert cli.main(["evaluate", "--data", data_path, "--physics", "nominal", "--ckpt",
                     "c"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rl2s evaluate: error: physics:") and "\n" not in err
