"""The hybrid simulator (issue 62, item 3; SimGAN's hybrid): the calibrated physics plus a
learned residual, trained through ``train_step``::

    next_obs = physics(obs, action) + (learned(obs, action) - obs)

What is learned. The project's own model family, fitted by likelihood (method "bc") on a
Dataset whose next state is replaced by the physics' residual added to the state::

    next_obs' = obs + (next_obs - physics(obs, a_delayed))          (:func:`residual_data`)

so that its usual delta parametrisation (s' = s + delta) learns exactly what the physics
leaves unexplained. ``physics`` is the calibrated model of ``rl2s diagnose --physics``'s
calibrated.json (theta and per-actuator delays; the actions delayed within each episode, zeros
before its start, as the identification delays them), stepped once per row in C MuJoCo,
float64 (``residuals.predict``: no compilation, ~0.1 ms a row on the CPU).

At simulation time the trained ``Simulator`` gets the physics as its ``base``
(:func:`physics_base`: the MJX step, float32, ``calibrated.physics_dynamics``), so every
rollout, score and ``rl2s evaluate`` steps ``base(s, a) + delta``. The two engines differ by
float32 round-off and MJX's solver (the test measures it against the C reference); that gap
is a part of the residual the members never saw.

The normaliser: its obs and action statistics are the data's as for any model; its delta
statistics are the residual's (mean: the physics' average bias, e.g. a constant drift; std:
the residual's spread), so the members' normalised target is the standardised residual and
their noise is the residual's. A dim the physics gets exactly right has delta std at the
floor (1e-6) and a zero target.

What it rules out (``TrainConfig._check_physics_rules``): the adversarial methods (rl2s, gail)
and rl2s-bc roll the learned model inside ``train_step`` (its simulated samples, the VD that
picks the worst policies); those rollouts step the members alone, which model only the
residual, so they are refused, and training runs with the VD measurement off
(``vd.every`` 0): score the hybrid with ``rl2s evaluate``. A learned reward would be fitted to
the residual and is refused. With delays, the members see at least ``max(delays)`` past
actions (``dynamics.action_history``), which the physics reads from the rollouts' ``History``.

Files: ``rl2s train --physics DIR/calibrated.json --method bc`` (app/training.py) records the
path in the config (``TrainConfig.physics``) and the calibrated.json content in every saved
step's meta (``meta["physics"]``); :func:`load_hybrid` rebuilds the hybrid from a checkpoint
alone, in a fresh process. :func:`fit_hybrid` does it all in memory.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable

import jax
import numpy as np

from rl2s_jax.model.simulator import Simulator
from rl2s_jax.physics.calibrated import physics_dynamics
from rl2s_jax.physics.mjx_model import (
    PhysicsModel,
    delayed_actions,
)
from rl2s_jax.physics.physics_simulator import checked_model
from rl2s_jax.physics.residuals import predict
from rl2s_jax.train.checkpoint import load_checkpoint
from rl2s_jax.train.config import TrainConfig

__all__ = ["read_calibrated", "calibrated_model", "hybrid_config", "residual_data",
           "physics_meta", "physics_base", "attach_physics", "load_hybrid", "fit_hybrid"]

CALIBRATED_KEYS = ("task", "xml", "n_frames", "theta", "delays")


def read_calibrated(path: str) -> dict:
    """The content of a calibrated.json (``rl2s diagnose --physics``), its keys checked."""
    if not isinstance(path, str) or not os.path.isfile(path):
        raise FileNotFoundError(f"physics: no such file {path!r} (expected the calibrated.json "
                                f"that `rl2s diagnose --physics` writes)")
    try:
        with open(path) as f:
            content = json.load(f)
    except ValueError as err:
        raise ValueError(f"physics: {path} is not JSON ({err})") from None
    missing = [k for k in CALIBRATED_KEYS
               if not isinstance(content, dict) or k not in content]
    if missing:
        raise ValueError(f"physics: {path} lacks {missing} (expected the calibrated.json of "
                         f"`rl2s diagnose --physics`: {', '.join(CALIBRATED_KEYS)})")
    return content


def calibrated_model(content: dict) -> tuple[PhysicsModel, np.ndarray, np.ndarray]:
    """A calibrated.json's content -> (PhysicsModel, theta [K], delays [A]); its "integrator"
    and "collisions" (where the diagnosis changed the model's structure; files from before
    have none). Every field checked as ``rl2s evaluate --physics`` checks it
    (``physics_simulator.checked_model``)."""
    pm, theta, delays = checked_model(content)
    return pm, np.asarray(theta, np.float64), np.asarray(delays, int)


def hybrid_config(cfg: TrainConfig, ds, content: dict | None = None) -> TrainConfig:
    """``cfg`` of a hybrid run on Dataset ``ds`` (``cfg.physics`` set): the calibrated.json
    (``content``, default read from ``cfg.physics``) checked against the data (its task and
    action count), the VD measurement off, and the members seeing at least max(delays) past
    actions (module docstring). ``validate`` then refuses what a hybrid cannot train with.
    FileNotFoundError / ValueError in one line, before any work."""
    content = read_calibrated(cfg.physics) if content is None else content
    task = ds.meta.get("task")
    if content["task"] is not None and content["task"] != task:
        raise ValueError(f"physics: {cfg.physics} calibrates task {content['task']!r} but the "
                         f"data is task {task!r}")
    delays = np.asarray(content["delays"], int)
    if delays.shape != (ds.action_size,) or (delays < 0).any():
        raise ValueError(f"physics: {cfg.physics} has delays {delays.tolist()}; the data has "
                         f"{ds.action_size} actions (expected one delay >= 0 each)")
    history = max(cfg.dynamics.action_history, int(delays.max()) if delays.size else 0)
    cfg = cfg.override({"vd.every": 0, "dynamics.action_history": history})
    cfg._check_physics_rules()  # the method first: validate's other rules assume VD
    return cfg


def residual_data(ds, physics: str | dict | None, backend: str = "mujoco"):
    """The Dataset the residual is learned from (module docstring): ``next_obs`` replaced by
    obs + (next_obs - physics(obs, a_delayed)) for every row; everything else (rewards, done
    flags, episodes, values) as logged. ``physics``: a calibrated.json path or its content
    (None: ``ds`` itself); ``backend``: "mujoco" (C, float64) or "mjx" (``predict``)."""
    if physics is None:
        return ds
    content = read_calibrated(physics) if isinstance(physics, str) else physics
    pm, theta, delays = calibrated_model(content)
    if (ds.obs_size, ds.action_size) != (pm.obs_size, pm.action_size):
        raise ValueError(f"physics: its model has obs / action sizes {pm.obs_size} / "
                         f"{pm.action_size}, the data {ds.obs_size} / {ds.action_size}")
    obs, nxt = np.asarray(ds.obs, np.float64), np.asarray(ds.next_obs, np.float64)
    action = delayed_actions(np.asarray(ds.action), np.asarray(ds.episode_id),
                             np.asarray(ds.t), delays)
    stepped = predict(pm, theta, obs, action, backend=backend)
    return ds.replace(next_obs=(obs + (nxt - stepped)).astype(np.float32))


def physics_meta(physics: str | None) -> dict:
    """What a hybrid's checkpoint meta holds beside the config: {"physics": the calibrated.json
    content} ({} for a plain run)."""
    return {} if physics is None else {"physics": read_calibrated(physics)}


def physics_base(pm: PhysicsModel, theta, delays) -> Callable:
    """The calibrated physics as a ``Simulator.base``: ``base(obs [..., O], action [..., A],
    hist) -> next_obs [..., O]`` (MJX; ``hist`` carries the past actions a delay needs)."""
    dynamics, new_history = physics_dynamics(pm, theta, delays)
    if new_history is None:
        return lambda obs, action, hist: dynamics(obs, action, None)
    return lambda obs, action, hist: dynamics(obs, action, None, hist)


def attach_physics(sim: Simulator, meta: dict) -> Simulator:
    """``sim`` (a checkpoint's members, which learned the residual) with the physics of
    ``meta["physics"]`` as its base: the hybrid. Its history must hold the delays' actions."""
    pm, theta, delays = calibrated_model(meta["physics"])
    depth = int(delays.max()) if delays.size else 0
    if depth > sim.action_history:
        raise ValueError(f"physics: delays up to {depth} steps need the simulator to carry "
                         f"as many past actions; it carries {sim.action_history}")
    return sim.replace(base=physics_base(pm, theta, delays))


def load_hybrid(directory: str, step: int | None = None) -> tuple[Simulator, dict]:
    """``(simulator, meta)`` of a checkpoint as ``load_checkpoint`` gives them, a hybrid's
    with its physics attached (any other checkpoint loads as it is)."""
    return load_checkpoint(directory, step, attach=attach_physics)


def fit_hybrid(ds, policies, physics: str | dict, *, steps: int, config: TrainConfig | None
               = None, seed: int = 0, backend: str = "mujoco", chunk: int = 10) -> Simulator:
    """The hybrid fitted in memory, no files: the residual of ``physics`` (a calibrated.json
    path or its content) on Dataset ``ds`` learned by ``steps`` train_steps of method "bc"
    (``config``: the members' settings, default ``TrainConfig.small``; its method, physics,
    vd.every and dynamics.action_history are set here). policies: ``ds``'s policies,
    stacked [P, ...].
    -> the hybrid ``Simulator`` (its ``base`` the MJX physics)."""
    # Imported here to keep `import rl2s_jax.physics` light: the training loop and its
    # optimisers load only when a hybrid is fitted.
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.loop import fit
    from rl2s_jax.train.step import init, simulator

    content = read_calibrated(physics) if isinstance(physics, str) else physics
    base = config or TrainConfig.small(task=ds.meta.get("task"))
    name = physics if isinstance(physics, str) else "<in memory>"
    cfg = hybrid_config(base.override({"method": "bc", "eps": None, "physics": name}), ds,
                        content).validate()
    data = make_train_data(residual_data(ds, content, backend), policies, cfg)
    state = jax.jit(init, static_argnums=1)(jax.random.PRNGKey(seed), cfg, data)
    state, _ = fit(state, data, steps, chunk=chunk, progress=False)
    return attach_physics(simulator(state), {"physics": content})
