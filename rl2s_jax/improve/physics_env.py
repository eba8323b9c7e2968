"""A physics model (``physics.physics_simulator.PhysicsSimulator``: the calibrated or nominal
MJX model) as the brax Env that SAC fine-tunes in and the Gymnasium env wraps.

:class:`PhysicsEnv` is a ``SimulatorEnv`` stepping the physics' ``dynamics`` under the task's
reward_fn / done_fn, from real start states; with an action delay the episode's past of
actions rides in ``pipeline_state`` as (obs, History), started empty at every reset, as a
learned simulator's history does. The physics is deterministic (``deterministic`` changes
nothing) and has no ensemble, so no uncertainty of its own: MOPO's penalty and the stop rule
need an explicit ``uncertainty_fn``.
"""

from __future__ import annotations

from brax.envs.base import State

from rl2s_jax.envs.tasks import Task
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.physics.physics_simulator import PhysicsSimulator

__all__ = ["PhysicsEnv", "is_physics"]


def is_physics(sim) -> bool:
    """Whether ``sim`` is a physics model (stepped by :class:`PhysicsEnv`)."""
    return isinstance(sim, PhysicsSimulator)


class PhysicsEnv(SimulatorEnv):
    """``SimulatorEnv`` of a ``PhysicsSimulator`` (module docstring). start_pool [S, O]; task:
    default the physics' ``task_fns()``; ``options``: SimulatorEnv keywords (rollout_length,
    uncertainty_fn, uncertainty_penalty, uncertainty_threshold, halt_penalty)."""

    def __init__(self, sim: PhysicsSimulator, start_pool, task: Task | str | None = None, *,
                 deterministic: bool = False, **options):
        if not is_physics(sim):
            raise TypeError(f"sim: expected a PhysicsSimulator, got {type(sim).__name__}")
        if options.get("uncertainty_fn") is None and (
                options.get("uncertainty_penalty", 0.0) > 0
                or options.get("uncertainty_threshold") is not None):
            raise ValueError("uncertainty_penalty / uncertainty_threshold: u is a learned "
                             "ensemble's disagreement, and a physics model has none; leave "
                             "them off or pass uncertainty_fn=")
        del deterministic  # the physics is deterministic either way
        super().__init__(sim.dynamics, start_pool, sim.task_fns() if task is None else task,
                         **options)
        self.physics = sim

    def reset(self, rng) -> State:
        """A start obs drawn from the pool, with the empty past of actions under a delay."""
        state = super().reset(rng)
        hist = self.physics.new_history(())
        return state if hist is None else state.replace(pipeline_state=(state.obs, hist))
