"""The control of the open-loop diagnostic (``ablation_model.py --open-loop``): the REAL
dynamics (``oracle.oracle_dynamics``) rolled from the test policies' logged states under their
logged actions, exactly and with a small unbiased error added at every step.

The diagnostic compares a learned simulator's k-step returns under the logged actions with the
logged ones, and reads a shortfall as the model's own bias. But a fixed action sequence does
not correct a drifting state the way the policy that chose it would: a system whose gait is
kept up by feedback may lose it under replayed actions after any small error, with no bias at
all. This script measures that: at noise scale 0 the oracle should reproduce the logged
returns (the check of the windows and the oracle); at a scale sigma each step's next state gets
sigma x N(0, 1) x the data's one-step change std per dim (not on the absolute positions, which
no step reads), an error of known size and no bias. The scale whose k = 1 and k = 10 errors
match a learned model's says what its k = 50 numbers would be from noise alone. It also
records the oracle's own one-step error on logged rows (``oracle_step_check``).

    python experiments/open_loop_control.py --task ant [--transitions-per-policy 2000]
        [--windows 32] [--ks 1,10,50] [--noise 0,0.01,0.03,0.1] [--seeds 2]
        [--data test.npz] [--out DIR]

CPU: Ant, 19 test policies x 32 windows x 50 steps x 4 scales x 2 seeds, about 10 minutes on 2
cores with the collection. Writes OUT/open_loop_control_<task>.json and prints a table.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.envs.tasks import get_task, task_names
from rl2s_jax.evaluate.errors import noisy, one_step_std, open_loop_inputs, open_loop_summary
from rl2s_jax.evaluate.oracle import oracle_dynamics
from rl2s_jax.model.simulator import mean_square, open_loop_returns, step_errors
from rl2s_jax.paper.ablation import load_test_split, parse_noise


def oracle_step_check(ds, task, n_rows: int = 4096, seed: int = 0) -> dict:
    """The oracle's own one-step error on logged rows (``simulate.step_errors`` against the
    logged next states, in stds of the logged one-step change per dim): how exact the real
    dynamics rebuilt from an observation are, the control of every error measured against
    them. -> {"rows", "rmse", "reward_bias", "reward_abs", "rmse_per_dim"}"""
    obs, act, nxt = (np.asarray(x) for x in (ds.obs, ds.action, ds.next_obs))
    idx = np.random.default_rng(seed).choice(len(obs), min(n_rows, len(obs)), replace=False)
    o, a, n = (jnp.asarray(x[idx]) for x in (obs, act, nxt))
    scale = jnp.asarray(np.std(nxt.astype(np.float64) - obs, 0), jnp.float32)
    pred = jax.jit(oracle_dynamics(task))(o, a, jax.random.PRNGKey(seed))
    z, dr = step_errors(pred, n, o, a, task.reward_fn, scale)
    return {"rows": int(idx.size), "rmse": float(jnp.sqrt(mean_square(z, scale).mean())),
            "reward_bias": float(dr.mean()), "reward_abs": float(jnp.abs(dr).mean()),
            "rmse_per_dim": np.round(np.sqrt((np.asarray(z, np.float64) ** 2).mean(0)),
                                     5).tolist()}


def run(ds, task, *, ks, n_windows: int, scales, seeds: int, window_seed: int = 7) -> dict:
    """The oracle's open loop at every noise scale and seed against the logged windows.
    -> {"scales": {scale: open_loop_summary over the seeds as lanes}, ...}"""
    k_max = max(ks)
    rows, steps, real_r, real_end, obs, act, n_steps = open_loop_inputs(
        ds, task, k_max, n_windows, seed=window_seed)
    noise_std = jnp.asarray(one_step_std(ds, task.position_dims))
    real_dyn = oracle_dynamics(task)

    @jax.jit
    def lanes(scale, keys):
        def one(key):
            r, _, ended = open_loop_returns(noisy(real_dyn, scale, noise_std), task.reward_fn,
                                            task.done_fn, obs, act, n_steps, key)
            return r, ended
        return jax.lax.map(one, keys)

    out = {"windows_per_policy": n_windows, "seeds": seeds, "scales": {}}
    for scale in scales:
        t0 = time.perf_counter()
        keys = jnp.stack([jax.random.PRNGKey(100 + s) for s in range(seeds)])
        sim_r, sim_end = (np.asarray(x) for x in lanes(jnp.float32(scale), keys))
        sim_r = sim_r.reshape(seeds, *rows.shape, k_max).astype(np.float64)
        sim_end = sim_end.reshape(seeds, *rows.shape, k_max)
        out["scales"][str(scale)] = open_loop_summary(real_r, real_end, steps, sim_r, sim_end,
                                                      ks)
        print(f"[open-loop control] scale {scale}: {time.perf_counter() - t0:.1f}s", flush=True)
    return out


def table(res: dict, ks) -> str:
    lines = ["| noise scale | k | tau | spread | relative error | windows that end, oracle vs "
             "logged |", "|---:|---:|---|---|---|---|"]
    for scale, by_k in res["scales"].items():
        for k in ks:
            v = by_k[str(k)]
            f = lambda xs: ", ".join(f"{x:.3g}" for x in xs)
            lines.append(f"| {scale} | {k} | {f(v['tau'])} | {f(v['spread_ratio'])} | "
                         f"{f(v['relative_error'])} | {f(v['model_end'])} vs {v['real_end']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ints = lambda t: tuple(sorted({int(x) for x in t.split(",") if x}))
    ap.add_argument("--task", choices=[t for t in task_names() if t != "pointmass"],
                    default="ant")
    ap.add_argument("--transitions-per-policy", type=int, default=2000)
    ap.add_argument("--windows", type=int, default=32)
    ap.add_argument("--ks", type=ints, default=(1, 10, 50))
    ap.add_argument("--noise", default="0,0.01,0.03,0.1")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--data", help="a Dataset .npz of the policies to use (default: collect "
                    "the zoo's test split)")
    ap.add_argument("--out", default="results/open_loop_control")
    args = ap.parse_args(argv)
    scales = parse_noise(args.noise, zero_ok=True)
    for name in ("transitions_per_policy", "windows", "seeds"):
        if getattr(args, name) < 1:
            raise SystemExit(f"{name.replace('_', '-')}: expected an int >= 1, got "
                             f"{getattr(args, name)}")
    if not args.ks or args.ks[0] < 1:
        raise SystemExit(f"ks: expected ints >= 1, got {args.ks}")
    os.makedirs(args.out, exist_ok=True)
    task = get_task(args.task)
    t0 = time.perf_counter()
    ds = load_test_split(args.task, args.data, args.transitions_per_policy)
    print(f"[open-loop control] {args.task}: {ds.n_policies} policies, {ds.n_transitions} "
          f"rows ({time.perf_counter() - t0:.1f}s) on {jax.devices()[0].device_kind} (jax "
          f"{jax.__version__})", flush=True)
    res = run(ds, task, ks=args.ks, n_windows=args.windows, scales=scales, seeds=args.seeds)
    res["oracle_step_error"] = check = oracle_step_check(ds, task)
    print(f"[open-loop control] the oracle's own one-step error on {check['rows']} logged rows: "
          f"rmse {check['rmse']:.2g} stds of a step's change, reward {check['reward_bias']:.2g} "
          f"(mean absolute {check['reward_abs']:.2g})", flush=True)
    res.update(task=args.task, command=" ".join(["python", "experiments/open_loop_control.py",
                                                 *(argv if argv is not None else sys.argv[1:])]),
               hardware=jax.devices()[0].device_kind, jax_version=jax.__version__,
               transitions=ds.n_transitions, wall_s=round(time.perf_counter() - t0, 1))
    path = os.path.join(args.out, f"open_loop_control_{args.task}.json")
    write_json(path, res)
    print(table(res, args.ks))
    print(f"[open-loop control] wrote {path} ({res['wall_s']}s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
