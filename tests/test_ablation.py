"""experiments/ablation_model.py and its package parts (rl2s_jax.paper.ablation,
rl2s_jax.evaluate.errors): the evaluation point is chosen on the training policies only
(highest selection tau, ties to the lower selection AVD, non-finite last), the table reports
the TEST metrics at that point and at the last one, averaged over seeds; the diagnostics and
their control scripts."""
import json

import numpy as np
import pytest
from experiment_scripts import load_script

from rl2s_jax.data.summary import episode_lengths
from rl2s_jax.evaluate import errors
from rl2s_jax.paper import ablation as abl
from rl2s_jax.train.lanes import select_point
from rl2s_jax.train.step import simulator

_script = load_script


@pytest.fixture(scope="module")
def ab():
    return _script("ablation_model")


def _m(tau, avd, ndcg=1.0):
    return {"kendall_tau": tau, "ndcg@1": ndcg, "avd": avd, "mvd": 2 * avd, "spearman": tau}


def test_selection_uses_training_policies_only(tmp_path):
    seed0 = [  # test tau would favour step 100; the training policies pick step 200
        {"step": 100, "test": _m(0.9, 10.0), "select": _m(0.2, 5.0)},
        {"step": 200, "test": _m(0.4, 30.0), "select": _m(0.6, 9.0)},
        {"step": 300, "test": _m(0.5, 20.0), "select": _m(0.6, 8.0)},   # tie: lower AVD wins
        {"step": 400, "test": _m(0.1, 50.0), "select": _m(float("nan"), 1.0)},
    ]
    seed1 = [
        {"step": 100, "test": _m(0.3, 40.0), "select": _m(0.7, 3.0)},
        {"step": 200, "test": None, "select": _m(0.9, 1.0)},            # diverged: skipped
        {"step": 300, "test": _m(0.2, 60.0, ndcg=0.5), "select": _m(0.1, 2.0)},
    ]
    assert select_point(seed0)["step"] == 300 and select_point(seed1)["step"] == 100
    res = {"task": "hopper", "variant": "rl2s", "hardware": "cpu", "jax_version": "x",
           "command": "c", "timings": {}, "complete": True,
           "curves": {"rl2s": {"0": seed0, "1": seed1}}}
    table = abl.summarize_rows([res])["rl2s"]
    assert table["selected_steps"] == [300, 100]
    mean, std, n = table["selected"]["kendall_tau"]
    assert n == 2 and mean == pytest.approx(0.4) and std == pytest.approx(np.std([0.5, 0.3],
                                                                                ddof=1))
    assert table["final"]["avd"][:1] == (pytest.approx(55.0),)       # steps 400 and 300
    assert table["final"]["ndcg@1"][0] == pytest.approx(0.75)
    path = tmp_path / "ablation_hopper_rl2s.json"
    path.write_text(json.dumps(res))
    md = abl.write_summary(str(tmp_path), "hopper", [str(path)])
    assert md.splitlines()[2].startswith("| rl2s | 0.15")
    assert json.loads((tmp_path / "ablation_hopper.json").read_text())["rows"]["rl2s"][
        "selected_steps"] == [300, 100]


