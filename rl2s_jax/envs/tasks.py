"""Task registry: env factory, reward_fn(s, a, s'), done_fn(s') and sizes for each task.

A learned simulator only produces next observations; the reward and the termination come from
``Task.reward_fn`` and ``Task.done_fn``, written here as pure JAX functions of one transition.
They use ``[..., i]`` indexing, so they broadcast over any leading batch dimensions:
``obs [..., obs_size]``, ``action [..., action_size]`` -> ``reward [...]`` / ``done [...]``.

The MuJoCo tasks (hopper, walker2d, halfcheetah, ant) are brax's MJX environments with the x
position kept in the observation. Their reward functions reproduce brax's own reward exactly
(up to float32 rounding) for the *default* constructor arguments and ``backend='mjx'``. Two
details of brax/MJX shape them:

* Lagged body positions. ``mjx.step`` computes the kinematics (``xpos``) *before* integrating,
  so after an env step ``pipeline_state.x.pos`` belongs to the state one physics substep back,
  while ``q`` (and so the observation) is current. brax's forward velocity is
  ``(x.pos' - x.pos) / dt``; with semi-implicit Euler, ``x_lagged = q_x - h * qd_x`` (h the
  physics timestep), hence::

      x_velocity = ((x' - h v') - (x - h v)) / dt,   dt = h * n_frames.

  The one exception is the first step of an episode: ``reset`` runs ``mjx.forward``, so the
  first ``x.pos`` is not lagged and brax's reward there equals ``reward_fn(...) - v0 / n_frames``
  (``v0`` the reset x-velocity; at most 0.00125 for hopper/walker2d, ~0.02 typical for
  halfcheetah/ant). No function of the observations can tell the first step apart.
  The hopper/walker2d observation height ``obs[1]`` is itself the lagged ``x.pos`` height, so the
  healthy checks using it are exact; ant's healthy height is reconstructed as ``z' - h vz'``.

Two brax defaults would make the observation non-Markov, so these tasks change them (measured:
``experiments/oracle_check.py``, docs/RESULTS.md "The oracle"):

* No velocity clipping. brax's hopper and walker2d clip ``qvel`` to [-10, 10] in the
  observation; good walkers swing their legs faster than that at most steps, so the true next
  state could not be computed from the observation (the oracle's Walker2d values were a
  quarter of the true ones). Here the observation holds the full ``qvel``.
* A converged contact solver for Ant. brax's MJX Ant runs MJX's Newton solver for ONE
  iteration warm-started from the previous step's accelerations, a hidden state: one step from
  the observation was off by >1 in 10% of velocities. Here it runs 4 iterations (the next
  state no longer depends on the warm start; same cost per step on the CPU).

Overrides passed to ``make_env`` that change the reward or termination (weights, ranges,
``n_frames``, ``exclude_current_positions_from_observation``, ``backend``) are not reflected in
``reward_fn``/``done_fn``.
"""

from __future__ import annotations

import dataclasses
import difflib
import xml.etree.ElementTree as ET
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs import base as brax_base
from etils import epath

__all__ = [
    "POINTMASS_DT",
    "TASKS",
    "PointMass",
    "Task",
    "get_task",
    "register",
    "pointmass_done",
    "pointmass_dynamics",
    "pointmass_reward",
    "task_names",
]

RewardFn = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]
DoneFn = Callable[[jax.Array], jax.Array]


@dataclasses.dataclass(frozen=True)
class Task:
    """One task.

    Attributes:
      name: registry name.
      obs_size: observation size.
      action_size: action size (actions live in [-1, 1]).
      episode_length: time limit in env steps.
      make_env: ``make_env(**overrides)`` -> a fresh, unwrapped brax Env (no time limit, no
        auto-reset). For MuJoCo tasks the overrides go to the brax constructor.
      reward_fn: ``reward_fn(obs [..., O], action [..., A], next_obs [..., O]) -> [...]``.
      done_fn: ``done_fn(next_obs [..., O]) -> bool [...]`` (termination, not time limit).
      dt: seconds per env step, as used by ``reward_fn``; equals ``make_env().dt``.
      position_dims: observation dims holding absolute positions (x; x, y for Ant) that the
        dynamics do not depend on; simulator models leave them out of their inputs.
    """

    name: str
    obs_size: int
    action_size: int
    episode_length: int
    make_env: Callable[..., brax_base.Env]
    reward_fn: RewardFn
    done_fn: DoneFn
    dt: float
    position_dims: tuple[int, ...] = ()


