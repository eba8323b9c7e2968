"""Measured data from C MuJoCo (float64), optionally with planted physical changes.

:func:`collect_measured` runs zoo policies (a NumPy forward pass of the tanh-Gaussian MLP) in
the C engine on the same XML and options as a registered MJX task and records a Dataset in
the MJX task's observation convention (``PhysicsModel.state_to_obs``; the first observation of
an episode uses the lagged height too, where brax's reset does not: a difference of at most
``h * |v0|`` = 1e-5). Episodes start as brax's do (qpos0 and qvel 0 plus U(-0.005, 0.005)) and
end at the task's ``done_fn`` or its time limit.

A planted change (:class:`Planted`) edits the compiled C model's fields, as the MJX model's
parameters do: ``body_mass`` (inertia scaled alike), ``geom_friction`` (sliding),
``actuator_gear``, ``dof_damping`` and ``dof_armature`` take a factor; ``action_delay`` takes
a number of control steps by which the system applies the logged action of that actuator
late (zeros before the episode's start). ``meta["source"]["planted"]`` records the truth:
``[{"name", "element", "nominal", "value"}]``.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from rl2s_jax.data.dataset import Dataset
from rl2s_jax.physics.mjx_model import (
    Candidate,
    PhysicsModel,
    actuator_names,
    candidates_of,
    integrator_name,
    set_integrator,
    switch_collisions,
)

__all__ = ["Planted", "collect_measured", "numpy_policy_action"]

_FIELD_NAMES = ("body_mass", "geom_friction", "actuator_gear", "dof_damping", "dof_armature")


@dataclasses.dataclass(frozen=True)
class Planted:
    """One planted change: ``name`` (a quantity of mjx_model's table, ``action_delay``,
    ``integrator`` or ``geom_collides``), ``element`` (its MuJoCo name; for ``integrator`` the
    integrator the data's engine steps with, a name of mjx_model.INTEGRATORS), ``amount`` (a
    factor; for ``geom_margin`` the margin itself, in m; for ``action_delay`` control steps;
    for ``geom_collides`` 1 (the geom touches what has conaffinity) or 0 (nothing); unused for
    ``integrator``)."""

    name: str
    element: str
    amount: float


def numpy_policy_action(params: dict, obs: np.ndarray, rng: np.random.Generator | None
                        ) -> np.ndarray:
    """One policy's action in NumPy: tanh of a Gaussian sample (its mode when ``rng`` is None).
    params: one policy's pytree (NumPy or JAX arrays); obs [O] -> action [A]."""
    x = np.clip((obs - np.asarray(params["obs_mean"])) / np.asarray(params["obs_std"]),
                -10.0, 10.0)
    layers = params["layers"]
    for layer in layers[:-1]:
        x = x @ np.asarray(layer["w"]) + np.asarray(layer["b"])
        x = x / (1.0 + np.exp(-x))  # swish
    out = x @ np.asarray(layers[-1]["w"]) + np.asarray(layers[-1]["b"])
    loc, raw_scale = np.split(out, 2)
    if rng is None:
        return np.tanh(loc)
    scale = np.logaddexp(0.0, raw_scale) + 1e-3  # softplus + MIN_SCALE, as policy.py
    return np.tanh(loc + scale * rng.standard_normal(loc.shape))


def plant(pm: PhysicsModel, changes: list[Planted]):
    """A copy of ``pm``'s C model with ``changes`` applied -> (MjModel, delays [A], truth).
    Contacts switched (``geom_collides``) first: that model is compiled again."""
    switched = {ch.element: bool(ch.amount) for ch in changes if ch.name == "geom_collides"}
    mj = switch_collisions(pm.mj, pm.xml_path, switched)
    delays = np.zeros(mj.nu, dtype=int)
    truth = [{"name": "geom_collides", "element": n, "nominal": "no" if on else "yes",
              "value": "yes" if on else "no"} for n, on in switched.items()]
    cands = candidates_of(pm.mj)
    for ch in changes:
        if ch.name == "geom_collides":
            continue
        if ch.name == "integrator":
            truth.append({"name": "integrator", "element": "opt",
                          "nominal": integrator_name(mj), "value": ch.element})
            set_integrator(mj, ch.element)  # a ValueError naming the choices
            continue
        if ch.name == "action_delay":
            names = actuator_names(pm.mj)
            if ch.element not in names or int(ch.amount) != ch.amount or ch.amount < 0:
                raise ValueError(f"planted action_delay: expected an actuator of {names} and "
                                 f"a whole number of steps >= 0, got {ch.element!r}, {ch.amount}")
            delays[names.index(ch.element)] = int(ch.amount)
            truth.append({"name": ch.name, "element": ch.element, "nominal": 0,
                          "value": int(ch.amount)})
            continue
        match = [c for c in cands if c.name == ch.name and c.element == ch.element]
        if ch.name == "geom_margin":
            if not match or not ch.amount >= 0:
                raise ValueError(f"planted geom_margin[{ch.element}]: expected a colliding "
                                 f"geom of the model and a margin >= 0 (m), got {ch.amount}")
            mj.geom_margin[match[0].index] = ch.amount
            truth.append({"name": ch.name, "element": ch.element,
                          "nominal": match[0].nominal, "value": float(ch.amount)})
            continue
        if ch.name not in _FIELD_NAMES or not match or not ch.amount > 0:
            raise ValueError(f"planted {ch.name}[{ch.element}]: expected a quantity of "
                             f"{_FIELD_NAMES} of an element the model has and a factor > 0, "
                             f"got {ch.amount}")
        c: Candidate = match[0]
        if ch.name == "body_mass":
            mj.body_mass[c.index] *= ch.amount
            mj.body_inertia[c.index] *= ch.amount
        elif ch.name in ("geom_friction", "actuator_gear"):
            getattr(mj, ch.name)[c.index, 0] *= ch.amount
        else:
            getattr(mj, ch.name)[c.index] *= ch.amount
        truth.append({"name": ch.name, "element": ch.element, "nominal": c.nominal,
                      "value": c.nominal * ch.amount})
    return mj, delays, truth


