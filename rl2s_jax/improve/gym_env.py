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

Step info: ``info["uncertainty"]`` is the ensemble's disagreement at the step's (obs, action)
(``Simulator.disagreement``, with the episode's past for a simulator with history inputs)
when the simulator is a ``Simulator`` of >= 2 elites; the reward does not change with it. It
is absent otherwise (a dynamics function, or one elite, whose disagreement is 0 everywhere).

``render_mode="rgb_array"``: ``render()`` draws the current observation with MuJoCo's
renderer on the task's MjModel (the MJX tasks; qpos from the observation, the "track"
camera). Headless machines need ``MUJOCO_GL=egl`` (or ``osmesa``) set before Python starts.

Importing this module registers with Gymnasium (once; importing again does not re-register;
``import rl2s_jax`` registers the first id already, rl2s_jax/_gym.py):
``"rl2s/Simulator-v0"`` (``gymnasium.make(id, ckpt=..., data=..., **kwargs)`` is
:meth:`SimulatorGymEnv.from_checkpoint`; ``gymnasium.make_vec(id, num_envs, ckpt=...,
data=...)`` the vector env; ``physics="calibrated.json"`` or ``physics="nominal"`` in place of
``ckpt``: the physics model of `rl2s diagnose --physics`, :meth:`SimulatorGymEnv.from_physics`,
deterministic, with no ``info["uncertainty"]``) and ``"rl2s/<task>-v0"`` for every
registered task: the task's real brax env as a Gymnasium env (:class:`TaskGymEnv`), which
Minari exports name as their ``env_spec``.
"""
from __future__ import annotations

import os
from typing import Any, NamedTuple

import gymnasium as gym
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from etils import epath
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.checks import tree_where
from rl2s_jax.envs.tasks import Task, get_task, task_names
from rl2s_jax.improve.physics_env import PhysicsEnv, is_physics
from rl2s_jax.improve.sim_env import Dynamics, SimulatorEnv
from rl2s_jax.model.simulator import Simulator, start_pool
from rl2s_jax.physics.hybrid import load_hybrid
from rl2s_jax.physics.physics_simulator import PhysicsSimulator, physics_simulator

__all__ = ["SIMULATOR_ENV_ID", "SimulatorGymEnv", "SimulatorVectorEnv", "TaskGymEnv",
           "VecState", "make_simulator_env", "make_simulator_vector_env", "register_envs",
           "task_env_id", "vec_reset", "vec_step"]

_TASK_LIMIT = "task"  # max_episode_steps default: the task's episode_length
SIMULATOR_ENV_ID = "rl2s/Simulator-v0"
# The MJX tasks' MuJoCo models (brax's assets), for render(); their observation is qpos ++ qvel.
_MODEL_XML = {"hopper": "hopper.xml", "walker2d": "walker2d.xml",
              "halfcheetah": "half_cheetah.xml", "ant": "ant.xml"}
# Tasks whose observation holds brax's lagged torso height in place of qpos[1] (envs.tasks).
_LAGGED_HEIGHT = ("hopper", "walker2d")


def task_env_id(task: str) -> str:
    """The Gymnasium id of a registered task's real env: ``"rl2s/<task>-v0"``."""
    return f"rl2s/{task}-v0"


def _brax_env(sim, starts, task, deterministic) -> SimulatorEnv:
    """The SimulatorEnv; ``starts`` is a start pool [S, o] or a Dataset (its t == 0 rows)."""
    pool = start_pool(starts) if hasattr(starts, "episode_id") else starts
    env = PhysicsEnv if is_physics(sim) else SimulatorEnv
    return env(sim, pool, task, deterministic=deterministic)


def _limit(max_episode_steps, task: Task) -> int | None:
    limit = task.episode_length if max_episode_steps == _TASK_LIMIT else max_episode_steps
    if limit is not None and (not isinstance(limit, int | np.integer) or limit < 1):
        raise ValueError(f"max_episode_steps: expected an int >= 1 or None, got {limit!r}")
    return None if limit is None else int(limit)


