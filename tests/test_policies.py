"""The policy architecture: math against NumPy, and a stacked zoo under vmap == a loop."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo import zoo as zoo_mod


def _np_forward(params, obs):
    x = np.clip((obs - np.asarray(params["obs_mean"])) / np.asarray(params["obs_std"]), -10, 10)
    layers = params["layers"]
    for layer in layers[:-1]:
        z = x @ np.asarray(layer["w"]) + np.asarray(layer["b"])
        x = z / (1 + np.exp(-z))  # swish
    out = x @ np.asarray(layers[-1]["w"]) + np.asarray(layers[-1]["b"])
    loc, raw = np.split(out, 2, axis=-1)
    return loc, np.log1p(np.exp(raw)) + pol.MIN_SCALE


def _random_policy(key, obs_size=5, action_size=2):
    k1, k2, k3 = jax.random.split(key, 3)
    p = pol.init_policy(k1, obs_size, action_size, hidden=(16, 16))
    # non-trivial normaliser and a last layer that is not near zero
    p["obs_mean"] = jax.random.normal(k2, (obs_size,))
    p["obs_std"] = 0.5 + jax.random.uniform(k3, (obs_size,))
    p["layers"][-1]["w"] = p["layers"][-1]["w"] * 100
    return p


def test_policy_dist_matches_numpy():
    params = _random_policy(jax.random.PRNGKey(0))
    obs = np.random.default_rng(0).normal(size=(7, 5)).astype(np.float32)
    loc, scale = pol.policy_dist(params, jnp.asarray(obs))
    loc_np, scale_np = _np_forward(params, obs)
    np.testing.assert_allclose(loc, loc_np, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(scale, scale_np, rtol=1e-4, atol=1e-5)


def test_log_prob_matches_numpy_and_change_of_variables():
    params = _random_policy(jax.random.PRNGKey(1))
    obs = jnp.asarray(np.random.default_rng(1).normal(size=(4, 5)), jnp.float32)
    action, raw, logp = pol.sample_action(params, obs, jax.random.PRNGKey(2))
    loc, scale = (np.asarray(a, np.float64) for a in pol.policy_dist(params, obs))
    raw64 = np.asarray(raw, np.float64)
    gauss = np.sum(-0.5 * ((raw64 - loc) / scale) ** 2 - np.log(scale)
                   - 0.5 * np.log(2 * np.pi), -1)
    expected = gauss - np.sum(np.log(1 - np.tanh(raw64) ** 2), -1)
    np.testing.assert_allclose(logp, expected, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(action, np.tanh(raw64), atol=1e-6)
    assert np.all(np.abs(np.asarray(action)) < 1)


def test_vmap_over_stacked_zoo_equals_loop():
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    zoo = [_random_policy(k) for k in keys]
    stacked = pol.stack_params(zoo)
    assert pol.num_policies(stacked) == 4
    obs = jnp.asarray(np.random.default_rng(2).normal(size=(4, 6, 5)), jnp.float32)
    akeys = jax.random.split(jax.random.PRNGKey(4), 4)
    batched = jax.vmap(pol.sample_action)(stacked, obs, akeys)
    modes = jax.vmap(pol.mode_action)(stacked, obs)
    for i, p in enumerate(zoo):
        single = pol.sample_action(p, obs[i], akeys[i])
        for b, s in zip(batched, single, strict=True):
            np.testing.assert_allclose(b[i], s, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(modes[i], pol.mode_action(p, obs[i]), rtol=1e-5, atol=1e-6)
        one = pol.index_params(stacked, i)
        np.testing.assert_array_equal(one["layers"][0]["w"], p["layers"][0]["w"])


def test_lineage_split_holds_out_one_learner_run():
    """"lineage-validation": the training policies of the lineage (learner, seed) whose count is
    nearest a quarter of the training policies, ties to the later seed; "lineage-fit": the
    rest; test policies never; one lineage only: refused naming the split."""
    params = pol.stack_params([_random_policy(k) for k in jax.random.split(
        jax.random.PRNGKey(6), 12)])
    seeds = [0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 3, 0]  # policy 11 (seed 0) is a test policy
    zoo = zoo_mod.Zoo(task="pointmass", params=params, returns=np.arange(12.0),
                      return_se=np.full(12, 0.1), origins=[{"learner": "sac", "seed": s}
                                                           for s in seeds],
                      train_ids=list(range(11)), test_ids=[11])
    # counts: seed 0: 4, 1: 2, 2: 2, 3: 3; a quarter of 11 is 2.75: seed 3 (|3 - 2.75|)
    assert zoo.held_out_lineage() == ("sac", 3)
    assert zoo.split_ids("lineage-validation") == [8, 9, 10]
    assert zoo.split_ids("lineage-fit") == list(range(8))
    tie = zoo_mod.Zoo(**{**zoo.__dict__, "origins": [{"learner": "sac", "seed": s} for s in
                                                       [0, 0, 0, 0, 0, 1, 1, 2, 2, 0, 0, 0]]})
    assert tie.held_out_lineage() == ("sac", 2)  # seeds 1 and 2 both hold 2: the later
    assert tie.seen_lineage([11, 7]) == [True, True]
    one = zoo_mod.Zoo(**{**zoo.__dict__, "origins": [{"learner": "sac", "seed": 0}] * 12})
    with pytest.raises(ValueError, match="'lineage-validation' holds out one of the training "
                       "policies' learner lineages; this zoo's are all of 1"):
        one.split_ids("lineage-validation")


def test_protocol_validation_datasets_by_lineage():
    """paper.protocol.validation_datasets with "lineage": the training Dataset's policies of
    "lineage-fit" as train and of "lineage-validation" as test, each with its zoo ids."""
    from rl2s_jax.paper.protocol import validation_datasets

    class Part:  # the two things validation_datasets asks of a Dataset
        def __init__(self, ids):
            self.ids, self.meta = ids, {"source": {"zoo_ids": ids, "split": "train"}}

        def select_policies(self, rows):
            return Part([self.ids[r] for r in rows])

    seeds = [0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 3, 0]
    zoo = zoo_mod.Zoo(task="pointmass", params=None, returns=np.arange(12.0),
                      return_se=np.full(12, 0.1), origins=[{"learner": "sac", "seed": s}
                                                           for s in seeds],
                      train_ids=list(range(11)), test_ids=[11])
    train = Part([10, 3, 8, 0, 1, 2, 9, 4, 5, 6, 7])  # the data's own order
    out = validation_datasets(train, zoo, "lineage")
    assert out["test"].ids == [8, 9, 10] and out["train"].ids == list(range(8))
    assert out["test"].meta["source"] == {"zoo_ids": [8, 9, 10], "split": "lineage-validation"}
    assert validation_datasets(train, zoo)["test"].ids == zoo.split_ids("validation")


def test_zoo_round_trip(tmp_path):
    params = pol.stack_params([_random_policy(k) for k in jax.random.split(
        jax.random.PRNGKey(5), 3)])
    zoo = zoo_mod.Zoo(task="pointmass", params=params, returns=np.array([1.0, 2.0, 3.0]),
                  return_se=np.array([0.1, 0.2, 0.3]), origins=[{"seed": 0}] * 3,
                  train_ids=[0], test_ids=[1, 2])
    zoo_mod.save_zoo(zoo, str(tmp_path / "z"))
    back = zoo_mod.load_zoo(str(tmp_path / "z"))
    assert back.size == 3 and back.train_ids == [0] and back.test_ids == [1, 2]
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(back.params),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    assert back.split_ids("all") == [0, 1, 2]
    with pytest.raises(ValueError, match="split: expected one of .* 'lineage-validation'"):
        back.split_ids("holdout")
    with pytest.raises(ValueError, match="'validation' holds out every 4th training policy; "
                       "this zoo has 1 "):  # too few training policies to hold one out
        back.split_ids("validation")
    with pytest.raises(ValueError, match="disjoint"):
        zoo_mod.save_zoo(zoo_mod.Zoo(**{**zoo.__dict__, "test_ids": [0, 1]}), str(tmp_path / "bad"))
    with pytest.raises(FileNotFoundError, match="rl2s zoo"):
        zoo_mod.load_zoo(str(tmp_path / "missing"))
