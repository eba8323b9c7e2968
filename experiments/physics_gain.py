"""The gain of calibrating the physics (issue 62, item 4), side by side, on CPU sizes.

Planted C-MuJoCo Hopper cases (amounts fixed in CASES before any result was looked at). Per
case and collection seed: training data from the shipped Hopper zoo's TRAINING policies
(``collect_measured``, the change planted), held-out episodes of the same policies (another
collection seed), and the zoo's TEST policies' true values measured in the planted C model
(``simulator.c_values`` on ``measured.plant``'s model, the same start states and policy draws
for every simulator). ``identify`` calibrates on the training data; then, for the nominal and
the calibrated physics: one-step and open-loop k-step normalised RMSE on the held-out
episodes (``physics_errors``), value error AVD / MVD and Kendall tau on the test policies
(values from ``c_values``: C MuJoCo with the identified quantities, equal to the MJX
simulator's on a short horizon, tests/test_physics_simulator.py). Cells: mean [min, max]
over the seeds. Not measured here: the hybrid (physics + learned residual) and the learned
simulators (RL2S, BC).

    PYTHONPATH=. python experiments/physics_gain.py --seeds 0 1 2 --out /tmp/physics_gain.json

Measured with the command above (2-core AMD EPYC CPU, shared; jax 0.10.2, mujoco 4.0.0;
about 6 min; every run named the planted quantity, element and value; docs/DIAGNOSIS.md,
"Physics", "The gain", says why the calibrated rows are round-off: the data come from
the same C engine):

    case       simulator   one-step  k-step    AVD       MVD       tau   (means of 3 seeds)
    mass       nominal     0.0727    0.403     1.13      6.21      0.958
    mass       calibrated  3.63e-06  3.23e-06  1.24e-06  6.7e-06   1.000
    friction   nominal     0.16      0.573     2.49      17.5      0.912
    friction   calibrated  5.07e-06  3.24e-06  0.000338  0.00672   1.000
    gear       nominal     0.153     1.17      1.16      7.98      0.968
    gear       calibrated  5.02e-06  3.14e-06  1.87e-06  1.88e-05  1.000
    damping    nominal     0.0154    0.252     0.77      4.82      0.961
    damping    calibrated  3.72e-06  3.26e-06  1.9e-06   1.29e-05  1.000
    delay      nominal     0.475     3.15      14.7      46.7      0.702
    delay      calibrated  3.68e-06  3.04e-06  0         0         1.000

with [min, max] over seeds in the docs' table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np

from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.metrics import kendall_tau, value_differences
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.physics.calibrated import c_values, calibrated_mj, obs_bias_of
from rl2s_jax.physics.identify import FitConfig, identify
from rl2s_jax.physics.measured import Planted, collect_measured, plant
from rl2s_jax.physics.mjx_model import physics_model
from rl2s_jax.physics.residuals import physics_errors
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

CASES = {
    "mass": [("body_mass", "torso", 1.3)],
    "friction": [("geom_friction", "foot_geom", 0.6)],
    "gear": [("actuator_gear", "leg_joint", 0.7)],
    "damping": [("dof_damping", "foot_joint", 3.0)],
    "delay": [("action_delay", "thigh_joint", 2)],
}
METRICS = ("one_step", "kstep", "avd", "mvd", "tau")


def run_case(pm, task, zoo, case: str, seed: int, args) -> dict:
    """One planted case and seed -> {"found": top_cause, "nominal": {...}, "calibrated": {...}}."""
    changes = [Planted(*c) for c in CASES[case]]
    train_p, test_p = index_params(zoo.params, zoo.train_ids), index_params(zoo.params,
                                                                            zoo.test_ids)
    sizes = dict(transitions_per_policy=args.transitions, episode_length=args.episode_length,
                 changes=changes)
    train = collect_measured(pm, train_p, seed=seed, **sizes)
    held = collect_measured(pm, train_p, seed=1000 + seed, **sizes)
    t0 = time.perf_counter()
    found = identify(pm, train, FitConfig(rows=args.rows, seed=seed))
    seconds = time.perf_counter() - t0
    mj_true, d_true, truth = plant(pm, changes)
    pool, key = start_pool(held), jax.random.PRNGKey(seed)
    vals = dict(n_episodes=args.episodes, horizon=args.horizon, gamma=args.gamma)
    true, _ = c_values(pm, mj_true, d_true, test_p, task, pool, key, **vals)
    out = {"truth": truth, "found": found["top_cause"], "identify_s": seconds}
    zero = np.zeros(len(pm.candidates))
    for name, (theta, delays) in {"nominal": (zero, None),
                                  "calibrated": (found["theta"], found["delays"])}.items():
        err = physics_errors(pm, held, theta, delays, k=args.k, seed=seed)
        sim, _ = c_values(pm, calibrated_mj(pm, theta), delays, test_p, task, pool, key,
                          bias=obs_bias_of(pm, theta), **vals)
        vd = value_differences(true, sim)
        out[name] = {"one_step": err["one_step"]["rmse"], "kstep": err["kstep"][-1],
                     "avd": vd["avd"], "mvd": vd["mvd"], "tau": kendall_tau(true, sim)}
    return out


def table(results: dict) -> str:
    """Markdown: per case and simulator, each metric's mean [min, max] over seeds."""
    head = ("| case | simulator | one-step RMSE | k-step RMSE | AVD | MVD | Kendall tau |\n"
            "|---|---|---|---|---|---|---|")
    lines = [head]
    for case, runs in results.items():
        for sim in ("nominal", "calibrated"):
            cells = []
            for m in METRICS:
                x = np.array([r[sim][m] for r in runs])
                cells.append(f"{x.mean():.3g} [{x.min():.3g}, {x.max():.3g}]")
            lines.append(f"| {case} | {sim} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--transitions", type=int, default=300, help="per training policy")
    ap.add_argument("--episode-length", type=int, default=100)
    ap.add_argument("--rows", type=int, default=256, help="identify's rows per half")
    ap.add_argument("--k", type=int, default=10, help="open-loop steps of the k-step error")
    ap.add_argument("--episodes", type=int, default=5, help="value episodes per test policy")
    ap.add_argument("--horizon", type=int, default=100)
    ap.add_argument("--gamma", type=float, default=0.99)
    ap.add_argument("--out", default=None, help="write every run as JSON here")
    args = ap.parse_args(argv)
    pm, task, zoo = physics_model("hopper"), get_task("hopper"), load_zoo("hopper")
    results = {}
    for case in args.cases:
        results[case] = []
        for seed in args.seeds:
            r = run_case(pm, task, zoo, case, seed, args)
            results[case].append(r)
            f = r["found"]
            print(f"{case} seed {seed}: found "
                  f"{None if f is None else (f['name'], f['element'], round(f['value'], 4))}"
                  f" (truth {r['truth'][0]['value']:.4g}) in {r['identify_s']:.1f} s; "
                  f"nominal {r['nominal']}; calibrated {r['calibrated']}", flush=True)
    print(table(results))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"args": vars(args), "results": results}, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
