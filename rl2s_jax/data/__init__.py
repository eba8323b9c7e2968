"""Data: the Dataset (schema, file, validation), MJX collection, Minari, episodes, true values."""
# First: MuJoCo's MJX without its lines about the optional Warp backend (rl2s_jax/_quiet.py);
# this subpackage's modules import brax, which imports mujoco.mjx.
import rl2s_jax._quiet  # noqa: F401
