"""Minari datasets in and out: :func:`from_minari` reads a local Minari dataset into a
:class:`~rl2s_jax.data.Dataset` (validated like any Dataset), :func:`to_minari` writes a
Dataset as a Minari dataset. The mapping is in docs/DATA.md ("Minari"). Nothing is downloaded.

A Minari episode of T steps holds observations [T + 1, ...], actions [T, ...], rewards,
terminations and truncations [T]; ours holds the same transitions as T rows of
(obs, action, next_obs, reward, done, truncated) with t = 0 .. T-1. The policy of each
episode comes from its episode metadata (``policy_id`` or ``policy_name``, or the key given)
and is one policy when there is none. What Minari has no field for (task, gamma, true values,
policy names, episode ids) travels in the dataset metadata key ``rl2s_jax`` and per-episode
metadata, so Dataset -> Minari -> Dataset gives back the same Dataset. An export of a registered
task's data names its real env as the dataset's ``env_spec`` (:func:`task_env_spec`).

Python-side NumPy with one loop over episodes (file I/O, not a hot path).
"""
from __future__ import annotations

import json
import os
import re
import shutil
from typing import Any

import numpy as np

from rl2s_jax.data.dataset import (
    TRANSITION_FIELDS,
    VALUE_FIELDS,
    Dataset,
    DatasetError,
    TaskSizes,
    validate_dataset,
)
from rl2s_jax.envs.tasks import BUILT_IN, TASKS, data_task

__all__ = ["from_minari", "to_minari", "task_env_spec", "POLICY_KEYS"]

#: Episode-metadata keys read for the policy of an episode, in this order (first one present).
POLICY_KEYS = ("policy_id", "policy_name", "policy")
_RL2S_KEY = "rl2s_jax"  # dataset metadata written by to_minari
_EPISODE_ID_KEY = "rl2s_episode_id"  # our episode label (Minari numbers episodes 0, 1, ...)
_DATASET_ID = re.compile(r"^(?:[-_\w][-_\w/]*[-_\w]+/)?[-_\w]+?-v\d+$")
# The real env of a registered task as Gymnasium makes it: the entry point that
# rl2s_jax.improve.gym_env registers as "rl2s/<task>-v0" (named, not imported: a layer above).
_TASK_ENTRY_POINT = "rl2s_jax.improve.gym_env:TaskGymEnv"


def _minari():
    # Imported here to keep start-up fast: minari (h5py, pydantic) is only for `rl2s import`
    # and `rl2s export`.
    try:
        import minari
        from minari.data_collector import EpisodeBuffer
        from minari.dataset.minari_storage import MinariStorage
    except ImportError as e:  # pragma: no cover - a core dependency
        raise ImportError(f"minari: not installed ({e}); pip install 'minari[hdf5]'") from e
    return minari, MinariStorage, EpisodeBuffer


# --------------------------------------------------------------------------- Minari -> ours


def from_minari(source, *, task: str | None = None, gamma: float | None = None,
                policy_key: str | None = None, task_sizes: TaskSizes | None = None) -> Dataset:
    """A Dataset of a local Minari dataset.

    Args:
      source: a ``minari.MinariDataset``, a dataset directory (holding ``data/metadata.json``),
        its ``data/`` directory, or the id of a dataset in the local Minari root
        (``$MINARI_DATASETS_PATH`` or ``~/.minari/datasets``). Never downloads.
      task: the registered task the data comes from (meta.task; sizes are checked); default:
        the one an rl2s_jax export recorded, else None.
      gamma: meta.gamma; default: the one an export recorded, else None.
      policy_key: the episode-metadata key naming each episode's policy (int ids or names);
        default: the first of :data:`POLICY_KEYS` present, else all episodes are one policy.

    Observations and actions must be Box spaces (flattened to vectors, cast to float32);
    a step both terminated and truncated becomes ``done`` (our rows never carry both).
    Raises DatasetError naming what is wrong.
    """
    data_task(task, where="task", remedy="or leave --task out (data of no task: the reward "
              "and termination are learned from it)")  # before any work
    minari = _minari()[0]
    label = str(source) if not isinstance(source, minari.MinariDataset) else source.id
    mds = source if isinstance(source, minari.MinariDataset) else _open(source)
    try:
        return _from_minari(mds, task=task, gamma=gamma, policy_key=policy_key,
                            task_sizes=task_sizes, label=label)
    except DatasetError as e:
        raise e.with_path(label) from None