def test_tau_swing_from_the_adversarial_phase(tmp_path):
    """The swing is the mean |change| of test tau between consecutive evaluations, taken from
    the end of pre-training (a pre-trained run's first points are the MLE start), skipping
    diverged points; per lane, then mean and std over lanes."""
    taus = {"0": [0.1, 0.6, 0.5, 0.8, 0.7], "1": [0.9, 0.7, 0.7, 0.4, float("nan")]}
    lanes = {s: [{"step": 100 * (i + 1), "test": _m(t, 10.0), "select": _m(0.5, 1.0)}
                 for i, t in enumerate(ts)] for s, ts in taus.items()}
    lanes["1"][2]["test"] = None                                   # a diverged evaluation
    res = {"task": "hopper", "variant": "rl2s", "hardware": "cpu", "jax_version": "x",
           "command": "c", "timings": {}, "complete": True,
           "config": {"method": "rl2s", "pretrain_steps": 200}, "curves": {"rl2s": lanes}}
    # from step 200: lane 0 [0.6, 0.5, 0.8, 0.7]; lane 1 [0.7, (None), 0.4, (nan)]
    ref = [np.mean(np.abs(np.diff([0.6, 0.5, 0.8, 0.7]))), abs(0.4 - 0.7)]
    mean, std, n = abl.summarize_rows([res])["rl2s"]["tau_swing"]
    assert n == 2 and mean == pytest.approx(np.mean(ref))
    assert std == pytest.approx(np.std(ref, ddof=1))
    # an MLE variant (no pre-training phase) counts every evaluation
    res["config"] = {"method": "bc", "pretrain_steps": 200}
    assert abl.summarize_rows([res])["rl2s"]["tau_swing"][0] == pytest.approx(np.mean(
        [np.mean(np.abs(np.diff(taus["0"]))), np.mean(np.abs(np.diff([0.9, 0.7, 0.4])))]))
    assert abl.tau_swing(lanes["0"][:1]) is None                    # one point: no swing
    path = tmp_path / "ablation_hopper_rl2s.json"
    path.write_text(json.dumps(res))
    assert "tau swing" in abl.write_summary(str(tmp_path), "hopper", [str(path)]).splitlines()[0]


def test_rollout_settings_parse_and_reject_bad_input():
    assert abl.parse_rollouts("random:1, mean:0,fixed:0.5") == [
        ("random", 1.0), ("mean", 0.0), ("fixed", 0.5)]
    assert abl.parse_rollouts(None) == [] and abl.parse_rollouts("") == []
    assert abl.parse_rollouts("random:0:predictive,mean:1:rule") == [
        ("random", 0.0, "predictive"), ("mean", 1.0, "rule")]
    assert abl.rollout_row("rl2s", ("random", 0.0, "both")) == "rl2s@random:0:both"
    assert abl.rollout_row("rl2s", ("mean", 1.5)) == "rl2s@mean:1.5"
    for bad in ("average:0", "mean", "mean:-1", "mean:x", "random:nan", "random:0:often"):
        with pytest.raises(SystemExit, match="rollouts"):
            abl.parse_rollouts(bad)


def test_variant_specs_carry_their_own_settings(ab):
    assert abl.parse_variant("bc") == ("bc", {})
    assert abl.parse_variant("bc:multistep_steps=5+multistep_weight=0.5") == (
        "bc", {"multistep_steps": 5, "multistep_weight": 0.5})
    with pytest.raises(SystemExit, match="variants"):
        abl.parse_variant("mle:multistep_steps=5")
    with pytest.raises(SystemExit, match="multistep_steps"):   # checked before any work
        ab.main(["--task", "hopper", "--variants", "bc:multistep_steps=0", "--out", "/tmp/x"])
    with pytest.raises(SystemExit, match="no_such_key"):
        ab.main(["--task", "hopper", "--variants", "bc:no_such_key=1", "--out", "/tmp/x"])


def test_episode_lengths_count_whole_episodes():
    from types import SimpleNamespace
    # policy 0: episodes of 3 (done) and 5 (truncated), then 2 cut-off rows; policy 1: one
    # cut-off episode of 4 rows (no whole one: its rows count)
    ep = np.array([0] * 3 + [1] * 5 + [2] * 2 + [3] * 4)
    pid = np.array([0] * 10 + [1] * 4)
    done = np.zeros(14, bool)
    trunc = np.zeros(14, bool)
    done[2], trunc[7] = True, True
    ds = SimpleNamespace(policy_id=pid, episode_id=ep, done=done, truncated=trunc, n_policies=2)
    np.testing.assert_allclose(episode_lengths(ds), [4.0, 4.0])


