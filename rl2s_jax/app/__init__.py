"""What each command does, files in and files out: train, evaluate, improve, diagnose,
pipeline reports. ``rl2s_jax.cli`` only parses arguments and calls these."""
