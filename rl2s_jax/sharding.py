"""Spreading vmapped lanes (methods x seeds x eps) over devices, on one process or several
(issue 13, item 1; issue 40, item 2).

The lanes of ``experiments/paper.py`` never talk to each other, so sharding their leading axis
over a 1-D ``Mesh`` and replicating everything else (data, policies, start pools) lets
``jit(vmap(...))`` run each device's lanes where they live, with no collective. One device (or a
lane count no device count divides) gives today's program.

    mesh = lane_mesh(n_lanes)            # the most devices that divide n_lanes
    states = shard_lanes(states, mesh)   # leading axis split over the mesh
    data = replicate(data, mesh)
    host = to_host(states)               # NumPy, the whole lane axis, on every process

Several processes (hosts, or one process per GPU): ``initialize_distributed()`` first, before
any other JAX work; it calls ``jax.distributed.initialize`` from the environment
(docs/SCALING.md). Then ``jax.devices()`` lists every process's devices and ``lane_mesh``
spans them all, each process the same number of its own. Every process runs the same program
on the same tree (same keys, same data); ``shard_lanes`` / ``replicate`` give each device its
slice of its own process's copy, ``to_host`` gathers the lanes back (a collective: every
process calls it), and ``is_writer()`` is True on the one process that writes results. CPU
tests force several host devices with ``XLA_FLAGS=--xla_force_host_platform_device_count=4``
(tests/test_sharding.py; two processes of two devices: tests/test_distributed.py).
"""
from __future__ import annotations

import os

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

LANES = "lanes"
# The plain launch: JAX reads the coordinator itself, the other two are read here.
COORDINATOR_VAR, NUM_PROCESSES_VAR, PROCESS_ID_VAR = (
    "JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
# What JAX's SLURM detection needs (jax._src.clusters.slurm_cluster): an srun step's task.
SLURM_VARS = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID",
               "SLURM_LOCALID")


def _int_setting(value, name: str, low: int) -> int | None:
    """An int >= low from an argument (int) or an environment string, None when unset;
    ValueError naming ``name`` otherwise."""
    if value is None or value == "":
        return None
    try:
        out = int(value) if isinstance(value, (int, str)) and not isinstance(value, bool) else None
    except ValueError:
        out = None
    if out is None or out < low:
        raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
    return out


def _slurm_tasks() -> int:
    """The task count of the srun step this process is a task of (0 outside one)."""
    if not all(os.environ.get(v) for v in SLURM_VARS):
        return 0
    return _int_setting(os.environ["SLURM_NTASKS"], "SLURM_NTASKS", 1)


def initialize_distributed(coordinator_address: str | None = None,
                           num_processes: int | None = None,
                           process_id: int | None = None) -> bool:
    """``jax.distributed.initialize`` once, when this process is one of several; call it
    before any other JAX work. The settings come from the arguments, else from the
    environment: JAX_COORDINATOR_ADDRESS (host:port of process 0), JAX_NUM_PROCESSES,
    JAX_PROCESS_ID; inside an ``srun`` step of several tasks JAX reads SLURM's variables
    itself (JAX_COORDINATOR_ADDRESS may still name the coordinator). Nothing set: one process,
    nothing to do. ValueError, before any work, for a partial or malformed setting.
    -> whether it was called now."""
    coordinator = coordinator_address or os.environ.get(COORDINATOR_VAR) or None
    n_name = "num_processes" if num_processes is not None else NUM_PROCESSES_VAR
    n = _int_setting(num_processes if num_processes is not None
                     else os.environ.get(NUM_PROCESSES_VAR), n_name, 1)
    i_name = "process_id" if process_id is not None else PROCESS_ID_VAR
    i = _int_setting(process_id if process_id is not None
                     else os.environ.get(PROCESS_ID_VAR), i_name, 0)
    slurm = _slurm_tasks() > 1
    if jax.distributed.is_initialized() or not (slurm or coordinator or n is not None
                                                or i is not None):
        return False
    if coordinator is not None:
        host, _, port = coordinator.rpartition(":")
        if not host or not port.isdigit():
            raise ValueError(f"{COORDINATOR_VAR}: expected host:port of process 0 (e.g. "
                             f"node001:12345), got {coordinator!r}")
    if not slurm:  # a plain launch: all three, or none
        missing = [name for name, v in ((COORDINATOR_VAR, coordinator), (n_name, n),
                                        (i_name, i)) if v is None]
        if missing:
            raise ValueError(f"{', '.join(missing)}: expected with the other settings of a "
                             f"launch of several processes ({COORDINATOR_VAR}=host:port, "
                             f"{NUM_PROCESSES_VAR}=N, {PROCESS_ID_VAR}=0..N-1; docs/"
                             f"SCALING.md), got unset")
    if n is not None and i is not None and i >= n:
        raise ValueError(f"{i_name}: expected an int >= 0 and < {n} ({n_name}), got {i}")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=n,
                               process_id=i)
    return True