# --------------------------------------------------------------------------------------------
# MuJoCo locomotion tasks (brax MJX envs).


def _xml_timestep(xml_name: str) -> float:
    """Reads ``<option timestep=...>`` from a brax asset XML (no MuJoCo/MJX model is built)."""
    path = epath.resource_path("brax") / "envs" / "assets" / xml_name
    option = ET.fromstring(path.read_text()).find("option")
    return float(option.get("timestep"))


class _Loco(NamedTuple):
    """Constants of one brax locomotion env (defaults of its constructor)."""

    brax_name: str
    obs_size: int  # len(q) + len(qd)
    action_size: int
    substep: float  # physics timestep h, from the XML <option timestep>
    n_frames: int  # physics substeps per env step (hard-coded in brax's env __init__)
    x_idx: int  # obs index of the root x position (q[0])
    vx_idx: int  # obs index of the root x velocity (qd[0])

    @property
    def dt(self) -> float:
        return self.substep * self.n_frames


_LOCO = {
    # hopper.xml timestep 0.002, n_frames 4 -> dt 0.008. obs = q (6) ++ qd (6).
    "hopper": _Loco("hopper", 12, 3, _xml_timestep("hopper.xml"), 4, 0, 6),
    # walker2d.xml timestep 0.002, n_frames 4 -> dt 0.008. obs = q (9) ++ qd (9).
    "walker2d": _Loco("walker2d", 18, 6, _xml_timestep("walker2d.xml"), 4, 0, 9),
    # half_cheetah.xml timestep 0.01, n_frames 5 -> dt 0.05. obs = q (9) ++ qd (9).
    "halfcheetah": _Loco("halfcheetah", 18, 6, _xml_timestep("half_cheetah.xml"), 5, 0, 9),
    # ant.xml timestep 0.01, n_frames 5 -> dt 0.05. obs = q (15: xyz, quat, 8 joints) ++ qd (14).
    "ant": _Loco("ant", 29, 8, _xml_timestep("ant.xml"), 5, 0, 15),
}


def _forward_velocity(spec: _Loco, obs: jax.Array, next_obs: jax.Array) -> jax.Array:
    """brax's ``(x.pos'[x] - x.pos[x]) / dt`` from observations (see module docstring). [...]"""
    dx = next_obs[..., spec.x_idx] - obs[..., spec.x_idx]
    dv = next_obs[..., spec.vx_idx] - obs[..., spec.vx_idx]
    return (dx - spec.substep * dv) / spec.dt


def _ctrl_cost(weight: float, action: jax.Array) -> jax.Array:
    return weight * jnp.sum(jnp.square(action), axis=-1)


def hopper_reward(obs: jax.Array, action: jax.Array, next_obs: jax.Array) -> jax.Array:
    """Hopper reward: x_velocity + 1 (healthy, always: terminate_when_unhealthy) - 1e-3 |a|^2.

    Shapes: obs, next_obs [..., 12], action [..., 3] -> [...]. Exact except the first step of an
    episode (module docstring).
    """
    return _forward_velocity(_LOCO["hopper"], obs, next_obs) + 1.0 - _ctrl_cost(1e-3, action)


def hopper_done(next_obs: jax.Array) -> jax.Array:
    """Hopper termination: not healthy. next_obs [..., 12] -> bool [...].

    brax: healthy iff 0.7 < z, |q[2]| < 0.2 and every entry of (q[2:], qd) is in (-100, 100),
    with z = ``x.pos`` torso height = ``obs[1]`` and q[2] = ``obs[2]``: exact (the observation
    holds the full qd). NaNs are unhealthy in both.
    """
    z = next_obs[..., 1]
    angle = next_obs[..., 2]
    state_vec = next_obs[..., 2:]  # q[2:] ++ qd
    healthy = jnp.all((-100.0 < state_vec) & (state_vec < 100.0), axis=-1)
    healthy &= (0.7 < z) & (z < jnp.inf)
    healthy &= (-0.2 < angle) & (angle < 0.2)
    return ~healthy


def walker2d_reward(obs: jax.Array, action: jax.Array, next_obs: jax.Array) -> jax.Array:
    """Walker2d reward: x_velocity + 1 (healthy, always) - 1e-3 |a|^2.

    Shapes: obs, next_obs [..., 18], action [..., 6] -> [...]. Exact except the first step of an
    episode (module docstring).
    """
    return _forward_velocity(_LOCO["walker2d"], obs, next_obs) + 1.0 - _ctrl_cost(1e-3, action)


