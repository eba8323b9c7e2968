"""rl2s_jax/_xla_cpu.py: the jaxlib CPU deadlock of concurrent batched Cholesky calls."""
import os
import subprocess
import sys
import textwrap

from rl2s_jax import _xla_cpu

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_flag_added_once_and_a_users_own_setting_kept():
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert _xla_cpu.avoid_cholesky_deadlock(env)
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {_xla_cpu.FLAG}"
    assert not _xla_cpu.avoid_cholesky_deadlock(env)  # idempotent
    assert env["XLA_FLAGS"].count(_xla_cpu.FLAG_NAME) == 1
    mine = {"XLA_FLAGS": f"--{_xla_cpu.FLAG_NAME}=true"}
    assert not _xla_cpu.avoid_cholesky_deadlock(mine)
    assert mine["XLA_FLAGS"] == f"--{_xla_cpu.FLAG_NAME}=true"
    empty = {}
    assert _xla_cpu.avoid_cholesky_deadlock(empty) and empty["XLA_FLAGS"] == _xla_cpu.FLAG


# Eight independent batched Cholesky factorisations per scan step: on the 2-core machine (XLA's
# intra-op pool: 2 threads) with XLA's concurrency-optimised scheduler this hung in 3 of 3 runs
# (jaxlib 0.10.2). A machine with many more cores may not hang without the flag either.
_CONCURRENT_CHOLESKY = textwrap.dedent("""
    import os
    import rl2s_jax  # sets the flag, as every rl2s command and script does
    import jax, jax.numpy as jnp
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    mats = [m @ jnp.swapaxes(m, -1, -2) + 20 * jnp.eye(20)
            for m in (jax.random.normal(k, (256, 20, 20)) for k in keys)]

    @jax.jit
    def run(mats):
        def body(c, _):
            return c + 1e-9 * sum(jnp.linalg.cholesky(a * (1 + 1e-3 * c)).sum()
                                  for a in mats), None
        return jax.lax.scan(body, 0.0, None, length=50)[0]

    print("flags", os.environ.get("XLA_FLAGS", ""), flush=True)
    print("done", float(run(mats)))
""")


def test_concurrent_batched_cholesky_does_not_hang_after_importing_rl2s_jax():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=ROOT)
    try:
        out = subprocess.run([sys.executable, "-c", _CONCURRENT_CHOLESKY], env=env,
                             capture_output=True, text=True, timeout=90)
    except subprocess.TimeoutExpired:
        raise AssertionError("8 concurrent batched Cholesky calls hung on a 2-thread pool "
                             "(rl2s_jax/_xla_cpu.py's flag not in effect?)") from None
    assert out.returncode == 0, out.stderr[-2000:]
    assert _xla_cpu.FLAG in out.stdout and "done" in out.stdout
