"""Checkpoints: orbax CheckpointManager holding, per saved step,

- ``state``: the whole TrainState (exact resume: keys, optimisers, buffers, selection);
- ``simulator``: what evaluation needs: the generator ensemble (the moving average when the
  config has ``ema_decay``), its members' ranks and the normaliser;
- ``meta``: JSON with the TrainConfig and what the data looked like (task, sizes, policy names).

``load_simulator(dir)`` rebuilds a ``Simulator`` from ``simulator`` + ``meta`` alone, in a fresh
process and without the training data. Format 3 (the ensemble model family) is written; a
format-2 checkpoint (one generator, before the family) still loads for evaluation as a
one-member ensemble, but cannot be resumed.
"""
from __future__ import annotations

import os

import jax
import numpy as np
import orbax.checkpoint as ocp

from rl2s_jax import dynamics as dyn
from rl2s_jax.models import Normalizer, init_generator
from rl2s_jax.simulate import Simulator
from rl2s_jax.train import LEGACY_MODEL, TrainConfig, TrainState, simulator

FORMAT_VERSION = 3  # 2: Normalizer.obs_input_mask; 3: the ensemble model family
ITEMS = ("state", "simulator", "meta")


def _abstract(tree):
    return jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, tree)


class Checkpointer:
    """Save and restore training checkpoints under ``directory`` (created if missing)."""

    def __init__(self, directory: str | os.PathLike, max_to_keep: int | None = 3):
        self.directory = os.path.abspath(os.fspath(directory))
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
        self._mgr = ocp.CheckpointManager(self.directory, options=options, item_names=ITEMS)

    def steps(self) -> list[int]:
        return sorted(self._mgr.all_steps())

    def latest_step(self) -> int | None:
        return self._mgr.latest_step()

    def save(self, state: TrainState, meta: dict) -> int:
        """Save ``state`` under its step (blocking). -> the step."""
        step = int(jax.device_get(state.step))
        if step in self._mgr.all_steps():
            return step
        meta = {"format_version": FORMAT_VERSION, "step": step,
                "config": state.config.to_dict(), **meta}
        sim_ = simulator(state)
        sim = {"gen": sim_.gen, "norm": sim_.norm, "rank": sim_.rank}
        self._mgr.save(step, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), simulator=ocp.args.StandardSave(sim),
            meta=ocp.args.JsonSave(meta)), force=True)
        self._mgr.wait_until_finished()
        return step

    def meta(self, step: int | None = None) -> dict:
        step = self._resolve(step)
        return self._mgr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta

    def restore(self, template: TrainState, step: int | None = None) -> TrainState:
        """The saved TrainState at ``step`` (default: latest), shaped like ``template``."""
        step = self._resolve(step)
        meta = self.meta(step)
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"checkpoint: {self.directory} holds format_version "
                f"{meta.get('format_version')!r}, this code resumes {FORMAT_VERSION} (the "
                f"ensemble model family); load_simulator still evaluates it, but training "
                f"must start in a new --out directory")
        saved = TrainConfig.from_dict(meta["config"])
        if saved != template.config:
            new = template.config.to_dict()
            diff = {k: (v, new[k]) for k, v in saved.to_dict().items() if new[k] != v}
            raise ValueError(f"config: the checkpoint in {self.directory} was trained with a "
                             f"different config (saved vs requested: {diff}); use another "
                             f"--out directory or the same settings")
        out = self._mgr.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(_abstract(template))))
        return out.state

    def _resolve(self, step: int | None) -> int:
        steps = self.steps()
        if not steps:
            raise FileNotFoundError(f"checkpoint: no saved step in {self.directory}")
        if step is None:
            return steps[-1]
        if step not in steps:
            raise FileNotFoundError(f"checkpoint: step {step} not in {self.directory} "
                                    f"(saved: {steps})")
        return step

    def close(self) -> None:
        self._mgr.close()


def load_simulator(directory: str | os.PathLike, step: int | None = None) -> Simulator:
    """The learned simulator of a checkpoint directory, without the training data."""
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"ckpt: no checkpoint directory {directory}")
    ck = Checkpointer(directory, max_to_keep=None)
    try:
        step = ck._resolve(step)
        meta = ck.meta(step)
        version = meta.get("format_version")
        if version not in (2, FORMAT_VERSION):
            raise ValueError(f"ckpt: format_version 2 or {FORMAT_VERSION} expected, got "
                             f"{version!r} in {directory}")
        o, a = int(meta["data"]["obs_size"]), int(meta["data"]["action_size"])
        norm = Normalizer.from_data(np.zeros((2, o)), np.zeros((2, a)), np.zeros((2, o)))
        if version == 2:  # one generator (a list of layers), trained before the family
            cfg = TrainConfig.from_dict({**meta["config"], **LEGACY_MODEL})
            template = jax.eval_shape(lambda: {
                "gen": init_generator(jax.random.PRNGKey(0), o, a, cfg.gen_hidden),
                "norm": norm})
        else:
            cfg = TrainConfig.from_dict(meta["config"])
            template = jax.eval_shape(lambda: {
                "gen": dyn.init_ensemble(jax.random.PRNGKey(0), cfg.dynamics_spec, o, a,
                                         cfg.ensemble_size),
                "norm": norm, "rank": jax.numpy.zeros((cfg.ensemble_size,), jax.numpy.int32)})
        sim = ck._mgr.restore(step, args=ocp.args.Composite(
            simulator=ocp.args.StandardRestore(template))).simulator
    finally:
        ck.close()
    return Simulator(gen=sim["gen"], norm=sim["norm"], rank=sim.get("rank"), task=cfg.task,
                     obs_clip=cfg.obs_clip, noise_scale=cfg.sim_noise, n_elites=cfg.n_elites,
                     member_mode=cfg.member_mode, uncertainty=cfg.uncertainty)


def load_meta(directory: str | os.PathLike, step: int | None = None) -> dict:
    """The JSON meta of a checkpoint: config, data description, step."""
    ck = Checkpointer(directory, max_to_keep=None)
    try:
        return ck.meta(step)
    finally:
        ck.close()
