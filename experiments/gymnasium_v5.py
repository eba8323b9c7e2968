"""The MJX tasks' physics against Gymnasium's MuJoCo v5 envs (issue 62, item 5): data the
project did not make (C MuJoCo, float64, v5's own XML and solver), recorded with zoo policies.

For each task: the table of model differences (``gymnasium_v5.model_differences``); v5 data of
the zoo's policies (``collect_gymnasium``) and, as a control, C-MuJoCo data of the same
policies on the MJX task's own XML (``measured.collect_measured``: what float32 MJX vs float64
C alone costs); the one-step and open-loop k-step error of the nominal MJX physics
(``mjx_model.PhysicsModel.step``, theta = 0) on both, per observation dim, in and out of
contact and per policy, each as an RMSE over the RMS of the data's own change over that many
steps (1.0 = no better than predicting no change); the policies' true values in v5 against
their values in the MJX task (the zoo's, 16 MJX episodes each; ``--mjx-values`` re-measures
them with as many episodes as v5's) and the Kendall tau between the two rankings.

    python experiments/gymnasium_v5.py [--tasks hopper ...] [--split test] [--policies 0]
        [--transitions 1000] [--value-episodes 16] [--k 10] [--no-control] [--ablate]
        [--mjx-values] [--diagnose DIR] [--out FILE.json] [--results FILE.json]

``--ablate``: also v5 with its XML's <option> moved toward the MJX task's (Euler instead of
RK4; then also the MJX task's solver iterations), to see which difference the error comes
from. ``--diagnose DIR``: also ``rl2s diagnose --physics`` (app/physics_diagnosis.py) on the
v5 data. ``--results FILE``: each task's row (``paper.physics_tables.v5_row``: errors, tau and
its noise floor, AVD / MVD, the diagnosis) with this command and machine, merged into RESULTS'
``docs/results/gymnasium_v5.json`` (the folders of --out and --results are made first).

Results (2-core CPU shared with three other sessions, 2026-11-28; gymnasium 1.4.0, mujoco
4.0.0). Errors: RMSE / RMS of the data's change, mean over the observation dims.

Hopper, ``--tasks hopper`` (the 20 test policies, 1000 transitions and 16 value episodes each;
382 s) and ``--tasks hopper --no-control --ablate --mjx-values`` (676 s):

    data                           one-step  (in / out of contact)  10-step open loop
    v5 as it comes                 0.0587    (0.0457 / 0.0730)      0.0174
    v5 XML, Euler                  0.0096    (0.0041 / 0.0149)      0.0019
    v5 XML, Euler, 4 iterations    0.0096    (identical: Newton stops within 3 iterations)
    C MuJoCo on the MJX XML        3.8e-6    (4.1e-6 / 3.3e-6)      6.2e-6

    RK4 is most of the error (0.059 -> 0.0096); the rest is v5's other XML settings (every
    geom colliding, condim 1 on the body geoms, rootz ref, joint ranges 3.9e-6 rad apart).
    The largest one-step error is in the torso's vertical velocity (obs[7], 0.16 of its
    change), RMSE 0.019 m/s; joint velocities 0.03-0.07 rad/s.
    Values (20 test policies): Kendall tau v5 vs MJX re-measured (16 episodes each) 1.000,
    AVD 28.9, MVD 141.0 (hopper-008: 641 vs 500, se 64), mean v5 - MJX +26.9; against the
    zoo's MJX values 0.937, exactly the tau of the MJX re-measurement against the zoo's
    (0.937): the ranking does not change beyond measurement noise. v5's own reward sums to
    within 1.1 of the task reward over the same steps; v5's own termination fired at another
    step than the task's done_fn in 28 of 320 value episodes.

    The physics diagnosis, ``--tasks hopper --policies 5 --transitions 1000 --value-episodes 2
    --no-control --diagnose DIR`` (zoo ids 3, 6, 8, 14, 29; 211 s, the diagnosis 12 s): nothing
    named while the integrator was no candidate (actuator_gear[thigh_joint] 200 -> 196.8 cut
    the held-out error 1.6%, under the 10% minimum). With it (RESULTS' row 8; 21 s, the
    diagnosis 4 s): integrator[opt] Euler -> RK4, p 0.00011, unexplained 0.000: v5's RK4 is all
    of the one-step error, and no mass, friction, gear or delay stands in for it.

Walker2d, ``--tasks walker2d --policies 5 --transitions 200 --value-episodes 4 --ablate``
(zoo test ids by return; run with XLA_FLAGS=--xla_cpu_multi_thread_eigen=false, and it still
wedged in the "euler_iter" variant, so no values from that run):

    data                           one-step  (in / out of contact)  10-step open loop
    v5 as it comes                 0.0676    (0.0700 / 0.0644)      0.0599
    v5 XML, Euler                  0.0239    (0.0284 / 0.0147)      0.0478
    C MuJoCo on the MJX XML        3.4e-4    (4.8e-4 / 2.5e-6)      7.6e-6

    (An earlier run with 10 policies x 500 transitions: v5 one-step 0.0758, 10-step 0.0700,
    before it wedged.) Euler removes two thirds of the one-step error but not the open-loop
    one: v5's right foot friction (1.9 against 0.9) is the next difference.

    The physics diagnosis finds it. On v5 data of the first 10 test policies (ids 1, 2, 4, 5,
    6, 10, 14, 18, 19, 23), 600 transitions each in 100-step episodes, seed 0
    (``collect_gymnasium`` then ``diagnose_physics(PhysicsSpec(data, out))``, defaults; the
    same as ``--episode-length 100 --transitions 600 --diagnose DIR`` on those policies):
    top cause geom_friction[foot_geom] 0.9 -> 1.894, interval [1.839, 1.923] (v5's XML: 1.9),
    p 0.005, held-out gain 13.5%; unexplained 0.865 (the integrator's share stays); 30 s.
    With 5 policies x 400 transitions (10 test episodes) the same quantity came first,
    0.9 -> 1.889, gain 26%, but p 0.057 > 0.01: not kept, top cause None.

    The wedges on this CPU were jaxlib's deadlock of concurrent batched Cholesky calls
    (rl2s_jax/_xla_cpu.py; avoided since). With the integrator as a candidate,
    ``--tasks walker2d --policies 5 --episode-length 100 --transitions 600 --value-episodes 2
    --no-control --diagnose DIR`` (RESULTS' row 9; 63 s, the diagnosis 22 s) names both
    differences: integrator[opt] Euler -> RK4 (p 2.4e-07), then geom_friction[foot_geom]
    0.9 -> 1.9 (v5's XML: 1.9; p 0.00036); held-out one-step error 0.073 -> 0.010, 10-step
    open loop 0.327 -> 0.014, unexplained 0.009.

HalfCheetah (``--tasks halfcheetah --policies 5 --transitions 200 --value-episodes 4
--ablate``): v5 one-step 0.0013 (in contact 0.0025, out 3.9e-6), 10-step 0.0038; the
C-MuJoCo control 3.5e-6 one-step, 10-step 0.0039: v5's only physical differences (RK4 is not
used; more geoms collide; 100 iterations) cost little, and over 10 steps the float32 MJX
drifts from C MuJoCo as much on the MJX XML as on v5's. That run wedged in its third
dataset (XLA, above): no HalfCheetah values or diagnosis.

On one H200 host (MJX on the GPU: no wedge), ``--tasks T --transitions 500 --value-episodes 8
--mjx-values --no-control --diagnose DIR`` for the 20 test policies, one process per task:
    walker2d  one-step 0.077 (in / out of contact 0.083 / 0.066), 10-step 0.072; tau v5 vs
              MJX 0.895 (MJX re-measured vs the zoo's own values: 0.937), AVD 169, MVD 702;
              diagnosis: foot friction 0.9 -> 1.895 first but p 0.024 > 0.01, nothing kept.
    ant       one-step 0.214 (0.246 / 0.208), 10-step 0.591; tau v5 vs MJX 0.600 (noise floor
              0.705 at 8 episodes), AVD 942, MVD 1703, v5 - MJX +528 on average (weak
              policies gain most); diagnosis named nothing then; on the CPU (RESULTS' row
              10): RK4, margin 0.02, ankles colliding for the foot spheres: unexplained 0.
    halfcheetah  one-step 0.0082, 10-step 0.060; its diagnosis stopped on a split of one
              episode per policy (fixed since in identify.split_rows); no values that run.

HalfCheetah's values (GPU 1 of a 2x H200 host shared with a Walker2d protocol run; a714f44,
jax 0.11.2; 553 s), ``--tasks halfcheetah --transitions 500 --value-episodes 8 --mjx-values
--no-control --diagnose DIR --results FILE`` (it crashed writing FILE into a missing folder
after printing every number: gymnasium_v5.json's row is rebuilt from its log by ``v5_row``):
43 test policies, one-step 0.00819 (in / out of contact 0.00952 / 0.00764), 10-step 0.0460;
v5 differs in solver iterations (100 vs 4), float64 and contype on floor, torso, bshin, fshin;
the diagnosis names nothing (unexplained 1.000); tau v5 vs MJX 0.987 (MJX re-measured vs the
zoo's 0.973), AVD 43.4, MVD 408.9: the ranking is the same in both engines within the noise.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from rl2s_jax import compile_cache
from rl2s_jax._files import write_json
from rl2s_jax.app.physics_diagnosis import PhysicsSpec, diagnose_physics
from rl2s_jax.app.report import machine_info
from rl2s_jax.data.collect import measure_values
from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.metrics import kendall_tau, value_differences
from rl2s_jax.paper.physics_tables import merge_v5_row, v5_row
from rl2s_jax.physics.gymnasium_v5 import (
    V5_ENVS,
    collect_gymnasium,
    make_v5,
    print_differences,
)
from rl2s_jax.physics.identify import format_quantity
from rl2s_jax.physics.measured import collect_measured
from rl2s_jax.physics.mjx_model import physics_model
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

CHUNK = 1024  # transitions per MJX call (one compiled shape; the last chunk is padded)


def _chunked(fn, *arrays):
    """fn over rows of ``arrays`` in CHUNK-row pieces (padded to one shape) -> its outputs."""
    n = len(arrays[0])
    outs = []
    for lo in range(0, n, CHUNK):
        part = [a[lo:lo + CHUNK] for a in arrays]
        pad = CHUNK - len(part[0])
        part = [np.concatenate([p, np.repeat(p[-1:], pad, 0)]) if pad else p for p in part]
        out = jax.device_get(fn(*part))
        outs.append(jax.tree_util.tree_map(lambda x, m=CHUNK - pad: np.asarray(x)[:m], out))
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *outs)


def _windows(ds, k: int, stride: int) -> np.ndarray:
    """Start rows i (every ``stride``-th) whose episode holds rows i .. i + k - 1 -> [W]."""
    ep, n = np.asarray(ds.episode_id), ds.n_transitions
    starts = np.arange(0, n - k + 1, stride)
    return starts[ep[starts + k - 1] == ep[starts]]


_PROGRAMS = {}  # (id(pm), k) -> its jitted programs: every dataset of a task reuses them


def _programs(pm, k: int):
    """jit(vmap) of ``pm``'s nominal one step (with contact) and of its k-step rollout."""
    if (id(pm), k) not in _PROGRAMS:
        theta = jnp.zeros(len(pm.candidates), jnp.float32)

        def rollout(o0, actions):  # o0 [O], actions [k, A] -> [k, O]
            def body(o, a):
                o2 = pm.step(theta, o, a)
                return o2, o2
            return jax.lax.scan(body, o0, actions)[1]

        _PROGRAMS[(id(pm), k)] = (
            jax.jit(jax.vmap(lambda o, a: pm.step_with_contact(theta, o, a))),
            jax.jit(jax.vmap(rollout)))
    return _PROGRAMS[(id(pm), k)]


