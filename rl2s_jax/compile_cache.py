"""JAX's persistent compilation cache, on by default for the `rl2s` command and the tests.

XLA compilation dominates short runs on the CPU (a small ``rl2s train``: 149 s cold, 8 s with a
warm cache). ``enable()`` points JAX at ``$RL2S_COMPILATION_CACHE`` (default
``~/.cache/rl2s_jax/xla``) unless JAX already has a cache directory; set
``RL2S_COMPILATION_CACHE=off`` (or ``0``, ``none``, empty) to run without one.

Processes share the directory (the tests' two workers, two ``paper.py`` on one GPU). Without
a size limit JAX writes an entry in place and reads it without a lock, so a process can read
another's half-written executable: a test worker died of a segmentation fault in
``compilation_cache.get_executable_and_time`` that way. With a limit (``MAX_BYTES``) JAX's
cache takes a file lock (the ``filelock`` package) around every read and write, and evicts the
least recently used entries beyond it.
"""
from __future__ import annotations

import os

import jax

ENV_VAR = "RL2S_COMPILATION_CACHE"
DEFAULT_DIR = os.path.join(os.path.expanduser("~"), ".cache", "rl2s_jax", "xla")
OFF = ("", "0", "off", "none", "false", "no")
MAX_BYTES = 8 * 1024**3  # the cache's size limit: what turns JAX's file lock on (docstring)


def cache_dir() -> str | None:
    """The directory ``enable`` would use, or None where the user turned the cache off."""
    value = os.environ.get(ENV_VAR, DEFAULT_DIR)
    return None if value.strip().lower() in OFF else os.path.expanduser(value)


def enable(min_compile_secs: float = 1.0) -> str | None:
    """Turn the persistent cache on (programs that compile for at least ``min_compile_secs``
    are stored); returns the directory, or None when it is off or JAX already has one."""
    directory = cache_dir()
    if directory is None or jax.config.jax_compilation_cache_dir:
        return None
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError:
        return None   # an unwritable home: run without the cache rather than fail
    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_secs)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    return directory