def walker2d_done(next_obs: jax.Array) -> jax.Array:
    """Walker2d termination: not (0.8 < z < 2.0 and -1 < q[2] < 1). next_obs [..., 18] -> bool.

    z = ``obs[1]`` is brax's ``x.pos`` torso height and q[2] = ``obs[2]``: exact.
    """
    z = next_obs[..., 1]
    angle = next_obs[..., 2]
    healthy = (z > 0.8) & (z < 2.0) & (angle > -1.0) & (angle < 1.0)
    return ~healthy


def halfcheetah_reward(obs: jax.Array, action: jax.Array, next_obs: jax.Array) -> jax.Array:
    """HalfCheetah reward: x_velocity - 0.1 |a|^2. obs, next_obs [..., 18], action [..., 6].

    No clipping in the observation; exact except the first step of an episode.
    """
    return _forward_velocity(_LOCO["halfcheetah"], obs, next_obs) - _ctrl_cost(0.1, action)


def halfcheetah_done(next_obs: jax.Array) -> jax.Array:
    """HalfCheetah never terminates. next_obs [..., 18] -> False [...]."""
    return jnp.zeros(next_obs.shape[:-1], dtype=bool)


def ant_reward(obs: jax.Array, action: jax.Array, next_obs: jax.Array) -> jax.Array:
    """Ant reward: x_velocity + 1 (healthy, always) - 0.5 |a|^2 - 0 (contact cost).

    brax's Ant sets ``contact_cost = 0.0`` unconditionally (``contact_cost_weight`` is unused and
    ``use_contact_forces=True`` raises NotImplementedError), so there is no contact term and
    contact forces are not in the observation. obs, next_obs [..., 29], action [..., 8] -> [...].
    Exact except the first step of an episode.
    """
    return _forward_velocity(_LOCO["ant"], obs, next_obs) + 1.0 - _ctrl_cost(0.5, action)


def ant_done(next_obs: jax.Array) -> jax.Array:
    """Ant termination: lagged torso height z < 0.2 or z > 1.0. next_obs [..., 29] -> bool.

    brax tests ``x.pos`` height, one physics substep behind q; it equals ``q[2] - h qd[2]``
    (obs[2], obs[17]) up to float32 rounding.
    """
    spec = _LOCO["ant"]
    z = next_obs[..., 2] - spec.substep * next_obs[..., spec.vx_idx + 2]
    return (z < 0.2) | (z > 1.0)


ANT_SOLVER_ITERATIONS = 4


def _full_velocity(env: brax_base.Env) -> brax_base.Env:
    """``env`` with brax's hopper/walker2d observation minus its velocity clip: q with q[1]
    replaced by the (lagged) torso height, then the full qd (module docstring)."""

    class FullVelocity(type(env)):
        def _get_obs(self, pipeline_state):
            position = pipeline_state.q.at[1].set(pipeline_state.x.pos[0, 2])
            if self._exclude_current_positions_from_observation:
                position = position[1:]
            return jnp.concatenate((position, pipeline_state.qd))

    FullVelocity.__name__ = f"{type(env).__name__}FullVelocity"
    env.__class__ = FullVelocity
    return env


def _mjx_factory(brax_name: str) -> Callable[..., brax_base.Env]:
    def make_env(**overrides) -> brax_base.Env:
        """A fresh unwrapped brax MJX env with x positions in the observation."""
        # Imported here to keep start-up fast: brax.envs imports every brax environment.
        import brax.envs  # local: keeps `import rl2s_jax.envs.tasks` light

        kwargs = {
            "backend": "mjx",
            "exclude_current_positions_from_observation": False,
            **overrides,
        }
        env = brax.envs.get_environment(brax_name, **kwargs)
        if brax_name in ("hopper", "walker2d"):
            env = _full_velocity(env)
        if brax_name == "ant":  # see the module docstring: no hidden solver warm start
            env.sys = env.sys.tree_replace({"opt.iterations": ANT_SOLVER_ITERATIONS})
        return env

    make_env.__name__ = f"make_{brax_name}"
    return make_env


