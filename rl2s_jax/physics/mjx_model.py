"""A MuJoCo model as a parametrised one-step simulator of observations, through MJX.

:func:`physics_model` builds a :class:`PhysicsModel` for a registered locomotion task (the same
XML, options and ``n_frames`` as its brax MJX env) or for a user's MJCF file. Its ``step``::

    step(theta [K], obs [O], action [A]) -> next_obs [O]

sets (qpos, qvel) from the observation, runs ``n_frames`` ``mjx.step``s with the action as
``ctrl`` and maps the state back to an observation. It is pure, so ``jax.jit``, ``jax.vmap``
over transitions and ``jax.jacfwd`` over ``theta`` all apply. ``theta`` is one flat vector over
the model's candidate quantities (:class:`Candidate`), zero at the nominal model:

========================  =======================================  ========================
name                      element                                  value
========================  =======================================  ========================
``body_mass``             a body (its inertia scaled alike)        nominal * exp(theta)
``dof_damping``           a joint below the root                   nominal * exp(theta)
``dof_armature``          a joint below the root                   nominal * exp(theta)
``geom_friction``         a colliding geom (sliding friction)      nominal * exp(theta)
``actuator_gear``         an actuator (unnamed: its joint's name)  nominal * exp(theta)
``geom_margin``           a colliding geom (contact margin, m)     nominal + theta
``obs_bias``              an observation dim (``obs[i]``)          nominal + theta (0)
========================  =======================================  ========================

MuJoCo combines a contact pair's friction by the larger of its two geoms' values (so only the
larger geom of a pair moves it) and their margins by the sum: a pair whose geoms have margins
m1 and m2 is in contact (and pushing) from m1 + m2 apart, not from touching (measured: two
0.01 margins give a contact of margin 0.02). A dof quantity whose nominal value
is 0 is left out (a log factor cannot move it; MJX also builds frictionloss constraint rows
only where the nominal model has frictionloss, so frictionloss is not a candidate). A
per-actuator action delay of ``d`` control steps is not a continuous parameter:
:func:`delayed_actions` shifts the logged actions within each episode (zeros before the
episode's start) before ``step`` sees them.

Which geoms touch the floor is a candidate too, not through theta: :func:`collision_groups`
groups the geoms by type and size (a robot's like parts together) and :func:`switch_collisions`
compiles the model again with a group's contacts on or off (identify.py screens each group and
each swap of a colliding group for a non-colliding one on the same bodies).

The observation map. Registered tasks: obs = qpos ++ qvel, except that hopper's and walker2d's
``obs[1]`` is brax's torso height ``x.pos[0, 2]``, the kinematics one physics substep back
(tasks.py's docstring): ``obs[1] = z0 + q[1] - h qd[1]`` (``z0`` the torso's rest height, ``h``
the substep; exact for a slide joint under semi-implicit Euler). A user's MJCF
(``xml_path``): obs = qpos ++ qvel, nothing lagged.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Candidate", "PhysicsModel", "physics_model", "delayed_actions", "PHYSICS_TASKS",
           "LOG_QUANTITIES", "ADDED_QUANTITIES", "apply_to_mj", "theta_by_labels",
           "collision_groups", "switch_collisions"]

PHYSICS_TASKS = {"hopper": "hopper.xml", "walker2d": "walker2d.xml",
                 "halfcheetah": "half_cheetah.xml", "ant": "ant.xml"}
LOG_QUANTITIES = ("body_mass", "dof_damping", "dof_armature", "geom_friction", "actuator_gear")
ADDED_QUANTITIES = ("geom_margin",)  # nominal + theta, in the model (obs_bias: outside it)
_LAGGED_HEIGHT = ("hopper", "walker2d")  # obs[1] = lagged torso height (module docstring)


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One scalar model quantity: ``name`` (the MuJoCo field, or ``obs_bias``), ``element`` (the
    MuJoCo name of the body / joint / geom / actuator, or ``obs[i]``), ``index`` (its row in
    the field), ``nominal`` (its value in the nominal model)."""

    name: str
    element: str
    index: int
    nominal: float

    @property
    def log_scale(self) -> bool:
        return self.name in LOG_QUANTITIES

    def value(self, theta: float) -> float:
        """The quantity's value at parameter ``theta``."""
        return self.nominal * float(np.exp(theta)) if self.log_scale else self.nominal + theta

    def to_theta(self, value: float) -> float:
        """The parameter giving ``value`` (inverse of :meth:`value`)."""
        return float(np.log(value / self.nominal)) if self.log_scale else value - self.nominal

    @property
    def label(self) -> str:
        return f"{self.name}[{self.element}]"


