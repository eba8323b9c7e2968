"""The learned simulator as a Gymnasium environment, for RL code outside JAX.

:class:`SimulatorGymEnv` is a ``gymnasium.Env`` around :class:`~rl2s_jax.sim_env.SimulatorEnv`
(the same simulator as a brax Env): episodes start from real start states of a Dataset,
steps sample the learned dynamics and take reward and termination from the task's
``reward_fn`` / ``done_fn``, and an episode is truncated after ``max_episode_steps`` (the
task's ``episode_length`` by default) unless it terminated first. It passes
``gymnasium.utils.env_checker.check_env``. ``reset(seed=s)`` starts the episode from
``SimulatorEnv.reset(jax.random.PRNGKey(s))`` and every step is ``SimulatorEnv.step``, so a
seed and a sequence of actions give the same trajectory as the brax env (jitted, one step
per call). An unseeded ``reset`` continues the key stream: the next episode's key is
``jax.random.fold_in(previous episode's key, 1)``.

:class:`SimulatorVectorEnv` is a ``gymnasium.vector.VectorEnv`` of ``num_envs`` such episodes,
stepped together on the device by one jitted call (vmap over the envs), auto-resetting in the
same step (``AutoresetMode.SAME_STEP``: a finished env returns its new start observation and
``info["final_obs"]`` holds the last one). Observations, rewards and flags come back as NumPy.
JAX code that wants to stay on the device should use ``SimulatorEnv`` directly.
"""
from __future__ import annotations

import os
from typing import Any, NamedTuple

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.checks import tree_where
from rl2s_jax.envs.tasks import Task
from rl2s_jax.improve.sim_env import Dynamics, SimulatorEnv
from rl2s_jax.model.simulator import Simulator, start_pool
from rl2s_jax.train.checkpoint import load_simulator

__all__ = ["SimulatorGymEnv", "SimulatorVectorEnv", "VecState", "vec_reset", "vec_step"]

_TASK_LIMIT = "task"  # max_episode_steps default: the task's episode_length


def _brax_env(sim, starts, task, deterministic) -> SimulatorEnv:
    """The SimulatorEnv; ``starts`` is a start pool [S, o] or a Dataset (its t == 0 rows)."""
    pool = start_pool(starts) if hasattr(starts, "episode_id") else starts
    return SimulatorEnv(sim, pool, task, deterministic=deterministic)


def _limit(max_episode_steps, task: Task) -> int | None:
    limit = task.episode_length if max_episode_steps == _TASK_LIMIT else max_episode_steps
    if limit is not None and (not isinstance(limit, int | np.integer) or limit < 1):
        raise ValueError(f"max_episode_steps: expected an int >= 1 or None, got {limit!r}")
    return None if limit is None else int(limit)


def _spaces(task: Task) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    obs = gym.spaces.Box(-np.inf, np.inf, (task.obs_size,), np.float32)
    action = gym.spaces.Box(-1.0, 1.0, (task.action_size,), np.float32)  # the tasks' range
    return obs, action


def _from_files(ckpt: str | os.PathLike, data, step: int | None):

    sim = load_simulator(ckpt, step)
    ds = load_dataset(data) if isinstance(data, str | os.PathLike) else data
    return sim, ds


class SimulatorGymEnv(gym.Env):
    """A learned (or any) dynamics model as a Gymnasium env.

    Args:
      sim: a ``Simulator`` or any ``dynamics(obs [..., o], action [..., a], key) -> [..., o]``.
      starts: real episode start observations [S, o], or a Dataset (its rows with t == 0).
      task: a ``Task`` or its name (reward_fn, done_fn, sizes); default ``sim.task``.
      deterministic: step with the simulator's mean instead of a sample.
      max_episode_steps: truncate after this many steps (None: never); default the task's
        ``episode_length``.

    Observations are float32 [o]; actions float32 [a] in the Box [-1, 1] (passed to the
    dynamics and the reward as they are, as in the brax env); info is empty.
    """

    metadata = {"render_modes": []}

    def __init__(self, sim: Simulator | Dynamics, starts, task: Task | str | None = None, *,
                 deterministic: bool = False, max_episode_steps: int | None | str = _TASK_LIMIT):
        self.brax_env = _brax_env(sim, starts, task, deterministic)
        self.task = self.brax_env.task
        self.max_episode_steps = _limit(max_episode_steps, self.task)
        self.observation_space, self.action_space = _spaces(self.task)
        env = self.brax_env

        def step(state: State, action: jax.Array):
            state = env.step(state, action)
            return state, (state.obs, state.reward, state.done)

        self._reset_fn = jax.jit(env.reset)
        self._step_fn = jax.jit(step)
        self._state: State | None = None
        self._key: jax.Array | None = None  # key of the current episode
        self._t = 0

    @classmethod
    def from_checkpoint(cls, ckpt: str | os.PathLike, data, *, step: int | None = None,
                        **kwargs) -> SimulatorGymEnv:
        """The simulator of checkpoint directory ``ckpt`` (newest intact step unless ``step``)
        with start states from ``data`` (a Dataset or its .npz path)."""
        sim, ds = _from_files(ckpt, data, step)
        return cls(sim, ds, **kwargs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        elif self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(2**31 - 1)))
        else:
            self._key = jax.random.fold_in(self._key, 1)
        self._state = self._reset_fn(self._key)
        self._t = 0
        return np.array(self._state.obs, np.float32), {}

    def step(self, action):
        if self._state is None:
            raise gym.error.ResetNeeded("step: call reset() before the first step")
        action = np.asarray(action, np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action: expected shape {self.action_space.shape}, got "
                             f"{action.shape}")
        self._state, out = self._step_fn(self._state, jnp.asarray(action))
        obs, reward, done = jax.device_get(out)
        self._t += 1
        terminated = bool(done > 0.5)
        truncated = (not terminated and self.max_episode_steps is not None
                     and self._t >= self.max_episode_steps)
        return np.array(obs, np.float32), float(reward), terminated, bool(truncated), {}


