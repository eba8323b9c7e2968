"""rl2s_jax: Robust Learning to Simulate in JAX."""