def _open(source):
    """The MinariDataset at a path or of a local dataset id (no download)."""
    minari = _minari()[0]
    path = os.fspath(source)
    candidates = [path, os.path.join(path, "data")]
    if not os.path.isabs(path) and not os.path.exists(path):
        root = os.environ.get("MINARI_DATASETS_PATH") or os.path.join(
            os.path.expanduser("~"), ".minari", "datasets")
        candidates.append(os.path.join(root, path, "data"))
    for c in candidates:
        if os.path.isfile(os.path.join(c, "metadata.json")):
            try:
                return minari.MinariDataset(c)
            except ImportError as e:
                raise DatasetError("minari", "a dataset whose storage format is installed",
                                   str(e), path=c) from None
            except (ValueError, KeyError, AssertionError, OSError) as e:
                raise DatasetError("minari", "a readable Minari dataset",
                                   f"{type(e).__name__}: {e}", path=c) from None
    raise DatasetError(None, "a Minari dataset directory (holding data/metadata.json), its "
                       "data/ directory, or the id of a dataset in the local Minari root",
                       "none of these", path=path,
                       hint="rl2s never downloads; fetch it first, e.g. "
                            "`minari download ID`")


def _box_size(space, what: str) -> int:
    import gymnasium as gym  # local: start-up (interop only)

    if not isinstance(space, gym.spaces.Box):
        raise DatasetError(f"minari.{what}", "a Box space (vectors of floats)",
                           f"{type(space).__name__} {space}")
    return int(np.prod(space.shape, dtype=np.int64))


def _from_minari(mds, *, task, gamma, policy_key, task_sizes, label) -> Dataset:
    info = mds.storage.metadata
    obs_size = _box_size(mds.observation_space, "observation_space")
    action_size = _box_size(mds.action_space, "action_space")
    episodes = list(mds.iterate_episodes())
    if not episodes:
        raise DatasetError("minari", "at least one episode", "an empty dataset (0 episodes)")
    ep_meta = list(mds.storage.get_episode_metadata(mds.episode_indices))
    rows: dict[str, list[np.ndarray]] = {k: [] for k in TRANSITION_FIELDS if k != "policy_id"}
    for ep, m in zip(episodes, ep_meta, strict=True):
        steps = len(ep)
        obs = np.asarray(ep.observations)
        if steps == 0 or obs.shape[0] != steps + 1:
            raise DatasetError("minari.observations", f"T + 1 = {steps + 1} rows in episode "
                               f"{ep.id} (it has T = {steps} actions)", f"{obs.shape[0]}")
        obs = obs.reshape(steps + 1, obs_size).astype(np.float32)
        term = np.asarray(ep.terminations, bool).reshape(steps)
        trunc = np.asarray(ep.truncations, bool).reshape(steps)
        rows["obs"].append(obs[:-1])
        rows["next_obs"].append(obs[1:])
        rows["action"].append(np.asarray(ep.actions).reshape(steps, action_size)
                              .astype(np.float32))
        rows["reward"].append(np.asarray(ep.rewards).reshape(steps).astype(np.float32))
        rows["done"].append(term)
        rows["truncated"].append(trunc & ~term)
        rows["episode_id"].append(np.full(steps, int(m.get(_EPISODE_ID_KEY, ep.id)), np.int64))
        rows["t"].append(np.arange(steps, dtype=np.int32))
    arrays: dict[str, Any] = {k: np.concatenate(v) for k, v in rows.items()}
    saved = info.get(_RL2S_KEY) or {}
    saved_meta = saved.get("meta") or {}
    ep_policy, names = _episode_policies(ep_meta, [e.id for e in episodes], policy_key,
                                         saved_meta.get("policy_names"),
                                         info.get("algorithm_name") or mds.id)
    arrays["policy_id"] = np.repeat(ep_policy, [len(e) for e in episodes])
    spec = mds.env_spec
    limit = saved_meta.get("episode_length", spec.max_episode_steps if spec else None)
    if limit is not None and int(arrays["t"].max()) >= int(limit):
        limit = None  # the episodes ran past the env's time limit: it does not bound them
    # An export's own source (zoo, zoo_ids: how `rl2s train` finds the policies) is kept.
    source = dict(saved_meta.get("source") or {})
    source["minari"] = {"dataset_id": mds.id,
                        "path": os.path.abspath(os.fspath(mds.storage.data_path)),
                        "minari_version": info.get("minari_version"),
                        "env_id": spec.id if spec else None,
                        "algorithm_name": info.get("algorithm_name")}
    meta = {**saved_meta,
            "task": task if task is not None else saved_meta.get("task"),
            "obs_size": obs_size, "action_size": action_size, "n_policies": len(names),
            "gamma": gamma if gamma is not None else saved_meta.get("gamma"),
            "episode_length": None if limit is None else int(limit),
            "policy_names": names, "source": source}
    values = saved.get("values") or {}
    if values and len(values.get("value", [])) == len(names):
        arrays.update({k: np.asarray(values[k], np.float32) for k in VALUE_FIELDS})
    return Dataset.from_arrays(arrays, meta, task_sizes=task_sizes)