@dataclasses.dataclass(frozen=True, eq=False)
class PhysicsModel:
    """A MuJoCo model as ``step(theta, obs, action) -> next_obs`` (module docstring).

    mj: the nominal C model (``mujoco.MjModel``); mjx_model: its MJX twin (float32); task: the
    registered task or None; xml_path: the MJCF it was built from; n_frames: physics substeps
    per control step; candidates: the K quantities ``theta`` indexes; lag: (obs dim, qpos
    index, qvel index, rest offset) for each lagged observation dim. Compared and hashed by
    identity (it holds arrays), so a jitted function may take it as a static argument.
    """

    mj: object
    mjx_model: object
    task: str | None
    xml_path: str
    n_frames: int
    candidates: tuple[Candidate, ...]
    lag: tuple[tuple[int, int, int, float], ...] = ()

    @property
    def nq(self) -> int:
        return int(self.mj.nq)

    @property
    def nv(self) -> int:
        return int(self.mj.nv)

    @property
    def obs_size(self) -> int:
        return self.nq + self.nv

    @property
    def action_size(self) -> int:
        return int(self.mj.nu)

    @property
    def substep(self) -> float:
        return float(self.mj.opt.timestep)

    def index(self, name: str, element: str) -> int:
        """Position in ``theta`` of quantity ``name`` of ``element``; KeyError if absent."""
        for i, c in enumerate(self.candidates):
            if c.name == name and c.element == element:
                return i
        raise KeyError(f"no candidate {name}[{element}]; have "
                       f"{[c.label for c in self.candidates]}")

    def obs_to_state(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """obs [O] -> (qpos [nq], qvel [nv])."""
        q, v = obs[: self.nq], obs[self.nq: self.nq + self.nv]
        for o, iq, iv, z0 in self.lag:
            q = q.at[iq].set(obs[o] - z0 + self.substep * v[iv])
        return q, v

    def state_to_obs(self, q: jax.Array, v: jax.Array) -> jax.Array:
        """(qpos [nq], qvel [nv]) -> obs [O]."""
        obs = jnp.concatenate([q, v])
        for o, iq, iv, z0 in self.lag:
            obs = obs.at[o].set(z0 + q[iq] - self.substep * v[iv])
        return obs

    def obs_to_state_np(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`obs_to_state` in NumPy float64."""
        q, v = obs[: self.nq].copy(), obs[self.nq: self.nq + self.nv]
        for o, iq, iv, z0 in self.lag:
            q[iq] = obs[o] - z0 + self.substep * v[iv]
        return q, v

    def state_to_obs_np(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """:meth:`state_to_obs` in NumPy float64."""
        obs = np.concatenate([q, v])
        for o, iq, iv, z0 in self.lag:
            obs[o] = z0 + q[iq] - self.substep * v[iv]
        return obs

    def apply(self, theta: jax.Array):
        """The MJX model with ``theta`` [K] applied (obs bias excluded)."""
        m = self.mjx_model
        fields = {}
        for name in LOG_QUANTITIES:
            pos = [i for i, c in enumerate(self.candidates) if c.name == name]
            if not pos:
                continue
            rows = np.array([self.candidates[i].index for i in pos])
            field = getattr(m, "body_mass" if name == "body_mass" else name)
            factor = jnp.ones(field.shape[0], theta.dtype).at[rows].set(
                jnp.exp(theta[np.array(pos)]))
            if name == "body_mass":
                fields["body_mass"] = m.body_mass * factor
                fields["body_inertia"] = m.body_inertia * factor[:, None]
            elif name in ("geom_friction", "actuator_gear"):
                fields[name] = field.at[:, 0].set(field[:, 0] * factor)
            else:
                fields[name] = field * factor
        for name in ADDED_QUANTITIES:
            pos = [i for i, c in enumerate(self.candidates) if c.name == name]
            if pos:
                rows = np.array([self.candidates[i].index for i in pos])
                fields[name] = getattr(m, name).at[rows].add(
                    theta[np.array(pos)].astype(getattr(m, name).dtype))
        return m.replace(**fields)

    def obs_bias(self, theta: jax.Array) -> jax.Array:
        """The observation bias [O] that ``theta`` [K] holds (0 where it has none)."""
        bias = jnp.zeros((self.obs_size,), theta.dtype)
        pos = [i for i, c in enumerate(self.candidates) if c.name == "obs_bias"]
        if pos:
            rows = np.array([self.candidates[i].index for i in pos])
            bias = bias.at[rows].set(theta[np.array(pos)])
        return bias

    def step(self, theta: jax.Array, obs: jax.Array, action: jax.Array) -> jax.Array:
        """One control step: theta [K], obs [O], action [A] -> next_obs [O] (module docstring)."""
        return self.step_with_contact(theta, obs, action)[0]

    def step_with_contact(self, theta: jax.Array, obs: jax.Array, action: jax.Array
                          ) -> tuple[jax.Array, jax.Array]:
        """:meth:`step` plus whether any contact is active in the first substep (bool [])."""
        from mujoco import mjx  # local: keeps `import rl2s_jax.physics` free of MuJoCo

        m = self.apply(theta)
        bias = self.obs_bias(theta)
        q, v = self.obs_to_state(obs - bias)
        data = mjx.make_data(m).replace(qpos=q, qvel=v, ctrl=action)
        data = mjx.step(m, data)
        dist = data._impl.contact.dist if hasattr(data, "_impl") else data.contact.dist
        touching = jnp.any(dist < 0) if dist.size else jnp.zeros((), bool)
        data = jax.lax.fori_loop(0, self.n_frames - 1, lambda _, d: mjx.step(m, d), data)
        return self.state_to_obs(data.qpos, data.qvel) + bias, touching

    def batch_step(self) -> Callable[[jax.Array, jax.Array, jax.Array], jax.Array]:
        """jit(vmap(step)) over transitions: theta [K], obs [N, O], action [N, A] -> [N, O]."""
        return jax.jit(jax.vmap(self.step, in_axes=(None, 0, 0)))


def _name(mj, obj, i: int) -> str:
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    return mujoco.mj_id2name(mj, obj, i) or ""


def candidates_of(mj) -> tuple[Candidate, ...]:
    """The candidate quantities of a C model (module docstring's table), in that order."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    ob = mujoco.mjtObj
    out = [Candidate("body_mass", _name(mj, ob.mjOBJ_BODY, b) or f"body{b}", b,
                     float(mj.body_mass[b])) for b in range(1, mj.nbody) if mj.body_mass[b] > 0]
    root_bodies = {b for b in range(mj.nbody) if mj.body_parentid[b] == 0}
    for field in ("dof_damping", "dof_armature"):
        for d in range(mj.nv):
            j = int(mj.dof_jntid[d])
            if mj.jnt_bodyid[j] in root_bodies or getattr(mj, field)[d] <= 0:
                continue
            out.append(Candidate(field, _name(mj, ob.mjOBJ_JOINT, j) or f"joint{j}", d,
                                 float(getattr(mj, field)[d])))
    for g in range(mj.ngeom):
        if (mj.geom_contype[g] or mj.geom_conaffinity[g]) and mj.geom_friction[g, 0] > 0:
            out.append(Candidate("geom_friction", _name(mj, ob.mjOBJ_GEOM, g) or f"geom{g}", g,
                                 float(mj.geom_friction[g, 0])))
    for a in range(mj.nu):
        name = _name(mj, ob.mjOBJ_ACTUATOR, a) or _name(mj, ob.mjOBJ_JOINT, mj.actuator_trnid[a, 0])
        out.append(Candidate("actuator_gear", name or f"actuator{a}", a,
                             float(mj.actuator_gear[a, 0])))
    out += [Candidate("geom_margin", _name(mj, ob.mjOBJ_GEOM, g) or f"geom{g}", g,
                      float(mj.geom_margin[g]))
            for g in range(mj.ngeom) if mj.geom_contype[g] or mj.geom_conaffinity[g]]
    out += [Candidate("obs_bias", f"obs[{i}]", i, 0.0) for i in range(mj.nq + mj.nv)]
    return tuple(out)


def apply_to_mj(mj, candidates, theta) -> None:
    """Apply ``theta`` [K] of ``candidates`` to a C model in place, from its current values,
    as :meth:`PhysicsModel.apply` does to the MJX model (observation bias excluded)."""
    for c, th in zip(candidates, np.asarray(theta, np.float64), strict=True):
        if c.name == "obs_bias":
            continue
        if c.name in ADDED_QUANTITIES:
            getattr(mj, c.name)[c.index] += th
            continue
        f = np.exp(th)
        if c.name == "body_mass":
            mj.body_mass[c.index] *= f
            mj.body_inertia[c.index] *= f
        elif c.name in ("geom_friction", "actuator_gear"):
            getattr(mj, c.name)[c.index, 0] *= f
        else:
            getattr(mj, c.name)[c.index] *= f


def theta_by_labels(pm: PhysicsModel, labels, theta):
    """``theta`` saved for the candidates ``labels`` (a calibrated.json's) -> theta [K] over
    ``pm``'s candidates: as saved where the labels are the model's; scattered where they are
    a subset (a file written before candidates were added: those at their nominal value,
    theta 0); None where they are neither (or theta is no list of one value per label)."""
    have = [c.label for c in pm.candidates]
    if list(labels) == have:
        return theta
    if (not isinstance(theta, (list, tuple)) or len(labels) != len(theta)
            or not set(labels) <= set(have)):
        return None
    full = [0.0] * len(have)
    for lab, th in zip(labels, theta, strict=True):
        full[have.index(lab)] = th
    return full


def actuator_names(mj) -> list[str]:
    """Each actuator's name (an unnamed one by the joint it drives)."""
    return [c.element for c in candidates_of(mj) if c.name == "actuator_gear"]


def task_xml(task: str) -> str:
    """Path of a registered locomotion task's MJCF (brax's asset)."""
    from etils import epath  # local: keeps `import rl2s_jax.physics` light

    if task not in PHYSICS_TASKS:
        raise ValueError(f"task: expected one of {sorted(PHYSICS_TASKS)} (a task with a "
                         f"physics model) or --sim-xml FILE, got {task!r}")
    return str(epath.resource_path("brax") / "envs" / "assets" / PHYSICS_TASKS[task])


# MuJoCo's integrators by name (mujoco.mjtIntegrator's values); the ones MJX also steps are the
# identification's integrator candidates (identify.FitConfig.integrators)
INTEGRATORS = {"Euler": 0, "RK4": 1, "implicit": 2, "implicitfast": 3}


def integrator_name(mj) -> str:
    """The name (INTEGRATORS) of a C model's integrator."""
    by_value = {v: k for k, v in INTEGRATORS.items()}
    return by_value.get(int(mj.opt.integrator), f"mjtIntegrator {int(mj.opt.integrator)}")


def integrator_value(name: str) -> int:
    """mujoco.mjtIntegrator's value of an integrator's name; ValueError naming the choices."""
    if name not in INTEGRATORS:
        raise ValueError(f"integrator: expected one of {', '.join(INTEGRATORS)}, got {name!r}")
    return INTEGRATORS[name]


def set_integrator(mj, name: str) -> None:
    """Set a C model's integrator by name (in place); ValueError naming the choices."""
    mj.opt.integrator = integrator_value(name)


def _geom_collides(mj, g: int) -> bool:
    return bool(mj.geom_contype[g] or mj.geom_conaffinity[g])


def collision_groups(mj) -> list[dict]:
    """The geoms off the world body, grouped by (type, size, colliding or not): what one
    structural candidate switches together, so that a robot's like parts (four ankles) go
    as one. -> [{"names": [geom names], "bodies": [their bodies' ids], "collides": bool}],
    by their first geom."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    groups: dict[tuple, dict] = {}
    for g in range(mj.ngeom):
        if mj.geom_bodyid[g] == 0:
            continue
        key = (int(mj.geom_type[g]), tuple(np.round(mj.geom_size[g], 6).tolist()),
               _geom_collides(mj, g))
        group = groups.setdefault(key, {"names": [], "bodies": [], "collides": key[2]})
        group["names"].append(_name(mj, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}")
        group["bodies"].append(int(mj.geom_bodyid[g]))
    return list(groups.values())


# A C model's <option> fields that the simulation depends on (switch_collisions keeps them;
# gymnasium_v5 compares two models' by them)
MODEL_OPTIONS = ("timestep", "integrator", "solver", "iterations", "ls_iterations", "tolerance",
                 "ls_tolerance", "cone", "jacobian", "impratio", "noslip_iterations", "gravity",
                 "disableflags", "enableflags")


def switch_collisions(mj, xml_path: str, collisions: dict):
    """A C model as ``mj`` (built from ``xml_path``, with its options) whose geoms' contacts
    are switched by name: {name: True} gives a non-colliding geom contype 1 (it then touches
    what has conaffinity 1, such as a floor), {name: False} contype and conaffinity 0. It is
    compiled again from the XML, because MuJoCo builds a body's collision structures (its
    geoms' bounding volumes) from the geoms that collide when it compiles; with nothing to
    switch, a copy of ``mj``. ValueError naming a geom the model lacks."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    if not collisions:
        return copy.deepcopy(mj)
    spec = mujoco.MjSpec.from_file(xml_path)
    by_name = {g.name or f"geom{i}": g for i, g in enumerate(spec.geoms)}
    for name, on in collisions.items():
        if name not in by_name:
            raise ValueError(f"collisions: expected geom names of {xml_path}, got {name!r}")
        g = by_name[name]
        if on and not (g.contype or g.conaffinity):
            g.contype = 1
        elif not on:
            g.contype = g.conaffinity = 0
    out = spec.compile()
    if out.ngeom != mj.ngeom:
        raise ValueError(f"collisions: {xml_path} is not the model's XML ({out.ngeom} geoms "
                         f"against {mj.ngeom})")
    for name in MODEL_OPTIONS:
        setattr(out.opt, name, getattr(mj.opt, name))
    return out


def load_mj(task: str | None, xml_path: str | None = None):
    """The nominal C model (``mujoco.MjModel``) of a task, as its MJX env runs it, or of an
    MJCF file."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    from rl2s_jax.envs.tasks import ANT_SOLVER_ITERATIONS

    mj = mujoco.MjModel.from_xml_path(xml_path or task_xml(task))
    if task == "ant" and xml_path is None:
        mj.opt.iterations = ANT_SOLVER_ITERATIONS
    return mj


def physics_model(task: str | None = None, *, xml_path: str | None = None,
                  n_frames: int | None = None, integrator: str | None = None,
                  collisions: dict | None = None) -> PhysicsModel:
    """The physics model of a registered task (its MJX env's XML, options, ``n_frames``) or of
    a user's MJCF (``xml_path``; obs = qpos ++ qvel; ``n_frames`` default 1); ``integrator``
    (INTEGRATORS' names) in place of the XML's and geoms' contacts switched by
    ``collisions`` ({geom name: bool}, :func:`switch_collisions`): a calibrated model's. Its
    candidates stay the XML's, so that a calibrated theta keeps its meaning."""
    from mujoco import mjx  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    from rl2s_jax.envs.tasks import _LOCO

    if xml_path is None:
        task_xml(task)  # a clear error for a task without a physics model
        n_frames = n_frames or _LOCO[task].n_frames
    elif n_frames is not None and n_frames < 1:
        raise ValueError(f"n_frames: expected a positive integer, got {n_frames}")
    mj = load_mj(task if xml_path is None else None, xml_path)
    if integrator is not None:
        set_integrator(mj, integrator)
    candidates = candidates_of(mj)
    if collisions:
        mj = switch_collisions(mj, xml_path or task_xml(task), collisions)
    lag = ()
    if xml_path is None and task in _LAGGED_HEIGHT:
        lag = ((1, 1, 1, float(mj.body_pos[1, 2])),)
    return PhysicsModel(mj=mj, mjx_model=mjx.put_model(mj), task=task if xml_path is None
                        else None, xml_path=xml_path or task_xml(task),
                        n_frames=int(n_frames or 1), candidates=candidates, lag=lag)


def delayed_actions(action: np.ndarray, episode_id: np.ndarray, t: np.ndarray,
                    delays) -> np.ndarray:
    """The actions a system with per-actuator delays applied: column ``j`` of row ``i`` is the
    logged action ``delays[j]`` steps earlier in the same episode (0 before its start).

    action [N, A], episode_id [N], t [N] (rows of an episode contiguous, t = 0, 1, ...),
    delays [A] ints >= 0 -> [N, A].
    """
    delays = np.asarray(delays, dtype=int)
    if delays.shape != (action.shape[1],) or (delays < 0).any():
        raise ValueError(f"delays: expected {action.shape[1]} non-negative ints, got {delays}")
    out = np.zeros_like(action)
    for j, d in enumerate(delays):
        src = np.arange(len(action)) - d
        ok = (t >= d) & (src >= 0)
        ok[ok] &= episode_id[src[ok]] == episode_id[ok]
        out[ok, j] = action[src[ok], j]
    return out