def _loco_task(name: str, reward_fn: RewardFn, done_fn: DoneFn) -> Task:
    spec = _LOCO[name]
    return Task(
        name=name,
        obs_size=spec.obs_size,
        action_size=spec.action_size,
        episode_length=1000,
        make_env=_mjx_factory(spec.brax_name),
        reward_fn=reward_fn,
        done_fn=done_fn,
        dt=spec.dt,
        position_dims=(0, 1) if name == "ant" else (0,),
    )


# --------------------------------------------------------------------------------------------
# Point mass: a tiny pure-JAX task with known dynamics, for fast tests.

POINTMASS_DT = 0.05
_PM_DECAY = 0.95  # velocity decay per step
_PM_GAIN = 2.0  # acceleration per unit action
_PM_LIMIT = 2.0  # terminate when |p| > limit
_PM_CTRL = 0.1  # control cost weight
_PM_ALIVE = 1.0  # per-step bonus, so that ending an episode early never pays


def pointmass_dynamics(obs: jax.Array, action: jax.Array) -> jax.Array:
    """True point-mass dynamics. obs [..., 2] = (p, v), action [..., 1] -> next_obs [..., 2].

    With a = clip(action, -1, 1) and dt = 0.05 (semi-implicit Euler)::

        v' = 0.95 v + dt * 2.0 * a
        p' = p + dt * v'
    """
    p, v = obs[..., 0], obs[..., 1]
    a = jnp.clip(action[..., 0], -1.0, 1.0)
    v_next = _PM_DECAY * v + POINTMASS_DT * _PM_GAIN * a
    p_next = p + POINTMASS_DT * v_next
    return jnp.stack([p_next, v_next], axis=-1)


def pointmass_reward(obs: jax.Array, action: jax.Array, next_obs: jax.Array) -> jax.Array:
    """1 - p'^2 - 0.1 |action|^2 (raw, unclipped action, as brax's ctrl costs). -> [...].

    The alive bonus makes surviving worth more than terminating, as in the MuJoCo tasks.
    """
    del obs
    return _PM_ALIVE - jnp.square(next_obs[..., 0]) - _ctrl_cost(_PM_CTRL, action)


def pointmass_done(next_obs: jax.Array) -> jax.Array:
    """Terminates when |p'| > 2.0. next_obs [..., 2] -> bool [...]."""
    return jnp.abs(next_obs[..., 0]) > _PM_LIMIT


class PointMass(brax_base.Env):
    """1-D point mass as a brax Env, in pure JAX (no physics engine).

    ``State.pipeline_state`` and ``State.obs`` are both the state vector (p, v) [2]. ``reset``
    draws p, v ~ U[-0.5, 0.5]; ``step`` applies :func:`pointmass_dynamics`, returns reward
    :func:`pointmass_reward` and ``done`` (float32) from :func:`pointmass_done`, and never
    resets by itself (like brax envs, it keeps stepping after ``done``).
    """

    def reset(self, rng: jax.Array) -> brax_base.State:
        x = jax.random.uniform(rng, (2,), minval=-0.5, maxval=0.5, dtype=jnp.float32)
        zero = jnp.zeros((), jnp.float32)
        return brax_base.State(pipeline_state=x, obs=x, reward=zero, done=zero)

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        x = state.pipeline_state
        x_next = pointmass_dynamics(x, action).astype(jnp.float32)
        reward = pointmass_reward(x, action, x_next).astype(jnp.float32)
        done = pointmass_done(x_next).astype(jnp.float32)
        return state.replace(pipeline_state=x_next, obs=x_next, reward=reward, done=done)

    @property
    def observation_size(self) -> int:
        return 2

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "jax"

    @property
    def dt(self) -> float:
        return POINTMASS_DT


# --------------------------------------------------------------------------------------------
# Registry.

TASKS: dict[str, Task] = {
    "hopper": _loco_task("hopper", hopper_reward, hopper_done),
    "walker2d": _loco_task("walker2d", walker2d_reward, walker2d_done),
    "halfcheetah": _loco_task("halfcheetah", halfcheetah_reward, halfcheetah_done),
    "ant": _loco_task("ant", ant_reward, ant_done),
    "pointmass": Task(
        name="pointmass",
        obs_size=2,
        action_size=1,
        episode_length=50,
        make_env=PointMass,
        reward_fn=pointmass_reward,
        done_fn=pointmass_done,
        dt=POINTMASS_DT,
    ),
}


BUILT_IN = tuple(TASKS)


