"""Your own system: a damped pendulum simulated in NumPy, no built-in task.

Its reward and termination rules are known, so they are registered from Python
(``rl2s_jax.envs.tasks.register``); its data is made here with plain NumPy and handed over as a
``Dataset`` (docs/DATA.md). Then a simulator is learned from the training policies' data and
ranks policies it never saw, against their logged returns. Runs on the CPU in about two
minutes:

    python examples/own_system.py [--quick]
"""
import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import rl2s_jax as rl2s
from rl2s_jax.data.dataset import Dataset
from rl2s_jax.envs.tasks import register
from rl2s_jax.evaluate.scores import evaluate_simulator
from rl2s_jax.policy import policy as policies

DT, GRAVITY, DAMPING, GAIN = 0.05, 9.8, 0.3, 4.0
EPISODE = 60


def pendulum_step(obs: np.ndarray, action: np.ndarray) -> np.ndarray:
    """The real system (NumPy): obs [..., 2] = (angle, angular velocity), action [..., 1]."""
    angle, vel = obs[..., 0], obs[..., 1]
    vel = vel + DT * (-GRAVITY * np.sin(angle) - DAMPING * vel + GAIN * action[..., 0])
    return np.stack([angle + DT * vel, vel], -1)


def reward_fn(obs, action, next_obs):
    """Upright is angle pi: reward 1 + cos(angle - pi) minus a small torque cost (JAX)."""
    return 1.0 - jnp.cos(next_obs[..., 0]) - 0.01 * jnp.sum(action ** 2, -1)


def done_fn(next_obs):
    return jnp.abs(next_obs[..., 1]) > 25.0  # spinning out of control ends an episode


def make_policies(n: int, seed: int, low: float, high: float):
    """n policies of the project's policy family, each pushed by its own constant bias."""
    ps = []
    for i, bias in enumerate(np.linspace(low, high, n)):
        p = policies.init_policy(jax.random.PRNGKey(seed + i), 2, 1, hidden=(16,))
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:1].set(bias)
        ps.append(p)
    return policies.stack_params(ps)


def record(params, n_episodes: int, seed: int) -> Dataset:
    """Each policy's episodes on the NumPy pendulum, as a Dataset (every row a transition)."""
    act = jax.jit(jax.vmap(policies.sample_action))  # over policies, each over its episodes
    P = jax.tree_util.tree_leaves(params)[0].shape[0]
    rng = np.random.default_rng(seed)
    obs = np.stack([rng.uniform(-0.3, 0.3, (P, n_episodes)), np.zeros((P, n_episodes))], -1)
    alive = np.ones((P, n_episodes), bool)
    rows = []
    key = jax.random.PRNGKey(seed)
    for t in range(EPISODE):
        key, k = jax.random.split(key)
        a = np.asarray(act(params, jnp.asarray(obs, jnp.float32), jax.random.split(k, P))[0])
        nxt = pendulum_step(obs, a)
        r = np.asarray(reward_fn(obs, a, nxt))
        done = np.asarray(done_fn(nxt))
        rows.append((obs, a, nxt, r, done, alive.copy(), t))
        alive &= ~done
        obs = nxt
    arrays = {k: [] for k in ("obs", "action", "next_obs", "reward", "done", "truncated",
                              "policy_id", "episode_id", "t")}
    for p in range(P):  # rows grouped by episode, in time order
        for e in range(n_episodes):
            for obs_t, a, nxt, r, done, live, t in rows:
                if not live[p, e]:
                    break
                arrays["obs"].append(obs_t[p, e])
                arrays["action"].append(a[p, e])
                arrays["next_obs"].append(nxt[p, e])
                arrays["reward"].append(r[p, e])
                arrays["done"].append(done[p, e])
                arrays["truncated"].append(t == EPISODE - 1 and not done[p, e])
                arrays["policy_id"].append(p)
                arrays["episode_id"].append(p * n_episodes + e)
                arrays["t"].append(t)
    dtypes = {"obs": np.float32, "action": np.float32, "next_obs": np.float32,
              "reward": np.float32, "done": bool, "truncated": bool, "policy_id": np.int32,
              "episode_id": np.int32, "t": np.int32}
    arrays = {k: np.asarray(v, dtypes[k]) for k, v in arrays.items()}
    meta = {"task": "damped_pendulum", "obs_size": 2, "action_size": 1, "n_policies": P,
            "gamma": None, "episode_length": EPISODE,
            "policy_names": [f"pendulum-{i:02d}" for i in range(P)],
            "source": {"recorded_by": "examples/own_system.py", "seed": seed}}
    return Dataset.from_arrays(arrays, meta)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer episodes and steps (tests)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    register("damped_pendulum", reward_fn=reward_fn, done_fn=done_fn, obs_size=2,
             action_size=1, episode_length=EPISODE, dt=DT, replace=True)
    train_pols = make_policies(6, seed=0, low=-1.5, high=1.5)
    test_pols = make_policies(6, seed=100, low=-0.8, high=2.0)  # unseen, another spread
    n_ep = 8 if args.quick else 24
    train_ds, test_ds = record(train_pols, n_ep, seed=1), record(test_pols, n_ep, seed=2)
    config = rl2s.TrainConfig.small().override(
        {"task": "damped_pendulum", "method": "bc", "vd.horizon": EPISODE, "gamma": 0.99})
    data = rl2s.make_train_data(train_ds, train_pols, config)
    state = jax.jit(rl2s.init, static_argnums=1)(jax.random.PRNGKey(0), config, data)
    steps = 20 if args.quick else 150
    state, metrics = jax.jit(rl2s.train_steps, static_argnums=2)(state, data, steps)
    report = evaluate_simulator(rl2s.simulator(state), test_ds, test_pols,
                                key=jax.random.PRNGKey(1), n_episodes=8, horizon=EPISODE,
                                gamma=0.99)
    m = report["metrics"]
    print(f"damped pendulum: {train_ds.n_transitions} training transitions of 6 policies; "
          f"after {steps} BC steps the simulator ranks 6 unseen policies with Kendall tau "
          f"{m['kendall_tau']:.2f} (AVD {m['avd']:.2f}; true values "
          f"{np.round(report['true_value'], 1)}; {time.perf_counter() - t0:.0f}s)")
    return report


if __name__ == "__main__":
    main()
