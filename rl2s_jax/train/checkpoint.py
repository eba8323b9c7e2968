"""Checkpoints: orbax CheckpointManager holding, per saved step,

- ``state``: the whole TrainState (exact resume: keys, optimisers, buffers, selection);
- ``simulator``: what evaluation needs: the generator ensemble (the moving average when the
  config has ``ema_decay``), its members' ranks and the normaliser, the learned
  termination hazard where the config's ``termination`` uses one and the learned reward head
  where its ``reward`` is "learned";
- ``meta``: JSON with the TrainConfig and what the data looked like (task, sizes, policy names).

``load_simulator(dir)`` rebuilds a ``Simulator`` from ``simulator`` + ``meta`` alone, in a fresh
process and without the training data. Format 3 (the ensemble model family) is written; a
format-2 checkpoint (one generator, before the family) still loads for evaluation as a
one-member ensemble, but cannot be resumed.

Broken steps (a truncated JSON file, a missing or truncated array file, a missing item): every
load names the step and what is wrong with it. Without an explicit step, loads (evaluation and
the training resume alike) fall back to the newest intact step and say so with a
:class:`CheckpointWarning`; an explicitly requested broken step, or a directory without any
intact step, raises :class:`CheckpointError`.
"""
from __future__ import annotations

import ast
import dataclasses
import json
import os
import re
import shutil
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import TypeVar

import jax
import numpy as np
import orbax.checkpoint as ocp

from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.generator import init_generator
from rl2s_jax.model.reward import init_reward
from rl2s_jax.model.simulator import Simulator
from rl2s_jax.model.termination import LEARNED, init_hazard
from rl2s_jax.train.config import LEGACY_MODEL, TrainConfig
from rl2s_jax.train.step import TrainState, simulator

FORMAT_VERSION = 3  # 2: Normalizer.obs_input_mask; 3: the ensemble model family
ITEMS = ("state", "simulator", "meta")
META_KEYS = ("format_version", "step", "config")

T = TypeVar("T")


class CheckpointError(ValueError):
    """A checkpoint cannot be used: the requested step is broken, no step is intact, or it was
    written by another config or format."""


class CheckpointWarning(UserWarning):
    """Broken steps were skipped in favour of the newest intact one."""


class _Broken(Exception):
    """Internal: this step's files are damaged (the message says how)."""


def _abstract(tree):
    return jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, tree)


def _uncommitted(tree):
    """The restored arrays as a fresh run holds them: uncommitted, on the default device.

    orbax commits each restored array to its device, and jit lowers a committed argument with
    a sharding annotation that an uncommitted one lacks: a resumed run (or a loaded simulator)
    would compile every program anew, for the in-memory and the persistent compilation cache
    alike, rather than reuse what the fresh run compiled (~12 s per train program on the
    CPU). Arrays placed on several devices keep their placement."""
    def leaf(x):
        if (isinstance(x, jax.Array) and len(x.sharding.device_set) == 1
                and not jax.dtypes.issubdtype(x.dtype, jax.dtypes.extended)):
            return jax.device_put(np.asarray(x))
        return x
    return jax.tree_util.tree_map(leaf, tree)


