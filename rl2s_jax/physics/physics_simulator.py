"""The calibrated (or nominal) physics as a simulator that `rl2s evaluate`, `rl2s improve` and
the Gymnasium env take in place of a learned one (issue 62, item 3).

:class:`PhysicsSimulator` exposes what those callers use of a learned ``Simulator``:
``dynamics(obs, action, key[, hist])`` (:func:`calibrated.physics_dynamics`: the MJX step at
``theta`` with the per-actuator ``delays``), ``markov`` and ``new_history`` (the past of
actions a delay needs), ``task_fns()`` (the registered task's reward_fn / done_fn) and
``terminations`` (the task's rule; no learned hazard). It is deterministic: ``mean`` and
``sample`` are the same step, the key is unused. It has no ensemble, so no disagreement:
``uncertainty_fn`` / ``disagreement`` are absent, and what needs them (MOPO's penalty, the
stop rule, `rl2s evaluate --level`'s value intervals, the Gymnasium env's
``info["uncertainty"]``) is refused or left out. ``n_members`` is 1 (``replace`` of the
ensemble's fields returns it as it is): the deployment guard of `rl2s improve` reads the
physics' own values as its one member's.

:func:`physics_simulator` makes one from ``"nominal"`` (the data's registered task's MJX model)
or a ``calibrated.json`` (`rl2s diagnose --physics` writes it)::

    {"task": "hopper" | null, "xml": MJCF path (used when task is null), "n_frames": int | null,
     "theta": [K] | null, "delays": [A] | null, "labels": [K] (optional),
     "integrator": "RK4" | ... | null, "collisions": {geom name: true | false} | null}

``theta`` holds one value per candidate quantity of the model (``PhysicsModel.candidates``, in
that order; null: the nominal model), ``delays`` one int per actuator (null: none),
``labels`` the candidates' labels, checked against the model's, and ``integrator`` and
``collisions`` the model's structure where the diagnosis changed it (mjx_model.INTEGRATORS'
names; geoms whose contacts it switched). A user's MJCF (``task`` null)
takes the data's registered task for its rewards and terminations.
"""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np

from rl2s_jax.data.dataset import spread_rows
from rl2s_jax.envs.tasks import TASKS, get_task
from rl2s_jax.physics.calibrated import _theta_delays, physics_dynamics
from rl2s_jax.physics.mjx_model import (
    PHYSICS_TASKS,
    PhysicsModel,
    delayed_actions,
    physics_model,
    theta_by_labels,
)
from rl2s_jax.physics.residuals import predict

__all__ = ["NOMINAL", "PhysicsSimulator", "one_step_mse", "physics_simulator"]

NOMINAL = "nominal"  # --physics nominal: the data's task's MJX model as it is


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class PhysicsSimulator:
    """A physics model at ``theta`` [K] with action ``delays`` [A] as a simulator (module
    docstring). pm: the model (hashed by identity); task: the registered task whose reward_fn
    / done_fn the rollouts step with; source: where it came from (a calibrated.json path or
    "nominal"), for reports. A static pytree: a jitted function takes it as an argument and
    compiles once per simulator."""

    pm: PhysicsModel
    theta: tuple[float, ...]
    delays: tuple[int, ...]
    task: str
    source: str = NOMINAL

    n_members = 1  # one deterministic model: no ensemble (the guard's one member)
    rank = None
    n_elites = None

    def replace(self, **fields) -> PhysicsSimulator:
        """Itself for the ensemble's fields (``rank``, ``member_mode``, ``n_elites``: one
        member, nothing to pick, as the deployment guard's ``member_values`` sets them);
        ``dataclasses.replace`` for its own."""
        for k in ("rank", "member_mode", "n_elites"):
            fields.pop(k, None)
        return dataclasses.replace(self, **fields) if fields else self

    def _dynamics(self):
        # made at every call, not cached: its arrays are constants of the trace that calls it
        # (one kept from an earlier trace would leak into the next)
        return physics_dynamics(self.pm, np.asarray(self.theta), np.asarray(self.delays))

    @property
    def markov(self) -> bool:
        """True without a delay: a step needs only (obs, action)."""
        return not any(self.delays)

    def new_history(self, batch_shape: tuple[int, ...]):
        """The empty past of actions of episodes starting now (None without a delay)."""
        return None if self.markov else self._dynamics()[1](tuple(batch_shape))

    def dynamics(self, obs: jax.Array, action: jax.Array, key: jax.Array | None = None,
                 hist=None) -> jax.Array:
        """One control step of the physics: obs [..., O], action [..., A] -> next obs [..., O]
        (``hist``: the episode's past, required with a delay; ``key`` unused)."""
        if self.markov:
            return self._dynamics()[0](obs, action, key)
        if hist is None:
            raise ValueError(f"hist: this physics delays actuators by {list(self.delays)} "
                             f"steps; pass the episode's past (new_history at its start)")
        return self._dynamics()[0](obs, action, key, hist)

    def sample(self, obs, action, key=None, hist=None) -> jax.Array:
        """The step (deterministic: the same as ``mean``)."""
        return self.dynamics(obs, action, key, hist)

    def mean(self, obs, action, hist=None) -> jax.Array:
        return self.dynamics(obs, action, None, hist)

    def task_fns(self):
        """The registered task's ``Task`` (reward_fn, done_fn, sizes)."""
        return get_task(self.task)

    def terminations(self, done_fn):
        """(done_fn, hazard_fn) for ``advance_values``: the task's rule, no hazard."""
        return done_fn, None


