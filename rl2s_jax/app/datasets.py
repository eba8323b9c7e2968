"""`rl2s collect`, `inspect`, `import` and `export`: Dataset files in and out. Each takes its
spec (app/specs.py) and returns the command's exit status."""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time

from rl2s_jax.app.specs import CollectSpec, ExportSpec, ImportSpec, InspectSpec
from rl2s_jax.data.dataset import DatasetError, load_dataset, save_dataset
from rl2s_jax.data.summary import dataset_summary


def run_collect(spec: CollectSpec) -> int:
    """Collect a Dataset from a zoo split (MJX, vmapped) and write it to ``spec.out``."""
    # local: the pipeline's stack (JAX, brax, MJX), which inspect, import and export need not
    from rl2s_jax.app.pipeline import collect_dataset

    t0 = time.time()
    ds = collect_dataset(spec.task, spec.split, spec.transitions_per_policy, seed=spec.seed,
                         envs_per_policy=spec.envs_per_policy, gamma=spec.gamma,
                         value_episodes=spec.value_episodes, episode_length=spec.episode_length,
                         zoo_path=spec.zoo)
    _write(ds, spec.out, f"collected in {time.time() - t0:.0f}s -> {spec.out}")
    return 0


def _write(ds, out: str, done: str) -> None:
    """Save ``ds`` at ``out`` (its directories made), then print its summary and ``done``."""
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    save_dataset(out, ds)
    print(dataset_summary(ds))
    print(done)


def run_inspect(spec: InspectSpec) -> int:
    """Validate a Dataset file and print its summary; 1 (one line) where it is not valid."""
    try:
        ds = load_dataset(spec.data)
    except DatasetError as err:
        print(f"rl2s inspect: {err}", file=sys.stderr)
        return 1
    print(dataset_summary(ds))
    return 0


def run_import(spec: ImportSpec) -> int:
    """A local Minari dataset -> our Dataset file (validated)."""
    # local: the task registry (brax, MJX) that minari.py loads, which inspect need not
    from rl2s_jax.data.minari import from_minari

    ds = from_minari(spec.minari, task=spec.task, gamma=spec.gamma, policy_key=spec.policy_key)
    _write(ds, spec.out, f"imported {spec.minari} -> {spec.out}")
    return 0


def run_export(spec: ExportSpec) -> int:
    """Our Dataset file -> a Minari dataset directory."""
    # local: the task registry (brax, MJX) that minari.py loads, which inspect need not
    from rl2s_jax.data.minari import _default_id, to_minari

    ds = load_dataset(spec.data)
    out = os.path.abspath(spec.out)
    # Written beside its place, then moved in: a stop or an error leaves --out as it was.
    staging = tempfile.mkdtemp(dir=os.path.dirname(out), prefix=f".{os.path.basename(out)}.")
    try:
        mds = to_minari(ds, os.path.join(staging, "new"), dataset_id=spec.dataset_id
                        or _default_id(os.path.basename(out)))
        if os.path.lexists(out):  # empty, or replaced with --force (checked at the door)
            os.replace(out, os.path.join(staging, "old"))
        os.replace(os.path.join(staging, "new"), out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"exported {spec.data} ({mds.total_episodes} episodes, {mds.total_steps} steps) -> "
          f"Minari dataset {mds.id!r} in {spec.out}")
    return 0