class Checkpointer:
    """Save and restore training checkpoints under ``directory`` (created if missing unless
    ``create=False``).

    ``broken`` maps each step found broken so far to what is wrong with it.
    """

    def __init__(self, directory: str | os.PathLike, max_to_keep: int | None = 3, *,
                 create: bool = True):
        self.directory = os.path.abspath(os.fspath(directory))
        self._options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=create)
        self._mgr = self._manager()
        self.broken: dict[int, str] = {}

    def _manager(self) -> ocp.CheckpointManager:
        return ocp.CheckpointManager(self.directory, options=self._options, item_names=ITEMS)

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
        if sim_.hazard is not None:
            sim["hazard"] = sim_.hazard
        if sim_.reward is not None:
            sim["reward"] = sim_.reward
        self._mgr.save(step, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), simulator=ocp.args.StandardSave(sim),
            meta=ocp.args.JsonSave(meta)), force=True)
        self._mgr.wait_until_finished()
        return step

    # ----------------------------------------------------------------- loading with fallback

    def meta(self, step: int | None = None) -> dict:
        """The JSON meta of ``step`` (default: the newest step whose meta is intact)."""
        return self.load_intact(step, ("meta",), self._read_meta)[1]

    def restore(self, template: TrainState, step: int | None = None) -> TrainState:
        """The saved TrainState at ``step`` (default: the newest intact step), shaped like
        ``template``. Raises CheckpointError if it was trained with another config."""
        def load(s: int) -> TrainState:
            version = self._read_meta(s).get("format_version")
            if version != FORMAT_VERSION:
                raise CheckpointError(
                    f"checkpoint: {self.directory} step {s} holds format_version {version!r}, "
                    f"this code resumes {FORMAT_VERSION} (the ensemble model family); "
                    f"load_simulator still evaluates it, but training must start in a new "
                    f"--out directory")
            saved = self._config(s)
            if saved != template.config:
                new = template.config.to_dotted()
                diff = {k: (v, new[k]) for k, v in saved.to_dotted().items() if new[k] != v}
                raise CheckpointError(
                    f"config: the checkpoint in {self.directory} was trained with a different "
                    f"config (saved vs requested: {diff}); use another --out directory or the "
                    f"same settings")
            absent = self._fields_saved_without(s, template)
            if not absent:
                return self._restore_item(s, "state",
                                          ocp.args.StandardRestore(_abstract(template)))
            # a state saved before these fields existed (each None in the template): restore
            # the saved fields by name, keep the template's None for the others
            fields = {f.name: getattr(template, f.name) for f in dataclasses.fields(template)
                      if f.metadata.get("pytree_node", True) and f.name not in absent}
            restored = self._restore_item(s, "state", ocp.args.StandardRestore(
                _abstract(fields)))
            return template.replace(**restored)

        return self.load_intact(step, ("meta", "state"), load)[1]

    def _fields_saved_without(self, step: int, template: TrainState) -> set[str]:
        """The TrainState fields that the saved state of ``step`` lacks (it was saved before
        they were added) and that are None in ``template``, so that restoring without them
        loses nothing. Empty when the state's tree metadata cannot be read (the restore then
        names the damage)."""
        try:
            with open(os.path.join(self.directory, str(step), "state", "_METADATA")) as f:
                keys = json.load(f)["tree_metadata"]
            saved = {ast.literal_eval(k)[0] for k in keys}  # keys: "('gen', 'layers', ...)"
        except (OSError, ValueError, KeyError, TypeError, IndexError, SyntaxError):
            return set()
        return {f.name for f in dataclasses.fields(template)
                if f.metadata.get("pytree_node", True) and f.name not in saved
                and getattr(template, f.name) is None}

    def load_intact(self, step: int | None, items: Sequence[str], load: Callable[[int], T]
                    ) -> tuple[int, T]:
        """``(step, load(step))`` for ``step``, or without one for the newest step whose
        ``items`` are intact and load; skipped steps are named in one CheckpointWarning.

        A step is broken when an item's files fail the checks of :meth:`problem` or
        ``load`` fails to read them; CheckpointError from ``load`` (another config or
        format: not damage) is raised as it is.
        """
        steps = self.steps()
        if not steps:
            raise FileNotFoundError(f"checkpoint: no saved step in {self.directory}")
        if step is not None:
            if step not in steps:
                raise FileNotFoundError(f"checkpoint: step {step} not in {self.directory} "
                                        f"(saved: {steps})")
            value, why = self._try(step, items, load)
            if why is None:
                return step, value
            raise CheckpointError(f"checkpoint {self.directory}: step {step} is broken: {why} "
                                  f"(saved steps: {steps}; leave out the step to use the "
                                  f"newest intact one)")
        skipped: list[tuple[int, str]] = []
        for s in reversed(steps):
            value, why = self._try(s, items, load)
            if why is None:
                if skipped:
                    warnings.warn(_fallback_message(self.directory, skipped, s),
                                  CheckpointWarning, stacklevel=3)
                return s, value
            skipped.append((s, why))
        raise CheckpointError(f"checkpoint {self.directory}: no intact step: "
                              + "; ".join(f"step {s}: {why}" for s, why in skipped))

    def _try(self, step: int, items: Sequence[str], load: Callable[[int], T]
             ) -> tuple[T | None, str | None]:
        why = self.problem(step, items)
        if why is None:
            try:
                return load(step), None
            except CheckpointError:
                raise
            except _Broken as e:
                why = str(e)
            except Exception as e:  # orbax / tensorstore errors of damaged files vary widely
                why = _describe(e, os.path.join(self.directory, str(step)))
        self.broken[step] = why
        return None, why

    def problem(self, step: int, items: Sequence[str] = ITEMS) -> str | None:
        """What is visibly wrong with the files of ``items`` at ``step``, or None (then only
        reading the arrays can tell: see :meth:`load_intact`)."""
        root = os.path.join(self.directory, str(step))
        for item in items:
            path = os.path.join(root, item)
            if not os.path.isdir(path):
                return f"{item}/ is missing"
            for name in ("metadata", "_METADATA"):
                file = os.path.join(path, name)
                if not os.path.isfile(file):
                    continue
                try:
                    with open(file, "rb") as f:
                        json.loads(f.read().decode("utf-8"))
                except (ValueError, UnicodeDecodeError) as e:
                    return (f"{item}/{name} is not valid JSON ({e}; "
                            f"{os.path.getsize(file)} bytes)")
            if (any(n.startswith("ocdbt.process_") for n in os.listdir(path))
                    and not os.path.isfile(os.path.join(path, "manifest.ocdbt"))):
                return f"{item}/manifest.ocdbt is missing"
        return None

    def _read_meta(self, step: int) -> dict:
        meta = self._restore_item(step, "meta", ocp.args.JsonRestore())
        if not isinstance(meta, dict):
            raise _Broken(f"meta/metadata holds {type(meta).__name__}, not a JSON object")
        missing = [k for k in META_KEYS if k not in meta]
        if missing:
            raise _Broken(f"meta/metadata lacks {missing}")
        if meta["format_version"] not in (2, FORMAT_VERSION):  # 2 loads for evaluation only
            raise CheckpointError(f"ckpt: format_version 2 or {FORMAT_VERSION} expected, got "
                                  f"{meta['format_version']!r} in {self.directory} step {step}")
        return meta

    def _config(self, step: int) -> TrainConfig:
        try:
            return TrainConfig.from_saved(self._read_meta(step)["config"])
        except (TypeError, ValueError) as e:
            raise _Broken(f"meta/metadata holds an unreadable config ({e})") from None

    def _restore_item(self, step: int, item: str, args):
        try:
            return _uncommitted(getattr(
                self._mgr.restore(step, args=ocp.args.Composite(**{item: args})), item))
        except CheckpointError:
            raise
        except Exception as e:
            _drop_closed_loop_noise()
            raise _Broken(_describe(e, os.path.join(self.directory, str(step)), item)) from None

    # ----------------------------------------------------------------- resuming from a step

    def set_aside_after(self, step: int) -> dict[str, list[int]]:
        """Move every saved step after ``step`` out of the way of a run resumed from ``step``
        (which saves those step numbers anew): broken ones to ``corrupt/``, intact ones to
        ``superseded/`` under the directory. -> {"corrupt": [...], "superseded": [...]}."""
        moved: dict[str, list[int]] = {"corrupt": [], "superseded": []}
        later = [s for s in self.steps() if s > step]
        if not later:
            return moved
        self._mgr.close()
        for s in later:
            kind = "corrupt" if s in self.broken else "superseded"
            dest_dir = os.path.join(self.directory, kind)
            os.makedirs(dest_dir, exist_ok=True)
            dest, n = os.path.join(dest_dir, str(s)), 1
            while os.path.exists(dest):
                dest, n = os.path.join(dest_dir, f"{s}-{n}"), n + 1
            shutil.move(os.path.join(self.directory, str(s)), dest)
            moved[kind].append(s)
        self._mgr = self._manager()
        return moved

    def close(self) -> None:
        self._mgr.close()