def _episode(pm, mj, data, params, delays, rng, length, done_fn):
    """One episode in C MuJoCo -> dict of lists (obs, action, next_obs, done)."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    mujoco.mj_resetData(mj, data)
    data.qpos[:] = mj.qpos0 + rng.uniform(-5e-3, 5e-3, mj.nq)
    data.qvel[:] = rng.uniform(-5e-3, 5e-3, mj.nv)
    mujoco.mj_forward(mj, data)
    obs = pm.state_to_obs_np(data.qpos.copy(), data.qvel.copy())
    rec = {"obs": [], "action": [], "next_obs": [], "done": []}
    for _ in range(length):
        action = numpy_policy_action(params, obs.astype(np.float32), rng).astype(np.float32)
        rec["action"].append(action)
        late = np.array(rec["action"])
        data.ctrl[:] = [late[-1 - d, j] if len(late) > d else 0.0 for j, d in enumerate(delays)]
        mujoco.mj_step(mj, data, nstep=pm.n_frames)
        nxt = pm.state_to_obs_np(data.qpos.copy(), data.qvel.copy())
        done = bool(done_fn(nxt))
        rec["obs"].append(obs)
        rec["next_obs"].append(nxt)
        rec["done"].append(done)
        obs = nxt
        if done:
            break
    return rec


def collect_measured(pm: PhysicsModel, params, *, transitions_per_policy: int,
                     episode_length: int, seed: int = 0, changes: list[Planted] = (),
                     policy_names: list[str] | None = None, source: dict | None = None
                     ) -> Dataset:
    """Record ``transitions_per_policy`` transitions of each policy of a stacked zoo
    (``params`` [P, ...]) in C MuJoCo with ``changes`` planted (module docstring)."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    from rl2s_jax.envs.tasks import get_task  # local: as above (brax)

    if transitions_per_policy < 1 or episode_length < 1:
        raise ValueError(f"transitions_per_policy, episode_length: expected positive ints, got "
                         f"{transitions_per_policy}, {episode_length}")
    mj, delays, truth = plant(pm, list(changes))
    data = mujoco.MjData(mj)
    n_pol = jax.tree_util.tree_leaves(params)[0].shape[0]
    task = get_task(pm.task) if pm.task else None
    done_fn = (lambda o: bool(np.asarray(task.done_fn(o)))) if task else (lambda o: False)
    rng = np.random.default_rng(seed)
    rows = {k: [] for k in ("obs", "action", "next_obs", "done", "truncated", "policy_id",
                            "episode_id", "t")}
    episode = 0
    for p in range(n_pol):
        one = jax.tree_util.tree_map(lambda x, p=p: np.asarray(x[p]), params)
        got = 0
        while got < transitions_per_policy:
            rec = _episode(pm, mj, data, one, delays, rng,
                           min(episode_length, transitions_per_policy - got), done_fn)
            n = len(rec["obs"])
            for k in ("obs", "action", "next_obs", "done"):
                rows[k] += rec[k]
            full = n == episode_length and not rec["done"][-1]
            rows["truncated"] += [False] * (n - 1) + [full]
            rows["policy_id"] += [p] * n
            rows["episode_id"] += [episode] * n
            rows["t"] += list(range(n))
            episode += 1
            got += n
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    obs, nxt = arrays["obs"].astype(np.float32), arrays["next_obs"].astype(np.float32)
    act = arrays["action"].astype(np.float32)
    reward = (np.asarray(task.reward_fn(obs, act, nxt)) if task
              else np.zeros(len(obs))).astype(np.float32)
    meta = {"task": pm.task, "obs_size": pm.obs_size, "action_size": pm.action_size,
            "n_policies": int(n_pol), "gamma": None, "episode_length": int(episode_length),
            "policy_names": list(policy_names or [f"policy-{i:03d}" for i in range(n_pol)]),
            "source": {"collector": "rl2s_jax.physics.measured", "engine": "mujoco C float64",
                       "xml": pm.xml_path, "seed": seed, "planted": truth, **(source or {})}}
    return Dataset.from_arrays({**arrays, "obs": obs, "action": act, "next_obs": nxt,
                                "reward": reward,
                                "policy_id": arrays["policy_id"].astype(np.int32),
                                "episode_id": arrays["episode_id"].astype(np.int32),
                                "t": arrays["t"].astype(np.int32)}, meta)