def _spaces(task: Task) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    obs = gym.spaces.Box(-np.inf, np.inf, (task.obs_size,), np.float32)
    action = gym.spaces.Box(-1.0, 1.0, (task.action_size,), np.float32)  # the tasks' range
    return obs, action


def _from_files(ckpt: str | os.PathLike | None, data, step: int | None, physics=None):
    """(simulator, Dataset): the checkpoint's, or with ``physics`` (a calibrated.json or
    "nominal") the physics model for the data's task (``physics_simulator``)."""
    if data is None:
        raise ValueError("data: required (the Dataset, or its .npz path, whose start states "
                         "the episodes start from)")
    if (ckpt is None) == (physics is None):
        raise ValueError("physics: give ckpt= (a learned simulator's checkpoint) or physics= "
                         "(a calibrated.json or 'nominal'), one of them")
    if physics is None:  # the checkpoint first: a wrong path fails before the data loads
        sim = load_hybrid(ckpt, step)[0]  # any checkpoint; a hybrid with its physics
    elif step is not None:
        raise ValueError("step: a checkpoint's step; a physics model has none")
    ds = load_dataset(data) if isinstance(data, str | os.PathLike) else data
    if physics is not None:
        sim = physics_simulator(str(physics), ds.meta.get("task"), ds.obs_size, ds.action_size)
    return sim, ds


def _disagreement_fn(sim):
    """u(state, action [a]) -> [] float32: the simulator's elite disagreement at the state's
    obs (with the episode's past where the members see one), or None where there is none to
    report (not a Simulator, or fewer than 2 elites)."""
    if not isinstance(sim, Simulator):
        return None
    members = sim.n_members
    elites = members if sim.rank is None or sim.n_elites is None else min(sim.n_elites, members)
    if elites < 2:
        return None

    def disagreement(state: State, action: jax.Array) -> jax.Array:
        hist = state.pipeline_state[1] if isinstance(state.pipeline_state, tuple) else None
        return sim.disagreement(state.obs, action, hist).astype(jnp.float32)

    return disagreement


def _model_xml(task: Task) -> str:
    """The MuJoCo model file of ``task``; NotImplementedError naming a task without one."""
    if task.name not in _MODEL_XML:
        raise NotImplementedError(
            f"render: task {task.name!r} has no MuJoCo model to draw; rendering is for the MJX "
            f"tasks ({', '.join(_MODEL_XML)})")
    return _MODEL_XML[task.name]


def _check_render_mode(render_mode, task: Task) -> None:
    """ValueError for an unknown render mode, NotImplementedError for "rgb_array" on a task
    without a MuJoCo model; before any env is built."""
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
    if render_mode == "rgb_array":
        _model_xml(task)


def _episode_key(env, seed: int | None) -> jax.Array:
    """The key of the next episode: from ``seed``; else, the first time, a draw of the env's
    ``np_random``; else the last episode's key folded with 1."""
    if seed is not None:
        return jax.random.PRNGKey(seed)
    if env._key is None:
        return jax.random.PRNGKey(int(env.np_random.integers(2**31 - 1)))
    return jax.random.fold_in(env._key, 1)


def _checked_action(env, action, name: str) -> np.ndarray:
    """A step's action as float32, after checking the env was reset and the shape matches its
    action space (``name``: the argument's name in the error)."""
    if env._state is None:
        raise gym.error.ResetNeeded("step: call reset() before the first step")
    action = np.asarray(action, np.float32)
    if action.shape != env.action_space.shape:
        raise ValueError(f"{name}: expected shape {env.action_space.shape}, got {action.shape}")
    return action