def is_writer() -> bool:
    """True on the process that writes results (process 0; the only one without multi-host)."""
    return jax.process_index() == 0


def lane_mesh(n_lanes: int, devices=None) -> Mesh:
    """A 1-D mesh over the most of ``devices`` (default: every process's, ``jax.devices()``)
    that divides n_lanes evenly (1 when none but one does). Devices of several processes: each
    process gives the same number of its own (the first ones, process by process), so every
    process holds the same number of lanes; ValueError when no such count divides n_lanes."""
    if not isinstance(n_lanes, int) or isinstance(n_lanes, bool) or n_lanes < 1:
        raise ValueError(f"n_lanes: expected an int >= 1, got {n_lanes!r}")
    devices = list(jax.devices() if devices is None else devices)
    by_process: dict[int, list] = {}
    for d in devices:
        by_process.setdefault(d.process_index, []).append(d)
    if len(by_process) == 1:
        n = max(d for d in range(1, len(devices) + 1) if n_lanes % d == 0)
        return Mesh(np.asarray(devices[:n]), (LANES,))
    n_proc = len(by_process)
    fits = [k for k in range(1, min(map(len, by_process.values())) + 1)
            if n_lanes % (n_proc * k) == 0]
    if not fits:
        raise ValueError(f"n_lanes: {n_lanes} lanes do not split evenly over {n_proc} "
                         f"processes (each must hold as many lanes as the others); expected "
                         f"a multiple of {n_proc}")
    k = max(fits)
    return Mesh(np.asarray([d for local in by_process.values() for d in local[:k]]), (LANES,))


def _put(tree, sharding: NamedSharding):
    """``tree`` placed with ``sharding``. Over devices of several processes, each device takes
    its slice of this process's copy (every process passes the same values); a leaf that
    already spans processes is resharded."""
    if sharding.is_fully_addressable:
        return jax.device_put(tree, sharding)

    def put(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return jax.device_put(x, sharding)
        x = np.asarray(x)
        return jax.make_array_from_process_local_data(sharding, x, x.shape)

    return jax.tree_util.tree_map(put, tree)


def shard_lanes(tree, mesh: Mesh):
    """Every leaf split along its leading (lane) axis over ``mesh``. Leaves must share that
    axis, and its length must be a multiple of the mesh size."""
    leaves = jax.tree_util.tree_leaves(tree)
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(f"tree: expected every leaf to have the same leading lane axis, got "
                         f"leading sizes {sorted(sizes, key=str)}")
    n = sizes.pop()
    if n % mesh.size:
        raise ValueError(f"tree: {n} lanes do not split evenly over {mesh.size} devices "
                         f"(lane_mesh({n}) chooses a count that does)")
    if mesh.size == 1:  # nothing to split: leave the arrays where they are (no copy)
        return tree
    return _put(tree, NamedSharding(mesh, PartitionSpec(LANES)))


def replicate(tree, mesh: Mesh):
    """Every leaf copied to every device of ``mesh`` (as it is, for one device)."""
    if mesh.size == 1:
        return tree
    return _put(tree, NamedSharding(mesh, PartitionSpec()))


def to_host(tree):
    """Every leaf as a NumPy array of its whole value, on every process. Leaves that span
    several processes (``shard_lanes`` / ``replicate`` over their mesh, and what jit computes
    from them) are gathered: a collective, so every process calls it with the same tree."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    spread = {i: x for i, x in enumerate(leaves)
              if isinstance(x, jax.Array) and not x.is_fully_addressable}
    gathered = (dict(zip(spread, multihost_utils.process_allgather(list(spread.values()),
                                                                   tiled=True), strict=True))
                if spread else {})
    return jax.tree_util.tree_unflatten(treedef, [
        np.asarray(gathered[i] if i in gathered else jax.device_get(x))
        for i, x in enumerate(leaves)])