def test_hazard_check_reads_each_lanes_learned_hazard(pm_falls):
    """hazard_check on two lanes' simulators: per lane the summed h(s, a) over the data's rows
    and its cross-entropy, against the hazard each lane learned (model.termination)."""
    import jax
    import jax.numpy as jnp

    from rl2s_jax.model.termination import hazard_prob
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.lanes import init_lanes

    ds, params = pm_falls
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_every=0, termination="both",
                            hazard_hidden=(16,), hazard_steps=20)
    states = init_lanes(jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)]), cfg,
                        make_train_data(ds, params, cfg))
    res = errors.hazard_check(simulator(states, average=False), ds)
    done = np.asarray(ds.done)
    assert res["rows"] == done.size and res["done"] == int(done.sum())
    for lane in range(2):
        lane_state = jax.tree_util.tree_map(lambda x, i=lane: x[i], states)
        h = np.asarray(hazard_prob(lane_state.hazard, lane_state.norm, jnp.asarray(ds.obs),
                                   jnp.asarray(ds.action), cfg.outcome.hazard_window), np.float64)
        assert res["predicted"][lane] == pytest.approx(h.sum(), abs=0.1)
        p = np.clip(h, 1e-7, 1 - 1e-7)
        bce = -np.mean(done * np.log(p) + (1 - done) * np.log1p(-p))
        assert res["bce"][lane] == pytest.approx(bce, abs=1e-4)
    assert res["predicted"][0] != res["predicted"][1]  # each lane its own hazard


def test_termination_causes_split_the_done_rule():
    from rl2s_jax.envs.tasks import get_task
    o = np.zeros((5, 12), np.float32)
    o[:, 1] = 1.2
    o[0, 1] = 0.5            # fell
    o[1, 2] = 0.3            # tilted
    o[2, 1], o[2, 2] = 0.6, -0.25   # both
    o[3, 7] = 150.0          # a velocity blew up
    ended = np.array([True, True, True, True, False])   # the last one ran to the horizon
    causes = errors.termination_causes("hopper", o, ended)
    assert causes == {"ended": 0.8, "z <= 0.7": 0.5, "|angle| >= 0.2": 0.5,
                      "|q[2:], qd| >= 100": 0.25}
    # every ended state breaks some rule, exactly as the task's done_fn says
    done = np.asarray(get_task("hopper").done_fn(o))
    assert done[:4].all() and not done[4]
    assert errors.termination_causes("halfcheetah", o, ended) is None


def test_terminal_states_are_where_the_value_rollouts_stop():
    """terminal_states runs the episodes of simulate.simulated_returns (same keys, same
    draws): an episode ended there iff its rollout stopped before the horizon, and its
    terminal state is one the task's done_fn ends on."""
    import jax
    import jax.numpy as jnp
    from test_train import _policies as _pm_policies  # biased pointmass policies

    from rl2s_jax import train as T
    from rl2s_jax.data.collect import collect
    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.model.simulator import simulated_returns, start_pool

    task = get_task("pointmass")
    policies = _pm_policies([-2.0, 0.0, 2.0])
    ds = collect(task.make_env(), policies, key=jax.random.PRNGKey(0), transitions_per_policy=200,
                 envs_per_policy=2, episode_length=task.episode_length, task="pointmass",
                 value_episodes=2, progress=False)
    cfg = T.TrainConfig.small(task="pointmass", method="bc", vd_every=0, vd_horizon=40)
    data = T.make_train_data(ds, policies, cfg)
    sim = T.simulator(T.train_steps(T.init(jax.random.PRNGKey(1), cfg, data), data, 5)[0])
    pool, key, horizon = start_pool(ds), jax.random.PRNGKey(9), 40
    lanes = jax.tree_util.tree_map(lambda x: x[None], sim)
    terminal, ended = errors.terminal_states(lanes, policies, pool, key[None], task=task,
                                         n_episodes=6, horizon=horizon)
    terminal, ended = np.asarray(terminal[0]), np.asarray(ended[0])
    _, length = simulated_returns(policies, sim.dynamics, task.reward_fn, task.done_fn, pool,
                                  key, n_episodes=6, horizon=horizon, gamma=0.99)
    length = np.asarray(length)
    assert ended.any() and (~ended).any()
    assert np.all(ended[length < horizon]) and np.all(length[~ended] == horizon)
    done = np.asarray(task.done_fn(jnp.asarray(terminal)))
    np.testing.assert_array_equal(done[ended], True)


