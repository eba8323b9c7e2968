"""The Dataset: transitions that many policies collected, its ``.npz`` file format, validation.

A :class:`Dataset` is a ``flax.struct`` pytree of arrays over ``N`` transitions and ``P``
policies, plus a static JSON-serialisable ``meta`` dict. Files are written by
:func:`save_dataset` and read by :func:`load_dataset`, which validates everything before
returning and raises :class:`DatasetError` naming the offending field otherwise. Nothing is
ever repaired silently; the only conversion is integer ids stored as int64 being narrowed to
int32 once they are checked to fit. The schema and the rules are in ``docs/DATA.md``.

Everything here is Python-side NumPy (vectorised, O(N)); nothing is jitted.
"""

from __future__ import annotations

import difflib
import json
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from flax import struct

from rl2s_jax._files import atomic_open

__all__ = [
    "FORMAT_VERSION",
    "TRANSITION_FIELDS",
    "VALUE_FIELDS",
    "META_KEYS",
    "Dataset",
    "DatasetError",
    "concat_datasets",
    "spread_rows",
    "save_dataset",
    "load_dataset",
    "validate_dataset",
]

FORMAT_VERSION = 1
TRANSITION_FIELDS = (
    "obs", "action", "next_obs", "reward", "done", "truncated", "policy_id", "episode_id", "t",
)
VALUE_FIELDS = ("value", "value_se", "value_discounted", "value_discounted_se")
ARRAY_FIELDS = TRANSITION_FIELDS + VALUE_FIELDS
META_KEYS = (
    "task", "obs_size", "action_size", "n_policies", "gamma", "episode_length", "policy_names",
    "source",
)
_FLOAT_FIELDS = ("obs", "action", "next_obs", "reward") + VALUE_FIELDS
_BOOL_FIELDS = ("done", "truncated")
_INT_FIELDS = ("policy_id", "episode_id", "t")
_WIDTH_KEY = {"obs": "obs_size", "action": "action_size", "next_obs": "obs_size"}
_I32 = np.iinfo(np.int32)

#: ``task_sizes(task_name) -> (obs_size, action_size)``, or None when the task is unknown.
TaskSizes = Callable[[str], tuple[int, int] | None]


class DatasetError(ValueError):
    """Bad dataset input. ``field`` is the array or meta key at fault (None: the file itself).

    The message reads ``[path: ]field 'obs': expected shape [N, 11] (obs_size from meta),
    got (500, 12)[; hint]``, or ``file 'path': expected ..., got ...`` for the file itself.
    """

    def __init__(self, field: str | None, expected: str, got: str, *, hint: str | None = None,
                 path: str | None = None):
        self.field, self.expected, self.got, self.hint, self.path = field, expected, got, hint, path
        if field is None:
            label = "file" if path is None else f"file '{path}'"
        else:
            label = f"field '{field}'" if path is None else f"{path}: field '{field}'"
        msg = f"{label}: expected {expected}, got {got}"
        super().__init__(f"{msg}; {hint}" if hint else msg)

    def with_path(self, path: str) -> DatasetError:
        return DatasetError(self.field, self.expected, self.got, hint=self.hint, path=path)


