"""Planted effects for brax envs (MJX Hopper and the other registered tasks), as env wrappers.

Plain ``brax.envs.base.Wrapper`` subclasses (not brax's training wrappers, which
:func:`rl2s_jax.collect.check_env` refuses): they leave the observation as it is, keep their
own state in ``state.info``, and are pure functions of (state, action), so they run under
``jit``/``vmap`` and inside :func:`rl2s_jax.collect.collect`. Wrappers compose (each keeps a
distinct ``info`` key).

* :class:`DelayedActions`: listed actuators apply the action of ``lag`` steps ago.
* :class:`EpisodeMass`: body masses (and inertias) scaled by a factor drawn per episode.
* :class:`ProcessNoise`: signal-dependent Gaussian noise on chosen joint velocities.
* :class:`ActionGain`: every action scaled by a fixed gain (weaker actuators).

Two effects live in the data rather than in one env: "unobserved" (joint velocities removed
from the observation, :func:`hide_obs_dims`) and "drift" (the actuator gain falls over the
recording order: the data is recorded in chunks, each with a lower :class:`ActionGain`).
:func:`collect_planted` records any effect; :func:`make_planted_env` builds a registered task
with one env effect; :func:`planted_truth` gives the ground truth in the form of
:func:`rl2s_jax.diagnose.planted.make_planted`.
"""
from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, PipelineEnv, State, Wrapper

from rl2s_jax.data.collect import EPISODE_LENGTH, collect, default_envs_per_policy
from rl2s_jax.data.dataset import Dataset, concat_datasets
from rl2s_jax.envs.tasks import _LOCO, PointMass, get_task

__all__ = [
    "EFFECTS",
    "ActionGain",
    "DelayedActions",
    "EpisodeMass",
    "ProcessNoise",
    "collect_planted",
    "hide_obs_dims",
    "make_planted_env",
    "planted_truth",
    "velocity_obs_dims",
]

#: Effect name -> its keyword arguments and their defaults (``make_planted_env``).
EFFECTS: dict[str, dict[str, Any]] = {
    "clean": {},
    "delay": {"lag": 2, "actuators": (0,)},
    "episode_param": {"scale_range": (0.5, 2.0), "bodies": None},
    "noise": {"dims": (3,), "scale": 0.3, "base": 0.1},
    "unobserved": {"dims": (3, 4, 5)},
    "drift": {"gain_start": 1.0, "gain_end": 0.6, "chunks": 4},
}
#: Effects made at recording time (:func:`collect_planted`), not by one wrapped env.
DATA_EFFECTS = ("unobserved", "drift")


def _index_tuple(name: str, value: Any, size: int, low: int = 0) -> tuple[int, ...]:
    """Distinct ints in [low, size) as a tuple; ValueError naming ``name`` otherwise."""
    expected = f"a non-empty set of distinct ints in [{low}, {size})"
    try:
        arr = np.atleast_1d(np.asarray(value))
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected {expected}, got {value!r}") from None
    if (arr.ndim != 1 or arr.size == 0 or not np.issubdtype(arr.dtype, np.integer)
            or len(set(arr.tolist())) != arr.size or arr.min() < low or arr.max() >= size):
        raise ValueError(f"{name}: expected {expected}, got {value!r}")
    return tuple(int(i) for i in arr)


def _check_lag(lag: Any) -> int:
    if not isinstance(lag, (int, np.integer)) or isinstance(lag, bool) or lag < 1:
        raise ValueError(f"lag: expected an int >= 1 (env steps), got {lag!r}")
    return int(lag)


def _check_range(scale_range: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in scale_range)
    except (TypeError, ValueError):
        raise ValueError(f"scale_range: expected (low, high) with 0 < low < high, got "
                         f"{scale_range!r}") from None
    if not 0 < lo < hi < math.inf:
        raise ValueError(f"scale_range: expected (low, high) with 0 < low < high, got "
                         f"{scale_range!r}")
    return lo, hi


def _check_nonneg(name: str, value: Any, positive: bool) -> float:
    ok = isinstance(value, (int, float, np.floating)) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or value < 0 or (positive and value == 0):
        raise ValueError(f"{name}: expected a {'positive' if positive else 'non-negative'} "
                         f"number, got {value!r}")
    return float(value)