def test_open_loop_check_compares_each_lane_with_the_logged_windows(pm_falls):
    """Two lanes of an (untrained) pointmass BC model: the real side is the logged windows'
    reward sums (NumPy), the model side each lane's own open-loop rollout, and the summaries
    are what their definitions say."""
    import jax
    import jax.numpy as jnp

    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.model.simulator import logged_window_returns, open_loop_windows
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init

    ds, params = pm_falls
    task = get_task("pointmass")
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=20, vd_every=3)
    data = make_train_data(ds, params, cfg)
    states = jax.vmap(lambda k: init(k, cfg, data))(jnp.stack(
        [jax.random.PRNGKey(0), jax.random.PRNGKey(1)]))
    res = errors.open_loop_check(simulator(states, average=False), ds, task, ks=(1, 5),
                                 n_windows=64)
    rows, steps = open_loop_windows(ds, 5, 64, seed=7)
    real, real_end = logged_window_returns(ds, rows, steps, 5, task.reward_fn)
    np.testing.assert_allclose(res["5"]["real_per_policy"], real.sum(-1).mean(-1), atol=0.01)
    assert res["5"]["real_end"] == pytest.approx(real_end.mean(), abs=1e-4)
    model = np.asarray(res["5"]["model_per_policy"])
    assert model.shape == (2, ds.n_policies) and not np.allclose(model[0], model[1])
    ratio = np.std(model, axis=1) / np.std(real.sum(-1).mean(-1))
    np.testing.assert_allclose(res["5"]["spread_ratio"], ratio, atol=2e-3)
    assert all(-1 <= t <= 1 for t in res["1"]["tau"] + res["5"]["tau"])
    assert res["1"]["real_end"] <= res["5"]["real_end"]  # windows end more often when longer


def test_validation_policies_are_spread_over_the_values_and_held_out_whole(pm_falls):
    ds, _ = pm_falls
    ds = ds.replace(meta={**ds.meta, "source": {"zoo": "z", "zoo_ids": [10, 11, 12, 13]}})
    order = np.argsort(np.asarray(ds.value_discounted))
    fit, valid = abl.split_validation(ds, 2)
    held = sorted([int(order[1]), int(order[3])])  # the middle of each half of the ranking
    assert valid.meta["source"]["zoo_ids"] == [10 + i for i in held]
    assert fit.meta["source"]["zoo_ids"] == [10 + i for i in range(4) if i not in held]
    assert valid.n_transitions + fit.n_transitions == ds.n_transitions
    np.testing.assert_allclose(np.asarray(valid.value_discounted),
                               np.asarray(ds.value_discounted)[held])
    with pytest.raises(SystemExit, match="validation-policies: expected 2 ... 2"):
        abl.split_validation(ds, 3)


@pytest.fixture(scope="module")
def olc():
    return _script("open_loop_control")


def test_open_loop_control_reproduces_the_logged_windows_without_noise(olc, pm_falls):
    """experiments/open_loop_control.py: the real dynamics under the logged actions give the
    logged k-step returns (pointmass's oracle is exact), and an added step error moves them."""
    from rl2s_jax.envs.tasks import get_task

    ds, _ = pm_falls
    res = olc.run(ds, get_task("pointmass"), ks=(1, 5), n_windows=32, scales=[0.0, 0.5],
                  seeds=2)
    exact, noisy = res["scales"]["0.0"], res["scales"]["0.5"]
    for k in ("1", "5"):
        assert exact[k]["tau"] == [1.0, 1.0] and exact[k]["spread_ratio"] == [1.0, 1.0]
        assert exact[k]["relative_error"] == [0.0, 0.0]
        assert exact[k]["model_end"] == [exact[k]["real_end"]] * 2
        assert min(noisy[k]["relative_error"]) > 0.0
    np.testing.assert_allclose(exact["5"]["model_per_policy"][0], exact["5"]["real_per_policy"],
                               atol=0.01)


