"""Storage of zoo training runs: orbax checkpoints in a work directory and export files.

Pytrees are stored as flat dicts ``{'leaf_00000': array, ...}`` in leaf order, with their
specs (key path, shape, dtype) in the JSON meta, so a checkpoint or an export describes itself
and is checked against the learner that resumes it. Zero-size leaves (MJX states have some)
are left out of orbax, which refuses them, and recreated on restore.

Export files carry a run between machines: one compressed ``.npz`` holding every learner's
latest checkpoint (split into ``PATH.partNN`` files when larger than the limit). When the whole
state does not fit, the export is *light*: without the transient fields (replay buffer, env
states); ``zoo_train`` then re-fills them with the current policies, so the continued run is a
valid continuation but not bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import glob
import io
import json
import math
import os
import re

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import atomic_open

FORMAT = 1
EXPORT_MAX_BYTES = 15 * 2**20


def strong(tree):
    """Drop weak types, so a fresh state and a restored one compile to the same program."""
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, x.dtype), tree)


def tree_spec(tree) -> list[list]:
    """[[keystr path, shape, dtype], ...] of a pytree's leaves (arrays or shape structs)."""
    return [[jax.tree_util.keystr(p), list(x.shape), str(np.dtype(x.dtype))]
            for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]]


def flatten(tree) -> dict[str, np.ndarray]:
    """{'leaf_00000': array, ...} in leaf order (host numpy)."""
    leaves = jax.device_get(jax.tree_util.tree_leaves(tree))
    return {f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)}


def unflatten(template, arrays: dict[str, np.ndarray], what: str):
    """The pytree of ``template`` with leaf i from ``arrays['leaf_i']`` (zero-size leaves may
    be missing). Shapes and dtypes are checked."""
    leaves, treedef = jax.tree_util.tree_flatten(template)
    out = []
    for i, t in enumerate(leaves):
        name = f"leaf_{i:05d}"
        if name not in arrays:
            if int(np.prod(t.shape)) != 0:
                raise ValueError(f"{what}: leaf {i} missing")
            out.append(np.zeros(t.shape, t.dtype))
            continue
        a = arrays[name]
        if tuple(a.shape) != tuple(t.shape) or np.dtype(a.dtype) != np.dtype(t.dtype):
            raise ValueError(f"{what}: leaf {i} is {a.shape} {a.dtype}, expected {t.shape} "
                             f"{t.dtype}")
        out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


def _template(spec: list[list]) -> dict[str, jax.ShapeDtypeStruct]:
    return {f"leaf_{i:05d}": jax.ShapeDtypeStruct(tuple(shape), np.dtype(dtype))
            for i, (_, shape, dtype) in enumerate(spec)}


def check_spec(saved: list[list], expected: list[list], what: str, where: str) -> None:
    if [s[:2] for s in saved] != [s[:2] for s in expected]:
        diff = next((a, b) for a, b in zip(saved + [None], expected + [None], strict=False)
                    if a is None or b is None or a[:2] != b[:2])
        raise ValueError(f"{what}: the saved training state in {where} does not match this "
                         f"learner's (first difference: saved {diff[0]} vs now {diff[1]}); use "
                         "another --work directory or the same settings")


class ZooCheckpointer:
    """Orbax checkpoints of one learner's run: items state, snapshots (flat dicts of arrays)
    and meta (JSON). Only the latest is kept."""

    ITEMS = ("state", "snapshots", "meta")

    def __init__(self, directory: str):
        # Imported here to keep start-up fast: orbax is slow to import; only zoo building needs it.
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.directory = os.path.abspath(directory)
        self._mgr = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=1, create=True),
            item_names=self.ITEMS)

    def latest(self) -> int | None:
        return self._mgr.latest_step()

    def save(self, step: int, state: dict, snapshots: dict, meta: dict) -> None:
        ocp = self._ocp
        nonempty = lambda d: {k: v for k, v in d.items() if v.size}  # orbax refuses size 0
        self._mgr.save(step, args=ocp.args.Composite(
            state=ocp.args.StandardSave(nonempty(state)),
            snapshots=ocp.args.StandardSave(nonempty(snapshots)),
            meta=ocp.args.JsonSave(meta)), force=True)
        self._mgr.wait_until_finished()

    def meta(self, step: int | None = None) -> dict:
        ocp = self._ocp
        step = self.latest() if step is None else step
        return self._mgr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta

    def restore(self, step: int | None = None, state: bool = True) -> dict:
        """{'meta', 'state' (unless state=False), 'snapshots'}: flat dicts of numpy arrays."""
        ocp = self._ocp
        step = self.latest() if step is None else step
        meta = self.meta(step)
        nonempty = lambda spec: {k: v for k, v in _template(spec).items()
                                 if int(np.prod(v.shape))}
        items = {"snapshots": ocp.args.StandardRestore(nonempty(meta["snapshot_spec"]))}
        if state:
            items["state"] = ocp.args.StandardRestore(nonempty(meta["state_spec"]))
        out = self._mgr.restore(step, args=ocp.args.Composite(**items))
        host = lambda d: {k: np.asarray(v) for k, v in d.items()}
        res = {"meta": meta, "snapshots": host(out.snapshots)}
        if state:
            res["state"] = host(out.state)
        return res

    def close(self) -> None:
        self._mgr.close()


