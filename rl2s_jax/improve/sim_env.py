"""A learned simulator exposed as a brax ``Env``, so any JAX RL code can train inside it.

``SimulatorEnv(sim, start_pool)`` starts each episode from a real start state drawn from the
pool [S, o] and steps with the simulator: ``sim.sample`` (stochastic, default) or ``sim.mean``
(``deterministic=True``). Rewards and terminations come from the task's ``reward_fn`` /
``done_fn`` (a Simulator's ``task_fns``: for data of no task, its learned reward and hazard).
The PRNG key of the stochastic step rides in ``state.info["rng"]`` and is split at every
step, so ``step`` stays a pure function of (state, action).

Like brax's own envs it never resets by itself; wrap it for a time limit, e.g.
``brax.envs.training.wrap(env, episode_length=L, action_repeat=1)`` (note brax's
AutoResetWrapper restarts every env from the start state its first ``reset`` drew; SAC here
(``rl2s_jax.policy.sac``) does its own auto-reset with a fresh pool draw per episode).

Fine-tuning inside a learned model without exploiting its errors (configuration, all off by
default):

* **branched rollouts** (MBPO): ``start_pool=branch_pool(ds)`` (every real state of a
  Dataset, not only episode starts) and ``rollout_length=h``: each rollout starts from a
  real state and is cut after h steps. The cut is a time limit, not a termination: ``done``
  stays 0 and ``info["truncation"]`` turns 1, which SAC reads to end the rollout and
  bootstrap through it.
* **uncertainty penalty** (MOPO): reward r - lambda * u(s, a), with
  ``uncertainty_fn(obs [..., o], action [..., a]) -> u [...]`` (u >= 0; e.g. an ensemble's
  disagreement) and ``uncertainty_penalty=lambda``.
* **stop rule** (MOReL): the rollout terminates (``done`` = 1, and ``halt_penalty`` is
  subtracted from that step's reward) when u exceeds ``uncertainty_threshold``.

Without an explicit ``uncertainty_fn`` a Simulator's ensemble disagreement is used
(``Simulator.disagreement``, the measure its ``uncertainty`` field names: the elites' spread,
which grows where the members extrapolate; ``simulator_uncertainty``); it needs at least two
elites. Every step records u and whether the stop rule fired in
``state.metrics["uncertainty"]`` / ``["halted"]``.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State

from rl2s_jax.envs.tasks import Task, get_task
from rl2s_jax.model.simulator import Simulator, end_key, ends_episode, step_dynamics

Dynamics = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]
Uncertainty = Callable[[jax.Array, jax.Array], jax.Array]


def branch_pool(ds, max_states: int | None = None, seed: int = 0) -> jax.Array:
    """Real states to branch rollouts from: every obs row of the Dataset ``ds`` [S, o]
    (a uniform subsample without replacement of ``max_states`` rows when there are more)."""
    obs = np.asarray(ds.obs, np.float32)
    if obs.shape[0] == 0:
        raise ValueError("obs: expected some transitions to branch from, got none")
    if max_states is not None:
        if max_states < 1:
            raise ValueError(f"max_states: expected >= 1, got {max_states}")
        if obs.shape[0] > max_states:
            idx = np.random.default_rng(seed).choice(obs.shape[0], max_states, replace=False)
            obs = obs[np.sort(idx)]
    return jnp.asarray(obs)


def simulator_uncertainty(sim) -> Uncertainty:
    """A Simulator's per-step u(obs [..., o], action [..., a]) -> [...]: its ensemble's
    disagreement (``Simulator.disagreement``). Raises for a simulator of one elite, whose
    disagreement is 0 everywhere, and for anything that is not a Simulator."""
    if not isinstance(sim, Simulator):
        raise ValueError("uncertainty_fn: the uncertainty penalty / stop rule needs "
                         "u(obs, action); pass uncertainty_fn= (only a Simulator has its own "
                         f"u, got {type(sim).__name__})")
    if not sim.markov:
        raise ValueError("uncertainty_penalty / uncertainty_threshold: the disagreement of a "
                         "simulator with history inputs needs each step's past, which the "
                         "penalty does not carry yet; leave them off for this simulator")
    members = sim.n_members
    elites = members if sim.rank is None or sim.n_elites is None else min(sim.n_elites, members)
    if elites < 2:
        raise ValueError(f"uncertainty_penalty / uncertainty_threshold: u is the ensemble's "
                         f"disagreement, which needs >= 2 elites; this simulator has {members} "
                         f"member(s), {elites} elite(s) (train an ensemble model)")
    return sim.disagreement


def uncertainty_scale(uncertainty_fn: Uncertainty, obs, action) -> jax.Array:
    """Mean uncertainty over real (obs [N, o], action [N, a]) pairs: divide u by it so that
    a penalty lambda or a threshold reads in units of the data's typical u. -> []"""
    return jnp.mean(uncertainty_fn(jnp.asarray(obs), jnp.asarray(action)))


