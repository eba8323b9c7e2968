"""Policies and the learners that train them: the tanh-Gaussian MLP policy, SAC, PPO."""
# First: MuJoCo's MJX without its lines about the optional Warp backend (rl2s_jax/_quiet.py);
# this subpackage's modules import brax, which imports mujoco.mjx.
import rl2s_jax._quiet  # noqa: F401