def _top_field(name: str) -> str:
    m = re.match(r"^\.(\w+)", name)
    return m.group(1) if m else ""


def write_export(path: str, runs: dict[str, dict], max_bytes: int = EXPORT_MAX_BYTES,
                 log=print) -> list[str]:
    """Write learner runs ({name: {'meta', 'state', 'snapshots'}}) as one compressed npz;
    without the transient state fields (light) when the full one exceeds ``max_bytes``;
    split into PATH.partNN files when still too large. -> the files written."""

    def pack(light: bool) -> bytes:
        arrays = {}
        for name, run in runs.items():
            meta = dict(run["meta"], export_exact=not light)
            transient = set(meta["transient"])
            for k, v in run["state"].items():
                field = _top_field(meta["state_spec"][int(k.split("_")[1])][0])
                if not (light and field in transient):
                    arrays[f"{name}/state/{k}"] = v
            for k, v in run["snapshots"].items():
                arrays[f"{name}/snapshots/{k}"] = v
            arrays[f"{name}/meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    data = pack(light=False)
    if len(data) > max_bytes:
        full = len(data)
        data = pack(light=True)
        log(f"[zoo] export: the full state is {full / 2**20:.1f} MiB (> "
            f"{max_bytes / 2**20:.0f} MiB); writing it without replay buffers and env states "
            f"({len(data) / 2**20:.1f} MiB): resuming from it re-fills them, not bit-identical")
    for old in glob.glob(glob.escape(path) + ".part*") + ([path] if os.path.exists(path) else []):
        os.remove(old)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if len(data) <= max_bytes:
        with atomic_open(path, "wb") as f:
            f.write(data)
        return [path]
    files = []
    for i in range(math.ceil(len(data) / max_bytes)):
        files.append(f"{path}.part{i:02d}")
        with atomic_open(files[-1], "wb") as f:
            f.write(data[i * max_bytes:(i + 1) * max_bytes])
    log(f"[zoo] export: {len(data) / 2**20:.1f} MiB split into {len(files)} files {path}.partNN")
    return files


def read_export(path: str) -> dict[str, dict]:
    """The runs of an export file (PATH or PATH.part00, PATH.part01, ...)."""
    parts = sorted(glob.glob(glob.escape(path) + ".part*"))
    if os.path.exists(path):
        with open(path, "rb") as f:
            data = f.read()
    elif parts:
        data = b"".join(open(p, "rb").read() for p in parts)
    else:
        raise FileNotFoundError(f"import: no file {path} (nor {path}.partNN)")
    runs: dict[str, dict] = {}
    with np.load(io.BytesIO(data)) as z:
        for key in z.files:
            name, _, rest = key.partition("/")
            run = runs.setdefault(name, {"state": {}, "snapshots": {}})
            if rest == "meta":
                run["meta"] = json.loads(z[key].tobytes().decode())
            else:
                kind, _, leaf = rest.partition("/")
                run[kind][leaf] = z[key]
    return runs


def load_runs(work_dir: str, names) -> dict[str, dict]:
    """The latest checkpoint of each learner in ``work_dir`` as flat dicts (for export)."""
    runs = {}
    for name in names:
        directory = os.path.join(work_dir, name, "ckpt")
        if not os.path.isdir(directory):
            continue
        ck = ZooCheckpointer(directory)
        try:
            if ck.latest() is not None:
                runs[name] = ck.restore()
        finally:
            ck.close()
    return runs


__all__ = ["EXPORT_MAX_BYTES", "FORMAT", "ZooCheckpointer", "check_spec", "flatten", "load_runs",
           "read_export", "strong", "tree_spec", "unflatten", "write_export"]