# --------------------------------------------------------------------------- delay


class DelayedActions(Wrapper):
    """Actuators ``actuators`` apply the action of ``lag`` env steps ago (zeros before the
    episode start); the others apply the current action.

    ``state.info["delay_queue"]`` [lag, action_size]: actions a_{t-lag} ... a_{t-1}.
    """

    def __init__(self, env: Env, lag: int = 2, actuators: Sequence[int] = (0,)):
        super().__init__(env)
        self.lag = _check_lag(lag)
        self.actuators = _index_tuple("actuators", actuators, int(env.action_size))
        self._delayed = np.isin(np.arange(env.action_size), self.actuators)

    def reset(self, rng: jax.Array) -> State:
        state = self.env.reset(rng)
        queue = jnp.zeros((self.lag, self.env.action_size), jnp.float32)
        return state.replace(info={**state.info, "delay_queue": queue})

    def step(self, state: State, action: jax.Array) -> State:
        queue = state.info["delay_queue"]
        applied = jnp.where(self._delayed, queue[0], action)
        nxt = self.env.step(state, applied)
        queue = jnp.concatenate([queue[1:], action[None].astype(queue.dtype)], axis=0)
        return nxt.replace(info={**nxt.info, "delay_queue": queue})


# --------------------------------------------------------------------------- mass


def _with_sys(env: Env, sys: Any) -> Env:
    """A shallow copy of the wrapper chain ``env`` whose innermost env steps with ``sys``.

    Built at trace time, so ``sys`` may hold traced arrays (one per vmapped env); the original
    env objects are not touched.
    """
    clone = copy.copy(env)
    if isinstance(env, Wrapper):
        clone.env = _with_sys(env.env, sys)
    else:
        clone.sys = sys
    return clone


class EpisodeMass(Wrapper):
    """Body masses scaled per episode by a hidden factor, log-uniform in ``scale_range``.

    ``bodies``: MuJoCo body ids to scale (None: every body but the world, 0). The inertia
    tensors are scaled by the same factor (a density change; a heavier body with unchanged
    inertia would be unphysical). ``state.info["mass_scale"]`` holds the factor.

    MJX recomputes everything mass-dependent in the dynamics (subtree com, composite inertia,
    mass matrix, gravity and Coriolis terms) from ``body_mass``/``body_inertia`` each step, so
    replacing them in ``sys`` is enough. Only the constraint regulariser weights
    (``body_invweight0``/``dof_invweight0``, computed once at model load) stay at the nominal
    masses: contacts keep their nominal softness. The reset state is drawn with the nominal
    system (its observation does not depend on masses).
    """

    def __init__(self, env: Env, scale_range: tuple[float, float] = (0.5, 2.0),
                 bodies: Sequence[int] | None = None):
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, PipelineEnv):
            raise ValueError(f"env: EpisodeMass needs a brax PipelineEnv (it scales "
                             f"sys.body_mass), got {type(base).__name__}")
        self.scale_range = _check_range(scale_range)
        nbody = int(base.sys.nbody)
        self.bodies = (tuple(range(1, nbody)) if bodies is None
                       else _index_tuple("bodies", bodies, nbody, low=1))

    def reset(self, rng: jax.Array) -> State:
        rng_env, rng_scale = jax.random.split(rng)
        lo, hi = self.scale_range
        scale = jnp.exp(jax.random.uniform(rng_scale, (), jnp.float32, math.log(lo),
                                           math.log(hi)))
        state = self.env.reset(rng_env)
        return state.replace(info={**state.info, "mass_scale": scale})

    def step(self, state: State, action: jax.Array) -> State:
        return self.scaled_env(state.info["mass_scale"]).step(state, action)

    def scaled_env(self, scale: jax.Array) -> Env:
        """The inner env with the listed bodies' mass and inertia multiplied by ``scale``."""
        sys = self.unwrapped.sys
        idx = np.asarray(self.bodies)
        sys = sys.replace(body_mass=sys.body_mass.at[idx].multiply(scale),
                          body_inertia=sys.body_inertia.at[idx].multiply(scale))
        return _with_sys(self.env, sys)


