"""The oracle simulator: the task's real dynamics stepped from an observation.

It is the control of every simulator evaluation. A learned simulator maps (obs, action) to the
next obs; the oracle does the same with the true physics, so running it through exactly the
evaluation path of a learned simulator (start states, horizon, gamma, reward_fn / done_fn,
episodes) measures the ceiling of any simulator of this observation, and shows how much of a
metric is evaluation noise rather than model error.

For the MJX tasks one oracle step is: q and qd from the observation, ``env.pipeline_init(q,
qd)`` (``mjx.forward``), one ``env.pipeline_step``, the env's own ``_get_obs``. What the
observation does not hold is lost, so the oracle is not bit-exact:

* hopper / walker2d observe the torso height as brax's lagged ``x.pos`` (one physics substep
  behind q, see ``tasks``): q[1] is rebuilt as ``obs[1] - z0 + h * qd[1]`` with z0 the torso's
  height at q[1] = 0 (read off the model);
* MJX warm-starts its constraint solver from the previous step's accelerations; the oracle
  starts each step cold. With a converged solver this does not matter (the tasks' Ant runs 4
  Newton iterations instead of brax's 1 for this reason; ``tasks``).

(brax's own hopper / walker2d also clip the observed velocities to +-10, which no oracle can
undo; the tasks' observations hold the full velocities, see ``tasks``.)

``pointmass`` is pure JAX, so its oracle is exact.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from rl2s_jax.envs.tasks import _LOCO, Task, get_task, pointmass_dynamics
from rl2s_jax.model.simulator import Dynamics

# Tasks whose observation holds brax's lagged torso height in place of q[1].
_LAGGED_HEIGHT = ("hopper", "walker2d")


def oracle_dynamics(task: Task | str, env=None) -> Dynamics:
    """The real dynamics of ``task`` as ``dynamics(obs [..., o], action [..., a], key) ->
    next_obs [..., o]`` (the key is unused: the physics is deterministic).

    env: the unwrapped env to step (default ``task.make_env()``); pass a wrapped or modified
    env (e.g. one with planted effects) to get the oracle of that system.
    """
    task = get_task(task) if isinstance(task, str) else task
    if task.name == "pointmass" and env is None:
        return lambda obs, action, key: pointmass_dynamics(obs, action)
    if task.name not in _LOCO:
        raise ValueError(f"task: no oracle for {task.name!r}; expected one of "
                         f"{', '.join(['pointmass', *_LOCO])}")
    env = env if env is not None else task.make_env()
    spec = _LOCO[task.name]
    nq = int(env.sys.q_size())
    nv = int(env.sys.qd_size())
    if nq + nv != task.obs_size:
        raise ValueError(f"env: q ({nq}) + qd ({nv}) sizes do not make the task's observation "
                         f"({task.obs_size}); the oracle needs the full-state observation")
    z0 = None
    if task.name in _LAGGED_HEIGHT:
        q0 = jnp.asarray(env.sys.init_q, jnp.float32)
        # The torso's height minus the rootz joint's value: a constant offset of the model.
        z0 = env.pipeline_init(q0, jnp.zeros(nv)).x.pos[0, 2] - q0[1]

    def step_one(obs: jax.Array, action: jax.Array) -> jax.Array:
        q, qd = obs[:nq], obs[nq:]
        if z0 is not None:
            q = q.at[1].set(obs[1] - z0 + spec.substep * qd[1])
        state = env.pipeline_init(q, qd)
        state = env.pipeline_step(state, action)
        return env._get_obs(state).astype(obs.dtype)

    def dynamics(obs: jax.Array, action: jax.Array, key: jax.Array) -> jax.Array:
        del key
        lead = obs.shape[:-1]
        flat = jax.vmap(step_one)(obs.reshape(-1, obs.shape[-1]),
                                  action.reshape(-1, action.shape[-1]))
        return flat.reshape(*lead, obs.shape[-1])

    return dynamics


__all__ = ["oracle_dynamics"]