@struct.dataclass
class Dataset:
    """Transitions of P policies. Shapes: obs/next_obs [N, obs_size], action [N, action_size],
    reward/done/truncated/policy_id/episode_id/t [N]; the value fields [P] or all None."""

    obs: Any  # [N, obs_size] float32
    action: Any  # [N, action_size] float32
    next_obs: Any  # [N, obs_size] float32
    reward: Any  # [N] float32
    done: Any  # [N] bool: termination
    truncated: Any  # [N] bool: time limit hit
    policy_id: Any  # [N] int32 in [0, P)
    episode_id: Any  # [N] int32; an episode's rows are contiguous and time-ordered
    t: Any  # [N] int32; 0 at an episode's first row
    value: Any = None  # [P] float32: mean undiscounted episode return
    value_se: Any = None  # [P] float32
    value_discounted: Any = None  # [P] float32: mean discounted return (meta["gamma"])
    value_discounted_se: Any = None  # [P] float32
    meta: dict = struct.field(pytree_node=False, default_factory=dict)

    @property
    def n_transitions(self) -> int:
        return int(np.shape(self.reward)[0])

    @property
    def n_policies(self) -> int:
        return int(self.meta["n_policies"])

    @property
    def obs_size(self) -> int:
        return int(self.meta["obs_size"])

    @property
    def action_size(self) -> int:
        return int(self.meta["action_size"])

    @property
    def has_values(self) -> bool:
        return self.value is not None

    def arrays(self) -> dict[str, np.ndarray]:
        """The present array fields as NumPy arrays (absent value fields left out)."""
        out = {k: np.asarray(getattr(self, k)) for k in TRANSITION_FIELDS}
        out.update({k: np.asarray(getattr(self, k)) for k in VALUE_FIELDS
                    if getattr(self, k) is not None})
        return out

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any], meta: dict, *,
                    task_sizes: TaskSizes | None = None) -> Dataset:
        """Validate ``arrays`` (field name -> array) against ``meta`` and build a Dataset.

        int64 ids are narrowed to int32 (they are checked to fit); nothing else is converted.
        """
        arrays = {k: v for k, v in arrays.items()
                  if v is not None and k not in ("meta", "format_version")}
        validate_dataset(arrays, meta, task_sizes=task_sizes)
        fields = {}
        for k, v in arrays.items():
            v = np.asarray(v)
            fields[k] = v.astype(np.int32) if k in _INT_FIELDS and v.dtype != np.int32 else v
        return cls(**fields, meta=dict(meta))

    def select_policies(self, ids: Sequence[int]) -> Dataset:
        """A new Dataset holding only the rows of policies ``ids``, renumbered so that
        ``ids[i]`` becomes policy ``i``; rows keep their order; values and meta follow.

        ``meta["source"]["selected_policies"]`` records the kept ids relative to the
        original (unselected) dataset.
        """
        ids = np.asarray(ids)
        p = self.n_policies
        if ids.ndim != 1 or ids.size == 0 or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"select_policies: expected a non-empty list of int ids, got {ids!r}")
        if len(np.unique(ids)) != ids.size or ids.min() < 0 or ids.max() >= p:
            raise ValueError(f"select_policies: ids must be distinct and in [0, {p}), got "
                             f"{ids.tolist()}")
        remap = np.full(p, -1, np.int32)
        remap[ids] = np.arange(ids.size, dtype=np.int32)
        new_pid = remap[np.asarray(self.policy_id)]
        keep = new_pid >= 0
        fields = {k: np.asarray(getattr(self, k))[keep] for k in TRANSITION_FIELDS}
        fields["policy_id"] = new_pid[keep]
        if self.has_values:
            fields.update({k: np.asarray(getattr(self, k))[ids] for k in VALUE_FIELDS})
        meta = dict(self.meta)
        meta["n_policies"] = int(ids.size)
        meta["policy_names"] = [meta["policy_names"][i] for i in ids]
        source = dict(meta.get("source") or {})
        prev = source.get("selected_policies")
        source["selected_policies"] = [int(prev[i]) if prev is not None else int(i) for i in ids]
        meta["source"] = source
        return Dataset(**fields, meta=meta)


def spread_rows(n: int, max_rows: int) -> np.ndarray:
    """Row indices [min(n, max_rows)] int64: all ``n`` rows, or ``max_rows`` of them evenly
    spread from the first to the last (a fixed subset: no draw, the same every call)."""
    if n <= max_rows:
        return np.arange(n)
    return np.round(np.linspace(0, n - 1, max_rows)).astype(np.int64)