def physics_errors(pm, ds, k: int, stride: int) -> dict:
    """One-step and open-loop k-step error of ``pm``'s nominal physics on ``ds``.

    Each error is an RMSE over the RMS of the data's own change over the same steps, per
    observation dim [O] and its mean over dims; one-step also in and out of contact and per
    policy [P]; k-step by step 1..k (mean over dims).
    """
    one, rollouts = _programs(pm, k)
    obs, act, nxt = (np.asarray(x) for x in (ds.obs, ds.action, ds.next_obs))
    t0 = time.time()
    pred, touching = _chunked(one, obs, act)
    seconds_one = time.time() - t0
    err2, change2 = (pred - nxt) ** 2, (nxt - obs) ** 2
    rel = lambda e2, c2: np.sqrt(e2.mean(0)) / np.maximum(np.sqrt(c2.mean(0)), 1e-8)
    pid = np.asarray(ds.policy_id)
    out = {"one_step": rel(err2, change2).tolist(),
           "one_step_mean": float(rel(err2, change2).mean()),
           "one_step_rmse": np.sqrt(err2.mean(0)).tolist(),
           "contact_share": float(touching.mean()),
           "one_step_by_policy": [float(rel(err2[pid == p], change2[pid == p]).mean())
                                  for p in range(ds.n_policies)],
           "seconds_one_step": seconds_one}
    for name, m in (("in_contact", touching), ("no_contact", ~touching)):
        out[f"one_step_{name}"] = float(rel(err2[m], change2[m]).mean()) if m.any() else None

    starts = _windows(ds, k, stride)
    rows = starts[:, None] + np.arange(k)[None, :]  # [W, k]

    t0 = time.time()
    roll = _chunked(rollouts, obs[starts], act[rows])  # [W, k, O]
    truth = nxt[rows]  # [W, k, O]
    e2 = (roll - truth) ** 2
    c2 = (truth - obs[starts][:, None, :]) ** 2
    by_step = [float(rel(e2[:, j], c2[:, j]).mean()) for j in range(k)]
    out.update({"k": k, "windows": len(starts), "k_step": rel(e2[:, -1], c2[:, -1]).tolist(),
                "k_step_rmse": np.sqrt(e2[:, -1].mean(0)).tolist(),
                "k_step_mean": by_step[-1], "k_step_by_step": by_step,
                "k_step_finite": float(np.isfinite(roll).all(axis=(1, 2)).mean()),
                "seconds_k_step": time.time() - t0})
    return out


