"""Spreading vmapped lanes (methods x seeds x eps) over the local devices (issue 13, item 1).

The lanes of ``experiments/paper.py`` never talk to each other, so sharding their leading axis
over a 1-D ``Mesh`` and replicating everything else (data, policies, start pools) lets
``jit(vmap(...))`` run each device's lanes where they live, with no collective. One device (or a
lane count no device count divides) gives today's program.

    mesh = lane_mesh(n_lanes)            # the most devices that divide n_lanes
    states = shard_lanes(states, mesh)   # leading axis split over the mesh
    data = replicate(data, mesh)

Multi-host: ``initialize_distributed()`` calls ``jax.distributed.initialize()`` when the usual
coordinator variables are set; ``is_writer()`` is True on the one process that writes results.
CPU tests force several host devices with ``XLA_FLAGS=--xla_force_host_platform_device_count=4``.
"""
from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

LANES = "lanes"
_COORDINATOR_VARS = ("JAX_COORDINATOR_ADDRESS", "COORDINATOR_ADDRESS")


_initialized = False


def initialize_distributed() -> bool:
    """``jax.distributed.initialize()`` (it reads the addresses itself) once, when a
    coordinator address is in the environment; call it before any other JAX work.
    -> whether it was called now."""
    global _initialized
    if _initialized or not any(os.environ.get(v) for v in _COORDINATOR_VARS):
        return False
    jax.distributed.initialize()
    _initialized = True
    return True


def is_writer() -> bool:
    """True on the process that writes results (process 0; the only one without multi-host)."""
    return jax.process_index() == 0


def lane_mesh(n_lanes: int, devices=None) -> Mesh:
    """A 1-D mesh over the most of ``devices`` (default: all of them) that divides n_lanes
    evenly (1 when none but one does)."""
    if not isinstance(n_lanes, int) or n_lanes < 1:
        raise ValueError(f"n_lanes: expected an int >= 1, got {n_lanes!r}")
    devices = list(jax.devices() if devices is None else devices)
    n = max(d for d in range(1, len(devices) + 1) if n_lanes % d == 0)
    return Mesh(np.asarray(devices[:n]), (LANES,))


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
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(LANES)))


def replicate(tree, mesh: Mesh):
    """Every leaf copied to every device of ``mesh`` (as it is, for one device)."""
    if mesh.size == 1:
        return tree
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))
