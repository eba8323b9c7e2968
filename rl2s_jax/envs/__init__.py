"""Tasks: the MJX environments (brax, backend="mjx") with their reward and termination functions."""
# First: MuJoCo's MJX without its lines about the optional Warp backend (rl2s_jax/_quiet.py);
# this subpackage's modules import brax, which imports mujoco.mjx.
import rl2s_jax._quiet  # noqa: F401