def real_rows(ds, max_rows: int = 20_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A uniform subsample of at most ``max_rows`` real (obs [n, o], action [n, a]) rows of a
    Dataset, for ``uncertainty_scale``."""
    n = ds.n_transitions
    rows = np.sort(np.random.default_rng(seed).choice(n, min(max_rows, n), replace=False))
    return np.asarray(ds.obs, np.float32)[rows], np.asarray(ds.action, np.float32)[rows]


def scaled_env_options(sim, obs_rows, action_rows, *, rollout_length: int | None = None,
                       uncertainty_penalty: float = 0.0,
                       uncertainty_threshold: float | None = None,
                       halt_penalty: float = 0.0) -> dict:
    """SimulatorEnv keywords (rollout_length, penalty, stop rule) with u = the simulator's
    ensemble disagreement (``simulator_uncertainty``) divided by its mean over the real rows
    (``real_rows``), so that the penalty lambda and the threshold read in units of the data's
    typical u. ``sim`` may be a traced Simulator (inside a vmap over simulators)."""
    opts: dict = {}
    if rollout_length is not None:
        opts["rollout_length"] = int(rollout_length)
    if uncertainty_penalty > 0 or uncertainty_threshold is not None:
        fn = simulator_uncertainty(sim)
        scale = uncertainty_scale(fn, obs_rows, action_rows)
        opts.update(uncertainty_fn=lambda o, a: fn(o, a) / scale,
                    uncertainty_penalty=float(uncertainty_penalty),
                    uncertainty_threshold=uncertainty_threshold,
                    halt_penalty=float(halt_penalty))
    return opts


class SimulatorEnv(Env):
    """A learned (or any) dynamics model as a brax Env.

    Args:
      sim: a ``Simulator`` or any ``dynamics(obs [..., o], action [..., a], key) -> [..., o]``.
      start_pool: real episode start observations [S, o]; ``reset`` draws one uniformly.
      task: a ``Task`` or its registry name, giving ``reward_fn`` / ``done_fn`` and sizes.
        Defaults to ``sim.task_fns()`` for a Simulator (its registered task's, or its learned
        reward and termination); required for a plain dynamics function.
      deterministic: step with ``sim.mean`` instead of ``sim.sample`` (Simulator only).

      rollout_length: cut rollouts after this many steps (``info["truncation"]``; None: no
        limit, as brax envs).
      uncertainty_fn: u(obs, action) >= 0 for the penalty and the stop rule (default: the
        Simulator's ensemble disagreement, when either is on; ``simulator_uncertainty``).
      uncertainty_penalty: lambda >= 0 of the reward r - lambda * u.
      uncertainty_threshold: terminate when u > this (None: never); may be a traced scalar.
      halt_penalty: subtracted from the reward of a step the stop rule ends (>= 0).

    State: ``obs`` is the observation [o] and so is ``pipeline_state``, except for a Simulator
    with history inputs, where it is (obs, the episode's ``History``); ``reward``, ``done`` are
    float32 scalars; ``info["rng"]`` the key of the next stochastic step,
    ``info["rollout_step"]`` the steps taken, ``info["truncation"]`` 1 at the rollout length;
    ``metrics["uncertainty"]``, ``metrics["halted"]`` of the last step.
    """

    def __init__(self, sim: Simulator | Dynamics, start_pool, task: Task | str | None = None,
                 *, deterministic: bool = False, rollout_length: int | None = None,
                 uncertainty_fn: Uncertainty | None = None, uncertainty_penalty: float = 0.0,
                 uncertainty_threshold: float | jax.Array | None = None,
                 halt_penalty: float = 0.0):
        if isinstance(sim, Simulator):
            if task is None:  # the registered task's rules, or the learned reward / hazard
                task = sim.task_fns()
            if deterministic:
                self._dynamics = lambda obs, action, key, hist=None: sim.mean(obs, action, hist)
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
        # A Simulator with a learned termination hazard ends episodes as value rollouts do.
        self._done_fn, self._hazard_fn = (sim.terminations(self.task.done_fn)
                                          if isinstance(sim, Simulator)
                                          else (self.task.done_fn, None))
        pool = np.asarray(start_pool, np.float32)
        if pool.ndim != 2 or pool.shape[0] < 1 or pool.shape[1] != self.task.obs_size:
            raise ValueError(f"start_pool: expected shape [S >= 1, {self.task.obs_size}] "
                             f"(obs_size of task {self.task.name!r}), got {pool.shape}")
        if not np.all(np.isfinite(pool)):
            raise ValueError("start_pool: expected finite values, got NaN or inf")
        self.start_pool = jnp.asarray(pool)
        self.deterministic = bool(deterministic)
        self.sim = sim
        if rollout_length is not None and int(rollout_length) < 1:
            raise ValueError(f"rollout_length: expected >= 1 or None, got {rollout_length}")
        self.rollout_length = None if rollout_length is None else int(rollout_length)
        if uncertainty_penalty < 0:
            raise ValueError(f"uncertainty_penalty: expected >= 0, got {uncertainty_penalty}")
        if halt_penalty < 0:
            raise ValueError(f"halt_penalty: expected >= 0, got {halt_penalty}")
        self.uncertainty_penalty = float(uncertainty_penalty)
        self.uncertainty_threshold = uncertainty_threshold
        self.halt_penalty = float(halt_penalty)
        needs_u = uncertainty_penalty > 0 or uncertainty_threshold is not None
        if uncertainty_fn is None and needs_u:
            uncertainty_fn = simulator_uncertainty(sim)
        if uncertainty_fn is not None and not callable(uncertainty_fn):
            raise TypeError(f"uncertainty_fn: expected a function (obs, action) -> u, got "
                            f"{type(uncertainty_fn).__name__}")
        self.uncertainty_fn = uncertainty_fn

    def reset(self, rng: jax.Array) -> State:
        """A start obs drawn from the pool; rng: one PRNG key."""
        k_idx, k_step = jax.random.split(rng)
        idx = jax.random.randint(k_idx, (), 0, self.start_pool.shape[0])
        obs = self.start_pool[idx]
        zero = jnp.zeros((), jnp.float32)
        hist = self.sim.new_history(()) if isinstance(self.sim, Simulator) else None
        return State(pipeline_state=obs if hist is None else (obs, hist), obs=obs,
                     reward=zero, done=zero,
                     metrics={"uncertainty": zero, "halted": zero},
                     info={"rng": k_step, "rollout_step": jnp.zeros((), jnp.int32),
                           "truncation": zero})

    def step(self, state: State, action: jax.Array) -> State:
        """One simulated step. action [a] -> next State (reward from obs, action, next obs)."""
        k_dyn, k_next = jax.random.split(state.info["rng"])
        obs = state.obs
        k_dyn, k_end = end_key(k_dyn, self._hazard_fn)
        hist = state.pipeline_state[1] if isinstance(state.pipeline_state, tuple) else None
        next_obs, hist = step_dynamics(self._dynamics, obs, action, k_dyn, hist)
        next_obs = next_obs.astype(jnp.float32)
        reward = self.task.reward_fn(obs, action, next_obs).astype(jnp.float32)
        done = ends_episode(obs, action, next_obs, k_end, self._done_fn,
                            self._hazard_fn).astype(jnp.float32)
        u = halted = jnp.zeros((), jnp.float32)
        if self.uncertainty_fn is not None:
            u = jnp.asarray(self.uncertainty_fn(obs, action), jnp.float32).reshape(())
            reward = reward - self.uncertainty_penalty * u
            if self.uncertainty_threshold is not None:
                halted = (u > self.uncertainty_threshold).astype(jnp.float32)
                reward = reward - self.halt_penalty * halted
                done = jnp.maximum(done, halted)
        steps = state.info["rollout_step"] + 1
        truncation = jnp.zeros((), jnp.float32)
        if self.rollout_length is not None:
            truncation = ((steps >= self.rollout_length) & (done < 0.5)).astype(jnp.float32)
        info = {**state.info, "rng": k_next, "rollout_step": steps, "truncation": truncation}
        metrics = {**state.metrics, "uncertainty": u, "halted": halted}
        return state.replace(pipeline_state=next_obs if hist is None else (next_obs, hist),
                             obs=next_obs, reward=reward, done=done, info=info,
                             metrics=metrics)

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