def _read(source: str) -> dict:
    if not os.path.isfile(source):
        raise ValueError(f"physics: no such file {source!r} (expected a calibrated.json from "
                         f"`rl2s diagnose --physics`, or {NOMINAL!r})")
    try:
        with open(source) as f:
            c = json.load(f)
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"physics: {source} is not a calibrated.json (not JSON: {e})") from None
    if not isinstance(c, dict):
        raise ValueError(f"physics: {source}: expected a JSON object with task, xml, n_frames, "
                         f"theta, delays; got {type(c).__name__}")
    return c


def _structure(c: dict, source: str) -> dict:
    """A calibrated.json's changes of the model's structure: {"integrator", "collisions"}
    (physics_model's arguments; a bad integrator or geom name is its ValueError, given the
    file's name by ``_build``)."""
    integrator, collisions = c.get("integrator"), c.get("collisions")
    if collisions is not None and not (isinstance(collisions, dict) and all(
            isinstance(k, str) and isinstance(v, bool) for k, v in collisions.items())):
        raise ValueError(f"physics: {source}: collisions: expected {{geom name: true | "
                         f"false}} or null, got {collisions!r}")
    return {"integrator": integrator, "collisions": collisions}


def _model_of(c: dict, source: str, data_task: str | None) -> PhysicsModel:
    """The physics model a calibrated.json names (its structure too), checked against the
    data's task."""
    task, xml, n_frames = c.get("task"), c.get("xml"), c.get("n_frames")
    structure = _structure(c, source)
    if n_frames is not None and (isinstance(n_frames, bool) or not isinstance(n_frames, int)
                                 or n_frames < 1):
        raise ValueError(f"physics: {source}: n_frames: expected an int >= 1 or null, got "
                         f"{n_frames!r}")
    if task is None:
        if not isinstance(xml, str) or not os.path.isfile(xml):
            raise ValueError(f"physics: {source}: xml: expected the MJCF file of a model of no "
                             f"registered task (task null), got {xml!r}")
        return _build(source, None, xml_path=xml, n_frames=n_frames, **structure)
    if task not in PHYSICS_TASKS:
        raise ValueError(f"physics: {source}: task: expected one of {sorted(PHYSICS_TASKS)} "
                         f"or null (with xml), got {task!r}")
    if task != data_task:
        raise ValueError(f"physics: {source} models task {task!r} but the data is task "
                         f"{data_task!r}")
    return _build(source, task, n_frames=n_frames, **structure)


def _build(source: str, task: str | None, **kw) -> PhysicsModel:
    try:
        return physics_model(task, **kw)
    except ValueError as e:  # an integrator or a geom the model lacks
        raise ValueError(f"physics: {source}: {e}") from None


def checked_model(content: dict, source: str = "calibrated.json",
                  data_task: str | None = None) -> tuple[PhysicsModel, tuple, tuple]:
    """A calibrated.json's content -> (PhysicsModel with its structure, theta [K], delays
    [A]), every field checked (ValueError naming ``source`` and the field); ``data_task``:
    the data's task it must model (default the file's own)."""
    pm = _model_of(content, source, content.get("task") if data_task is None else data_task)
    return (pm, *_values(content, source, pm))