def concat_datasets(datasets: Sequence[Dataset]) -> Dataset:
    """The rows of ``datasets`` one after another, in the order given (recording order), as
    one Dataset of the same policies.

    Episode ids continue across the parts (part k's episodes come after part k-1's). The
    parts must agree on task, obs/action sizes, policies and episode length. True values
    are kept when every part has them: a policy's value is then its mean over the parts
    (each part measured with the same number of episodes) and its standard error
    sqrt(sum se^2) / K. ``meta["source"]`` is the first part's, with ``parts`` = K.
    """
    parts = list(datasets)
    if not parts or not all(isinstance(d, Dataset) for d in parts):
        raise ValueError("datasets: expected a non-empty sequence of Dataset")
    first = parts[0]
    for i, d in enumerate(parts[1:], 1):
        for key in ("task", "obs_size", "action_size", "n_policies", "policy_names",
                    "episode_length"):
            if d.meta.get(key) != first.meta.get(key):
                raise ValueError(f"datasets[{i}]: meta {key!r} is {d.meta.get(key)!r}, but "
                                 f"datasets[0] has {first.meta.get(key)!r}")
    fields = {}
    for k in TRANSITION_FIELDS:
        fields[k] = np.concatenate([np.asarray(getattr(d, k)) for d in parts], axis=0)
    ids = [np.asarray(d.episode_id, np.int64) - int(np.min(d.episode_id)) for d in parts]
    offsets = np.cumsum([0] + [int(i.max()) + 1 for i in ids[:-1]])
    fields["episode_id"] = np.concatenate(
        [i + o for i, o in zip(ids, offsets, strict=True)]).astype(np.int32)
    meta = {**first.meta, "source": {**(first.meta.get("source") or {}), "parts": len(parts)}}
    if all(d.has_values for d in parts):
        k = len(parts)
        for name in ("value", "value_discounted"):
            fields[name] = np.mean([np.asarray(getattr(d, name)) for d in parts], axis=0)
            fields[name + "_se"] = np.sqrt(np.sum(
                [np.asarray(getattr(d, name + "_se")) ** 2 for d in parts], axis=0)) / k
    elif any(d.has_values for d in parts):
        meta["gamma"] = None  # values of only some parts: dropped with their discount
    return Dataset.from_arrays(fields, meta)


# --------------------------------------------------------------------------- file format


def save_dataset(path: str | os.PathLike, ds: Dataset, *,
                 task_sizes: TaskSizes | None = None) -> str:
    """Validate ``ds`` and write it to exactly ``path`` (np.savez_compressed; no suffix added).

    Keys: the array fields under their names (absent value fields not written), ``meta`` (a
    JSON string in a 0-d unicode array) and ``format_version`` (1). The file is written to a
    temporary name and renamed, so a crash never leaves a half-written file at ``path``.
    """
    path = os.fspath(path)
    validate_dataset(ds, task_sizes=task_sizes)
    arrays = ds.arrays()
    arrays["meta"] = np.array(json.dumps(ds.meta))
    arrays["format_version"] = np.array(FORMAT_VERSION, dtype=np.int64)
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


def load_dataset(path: str | os.PathLike, *, task_sizes: TaskSizes | None = None) -> Dataset:
    """Read and validate a file written by :func:`save_dataset`; never modifies the file.

    ``task_sizes(task) -> (obs_size, action_size) | None`` checks the sizes against a
    registered task; by default the registry ``rl2s_jax.tasks.get_task`` is asked (skipped
    when the task is None, unregistered, or the registry cannot be imported). Pass
    ``task_sizes=lambda name: None`` to skip the check. Raises :class:`DatasetError`.
    """
    path = os.fspath(path)
    try:
        raw = _read_npz(path)
        if not raw:
            raise DatasetError(None, "an archive holding the dataset fields",
                               "an empty archive (no arrays, N = 0)")
        _check_format_version(raw.pop("format_version", None))
        if "meta" not in raw:
            raise DatasetError("meta", "a JSON string in a 0-d unicode array", "missing")
        meta = _parse_meta(raw.pop("meta"))
        return Dataset.from_arrays(raw, meta, task_sizes=task_sizes)
    except DatasetError as e:
        raise e.with_path(path) from None


def _read_npz(path: str) -> dict[str, np.ndarray]:
    expected = "an .npz archive written by save_dataset"
    if not os.path.exists(path):
        raise DatasetError(None, expected, "no such file")
    if os.path.isdir(path):
        raise DatasetError(None, expected, "a directory")
    if os.path.getsize(path) == 0:
        raise DatasetError(None, expected, "an empty file (0 bytes)")
    with open(path, "rb") as f:
        magic = f.read(6)
    if not magic.startswith(b"PK\x03\x04"):
        hint = "this is a single .npy array, not an .npz archive" if magic == b"\x93NUMPY" else None
        raise DatasetError(None, expected, f"not a zip archive (starts with {magic!r})", hint=hint)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # zipfile.BadZipFile, pickled/object arrays, truncated members...
        raise DatasetError(None, expected,
                           f"an unreadable archive ({type(e).__name__}: {e})") from None


def _check_format_version(v: Any) -> None:
    if v is None:
        raise DatasetError("format_version", f"{FORMAT_VERSION}", "missing")
    v = np.asarray(v)
    if v.shape != () or not np.issubdtype(v.dtype, np.integer) or int(v) != FORMAT_VERSION:
        raise DatasetError("format_version", f"{FORMAT_VERSION} (an int; the only version this "
                           "code reads)", f"{v!r}")