# --------------------------------------------------------------------------- noise


# brax env class -> how many leading q entries exclude_current_positions_from_observation drops.
_EXCLUDED_POSITIONS = {"Hopper": 1, "Walker2d": 1, "Halfcheetah": 1, "Ant": 2}


def velocity_obs_dims(env: Env) -> tuple[int, ...]:
    """Obs index of each joint velocity (qvel entry) of ``env``'s innermost env.

    brax's hopper, walker2d, halfcheetah and ant observations are q (less the excluded
    current positions) then qvel (brax's hopper and walker2d clip it to +-10; the tasks'
    subclasses do not); the PointMass state
    is (p, v), obs = state. Other envs: ValueError.
    """
    base = env.unwrapped
    if isinstance(base, PointMass):
        return (1,)
    excluded = next((_EXCLUDED_POSITIONS[c.__name__] for c in type(base).__mro__
                     if c.__name__ in _EXCLUDED_POSITIONS), None)
    if isinstance(base, PipelineEnv) and excluded is not None:
        n_q_obs = int(base.sys.q_size())
        if base._exclude_current_positions_from_observation:
            n_q_obs -= excluded
        return tuple(n_q_obs + j for j in range(int(base.sys.qd_size())))
    raise ValueError(f"env: ProcessNoise supports PointMass and brax's Hopper, Walker2d, "
                     f"Halfcheetah and Ant, got {type(base).__name__}")


def _actuator_of_dof(base: Env, nv: int) -> np.ndarray:
    """[nv] int: the actuator driving each dof (a hinge/slide joint), -1 for none."""
    if isinstance(base, PointMass):
        return np.zeros(1, int)
    sys = base.sys
    out = np.full(nv, -1)
    joints = np.asarray(sys.actuator_trnid)[:, 0]
    for act, joint in enumerate(joints):
        out[int(np.asarray(sys.jnt_dofadr)[joint])] = act
    return out


class ProcessNoise(Wrapper):
    """After each step, joint velocities ``dims`` (qvel indices) get Gaussian noise of std
    ``scale * (base + |a_k|)``: a_k the actuator driving that joint, or the mean |a| over
    actuators for an unactuated dof. Motor noise that grows with the command, so a model
    with a constant per-dim noise level cannot absorb it.

    The noise is an impulse at the end of the step: the observation (recomputed from the
    perturbed state) shows it, and the next step starts from it; reward and done are those of
    the unperturbed step. ``obs_dims``: the obs indices of ``dims``. ``state.info
    ["noise_key"]`` carries the key.
    """

    def __init__(self, env: Env, dims: Sequence[int] = (3,), scale: float = 0.3,
                 base: float = 0.1):
        super().__init__(env)
        vel_obs = velocity_obs_dims(env)
        self.dims = _index_tuple("dims", dims, len(vel_obs))
        self.scale = _check_nonneg("scale", scale, positive=True)
        self.base = _check_nonneg("base", base, positive=False)
        self.obs_dims = tuple(vel_obs[d] for d in self.dims)
        self._actuator = _actuator_of_dof(env.unwrapped, len(vel_obs))[list(self.dims)]

    def reset(self, rng: jax.Array) -> State:
        rng_env, rng_noise = jax.random.split(rng)
        state = self.env.reset(rng_env)
        return state.replace(info={**state.info, "noise_key": rng_noise})

    def step(self, state: State, action: jax.Array) -> State:
        key, sub = jax.random.split(state.info["noise_key"])
        nxt = self.env.step(state, action)
        a = jnp.abs(action)
        magnitude = jnp.where(self._actuator >= 0, a[np.maximum(self._actuator, 0)], a.mean())
        noise = self.scale * (self.base + magnitude) * jax.random.normal(sub, magnitude.shape)
        nxt = self._perturb(nxt, noise.astype(jnp.float32))
        return nxt.replace(info={**nxt.info, "noise_key": key})

    def _perturb(self, state: State, noise: jax.Array) -> State:
        """Add noise [k] to qvel entries ``dims`` and recompute the observation."""
        base = self.unwrapped
        dims = np.asarray(self.dims)
        ps = state.pipeline_state
        if isinstance(base, PointMass):
            ps = ps.at[1 + dims].add(noise)
            return state.replace(pipeline_state=ps, obs=ps)
        # brax's MJX state holds qvel twice: mjx.Data.qvel (what mjx.step reads) and qd.
        ps = ps.replace(qvel=ps.qvel.at[dims].add(noise), qd=ps.qd.at[dims].add(noise))
        return state.replace(pipeline_state=ps, obs=base._get_obs(ps))


