"""Your own system, with no task registered: a damped pendulum simulated in NumPy.

Nothing here tells rl2s_jax the system's reward or termination rule: its data (made here, with
plain NumPy, from a few policies) is a ``Dataset`` with ``meta.task = None``, like a log of a
real machine or a Minari import. `rl2s train` (here ``run_training``, the same code) then
learns the reward as a head r(s, a, s') fitted on the logged rewards and the termination as
a hazard h(s, a) fitted on the logged done flags, says so, and reports both against held-out
episodes; the simulator ranks policies it never saw, given as a policy file, against their
logged returns. (``examples/own_system.py`` registers the same kind of system's rules
instead.) Runs on the CPU in about a minute:

    python examples/own_system_unregistered.py [--quick] [--out DIR]
"""
import argparse
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import rl2s_jax as rl2s
from rl2s_jax.app.evaluation import evaluate_checkpoint
from rl2s_jax.app.training import format_summary
from rl2s_jax.policy import policy as policies

DT, GRAVITY, DAMPING, GAIN = 0.05, 9.8, 0.2, 5.0  # torque below gravity: it must pump
EPISODE = 100
SPIN_LIMIT = 7.0  # the machine's safety stop: |angular velocity| above this ends the run


def pendulum(obs: np.ndarray, action: np.ndarray):
    """The real system, one step (NumPy): obs [..., 2] = (angle, angular velocity), angle 0
    hanging down; action [..., 1]. -> (next obs, reward: height 1 - cos(angle) minus a torque
    cost, done: the safety stop fired)."""
    angle, vel = obs[..., 0], obs[..., 1]
    vel = vel + DT * (-GRAVITY * np.sin(angle) - DAMPING * vel + GAIN * action[..., 0])
    nxt = np.stack([angle + DT * vel, vel], -1)
    reward = 1.0 - np.cos(nxt[..., 0]) - 0.01 * np.sum(action ** 2, -1)
    return nxt, reward, np.abs(vel) > SPIN_LIMIT


def make_policies(n: int, seed: int) -> policies.Params:
    """n policies of the project's tanh-Gaussian MLP family, each a different controller: its
    pre-tanh mean k_v * velocity + k_a * angle + b (exactly: swish(x) - swish(-x) = x), so
    some pump the swing up and spin out, some hold it still, some push it aside."""
    rng = np.random.default_rng(seed)
    ps = []
    for i in range(n):
        p = policies.init_policy(jax.random.PRNGKey(seed + i), 2, 1, hidden=(4,))
        k_v, k_a, b = rng.uniform(-0.5, 3.0), rng.uniform(-1.5, 1.5), rng.uniform(-0.5, 0.5)
        w0 = np.zeros((2, 4), np.float32)
        w0[1, :2], w0[0, 2:] = (1.0, -1.0), (1.0, -1.0)  # units: +-velocity, +-angle
        w1 = np.zeros((4, 2), np.float32)
        w1[:, 0] = (k_v, -k_v, k_a, -k_a)
        p["layers"] = [{"w": jnp.asarray(w0), "b": jnp.zeros(4)},
                       {"w": jnp.asarray(w1), "b": jnp.asarray([b, -1.0], jnp.float32)}]
        ps.append(p)
    return policies.stack_params(ps)


def record(params, n_episodes: int, seed: int) -> rl2s.Dataset:
    """Each policy's episodes on the NumPy pendulum, as a Dataset of no task."""
    act = jax.jit(jax.vmap(policies.sample_action))  # over policies, each over its episodes
    P = jax.tree_util.tree_leaves(params)[0].shape[0]
    rng = np.random.default_rng(seed)
    obs = np.stack([rng.uniform(-0.3, 0.3, (P, n_episodes)), np.zeros((P, n_episodes))], -1)
    alive = np.ones((P, n_episodes), bool)
    steps = []
    key = jax.random.PRNGKey(seed)
    for _ in range(EPISODE):
        key, k = jax.random.split(key)
        a = np.asarray(act(params, jnp.asarray(obs, jnp.float32), jax.random.split(k, P))[0])
        nxt, reward, done = pendulum(obs, a)
        steps.append((obs, a, nxt, reward, done, alive.copy()))
        alive &= ~done
        obs = nxt
    cols = {k: [] for k in ("obs", "action", "next_obs", "reward", "done", "truncated",
                            "policy_id", "episode_id", "t")}
    for p in range(P):  # rows grouped by episode, in time order
        for e in range(n_episodes):
            for t, (o, a, nxt, r, done, live) in enumerate(steps):
                if not live[p, e]:
                    break
                for name, v in (("obs", o[p, e]), ("action", a[p, e]),
                                ("next_obs", nxt[p, e]), ("reward", r[p, e]),
                                ("done", done[p, e]),
                                ("truncated", t == EPISODE - 1 and not done[p, e]),
                                ("policy_id", p), ("episode_id", p * n_episodes + e),
                                ("t", t)):
                    cols[name].append(v)
    dtypes = dict(obs=np.float32, action=np.float32, next_obs=np.float32, reward=np.float32,
                  done=bool, truncated=bool, policy_id=np.int32, episode_id=np.int32,
                  t=np.int32)
    arrays = {k: np.asarray(v, dtypes[k]) for k, v in cols.items()}
    meta = {"task": None, "obs_size": 2, "action_size": 1, "n_policies": P, "gamma": None,
            "episode_length": EPISODE, "policy_names": [f"pendulum-{i:02d}" for i in range(P)],
            "source": {"recorded_by": "examples/own_system_unregistered.py", "seed": seed}}
    return rl2s.Dataset.from_arrays(arrays, meta)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer episodes and steps (tests)")
    ap.add_argument("--out", help="directory for the data, policies and run (default: a "
                    "temporary one)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = args.out or tempfile.mkdtemp(prefix="rl2s_pendulum_")
    os.makedirs(out, exist_ok=True)
    train_pols, test_pols = make_policies(6, seed=0), make_policies(6, seed=100)  # unseen
    n_ep = 10 if args.quick else 24
    paths = {k: os.path.join(out, f"{k}.npz") for k in ("train", "test")}
    for split, params, seed in (("train", train_pols, 1), ("test", test_pols, 2)):
        rl2s.save_dataset(paths[split], record(params, n_ep, seed))
        rl2s.save_policies(os.path.join(out, f"{split}_policies.npz"), params,
                           [f"pendulum-{i:02d}" for i in range(6)])
    # the cpu profile's model, smaller learned reward and termination heads
    overrides = dict(vd_horizon=EPISODE, hazard_hidden=(64, 64), hazard_steps=1500,
                     reward_hidden=(64, 64), reward_steps=1500)
    summary = rl2s.run_training(rl2s.TrainSpec(
        paths["train"], 40 if args.quick else 150, os.path.join(out, "run"), "bc",
        profile="cpu", policy_file=os.path.join(out, "train_policies.npz"), set=overrides,
        quiet=True))
    print(format_summary(summary))
    report = evaluate_checkpoint(os.path.join(out, "run", "checkpoints"), paths["test"],
                                 policy_file=os.path.join(out, "test_policies.npz"))
    m = report["metrics"]
    print(f"damped pendulum, no task registered: the simulator (reward and termination "
          f"learned from the data) ranks 6 unseen policies with Kendall tau "
          f"{m['kendall_tau']:.2f} (AVD {m['avd']:.2f}; true values "
          f"{np.round(report['true_value'], 1)}, simulated "
          f"{np.round(report['sim_value'], 1)}; {time.perf_counter() - t0:.0f}s) -> {out}")
    return {"report": report, "summary": summary}


if __name__ == "__main__":
    main()
