"""PPO learns the tiny task; the zoo split; the shipped zoos meet the issue's shape."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.data.collect import measure_values
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy import policy as pol
from rl2s_jax.policy.ppo import compute_gae
from rl2s_jax.zoo import zoo as zoo_mod
from rl2s_jax.zoo.build import (
    MIN_TEST,
    SPLIT_SIZES,
    build_zoo,
    choose_split,
    learner_plans,
    spread_subset,
)


def test_gae_matches_python_loop():
    rng = np.random.default_rng(0)
    T, N, gamma, lam = 9, 3, 0.9, 0.8
    r, v, nv = (rng.normal(size=(T, N)).astype(np.float32) for _ in range(3))
    term = (rng.random((T, N)) < 0.2).astype(np.float32)
    trunc = ((rng.random((T, N)) < 0.2) & (term == 0)).astype(np.float32)
    adv, target = compute_gae(jnp.asarray(r), jnp.asarray(v), jnp.asarray(nv),
                              jnp.asarray(term), jnp.asarray(trunc), gamma, lam)
    expected = np.zeros((T, N))
    acc = np.zeros(N)
    for t in reversed(range(T)):
        delta = (r[t] + gamma * (1 - term[t]) * nv[t] - v[t]) * (1 - trunc[t])
        acc = delta + gamma * lam * (1 - term[t]) * (1 - trunc[t]) * acc
        expected[t] = acc
    np.testing.assert_allclose(adv, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(target, expected + v, rtol=1e-5, atol=1e-5)


def test_spread_subset_and_split():
    returns = np.array([0.0, 1.0, 1.1, 1.2, 1.3, 5.0, 9.0, 9.1, 10.0])
    keep = spread_subset(returns, 4)
    assert keep == [0, 5, 6, 8]  # targets 0, 3.33, 6.67, 10: nearest free policy each
    train, test = choose_split(np.arange(30.0)[::-1], n_train=5, min_test=20)
    assert len(train) == 5 and len(test) == 25 and not set(train) & set(test)
    assert 29 in train and 0 in train  # both ends of the return range are trained on
    with pytest.raises(ValueError, match="cannot give"):
        choose_split(np.arange(10.0), n_train=5, min_test=20)


def test_ppo_learns_pointmass_and_zoo_spreads():
    plans = learner_plans("pointmass", "ppo", env_steps=81_920, snapshots=8)
    zoo, _ = build_zoo("pointmass", algo="ppo", seeds=2, plans=plans, value_episodes=4,
                       n_train=4, zoo_size=12, min_test=8, progress=False,
                       log=lambda *_: None)
    assert zoo.size == 12 and len(zoo.train_ids) == 4
    env = get_task("pointmass").make_env()
    first = [i for i, o in enumerate(zoo.origins) if o["snapshot"] == 0]
    last = max(range(zoo.size), key=lambda i: zoo.origins[i]["snapshot"])
    vals = measure_values(env, pol.index_params(zoo.params, first + [last]),
                          key=jax.random.PRNGKey(7), n_episodes=64, episode_length=50)["value"]
    # The optimum is just under 50 (alive bonus 1 per step, small p^2 and control costs).
    assert vals[-1] > 48.0, vals
    assert vals[-1] > max(vals[:-1]) + 0.5, vals


@pytest.mark.parametrize("task", ["hopper", "walker2d", "halfcheetah", "ant"])
def test_shipped_zoo(task):
    zoo = zoo_mod.load_zoo(task)
    t = get_task(task)
    n_train, min_test = SPLIT_SIZES.get(task, 17), MIN_TEST.get(task, 8)
    assert zoo.task == task and zoo.size >= n_train + min_test
    assert len(zoo.train_ids) == n_train
    assert len(zoo.test_ids) >= 20       # issue 41: enough test policies for a worst case
    # the split chosen when the zoo was built; growth (rl2s zoo --extend) appends test policies
    grown = [i for e in zoo.info.get("extensions", []) for i in e["ids"]]
    base = zoo.size - len(grown)
    assert grown == list(range(base, zoo.size))
    train, test = choose_split(zoo.returns[:base], n_train, min_test)
    assert (zoo.train_ids, zoo.test_ids) == (train, sorted(test + grown))
    assert zoo.info["spread"]["test"]["pass"] or not grown
    assert not set(zoo.train_ids) & set(zoo.test_ids)
    assert zoo.params["obs_mean"].shape == (zoo.size, t.obs_size)
    assert zoo.params["layers"][-1]["b"].shape == (zoo.size, 2 * t.action_size)
    r = zoo.returns
    # near-random to strong: the initial random policies are in, and the best is far above
    random_like = [r[i] for i, o in enumerate(zoo.origins) if o["snapshot"] == 0]
    assert random_like and max(r) - min(r) > 500
    assert max(r) > 5 * max(abs(x) for x in random_like)
    assert all(np.isfinite(r)) and all(np.asarray(zoo.return_se) >= 0)
