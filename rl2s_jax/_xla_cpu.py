"""A jaxlib deadlock on small CPUs, avoided before JAX starts its backend.

jaxlib's CPU Cholesky (``lapack_spotrf_ffi``, which MJX's Newton solver calls batched over
the environments) splits a large batch over XLA's intra-op thread pool and waits for the
pieces from the thread it runs on, itself a worker of that pool. XLA's CPU runtime runs
independent operations at once, so when as many of those factorisations run together as the
pool has threads (the pool has one per core: two on a 2-core machine), every worker waits
for pieces that no free worker is left to run, and the process hangs with every thread
parked on a futex. Measured on the 2-core machine, jaxlib 0.10.2: a scan over two to eight
independent batched Cholesky factorisations of 256 20x20 matrices hung in 5 of 6 runs;
Gymnasium Walker2d-v5's one-step MJX check (``experiments/gymnasium_v5.py``) hung every time.
Single-threaded Eigen (``--xla_cpu_multi_thread_eigen=false``) did not help.

XLA's depth-first (memory-frugal) scheduler instead of its concurrency-optimised one makes
the program's buffers reuse each other, which orders those calls one after another: no hang
in 9 of 9 runs, Walker2d-v5's check and diagnosis done in 63 s. It costs some CPU throughput
(docs/BENCHMARKS.md) and leaves GPU programs alone. A user who sets the flag in
``XLA_FLAGS`` keeps theirs (``=true`` restores XLA's default).
"""
from __future__ import annotations

import os
from collections.abc import MutableMapping

FLAG_NAME = "xla_cpu_enable_concurrency_optimized_scheduler"
FLAG = f"--{FLAG_NAME}=false"


def avoid_cholesky_deadlock(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Add ``FLAG`` to ``environ["XLA_FLAGS"]`` unless it names the flag already.
    -> whether it was added. Takes effect only if JAX's backend has not started yet."""
    flags = environ.get("XLA_FLAGS", "")
    if FLAG_NAME in flags:
        return False
    environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True