def test_open_loop_control_noise_scale_and_bad_input(olc, pm_falls):
    ds, _ = pm_falls
    delta = np.asarray(ds.next_obs, np.float64) - np.asarray(ds.obs, np.float64)
    std = errors.one_step_std(ds, (0,))
    assert std[0] == 0.0  # a position dim gets no noise
    np.testing.assert_allclose(std[1:], delta.std(0)[1:], rtol=1e-5)
    for argv, field in ((["--noise", "a"], "noise"), (["--noise", "-1"], "noise"),
                        (["--windows", "0"], "windows"), (["--ks", "0,5"], "ks")):
        with pytest.raises(SystemExit, match=field):
            olc.main(argv + ["--out", "/tmp/olc_bad_input"])


def test_closed_loop_control_pairs_every_scale_with_the_exact_dynamics(pm_falls):
    """experiments/closed_loop_control.py on pointmass (exact oracle): the exact values are
    simulated_returns' on key 0, a vanishing step error leaves them (paired keys), a large one
    moves them, and another key gives other episodes."""
    import jax

    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.evaluate.oracle import oracle_dynamics
    from rl2s_jax.model.simulator import simulated_returns, start_pool

    clc = _script("closed_loop_control")
    ds, params = pm_falls
    task = get_task("pointmass")
    res = clc.run(ds, task, params, scales=[1e-6, 0.5], n_episodes=8, horizon=20, gamma=0.99)
    ret, _ = simulated_returns(params, oracle_dynamics(task), task.reward_fn, task.done_fn,
                               start_pool(ds), jax.random.PRNGKey(0), n_episodes=8,
                               horizon=20, gamma=0.99)
    np.testing.assert_allclose(res["exact"]["value"], np.asarray(ret).mean(-1), atol=0.01)
    tiny, big = res["scales"]["1e-06"], res["scales"]["0.5"]
    assert tiny["tau_vs_exact"] == 1.0 and tiny["relative_change"] < 1e-3
    assert big["relative_change"] > 10 * max(tiny["relative_change"], 1e-4)
    assert res["exact_other_keys"]["value"] != res["exact"]["value"]
    with pytest.raises(SystemExit, match="noise"):
        clc.main(["--noise", "0", "--out", "/tmp/clc_bad_input"])


