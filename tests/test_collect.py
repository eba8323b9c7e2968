"""Collection: episode boundaries, fresh starts, terminations, truncations, true values."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs import training as brax_training
from brax.envs.base import Env, State

from rl2s_jax.data.collect import collect, equal_chunks, measure_values
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo import zoo as zoo_mod


class CounterEnv(Env):
    """A user env, not registered: obs = (step, noise), reward 1, terminates at step K."""

    K = 7

    def reset(self, rng):
        obs = jnp.array([0.0, jax.random.uniform(rng)])
        return State(pipeline_state=obs, obs=obs, reward=jnp.zeros(()), done=jnp.zeros(()))

    def step(self, state, action):
        obs = state.obs.at[0].add(1.0)
        done = (obs[0] >= self.K).astype(jnp.float32)
        return state.replace(pipeline_state=obs, obs=obs, reward=jnp.ones(()), done=done)

    @property
    def observation_size(self):
        return 2

    @property
    def action_size(self):
        return 1

    @property
    def backend(self):
        return "jax"


def _policies(obs_size, action_size, biases):
    """Policies whose pre-tanh mean is pushed by a constant bias (to force behaviours)."""
    ps = []
    for i, b in enumerate(biases):
        p = pol.init_policy(jax.random.PRNGKey(i), obs_size, action_size, hidden=(8,))
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:action_size].set(b)
        ps.append(p)
    return pol.stack_params(ps)


def check_episode_structure(ds, done_fn, episode_length):
    """The invariants every collected Dataset must hold."""
    t, ep = ds.t, ds.episode_id
    new_ep = np.r_[True, ep[1:] != ep[:-1]]
    assert np.all(t[new_ep] == 0), "t restarts at 0 at each episode start"
    assert np.all(t[~new_ep] == t[np.flatnonzero(~new_ep) - 1] + 1), "t counts up by 1"
    ends = np.r_[new_ep[1:], True]
    # obs[i+1] == next_obs[i] inside an episode; a new episode after an end
    inner = ~ends[:-1]
    np.testing.assert_array_equal(ds.obs[1:][inner], ds.next_obs[:-1][inner])
    prev_end = np.r_[False, (ds.done | ds.truncated)[:-1]]
    assert np.all(new_ep[prev_end]), "an episode ends after done/truncated"
    # done is the env's termination; truncated only at the time limit
    np.testing.assert_array_equal(ds.done, np.asarray(done_fn(jnp.asarray(ds.next_obs))))
    assert np.all(ds.t[ds.truncated] == episode_length - 1)
    assert not np.any(ds.done & ds.truncated)
    assert np.all(ds.t < episode_length)
    # every episode starts from its own fresh random state (no cached reset state)
    starts = ds.obs[new_ep]
    assert len(np.unique(starts, axis=0)) == len(starts)


def test_pointmass_collection_structure(tmp_path):
    task = get_task("pointmass")
    params = _policies(2, 1, [3.0, 0.0, -3.0])
    ds = collect(task.make_env(), params, key=jax.random.PRNGKey(0), transitions_per_policy=700,
                 envs_per_policy=3, episode_length=task.episode_length, task="pointmass",
                 value_episodes=8, progress=False)
    assert ds.n_transitions == 3 * 700 and ds.n_policies == 3
    np.testing.assert_array_equal(ds.policy_id, np.repeat(np.arange(3), 700))
    check_episode_structure(ds, task.done_fn, task.episode_length)
    assert ds.done.sum() > 0 and ds.truncated.sum() > 0
    np.testing.assert_allclose(ds.reward, task.reward_fn(ds.obs, ds.action, ds.next_obs),
                               atol=1e-5)
    # the pushed policies terminate, the centred one stays alive to the time limit
    ends = [ds.done[ds.policy_id == i].sum() for i in range(3)]
    assert ends[0] > 0 and ends[2] > 0 and ends[1] == 0
    assert ds.value[1] > max(ds.value[0], ds.value[2])
    path = tmp_path / "pm.npz"
    save_dataset(path, ds)
    back = load_dataset(path)
    np.testing.assert_array_equal(back.obs, ds.obs)
    assert back.meta == ds.meta


def test_user_env_collection_and_exact_values():
    env = CounterEnv()
    params = _policies(2, 1, [0.0, 1.0])
    ds = collect(env, params, key=jax.random.PRNGKey(1), transitions_per_policy=50,
                 envs_per_policy=2, episode_length=5, value_episodes=0, progress=False)
    assert ds.meta["task"] is None and not ds.has_values
    check_episode_structure(ds, lambda o: o[..., 0] >= CounterEnv.K, 5)
    assert ds.truncated.sum() > 0 and ds.done.sum() == 0  # time limit 5 < K
    gamma = 0.9
    for L, length in ((10, CounterEnv.K), (5, 5)):
        v = measure_values(env, params, key=jax.random.PRNGKey(2), n_episodes=3,
                           episode_length=L, gamma=gamma)
        np.testing.assert_allclose(v["value"], [length, length])
        np.testing.assert_allclose(v["value_discounted"],
                                   [sum(gamma**t for t in range(length))] * 2, rtol=1e-6)
        np.testing.assert_allclose(v["value_se"], 0.0, atol=1e-6)


class TracedCounterEnv(CounterEnv):
    """CounterEnv that counts how often its step is traced (once per compiled scan)."""

    traces = 0

    def step(self, state, action):
        type(self).traces += 1
        return super().step(state, action)


def test_collection_compiles_one_scan_for_uneven_steps():
    # 25 steps per env in chunks of at most 10: three chunks of 9 (not 10, 10, 5, which
    # compiles the env step twice), the 2 extra steps trimmed.
    assert equal_chunks(25, 10) == (3, 9)
    for total, chunk in ((1, 100), (100, 100), (101, 100), (250, 100), (999, 7)):
        n, size = equal_chunks(total, chunk)
        assert size <= chunk and 0 <= n * size - total < n
    env = TracedCounterEnv()
    ds = collect(env, _policies(2, 1, [0.0, 1.0]), key=jax.random.PRNGKey(1),
                 transitions_per_policy=50, envs_per_policy=2, episode_length=5,
                 chunk_steps=10, value_episodes=0, progress=False)
    assert TracedCounterEnv.traces == 1
    assert ds.n_transitions == 100 and np.all(np.bincount(ds.policy_id) == 50)
    check_episode_structure(ds, lambda o: o[..., 0] >= CounterEnv.K, 5)
    with pytest.raises(ValueError, match="chunk_steps"):
        equal_chunks(10, 0)


@pytest.mark.parametrize("refresh_every", [1, 3, 100])
def test_every_episode_starts_fresh_whatever_the_refresh_period(refresh_every):
    # Episodes of 5 steps: with a period of 100 every end after the first needs the
    # on-demand refresh; with 3 some ends fall between scheduled refreshes.
    ds = collect(CounterEnv(), _policies(2, 1, [0.0, 1.0]), key=jax.random.PRNGKey(3),
                 transitions_per_policy=60, envs_per_policy=3, episode_length=5,
                 refresh_every=refresh_every, value_episodes=0, progress=False)
    check_episode_structure(ds, lambda o: o[..., 0] >= CounterEnv.K, 5)
    assert (ds.t == 0).sum() == 2 * 3 * 4  # 20 steps per env: 4 whole episodes each
    assert ds.meta["source"]["refresh_every"] == refresh_every


def test_bad_input_refused_before_work():
    env = CounterEnv()
    params = _policies(2, 1, [0.0])
    with pytest.raises(ValueError, match="transitions_per_policy"):
        collect(env, params, key=jax.random.PRNGKey(0), transitions_per_policy=0)
    with pytest.raises(ValueError, match="envs_per_policy"):
        collect(env, params, key=jax.random.PRNGKey(0), transitions_per_policy=4,
                envs_per_policy=8)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="refresh_every"):
            collect(env, params, key=jax.random.PRNGKey(0), transitions_per_policy=4,
                    refresh_every=bad)
    with pytest.raises(ValueError, match="AutoResetWrapper"):
        collect(brax_training.AutoResetWrapper(env), params, key=jax.random.PRNGKey(0),
                transitions_per_policy=4)


@pytest.mark.slow
def test_hopper_collection_with_shipped_zoo(hopper_train_ds):
    task = get_task("hopper")
    ds = hopper_train_ds  # the zoo's 17 training policies, 40-step episodes
    check_episode_structure(ds, task.done_fn, 40)
    assert ds.done.sum() > 0 and ds.truncated.sum() > 0
    later = ds.t > 0  # brax's first step of an episode differs slightly (see tasks.py)
    np.testing.assert_allclose(ds.reward[later], task.reward_fn(
        ds.obs, ds.action, ds.next_obs)[later], atol=1e-4)
    assert ds.has_values and ds.value.shape == (17,)
    assert ds.meta["source"]["zoo_ids"] == list(zoo_mod.load_zoo("hopper").train_ids)