# --------------------------------------------------------------------------- drift


class ActionGain(Wrapper):
    """Every action multiplied by ``gain`` before the inner env applies it (a weaker or
    stronger actuator; brax/MuJoCo clip the result to the control range as usual)."""

    def __init__(self, env: Env, gain: float = 1.0):
        super().__init__(env)
        self.gain = _check_nonneg("gain", gain, positive=True)

    def step(self, state: State, action: jax.Array) -> State:
        return self.env.step(state, action * jnp.asarray(self.gain, action.dtype))


def _drift_gains(kw: dict[str, Any]) -> np.ndarray:
    """[chunks] the actuator gain of each recording chunk, linear from start to end."""
    start = _check_nonneg("gain_start", kw["gain_start"], positive=True)
    end = _check_nonneg("gain_end", kw["gain_end"], positive=True)
    chunks = kw["chunks"]
    if not isinstance(chunks, (int, np.integer)) or isinstance(chunks, bool) or chunks < 2:
        raise ValueError(f"chunks: expected an int >= 2 (recording chunks), got {chunks!r}")
    if start == end:
        raise ValueError(f"gain_end: expected a gain other than gain_start ({start}), got {end}")
    return np.linspace(start, end, int(chunks))


# --------------------------------------------------------------------------- unobserved


def hide_obs_dims(ds: Any, dims: Sequence[int]) -> Any:
    """A copy of Dataset ``ds`` without obs columns ``dims`` (in obs and next_obs).

    The result no longer matches its registered task's observation, so ``meta["task"]`` is
    cleared (the task is kept as ``meta["source"]["task"]``) and the hidden columns are
    recorded as ``meta["source"]["hidden_obs_dims"]``.
    """

    hidden = _index_tuple("dims", dims, ds.obs_size)
    if len(hidden) == ds.obs_size:
        raise ValueError(f"dims: expected to leave at least one obs dim, got all of {hidden}")
    keep = np.setdiff1d(np.arange(ds.obs_size), hidden)
    arrays = ds.arrays()
    arrays["obs"], arrays["next_obs"] = arrays["obs"][:, keep], arrays["next_obs"][:, keep]
    source = {**(ds.meta.get("source") or {}), "task": ds.meta.get("task"),
              "hidden_obs_dims": sorted(hidden)}
    meta = {**ds.meta, "task": None, "obs_size": int(keep.size), "source": source}
    return Dataset.from_arrays(arrays, meta)


def _hidden_truth(task_name: str, qvel: Sequence[int]) -> dict[str, Any]:
    """Truth of the "unobserved" effect: the obs columns removed and, for tasks whose joints
    all have one dof (so qvel j is the rate of qpos j), the obs dims of those joints'
    positions, which need the lost velocity to be predicted."""
    vel_obs = _registered_velocity_obs_dims(task_name)
    qvel = sorted(_index_tuple("dims", qvel, len(vel_obs)))
    truth = {"effect": "unobserved_state", "hidden": [f"qvel[{j}]" for j in qvel],
             "removed_obs_dims": [vel_obs[j] for j in qvel]}
    if task_name in _ONE_DOF_TASKS:  # the registered tasks keep every q: qpos j is obs j
        truth["dims"] = [j for j in qvel if j < vel_obs[0]]
    return truth


# Registered tasks whose joints all have one dof (qvel j is the rate of qpos j). Their
# observations keep every q (tasks.make_env: exclude_current_positions_from_observation=False).
_ONE_DOF_TASKS = ("hopper", "walker2d", "halfcheetah", "pointmass")


# --------------------------------------------------------------------------- by name


