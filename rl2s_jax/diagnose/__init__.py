"""Diagnosis: where a learned simulator is wrong, why, and how much an extended model gains.

See docs/DIAGNOSIS.md for the method and the report schema.
"""
# First: MuJoCo's MJX without its lines about the optional Warp backend (rl2s_jax/_quiet.py);
# this subpackage's modules import brax, which imports mujoco.mjx.
import rl2s_jax._quiet  # noqa: F401
