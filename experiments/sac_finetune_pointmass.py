"""SAC fine-tuning settings on pointmass (CPU, ~5 min): the numbers behind
``SACConfig.fine_tuning()`` (docs/EVALUATION.md, "Policy improvement").

    python experiments/sac_finetune_pointmass.py

Part 1 fine-tunes five PPO snapshots (mediocre to near optimal) in the real env with
``SACConfig.fine_tuning()``, without its KL anchor, with a stronger anchor, and with plain SAC
(``SACConfig()``: alpha from 1, target entropy -action_size, no anchor); 1000 iterations of
8 envs, 2 updates each, 400 critic warm-up updates. Part 2 fine-tunes snapshots 1 and 4 inside
a model with a planted error (reversed action where p > 0.3) with the uncertainty penalty
lambda * u (u = the exact error) for lambda in 0, 1, 5. Prints real returns C0 -> C1 (64
episodes each).
"""
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from rl2s_jax import policies as pol  # noqa: E402
from rl2s_jax.collect import measure_values  # noqa: E402
from rl2s_jax.improve import improve_policies, measure_improvement  # noqa: E402
from rl2s_jax.ppo import PPOConfig, make_ppo, train_snapshots  # noqa: E402
from rl2s_jax.sac import SACConfig  # noqa: E402
from rl2s_jax.sim_env import SimulatorEnv  # noqa: E402
from rl2s_jax.tasks import PointMass, get_task, pointmass_dynamics  # noqa: E402

SIZES = dict(n_envs=8, batch_size=128, hidden=(64, 64), warmup_steps=16, buffer_size=20_000,
             episode_length=50, updates_per_step=2, critic_warmup_updates=400)


def planted(o, a):
    return pointmass_dynamics(o, jnp.where(o[..., :1] > 0.3, -a, a))


def planted_error(o, a):
    return jnp.linalg.norm(planted(o, a) - pointmass_dynamics(o, a), axis=-1)


def run(env, params, cfg, label):
    t0 = time.perf_counter()
    after, _ = improve_policies(env, None, None, params, jax.random.PRNGKey(2), cfg,
                                n_iterations=1000)
    res = measure_improvement(PointMass(), params, after, jax.random.PRNGKey(3), n_episodes=64,
                              episode_length=50, gamma=0.99)
    print(f"{label:<28} C0 {np.round(res['c0'], 1)} -> C1 {np.round(res['c1'], 1)} "
          f"(SE {np.round(res['c1_se'], 1)}) {time.perf_counter() - t0:.0f}s", flush=True)


def main():
    env = PointMass()
    ppo = PPOConfig(num_envs=64, unroll_length=16, num_minibatches=4, episode_length=50,
                    gamma=0.95, learning_rate=1e-3)
    params = jax.jit(lambda k: train_snapshots(make_ppo(env, ppo), k, 4, 10))(
        jax.random.PRNGKey(0))
    v = measure_values(env, params, key=jax.random.PRNGKey(1), n_episodes=64, episode_length=50)
    print("PPO snapshots' real returns", np.round(np.asarray(v["value"]), 1))
    print("-- part 1: in the real env")
    for label, cfg in (("fine_tuning()", SACConfig.fine_tuning(**SIZES)),
                       ("fine_tuning(kl_weight=0)", SACConfig.fine_tuning(**SIZES, kl_weight=0.0)),
                       ("fine_tuning(kl_weight=0.1)",
                        SACConfig.fine_tuning(**SIZES, kl_weight=0.1)),
                       ("plain SACConfig()", SACConfig(**SIZES))):
        run(env, params, cfg, label)
    print("-- part 2: in a model with a planted error, snapshots 1 and 4")
    two = pol.index_params(params, np.array([1, 4]))
    pool = np.random.default_rng(0).uniform(-0.5, 0.5, (64, 2)).astype(np.float32)
    for lam in (0.0, 1.0, 5.0):
        sim = SimulatorEnv(lambda o, a, k: planted(o, a), pool, get_task("pointmass"),
                           uncertainty_fn=planted_error, uncertainty_penalty=lam)
        run(sim, two, SACConfig.fine_tuning(**SIZES), f"penalty lambda = {lam}")


if __name__ == "__main__":
    main()