def _episode_policies(ep_meta: list[dict], ep_ids: list[int], policy_key: str | None,
                      saved_names: list[str] | None, default_name: str
                      ) -> tuple[np.ndarray, list[str]]:
    """(policy id of each episode [E], policy names [P]) from the episode metadata."""
    if policy_key is None:
        policy_key = next((k for k in POLICY_KEYS if k in ep_meta[0]), None)
        if policy_key is None:
            return np.zeros(len(ep_meta), np.int64), [str(default_name)]
    missing = [i for i, m in enumerate(ep_meta) if policy_key not in m]
    if missing:
        raise DatasetError(f"minari.episode_metadata.{policy_key}", "on every episode (or "
                           "on none: then the data is one policy)",
                           f"missing on {len(missing)} of {len(ep_meta)} episodes, the first "
                           f"episode {ep_ids[missing[0]]}")
    values = [m[policy_key] for m in ep_meta]
    if all(isinstance(v, int | np.integer) and not isinstance(v, bool) for v in values):
        ids = np.asarray(values, np.int64)
        if ids.min() < 0:
            i = int(np.argmin(ids))
            raise DatasetError(f"minari.episode_metadata.{policy_key}", "policy ids >= 0",
                               f"{ids[i]} on episode {ep_ids[i]}")
        n = int(ids.max()) + 1
        if saved_names is not None and len(saved_names) >= n:
            return ids, list(saved_names)
        names = [str(i) for i in range(n)]
        for i, m in zip(ids, ep_meta, strict=True):  # names from policy_name where given
            if "policy_name" in m:
                names[i] = str(m["policy_name"])
        return ids, names
    text = [v.decode() if isinstance(v, bytes) else str(v) for v in values]
    names = list(dict.fromkeys(text))  # in order of first appearance
    index = {n: i for i, n in enumerate(names)}
    return np.asarray([index[v] for v in text], np.int64), names


# --------------------------------------------------------------------------- ours -> Minari


def task_env_spec(meta: dict):
    """The Gymnasium ``EnvSpec`` of the env a Dataset of a registered task was collected in,
    from its ``meta``: id ``"rl2s/<task>-v0"`` (registered by ``rl2s_jax.improve.gym_env``),
    entry point ``TaskGymEnv`` with ``kwargs={"task": <task>}``, ``max_episode_steps`` the
    data's ``episode_length`` (the task's when meta has none). None for data of no built-in
    task (one registered from Python exists only in its process). ``gymnasium.make(spec)``
    builds it (``minari``'s ``recover_environment`` too)."""
    from gymnasium.envs.registration import EnvSpec  # local: start-up (interop only)

    task = meta.get("task")
    if task not in BUILT_IN:  # a task registered from Python exists in its process only
        return None
    limit = meta.get("episode_length") or TASKS[task].episode_length
    return EnvSpec(id=f"rl2s/{task}-v0", entry_point=_TASK_ENTRY_POINT,
                   max_episode_steps=int(limit), kwargs={"task": task})