def _no_env(name: str) -> Callable[..., brax_base.Env]:
    def make_env(**_):
        raise NotImplementedError(f"task {name!r} was registered from Python without make_env, "
                                  f"so it has no real env: learn and evaluate from its data")
    return make_env


def register(name: str, *, reward_fn: RewardFn, done_fn: DoneFn, obs_size: int,
             action_size: int, episode_length: int, dt: float = 1.0,
             position_dims: tuple[int, ...] = (), make_env: Callable | None = None,
             replace: bool = False) -> Task:
    """Register your own system's task, so its Datasets (``meta.task = name``) train, evaluate
    and fine-tune with its known reward and termination rules.

    reward_fn(obs [..., o], action [..., a], next_obs [..., o]) -> [...] and
    done_fn(next_obs [..., o]) -> bool [...] must be JAX-traceable (they run inside the
    compiled rollouts); both are checked on zeros here. make_env: a brax Env factory, if the
    real system can be simulated (None: learning and evaluation from data only). Built-in
    tasks cannot be replaced; a task you registered can with ``replace=True``. Registration
    lasts for the Python process (the ``rl2s`` command knows only the built-in tasks).
    -> the Task."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty str, got {name!r}")
    if name in BUILT_IN:
        raise ValueError(f"name: {name!r} is a built-in task and cannot be replaced")
    if name in TASKS and not replace:
        raise ValueError(f"name: task {name!r} is registered already; pass replace=True")
    for field, v in (("obs_size", obs_size), ("action_size", action_size),
                     ("episode_length", episode_length)):
        if not isinstance(v, int | np.integer) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{field}: expected an int >= 1, got {v!r}")
    if not (isinstance(dt, int | float) and dt > 0):
        raise ValueError(f"dt: expected a positive float, got {dt!r}")
    if any(not 0 <= d < obs_size for d in position_dims):
        raise ValueError(f"position_dims: expected obs dims in [0, {obs_size}), got "
                         f"{position_dims!r}")
    for field, fn in (("reward_fn", reward_fn), ("done_fn", done_fn)):
        if not callable(fn):
            raise ValueError(f"{field}: expected a function, got {type(fn).__name__}")
    obs = jax.ShapeDtypeStruct((4, obs_size), jnp.float32)
    act = jax.ShapeDtypeStruct((4, action_size), jnp.float32)
    for field, fn, args in (("reward_fn", reward_fn, (obs, act, obs)), ("done_fn", done_fn,
                                                                       (obs,))):
        try:
            out = jax.eval_shape(fn, *args)
        except Exception as err:  # the user's function: any failure is reported as theirs
            raise ValueError(f"{field}: calling it on a batch of 4 zero rows (obs "
                             f"[4, {obs_size}], action [4, {action_size}]) failed: "
                             f"{type(err).__name__}: {err}") from err
        if getattr(out, "shape", None) != (4,):
            raise ValueError(f"{field}: on a batch of 4 rows expected shape (4,), got "
                             f"{getattr(out, 'shape', type(out).__name__)}")
    task = Task(name=name, obs_size=int(obs_size), action_size=int(action_size),
                episode_length=int(episode_length), make_env=make_env or _no_env(name),
                reward_fn=reward_fn, done_fn=done_fn, dt=float(dt),
                position_dims=tuple(int(d) for d in position_dims))
    TASKS[name] = task
    return task


def task_names() -> tuple[str, ...]:
    """Names of the registered tasks."""
    return tuple(TASKS)


def get_task(name: str) -> Task:
    """The task called ``name``; ValueError listing the known names if there is none."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; known tasks: {', '.join(task_names())}") from None


def data_task(name: str | None, no_task: bool = False, where: str = "data",
              remedy: str = "or pass --no-task to learn both from the data") -> str | None:
    """The task a Dataset's ``meta.task`` names, checked: a registered name, or None (data
    of no registered task: the reward and termination are learned from it). A name that is
    not registered is refused (a misspelt task must not silently turn into learned rules),
    naming the field, the name, the registered ones and the nearest, unless ``no_task`` (the
    command's --no-task) says to learn the reward and termination from the data; ``remedy``
    ends the error."""
    if name is None or name in TASKS or no_task:
        return name
    near = difflib.get_close_matches(str(name), task_names(), n=1, cutoff=0.6)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    raise ValueError(f"{where}: meta.task {name!r} is not a registered task{hint}; registered: "
                     f"{', '.join(task_names())}. Register it (rl2s_jax.register) for its "
                     f"reward and termination rules, {remedy}")
