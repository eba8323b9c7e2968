"""Measured data the project did not make: zoo policies in Gymnasium's MuJoCo v5 envs.

:func:`collect_gymnasium` runs a zoo's policies (their NumPy forward pass,
``measured.numpy_policy_action``) in ``gymnasium.make("Hopper-v5" | "Walker2d-v5" |
"HalfCheetah-v5" | "Ant-v5")`` -- C MuJoCo, float64, Gymnasium's own XML, solver and reset --
and records a Dataset in the MJX task's observation convention (``envs/tasks.py``):

* The state is read from ``env.unwrapped.data`` (qpos, qvel), never from Gymnasium's
  observation. v5's qpos is mapped to the MJX model's by ``qpos - (qpos0_v5 - qpos0_mjx)``: the
  two models agree on every body's pose under this map (Hopper's and Walker2d's ``rootz`` has
  ``ref=1.25`` in v5, none in brax; :func:`obs_map`, tested on body positions).
* obs = qpos ++ qvel (x kept, qvel unclipped; Ant: q(15) ++ qd(14), no contact forces), with
  Hopper's and Walker2d's ``obs[1]`` the lagged torso height ``z - h * vz`` as
  ``mjx_model.PhysicsModel.state_to_obs`` writes it, so ``obs_to_state`` inverts it exactly.
  (brax's ``x.pos`` is that height one substep back under semi-implicit Euler; v5 integrates
  Hopper, Walker2d and Ant with RK4, where no stored quantity is "one substep back". The first
  observation of an episode is lagged too, where brax's is not: at most ``h |v0|`` = 1e-5.)
* reward = the MJX task's ``reward_fn``, done = its ``done_fn`` (on the float32 observations
  the Dataset holds), so values compare with the MJX task's; episodes end there or at
  ``episode_length`` (at most the task's). Gymnasium's own reward over the same steps is kept
  per policy in ``meta["source"]``: ``gymnasium_value`` (its mean return over the value
  episodes) and ``gymnasium_reward_gap`` (mean of v5 reward - task reward over the data rows).
  v5's own termination tests the current height (brax: lagged) and is not used;
  ``gymnasium_termination_differs`` counts value episodes where it fired at another step.
* True values: ``value_episodes`` fresh episodes per policy (``gamma`` discount), as
  ``data.collect.measure_values`` defines them.

:func:`model_differences` lists, per task, what differs between v5's compiled model and the
MJX task's (``mjx_model.load_mj``): options, frame skip, reset noise, and per named element
masses, inertias, dof damping / armature / frictionloss, joint ranges and rest positions,
geom friction and contact settings, actuator gear and ranges. ``print_differences`` prints it.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from rl2s_jax.data.dataset import Dataset
from rl2s_jax.physics.measured import numpy_policy_action
from rl2s_jax.physics.mjx_model import MODEL_OPTIONS, PhysicsModel, load_mj, physics_model

__all__ = ["V5_ENVS", "ObsMap", "collect_gymnasium", "make_v5", "model_differences",
           "obs_map", "print_differences"]

V5_ENVS = {"hopper": "Hopper-v5", "walker2d": "Walker2d-v5", "halfcheetah": "HalfCheetah-v5",
           "ant": "Ant-v5"}


def make_v5(task: str, **env_kwargs):
    """``gymnasium.make`` of the v5 env of an MJX task (``env_kwargs`` go to its constructor,
    e.g. ``xml_file``)."""
    import gymnasium  # local: keeps `import rl2s_jax.physics` free of Gymnasium

    if task not in V5_ENVS:
        raise ValueError(f"task: expected one of {sorted(V5_ENVS)} (an MJX task with a "
                         f"Gymnasium v5 twin), got {task!r}")
    return gymnasium.make(V5_ENVS[task], **env_kwargs)


@dataclasses.dataclass(frozen=True)
class ObsMap:
    """v5 (qpos [nq], qvel [nv]) -> the MJX task's observation [nq + nv] (module docstring).

    offset: v5 qpos0 - the MJX model's qpos0 [nq]; lag: ``PhysicsModel.lag``; substep: h."""

    offset: np.ndarray
    lag: tuple
    substep: float

    def mjx_qpos(self, qpos: np.ndarray) -> np.ndarray:
        """v5 qpos [nq] -> the MJX model's qpos of the same pose [nq]."""
        return np.asarray(qpos, np.float64) - self.offset

    def __call__(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        q, v = self.mjx_qpos(qpos), np.asarray(qvel, np.float64)
        obs = np.concatenate([q, v])
        for o, iq, iv, z0 in self.lag:
            obs[o] = z0 + q[iq] - self.substep * v[iv]
        return obs


def obs_map(pm: PhysicsModel, v5_model) -> ObsMap:
    """The observation map from a v5 env's model (``env.unwrapped.model``) to ``pm``'s
    convention; a clear error when the two models' coordinates do not match in size."""
    if (v5_model.nq, v5_model.nv, v5_model.nu) != (pm.nq, pm.nv, pm.action_size):
        raise ValueError(f"v5 model: expected nq, nv, nu = {pm.nq}, {pm.nv}, "
                         f"{pm.action_size} as the MJX task {pm.task!r}, got {v5_model.nq}, "
                         f"{v5_model.nv}, {v5_model.nu}")
    return ObsMap(offset=np.asarray(v5_model.qpos0, np.float64) - np.asarray(pm.mj.qpos0),
                  lag=pm.lag, substep=pm.substep)


def _episode(env, omap: ObsMap, params, rng, length: int, done_fn) -> dict:
    """One v5 episode of at most ``length`` steps, ended by ``done_fn`` -> dict of lists:
    obs, action, next_obs (float64), done, gym_reward, gym_terminated."""
    env.reset(seed=int(rng.integers(2 ** 31)))
    data = env.unwrapped.data
    obs = omap(data.qpos, data.qvel)
    rec = {k: [] for k in ("obs", "action", "next_obs", "done", "gym_reward",
                           "gym_terminated")}
    for _ in range(length):
        action = numpy_policy_action(params, obs.astype(np.float32), rng).astype(np.float32)
        _, gym_reward, terminated, _, _ = env.step(action)
        nxt = omap(data.qpos, data.qvel)
        done = bool(done_fn(nxt.astype(np.float32)))
        for k, v in (("obs", obs), ("action", action), ("next_obs", nxt), ("done", done),
                     ("gym_reward", float(gym_reward)), ("gym_terminated", bool(terminated))):
            rec[k].append(v)
        obs = nxt
        if done:
            break
    return rec


def _task_rewards(task, rec: dict) -> np.ndarray:
    """The MJX task's reward [n] of an episode's rows, on the float32 observations."""
    f32 = lambda k: np.asarray(rec[k], np.float32)
    return np.asarray(task.reward_fn(f32("obs"), f32("action"), f32("next_obs")), np.float64)


def _values(env, omap, task, done_fn, params_of, n_pol, n_episodes, length, gamma, rng):
    """True values [P] (``measure_values``' fields) and v5's own returns over the same steps."""
    ret, dret, gym_ret = (np.zeros((n_pol, n_episodes)) for _ in range(3))
    differs = 0
    for p in range(n_pol):
        for e in range(n_episodes):
            rec = _episode(env, omap, params_of(p), rng, length, done_fn)
            r = _task_rewards(task, rec)
            ret[p, e], dret[p, e] = r.sum(), np.sum(r * gamma ** np.arange(len(r)))
            gym_ret[p, e] = np.sum(rec["gym_reward"])
            first = np.flatnonzero(rec["gym_terminated"])
            gym_end = int(first[0]) if first.size else None
            differs += gym_end != (len(r) - 1 if rec["done"][-1] else None)
    se = (lambda x: x.std(axis=1, ddof=1) / math.sqrt(n_episodes)) if n_episodes > 1 else (
        lambda x: np.zeros(n_pol))
    values = {"value": ret.mean(1), "value_se": se(ret), "value_discounted": dret.mean(1),
              "value_discounted_se": se(dret)}
    return ({k: v.astype(np.float32) for k, v in values.items()},
            {"gymnasium_value": gym_ret.mean(1).tolist(),
             "gymnasium_value_se": se(gym_ret).tolist(),
             "gymnasium_termination_differs": int(differs)})


def _checked_sizes(task, task_name: str, transitions_per_policy, episode_length,
                   value_episodes, gamma) -> int:
    """collect_gymnasium's arguments checked, each bad one named -> the episode length."""
    if task is None:
        raise ValueError(f"task_name: expected one of {sorted(V5_ENVS)}, got {task_name!r}")
    episode_length = task.episode_length if episode_length is None else episode_length
    for name, v, lo, hi in (("transitions_per_policy", transitions_per_policy, 1, None),
                            ("episode_length", episode_length, 1, task.episode_length),
                            ("value_episodes", value_episodes, 0, None)):
        if (not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < lo
                or (hi is not None and v > hi)):
            raise ValueError(f"{name}: expected an int in [{lo}, {hi or 'inf'}], got {v!r}")
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma: expected a float in (0, 1], got {gamma!r}")
    return episode_length


def collect_gymnasium(task_name: str, params, *, transitions_per_policy: int,
                      episode_length: int | None = None, value_episodes: int = 16,
                      gamma: float = 0.999, seed: int = 0,
                      policy_names: list[str] | None = None, source: dict | None = None,
                      env_kwargs: dict | None = None) -> Dataset:
    """Record ``transitions_per_policy`` transitions of each policy of a stacked zoo
    (``params`` [P, ...]) in the v5 env of MJX task ``task_name``, plus each policy's true
    value over ``value_episodes`` fresh episodes (0: none); module docstring.

    episode_length: at most the task's (default). env_kwargs: to ``gymnasium.make``.
    meta.source: engine, env_id, gymnasium / mujoco versions, seed, v5's own rewards, and
    ``source`` (e.g. ``{"zoo": task, "zoo_ids": ids}``, so the values views find the policies).
    """
    import gymnasium  # local: keeps `import rl2s_jax.physics` free of Gymnasium
    import mujoco  # local: as above

    from rl2s_jax.envs.tasks import get_task  # local: keeps `import rl2s_jax.physics` light

    task = get_task(task_name) if task_name in V5_ENVS else None
    episode_length = _checked_sizes(task, task_name, transitions_per_policy, episode_length,
                                    value_episodes, gamma)
    n_pol = jax.tree_util.tree_leaves(params)[0].shape[0]
    if policy_names is not None and len(policy_names) != n_pol:
        raise ValueError(f"policy_names: expected {n_pol} names, got {len(policy_names)}")
    pm = physics_model(task_name)
    env = make_v5(task_name, **(env_kwargs or {}))
    omap = obs_map(pm, env.unwrapped.model)
    done_fn = jax.jit(task.done_fn)
    params_of = lambda p: jax.tree_util.tree_map(lambda x: np.asarray(x[p]), params)

    rng = np.random.default_rng(seed)
    rows = {k: [] for k in ("obs", "action", "next_obs", "done", "truncated", "policy_id",
                            "episode_id", "t", "gym_reward")}
    episode = 0
    for p in range(n_pol):
        got = 0
        while got < transitions_per_policy:
            rec = _episode(env, omap, params_of(p), rng,
                           min(episode_length, transitions_per_policy - got), done_fn)
            n = len(rec["obs"])
            for k in ("obs", "action", "next_obs", "done", "gym_reward"):
                rows[k] += rec[k]
            rows["truncated"] += [False] * (n - 1) + [n == episode_length and not rec["done"][-1]]
            rows["policy_id"] += [p] * n
            rows["episode_id"] += [episode] * n
            rows["t"] += list(range(n))
            episode, got = episode + 1, got + n
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    gym_reward = arrays.pop("gym_reward")
    reward = _task_rewards(task, arrays)
    gap = [float(np.mean(gym_reward[arrays["policy_id"] == p] - reward[arrays["policy_id"] == p]))
           for p in range(n_pol)]
    values, gym_values = {}, {}
    if value_episodes:
        values, gym_values = _values(env, omap, task, done_fn, params_of, n_pol, value_episodes,
                                     episode_length, gamma, np.random.default_rng([seed, 1]))
    env.close()
    meta = {"task": task_name, "obs_size": task.obs_size, "action_size": task.action_size,
            "n_policies": int(n_pol), "gamma": float(gamma) if values else None,
            "episode_length": int(episode_length),
            "policy_names": list(policy_names or [f"policy-{i:03d}" for i in range(n_pol)]),
            "source": {"collector": "rl2s_jax.physics.gymnasium_v5", "engine": "gymnasium-v5",
                       "env_id": V5_ENVS[task_name], "env_kwargs": dict(env_kwargs or {}),
                       "gymnasium": gymnasium.__version__, "mujoco": mujoco.__version__,
                       "seed": seed, "value_episodes": int(value_episodes),
                       "gymnasium_reward_gap": gap, **gym_values, **(source or {})}}
    f32 = {k: arrays[k].astype(np.float32) for k in ("obs", "action", "next_obs")}
    return Dataset.from_arrays({**arrays, **f32, "reward": reward.astype(np.float32),
                                **{k: arrays[k].astype(np.int32)
                                   for k in ("policy_id", "episode_id", "t")},
                                **values}, meta)


# ------------------------------------------------------------------------ model differences

_BRAX_ENVS = {"hopper": ("hopper", "Hopper"), "walker2d": ("walker2d", "Walker2d"),
              "halfcheetah": ("half_cheetah", "Halfcheetah"), "ant": ("ant", "Ant")}
# (field, MuJoCo object type name, how a row is indexed): per-element quantities compared by
# the element's name.
_FIELDS = (("body_mass", "BODY", "body"), ("body_inertia", "BODY", "body"),
           ("dof_damping", "JOINT", "dof"), ("dof_armature", "JOINT", "dof"),
           ("dof_frictionloss", "JOINT", "dof"), ("jnt_range", "JOINT", "jnt"),
           ("jnt_stiffness", "JOINT", "jnt"), ("qpos0", "JOINT", "qpos"),
           ("geom_friction", "GEOM", "geom"), ("geom_contype", "GEOM", "geom"),
           ("geom_conaffinity", "GEOM", "geom"), ("geom_condim", "GEOM", "geom"),
           ("geom_margin", "GEOM", "geom"), ("geom_solref", "GEOM", "geom"),
           ("geom_solimp", "GEOM", "geom"), ("geom_size", "GEOM", "geom"),
           ("actuator_gear", "ACTUATOR", "actuator"),
           ("actuator_ctrlrange", "ACTUATOR", "actuator"))


def _elements(mj, obj: str, how: str) -> dict[str, np.ndarray]:
    """name -> the rows of a field indexed ``how``, for every element of type ``obj``."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    kind = getattr(mujoco.mjtObj, f"mjOBJ_{obj}")
    count = {"BODY": mj.nbody, "JOINT": mj.njnt, "GEOM": mj.ngeom, "ACTUATOR": mj.nu}[obj]
    out = {}
    for i in range(count):
        name = mujoco.mj_id2name(mj, kind, i) or f"{obj.lower()}{i}"
        if how == "dof":
            rows = np.flatnonzero(np.asarray(mj.dof_jntid) == i)
        elif how == "qpos":
            adr = int(mj.jnt_qposadr[i])
            size = {0: 7, 1: 4, 2: 1, 3: 1}[int(mj.jnt_type[i])]
            rows = np.arange(adr, adr + size)
        else:
            rows = np.array([i])
        out[name] = rows
    return out


def _fmt(x) -> str:
    x = np.atleast_1d(np.asarray(x, np.float64)).ravel()
    return " ".join(f"{v:.8g}" for v in x)


def model_differences(task: str, v5_model=None, *, rtol: float = 1e-6,
                      model=None) -> list[dict]:
    """What differs between the v5 env's compiled model and the MJX task's.

    -> rows ``{"quantity", "element", "mjx", "v5"}`` (values as strings; "absent" where an
    element exists in one model only). v5_model: ``env.unwrapped.model`` (default: a fresh
    ``make_v5(task)``'s); model: the ``mujoco.MjModel`` compared with it (default the MJX
    task's, ``load_mj(task)``). Numbers equal within ``rtol`` are not listed.
    """
    import importlib  # local: keeps `import rl2s_jax.physics` light (brax below)
    import inspect  # local: as above

    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    from rl2s_jax.envs.tasks import _LOCO  # local: as above

    env = make_v5(task) if v5_model is None else None
    v5 = v5_model if env is None else env.unwrapped.model
    mjx = load_mj(task) if model is None else model
    rows = []

    def differ(a, b) -> bool:
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        return a.shape != b.shape or not np.allclose(a, b, rtol=rtol, atol=1e-12)

    def add(quantity, element, a, b):
        rows.append({"quantity": quantity, "element": element, "mjx": a, "v5": b})

    for opt in MODEL_OPTIONS:
        a, b = getattr(mjx.opt, opt), getattr(v5.opt, opt)
        if differ(a, b):
            name = {"integrator": mujoco.mjtIntegrator, "solver": mujoco.mjtSolver,
                    "cone": mujoco.mjtCone, "jacobian": mujoco.mjtJacobian}.get(opt)
            fmt = (lambda x, e=name: e(int(x)).name) if name else _fmt
            add(f"opt.{opt}", "", fmt(a), fmt(b))
    module, cls = _BRAX_ENVS[task]
    brax_env = getattr(importlib.import_module(f"brax.envs.{module}"), cls)
    brax_noise = inspect.signature(brax_env.__init__).parameters["reset_noise_scale"].default
    v5_env = env.unwrapped if env is not None else make_v5(task).unwrapped
    add("precision", "", "float32 (MJX)", "float64 (C MuJoCo)")
    if _LOCO[task].n_frames != v5_env.frame_skip:
        add("n_frames / frame_skip", "", str(_LOCO[task].n_frames), str(v5_env.frame_skip))
    if differ(brax_noise, v5_env._reset_noise_scale):
        add("reset_noise_scale", "", _fmt(brax_noise), _fmt(v5_env._reset_noise_scale))
    for obj in ("BODY", "JOINT", "GEOM", "ACTUATOR"):  # elements in one model only
        ea, eb = _elements(mjx, obj, "one"), _elements(v5, obj, "one")
        for name in [n for n in ea if n not in eb] + [n for n in eb if n not in ea]:
            add(obj.lower(), name, "present" if name in ea else "absent",
                "present" if name in eb else "absent")
    for field, obj, how in _FIELDS:
        ea, eb = _elements(mjx, obj, how), _elements(v5, obj, how)
        for name in list(ea) + [n for n in eb if n not in ea]:
            a = np.asarray(getattr(mjx, field))[ea[name]] if name in ea else None
            b = np.asarray(getattr(v5, field))[eb[name]] if name in eb else None
            if a is not None and b is not None and differ(a, b):
                add(field, name, _fmt(a), _fmt(b))
    if env is not None:
        env.close()
    return rows


def print_differences(task: str, rows: list[dict] | None = None) -> str:
    """The table of :func:`model_differences` as text (also printed)."""
    rows = model_differences(task) if rows is None else rows
    head = ("quantity", "element", "mjx", "v5")
    width = [max(len(head[i]), *(len(str(r[k])) for r in rows))
             for i, k in enumerate(head)]
    line = lambda cells: "  ".join(str(c).ljust(w) for c, w in zip(cells, width, strict=True))
    text = "\n".join([f"{task}: MJX task vs {V5_ENVS[task]} ({len(rows)} rows)", line(head),
                      *(line([r[k] for k in head]) for r in rows)])
    print(text)
    return text