def to_minari(ds: Dataset, path: str | os.PathLike, *, dataset_id: str | None = None,
              author: str | None = None, description: str | None = None):
    """Write ``ds`` as a Minari dataset (hdf5) into the new directory ``path`` (its
    ``data/`` holds metadata.json and main_data.hdf5). -> the ``minari.MinariDataset``.

    ``dataset_id`` defaults to the directory name (with ``-v0`` appended when it has no
    version). Put ``path`` at ``$MINARI_DATASETS_PATH/<dataset_id>`` for
    ``minari.load_dataset(dataset_id)`` to find it. Minari keeps each episode's observations
    once, so ``next_obs`` of a row must equal ``obs`` of the episode's next row (true for data
    from ``rl2s collect``); otherwise DatasetError names the first row where they differ.
    Data of a registered task (``meta.task``) gets the dataset metadata ``env_spec`` of
    :func:`task_env_spec`; other data has none.
    """
    import gymnasium as gym  # local: start-up (interop only)

    minari, MinariStorage, EpisodeBuffer = _minari()
    validate_dataset(ds)
    path = os.path.abspath(os.fspath(path))
    if os.path.exists(path) and (not os.path.isdir(path) or os.listdir(path)):
        raise DatasetError(None, "a new or empty directory to write the Minari dataset into",
                           "an existing file or non-empty directory", path=path)
    dataset_id = dataset_id or _default_id(os.path.basename(path))
    if not _DATASET_ID.match(dataset_id):
        raise DatasetError("dataset_id", "(namespace/)name-vN, e.g. 'rl2s/hopper-v0'",
                           repr(dataset_id))
    a = ds.arrays()
    obs, next_obs, ep = a["obs"], a["next_obs"], a["episode_id"]
    starts = np.flatnonzero(np.r_[True, ep[1:] != ep[:-1]])
    ends = np.r_[starts[1:], len(ep)]
    same_episode = ep[1:] == ep[:-1]
    differs = same_episode & np.any(next_obs[:-1] != obs[1:], axis=1)
    if differs.any():
        i = int(np.flatnonzero(differs)[0])
        raise DatasetError("next_obs", "next_obs[i] == obs[i + 1] within an episode (Minari "
                           "stores each episode's observations once)",
                           f"they differ at row {i} (episode {ep[i]})")
    high = 1.0 if np.all(np.abs(a["action"]) <= 1.0) else np.inf
    obs_space = gym.spaces.Box(-np.inf, np.inf, (ds.obs_size,), np.float32)
    act_space = gym.spaces.Box(-high, high, (ds.action_size,), np.float32)

    buffers, ep_meta = [], []
    names = ds.meta["policy_names"]
    for k, (lo, hi) in enumerate(zip(starts, ends, strict=True)):
        buffers.append(EpisodeBuffer(
            id=k, observations=np.concatenate([obs[lo:hi], next_obs[hi - 1:hi]]),
            actions=a["action"][lo:hi], rewards=a["reward"][lo:hi],
            terminations=a["done"][lo:hi], truncations=a["truncated"][lo:hi], infos={}))
        p = int(a["policy_id"][lo])
        ep_meta.append({"policy_id": p, "policy_name": str(names[p]),
                        _EPISODE_ID_KEY: int(ep[lo])})
    rl2s = {"meta": ds.meta,
            "values": {k: a[k].tolist() for k in VALUE_FIELDS if k in a}}
    info = {"dataset_id": dataset_id, "minari_version": minari.__version__,
            "algorithm_name": "rl2s_jax", "description": description or (
                f"exported by rl2s_jax from a Dataset of task {ds.meta.get('task')!r}: "
                f"{ds.n_transitions} transitions of {ds.n_policies} policies"),
            _RL2S_KEY: json.loads(json.dumps(rl2s))}
    if author:
        info["author"] = {author}
    tmp = f"{path}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        os.makedirs(os.path.join(tmp, "data"))
        storage = MinariStorage.new(os.path.join(tmp, "data"), observation_space=obs_space,
                                    action_space=act_space, env_spec=task_env_spec(ds.meta),
                                    data_format="hdf5")
        storage.update_metadata(info)
        storage.update_episodes(buffers)
        storage.update_episode_metadata(ep_meta)
        if os.path.isdir(path):
            os.rmdir(path)  # checked empty above
        os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return minari.MinariDataset(os.path.join(path, "data"))


def _default_id(name: str) -> str:
    name = re.sub(r"[^-\w]", "_", name) or "rl2s"
    return name if re.search(r"-v\d+$", name) else f"{name}-v0"
