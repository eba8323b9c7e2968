"""A zoo: stacked policies with measured returns and a train/test split; the shipped zoos.

On disk: ``<dir>/zoo.npz`` (params, flattened by path) and ``zoo.json`` (returns, origins,
split). The shipped zoos are package data under ``rl2s_jax/zoo/shipped/<task>/``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections import Counter
from collections.abc import Sequence

import numpy as np

from rl2s_jax._files import atomic_open, write_json
from rl2s_jax.policy.policy import (
    Params,
    flatten_params,
    index_params,
    load_policies,
    num_policies,
    unflatten_params,
)
from rl2s_jax.zoo.likelihood import warn_if_mismatched

ZOO_ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "shipped")
# The "validation" split: every VALIDATION_EVERY-th training policy by return (from the
# middle of each group), held out of the training policies ("fit": the rest), so a recipe
# can be chosen on policies the simulator never saw without touching the test policies.
VALIDATION_EVERY = 4
# Datasets collected before the zoos became package data name them by this repository path.
_OLD_ZOO_PREFIX = "rl2s_jax/zoo/shipped/"


@dataclasses.dataclass
class Zoo:
    """A stacked set of P policies with their measured real returns and a fixed split.

    params: stacked policy params [P, ...]; returns / return_se: [P] mean undiscounted episode
    return and its standard error (measured by ``collect.measure_values``); origins: P dicts
    (seed, iteration, env_steps); train_ids / test_ids: disjoint index lists. ``split_ids``
    also serves "fit" / "validation": the training policies split again (VALIDATION_EVERY),
    and "lineage-fit" / "lineage-validation": one learner lineage of them held out
    (``held_out_lineage``).
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
        if split in ("fit", "validation"):
            by_return = sorted(self.train_ids, key=lambda i: (self.returns[i], i))
            held = set(by_return[VALIDATION_EVERY // 2::VALIDATION_EVERY])
            if not held:
                raise ValueError(f"split: {split!r} holds out every {VALIDATION_EVERY}th "
                                 f"training policy; this zoo has {len(self.train_ids)} "
                                 f"(needs {VALIDATION_EVERY // 2 + 1} or more)")
            return [i for i in self.train_ids if (i in held) == (split == "validation")]
        if split in ("lineage-fit", "lineage-validation"):
            held_out = self.held_out_lineage()
            return [i for i in self.train_ids
                    if (self.lineage(i) == held_out) == (split == "lineage-validation")]
        raise ValueError(f"split: expected one of 'train', 'test', 'all', 'fit', 'validation', "
                         f"'lineage-fit', 'lineage-validation', got {split!r}")

    def policy_names(self, ids: Sequence[int]) -> list[str]:
        return [f"{self.task}-{i:03d}" for i in ids]

    def lineage(self, i: int) -> tuple:
        """Policy i's learner lineage: (learner, learner seed) of its origin; snapshots of one
        learner run share it."""
        o = self.origins[i]
        return (o.get("learner", "?"), o.get("seed"))

    def held_out_lineage(self) -> tuple:
        """The training lineage that "lineage-validation" holds out (and "lineage-fit" leaves
        out): the one whose count of training policies is nearest a 1/VALIDATION_EVERY share
        of them (ties: the later learner seed), so that a simulator of the others meets its
        policies as it meets a test policy of a learner run it never saw."""
        counts = Counter(self.lineage(i) for i in self.train_ids)
        if len(counts) < 2:
            raise ValueError(f"split: 'lineage-validation' holds out one of the training "
                             f"policies' learner lineages; this zoo's are all of "
                             f"{len(counts)} ({sorted(map(str, counts))})")
        share = len(self.train_ids) / VALIDATION_EVERY
        return min(counts, key=lambda ln: (abs(counts[ln] - share), -_seed_order(ln[1]),
                                           str(ln[0])))

    def seen_lineage(self, ids: Sequence[int]) -> list[bool]:
        """Per policy of ``ids``: does the training split hold a policy of its lineage?
        (Known without any truth: the data a simulator learns from names its policies.)"""
        train = {self.lineage(i) for i in self.train_ids}
        return [self.lineage(int(i)) in train for i in ids]


def _seed_order(seed) -> float:
    """A learner seed as a number for ordering (None or odd values first)."""
    return float(seed) if isinstance(seed, int | float) else float("-inf")


def names_to_zoo_ids(names: Sequence[str]) -> list[int]:
    """The zoo ids in policy names "<task>-<id>" (``Zoo.policy_names``' inverse)."""
    return [int(name.rsplit("-", 1)[1]) for name in names]


def zoo_dir(task: str, root: str | None = None) -> str:
    return os.path.join(root or ZOO_ROOT, task)


def save_zoo(zoo: Zoo, directory: str) -> None:
    """Write ``zoo.npz`` (params) and ``zoo.json`` (everything else) into ``directory``."""
    if set(zoo.train_ids) & set(zoo.test_ids):
        raise ValueError("train_ids and test_ids must be disjoint")
    os.makedirs(directory, exist_ok=True)
    with atomic_open(os.path.join(directory, "zoo.npz"), "wb") as f:
        np.savez_compressed(f, **flatten_params(zoo.params))
    meta = {"task": zoo.task, "size": zoo.size,
            "returns": [float(r) for r in zoo.returns],
            "return_se": [float(r) for r in zoo.return_se],
            "origins": zoo.origins, "train_ids": [int(i) for i in zoo.train_ids],
            "test_ids": [int(i) for i in zoo.test_ids], "info": zoo.info}
    write_json(os.path.join(directory, "zoo.json"), meta)


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
        params = unflatten_params({k: data[k] for k in data.files})
    zoo = Zoo(task=meta["task"], params=params, returns=np.asarray(meta["returns"], np.float32),
              return_se=np.asarray(meta["return_se"], np.float32), origins=meta["origins"],
              train_ids=meta["train_ids"], test_ids=meta["test_ids"], info=meta.get("info", {}))
    if zoo.size != len(zoo.returns):
        raise ValueError(f"zoo {directory}: {zoo.size} policies but {len(zoo.returns)} returns")
    return zoo


def policy_source(ds, zoo: str | None = None, *, policy_file: str | None = None,
                  data_path: str | None = None, flag: str = "policy-file") -> dict:
    """Where ``policies_for`` takes the policies that collected ``ds`` from (arguments as
    there). -> {"policy_file": path, "label": the flag or field that named it} or {"zoo":
    directory or task name, "zoo_ids": the data's policies in it}."""
    if zoo is not None and policy_file is not None:
        raise ValueError(f"{flag}: give the data's policies by --zoo DIR or by "
                         f"--{flag} FILE, not both")
    source = ds.meta.get("source") or {}
    if policy_file is not None:
        return {"policy_file": os.fspath(policy_file), "label": flag}
    if zoo is None and source.get("policy_file") is not None:
        path = source["policy_file"]
        if not isinstance(path, str) or not path:
            raise ValueError(f"meta.source.policy_file: expected a path (str), got {path!r}")
        if not os.path.isabs(path):
            if data_path is None:
                raise ValueError(f"meta.source.policy_file: {path!r} is relative to the data "
                                 f"file's directory, but the data file is not known here "
                                 f"(pass data_path=)")
            path = os.path.join(os.path.dirname(os.path.abspath(data_path)), path)
        return {"policy_file": path, "label": "meta.source.policy_file"}
    ids, zoo = source.get("zoo_ids"), zoo or source.get("zoo")
    if zoo is None or ids is None:
        raise ValueError("zoo: the Dataset's meta.source names no zoo and zoo_ids (nor a "
                         "policy_file), so the policies that collected it are unknown; pass "
                         f"--zoo DIR or --{flag} FILE")
    return {"zoo": zoo, "zoo_ids": [int(i) for i in ids]}


def policies_for(ds, zoo: str | None = None, *, policy_file: str | None = None,
                 data_path: str | None = None, flag: str = "policy-file") -> Params:
    """The stacked policies [P, ...] that collected ``ds``, in its policy_id order.

    From ``zoo`` (a directory or task name; the Dataset's meta.source.zoo_ids pick its
    policies) or ``policy_file`` (a ``save_policies`` file holding exactly the data's P
    policies), at most one of them; else from what meta.source names: a ``policy_file``
    (a relative path is resolved against the directory of ``data_path``, the file ``ds`` was
    loaded from) or a ``zoo`` with ``zoo_ids`` (``policy_source``). ``flag``: the command-line
    option that gave ``policy_file`` (without its dashes), named by the errors.
    """
    where = policy_source(ds, zoo, policy_file=policy_file, data_path=data_path, flag=flag)
    if "policy_file" in where:
        return _file_policies(ds, where["policy_file"], where["label"])
    zoo, ids = where["zoo"], where["zoo_ids"]
    z = load_zoo(zoo)
    if max(ids) >= z.size:
        raise ValueError(f"zoo: meta.source.zoo_ids go up to {max(ids)} but {zoo} has "
                         f"{z.size} policies")
    names = ds.meta.get("policy_names")
    if names and list(names) != z.policy_names(ids):
        raise ValueError(f"zoo: policy names {z.policy_names(ids)[:3]}... of {zoo} do not "
                         f"match the Dataset's {list(names)[:3]}...")
    return index_params(z.params, np.asarray(ids))


def _file_policies(ds, path: str, label: str) -> Params:
    """The policies of policy file ``path`` for ``ds``: as many as the data's, of its sizes,
    not its own names in another order. ``label`` (the flag or field) starts every error; a
    PolicyFileWarning where its policies do not explain the data's actions
    (``likelihood.policy_file_mismatch``)."""
    try:
        params, names = load_policies(path)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{label}: {err}") from None
    except ValueError as err:
        raise ValueError(f"{label}: {err}") from None
    if num_policies(params) != ds.n_policies:
        raise ValueError(f"{label}: {path} holds {num_policies(params)} policies, but the "
                         f"Dataset holds {ds.n_policies} (its n_policies): the file must hold "
                         f"the policies that collected the data, in its policy_id order")
    obs, act = params["obs_mean"].shape[1], params["layers"][-1]["b"].shape[1] // 2
    if (obs, act) != (ds.obs_size, ds.action_size):
        raise ValueError(f"{label}: the policies of {path} take observations of size {obs} "
                         f"and act in {act} dims, the Dataset's obs_size / action_size are "
                         f"{ds.obs_size} / {ds.action_size}")
    data_names = list(ds.meta.get("policy_names") or [])
    if names != data_names and sorted(names) == sorted(data_names):
        raise ValueError(f"{label}: {path} names the Dataset's policies in another order "
                         f"({names[:3]}... against its policy_names {data_names[:3]}...): "
                         f"the file must list them in the data's policy_id order")
    warn_if_mismatched(ds, params, label, path, names)  # the logged actions' likelihood
    return params