# --------------------------------------------------------------------------- validation


def validate_dataset(ds_or_arrays: Dataset | Mapping[str, Any], meta: dict | str | None = None,
                     *, task_sizes: TaskSizes | None = None) -> None:
    """Check a Dataset, or a mapping field name -> array (plus optional ``meta`` /
    ``format_version`` keys, as in a loaded npz), against ``meta`` (a dict, or its JSON string;
    default: ``ds.meta`` or ``arrays["meta"]``). Raises :class:`DatasetError`; returns None.

    O(N) vectorised NumPy. ``task_sizes`` as in :func:`load_dataset`.
    """
    if isinstance(ds_or_arrays, Dataset):
        arrays = ds_or_arrays.arrays()
        meta = ds_or_arrays.meta if meta is None else meta
    else:
        arrays = {k: v for k, v in ds_or_arrays.items()
                  if k not in ("meta", "format_version") and v is not None}
        if meta is None:
            if "meta" not in ds_or_arrays:
                raise DatasetError("meta", "a JSON object with keys " + ", ".join(META_KEYS),
                                   "missing")
            meta = ds_or_arrays["meta"]
    meta = _parse_meta(meta)
    _check_names(arrays)
    a = {k: np.asarray(v) for k, v in arrays.items()}
    n = _check_dtypes_and_shapes(a, meta)
    _check_task_sizes(a, meta, task_sizes)
    _check_values(a, meta, n)
    _check_episodes(a, meta)


def _parse_meta(meta: Any) -> dict:
    if isinstance(meta, np.ndarray):
        if meta.shape != () or meta.dtype.kind != "U":
            raise DatasetError("meta", "a JSON string in a 0-d unicode array",
                               f"an array of dtype {meta.dtype} and shape {meta.shape}")
        meta = str(meta[()])
    if isinstance(meta, str):
        try:
            meta = json.loads(meta)
        except json.JSONDecodeError as e:
            raise DatasetError("meta", "a JSON object", f"unparsable JSON ({e})") from None
    if not isinstance(meta, dict):
        raise DatasetError("meta", "a JSON object (dict)", type(meta).__name__)
    missing = [k for k in META_KEYS if k not in meta]
    if missing:
        raise DatasetError("meta", "keys " + ", ".join(META_KEYS),
                           "missing key(s) " + ", ".join(repr(k) for k in missing))
    try:
        json.dumps(meta)
    except (TypeError, ValueError) as e:
        raise DatasetError("meta", "a JSON-serialisable dict", f"{e}") from None

    def bad(key: str, expected: str) -> DatasetError:
        return DatasetError(f"meta.{key}", expected, repr(meta[key]))

    def is_int(x: Any) -> bool:
        return isinstance(x, int) and not isinstance(x, bool)

    if meta["task"] is not None and not isinstance(meta["task"], str):
        raise bad("task", "a task name (str) or None")
    for key in ("obs_size", "action_size", "n_policies"):
        if not is_int(meta[key]) or meta[key] < 1:
            raise bad(key, "a positive int")
    g = meta["gamma"]
    if g is not None and (not isinstance(g, int | float) or isinstance(g, bool) or not 0 < g <= 1):
        raise bad("gamma", "a float in (0, 1] or None")
    el = meta["episode_length"]
    if el is not None and (not is_int(el) or el < 1):
        raise bad("episode_length", "a positive int (the time limit) or None")
    names = meta["policy_names"]
    if (not isinstance(names, list) or len(names) != meta["n_policies"]
            or not all(isinstance(s, str) for s in names)):
        raise bad("policy_names", f"a list of n_policies = {meta['n_policies']} strings")
    if not isinstance(meta["source"], dict):
        raise bad("source", "a dict describing how the data was made")
    return meta


# Names other datasets (D4RL, gym) use for our fields.
_ALIASES = {"observations": "obs", "observation": "obs", "states": "obs", "actions": "action",
            "rewards": "reward", "next_observations": "next_obs", "dones": "done",
            "terminals": "done", "terminated": "done", "terminations": "done",
            "timeouts": "truncated", "truncations": "truncated", "policy": "policy_id",
            "episode": "episode_id", "timestep": "t", "timesteps": "t", "step": "t"}