def option_variants(task: str, directory: str) -> dict[str, dict]:
    """v5's XML with its <option> moved toward the MJX task's, one step at a time, written to
    ``directory`` -> {name: env_kwargs}: "euler" (integrator Euler, where v5 says RK4) and
    "euler_iter" (also the MJX task's solver iterations)."""
    mjx_iterations = str(physics_model(task).mj.opt.iterations)
    env = make_v5(task)
    tree = ET.parse(env.unwrapped.fullpath)
    env.close()
    option = tree.getroot().find("option")
    out = {}
    for name, edits in (("euler", {"integrator": "Euler"}),
                        ("euler_iter", {"integrator": "Euler", "iterations": mjx_iterations})):
        if name == "euler" and option.get("integrator", "Euler") == "Euler":
            continue
        for key, value in edits.items():
            option.set(key, value)
        path = os.path.join(directory, f"{task}_{name}.xml")
        tree.write(path)
        out[name] = {"xml_file": path}
    return out


def run_task(task: str, args) -> dict:
    zoo = load_zoo(task)
    ids = zoo.split_ids(args.split)
    if args.policies:  # evenly spaced by return
        by_return = sorted(ids, key=lambda i: zoo.returns[i])
        ids = sorted(by_return[j] for j in np.linspace(0, len(ids) - 1, args.policies)
                     .round().astype(int))
    params = index_params(zoo.params, np.asarray(ids))
    names = zoo.policy_names(ids)
    rec = {"task": task, "env_id": V5_ENVS[task], "split": args.split, "zoo_ids": ids}
    rec["differences"] = print_differences(task)
    t0 = time.time()
    v5 = collect_gymnasium(task, params, transitions_per_policy=args.transitions,
                           episode_length=args.episode_length,
                           value_episodes=args.value_episodes, seed=args.seed,
                           policy_names=names, source={"zoo": task, "zoo_ids": ids})
    rec["seconds_collect_v5"] = time.time() - t0
    pm = physics_model(task)
    data = {"v5": v5}
    if args.control:
        t0 = time.time()
        data["mjx_xml_c"] = collect_measured(pm, params, transitions_per_policy=args.transitions,
                                             episode_length=get_task(task).episode_length,
                                             seed=args.seed,
                                             policy_names=names)
        rec["seconds_collect_control"] = time.time() - t0
    if args.ablate:  # which of v5's options the one-step error comes from
        for name, kwargs in option_variants(task, tempfile.mkdtemp()).items():
            data[f"v5_{name}"] = collect_gymnasium(task, params,
                                                   transitions_per_policy=args.transitions,
                                                   value_episodes=0, seed=args.seed,
                                                   policy_names=names, env_kwargs=kwargs)
    for name, ds in data.items():
        rec[name] = physics_errors(pm, ds, args.k, args.stride)
        rec[name]["transitions"] = ds.n_transitions
        rec[name]["done_share"] = float(np.mean(ds.done))
        e = rec[name]
        print(f"{task} {name}: {ds.n_transitions} transitions, {e['contact_share']:.2f} in "
              f"contact; one-step {e['one_step_mean']:.4g} (in contact "
              f"{e['one_step_in_contact']:.4g}, out {e['one_step_no_contact']:.4g}), "
              f"{args.k}-step {e['k_step_mean']:.4g}")
        print("  one-step by dim " + " ".join(f"{x:.3g}" for x in e["one_step"]))
        print("  one-step RMSE   " + " ".join(f"{x:.3g}" for x in e["one_step_rmse"]))
        print(f"  {args.k}-step by dim " + " ".join(f"{x:.3g}" for x in e["k_step"]))

    if args.diagnose:  # the physics diagnosis (rl2s diagnose --physics) of the v5 data
        out_dir = os.path.join(args.diagnose, task)
        os.makedirs(out_dir, exist_ok=True)
        path = save_dataset(os.path.join(out_dir, "v5.npz"), v5)
        report = diagnose_physics(PhysicsSpec(data=path, out=out_dir, k=args.k, quiet=True))
        ph = report["physics"]
        rec["physics_diagnosis"] = {k: ph[k] for k in ("top_cause", "parameters", "unexplained",
                                                       "seconds", "error_nominal",
                                                       "error_calibrated")}
        print(f"{task} physics diagnosis ({ph['seconds']:.0f} s): top cause {ph['top_cause']}; "
              f"unexplained {ph['unexplained']:.3f}; parameters "
              + "; ".join(f"{format_quantity(p, interval=False)} "
                          f"(gain {p['gain']:.3f}, p {p['p_value']:.2g}, "
                          f"{'kept' if p['significant'] else 'not kept'})"
                          for p in ph["parameters"]))
    zoo_values = mjx_values = np.asarray(zoo.returns, np.float64)[ids]
    rec["mjx_values_from"] = "zoo.json returns (collect.measure_values, 16 MJX episodes)"
    if args.mjx_values:  # and MJX against itself: the ranking noise of two measurements
        t0 = time.time()
        mjx_values = measure_values(get_task(task).make_env(), params,
                                    key=jax.random.PRNGKey(args.seed),
                                    n_episodes=args.value_episodes,
                                    episode_length=get_task(task).episode_length)["value"]
        rec["mjx_values_from"] = f"measure_values, {args.value_episodes} MJX episodes"
        rec["seconds_mjx_values"] = time.time() - t0
        rec["mjx_remeasured_vs_zoo_tau"] = kendall_tau(zoo_values, mjx_values)
        rec["v5_vs_zoo_tau"] = kendall_tau(zoo_values, np.asarray(v5.value, np.float64))
        print(f"{task}: Kendall tau, MJX re-measured vs the zoo's MJX values "
              f"{rec['mjx_remeasured_vs_zoo_tau']:.3f}; v5 vs the zoo's {rec['v5_vs_zoo_tau']:.3f}")
    v5_values = np.asarray(v5.value, np.float64)
    mjx_values = np.asarray(mjx_values, np.float64)
    vd = value_differences(mjx_values, v5_values)
    rec["values"] = {"v5": v5_values.tolist(), "v5_se": np.asarray(v5.value_se).tolist(),
                     "mjx": mjx_values.tolist(), "kendall_tau": kendall_tau(mjx_values, v5_values),
                     "avd": vd["avd"], "mvd": vd["mvd"],
                     "mean_v5_minus_mjx": float(np.mean(v5_values - mjx_values)),
                     "gymnasium_value": v5.meta["source"]["gymnasium_value"],
                     "gymnasium_reward_gap": v5.meta["source"]["gymnasium_reward_gap"],
                     "gymnasium_termination_differs":
                         v5.meta["source"]["gymnasium_termination_differs"]}
    tau = rec["values"]["kendall_tau"]
    print(f"{task} values: Kendall tau (MJX vs v5) {tau:.3f}, AVD {vd['avd']:.1f}, MVD "
          f"{vd['mvd']:.1f}, mean v5 - MJX {rec['values']['mean_v5_minus_mjx']:+.1f} over "
          f"{len(ids)} policies")
    own, se = rec["values"]["gymnasium_value"], rec["values"]["v5_se"]
    for i, name in enumerate(names):
        print(f"  {name}: MJX {mjx_values[i]:8.1f}  v5 {v5_values[i]:8.1f} +- {se[i]:.1f}  "
              f"(v5's own reward {own[i]:8.1f})")
    return rec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["hopper"], choices=sorted(V5_ENVS))
    ap.add_argument("--split", default="test", help="the zoo's split whose policies run")
    ap.add_argument("--policies", type=int, default=0,
                    help="that many of the split's policies, evenly spaced by return (0: all)")
    ap.add_argument("--transitions", type=int, default=1000, help="per policy")
    ap.add_argument("--value-episodes", type=int, default=16)
    ap.add_argument("--episode-length", type=int, default=None,
                    help="of the v5 data and value episodes (default: the task's, 1000); "
                    "shorter gives the diagnosis more episodes to test on")
    ap.add_argument("--k", type=int, default=10, help="open-loop steps")
    ap.add_argument("--stride", type=int, default=10, help="rows between k-step windows")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-control", dest="control", action="store_false",
                    help="skip the C-MuJoCo control on the MJX task's own XML")
    ap.add_argument("--ablate", action="store_true",
                    help="also v5 with the integrator / solver iterations of the MJX task")
    ap.add_argument("--diagnose", metavar="DIR",
                    help="run the physics diagnosis on the v5 data; reports in DIR/<task>")
    ap.add_argument("--mjx-values", action="store_true",
                    help="re-measure the MJX values (else the zoo's)")
    ap.add_argument("--out", default=None, help="write the record as JSON here")
    ap.add_argument("--results", metavar="FILE", help="add each task's row, with this command "
                    "and machine, to RESULTS' JSON (docs/results/gymnasium_v5.json)")
    args = ap.parse_args(argv)
    compile_cache.enable()
    if args.k < 1 or args.transitions < args.k or args.value_episodes < 2:
        ap.error("expected --k >= 1, --transitions >= --k, --value-episodes >= 2")
    for path in (args.out, args.results):  # their folders before any work (atomic writes)
        if path:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    t0 = time.time()
    record = {"args": vars(args), "tasks": [run_task(t, args) for t in args.tasks]}
    record["seconds"] = time.time() - t0
    if args.out:
        write_json(args.out, record)
    if args.results:  # RESULTS' "Physics diagnosis (issue 62)" table: paper.physics_tables
        command = "python experiments/gymnasium_v5.py " + " ".join(sys.argv[1:] if argv is None
                                                                     else argv)
        machine = {**machine_info(), "cpu_count": os.cpu_count(), "mujoco": mujoco.__version__}
        for rec in record["tasks"]:
            merge_v5_row(args.results, v5_row(rec, command, machine))
    print(f"done in {record['seconds']:.0f} s")
    return record


if __name__ == "__main__":
    main()
