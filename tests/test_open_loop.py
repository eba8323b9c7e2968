"""Open-loop rollouts under logged actions (rl2s_jax.simulate.open_loop_*): the windows against
a NumPy scan of the episodes, the true dynamics reproducing the logged rewards and ends
exactly, and a biased dynamics against a NumPy rollout."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.envs.tasks import get_task, pointmass_dynamics
from rl2s_jax.model.simulator import logged_window_returns, open_loop_returns, open_loop_windows

K = 12


def _windows_ref(ds, k):
    """Per row: (logged steps from it to its episode's end, that end is a termination)."""
    pid, eid, done = (np.asarray(x) for x in (ds.policy_id, ds.episode_id, ds.done))
    left, term = np.zeros(len(pid), int), np.zeros(len(pid), bool)
    for r in range(len(pid)):
        e = r
        while e + 1 < len(pid) and eid[e + 1] == eid[r] and pid[e + 1] == pid[r]:
            e += 1
        left[r], term[r] = e - r + 1, bool(done[e])
    return left, term


def test_windows_match_a_scan_of_the_episodes(pm_falls):
    ds, _ = pm_falls
    rows, steps = open_loop_windows(ds, K, 300, seed=1)
    left, term = _windows_ref(ds, K)
    assert rows.shape == steps.shape == (ds.n_policies, 300)
    assert np.all(np.asarray(ds.policy_id)[rows] == np.arange(ds.n_policies)[:, None])
    assert np.all((left[rows] >= K) | term[rows])  # never a window of unknown outcome
    np.testing.assert_array_equal(steps, np.minimum(left[rows], K))
    assert (steps < K).any() and (steps == K).any()  # both kinds occur in this data
    with pytest.raises(ValueError, match="k: expected an int >= 1"):
        open_loop_windows(ds, 0, 10)


def test_true_dynamics_reproduce_the_logged_windows(pm_falls):
    """Pointmass's own dynamics under the logged actions earn the logged rewards and end where
    the logged episodes ended."""
    ds, _ = pm_falls
    task = get_task("pointmass")
    rows, steps = open_loop_windows(ds, K, 200)
    real_r, real_end = logged_window_returns(ds, rows, steps, K, task.reward_fn)
    idx = rows[..., None] + np.minimum(np.arange(K), steps[..., None] - 1)
    r, live, ended = jax.jit(lambda o, a, s: open_loop_returns(
        lambda x, u, key: pointmass_dynamics(x, u), task.reward_fn, task.done_fn, o, a, s,
        jax.random.PRNGKey(0)))(jnp.asarray(np.asarray(ds.obs)[rows.ravel()]),
                                jnp.asarray(np.asarray(ds.action)[idx.reshape(-1, K)]),
                                jnp.asarray(steps.ravel()))
    np.testing.assert_allclose(np.asarray(r).reshape(real_r.shape), real_r, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(live).sum(-1).reshape(steps.shape), steps)
    assert real_end.any() and not real_end.all()
    np.testing.assert_array_equal(np.asarray(ended).any(-1).reshape(steps.shape), real_end)


def test_a_biased_dynamics_against_a_numpy_rollout(pm_falls):
    """The mass drifts outward by 0.05 a step: its windows end earlier and earn other rewards,
    as a plain NumPy loop over the same logged actions says."""
    ds, _ = pm_falls
    task = get_task("pointmass")
    rows, steps = open_loop_windows(ds, K, 50)
    rows, steps = rows.ravel(), steps.ravel()
    idx = rows[:, None] + np.minimum(np.arange(K), steps[:, None] - 1)
    obs0, acts = np.asarray(ds.obs, np.float64)[rows], np.asarray(ds.action, np.float64)[idx]

    def biased(x, u):
        nxt = np.asarray(pointmass_dynamics(jnp.asarray(x, jnp.float32),
                                            jnp.asarray(u, jnp.float32)), np.float64)
        return nxt + np.stack([0.05 * np.sign(x[..., 0]), 0 * x[..., 1]], -1)

    want_r, want_live = np.zeros((len(rows), K)), np.zeros((len(rows), K), bool)
    for i in range(len(rows)):
        s = obs0[i]
        for j in range(steps[i]):
            nxt = biased(s, acts[i, j])
            want_live[i, j] = True
            want_r[i, j] = 1 - nxt[0] ** 2 - 0.1 * acts[i, j, 0] ** 2
            if abs(nxt[0]) > 2.0:
                break
            s = nxt
    dyn = lambda x, u, key: (pointmass_dynamics(x, u)
                             + jnp.stack([0.05 * jnp.sign(x[..., 0]), 0 * x[..., 1]], -1))
    r, live, _ = open_loop_returns(dyn, task.reward_fn, task.done_fn,
                                   jnp.asarray(obs0, jnp.float32),
                                   jnp.asarray(acts, jnp.float32), jnp.asarray(steps),
                                   jax.random.PRNGKey(0))
    np.testing.assert_array_equal(np.asarray(live), want_live)
    np.testing.assert_allclose(np.asarray(r), want_r, atol=1e-4)
    real_r, _ = logged_window_returns(ds, rows, steps, K, task.reward_fn)
    assert np.abs(np.asarray(r) - real_r).max() > 0.01  # the bias is seen
    assert want_live.sum() < steps.sum()  # and it ends windows early


def test_visited_step_errors_of_a_known_offset(pm_falls):
    """A simulator that is the true pointmass plus a constant offset (c_p, c_v): on every
    visited state its error is exactly that offset in units of the scale, and under the
    reward p' the reward difference is c_p; the reference against itself errs by nothing."""
    from rl2s_jax.model.simulator import (
        mean_square,
        simulated_returns,
        start_pool,
        step_errors,
        visited_step_errors,
    )

    ds, params = pm_falls
    true = lambda o, a, k: pointmass_dynamics(o, a)
    c = jnp.asarray([0.03, -0.2])
    scale = jnp.asarray([0.1, 0.5])
    shifted = lambda o, a, k: pointmass_dynamics(o, a) + c
    reward_p = lambda o, a, n: n[..., 0]
    pool = start_pool(ds)
    out = visited_step_errors(params, shifted, true, reward_p, None, pool, jax.random.PRNGKey(3),
                              n_episodes=5, horizon=30, scale=scale)
    want_rmse = np.sqrt(np.mean((np.asarray(c) / np.asarray(scale)) ** 2))
    np.testing.assert_allclose(out["rmse"], want_rmse, rtol=1e-4)
    np.testing.assert_allclose(out["rmse_per_dim"],
                               np.broadcast_to(np.abs(np.asarray(c) / np.asarray(scale)),
                                               (ds.n_policies, 2)), rtol=1e-4)
    np.testing.assert_allclose(out["reward_bias"], 0.03, rtol=1e-4)
    np.testing.assert_allclose(out["reward_abs"], 0.03, rtol=1e-4)
    np.testing.assert_array_equal(out["steps"], 5 * 30)  # no termination: every step counts
    # a scale of 0 leaves a dim out
    z, _ = step_errors(jnp.asarray([1.0, 5.0]), jnp.zeros(2), jnp.zeros(2), jnp.zeros(1),
                       reward_p, jnp.asarray([2.0, 0.0]))
    np.testing.assert_array_equal(z, [0.5, 0.0])
    assert float(mean_square(z, jnp.asarray([2.0, 0.0]))) == pytest.approx(0.25)
    # the episodes are those of simulated_returns (same key: start states, actions, ends)
    task = get_task("pointmass")
    same = visited_step_errors(params, true, true, task.reward_fn, task.done_fn, pool,
                               jax.random.PRNGKey(4), n_episodes=6, horizon=40, scale=scale)
    _, lengths = simulated_returns(params, true, task.reward_fn, task.done_fn, pool,
                                   jax.random.PRNGKey(4), n_episodes=6, horizon=40, gamma=1.0)
    np.testing.assert_array_equal(same["steps"], np.asarray(lengths).sum(-1))
    assert (np.asarray(lengths) < 40).any()  # some episodes did end early
    np.testing.assert_array_equal(same["rmse"], 0.0)
    np.testing.assert_array_equal(same["reward_bias"], 0.0)
