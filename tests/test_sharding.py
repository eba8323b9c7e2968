"""rl2s_jax.sharding: lanes spread over devices give the single-device results (issue 13)."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

from rl2s_jax import sharding

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Runs in a fresh process: the forced host device count must be set before JAX starts.
SHARDED_VS_PLAIN = textwrap.dedent("""
    import sys
    sys.path[:0] = [{root!r} + "/tests"]
    import jax, jax.numpy as jnp, numpy as np
    assert jax.device_count() == 4, jax.devices()
    from test_train import _policies
    from rl2s_jax.evaluate.lane_scores import lane_returns
    from rl2s_jax.train.lanes import train_lanes
    from rl2s_jax import train as T
    from rl2s_jax.data.collect import collect
    from rl2s_jax.sharding import lane_mesh, replicate, shard_lanes
    from rl2s_jax.model.simulator import start_pool
    from rl2s_jax.envs.tasks import get_task

    task = get_task("pointmass")
    policies = _policies([-2.0, 0.0, 1.0, 2.0])
    ds = collect(task.make_env(), policies, key=jax.random.PRNGKey(0), transitions_per_policy=400,
                 envs_per_policy=2, episode_length=task.episode_length, task="pointmass",
                 value_episodes=2, progress=False)
    # collection: the policy axis split over the 4 devices gives the one-device data
    from rl2s_jax.data.collect import _policy_mesh, _shard_batch
    assert _policy_mesh(4, True).size == 4 and _policy_mesh(6, True).size == 3
    assert _policy_mesh(4, False).size == 1
    split = _shard_batch({{"x": jnp.zeros((8, 3)), "key": jax.random.PRNGKey(0)}},
                         _policy_mesh(4, True), 8)
    assert [s.data.shape[0] for s in split["x"].addressable_shards] == [2, 2, 2, 2]
    assert split["key"].sharding.is_fully_replicated
    one = collect(task.make_env(), policies, key=jax.random.PRNGKey(0),
                  transitions_per_policy=400, envs_per_policy=2,
                  episode_length=task.episode_length, task="pointmass", value_episodes=2,
                  progress=False, shard=False)
    for name in ("policy_id", "episode_id", "t", "done", "truncated"):
        np.testing.assert_array_equal(getattr(ds, name), getattr(one, name), err_msg=name)
    for name in ("obs", "action", "next_obs", "reward", "value", "value_discounted"):
        np.testing.assert_allclose(getattr(ds, name), getattr(one, name), rtol=1e-5,
                                   atol=1e-5, err_msg=name)
    cfg = T.TrainConfig.small(task="pointmass", method="rl2s", vd_horizon=20, vd_every=2,
                              pretrain_steps=2, disc_warmup_steps=1)
    data = T.make_train_data(ds, policies, cfg)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(4)])
    eps = jnp.asarray([0.25, 0.5, 1.0, 0.25])
    states = jax.jit(jax.vmap(lambda k, e, d: T.init(k, cfg, d, eps=e), in_axes=(0, 0, None)))(
        keys, eps, data)
    mesh = lane_mesh(4)
    assert mesh.size == 4 and lane_mesh(6).size == 3 and lane_mesh(5).size == 1
    plain, _ = train_lanes(states, data, 4, cfg, {{}})
    sharded, _ = train_lanes(shard_lanes(states, mesh), replicate(data, mesh), 4, cfg, {{}})
    leaf = sharded.gen["layers"][0]["w"]
    assert len(leaf.sharding.device_set) == 4, leaf.sharding
    assert [s.data.shape[0] for s in leaf.addressable_shards] == [1, 1, 1, 1]
    # the critic's Adam (beta1 0.5) turns float reassociation in near-zero gradients into
    # differences of up to a few Adam steps (lr 1e-3) in a few of its biases, which reach a
    # few generator weights of a lane (~1.6e-4 in 4 of 49152 with session 14's data); nearly
    # every element agrees to float tolerance
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(plain),
                            jax.tree_util.tree_leaves(sharded), strict=True):
        a, b, disc = np.asarray(a), np.asarray(b), ".disc" in jax.tree_util.keystr(path)
        share = np.isclose(a, b, rtol=1e-4, atol=1e-5).mean()
        assert share > (0.99 if disc else 0.999), (jax.tree_util.keystr(path), share)
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=5e-3 if disc else 1e-3)
    # the evaluation of the lanes, too
    pool, ekeys = start_pool(ds), jnp.stack([jax.random.PRNGKey(9 + s) for s in range(4)])
    roll = dict(n_episodes=4, horizon=20, gamma=0.99)
    r1, _ = lane_returns(T.simulator(plain), policies, pool, ekeys, **roll)
    r2, _ = lane_returns(T.simulator(sharded), policies, pool, ekeys, **roll)
    np.testing.assert_allclose(np.asarray(r1), np.asarray(r2), rtol=1e-4, atol=1e-4)
    print("SHARDED == PLAIN")
""")


def test_sharded_lanes_equal_the_single_device_run():
    """Four forced host devices: collection with its policies split one per device gives the
    one-device data; pre-training + WGAIL lanes split one per device train and evaluate to
    the same numbers as the unsharded program."""
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4",
           "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", SHARDED_VS_PLAIN.format(root=ROOT)], env=env,
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0 and "SHARDED == PLAIN" in out.stdout, out.stderr[-3000:]


def test_lane_mesh_and_shard_lanes_checks():
    mesh = sharding.lane_mesh(3)  # this process has one device
    assert mesh.size == 1 and mesh.axis_names == (sharding.LANES,)
    tree = {"a": jnp.zeros((3, 2)), "b": jnp.ones(3)}
    out = sharding.shard_lanes(tree, mesh)
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(lambda x, y: bool((x == y).all()),
                                                         out, tree))
    with pytest.raises(ValueError, match="leading lane axis"):
        sharding.shard_lanes({"a": jnp.zeros((3, 2)), "b": jnp.ones(4)}, mesh)
    with pytest.raises(ValueError, match="leading lane axis"):
        sharding.shard_lanes({"a": jnp.zeros(())}, mesh)
    with pytest.raises(ValueError, match="n_lanes"):
        sharding.lane_mesh(0)
    two = sharding.lane_mesh(4, devices=jax.devices() * 2)  # a device list as a 2-device mesh
    with pytest.raises(ValueError, match="do not split evenly"):
        sharding.shard_lanes(jnp.zeros(3), two)
    assert sharding.is_writer()
    assert sharding.initialize_distributed() is False  # no coordinator in the environment
