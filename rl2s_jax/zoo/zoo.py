"""A zoo: stacked policies with measured returns and a train/test split; the shipped zoos.

On disk: ``<dir>/zoo.npz`` (params, flattened by path) and ``zoo.json`` (returns, origins,
split). The shipped zoos are package data under ``rl2s_jax/zoo/shipped/<task>/``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.policy.policy import Params, index_params, num_policies

ZOO_ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "shipped")
# Datasets collected before the zoos became package data name them by this repository path.
_OLD_ZOO_PREFIX = "rl2s_jax/zoo/shipped/"


@dataclasses.dataclass
class Zoo:
    """A stacked set of P policies with their measured real returns and a fixed split.

    params: stacked policy params [P, ...]; returns / return_se: [P] mean undiscounted episode
    return and its standard error (measured by ``collect.measure_values``); origins: P dicts
    (seed, iteration, env_steps); train_ids / test_ids: disjoint index lists.
    """

    task: str
    params: Params
    returns: np.ndarray
    return_se: np.ndarray
    origins: list[dict]
    train_ids: list[int]
    test_ids: list[int]
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def size(self) -> int:
        return num_policies(self.params)

    def split_ids(self, split: str) -> list[int]:
        if split == "train":
            return list(self.train_ids)
        if split == "test":
            return list(self.test_ids)
        if split == "all":
            return list(range(self.size))
        raise ValueError(f"split: expected one of 'train', 'test', 'all', got {split!r}")

    def policy_names(self, ids: Sequence[int]) -> list[str]:
        return [f"{self.task}-{i:03d}" for i in ids]


def _flatten(params: Params) -> dict[str, np.ndarray]:
    flat = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        name = "/".join(str(getattr(p, "key", getattr(p, "idx", p))) for p in path)
        flat[name] = np.asarray(leaf)
    return flat


def _unflatten(flat: dict[str, np.ndarray]) -> Params:
    n_layers = 1 + max(int(k.split("/")[1]) for k in flat if k.startswith("layers/"))
    return {"obs_mean": jnp.asarray(flat["obs_mean"]), "obs_std": jnp.asarray(flat["obs_std"]),
            "layers": [{"w": jnp.asarray(flat[f"layers/{i}/w"]),
                        "b": jnp.asarray(flat[f"layers/{i}/b"])} for i in range(n_layers)]}


def zoo_dir(task: str, root: str | None = None) -> str:
    return os.path.join(root or ZOO_ROOT, task)


def save_zoo(zoo: Zoo, directory: str) -> None:
    """Write ``zoo.npz`` (params) and ``zoo.json`` (everything else) into ``directory``."""
    if set(zoo.train_ids) & set(zoo.test_ids):
        raise ValueError("train_ids and test_ids must be disjoint")
    os.makedirs(directory, exist_ok=True)
    np.savez_compressed(os.path.join(directory, "zoo.npz"), **_flatten(zoo.params))
    meta = {"task": zoo.task, "size": zoo.size,
            "returns": [float(r) for r in zoo.returns],
            "return_se": [float(r) for r in zoo.return_se],
            "origins": zoo.origins, "train_ids": [int(i) for i in zoo.train_ids],
            "test_ids": [int(i) for i in zoo.test_ids], "info": zoo.info}
    with open(os.path.join(directory, "zoo.json"), "w") as f:
        json.dump(meta, f, indent=1)


def load_zoo(task_or_dir: str) -> Zoo:
    """Load a zoo by task name (the shipped one, package data) or by directory. A Dataset
    meta's ``rl2s_jax/zoo/shipped/<task>`` (where the shipped zoos lived before) names the shipped
    zoo of that task."""
    candidates = [task_or_dir, zoo_dir(task_or_dir)]
    norm = task_or_dir.replace(os.sep, "/").rstrip("/")
    if norm.startswith(_OLD_ZOO_PREFIX) or f"/{_OLD_ZOO_PREFIX}" in norm:
        candidates.append(zoo_dir(norm.rsplit("/", 1)[-1]))
    directory = next((c for c in candidates
                      if os.path.exists(os.path.join(c, "zoo.npz"))), candidates[0])
    npz, js = os.path.join(directory, "zoo.npz"), os.path.join(directory, "zoo.json")
    if not (os.path.exists(npz) and os.path.exists(js)):
        raise FileNotFoundError(
            f"zoo: no zoo.npz/zoo.json under {directory!r}; build one with `rl2s zoo --task T`")
    with open(js) as f:
        meta = json.load(f)
    with np.load(npz) as data:
        params = _unflatten({k: data[k] for k in data.files})
    zoo = Zoo(task=meta["task"], params=params, returns=np.asarray(meta["returns"], np.float32),
              return_se=np.asarray(meta["return_se"], np.float32), origins=meta["origins"],
              train_ids=meta["train_ids"], test_ids=meta["test_ids"], info=meta.get("info", {}))
    if zoo.size != len(zoo.returns):
        raise ValueError(f"zoo {directory}: {zoo.size} policies but {len(zoo.returns)} returns")
    return zoo


def policies_for(ds, zoo: str | None = None):
    """The stacked policies that collected ``ds``: from ``zoo`` (a directory or task name) or
    from the zoo the Dataset's meta.source names, with the source's zoo_ids."""

    source = ds.meta.get("source") or {}
    ids = source.get("zoo_ids")
    zoo = zoo or source.get("zoo")
    if zoo is None or ids is None:
        raise ValueError("zoo: the Dataset's meta.source names no zoo and zoo_ids, so the "
                         "policies that collected it are unknown; pass --zoo DIR")
    z = load_zoo(zoo)
    if max(ids) >= z.size:
        raise ValueError(f"zoo: meta.source.zoo_ids go up to {max(ids)} but {zoo} has "
                         f"{z.size} policies")
    names = ds.meta.get("policy_names")
    if names and list(names) != z.policy_names(ids):
        raise ValueError(f"zoo: policy names {z.policy_names(ids)[:3]}... of {zoo} do not "
                         f"match the Dataset's {list(names)[:3]}...")
    return index_params(z.params, np.asarray(ids))