class _Picture:
    """Draws observations of an MJX task: qpos from the observation [o] (qpos ++ qvel; the
    lagged torso height of hopper / walker2d turned back into qpos[1] as the oracle does),
    ``mj_forward``, then MuJoCo's offscreen renderer through the model's "track" camera."""

    def __init__(self, task: Task):
        xml = _model_xml(task)
        path = epath.resource_path("brax") / "envs" / "assets" / xml
        self.model = mujoco.MjModel.from_xml_path(str(path))
        self.data = mujoco.MjData(self.model)
        nq, nv = self.model.nq, self.model.nv
        if nq + nv != task.obs_size:
            raise ValueError(f"task: qpos ({nq}) + qvel ({nv}) of {xml} do not make the "
                             f"observation of {task.name!r} ({task.obs_size})")
        self.z0 = None
        if task.name in _LAGGED_HEIGHT:  # torso height minus the rootz joint, at qpos0
            mujoco.mj_kinematics(self.model, self.data)
            self.z0 = float(self.data.xpos[1, 2] - self.model.qpos0[1])
        self.renderer: mujoco.Renderer | None = None

    def qpos(self, obs: np.ndarray) -> np.ndarray:
        """qpos [nq] of an observation [o]."""
        nq = self.model.nq
        qpos = np.asarray(obs[:nq], np.float64).copy()
        if self.z0 is not None:
            qpos[1] = obs[1] - self.z0 + self.model.opt.timestep * obs[nq + 1]
        return qpos

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The rgb image [H, W, 3] uint8 of an observation [o]."""
        if self.renderer is None:  # the GL context: only when a frame is asked for
            self.renderer = mujoco.Renderer(self.model)
        self.data.qpos[:] = self.qpos(obs)
        self.data.qvel[:] = np.asarray(obs[self.model.nq:], np.float64)
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera="track")
        return self.renderer.render()

    def close(self):
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


class _BraxGymEnv(gym.Env):
    """A brax Env of a task behind the Gymnasium API (one jitted reset / step per call)."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, env: Env, task: Task, max_episode_steps, render_mode: str | None,
                 disagreement=None):
        _check_render_mode(render_mode, task)
        self.brax_env = env
        self.task = task
        self.max_episode_steps = _limit(max_episode_steps, task)
        self.observation_space, self.action_space = _spaces(task)
        self.render_mode = render_mode
        self._picture = _Picture(task) if render_mode == "rgb_array" else None
        self.metadata = {**type(self).metadata, "render_fps": 1.0 / task.dt,
                         "render_modes": ["rgb_array"] if task.name in _MODEL_XML else []}

        def step(state: State, action: jax.Array):
            u = () if disagreement is None else (disagreement(state, action),)
            state = env.step(state, action)
            return state, (state.obs, state.reward, state.done, *u)

        self._reset_fn = jax.jit(env.reset)
        self._step_fn = jax.jit(step)
        self._state: State | None = None
        self._key: jax.Array | None = None  # key of the current episode
        self._t = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._key = _episode_key(self, seed)
        self._state = self._reset_fn(self._key)
        self._t = 0
        return np.array(self._state.obs, np.float32), {}

    def step(self, action):
        action = _checked_action(self, action, "action")
        self._state, out = self._step_fn(self._state, jnp.asarray(action))
        obs, reward, done, *u = jax.device_get(out)
        self._t += 1
        terminated = bool(done > 0.5)
        truncated = (not terminated and self.max_episode_steps is not None
                     and self._t >= self.max_episode_steps)
        info = {"uncertainty": float(u[0])} if u else {}
        return np.array(obs, np.float32), float(reward), terminated, bool(truncated), info

    def render(self):
        """The current observation drawn by MuJoCo: rgb [H, W, 3] uint8 (render_mode
        "rgb_array"); None with a warning when render_mode is None."""
        _model_xml(self.task)  # NotImplementedError for a task without a model
        if self.render_mode is None:
            gym.logger.warn("render: the env was made without render_mode; pass "
                            "render_mode='rgb_array' to draw frames")
            return None
        if self._state is None:
            raise gym.error.ResetNeeded("render: call reset() before the first frame")
        return self._picture(np.asarray(self._state.obs))

    def close(self):
        if self._picture is not None:
            self._picture.close()


