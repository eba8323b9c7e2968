"""Calling rl2s_jax.train_step from your own JAX code.

Collects a small dataset on the tiny point-mass task, then trains an RL2S simulator with a
hand-written loop: init, a lax.scan over train_step, a vmap over two seeds, metrics read back
between chunks. Runs on the CPU in about a minute:

    python examples/custom_loop.py
"""
import time

import jax
import jax.numpy as jnp
import numpy as np

import rl2s_jax as rl2s
from rl2s_jax.data.collect import collect
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.policy import policy as policies

t_start = time.perf_counter()
task = get_task("pointmass")

# 1. Five policies that push the point mass in different directions collect the data.
zoo = []
for i, bias in enumerate([-2.0, -1.0, 0.0, 1.0, 2.0]):
    p = policies.init_policy(jax.random.PRNGKey(i), task.obs_size, task.action_size, hidden=(8,))
    p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:task.action_size].set(bias)
    zoo.append(p)
zoo = policies.stack_params(zoo)
ds = collect(task.make_env(), zoo, key=jax.random.PRNGKey(0), transitions_per_policy=1000,
             envs_per_policy=4, episode_length=task.episode_length, task="pointmass",
             value_episodes=16, progress=False)

# 2. Config (static) and device-resident data; the state is a plain pytree.
config = rl2s.TrainConfig.small().override(
    {"task": "pointmass", "method": "rl2s", "vd.horizon": task.episode_length})
data = rl2s.make_train_data(ds, zoo, config)
state = jax.jit(rl2s.init, static_argnums=1)(jax.random.PRNGKey(0), config, data)


# 3. Your own loop: a scanned chunk of train_step, jitted once.
@jax.jit
def chunk(state):
    def body(state, _):
        state, metrics = rl2s.train_step(state, data)
        return state, {k: metrics[k] for k in ("gen_loss", "disc_loss", "avd_train", "mvd_train")}
    return jax.lax.scan(body, state, None, length=20)


for _ in range(3):
    state, metrics = chunk(state)
    last = {k: float(v[-1]) for k, v in metrics.items()}
    print(f"step {int(state.step):3d}  " + "  ".join(f"{k} {v:8.3f}" for k, v in last.items()))

# 4. Two seeds as one program: vmap init and the scanned chunk over keys.
keys = jax.random.split(jax.random.PRNGKey(1), 2)
seeds = jax.vmap(lambda k: rl2s.init(k, config, data))(keys)
seeds, metrics = jax.jit(jax.vmap(chunk))(seeds)
avd = np.asarray(metrics["avd_train"][:, -1])
print("two seeds, AVD on the training policies:", np.round(avd, 3))

# 5. The learned simulator as a function: one step of every training policy's data.
sim = rl2s.simulator(state)
pred = sim.mean(jnp.asarray(ds.obs[:5]), jnp.asarray(ds.action[:5]))
print("predicted vs real next state:\n", np.c_[np.asarray(pred), ds.next_obs[:5]].round(3))
print(f"done in {time.perf_counter() - t_start:.0f}s")