def _suggest(name: str, missing: list[str]) -> str | None:
    """The field an unknown key most likely meant: an alias, else a missing field that is a
    prefix of it (or it of one), else the closest spelling, missing fields first."""
    if name in _ALIASES:
        return _ALIASES[name]
    low = name.lower()
    prefix = [f for f in missing if low.startswith(f) or f.startswith(low)]
    if prefix:
        return max(prefix, key=len)
    for pool in (missing, list(ARRAY_FIELDS)):
        close = difflib.get_close_matches(low, pool, n=1, cutoff=0.5)
        if close:
            return close[0]
    return None


def _check_names(arrays: Mapping[str, Any]) -> None:
    for k in arrays:
        if k not in ARRAY_FIELDS:
            guess = _suggest(k, [f for f in ARRAY_FIELDS if f not in arrays])
            hint = f"did you mean '{guess}'?" if guess else None
            raise DatasetError(k, "one of " + ", ".join(ARRAY_FIELDS), f"unknown field '{k}'",
                               hint=hint)
    for k in TRANSITION_FIELDS:
        if k not in arrays:
            raise DatasetError(k, "a required field", "missing")
    present = [k for k in VALUE_FIELDS if k in arrays]
    if present and len(present) != len(VALUE_FIELDS):
        first_missing = next(k for k in VALUE_FIELDS if k not in arrays)
        raise DatasetError(first_missing, "all four value fields (" + ", ".join(VALUE_FIELDS)
                           + ") or none", "only " + ", ".join(present))


def _check_dtypes_and_shapes(a: dict[str, np.ndarray], meta: dict) -> int:
    for k, x in a.items():
        if k in _FLOAT_FIELDS and x.dtype != np.float32:
            raise DatasetError(k, "dtype float32", f"dtype {x.dtype}",
                               hint="cast it yourself (x.astype(np.float32)); floats are "
                               "never converted on load")
        if k in _BOOL_FIELDS and x.dtype != np.bool_:
            raise DatasetError(k, "dtype bool", f"dtype {x.dtype}")
        if k in _INT_FIELDS and x.dtype not in (np.int32, np.int64):
            raise DatasetError(k, "dtype int32 (int64 accepted when it fits in int32)",
                               f"dtype {x.dtype}")
    obs = a["obs"]
    if obs.ndim != 2:
        raise DatasetError("obs", "shape [N, obs_size] (2-d)", f"{obs.shape}")
    n = obs.shape[0]
    if n == 0:
        raise DatasetError("obs", "at least one transition", "N = 0 (an empty dataset)")
    for k in TRANSITION_FIELDS:
        x = a[k]
        if k in _WIDTH_KEY:
            w = meta[_WIDTH_KEY[k]]
            if x.ndim != 2 or x.shape[1] != w:
                raise DatasetError(k, f"shape [N, {w}] ({_WIDTH_KEY[k]} from meta)", f"{x.shape}")
            if x.shape[0] != n:
                raise DatasetError(k, f"shape [{n}, {w}] (N = {n} from 'obs')", f"{x.shape}")
        elif x.shape != (n,):
            raise DatasetError(k, f"shape [{n}] (N = {n} from 'obs')", f"{x.shape}")
    for k in _INT_FIELDS:
        x = a[k]
        if x.dtype == np.int64 and (x.min() < _I32.min or x.max() > _I32.max):
            i = int(np.flatnonzero((x < _I32.min) | (x > _I32.max))[0])
            raise DatasetError(k, "values that fit in int32", f"{x[i]} at row {i}")
    for k in _FLOAT_FIELDS:
        if k in a and not np.isfinite(a[k]).all():
            bad = ~np.isfinite(a[k])
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            where = f"row {idx[0]}" if a[k].ndim == 1 else f"index {idx}"
            raise DatasetError(k, "finite values", f"{int(bad.sum())} non-finite value(s), "
                               f"first {a[k][idx]} at {where}")
    return n


def _default_task_sizes(name: str) -> tuple[int, int] | None:
    # Imported here so that a Dataset validates where the tasks cannot load (no brax/MuJoCo):
    # the sizes check is then skipped.
    try:
        from rl2s_jax.envs.tasks import get_task
    except ImportError:
        return None
    try:
        task = get_task(name)
    except (ValueError, KeyError):
        return None
    return int(task.obs_size), int(task.action_size)


