"""Your own system's task, registered from Python (rl2s_jax.envs.tasks.register), and the
example that learns and evaluates a simulator of a system no built-in task covers."""
import os
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from rl2s_jax.envs import tasks

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _reward(obs, action, next_obs):
    return -jnp.sum(next_obs ** 2, -1)


def _done(next_obs):
    return jnp.abs(next_obs[..., 0]) > 3.0


def test_register_checks_its_input_by_name():
    kw = dict(reward_fn=_reward, done_fn=_done, obs_size=3, action_size=2, episode_length=20)
    task = tasks.register("test_sys", **kw, replace=True)
    assert tasks.get_task("test_sys") is task and "test_sys" in tasks.task_names()
    with pytest.raises(ValueError, match="registered already"):
        tasks.register("test_sys", **kw)
    with pytest.raises(ValueError, match="built-in"):
        tasks.register("hopper", **kw)
    with pytest.raises(ValueError, match="obs_size"):
        tasks.register("test_bad", **{**kw, "obs_size": 0})
    with pytest.raises(ValueError, match="reward_fn: on a batch of 4 rows expected shape"):
        tasks.register("test_bad", **{**kw, "reward_fn": lambda o, a, n: n})
    with pytest.raises(ValueError, match="done_fn: calling it"):
        tasks.register("test_bad", **{**kw, "done_fn": lambda n: n @ jnp.ones(5)})
    with pytest.raises(NotImplementedError, match="without make_env"):
        task.make_env()
    assert "test_bad" not in tasks.task_names()
    np.testing.assert_allclose(np.asarray(task.reward_fn(jnp.zeros(3), jnp.zeros(2),
                                                         jnp.ones(3))), -3.0)


def test_own_system_example_learns_and_ranks(monkeypatch):
    monkeypatch.syspath_prepend(os.path.join(ROOT, "examples"))
    import own_system
    report = own_system.main(["--quick"])
    assert "damped_pendulum" in tasks.task_names()
    assert len(report["true_value"]) == 6 and np.isfinite(report["metrics"]["kendall_tau"])
    assert report["horizon"] == own_system.EPISODE
    sys.modules.pop("own_system", None)