def test_visited_error_check_measures_each_lane_against_the_real_dynamics(pm_falls):
    """Two lanes of an untrained pointmass BC model: per lane and test policy, the one-step
    error on visited and on logged states (pointmass's oracle is its exact dynamics), in the
    shapes the JSON keeps; the logged error against a NumPy computation at member mode
    'fixed' (the best member's mean: no draw)."""
    import jax
    import jax.numpy as jnp

    from rl2s_jax.envs.tasks import get_task, pointmass_dynamics
    from rl2s_jax.model.simulator import start_pool
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init, simulator

    ds, params = pm_falls
    task = get_task("pointmass")
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=20, vd_every=3,
                            member_mode="fixed")
    data = make_train_data(ds, params, cfg)
    states = jax.vmap(lambda k: init(k, cfg, data))(jnp.stack(
        [jax.random.PRNGKey(0), jax.random.PRNGKey(1)]))
    test = (params, start_pool(ds), None)
    res = errors.visited_error_check(simulator(states, average=False), ds, test, task,
                                     n_episodes=3, horizon=20, rows_per_policy=64, train_ds=ds)
    P = ds.n_policies
    for side in ("visited", "logged", "train_logged"):
        for k in ("rmse", "reward_bias", "reward_abs"):
            assert np.asarray(res[side][k]).shape == (2, P)
        assert np.asarray(res[side]["rmse_per_dim"]).shape == (2, 2)
        assert np.all(np.asarray(res[side]["rmse"]) > 0)  # an untrained model errs
        assert np.all(np.asarray(res[side]["reward_abs"]) + 1e-4
                      >= np.abs(np.asarray(res[side]["reward_bias"])))
    assert np.all((np.asarray(res["visited_steps"]) >= 3)
                  & (np.asarray(res["visited_steps"]) <= 60))
    # the logged side by NumPy: the same rows (seed 11), the lane's own model and scale
    rng = np.random.default_rng(11)
    pid = np.asarray(ds.policy_id)
    idx = np.stack([rng.choice(np.flatnonzero(pid == p), 64) for p in range(P)])
    obs, act = np.asarray(ds.obs)[idx], np.asarray(ds.action)[idx]
    for lane in range(2):
        sim = simulator(jax.tree_util.tree_map(lambda x, i=lane: x[i], states), average=False)
        model = np.asarray(sim.mean(jnp.asarray(obs), jnp.asarray(act)), np.float64)
        true = np.asarray(pointmass_dynamics(jnp.asarray(obs), jnp.asarray(act)), np.float64)
        z = (model - true) / np.asarray(sim.norm.delta_std, np.float64)
        np.testing.assert_allclose(res["logged"]["rmse"][lane],
                                   np.sqrt((z ** 2).mean(-1).mean(-1)), rtol=2e-3, atol=1e-4)
        np.testing.assert_allclose(res["logged"]["rmse_per_dim"][lane],
                                   np.sqrt((z ** 2).mean((0, 1))), rtol=2e-3, atol=1e-4)


def test_oracle_step_check_is_exact_on_pointmass(olc, pm_falls):
    from rl2s_jax.envs.tasks import get_task

    ds, _ = pm_falls
    check = olc.oracle_step_check(ds, get_task("pointmass"), n_rows=100)
    assert check["rows"] == 100 and check["rmse"] < 1e-5 and check["reward_abs"] < 1e-5
    assert len(check["rmse_per_dim"]) == 2