def _check_task_sizes(a: dict[str, np.ndarray], meta: dict, task_sizes: TaskSizes | None) -> None:
    task = meta["task"]
    if task is None:
        return
    sizes = (task_sizes or _default_task_sizes)(task)
    if sizes is None:
        return
    for k, want in (("obs", sizes[0]), ("action", sizes[1])):
        key = _WIDTH_KEY[k]
        if meta[key] != want:
            raise DatasetError(k, f"shape [N, {want}] ({key} of registered task '{task}')",
                               f"{a[k].shape}", hint=f"meta {key} is {meta[key]}")


def _check_values(a: dict[str, np.ndarray], meta: dict, n: int) -> None:
    pid, p = a["policy_id"], meta["n_policies"]
    out = (pid < 0) | (pid >= p)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise DatasetError("policy_id", f"values in [0, {p}) (n_policies from meta)",
                           f"{int(out.sum())} row(s) outside, first {pid[i]} at row {i}")
    if "value" not in a:
        return
    if meta["gamma"] is None:
        raise DatasetError("meta.gamma", "a float in (0, 1] (the dataset has value_discounted)",
                           "None")
    for k in VALUE_FIELDS:
        if a[k].shape != (p,):
            raise DatasetError(k, f"shape [{p}] (n_policies from meta)", f"{a[k].shape}")
    for k in ("value_se", "value_discounted_se"):
        if (a[k] < 0).any():
            i = int(np.flatnonzero(a[k] < 0)[0])
            raise DatasetError(k, "standard errors >= 0", f"{a[k][i]} for policy {i}")


def _episode_starts(episode_id: np.ndarray) -> np.ndarray:
    """[N] bool: True where a row starts a new episode (its episode_id differs from the
    previous row's)."""
    starts = np.empty(episode_id.shape[0], dtype=bool)
    starts[:1] = True
    np.not_equal(episode_id[1:], episode_id[:-1], out=starts[1:])
    return starts


def _check_episodes(a: dict[str, np.ndarray], meta: dict) -> None:
    ep, t, pid = a["episode_id"], a["t"].astype(np.int64), a["policy_id"]
    done, trunc = a["done"], a["truncated"]
    n = ep.shape[0]
    starts = _episode_starts(ep)
    start_rows = np.flatnonzero(starts)
    ids = ep[start_rows]
    order = np.argsort(ids, kind="stable")
    again = ids[order[1:]] == ids[order[:-1]]
    if again.any():
        seg = order[1:][again].min()  # the earliest segment that repeats an earlier id
        raise DatasetError("episode_id", "each episode's rows contiguous (an episode_id never "
                           "reappears after another episode started)",
                           f"episode_id {ids[seg]} reappears at row {start_rows[seg]}")
    bad = t[start_rows] != 0
    if bad.any():
        r = int(start_rows[np.flatnonzero(bad)[0]])
        raise DatasetError("t", "t == 0 at each episode's first row",
                           f"t = {t[r]} at row {r}, the first row of episode {ep[r]}")
    within = ~starts[1:]  # row i+1 continues the episode of row i
    bad = within & (t[1:] - t[:-1] != 1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DatasetError("t", "t increasing by 1 within an episode",
                           f"t = {t[i]} at row {i} then {t[i + 1]} at row {i + 1} "
                           f"(episode {ep[i]})")
    bad = within & (pid[1:] != pid[:-1])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DatasetError("policy_id", "one policy per episode",
                           f"policy_id {pid[i]} at row {i} then {pid[i + 1]} at row {i + 1} "
                           f"(episode {ep[i]})")
    both = done & trunc
    if both.any():
        i = int(np.flatnonzero(both)[0])
        raise DatasetError("done", "done (termination) and truncated (time limit) never both "
                           "true on a row", f"both at row {i}")
    not_last = np.empty(n, dtype=bool)
    not_last[:-1] = within
    not_last[-1:] = False
    for k, flag in (("done", done), ("truncated", trunc)):
        bad = flag & not_last
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DatasetError(k, f"{k} only on an episode's last row",
                               f"{k} at row {i} but episode {ep[i]} continues at row {i + 1}")
    el = meta["episode_length"]
    if el is not None and t.max() >= el:
        i = int(np.flatnonzero(t >= el)[0])
        raise DatasetError("t", f"t < {el} (episode_length from meta)", f"t = {t[i]} at row {i}")


# --------------------------------------------------------------------------- inspection