class SimulatorGymEnv(_BraxGymEnv):
    """A learned (or any) dynamics model as a Gymnasium env.

    Args:
      sim: a ``Simulator``, a ``PhysicsSimulator`` (the calibrated or nominal physics:
        :meth:`from_physics`) or any ``dynamics(obs [..., o], action [..., a], key) -> [..., o]``.
      starts: real episode start observations [S, o], or a Dataset (its rows with t == 0).
      task: a ``Task`` or its name (reward_fn, done_fn, sizes); default ``sim.task_fns()``.
      deterministic: step with the simulator's mean instead of a sample.
      max_episode_steps: truncate after this many steps (None: never); default the task's
        ``episode_length``.
      render_mode: None or "rgb_array" (the MJX tasks; NotImplementedError for others).

    Observations are float32 [o]; actions float32 [a] in the Box [-1, 1] (passed to the
    dynamics and the reward as they are, as in the brax env); step info holds
    ``"uncertainty"`` (float, the elites' disagreement at the step's (obs, action)) for a
    Simulator of >= 2 elites, else it is empty.
    """

    def __init__(self, sim: Simulator | PhysicsSimulator | Dynamics, starts,
                 task: Task | str | None = None, *, deterministic: bool = False,
                 max_episode_steps: int | None | str = _TASK_LIMIT,
                 render_mode: str | None = None):
        env = _brax_env(sim, starts, task, deterministic)
        super().__init__(env, env.task, max_episode_steps, render_mode, _disagreement_fn(sim))

    @classmethod
    def from_checkpoint(cls, ckpt: str | os.PathLike, data, *, step: int | None = None,
                        **kwargs) -> SimulatorGymEnv:
        """The simulator of checkpoint directory ``ckpt`` (newest intact step unless ``step``)
        with start states from ``data`` (a Dataset or its .npz path)."""
        sim, ds = _from_files(ckpt, data, step)
        return cls(sim, ds, **kwargs)

    @classmethod
    def from_physics(cls, physics: str | os.PathLike, data, **kwargs) -> SimulatorGymEnv:
        """The physics model ``physics`` (a calibrated.json of `rl2s diagnose --physics`, or
        "nominal": the data's task's MuJoCo model) with start states from ``data``."""
        sim, ds = _from_files(None, data, None, physics)
        return cls(sim, ds, **kwargs)