def _values(c: dict, source: str, pm: PhysicsModel) -> tuple[tuple, tuple]:
    """(theta, delays) of a calibrated.json, checked against the model's candidates."""
    labels, theta = c.get("labels"), c.get("theta")
    mine = [cand.label for cand in pm.candidates]
    if labels is not None and list(labels) != mine:
        theta = theta_by_labels(pm, labels, theta)  # a file from before candidates were added
        if theta is None:
            raise ValueError(f"physics: {source}: labels: its {len(labels)} quantities are not "
                             f"this model's {len(mine)} ({mine[:3]}...); it was written for "
                             f"another model")
    try:
        theta, delays = _theta_delays(pm, theta, c.get("delays"))
    except (TypeError, ValueError) as e:
        raise ValueError(f"physics: {source}: {e}") from None
    if not np.all(np.isfinite(theta)):
        raise ValueError(f"physics: {source}: theta: expected finite values")
    return tuple(float(x) for x in theta), tuple(int(d) for d in delays)


def physics_simulator(source: str, data_task: str | None, obs_size: int | None = None,
                      action_size: int | None = None) -> PhysicsSimulator:
    """The simulator of ``source`` ("nominal" or a calibrated.json path, module docstring) for
    data of task ``data_task`` with these sizes; ValueError naming the field before any
    model is compiled."""
    if not isinstance(source, str) or not source:
        raise ValueError(f"physics: expected a calibrated.json path or {NOMINAL!r}, got "
                         f"{source!r}")
    if source == NOMINAL:
        if data_task not in PHYSICS_TASKS:
            raise ValueError(f"physics: {NOMINAL!r} is the data's task's MuJoCo model, and its "
                             f"task {data_task!r} has none (expected one of "
                             f"{sorted(PHYSICS_TASKS)}); give a calibrated.json naming your "
                             f"MJCF (\"task\": null, \"xml\": FILE)")
        pm = physics_model(data_task)
        return PhysicsSimulator(pm, (0.0,) * len(pm.candidates), (0,) * pm.action_size,
                                data_task, NOMINAL)
    c = _read(source)
    if data_task not in TASKS:
        raise ValueError(f"physics: the data's task {data_task!r} is not registered, so no "
                         f"reward_fn / done_fn for the physics' rollouts")
    pm = _model_of(c, source, data_task)
    sizes = (pm.obs_size, pm.action_size)
    task = get_task(data_task)
    for what, want in (("the data's", (obs_size, action_size)),
                       (f"task {data_task!r}'s", (task.obs_size, task.action_size))):
        if None not in want and tuple(want) != sizes:
            raise ValueError(f"physics: {source}: the model's obs / action sizes {sizes} "
                             f"differ from {what} {tuple(want)}")
    theta, delays = _values(c, source, pm)
    return PhysicsSimulator(pm, theta, delays, data_task, source)



def one_step_mse(sim: PhysicsSimulator, ds, max_rows: int = 20_000,
                 backend: str = "mujoco") -> dict:
    """The physics' one-step error on the transitions of ``ds``, as ``one_step_errors``
    measures a learned simulator's ``heldout_mse``: the squared error of the next state per
    dim, in units of this data's std of s' - s, averaged over dims and up to ``max_rows`` rows
    evenly spread (each row's action delayed as the physics applies it, from its logged
    episode). Stepped in C MuJoCo by default (``residuals.predict``: float64, nothing to
    compile; the MJX step the rollouts take differs from it by float32 round-off), or
    ``backend="mjx"``. No NLL: the physics is deterministic. -> {"heldout_mse",
    "one_step_rows"}."""
    rows = spread_rows(ds.n_transitions, max_rows)
    action = np.asarray(ds.action, np.float64)
    if not sim.markov:
        action = delayed_actions(action, np.asarray(ds.episode_id), np.asarray(ds.t),
                                 sim.delays)
    obs, nxt = np.asarray(ds.obs, np.float64), np.asarray(ds.next_obs, np.float64)
    pred = predict(sim.pm, np.asarray(sim.theta), obs[rows], action[rows], backend=backend)
    scale = np.maximum((nxt - obs).std(0), 1e-6)
    return {"heldout_mse": float(np.mean(((pred - nxt[rows]) / scale) ** 2)),
            "one_step_rows": int(rows.size)}