def _fallback_message(directory: str, skipped: list[tuple[int, str]], used: int) -> str:
    which = ", ".join(str(s) for s, _ in skipped)
    noun = "step" if len(skipped) == 1 else "steps"
    why = "; ".join(f"step {s}: {w}" for s, w in skipped)
    return (f"checkpoint {directory}: broken {noun} {which} skipped ({why}); using step "
            f"{used}, the newest intact step")


def _describe(err: Exception, step_dir: str, item: str | None = None) -> str:
    """A one-line account of an orbax / tensorstore read error (their messages run to pages)."""
    text = str(err).strip()
    first = text.splitlines()[0] if text else ""
    for cut in (" [tensorstore_spec", ". See full TensorStore details", " See full TensorStore",
                " in OCDBT database"):
        first = first.split(cut)[0]
    if len(first) > 160:
        first = first[:160] + "..."
    files = re.findall(r'local file "([^"]+)"', text)
    where = f"; file {os.path.relpath(files[-1], step_dir)}" if files else ""
    label = f"{item} cannot be read" if item else "cannot be read"
    return f"{label} ({type(err).__name__}: {first}{where})"


_closed_loop_filter_installed = False


def _drop_closed_loop_noise() -> None:
    """After a failed orbax read, tensorstore's threads keep completing futures of the closed
    asyncio loop, and each failure prints a "RuntimeError: Event loop is closed" traceback
    through ``sys.unraisablehook``. Drop exactly those; pass everything else on."""
    global _closed_loop_filter_installed
    if _closed_loop_filter_installed:
        return
    previous = sys.unraisablehook

    def hook(unraisable):
        exc = unraisable.exc_value
        if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed":
            return
        previous(unraisable)

    sys.unraisablehook = hook
    _closed_loop_filter_installed = True