def _resolve(effect: Any, kwargs: dict[str, Any]) -> dict[str, Any]:
    if effect not in EFFECTS:
        raise ValueError(f"effect: expected one of {', '.join(map(repr, EFFECTS))} for brax "
                         f"envs, got {effect!r}")
    unknown = sorted(set(kwargs) - set(EFFECTS[effect]))
    if unknown:
        raise ValueError(f"effect {effect!r}: unknown argument(s) {', '.join(unknown)}; "
                         f"accepted: {', '.join(EFFECTS[effect]) or 'none'}")
    return {**EFFECTS[effect], **kwargs}


def make_planted_env(task_name: str, effect: str = "clean", *,
                     env_kwargs: dict[str, Any] | None = None, **effect_kwargs) -> Env:
    """The registered task's env (``get_task(task_name).make_env(**env_kwargs)``) with one
    planted effect: "clean" (unwrapped), "delay" (:class:`DelayedActions`: lag, actuators),
    "episode_param" (:class:`EpisodeMass`: scale_range, bodies) or "noise"
    (:class:`ProcessNoise`: dims = qvel indices, scale, base). Defaults in :data:`EFFECTS`.
    Arguments are checked before the env is built where they can be.
    """
    kw = _resolve(effect, effect_kwargs)
    if effect in DATA_EFFECTS:
        raise ValueError(f"effect: {effect!r} is made while recording, not by one env: use "
                         "collect_planted")
    task = get_task(task_name)
    if effect == "delay":
        _check_lag(kw["lag"])
        _index_tuple("actuators", kw["actuators"], task.action_size)
    elif effect == "episode_param":
        _check_range(kw["scale_range"])
    elif effect == "noise":
        _index_tuple("dims", kw["dims"], len(_registered_velocity_obs_dims(task_name)))
        _check_nonneg("scale", kw["scale"], positive=True)
        _check_nonneg("base", kw["base"], positive=False)
    env = task.make_env(**(env_kwargs or {}))
    wrapper = {"clean": None, "delay": DelayedActions, "episode_param": EpisodeMass,
               "noise": ProcessNoise}[effect]
    return env if wrapper is None else wrapper(env, **kw)


def planted_truth(effect: str = "clean", *, task_name: str = "hopper",
                  **effect_kwargs) -> dict[str, Any]:
    """Ground truth of ``make_planted_env(task_name, effect, **effect_kwargs)`` (registered
    task with default env arguments), as in ``make_planted``'s ``meta.source.planted``:

      {"effect": "none"}
      {"effect": "actuation_delay", "lag": 2, "actuators": [0]}
      {"effect": "hidden_episode_parameter", "parameter": "body_mass", "also_scaled":
       "body_inertia", "bodies": "all" | [ids], "distribution": "log-uniform", "range": [lo, hi]}
      {"effect": "stochastic_noise", "dims": [obs indices], "qvel": [qvel indices], "std":
       ..., "scale": s, "base": b}
      {"effect": "unobserved_state", "hidden": ["qvel[j]", ...], "removed_obs_dims": [...],
       "dims": [obs indices of those joints' positions] (tasks of one-dof joints)}
      {"effect": "time_drift", "over": "episode_order", "parameter": "actuator_gain",
       "actuators": "all", "start": g0, "end": g1, "chunks": K, "gains": [...]}
    """
    kw = _resolve(effect, effect_kwargs)
    task = get_task(task_name)
    if effect == "delay":
        return {"effect": "actuation_delay", "lag": _check_lag(kw["lag"]),
                "actuators": sorted(_index_tuple("actuators", kw["actuators"],
                                                 task.action_size))}
    if effect == "episode_param":
        lo, hi = _check_range(kw["scale_range"])
        bodies = "all" if kw["bodies"] is None else sorted(int(b) for b in kw["bodies"])
        return {"effect": "hidden_episode_parameter", "parameter": "body_mass",
                "also_scaled": "body_inertia", "bodies": bodies,
                "distribution": "log-uniform", "range": [lo, hi]}
    if effect == "noise":
        vel_obs = _registered_velocity_obs_dims(task_name)
        dims = sorted(_index_tuple("dims", kw["dims"], len(vel_obs)))
        return {"effect": "stochastic_noise", "dims": [vel_obs[d] for d in dims],
                "qvel": dims, "std": "scale * (base + |a_k|), a_k the joint's actuator",
                "scale": _check_nonneg("scale", kw["scale"], positive=True),
                "base": _check_nonneg("base", kw["base"], positive=False)}
    if effect == "unobserved":
        return _hidden_truth(task_name, kw["dims"])
    if effect == "drift":
        gains = _drift_gains(kw)
        return {"effect": "time_drift", "over": "episode_order", "parameter": "actuator_gain",
                "actuators": "all", "start": float(gains[0]), "end": float(gains[-1]),
                "chunks": int(gains.size), "gains": [round(float(g), 6) for g in gains]}
    return {"effect": "none"}