# --------------------------------------------------------------------------- vector env


class VecState(NamedTuple):
    """num_envs episodes in progress: ``env`` the brax State batched [B], ``t`` [B] steps taken
    in the current episodes, ``key`` the key of the next auto-resets."""

    env: State
    t: jax.Array
    key: jax.Array


def vec_reset(env: SimulatorEnv, num_envs: int, key: jax.Array) -> VecState:
    """Fresh episodes: env i starts from ``env.reset(split(k, num_envs)[i])`` with
    ``key, k = split(key)``."""
    key, k = jax.random.split(key)
    states = jax.vmap(env.reset)(jax.random.split(k, num_envs))
    return VecState(states, jnp.zeros(num_envs, jnp.int32), key)


def vec_step(env: SimulatorEnv, limit: int | None, vs: VecState, action: jax.Array):
    """One step of every env, action [B, a]; envs that end restart in the same step (from
    ``env.reset(split(k, B)[i])`` with ``key, k = split(vs.key)``).

    -> (VecState, (obs [B, o] (the new starts where an episode ended), reward [B],
    terminated [B], truncated [B], last obs [B, o] of the step before any restart)).
    """
    n = vs.t.shape[0]
    nxt = jax.vmap(env.step)(vs.env, action)
    t = vs.t + 1
    terminated = nxt.done > 0.5
    truncated = ~terminated & (t >= limit) if limit is not None else jnp.zeros_like(terminated)
    ended = terminated | truncated
    key, k = jax.random.split(vs.key)
    fresh = jax.vmap(env.reset)(jax.random.split(k, n))
    states = tree_where(ended, fresh, nxt)
    out = (states.obs, nxt.reward, terminated, truncated, nxt.obs)
    return VecState(states, jnp.where(ended, 0, t).astype(jnp.int32), key), out


class SimulatorVectorEnv(VectorEnv):
    """``num_envs`` simulated episodes stepped together on the device (one jitted call per
    ``step``), auto-reset in the same step. Arguments as :class:`SimulatorGymEnv`.

    ``step`` returns obs [B, o] float32, rewards [B] float32, terminations / truncations [B]
    bool and info ``{"final_obs": object array [B] (the last obs of envs that ended, else
    None), "_final_obs": [B] bool}`` when an env ended, else ``{}``. ``reset(seed=s)`` starts
    every env with :func:`vec_reset` from ``jax.random.PRNGKey(s)``.
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, sim: Simulator | Dynamics, starts, num_envs: int,
                 task: Task | str | None = None, *, deterministic: bool = False,
                 max_episode_steps: int | None | str = _TASK_LIMIT):
        if not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ValueError(f"num_envs: expected an int >= 1, got {num_envs!r}")
        self.brax_env = env = _brax_env(sim, starts, task, deterministic)
        self.task = env.task
        self.num_envs = int(num_envs)
        self.max_episode_steps = limit = _limit(max_episode_steps, self.task)
        self.single_observation_space, self.single_action_space = _spaces(self.task)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        n = self.num_envs
        self._reset_fn = jax.jit(lambda key: vec_reset(env, n, key))
        self._step_fn = jax.jit(lambda vs, action: vec_step(env, limit, vs, action))
        self._state: VecState | None = None
        self._key: jax.Array | None = None

    @classmethod
    def from_checkpoint(cls, ckpt: str | os.PathLike, data, num_envs: int, *,
                        step: int | None = None, **kwargs) -> SimulatorVectorEnv:
        """As :meth:`SimulatorGymEnv.from_checkpoint`, with ``num_envs`` envs."""
        sim, ds = _from_files(ckpt, data, step)
        return cls(sim, ds, num_envs, **kwargs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        elif self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(2**31 - 1)))
        else:
            self._key = jax.random.fold_in(self._key, 1)
        self._state = self._reset_fn(self._key)
        return np.array(self._state.env.obs, np.float32), {}

    def step(self, actions):
        if self._state is None:
            raise gym.error.ResetNeeded("step: call reset() before the first step")
        actions = np.asarray(actions, np.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions: expected shape {self.action_space.shape}, got "
                             f"{actions.shape}")
        self._state, out = self._step_fn(self._state, jnp.asarray(actions))
        obs, reward, terminated, truncated, last = (np.array(x) for x in jax.device_get(out))
        info: dict[str, Any] = {}
        ended = terminated | truncated
        if ended.any():
            final = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(ended):
                final[i] = last[i]
            info = {"final_obs": final, "_final_obs": ended}
        return obs, reward, terminated, truncated, info