def load_checkpoint(directory: str | os.PathLike, step: int | None = None, *,
                    attach: Callable[[Simulator, dict], Simulator] | None = None
                    ) -> tuple[Simulator, dict]:
    """``(simulator, meta)`` of ``step`` of a checkpoint directory (default: the newest step
    whose meta and simulator are intact; broken newer ones are skipped with a
    CheckpointWarning). ``meta["step"]`` is the step loaded. No training data needed.

    A hybrid's checkpoint (``meta["physics"]``: calibrated physics plus a learned residual)
    needs ``attach(simulator, meta) -> simulator`` to rebuild its physics, which lives above
    this layer (``rl2s_jax.physics.hybrid.load_hybrid`` passes it); without it the load is
    refused, since its members alone model only the residual."""
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"ckpt: no checkpoint directory {directory}")
    ck = Checkpointer(directory, max_to_keep=None, create=False)

    def load(s: int) -> tuple[Simulator, dict]:
        meta = ck._read_meta(s)
        version = meta.get("format_version")
        if version not in (2, FORMAT_VERSION):
            raise CheckpointError(f"ckpt: format_version 2 or {FORMAT_VERSION} expected, got "
                                  f"{version!r} in {directory} step {s}")
        if version == 2:  # one generator (a list of layers), trained before the family
            cfg = TrainConfig.from_saved(meta["config"]).override(LEGACY_MODEL)
        else:
            cfg = ck._config(s)
        try:
            o, a = int(meta["data"]["obs_size"]), int(meta["data"]["action_size"])
        except (KeyError, TypeError, ValueError):
            raise _Broken("meta/metadata lacks data.obs_size / data.action_size") from None
        norm = Normalizer.from_data(np.zeros((2, o)), np.zeros((2, a)), np.zeros((2, o)))
        if version == 2:
            template = jax.eval_shape(lambda: {
                "gen": init_generator(jax.random.PRNGKey(0), o, a, cfg.dynamics.hidden),
                "norm": norm})
        else:
            template = jax.eval_shape(lambda: {
                "gen": dyn.init_ensemble(jax.random.PRNGKey(0), cfg.dynamics, o, a,
                                         cfg.ensemble_size),
                "norm": norm, "rank": jax.numpy.zeros((cfg.ensemble_size,), jax.numpy.int32),
                **({"hazard": init_hazard(jax.random.PRNGKey(0), o, a, cfg.outcome.hazard_hidden)}
                   if cfg.outcome.termination in LEARNED else {}),
                **({"reward": init_reward(jax.random.PRNGKey(0), o, a, cfg.outcome.reward_hidden)}
                   if cfg.outcome.reward == "learned" else {})})
        sim = ck._restore_item(s, "simulator", ocp.args.StandardRestore(template))
        return Simulator(gen=sim["gen"], norm=sim["norm"], rank=sim.get("rank"),
                         hazard=sim.get("hazard"), reward=sim.get("reward"),
                         **cfg.simulator_settings()), meta

    try:
        sim, meta = ck.load_intact(step, ("meta", "simulator"), load)[1]
    finally:
        ck.close()
    if meta.get("physics") is None:
        return sim, meta
    if attach is None:  # after the load: a failing attach is not a broken step
        raise CheckpointError(
            f"ckpt: {directory} is a hybrid (calibrated physics plus a learned residual, "
            f"meta.physics); its members alone model only the residual: load it with "
            f"rl2s_jax.physics.hybrid.load_hybrid (rl2s evaluate does)")
    return attach(sim, meta), meta


def load_simulator(directory: str | os.PathLike, step: int | None = None) -> Simulator:
    """The learned simulator of a checkpoint directory, without the training data (see
    :func:`load_checkpoint` for the choice of step)."""
    return load_checkpoint(directory, step)[0]


def load_meta(directory: str | os.PathLike, step: int | None = None) -> dict:
    """The JSON meta of a checkpoint: config, data description, step; of the same step that
    :func:`load_simulator` loads (a hybrid's too)."""
    return load_checkpoint(directory, step, attach=lambda sim, _: sim)[1]
