"""Why do simulated robots fall? (issue 10; docs/RESULTS.md, "The model fix").

Trains one BC ensemble (3 members of 4x200 unless --set says otherwise) on the zoo's train
split and prints, every --every steps, one JSON line: the one-step error of the elites' mean in
delta stds (normalised MSE, per dim on the TEST policies' rows, and over every 7th training
row), and each test policy's simulated episode length and value under the --rollouts settings
(MODE:NOISE), sorted by true value. --oracle-noise runs the REAL dynamics with Gaussian noise of
that many delta stds added at every step (how much i.i.d. noise the policies survive).

    python experiments/rollout_error_study.py --task walker2d --n 10000 --steps 400 \\
        --every 200 --rollouts random:1,mean:0 --set bc_lr=1e-3 nll_beta=0 \\
        [--oracle-noise 0,0.05,0.2]

Data: the zoo's split, collected once into --data-dir (paper.load_or_collect).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ablation_model import episode_lengths, parse_rollouts  # noqa: E402
from paper import _lane_returns, load_or_collect, train_lanes  # noqa: E402

from rl2s_jax.cli import _overrides  # noqa: E402
from rl2s_jax.evaluate import ranking_metrics  # noqa: E402
from rl2s_jax.fit import make_config, policies_for  # noqa: E402
from rl2s_jax.oracle import oracle_dynamics  # noqa: E402
from rl2s_jax.simulate import simulated_returns, start_pool  # noqa: E402
from rl2s_jax.tasks import get_task  # noqa: E402
from rl2s_jax.train import init, make_train_data, simulator, true_values  # noqa: E402


def normalised_mse(sim, obs, action, next_obs) -> np.ndarray:
    """Per-dim mean squared error of the mean next state, in delta stds. -> [o]"""
    mean = np.asarray(jax.jit(sim.mean)(obs, action))
    err = (mean - np.asarray(next_obs)) / np.asarray(sim.norm.delta_std)
    return (err**2).mean(0)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="walker2d")
    p.add_argument("--n", type=int, default=10_000, help="transitions per policy")
    p.add_argument("--data-dir", default="/tmp/study")
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--every", type=int, default=200)
    p.add_argument("--set", nargs="*", default=[], help="TrainConfig field=value")
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--horizon", type=int, default=1000)
    p.add_argument("--rollouts", default="random:1,mean:0")
    p.add_argument("--oracle-noise", default="")
    a = p.parse_args(argv)
    rollouts = parse_rollouts(a.rollouts)
    task = get_task(a.task)
    data_dir = os.path.join(a.data_dir, f"data_{a.task}")
    d, _ = load_or_collect(a.task, {"transitions_per_policy": a.n, "value_episodes": 4},
                           data_dir, 0, None, True)
    train_ds, test_ds = d["train"], d["test"]
    overrides = dict(gen_hidden=(200, 200, 200, 200), ensemble_size=3, n_elites=2,
                     holdout_rows=4096, vd_every=0)
    overrides.update(_overrides(a.set))
    cfg = make_config(train_ds, "bc", "gpu", overrides=overrides)
    data = make_train_data(train_ds, policies_for(train_ds), cfg)
    test_pols, pool = policies_for(test_ds), start_pool(test_ds)
    truth = true_values(test_ds, a.horizon, cfg.gamma)
    order = np.argsort(truth)
    print(json.dumps({"true_values": np.round(truth[order]).tolist(),
                      "true_lengths": np.round(episode_lengths(test_ds)[order]).tolist()}))
    test_rows = [jnp.asarray(np.asarray(x)) for x in (test_ds.obs, test_ds.action,
                                                       test_ds.next_obs)]
    train_rows = [jnp.asarray(np.asarray(x)[::7]) for x in (train_ds.obs, train_ds.action,
                                                             train_ds.next_obs)]
    states = jax.jit(jax.vmap(lambda k, dd: init(k, cfg, dd), in_axes=(0, None)))(
        jax.random.PRNGKey(0)[None], data)
    compiled, t0 = {}, time.time()
    for _ in range(a.steps // a.every):
        states, _ = jax.block_until_ready(train_lanes(states, data, a.every, cfg, compiled))
        sims = simulator(states, average=False)
        one = jax.tree_util.tree_map(lambda x: x[0], sims)
        per_dim = normalised_mse(one, *test_rows)
        point = {"step": int(states.step[0]), "seconds": round(time.time() - t0, 1),
                 "train_nmse": float(normalised_mse(one, *train_rows).mean()),
                 "test_nmse": float(per_dim.mean()),
                 "test_nmse_per_dim": np.round(per_dim, 4).tolist()}
        for mode, noise in rollouts:
            ret, length = _lane_returns(sims.replace(member_mode=mode, noise_scale=noise),
                                        test_pols, pool, jax.random.PRNGKey(7)[None],
                                        n_episodes=a.episodes, horizon=a.horizon,
                                        gamma=cfg.gamma)
            v, ln = np.asarray(ret)[0].mean(-1), np.asarray(length)[0].mean(-1)
            r = ranking_metrics(truth, v, ks=(1,))
            point[f"{mode}:{noise:g}"] = {
                "tau": round(float(r["kendall_tau"]), 3), "avd": round(float(r["avd"]), 1),
                "lengths": np.round(ln[order]).tolist(), "values": np.round(v[order]).tolist()}
        print(json.dumps(point), flush=True)
    delta_std = jnp.asarray(np.asarray(sims.norm.delta_std)[0])
    real = oracle_dynamics(task)
    for sigma in (float(x) for x in a.oracle_noise.split(",") if x.strip()):
        def noisy(obs, action, key, sigma=sigma):
            k_real, k_noise = jax.random.split(key)
            nxt = real(obs, action, k_real)
            return nxt + sigma * delta_std * jax.random.normal(k_noise, nxt.shape)

        ret, length = jax.jit(lambda k, f=noisy: simulated_returns(
            test_pols, f, task.reward_fn, task.done_fn, pool, k, n_episodes=a.episodes,
            horizon=a.horizon, gamma=cfg.gamma))(jax.random.PRNGKey(3))
        v, ln = np.asarray(ret).mean(-1), np.asarray(length).mean(-1)
        r = ranking_metrics(truth, v, ks=(1,))
        print(json.dumps({"oracle_noise": sigma, "tau": round(float(r["kendall_tau"]), 3),
                          "lengths": np.round(ln[order]).tolist(),
                          "values": np.round(v[order]).tolist()}), flush=True)


if __name__ == "__main__":
    main()
