"""The gain of calibrating the physics (issue 62, item 4): nominal and calibrated physics beside
the learned simulators (BC, RL2S) and the hybrid, on planted C-MuJoCo Hopper cases.

Planted C-MuJoCo Hopper cases (amounts fixed in CASES before any result was looked at). Per
case and collection seed: training data from the shipped Hopper zoo's TRAINING policies
(``collect_measured``, the change planted), held-out episodes of the same policies (another
collection seed), and the zoo's TEST policies' true values measured in the planted C model
(``simulator.c_values`` on ``measured.plant``'s model, the same start states and policy draws
for every simulator). ``identify`` calibrates on the training data; then, for the nominal and
the calibrated physics: one-step and open-loop k-step normalised RMSE on the held-out
episodes (``physics_errors``), value error AVD / MVD and Kendall tau on the test policies
(values from ``c_values``: C MuJoCo with the identified quantities, equal to the MJX
simulator's on a short horizon, tests/test_physics_simulator.py).

The learned simulators (``--learned bc rl2s``) are trained on the same training data (saved
as ``--work``/<case>_<seed>/train.npz) by the project's own training, ``rl2s train``'s
``app.training.run_training`` (``paper.simulator_gain.train_learned``; the training profile
``--train-profile``, ``--steps`` steps, VD at this script's gamma and horizon) and scored
alike (``paper.simulator_gain``: the same held-out rows and windows, their mean next state
fed the logged actions; values from the same start states and policy draws). The hybrid's
column (``rl2s_jax.physics.hybrid``'s ``fit_hybrid``; ``hybrid_row`` says what it calls) is
trained on the calibrated physics' residual and scored alike; where that module does not
import, it is skipped with a printed note. The
table: mean over seeds with a 95% t interval (``stats.t_interval``).

Profiles (explicit flags override them; PROFILES):

- ``cpu``: to check the code end to end on a 2-core CPU: 300 transitions per policy, 150
  training steps (100 of them BC pre-training for RL2S), 5 value episodes. One case and seed
  (``--profile cpu --cases mass --seeds 0``) took 373 s wall on the shared 2-core CPU (the
  process got 41% of it; 150 s of CPU): collection, identification and the physics' values
  ~36 s, BC 74 s, RL2S 263 s (compilation included); with ``--learned`` (none) and ``--jobs
  2``, two cases in 153 s. The hybrid column, run in an export of branch ``hybrid`` (050e734)
  with this script and ``paper/simulator_gain.py``, ``physics/residuals.py`` copied in
  (``--cases delay --seeds 0 --learned --episodes 2 --horizon 30 --k 3``): 294 s on the CPU
  (its MJX base compiles), one-step 5.4e-6, k-step 6.9e-6, AVD 9e-6, tau 1 (the calibration
  is exact here, so the residual it learns is ~0; nominal 0.466, 1.15, 2.97, 0.789).
- ``gpu``: the table, on one H200 host (16 cores) in one device call, ``--jobs 15`` (one
  process per case and seed: C MuJoCo is single-threaded; every process allocates GPU memory
  as it needs it): 1000 transitions per policy, 600 training steps of the ``cpu`` training
  profile's members (3 of 3x128; the paper's 7 of 4x512 with 1000 pre-training steps do not
  fit 15 units into one 9-minute call), 16 value episodes. Measured (2026-11-28, main at
  a714f44, jax 0.11.2, mujoco 4.0.0): 432 s in the script, 7 min 18 s wall, on a 2x H200
  host's 32 cores and GPU 0, both shared with an Ant protocol run: identification 2.6-7.8 s,
  BC 25-42 s, the hybrid 60-89 s, RL2S 103-113 s per unit (compilation included). The table
  (docs/results/physics_gain.json, RESULTS; docs/DIAGNOSIS.md "The gain" reads it): 14 of
  15 runs named the planted quantity (damping seed 2 nothing); the calibrated physics at
  round-off (~3.5e-6; friction seed 2 5e-4) and tau 1.000 where named; the hybrid one-step
  1.2e-4 - 7e-4, tau 0.996 - 1.000; BC tau 0.69 - 0.89 and RL2S 0.51 - 0.85, both below the
  nominal physics' 0.78 - 0.98 in every case at these sizes. The JSON is rewritten after
  every unit (its folder is made first), so a call cut short keeps what finished, and
  ``--resume`` (same command) runs only the rest:

    timeout 540 env PYTHONPATH=. python experiments/physics_gain.py --profile gpu --jobs 15 \
        --out docs/results/physics_gain.json [--resume]
    python experiments/paper_tables.py   # RESULTS' block from the JSON

Measured before the learned simulators were added, with ``python experiments/physics_gain.py
--seeds 0 1 2 --out /tmp/physics_gain.json`` (today: add ``--learned`` with no method; the
``cpu`` profile has these sizes) (2-core AMD EPYC CPU, shared; jax 0.10.2,
mujoco 4.0.0; about 6 min; every run named the planted quantity, element and value;
docs/DIAGNOSIS.md, "Physics", "The gain", says why the calibrated rows are round-off: the data
come from the same C engine):

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
import functools
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context

import jax
import mujoco
import numpy as np

from rl2s_jax import compile_cache
from rl2s_jax._files import write_text
from rl2s_jax.app.report import machine_info
from rl2s_jax.app.training import make_config
from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.paper.simulator_gain import (
    gain_rows,
    learned_scores,
    seed_summary,
    train_learned,
    value_scores,
)
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
PROFILES = {
    "cpu": dict(transitions=300, episode_length=100, rows=256, k=10, episodes=5, horizon=100,
                steps=150, train_profile="cpu"),
    "gpu": dict(transitions=1000, episode_length=100, rows=256, k=10, episodes=16, horizon=100,
                steps=600, train_profile="cpu"),
}
SIMULATORS = ("nominal", "calibrated", "hybrid", "bc", "rl2s")


@functools.cache
def _models():
    compile_cache.enable()  # as the CLI: each --jobs process reuses what another compiled
    return physics_model("hopper"), get_task("hopper"), load_zoo("hopper")


def hybrid_row(found: dict, train, ctx: dict, args) -> dict | None:
    """The hybrid's column (branch ``hybrid``'s ``physics/hybrid.py``): ``fit_hybrid(train,
    policies, calibrated, steps=, config=, seed=)`` learns what the calibrated physics (this
    run's identified theta and delays, as calibrated.json holds them) leaves of the training
    data, with the BC members' settings; scored as the learned simulators are (its members
    read the logged past actions its delays need). None (main prints why, once) when that
    module or function is absent."""
    try:
        from rl2s_jax.physics import hybrid  # local: another branch's module, optional
    except ImportError:
        return None
    if not hasattr(hybrid, "fit_hybrid"):
        return None
    pm = ctx["pm"]
    calibrated = {"task": pm.task, "xml": pm.xml_path, "n_frames": pm.n_frames,
                  "theta": [float(x) for x in found["theta"]],
                  "delays": [int(d) for d in found["delays"]],
                  "labels": [c.label for c in pm.candidates]}
    config = make_config(train, "bc", args.train_profile,
                         overrides={"gamma": args.gamma, "vd.horizon": args.horizon})
    sim = hybrid.fit_hybrid(train, ctx["train_p"], calibrated, steps=args.steps, config=config,
                            seed=ctx["seed"])
    return learned_scores(sim, ctx["held"], ctx["task"], ctx["test_p"], ctx["pool"],
                          ctx["key"], ctx["true"], k=args.k, seed=ctx["seed"],
                          n_episodes=args.episodes, horizon=args.horizon, gamma=args.gamma)


def run_case(case: str, seed: int, args) -> dict:
    """One planted case and seed -> {"truth", "found", "identify_s", and a row per simulator:
    {"one_step", "kstep", "avd", "mvd", "tau"} (None where skipped)}."""
    pm, task, zoo = _models()
    changes = [Planted(*c) for c in CASES[case]]
    train_p, test_p = index_params(zoo.params, zoo.train_ids), index_params(zoo.params,
                                                                            zoo.test_ids)
    ids = list(zoo.train_ids)
    sizes = dict(transitions_per_policy=args.transitions, episode_length=args.episode_length,
                 changes=changes, policy_names=zoo.policy_names(ids),
                 source={"zoo": "hopper", "zoo_ids": ids})
    train = collect_measured(pm, train_p, seed=seed, **sizes)
    held = collect_measured(pm, train_p, seed=1000 + seed, **sizes)
    folder = os.path.join(args.work, f"{case}_{seed}")
    os.makedirs(folder, exist_ok=True)
    train_path = os.path.join(folder, "train.npz")
    save_dataset(train_path, train)
    t0 = time.perf_counter()
    found = identify(pm, train, FitConfig(rows=args.rows, seed=seed))
    seconds = time.perf_counter() - t0
    mj_true, d_true, truth = plant(pm, changes)
    pool, key = start_pool(held), jax.random.PRNGKey(seed)
    vals = dict(n_episodes=args.episodes, horizon=args.horizon, gamma=args.gamma)
    true, _ = c_values(pm, mj_true, d_true, test_p, task, pool, key, **vals)
    out = {"case": case, "seed": seed, "truth": truth, "found": found["top_cause"],
           "identify_s": seconds, "seconds": {}}
    zero = np.zeros(len(pm.candidates))
    for name, (theta, delays) in {"nominal": (zero, None),
                                  "calibrated": (found["theta"], found["delays"])}.items():
        err = physics_errors(pm, held, theta, delays, k=args.k, seed=seed)
        sim, _ = c_values(pm, calibrated_mj(pm, theta), delays, test_p, task, pool, key,
                          bias=obs_bias_of(pm, theta), **vals)
        out[name] = {"one_step": err["one_step"]["rmse"], "kstep": err["kstep"][-1],
                     **value_scores(true, sim)}
    ctx = dict(pm=pm, task=task, held=held, train_p=train_p, test_p=test_p, pool=pool, key=key,
               true=true, seed=seed)
    t0 = time.perf_counter()
    out["hybrid"] = hybrid_row(found, train, ctx, args)
    out["seconds"]["hybrid"] = time.perf_counter() - t0
    for method in args.learned:
        t0 = time.perf_counter()
        sim = train_learned(train_path, method, os.path.join(folder, method), steps=args.steps,
                            profile=args.train_profile, seed=seed, gamma=args.gamma,
                            horizon=args.horizon, log=lambda s: None)
        out[method] = learned_scores(sim, held, task, test_p, pool, key, true, k=args.k,
                                     seed=seed, **vals)
        out["seconds"][method] = time.perf_counter() - t0
    return out


def _unit(unit: tuple[str, int], args) -> tuple[str, int, dict]:
    case, seed = unit
    return case, seed, run_case(case, seed, args)


def _report(case: str, seed: int, r: dict) -> None:
    f = r["found"]
    rows = "; ".join(f"{s} " + " ".join(f"{m} {v:.3g}" for m, v in r[s].items())
                     for s in SIMULATORS if r.get(s))
    print(f"{case} seed {seed}: found "
          f"{None if f is None else (f['name'], f['element'], round(f['value'], 4))}"
          f" (truth {r['truth'][0]['value']:.4g}) in {r['identify_s']:.1f} s; {rows}; "
          f"seconds {({k: round(v, 1) for k, v in r['seconds'].items()})}", flush=True)


def parse(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--profile", default="cpu", choices=list(PROFILES))
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--transitions", type=int, help="per training policy")
    ap.add_argument("--episode-length", type=int)
    ap.add_argument("--rows", type=int, help="identify's rows per half")
    ap.add_argument("--k", type=int, help="open-loop steps of the k-step error")
    ap.add_argument("--episodes", type=int, help="value episodes per test policy")
    ap.add_argument("--horizon", type=int)
    ap.add_argument("--gamma", type=float, default=0.99)
    ap.add_argument("--learned", nargs="*", default=["bc", "rl2s"], choices=["bc", "rl2s"])
    ap.add_argument("--steps", type=int, help="training steps of each learned simulator")
    ap.add_argument("--train-profile", choices=["cpu", "gpu"], help="rl2s train's --profile")
    ap.add_argument("--jobs", type=int, default=1, help="processes, one (case, seed) each")
    ap.add_argument("--work", default=None, help="folder for the data and checkpoints")
    ap.add_argument("--out", default=None, help="write every run as JSON here")
    ap.add_argument("--resume", action="store_true", help="keep the (case, seed) units that "
                    "--out already holds (the same sizes: yours to keep) and run the rest")
    args = ap.parse_args(argv)
    for name, value in PROFILES[args.profile].items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    args.work = args.work or tempfile.mkdtemp(prefix="physics_gain_")
    return args


def summarise(results: dict) -> dict:
    """{case: {seed: run}} -> {case: seed_summary over its seeds so far}."""
    return {c: seed_summary([runs[s] for s in sorted(runs)], list(SIMULATORS))
            for c, runs in results.items() if runs}


def write(args, argv, results: dict, seconds: float, n_units: int) -> None:
    """The JSON of the units done so far ("complete" once all ``n_units`` are)."""
    done = sum(len(r) for r in results.values())
    doc = {"command": "PYTHONPATH=. python experiments/physics_gain.py " + " ".join(argv),
           "machine": {**machine_info(), "cpu_count": os.cpu_count(),
                       "mujoco": mujoco.__version__},
           "seconds": seconds, "complete": done == n_units, "units_done": done,
           "args": vars(args), "summary": summarise(results),
           "results": {c: [runs[s] for s in sorted(runs)] for c, runs in results.items()}}
    write_text(args.out, json.dumps(doc, indent=1, default=float))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse(argv)
    if args.out:  # its folder before any work: a missing one lost a whole GPU run
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    # several processes share one GPU: each takes the memory it needs, not 75% of it
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    try:
        from rl2s_jax.physics import hybrid  # local: another branch's module, optional
        if not hasattr(hybrid, "fit_hybrid"):
            print("hybrid: skipped (rl2s_jax.physics.hybrid has no fit_hybrid; hybrid_row "
                  "says what it calls)", flush=True)
    except ImportError as e:
        print(f"hybrid: skipped (rl2s_jax.physics.hybrid does not import: {e})", flush=True)
    units = [(c, s) for c in args.cases for s in args.seeds]
    t0 = time.perf_counter()
    results = {c: {} for c in args.cases}
    if args.resume and args.out and os.path.exists(args.out):  # the units a cut run finished
        with open(args.out) as fh:
            for case, runs in json.load(fh)["results"].items():
                for r in runs:
                    if (case, r["seed"]) in units:
                        results[case][r["seed"]] = r
        print(f"resumed: {sum(map(len, results.values()))} unit(s) from {args.out}")
        units_left = [(c, s) for c, s in units if s not in results[c]]
    else:
        units_left = units

    def record(case, seed, r):  # the JSON rewritten after every unit: a cut-off run keeps them
        results[case][seed] = r
        _report(case, seed, r)
        if args.out:
            write(args, argv, results, time.perf_counter() - t0, len(units))

    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
            for f in as_completed([pool.submit(_unit, u, args) for u in units_left]):
                record(*f.result())
    else:
        for unit in units_left:
            record(*_unit(unit, args))
    if args.out:
        write(args, argv, results, time.perf_counter() - t0, len(units))
    print("\n".join(gain_rows(summarise(results))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
