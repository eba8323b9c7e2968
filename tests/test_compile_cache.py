"""rl2s_jax.compile_cache: the persistent cache the tests and the CLI share, with its size
limit set, so that JAX locks each entry while one process writes it and another reads it."""
import jax


def test_the_cache_is_on_with_a_size_limit_and_its_file_lock():
    from jax._src.lru_cache import LRUCache

    from rl2s_jax import compile_cache

    # tests/conftest.py turned it on, as the CLI does
    assert jax.config.jax_compilation_cache_dir == compile_cache.cache_dir()
    assert jax.config.jax_compilation_cache_max_size == compile_cache.MAX_BYTES > 0
    cache = LRUCache(jax.config.jax_compilation_cache_dir,
                     max_size=jax.config.jax_compilation_cache_max_size)
    assert cache.eviction_enabled and cache.lock is not None  # filelock is installed
    cache.lock.acquire(timeout=10)  # the lock JAX's reads and writes take
    cache.lock.release()