class TaskGymEnv(_BraxGymEnv):
    """A registered task's real environment (``task.make_env()``, its own reward and
    termination) as a Gymnasium env: the env of ``"rl2s/<task>-v0"``, and of the ``env_spec``
    of a Minari export. ``reset(seed=s)`` is the brax env's ``reset(jax.random.PRNGKey(s))``.

    Args:
      task: a registered task's name (or the ``Task``).
      max_episode_steps, render_mode: as :class:`SimulatorGymEnv`.
    """

    def __init__(self, task: Task | str, *, max_episode_steps: int | None | str = _TASK_LIMIT,
                 render_mode: str | None = None):
        task = get_task(task) if isinstance(task, str) else task
        if not isinstance(task, Task):
            raise TypeError(f"task: expected a Task or a task name, got {type(task).__name__}")
        _check_render_mode(render_mode, task)  # before the (MJX) env is built
        _limit(max_episode_steps, task)
        super().__init__(task.make_env(), task, max_episode_steps, render_mode)


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
    None), "_final_obs": [B] bool}`` when an env ended; for a Simulator of >= 2 elites info
    also holds ``"uncertainty"`` [B] float32 (each env's elite disagreement at its step's
    (obs, action)) and ``"_uncertainty"`` [B] bool (all True). ``reset(seed=s)`` starts
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
        disagreement = _disagreement_fn(sim)

        def step(vs: VecState, action: jax.Array):
            u = () if disagreement is None else (jax.vmap(disagreement)(vs.env, action),)
            vs, out = vec_step(env, limit, vs, action)
            return vs, (*out, *u)

        self._reset_fn = jax.jit(lambda key: vec_reset(env, n, key))
        self._step_fn = jax.jit(step)
        self._state: VecState | None = None
        self._key: jax.Array | None = None

    @classmethod
    def from_checkpoint(cls, ckpt: str | os.PathLike, data, num_envs: int, *,
                        step: int | None = None, **kwargs) -> SimulatorVectorEnv:
        """As :meth:`SimulatorGymEnv.from_checkpoint`, with ``num_envs`` envs."""
        sim, ds = _from_files(ckpt, data, step)
        return cls(sim, ds, num_envs, **kwargs)

    @classmethod
    def from_physics(cls, physics: str | os.PathLike, data, num_envs: int,
                     **kwargs) -> SimulatorVectorEnv:
        """As :meth:`SimulatorGymEnv.from_physics`, with ``num_envs`` envs."""
        sim, ds = _from_files(None, data, None, physics)
        return cls(sim, ds, num_envs, **kwargs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._key = _episode_key(self, seed)
        self._state = self._reset_fn(self._key)
        return np.array(self._state.env.obs, np.float32), {}

    def step(self, actions):
        actions = _checked_action(self, actions, "actions")
        self._state, out = self._step_fn(self._state, jnp.asarray(actions))
        obs, reward, terminated, truncated, last, *u = (np.array(x) for x in
                                                         jax.device_get(out))
        info: dict[str, Any] = {}
        ended = terminated | truncated
        if ended.any():
            final = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(ended):
                final[i] = last[i]
            info = {"final_obs": final, "_final_obs": ended}
        if u:
            info.update(uncertainty=u[0], _uncertainty=np.ones(self.num_envs, bool))
        return obs, reward, terminated, truncated, info


# --------------------------------------------------------------------------- registration


def make_simulator_env(ckpt: str | os.PathLike | None = None, data=None, *,
                       physics: str | os.PathLike | None = None, step: int | None = None,
                       **kwargs) -> SimulatorGymEnv:
    """The entry point of ``gymnasium.make("rl2s/Simulator-v0", ckpt=..., data=...,
    **kwargs)``: :meth:`SimulatorGymEnv.from_checkpoint`; with ``physics=`` in place of
    ``ckpt``, :meth:`SimulatorGymEnv.from_physics`."""
    sim, ds = _from_files(ckpt, data, step, physics)
    return SimulatorGymEnv(sim, ds, **kwargs)


def make_simulator_vector_env(ckpt: str | os.PathLike | None = None, data=None,
                              num_envs: int = 1, *, physics: str | os.PathLike | None = None,
                              step: int | None = None, **kwargs) -> SimulatorVectorEnv:
    """The vector entry point of ``gymnasium.make_vec("rl2s/Simulator-v0", num_envs,
    ckpt=..., data=...)`` (or ``physics=...`` in place of ``ckpt``): as
    :func:`make_simulator_env`."""
    sim, ds = _from_files(ckpt, data, step, physics)
    return SimulatorVectorEnv(sim, ds, num_envs, **kwargs)


def register_envs() -> None:
    """Register ``"rl2s/Simulator-v0"`` and ``"rl2s/<task>-v0"`` (every registered task's real
    env, truncated at its episode length) with Gymnasium. Ids already in the registry are
    left as they are, so calling it again (or importing this module again) does not warn."""
    specs = {SIMULATOR_ENV_ID: dict(entry_point=f"{__name__}:make_simulator_env",
                                    vector_entry_point=f"{__name__}:make_simulator_vector_env")}
    for name in task_names():
        specs[task_env_id(name)] = dict(entry_point=f"{__name__}:TaskGymEnv",
                                        kwargs={"task": name},
                                        max_episode_steps=get_task(name).episode_length)
    for env_id, spec in specs.items():
        if env_id not in gym.registry:
            gym.register(env_id, **spec)


register_envs()