def collect_planted(task_name: str, effect: str, params: Any, *, key: jax.Array,
                    transitions_per_policy: int, env_kwargs: dict[str, Any] | None = None,
                    effect_kwargs: dict[str, Any] | None = None, **collect_kwargs) -> Any:
    """Record a registered task with one planted effect from the stacked policies ``params``.

    Env effects collect from :func:`make_planted_env`. "unobserved" collects the clean task
    and removes the listed joint velocities (``dims``, qvel indices) from the observation
    (:func:`hide_obs_dims`). "drift" records ``chunks`` chunks one after another, chunk k
    with every action scaled by the k-th gain (linear from ``gain_start`` to ``gain_end``),
    each chunk with the envs per policy of the whole recording (so as many sequential steps
    as a plain recording, and episodes cut at the chunk's end), and concatenates them in
    recording order (:func:`rl2s_jax.data.concat_datasets`; each
    policy's true value is then the mean over the chunks). ``collect_kwargs`` go to
    :func:`rl2s_jax.collect.collect` (``task`` is set here); ``meta["source"]["planted"]``
    holds :func:`planted_truth`. -> Dataset
    """

    effect_kwargs = dict(effect_kwargs or {})
    truth = planted_truth(effect, task_name=task_name, **effect_kwargs)  # checks arguments
    source = {**(collect_kwargs.pop("source", None) or {}), "planted": truth}
    n = int(transitions_per_policy)
    if effect == "drift":
        gains = _drift_gains(_resolve(effect, effect_kwargs))
        keys = jax.random.split(key, gains.size)
        env = get_task(task_name).make_env(**(env_kwargs or {}))
        per_chunk = -(-n // gains.size)
        # As many envs per policy as the whole recording would get (collect's default): with
        # the chunk's own default, 4 chunks took 4x the sequential steps of a plain recording
        # (1 env per policy at 5000 transitions), 523 s on the H100 against ~100 s.
        envs = collect_kwargs.pop("envs_per_policy", None) or default_envs_per_policy(
            n, collect_kwargs.get("episode_length", EPISODE_LENGTH))
        parts = [collect(ActionGain(env, float(g)), params, key=k,
                         transitions_per_policy=per_chunk,
                         envs_per_policy=min(int(envs), per_chunk), task=task_name,
                         source={**source, "chunk": i, "actuator_gain": float(g)},
                         **collect_kwargs)
                 for i, (g, k) in enumerate(zip(gains, keys, strict=True))]
        ds = concat_datasets(parts)
        ds.meta["source"] = {**source, "chunks": int(gains.size)}
        return ds
    env_effect = "clean" if effect == "unobserved" else effect
    env = make_planted_env(task_name, env_effect, env_kwargs=env_kwargs,
                           **({} if effect == "unobserved" else effect_kwargs))
    ds = collect(env, params, key=key, transitions_per_policy=n, task=task_name,
                 source=source, **collect_kwargs)
    if effect == "unobserved":
        ds = hide_obs_dims(ds, truth["removed_obs_dims"])
    return ds


def _registered_velocity_obs_dims(task_name: str) -> tuple[int, ...]:
    """Obs indices of qvel for a registered task's default env, without building it: the
    MuJoCo tasks keep every q in the observation, then qvel (tasks._LOCO.vx_idx = len(q))."""

    task = get_task(task_name)
    if task_name in _LOCO:
        offset = _LOCO[task_name].vx_idx
        return tuple(range(offset, task.obs_size))
    if task_name == "pointmass":
        return (1,)
    raise ValueError(f"task_name: no known velocity layout for {task_name!r}")