def test_plot_controls_reads_the_control_runs_and_draws_them(tmp_path):
    pc = _script("plot_controls")
    open_run = {"task": "ant", "scales": {
        "0.0": {"50": {"relative_error": [0.01, 0.03]}},
        "0.1": {"50": {"relative_error": [0.5, 0.6]}}}}
    closed_run = {"task": "ant", "episodes": 8, "exact_other_keys": {"tau_vs_exact": 0.8},
                  "scales": {"0.1": {"tau_vs_exact": 0.7, "spread_ratio": 0.6,
                                     "relative_change": 0.3}}}
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "open_loop_control_ant.json").write_text(json.dumps(open_run))
    (tmp_path / "runs" / "closed_loop_control_ant.json").write_text(json.dumps(closed_run))
    s, err = pc.open_loop_curve(open_run)
    np.testing.assert_allclose(s, [0.0, 0.1])
    np.testing.assert_allclose(err, [0.02, 0.55])
    s, tau = pc.closed_loop_curve(closed_run, "tau_vs_exact")
    np.testing.assert_allclose(s, [0.0, 0.1])
    np.testing.assert_allclose(tau, [1.0, 0.7])
    out = tmp_path / "fig.png"
    assert pc.main(["--runs", str(tmp_path / "runs"), "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
    with pytest.raises(SystemExit, match="runs"):
        pc.main(["--runs", str(tmp_path / "empty"), "--out", str(out)])
    with pytest.raises(SystemExit, match="model"):
        pc.main(["--runs", str(tmp_path / "runs"), "--model", "ant=/nonexistent.json"])


def test_model_fit_measures_the_elites_average_and_learns_pointmass(pm_falls):
    """experiments/model_fit.py: the step error of the elites' average mean, against NumPy on
    an untrained two-lane model, and a BC fit on pointmass (linear dynamics) whose error on
    every set falls well below the untrained one's; variant specs and bad input."""
    import jax
    import jax.numpy as jnp

    mf = _script("model_fit")
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init

    ds, params = pm_falls
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_every=0, n_elites=2,
                            holdout_frac=0.25)
    data = make_train_data(ds, params, cfg)
    states = jax.vmap(lambda k: init(k, cfg, data))(jnp.stack([jax.random.PRNGKey(0),
                                                               jax.random.PRNGKey(1)]))
    rows = mf.logged_rows(ds.obs, ds.action, ds.next_obs, 100, 0)
    got = jax.vmap(lambda s: mf.step_error(s.gen, s.rank, s.norm, 2, *rows))(states)
    obs, act, nxt = (np.asarray(x, np.float64) for x in rows)
    for lane in range(2):
        s = jax.tree_util.tree_map(lambda x, i=lane: x[i], states)
        from rl2s_jax.model import dynamics as dyn
        means = np.asarray(dyn.ensemble_dist(s.gen, dyn.markov_inputs(
            s.norm, jnp.asarray(rows[0]), jnp.asarray(rows[1])))[0], np.float64)
        elites = np.argsort(np.asarray(s.rank))[:2]
        assert set(elites) == set(np.flatnonzero(np.asarray(s.rank) < 2))
        y = ((nxt - obs - np.asarray(s.norm.delta_mean)) / np.asarray(s.norm.delta_std))
        avg = means[elites].mean(0)
        np.testing.assert_allclose(float(got["rmse"][lane]), np.sqrt(((avg - y) ** 2).mean()),
                                   rtol=1e-4)
        np.testing.assert_allclose(np.asarray(got["rmse_per_dim"][lane]),
                                   np.sqrt(((avg - y) ** 2).mean(0)), rtol=1e-4)
        member = np.sqrt(((means[elites] - y) ** 2).mean((1, 2))).mean()
        np.testing.assert_allclose(float(got["member_rmse"][lane]), member, rtol=1e-4)
    # learning: 60 steps of BC take every set's error far below the untrained model's
    res = mf.fit_and_measure(cfg, ds, ds, dict(seeds=1, steps=60, eval_every=30, rows=512),
                             {}, policies=params)
    first = float(got["rmse"].mean())
    for name in ("train", "heldout", "test"):
        assert res["curves"][-1][name]["rmse"][0] < 0.2 * first, (name, res["curves"][-1])
    assert res["complete"] and len(res["rmse_per_dim"]["test"][0]) == 2
    row = f"| x | {res['curves'][-1]['train']['rmse'][0]:.3f} |"
    assert row in mf.table([{**res, "variant": "x", "train_seconds": 1.0}])
    # variant specs: hidden sizes by 'x' and '-', other keys as ablation_model's; bad input
    assert mf.parse_fit_variant("bc:gen_hidden=64x3+bc_lr=3e-4") == (
        "bc", {"gen_hidden": (64, 64, 64), "bc_lr": 3e-4})
    assert mf.parse_fit_variant("bc:gen_hidden=128-64")[1] == {"gen_hidden": (128, 64)}
    with pytest.raises(SystemExit, match="likelihood"):
        mf.parse_fit_variant("rl2s")
    with pytest.raises(SystemExit, match="gen_hidden"):
        mf.parse_fit_variant("bc:gen_hidden=x")
    # the whole --variants list is checked before any work (ablation_model.check_variants)
    assert mf.check_variants("pointmass", "bc,bc:gen_hidden=8x2,", mf.parse_fit_variant) == [
        "bc", "bc:gen_hidden=8x2"]
    with pytest.raises(SystemExit, match="bc_lr"):
        mf.check_variants("pointmass", "bc,bc:bc_lr=-1", mf.parse_fit_variant)
    with pytest.raises(SystemExit, match="likelihood"):
        mf.check_variants("pointmass", "bc,rl2s", mf.parse_fit_variant)
    with pytest.raises(SystemExit, match="variants"):
        mf.check_variants("pointmass", ",", mf.parse_fit_variant)
