"""A fast front door (issue 65, item 4): the parser and ``import rl2s_jax`` load no JAX, brax
or MuJoCo; the parser's light names match what they stand for; the Gymnasium id exists after
``import rl2s_jax`` in either import order. Timings: docs/BENCHMARKS.md (a figure, not a test)."""

import subprocess
import sys
import textwrap

HEAVY = ("jax", "jaxlib", "brax", "mujoco", "flax", "optax", "orbax")


def run_python(code: str) -> str:
    """Run ``code`` in a fresh interpreter; its stdout (a failure shows its stderr)."""
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_cli_and_its_parser_load_no_jax():
    out = run_python(f"""
        import sys
        import rl2s_jax.cli as cli
        cli.build_parser().parse_args(["collect", "--task", "hopper", "--out", "x.npz",
                                       "--transitions-per-policy", "5"])
        print(sorted({{m.split(".")[0] for m in sys.modules}} & set({HEAVY!r})))""")
    assert out.strip() == "[]"


def test_import_rl2s_jax_is_lazy_until_a_public_name_is_used():
    out = run_python("""
        import sys
        import rl2s_jax
        print("jax" in sys.modules)
        from rl2s_jax import Dataset, load_simulator
        print("jax" in sys.modules, Dataset.__module__, load_simulator.__module__)
        missing = [n for n in rl2s_jax.__all__ if not hasattr(rl2s_jax, n)]
        print(missing, set(rl2s_jax.__all__) <= set(dir(rl2s_jax)))""")
    assert out.splitlines() == ["False", "True rl2s_jax.data.dataset rl2s_jax.train.checkpoint",
                                "[] True"]


def test_unknown_public_name_is_an_attribute_error():
    out = run_python("""
        import rl2s_jax
        try:
            rl2s_jax.no_such_name
        except AttributeError as err:
            print(err)""")
    assert "no attribute 'no_such_name'" in out


def test_light_names_match_the_registries():
    from rl2s_jax import _gym, _names
    from rl2s_jax.envs.tasks import BUILT_IN
    from rl2s_jax.improve import gym_env
    from rl2s_jax.improve.recipes import IMPROVE_RECIPES

    assert _names.BUILT_IN_TASKS == BUILT_IN
    assert sorted(_names.IMPROVE_RECIPE_NAMES) == sorted(IMPROVE_RECIPES)
    assert _gym.SIMULATOR_ENV_ID == gym_env.SIMULATOR_ENV_ID
    assert _gym._GYM_ENV == gym_env.__name__


def test_a_registered_task_is_a_parser_choice():
    """Registering imports envs.tasks; the parser then asks its registry."""
    out = run_python("""
        import jax.numpy as jnp
        import rl2s_jax
        from rl2s_jax import cli
        rl2s_jax.register("my_cart", reward_fn=lambda o, a, n: jnp.sum(n, -1),
                          done_fn=lambda n: n[..., 0] > 1, obs_size=2, action_size=1,
                          episode_length=10)
        args = cli.build_parser().parse_args(["collect", "--task", "my_cart", "--out", "x",
                                              "--transitions-per-policy", "5"])
        print(args.task)""")
    assert out.strip() == "my_cart"


def test_gymnasium_id_after_import_in_either_order():
    """gymnasium 1.x loads no plugin entry points: ``import rl2s_jax`` registers the id (no
    JAX loaded), before or after gymnasium; ``make`` reaches our entry point."""
    out = run_python("""
        import sys
        import rl2s_jax
        import gymnasium
        print(gymnasium.spec("rl2s/Simulator-v0").entry_point, "jax" in sys.modules)""")
    assert out.strip() == "rl2s_jax.improve.gym_env:make_simulator_env False"
    out = run_python("""
        import gymnasium
        try:
            gymnasium.make("rl2s_jax:rl2s/Simulator-v0", ckpt="/no/such/run", data="x.npz")
        except FileNotFoundError as err:
            print(err)""")
    assert "ckpt: no checkpoint directory /no/such/run" in out
