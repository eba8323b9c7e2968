"""`rl2s improve`: fine-tune chosen policies of a Dataset inside a saved simulator, write them
as a zoo, and measure the real gain.

``fine_tune(ImproveSpec(ckpt=..., data=..., out=...))`` (``run_improve(spec)``: the command,
which prints its summary) checks every input first (checkpoint, data of the same
task, policy indices, SAC fields, the policies: a zoo or a policy file), then fine-tunes the
chosen policies with SAC inside the checkpoint's simulator as one vmapped program
(``improve.improve_policies``), writes them to ``out`` in the zoo format
(``zoo.save_zoo``: ``load_zoo(out)``, ``rl2s collect --zoo out`` and ``measure_values``
take them), and, unless ``no_measure``, measures their real return before and after
(``improve.paired_episode_returns``) with one PNG per policy and a summary (``summary.json``,
``summary.md``).

``ImproveSpec(physics=..., data=..., out=...)`` (``rl2s improve --physics SRC``) fine-tunes in a
physics model instead (a calibrated.json of `rl2s diagnose --physics`, or "nominal":
``simulator_of``, ``improve.physics_env.PhysicsEnv``): deterministic, one model, so the guard
reads its values as its one member's with a floor of 0, and nothing that needs an ensemble's
disagreement (the MOPO penalty, the stop rule, ``--recipe``) is taken.

The deployment guard is on by default (margin ``GUARD_MARGIN``, 0.02, or the recipe's;
``no_guard=True`` turns it off, as ``rl2s improve --no-guard``): a fine-tuned policy is deployed
only where every elite member of the simulator, alone and on the same simulated episodes,
predicts a gain larger than that fraction of the start's simulated value
(``improve.deployment_guard``); elsewhere the start policy is kept and written to the zoo
(improvement 0 by definition). Only the simulator decides, never the real system. The real
returns then also give the deployed policies' MPI / API (``summary["guard"]``), and every
policy's row says deployed or kept, the members' predicted gain (``predicted_gain``: the
smallest over the members, the guard's criterion, and ``predicted_gain_mean``) and the real gain
of what was deployed (``real_gain``).

Why these defaults (the section "The guard, paired, and over snapshots" of RESULTS@bf0c7b2,
measured on the four MuJoCo tasks, 2 seeds each of RL2S and GAIL): at margin 0.02 the
guard on the final actor deployed no policy that lost in reality in any of the 8 lanes (MPI
0.000 everywhere), where deploying every fine-tuned policy lost on every task (MPI -0.07 to
-3.5). The guard over snapshots (``guard_snapshots``) deployed a few more policies but passed
two losses (GAIL on walker2d and halfcheetah: more candidates, more chances for the members
to agree wrongly), so it stays an option and the default is the final actor's guard, the
more conservative of the two.
``guard_snapshots`` applies the guard to the actor kept after every chunk of iterations
(``improve.select_by_members``): the snapshot whose smallest predicted gain over the members
is largest deploys, if any is eligible; its real return is measured paired with the start's.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time

import jax
import numpy as np

from rl2s_jax._files import save_figure, write_json, write_text
from rl2s_jax.app.specs import ImproveSpec, check_floor_scale, check_no_guard_alone
from rl2s_jax.app.training import parse_overrides
from rl2s_jax.app.value_intervals import NO_INTERVAL
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import TASKS
from rl2s_jax.evaluate.trust import json_safe
from rl2s_jax.improve.finetune import (
    deployment_guard,
    guarded,
    improve_policies,
    improvement_metrics,
    member_values,
    paired_episode_returns,
    paired_returns,
    select_by_members,
    training_return_curve,
)
from rl2s_jax.improve.gain_intervals import gain_features, interval_guard, read_calibration
from rl2s_jax.improve.physics_env import PhysicsEnv, is_physics
from rl2s_jax.improve.recipes import IMPROVE_RECIPES, recipe_settings
from rl2s_jax.improve.sim_env import branch_pool, real_rows, scaled_env_options
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.physics.hybrid import load_hybrid
from rl2s_jax.physics.physics_simulator import NOMINAL, physics_simulator
from rl2s_jax.policy.policy import index_params, num_policies
from rl2s_jax.policy.sac import SACConfig
from rl2s_jax.train.checkpoint import load_meta
from rl2s_jax.train.config import saved_field
from rl2s_jax.zoo.zoo import Zoo, policies_for, policy_source, save_zoo

# The deployment guard's default margin (module docstring: the margin of the guard studies in
# docs/RESULTS.md, under which no deployed policy lost in reality).
GUARD_MARGIN = 0.02


def guard_margin(spec) -> float | None:
    """The guard's margin from a spec's (``ImproveSpec``, ``PipelineSpec``) --guard-margin (None:
    the --recipe's, else the default, ``GUARD_MARGIN``) and --no-guard (-> None: no guard);
    --no-guard with --guard-margin, --guard-snapshots or --guard-floor-scale is refused, and so
    is a --guard-floor-scale below 0 (before any work)."""
    check_floor_scale(getattr(spec, "guard_floor_scale", None))
    check_no_guard_alone(spec)
    if spec.no_guard:
        return None
    if spec.guard_margin is None and getattr(spec, "recipe", None):
        return IMPROVE_RECIPES[spec.recipe]["guard_margin"]
    return GUARD_MARGIN if spec.guard_margin is None else spec.guard_margin


def fine_tuning_overrides(overrides: dict | None, flag: str = "set") -> dict:
    """SACConfig overrides for fine-tuning, checked: unknown fields refused (naming the known
    ones), ``normalize_observations`` refused, tuple fields made tuples. Errors start with
    ``flag``. -> a new dict."""
    fields = {f.name for f in dataclasses.fields(SACConfig)}
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"{flag}: unknown SACConfig field(s) {unknown}; known: "
                         f"{sorted(fields)}")
    if overrides.get("normalize_observations"):
        raise ValueError(f"{flag}: normalize_observations is for training from scratch; a "
                         "fine-tuned policy keeps its own observation normaliser")
    for k in ("hidden", "actor_hidden", "ignore_obs_dims"):
        if k in overrides:
            overrides[k] = tuple(overrides[k])
    return overrides


def sac_config(overrides: dict | None, episode_length: int, iterations: int) -> SACConfig:
    """SACConfig with the fine-tuning defaults, ``episode_length``, a critic warm-up of a
    quarter of the ``iterations``' updates, and ``overrides`` (``fine_tuning_overrides``)."""
    overrides = fine_tuning_overrides(overrides)
    ups = int(overrides.get("updates_per_step", SACConfig.updates_per_step))
    cfg = SACConfig.fine_tuning(**{"episode_length": episode_length,
                                   "critic_warmup_updates": iterations * ups // 4, **overrides})
    cfg.validate()
    return cfg


def check_inputs(ckpt: str, data_path: str, policy_ids: list[int] | None):
    """Everything `rl2s improve` needs, checked before any work.
    -> (checkpoint meta, Dataset, policy indices)."""

    if not os.path.isdir(ckpt):
        raise FileNotFoundError(f"ckpt: no checkpoint directory {ckpt}")
    meta = load_meta(ckpt)
    ck_task = meta.get("config", {}).get("task")
    if not os.path.exists(data_path):
        raise FileNotFoundError(f"data: no such file {data_path}")
    ds = load_dataset(data_path)
    if ds.meta.get("task") != ck_task:
        raise ValueError(f"data: {data_path} is data of task {ds.meta.get('task')!r}, but the "
                         f"checkpoint's simulator models task {ck_task!r}")
    sizes = meta.get("data", {})
    if (sizes.get("obs_size"), sizes.get("action_size")) != (ds.obs_size, ds.action_size):
        raise ValueError(f"data: obs/action sizes ({ds.obs_size}, {ds.action_size}) differ from "
                         f"the checkpoint's ({sizes.get('obs_size')}, "
                         f"{sizes.get('action_size')})")
    return meta, ds, policy_indices(ds, data_path, policy_ids)


def policy_indices(ds, data_path: str, policy_ids: list[int] | None) -> list[int]:
    """The chosen indices into the data's policies (None: all), checked: in range, distinct."""
    P = ds.n_policies
    ids = list(range(P)) if policy_ids is None else [int(i) for i in policy_ids]
    if not ids:
        raise ValueError("policies: expected at least one policy index")
    bad = [i for i in ids if not 0 <= i < P]
    if bad:
        raise ValueError(f"policies: index {bad[0]} out of range: {data_path} holds {P} "
                         f"policies (0..{P - 1})")
    if len(set(ids)) != len(ids):
        raise ValueError(f"policies: expected distinct indices, got {ids}")
    return ids


def simulator_of(spec: ImproveSpec) -> tuple:
    """The simulator `rl2s improve` fine-tunes in, checked with the data and policy indices
    before any work: the checkpoint's (``check_inputs``), or ``spec.physics``'s
    (``physics_simulator``: a calibrated.json or "nominal", for the data's task).
    -> (simulator, Dataset, policy indices, {"checkpoint": its absolute path or None,
    "physics": the physics' calibrated.json (absolute) or "nominal", or None})."""
    if spec.physics is None:
        _, ds, ids = check_inputs(spec.ckpt, spec.data, spec.policies)
        return (load_hybrid(spec.ckpt, spec.step)[0], ds, ids,
                {"checkpoint": os.path.abspath(spec.ckpt), "physics": None})
    if not os.path.exists(spec.data):
        raise FileNotFoundError(f"data: no such file {spec.data}")
    ds = load_dataset(spec.data)
    sim = physics_simulator(spec.physics, ds.meta.get("task"), ds.obs_size, ds.action_size)
    where = spec.physics if spec.physics == NOMINAL else os.path.abspath(spec.physics)
    return (sim, ds, policy_indices(ds, spec.data, spec.policies),
            {"checkpoint": None, "physics": where})


def apply_recipe(spec: ImproveSpec, sim, log, settings: dict) -> dict:
    """``settings`` (iterations, branch_length, uncertainty_penalty, floor_scale, overrides:
    the flags') with ``spec.recipe``'s for the simulator's task where a flag is not given."""
    if spec.recipe is None:
        return settings
    rs = recipe_settings(spec.recipe, sim.task)
    if not rs["zoo_recipe"]:
        log(f"[improve] recipe {spec.recipe}: task {sim.task!r} has no zoo learner to take "
            f"the discount, reward scale and batch from; SAC keeps the fine-tuning defaults")
    if settings["branch_length"] is None and rs["branch_length"] is not None and not sim.markov:
        raise ValueError(f"recipe: {spec.recipe} fine-tunes in branches from the data's logged "
                         "states, and this simulator's members see the episode's past "
                         "(history inputs), which those states lack; run without --recipe")
    out = {k: rs[k] if settings[k] is None else settings[k]
           for k in ("iterations", "branch_length", "uncertainty_penalty")}
    out["floor_scale"] = (rs["guard_floor_scale"] if settings["floor_scale"] is None
                          else settings["floor_scale"])
    out["overrides"] = {**rs["sac"], **(settings["overrides"] or {})}
    return out


def run_improve(spec: ImproveSpec) -> int:
    """`rl2s improve`'s body: ``fine_tune``, then its summary and the files written."""
    s = fine_tune(spec)
    print(summary_markdown(s))
    print(f"-> {spec.out}: zoo.npz, zoo.json, summary.json, summary.md"
          + (f", {len(s['plots'])} PNGs" if s["plots"] else ""))
    return 0


def fine_tune(spec: ImproveSpec, *, floor: float | None = None, chunk: int | None = None,
              log=print) -> dict:
    """Fine-tune the policies ``spec.policies`` (indices into the Dataset's policies; default
    all) inside the simulator of checkpoint ``spec.ckpt`` (or the physics model
    ``spec.physics``: ``simulator_of``) and write the zoo, plots and summary into ``spec.out``
    (module docstring). The policies come from ``spec.zoo``,
    ``spec.policy_file`` or what the data's meta.source names (``zoo.policies_for``). -> the
    summary dict (also out/summary.json). ``floor``: the guard's floor in value units
    (``deployment_guard``); None: the checkpoint's training MVD where comparable
    (``checkpoint_floor``), else 0; the guard uses ``spec.guard_floor_scale`` x it (None: the
    recipe's, else 1). ``spec.recipe``: a measured recipe (``improve.recipes``) for the
    simulator's task gives the iterations (else 1000), branch length, penalty (else 0) and SAC
    fields not given. ``chunk``: SAC iterations per compiled chunk (default a tenth)."""
    margin = guard_margin(spec)  # the spec checked the flags; this resolves the recipe's
    if floor is not None and not (np.isfinite(floor) and floor >= 0):
        raise ValueError(f"floor: expected a finite float >= 0 (value units) or None, got "
                         f"{floor!r}")
    measure = not spec.no_measure
    sim, ds, ids, inside = simulator_of(spec)
    cal = (read_calibration(spec.guard_calibration, sim.task) if spec.guard == "interval"
           else None)  # the interval guard's, checked before any work
    task = sim.task_fns()  # the registered task's rules, or the learned reward and hazard
    if measure and sim.task not in TASKS:
        log(f"[improve] {spec.data} is data of no registered task (meta.task "
            f"{ds.meta.get('task')!r}): no real system to measure the fine-tuned policies in, "
            f"so the real returns are skipped (as --no-measure)")
        measure = False
    settings = apply_recipe(spec, sim, log, dict(  # what the caller gave wins over the recipe
        iterations=spec.iterations, branch_length=spec.branch_length,
        uncertainty_penalty=spec.uncertainty_penalty, floor_scale=spec.guard_floor_scale,
        overrides=parse_overrides(spec.set)))
    iterations, branch_length, uncertainty_penalty, floor_scale, overrides = (
        settings[k] for k in ("iterations", "branch_length", "uncertainty_penalty",
                              "floor_scale", "overrides"))
    iterations = 1000 if iterations is None else iterations
    uncertainty_penalty = 0.0 if uncertainty_penalty is None else uncertainty_penalty
    episode_length = int(ds.meta.get("episode_length") or task.episode_length)
    cfg = sac_config(overrides, episode_length, iterations)
    where = policy_source(ds, spec.zoo, policy_file=spec.policy_file, data_path=spec.data)
    policies = index_params(policies_for(ds, spec.zoo, policy_file=spec.policy_file,
                                         data_path=spec.data), np.asarray(ids))
    names_all = ds.meta.get("policy_names") or [f"policy-{i}" for i in range(ds.n_policies)]
    names = [names_all[i] for i in ids]
    if branch_length is not None and not sim.markov:
        raise ValueError("branch-length: branched rollouts start from logged mid-episode "
                         "states without their past, and this simulator's members see the "
                         "episode's past (history inputs); fine-tune from episode starts")
    pool = (start_pool(ds) if branch_length is None
            else branch_pool(ds, max_states=100_000, seed=spec.seed))
    env_options = scaled_env_options(sim, *real_rows(ds, seed=spec.seed),
                                     rollout_length=branch_length,
                                     uncertainty_penalty=uncertainty_penalty,
                                     uncertainty_threshold=spec.uncertainty_threshold,
                                     halt_penalty=spec.halt_penalty)
    os.makedirs(spec.out, exist_ok=True)
    log(f"[improve] {len(ids)} policies of {spec.data} (task {task.name}) x {iterations} SAC "
        f"iterations inside {inside['checkpoint'] or 'the physics model ' + inside['physics']}")
    t0 = time.perf_counter()
    k_sac, k_measure = jax.random.split(jax.random.PRNGKey(spec.seed))
    chunk = chunk or max(1, iterations // 10)
    env = PhysicsEnv(sim, pool, task, **env_options) if is_physics(sim) else sim
    after, metrics = improve_policies(env, task, pool, policies, k_sac, cfg,
                                      n_iterations=iterations, chunk_iterations=chunk,
                                      env_options=env_options, progress=not spec.quiet,
                                      snapshots=spec.guard_snapshots)
    snapshots = None  # [C + 1, P, ...]: the start, then the actor after every chunk
    if spec.guard_snapshots:
        snapshots, after = after, jax.tree_util.tree_map(lambda x: x[-1], after)
    sac_seconds = time.perf_counter() - t0
    curve_x, curve = training_return_curve(metrics)
    gamma = float(ds.meta.get("gamma") or 0.999)

    guard, deployed = None, after  # deployed: what the zoo gets (the guard may keep starts)
    if margin is not None:  # the simulator's own verdict, start vs fine-tuned
        guard, deployed = _guard(spec, sim, ds, policies, after, snapshots, log, cal=cal,
                                 key=jax.random.fold_in(k_measure, 1), margin=margin,
                                 floor=floor, floor_scale=floor_scale, chunk=chunk,
                                 iterations=iterations, horizon=episode_length, gamma=gamma)

    measured = deployed_measured = None
    if measure:
        t0 = time.perf_counter()
        # paired: the start, the final and (the snapshot guard's) deployed policies share
        # start states and noise draws; the key of measure_improvement
        r0, rs = paired_episode_returns(task.make_env(), policies,
                                        [after] + ([deployed] if snapshots is not None else []),
                                        k_measure, n_episodes=spec.episodes,
                                        episode_length=episode_length, gamma=gamma)
        measured = paired_returns(r0, rs[0])
        deployed_measured = paired_returns(r0, rs[-1]) if snapshots is not None else None
        log(f"[improve] real returns measured in {time.perf_counter() - t0:.0f}s")

    origins = [{"name": n, "data_index": i, "zoo": where.get("zoo"),
                "zoo_id": where["zoo_ids"][i] if "zoo_ids" in where else None,
                "policy_file": (os.path.abspath(where["policy_file"])
                                if "policy_file" in where else None),
                "finetuned_in": inside["checkpoint"] or inside["physics"],
                "sac_iterations": iterations,
                "return_before": None if measured is None else float(measured["c0"][j]),
                **({} if guard is None else {"deployed": _deployed_text(guard, j)})}
               for j, (n, i) in enumerate(zip(names, ids, strict=True))]
    P = len(ids)
    returns = np.full(P, np.nan) if measured is None else np.asarray(measured["c1"])
    return_se = np.full(P, np.nan) if measured is None else np.asarray(measured["c1_se"])
    if deployed_measured is not None:  # a snapshot: its own paired measurement
        returns, return_se = deployed_measured["c1"], deployed_measured["c1_se"]
    if guard is not None and measured is not None:  # the zoo holds the deployed policies
        keep = np.asarray(guard["accepted"])
        returns = np.where(keep, returns, np.asarray(measured["c0"]))
        return_se = np.where(keep, return_se, np.asarray(measured["c0_se"]))
        guard.update(c1=returns.tolist(), c1_se=return_se.tolist())
        dep = improvement_metrics(measured["c0"], returns)  # a kept start: C1 = C0, I = 0
        guard.update(I=dep["I"].tolist(), mpi=dep["mpi"], api=dep["api"])
        log(f"[improve] deployed: MPI {guard['mpi']:.3f}  API {guard['api']:.3f} (fine-tuned "
            f"everywhere: MPI {measured['mpi']:.3f}  API {measured['api']:.3f})")
    save_zoo(Zoo(task=task.name, params=jax.device_get(deployed), returns=returns,
                 return_se=return_se, origins=origins, train_ids=[], test_ids=list(range(P)),
                 info={"made_by": "rl2s improve", **inside,
                       "data": os.path.abspath(spec.data), "sac": _jsonable(cfg),
                       "env_options": {k: v for k, v in env_options.items()
                                       if k != "uncertainty_fn"}}), spec.out)

    rows = []
    for j, (n, i) in enumerate(zip(names, ids, strict=True)):
        row = {"policy": n, "data_index": i,
               "data_value": None if ds.value is None else float(np.asarray(ds.value)[i]),
               "sim_return_curve": [_nan_none(x) for x in curve[j]]}
        if measured is not None:
            row.update({k: float(measured[k][j]) for k in ("c0", "c0_se", "c1", "c1_se", "I")})
        if guard is not None:
            row.update(_guard_row(guard, j))
            if "I" in guard:
                row["real_gain"] = guard["I"][j]
        elif measured is not None:  # no guard: every fine-tuned policy deployed
            row["real_gain"] = row["I"]
        rows.append(row)
    summary = {"task": task.name, **inside,
               "data": os.path.abspath(spec.data), "iterations": iterations, "recipe": spec.recipe,
               "sac": _jsonable(cfg), "env_options": {k: v for k, v in env_options.items()
                                                      if k != "uncertainty_fn"},
               "sac_seconds": round(sac_seconds, 1), "backend": jax.default_backend(),
               "n_episodes": spec.episodes if measured is not None else None,
               "curve_iterations": curve_x.tolist(), "policies": rows,
               "mpi": None if measured is None else measured["mpi"],
               "api": None if measured is None else measured["api"], "zoo": spec.out,
               "guard": guard}
    write_json(os.path.join(spec.out, "summary.json"), summary)
    write_text(os.path.join(spec.out, "summary.md"), summary_markdown(summary) + "\n")
    summary["plots"] = plot_policies(spec.out, summary) if measured is not None else []
    return summary


def _guard(spec: ImproveSpec, sim, ds, policies, after, snapshots, log, *, cal, key,
           margin: float, floor, floor_scale, chunk: int, iterations: int, horizon: int,
           gamma: float) -> tuple[dict, dict]:
    """``fine_tune``'s deployment guard: the interval guard where ``cal`` (a
    ``read_calibration``), else the floor guard (``deploy_through_guard``) with the floor
    ``floor`` (None: the checkpoint's training MVD, ``checkpoint_floor``) x ``floor_scale``.
    -> (the summary's guard block, the deployed policies [P, ...])."""
    P = num_policies(policies)
    if cal is not None:
        guard, deployed = deploy_through_interval_guard(
            sim, start_pool(ds), policies, after, key, calibration=cal,
            n_episodes=spec.guard_episodes, horizon=horizon, gamma=gamma)
        c = guard["calibration"]
        log(f"[improve] interval guard (level {c['level']}, q {c['q']}, n {c['n']}): "
            f"{int(np.sum(guard['accepted']))} of {P} fine-tuned policies kept, the lower end "
            "of the predicted gain's interval above 0")
        return guard, deployed
    floor, floor_source = ((float(floor), "given") if floor is not None
                           else (0.0, "a physics model has no training MVD")
                           if is_physics(sim)
                           else checkpoint_floor(spec.ckpt, spec.step, horizon, gamma))
    scale = 1.0 if floor_scale is None else float(floor_scale)
    floor, floor_source = scale * floor, (floor_source if scale == 1 else
                                          f"{scale:g} x {floor_source}")
    guard, deployed = deploy_through_guard(
        sim, None, start_pool(ds), policies, after, snapshots, key, margin=margin,
        n_episodes=spec.guard_episodes, horizon=horizon, gamma=gamma, chunk=chunk,
        iterations=iterations, floor=floor)
    guard.update(floor_source=floor_source, floor_scale=scale)
    log(f"[improve] guard (margin {margin}, floor {floor:.3g}: {floor_source}"
        + (f", over snapshots every {chunk} iterations" if snapshots is not None else "")
        + f"): {int(np.sum(guard['accepted']))} of {P} fine-tuned policies kept, "
        "every elite member predicting a gain")
    return guard, deployed


def _start_and_tuned_values(sim, policies, after, starts, key, task=None, **kw) -> tuple:
    """Each elite member's simulated values of the start and the fine-tuned policies, the
    same episodes for both (``member_values``). -> (v0 [M, P], v1 [M, P])."""
    both = jax.tree_util.tree_map(lambda a, b: jax.numpy.concatenate([a, b]), policies, after)
    values = member_values(sim, task, both, starts, key, **kw)
    P = values.shape[1] // 2
    return values[:, :P], values[:, P:]


def deploy_through_interval_guard(sim, starts, policies, after, key, *, calibration: dict,
                                  n_episodes: int, horizon: int, gamma: float
                                  ) -> tuple[dict, dict]:
    """The interval guard (``rl2s improve --guard interval``, ``gain_intervals``): the
    fine-tuned policy deploys where the lower end of its predicted relative gain's interval,
    G - q sigma from the elite members' values of the start and of it, is above 0; else the
    start. calibration: ``read_calibration``'s. -> (the summary's guard block: "kind",
    "calibration" (level, q (None: infinite), q_infinite, floor, n, source), "accepted",
    "gain" [P] G, "gain_member_sd" [P], "gain_lower" [P] (None: unbounded), the members'
    values and ``predicted_gains``; the deployed policies [P, ...])."""
    v0, v1 = _start_and_tuned_values(sim, policies, after, starts, key,
                                     n_episodes=n_episodes, horizon=horizon, gamma=gamma)
    feats = gain_features(v0, v1 - v0)
    accept, lower = interval_guard(feats, calibration)
    lo, mean = predicted_gains(v0, v1)
    cal = {**calibration, "q_infinite": not np.isfinite(calibration["q"])}
    guard = json_safe({"kind": "interval", "calibration": cal, "episodes": n_episodes,
                       "accepted": accept.tolist(), "gain": feats["gain"].tolist(),
                       "gain_member_sd": feats["member_sd"].tolist(),
                       "gain_lower": lower.tolist(), "sim_value_start": v0.tolist(),
                       "sim_value_tuned": v1.tolist(), "predicted_gain": lo,
                       "predicted_gain_mean": mean})
    return guard, guarded(policies, after, accept)


def deploy_through_guard(sim, task, starts, policies, after, snapshots, key, *, margin: float,
                         n_episodes: int, horizon: int, gamma: float, chunk: int | None = None,
                         iterations: int | None = None, floor: float = 0.0
                         ) -> tuple[dict, dict]:
    """The deployment guard (``rl2s improve`` and the pipeline): the start or the fine-tuned
    policy (``snapshots`` None: ``deployment_guard``), or the start or one of the
    ``snapshots`` [C + 1, P, ...] (index 0 the start; ``select_by_members``; ``chunk`` and
    ``iterations`` then name their iterations), by every elite member's simulated values;
    ``floor``: the smallest gain in value units that deploys (``deployment_guard``).
    -> (the summary's guard block, the deployed policies [P, ...])."""
    kw = dict(n_episodes=n_episodes, horizon=horizon, gamma=gamma)
    guard = {"margin": margin, "floor": floor, "episodes": n_episodes}
    if snapshots is None:
        v0, v1 = _start_and_tuned_values(sim, policies, after, starts, key, task=task, **kw)
        accept = deployment_guard(v0, v1, margin, floor)
        deployed = guarded(policies, after, accept)
        cand = v1  # the candidate whose predicted gain the summary shows
    else:
        deployed, info = select_by_members(sim, task, snapshots, starts, key, margin=margin,
                                           floor=floor, **kw)
        values, index = info["values"], info["index"]          # [C + 1, M, P], [P]
        v0, v1, accept = values[0], values[-1], index > 0
        guard.update(snapshot_every=chunk, snapshot=index.tolist(),
                     snapshot_iteration=[min(int(k) * chunk, iterations) for k in index],
                     sim_value_snapshots=values.tolist())
        # the chosen snapshot's values, or where the start is kept the final actor's
        cand = values[np.where(accept, index, len(values) - 1), :,
                      np.arange(values.shape[2])].T                 # [M, P]
    lo, mean = predicted_gains(v0, cand)
    guard.update(accepted=accept.tolist(), sim_value_start=v0.tolist(),
                 sim_value_tuned=v1.tolist(), predicted_gain=lo, predicted_gain_mean=mean)
    return guard, deployed


def training_error_floor(run: dict) -> dict:
    """The guard's floor from a training run's summary (``run_training``'s, also its
    summary.json): its MVD on the training policies with the horizon and gamma it was
    measured at, and the step."""
    by = run.get("vd_measured_by") or {}
    cfg = run.get("config") or {}
    return {"mvd": float(run["mvd_train"]),
            "horizon": int(by.get("horizon", saved_field(cfg, "vd.horizon"))),
            "gamma": float(by.get("gamma", cfg.get("gamma"))), "step": run.get("steps")}


def guard_floor(floor: dict | None, horizon: int, gamma: float) -> float:
    """A ``training_error_floor``'s MVD where it was measured at ``horizon`` and ``gamma``
    (the guard's), else 0: an error at another horizon or discount is not comparable (nor
    one not yet measured: NaN)."""
    if (not floor or not np.isfinite(floor["mvd"]) or floor["horizon"] != horizon
            or not np.isclose(floor["gamma"], gamma)):
        return 0.0
    return float(floor["mvd"])


def checkpoint_floor(ckpt: str, step: int | None, horizon: int, gamma: float) -> tuple:
    """``rl2s improve``'s floor: the MVD on the training policies in the summary.json that
    ``rl2s train`` wrote beside the checkpoint directory, where it was measured at the
    guard's horizon and gamma and (with ``step``) at that step. -> (floor, why) where why
    says where it came from or why it is 0."""
    path = os.path.join(os.path.dirname(os.path.normpath(ckpt)), "summary.json")
    try:
        with open(path) as f:
            floor = training_error_floor(json.load(f))
    except (OSError, ValueError, KeyError, TypeError):
        return 0.0, f"no training summary with mvd_train at {path}"
    if step is not None and floor["step"] is not None and int(step) != int(floor["step"]):
        return 0.0, f"the training MVD is of step {floor['step']}, not {step}"
    value = guard_floor(floor, horizon, gamma)
    if not value:
        return 0.0, (f"the training MVD was measured at horizon {floor['horizon']}, gamma "
                     f"{floor['gamma']}, not the guard's {horizon}, {gamma}")
    return value, f"the training MVD in {path}"


def predicted_gains(v0, v1) -> tuple[list, list]:
    """The simulator's predicted gain of each policy: (v1 - v0) / |v0| per elite member
    (v0, v1: [M, P] the members' values of the start and of the candidate), as the smallest
    over the members (the guard deploys where it exceeds the margin) and their mean.
    -> ([P], [P]) floats, None where |v0| is 0."""
    v0, v1 = np.asarray(v0, np.float64), np.asarray(v1, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = (v1 - v0) / np.abs(v0)
    lo, mean = g.min(axis=0), g.mean(axis=0)
    return [_nan_none(x) for x in lo], [_nan_none(x) for x in mean]


def _guard_row(guard: dict, j: int) -> dict:
    """Policy j's guard fields in the summary's row: deployed or not, the members' predicted
    gain; under the interval guard also G (``predicted_relative_gain``) and its interval's
    lower end (``gain_lower``, None: unbounded)."""
    row = {"deployed_fine_tuned": bool(guard["accepted"][j]),
           "predicted_gain": guard["predicted_gain"][j],
           "predicted_gain_mean": guard["predicted_gain_mean"][j]}
    if guard.get("kind") == "interval":
        row.update(predicted_relative_gain=guard["gain"][j], gain_lower=guard["gain_lower"][j])
    return row


def _deployed_text(guard: dict, j: int) -> str:
    """What the zoo holds for policy j under the guard (zoo.json origins)."""
    if not guard["accepted"][j]:
        return "start (the guard kept it)"
    if "snapshot" in guard:
        return f"fine-tuned (snapshot after {guard['snapshot_iteration'][j]} iterations)"
    return "fine-tuned"


def summary_markdown(s: dict) -> str:
    """The summary as a markdown table: real return before / after ± SE, I, simulated return;
    the guard's verdicts (``deployment_table``); why a simulated value has no interval
    (``NO_INTERVAL``)."""
    recipe = f" (recipe {s['recipe']})" if s.get("recipe") else ""
    lines = [f"# rl2s improve: {s['task']}, {s['iterations']} SAC iterations{recipe}",
             "", (f"physics model `{s['physics']}`" if s.get("physics")
                  else f"checkpoint `{s['checkpoint']}`") + f", data `{s['data']}`", ""]
    measured = s["mpi"] is not None
    if measured:
        lines += [f"MPI {s['mpi']:.3f}, API {s['api']:.3f} (real returns over "
                  f"{s['n_episodes']} episodes each)", ""]
    g = s.get("guard")
    if g and g.get("kind") == "interval":
        lines += [interval_guard_line(g), "", deployment_table(s), ""]
    elif g:
        kept = sum(g["accepted"])
        lines += [f"Deployment guard (margin {g['margin']}"
                  + (f", floor {g['floor']:.3g}: {g['floor_source']}" if "floor_source" in g
                     else "")
                  + (f", over snapshots every {g['snapshot_every']} iterations: deployed "
                     f"after {g['snapshot_iteration']}" if "snapshot" in g else "")
                  + f"): {kept} of {len(g['accepted'])} "
                  "fine-tuned policies deployed, the others kept as they were"
                  + (f"; deployed MPI {g['mpi']:.3f}, API {g['api']:.3f}" if "mpi" in g
                     else ""), "", deployment_table(s), ""]
    else:
        lines += ["No deployment guard (--no-guard): every fine-tuned policy deployed.", ""]
    head = "| policy | real C0 | real C1 | I | simulated return (start -> end) |"
    lines += [head, "|---|---:|---:|---:|---|"]
    for r in s["policies"]:
        c = [x for x in r["sim_return_curve"] if x is not None]
        sim = f"{c[0]:.1f} -> {c[-1]:.1f}" if c else "n/a"
        if measured:
            lines.append(f"| {r['policy']} | {r['c0']:.1f} ± {r['c0_se']:.1f} | "
                         f"{r['c1']:.1f} ± {r['c1_se']:.1f} | {r['I']:+.3f} | {sim} |")
        else:
            lines.append(f"| {r['policy']} | n/a | n/a | n/a | {sim} |")
    lines += ["", f"Why no interval: {NO_INTERVAL['sim_return']}."]
    if g and g.get("kind") != "interval":
        lines.append(f"Why no interval: {NO_INTERVAL['floor_guard']}.")
    return "\n".join(lines)


def interval_guard_line(g: dict) -> str:
    """The interval guard's line: its rule, calibration (level, q, floor, n, source) and
    what it deployed."""
    c = g["calibration"]
    q = "inf (too few calibration policies for the level)" if c["q_infinite"] else f"{c['q']:.3g}"
    return (f"Deployment guard: interval (deploy where the lower end of the predicted relative "
            f"gain's interval is above 0; level {c['level']}, q {q}, floor {c['floor']:.3g}, "
            f"n {c['n']} calibration policies, from {', '.join(c['source'])}): "
            f"{sum(g['accepted'])} of {len(g['accepted'])} fine-tuned policies deployed, the "
            "others kept as they were"
            + (f"; deployed MPI {g['mpi']:.3f}, API {g['api']:.3f}" if "mpi" in g else ""))


def deployment_table(s: dict) -> str:
    """Per policy under the guard: deployed or kept, the simulator's predicted gain (floor
    guard: the smallest over the elite members, which the guard compares with the margin, and
    their mean; interval guard: G and its interval's lower end, which it compares with 0) and
    the real gain of what was deployed (0 for a kept start), with the final actor's
    real gain for comparison (what deploying it anyway would have given)."""
    g = s["guard"]
    interval = g.get("kind") == "interval"
    lines = [("| policy | deployed | predicted relative gain G | its interval's lower end "
              if interval else "| policy | deployed | predicted gain (every member at least) "
              "| predicted gain (members' mean) ")
             + "| real gain | real gain, fine-tuned anyway |", "|---|---|---:|---:|---:|---:|"]

    def num(x):
        return "n/a" if x is None else f"{x:+.3f}"
    for j, r in enumerate(s["policies"]):
        what = _deployed_text(g, j).replace(" (the guard kept it)", "")
        what = ("kept (start)" if not g["accepted"][j] else
                "deployed" + what[len("fine-tuned"):])
        sim = ((g["gain"][j], "-inf" if g["gain_lower"][j] is None else num(g["gain_lower"][j]))
               if interval else (g["predicted_gain"][j], num(g["predicted_gain_mean"][j])))
        lines.append(f"| {r['policy']} | {what} | {num(sim[0])} | {sim[1]} | "
                     f"{num(r.get('real_gain'))} | {num(r.get('I'))} |")
    return "\n".join(lines)


def plot_policies(out: str, s: dict) -> list[str]:
    """One PNG per policy: real return before / after with standard-error bars, and SAC's
    simulated training return over the iterations. -> file names."""
    # Imported here to keep start-up fast: matplotlib loads in about a second, and only
    # the plots need it.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for r in s["policies"]:
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(9, 3.4),
                                       gridspec_kw={"width_ratios": [1, 2]})
        ax0.bar([0, 1], [r["c0"], r["c1"]], yerr=[r["c0_se"], r["c1_se"]], capsize=6,
                color=["tab:gray", "tab:blue"])
        ax0.set_xticks([0, 1], ["before", "after"])
        ax0.set_ylabel("real return")
        ax0.set_title(f"I = {r['I']:+.3f}")
        y = np.array([np.nan if v is None else v for v in r["sim_return_curve"]], float)
        ax1.plot(s["curve_iterations"], y, marker=".")
        ax1.set_xlabel("SAC iteration")
        ax1.set_ylabel("simulated training return")
        ax1.grid(alpha=0.3)
        fig.suptitle(r["policy"])
        fig.tight_layout()
        name = f"policy_{_safe(r['policy'])}.png"
        save_figure(fig, os.path.join(out, name), dpi=100)
        plt.close(fig)
        files.append(name)
    return files


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name))


def _nan_none(x):
    x = float(x)
    return x if np.isfinite(x) else None


def _jsonable(cfg: SACConfig) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(cfg).items()}


__all__ = ["GUARD_MARGIN", "apply_recipe", "check_inputs", "deploy_through_guard",
           "deploy_through_interval_guard", "deployment_table", "fine_tune",
           "fine_tuning_overrides", "guard_margin", "interval_guard_line",
           "policy_indices", "predicted_gains", "run_improve", "sac_config", "simulator_of",
           "summary_markdown"]
