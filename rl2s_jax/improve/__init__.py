"""Policy improvement inside a learned simulator: SAC fine-tuning, the deployment guard, the
simulator as a brax Env and as a Gymnasium env."""
# First: MuJoCo's MJX without its lines about the optional Warp backend (rl2s_jax/_quiet.py);
# this subpackage's modules import brax, which imports mujoco.mjx.
import rl2s_jax._quiet  # noqa: F401
