"""The oracle simulator (real dynamics through the learned simulator's evaluation path)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_train import _policies as _pm_policies  # biased pointmass policies

from rl2s_jax.data.collect import collect
from rl2s_jax.envs.tasks import get_task, pointmass_dynamics
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.evaluate.scores import evaluate_oracle
from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo import zoo as zoo_mod


def test_pointmass_oracle_is_the_true_dynamics():
    obs = jax.random.normal(jax.random.PRNGKey(0), (3, 5, 2))
    act = jax.random.uniform(jax.random.PRNGKey(1), (3, 5, 1), minval=-2, maxval=2)
    got = oracle_dynamics("pointmass")(obs, act, jax.random.PRNGKey(2))
    np.testing.assert_array_equal(got, pointmass_dynamics(obs, act))


def test_pointmass_oracle_ranks_perfectly_with_vd_within_noise():
    # Policies pushing ever harder one way: each is clearly worse than the one before.
    task = get_task("pointmass")
    pols = _pm_policies([0.0, 0.6, 1.0, 1.6])
    ds = collect(task.make_env(), pols, key=jax.random.PRNGKey(0), transitions_per_policy=400,
                 envs_per_policy=8, episode_length=task.episode_length, task="pointmass",
                 value_episodes=64, progress=False)
    r = evaluate_oracle("pointmass", ds, pols, key=jax.random.PRNGKey(1), n_episodes=256,
                        n_boot=200)
    true = np.asarray(r["true_value"])
    assert np.all(np.diff(true) < 0), true  # the construction worked: strictly worse
    assert r["metrics"]["kendall_tau"] == 1.0
    # VD within the noise of the two estimates: true from 64 real episodes (its se), simulated
    # from 256 episodes started at the data's start states.
    se = np.hypot(np.asarray(ds.value_discounted_se), np.asarray(r["intervals"]["metrics"]
                                                                 ["avd"]["std"]))
    assert np.all(np.asarray(r["vd"]) < 4 * se + 0.05 * np.abs(true)), (r["vd"], se)
    iv = r["intervals"]
    assert iv["metrics"]["kendall_tau"]["lo"] <= 1.0 == iv["metrics"]["kendall_tau"]["hi"]


@pytest.mark.slow
def test_hopper_oracle_steps_like_the_env_and_ranks_a_short_horizon(env_cache, hopper_train_ds):
    """On logged Hopper transitions the oracle's next observation is the env's (but for the
    clipped velocities and the solver's warm start), and over the data's 40-step horizon it
    orders every pair of zoo policies whose true values the data resolves, with VD within
    noise. (The data: conftest's hopper_train_ds, whose MJX collection compiles once for the
    tests that use it; four of its policies spread over the zoo's returns.)"""
    task = get_task("hopper")
    env = env_cache("hopper")
    zoo = zoo_mod.load_zoo("hopper")
    train = np.asarray(zoo.train_ids)
    order = np.argsort(zoo.returns[train])
    rows = [int(order[round(q * (len(order) - 1))]) for q in (0.0, 0.33, 0.66, 1.0)]
    ds = hopper_train_ds.select_policies(rows)
    ids = [int(train[r]) for r in rows]
    pols = pol.index_params(zoo.params, ids)
    assert ds.meta["policy_names"] == zoo.policy_names(ids)
    dyn = jax.jit(oracle_dynamics(task, env))
    obs, act, nxt = (jnp.asarray(x) for x in (ds.obs, ds.action, ds.next_obs))
    err = np.abs(np.asarray(dyn(obs, act, jax.random.PRNGKey(0))) - np.asarray(nxt)).max(-1)
    clipped = np.abs(np.asarray(ds.next_obs)[:, 6:]).max(-1) >= 10.0
    assert np.median(err) < 1e-4 and np.mean(err[~clipped] < 1e-2) > 0.95, np.quantile(
        err, [0.5, 0.9, 0.99])

    r = evaluate_oracle("hopper", ds, pols, key=jax.random.PRNGKey(1), n_episodes=24,
                        horizon=40)
    true, sim = np.asarray(r["true_value"]), np.asarray(r["sim_value"])
    se = np.asarray(ds.value_discounted_se)
    i, j = np.triu_indices(len(ids), 1)
    resolved = np.abs(true[i] - true[j]) > 4 * np.hypot(se[i], se[j])
    assert resolved.sum() >= 2, (true, se)
    assert np.all(np.sign(true[i] - true[j])[resolved] == np.sign(sim[i] - sim[j])[resolved]), \
        (true, sim, se)
    assert np.all(np.abs(true - sim) < 4 * se + 0.1 * np.abs(true)), (true, sim, se)


def test_oracle_refuses_a_task_it_cannot_step():
    from rl2s_jax.envs.tasks import Task

    bogus = Task("bogus", 2, 1, 10, make_env=None, reward_fn=None, done_fn=None, dt=0.1)
    with pytest.raises(ValueError, match="no oracle for 'bogus'"):
        oracle_dynamics(bogus)
