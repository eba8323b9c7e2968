"""A learned simulator exposed as a brax ``Env``, so any JAX RL code can train inside it.

``SimulatorEnv(sim, start_pool)`` starts each episode from a real start state drawn from the
pool [S, o] and steps with the simulator: ``sim.sample`` (stochastic, default) or ``sim.mean``
(``deterministic=True``). Rewards and terminations come from the task's ``reward_fn`` /
``done_fn``. The PRNG key of the stochastic step rides in ``state.info["rng"]`` and is split at
every step, so ``step`` stays a pure function of (state, action).

Like brax's own envs it has no time limit and never resets by itself; wrap it for that, e.g.
``brax.envs.training.wrap(env, episode_length=L, action_repeat=1)`` (note brax's
AutoResetWrapper restarts every env from the start state its first ``reset`` drew; SAC here
(``rl2s_jax.sac``) does its own auto-reset with a fresh pool draw per episode).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State

from rl2s_jax.simulate import Simulator
from rl2s_jax.tasks import Task, get_task

Dynamics = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


class SimulatorEnv(Env):
    """A learned (or any) dynamics model as a brax Env.

    Args:
      sim: a ``Simulator`` or any ``dynamics(obs [..., o], action [..., a], key) -> [..., o]``.
      start_pool: real episode start observations [S, o]; ``reset`` draws one uniformly.
      task: a ``Task`` or its registry name, giving ``reward_fn`` / ``done_fn`` and sizes.
        Defaults to ``sim.task`` for a Simulator; required for a plain dynamics function.
      deterministic: step with ``sim.mean`` instead of ``sim.sample`` (Simulator only).

    State: ``obs`` and ``pipeline_state`` are the observation [o]; ``reward``, ``done`` are
    float32 scalars; ``info["rng"]`` the key of the next stochastic step.
    """

    def __init__(self, sim: Simulator | Dynamics, start_pool, task: Task | str | None = None,
                 *, deterministic: bool = False):
        if isinstance(sim, Simulator):
            if task is None:
                if sim.task is None:
                    raise ValueError("task: the Simulator names no task; pass task=")
                task = sim.task
            if deterministic:
                self._dynamics = lambda obs, action, key: sim.mean(obs, action)
            else:
                self._dynamics = sim.sample
        elif callable(sim):
            if task is None:
                raise ValueError("task: required when sim is a dynamics function")
            if deterministic:
                raise ValueError("deterministic: only a Simulator has a mean; a dynamics "
                                 "function is stepped as it is (make it ignore its key)")
            self._dynamics = sim
        else:
            raise TypeError(f"sim: expected a Simulator or a dynamics function, "
                            f"got {type(sim).__name__}")
        self.task = get_task(task) if isinstance(task, str) else task
        if not isinstance(self.task, Task):
            raise TypeError(f"task: expected a Task or a task name, got {type(task).__name__}")
        pool = np.asarray(start_pool, np.float32)
        if pool.ndim != 2 or pool.shape[0] < 1 or pool.shape[1] != self.task.obs_size:
            raise ValueError(f"start_pool: expected shape [S >= 1, {self.task.obs_size}] "
                             f"(obs_size of task {self.task.name!r}), got {pool.shape}")
        if not np.all(np.isfinite(pool)):
            raise ValueError("start_pool: expected finite values, got NaN or inf")
        self.start_pool = jnp.asarray(pool)
        self.deterministic = bool(deterministic)
        self.sim = sim

    def reset(self, rng: jax.Array) -> State:
        """A start obs drawn from the pool; rng: one PRNG key."""
        k_idx, k_step = jax.random.split(rng)
        idx = jax.random.randint(k_idx, (), 0, self.start_pool.shape[0])
        obs = self.start_pool[idx]
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=obs, obs=obs, reward=zero, done=zero, metrics={},
                     info={"rng": k_step})

    def step(self, state: State, action: jax.Array) -> State:
        """One simulated step. action [a] -> next State (reward from obs, action, next obs)."""
        k_dyn, k_next = jax.random.split(state.info["rng"])
        obs = state.obs
        next_obs = self._dynamics(obs, action, k_dyn).astype(jnp.float32)
        reward = self.task.reward_fn(obs, action, next_obs).astype(jnp.float32)
        done = self.task.done_fn(next_obs).astype(jnp.float32)
        info = {**state.info, "rng": k_next}
        return state.replace(pipeline_state=next_obs, obs=next_obs, reward=reward, done=done,
                             info=info)

    @property
    def observation_size(self) -> int:
        return self.task.obs_size

    @property
    def action_size(self) -> int:
        return self.task.action_size

    @property
    def backend(self) -> str:
        return "jax"

    @property
    def dt(self) -> float:
        return self.task.dt
