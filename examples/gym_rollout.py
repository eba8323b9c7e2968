"""Roll a policy in a learned simulator through Gymnasium (trains nothing).

    python examples/gym_rollout.py --ckpt runs/rl2s/checkpoints --data test.npz

The simulator comes from a checkpoint of `rl2s train`, the start states from a Dataset, the
policy is the Dataset's first policy (from the zoo its meta names). Prints the return of one
episode and, with the vector env, the mean return of 16 episodes stepped together.
"""
import argparse

import jax
import numpy as np

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.improve.gym_env import SimulatorGymEnv, SimulatorVectorEnv
from rl2s_jax.policy.policy import mode_action
from rl2s_jax.zoo.zoo import policies_for

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--ckpt", required=True, help="checkpoint directory of rl2s train")
parser.add_argument("--data", required=True, help="Dataset (.npz) naming its policies' zoo")
args = parser.parse_args()
ds = load_dataset(args.data)
policy = jax.tree_util.tree_map(lambda x: x[0], policies_for(ds))  # the data's first policy
act = jax.jit(mode_action)

# One episode: the ten lines of docs/EVALUATION.md ("Gymnasium").
env = SimulatorGymEnv.from_checkpoint(args.ckpt, ds)
obs, info = env.reset(seed=0)
episode_return, done = 0.0, False
while not done:
    obs, reward, terminated, truncated, info = env.step(np.asarray(act(policy, obs)))
    episode_return += reward
    done = terminated or truncated
print(f"one episode in the learned simulator: return {episode_return:.2f}")

# Sixteen episodes at once: one jitted device call per step, auto-reset in the same step.
envs = SimulatorVectorEnv.from_checkpoint(args.ckpt, ds, num_envs=16)
obs, info = envs.reset(seed=0)
returns, finished, running = np.zeros(16), np.zeros(16, bool), np.zeros(16)
while not finished.all():
    obs, reward, terminated, truncated, info = envs.step(np.asarray(act(policy, obs)))
    running += reward
    ended = (terminated | truncated) & ~finished
    returns[ended], finished = running[ended], finished | ended
print(f"16 episodes in the vector env: mean return {returns.mean():.2f}")
