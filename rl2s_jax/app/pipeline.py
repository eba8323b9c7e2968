"""`rl2s pipeline` and `rl2s collect`: a task's zoo -> data -> the four simulators -> evaluation,
improvement, report (what `make hopper` runs)."""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax._timing import PartTimer, timed
from rl2s_jax.app.evaluation import evaluate_checkpoint
from rl2s_jax.app.improvement import (
    GUARD_MARGIN,
    deploy_through_guard,
    fine_tuning_overrides,
    guard_floor,
    guard_margin,
    training_error_floor,
)
from rl2s_jax.app.report import improvement_text, load_curve, machine_info, write_report
from rl2s_jax.app.specs import PipelineSpec, TrainSpec, check_floor_scale
from rl2s_jax.app.training import parse_overrides, run_training
from rl2s_jax.data.collect import collect
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.data.summary import dataset_summary
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate.scores import evaluate_simulator
from rl2s_jax.evaluate.setting import EvalSetting
from rl2s_jax.evaluate.trust import DEFAULT_LEVEL
from rl2s_jax.improve.finetune import improve_policies, paired_episode_returns, paired_returns
from rl2s_jax.improve.recipes import recipe_settings
from rl2s_jax.improve.sim_env import branch_pool, real_rows, scaled_env_options
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.policy.policy import index_params
from rl2s_jax.policy.sac import SACConfig
from rl2s_jax.train.checkpoint import load_simulator
from rl2s_jax.train.config import saved_field
from rl2s_jax.zoo.zoo import load_zoo, policies_for


def collect_dataset(task_name: str, split: str, transitions_per_policy: int, *, seed: int = 0,
                    envs_per_policy: int | None = None, gamma: float = 0.999,
                    value_episodes: int = 16, episode_length: int | None = None,
                    zoo_path: str | None = None, progress: bool = True,
                    timer: PartTimer | None = None):
    """Collect a Dataset from a registered task's zoo split (what `rl2s collect` runs).
    ``timer``: times "setup" (the zoo loaded, the env built) and collect's COLLECT_PARTS."""
    with timed(timer, "setup"):
        task = get_task(task_name)
        zoo = load_zoo(zoo_path or task_name)
        if zoo.task != task_name:
            raise ValueError(f"zoo: built for task {zoo.task!r}, not {task_name!r}")
        ids = zoo.split_ids(split)
        env = task.make_env()
    return collect(env, index_params(zoo.params, ids), key=jax.random.PRNGKey(seed),
                   transitions_per_policy=transitions_per_policy,
                   envs_per_policy=envs_per_policy,
                   episode_length=episode_length or task.episode_length, task=task_name,
                   policy_names=zoo.policy_names(ids), gamma=gamma,
                   value_episodes=value_episodes, progress=progress,
                   source={"zoo": zoo_path or task_name, "split": split,
                           "zoo_ids": ids, "seed": seed}, timer=timer)


PROFILES = {
    "cpu": dict(transitions_per_policy=2000, value_episodes=4, steps=300, eval_every=50,
                improve_iterations=300,
                sac=dict(n_envs=4, hidden=(64, 64), batch_size=128, critic_warmup_updates=200,
                         buffer_size=20_000),
                improve_recipe=dict(branch_length=None, uncertainty_penalty=0.0)),
    "gpu": dict(transitions_per_policy=100_000, value_episodes=32, steps=3000, eval_every=250,
                improve_iterations=5000,
                sac=dict(n_envs=16, critic_warmup_updates=2000),
                improve_recipe=dict(branch_length=None, uncertainty_penalty=0.0)),
}


def pipeline_keys(seed: int, method_index: int) -> dict[str, jax.Array]:
    """The keys of ``improve_in_simulators`` for the method at ``method_index`` of its
    checkpoints (``train.config.METHODS`` order by default): SAC fine-tuning ("improve"), the
    guard ("guard") and the paired real measurement shared by every method ("measure");
    scripts that repeat one method's fine-tuning (``experiments/guard_horizon.py``) take them
    here, so that they repeat it exactly."""
    return {"improve": jax.random.PRNGKey(seed + 10 + method_index),
            "measure": jax.random.PRNGKey(seed + 20),
            "guard": jax.random.PRNGKey(seed + 30 + method_index)}


def improve_in_simulators(task_name: str, test_path: str, ckpts: dict[str, str], sizes: dict,
                          horizon: int, seed: int = 0, guard_margin: float | None = GUARD_MARGIN,
                          guard_episodes: int = 16, guard_floors: dict | None = None,
                          guard_floor_scale: float = 1.0,
                          recipe: dict | None = None, train_path: str | None = None,
                          log=print) -> dict[str, dict]:
    """Fine-tune every test policy with SAC inside each method's simulator, pass it through
    the deployment guard (``guard_margin``; None: every fine-tuned policy deploys), then
    measure the real return (MJX) of what deploys, paired with the start policy's: C0 and C1
    over the same ``value_episodes`` start states and noise draws (``paired_episode_returns``),
    so that a kept start has C1 = C0 exactly (I = 0) and a deployed policy's real gain is not
    drowned by the two measurements' own noise. The guard is ``rl2s improve``'s
    (``improve.deployment_guard`` on the final actor): every elite member, over
    ``guard_episodes`` simulated episodes as long as the real ones the gain is measured on
    (the data's episode length; SAC's episodes may be shorter: ``horizon``), must predict a
    gain above ``guard_margin`` x |start value| and above the method's floor:
    ``guard_floor_scale`` x the simulator's MVD on the training policies, the worst error it is
    known to make, at the guard's horizon
    and gamma (``guard_floors[method]``, ``training_error_floor``, where measured there;
    else measured here on ``train_path``'s policies; else 0). A policy that a short horizon
    rewards for speed can fall later: judged over short episodes it would deploy and lose.
    ``recipe`` (default ``sizes["improve_recipe"]``, else none): the simulated env SAC
    fine-tunes in, {"branch_length": MBPO rollouts of that many steps from every real state of
    the test data (None: whole episodes from its start states), "uncertainty_penalty": MOPO's
    lambda on the ensemble's disagreement, in units of its mean on the test data}; the guard
    always values whole episodes from the start states.
    -> {method: {"c0", "c0_se", "c1", "c1_se", "I", "c0_data" (the data's true values),
    "deployed" (bool), "predicted_gain" / "predicted_gain_mean" (None without the guard)
    (lists [P]), "mpi", "api", "guard_margin", "guard_floor", "guard_floor_scale",
    "guard_horizon", "recipe"}}."""


    check_floor_scale(guard_floor_scale)
    ds = load_dataset(test_path)
    if not ds.has_values:
        raise ValueError(f"data: {test_path} has no true values, so C0 is unknown")
    task = get_task(task_name)
    policies, pool = policies_for(ds), start_pool(ds)
    episode_length = int(ds.meta.get("episode_length") or task.episode_length)
    gamma = float(ds.meta.get("gamma") or 0.999)
    cfg = SACConfig.fine_tuning(**{"episode_length": horizon, **sizes["sac"]})
    recipe = dict(sizes.get("improve_recipe") or {}) if recipe is None else dict(recipe)
    branch = recipe.get("branch_length")
    sac_pool = pool if branch is None else branch_pool(ds, max_states=100_000, seed=seed)
    P = len(ds.value)
    floors, train = {}, None  # train: (dataset, policies) of train_path, loaded where needed
    deployed, guards = [], {}
    for i, (method, ckpt) in enumerate(ckpts.items()):
        t0 = time.perf_counter()
        sim = load_simulator(ckpt)
        opts = scaled_env_options(sim, *real_rows(ds, seed=seed), rollout_length=branch,
                                  uncertainty_penalty=recipe.get("uncertainty_penalty", 0.0))
        keys = pipeline_keys(seed, i)
        params, _ = improve_policies(sim, task, sac_pool, policies, keys["improve"], cfg,
                                     n_iterations=sizes["improve_iterations"],
                                     chunk_iterations=min(1000, sizes["improve_iterations"]),
                                     env_options=opts)
        log(f"[pipeline] SAC in {method}'s simulator: {time.perf_counter() - t0:.0f}s")
        accept, lo, mean = np.ones(P, bool), [None] * P, [None] * P
        if guard_margin is not None:  # the simulator's own verdict, start vs fine-tuned
            floors[method] = guard_floor((guard_floors or {}).get(method), episode_length,
                                         gamma)
            if not floors[method] and train_path is not None:  # measured at the guard's
                if train is None:                                  # horizon and gamma
                    train_ds = load_dataset(train_path)
                    train = (train_ds, policies_for(train_ds, data_path=train_path))
                floors[method] = float(evaluate_simulator(
                    sim, *train, key=jax.random.PRNGKey(seed), n_episodes=guard_episodes,
                    horizon=episode_length, gamma=gamma)["metrics"]["mvd"])
            floors[method] *= guard_floor_scale
            g, params = deploy_through_guard(
                sim, task, pool, policies, params, None, keys["guard"],
                margin=guard_margin, n_episodes=guard_episodes, horizon=episode_length,
                gamma=gamma, floor=floors[method])
            accept = np.asarray(g["accepted"])
            lo, mean = g["predicted_gain"], g["predicted_gain_mean"]
            log(f"[pipeline] guard (margin {guard_margin}, floor {g['floor']:.3g}) in {method}'s "
                f"simulator: "
                f"{int(accept.sum())} of {P} fine-tuned policies deployed")
        deployed.append(params)
        guards[method] = (accept, lo, mean)
    # One real measurement of the start and every method's deployed policies, paired
    # (one MJX compile).
    t0 = time.perf_counter()
    r0, rs = paired_episode_returns(task.make_env(), policies, deployed,
                                    pipeline_keys(seed, 0)["measure"],
                                    n_episodes=sizes["value_episodes"],
                                    episode_length=episode_length, gamma=gamma)
    out = {}
    for method, r1 in zip(ckpts, rs, strict=True):
        m = paired_returns(r0, r1)
        accept, lo, mean = guards[method]
        out[method] = {"c0": m["c0"].tolist(), "c0_se": m["c0_se"].tolist(),
                       "c1": m["c1"].tolist(), "c1_se": m["c1_se"].tolist(),
                       "I": m["I"].tolist(), "mpi": m["mpi"], "api": m["api"],
                       "c0_data": [float(v) for v in ds.value],
                       "deployed": accept.tolist(), "predicted_gain": lo,
                       "predicted_gain_mean": mean, "guard_margin": guard_margin,
                       "guard_floor": floors.get(method), "guard_horizon": episode_length,
                       "guard_floor_scale": guard_floor_scale,
                       "recipe": recipe, "iterations": sizes["improve_iterations"]}
        log(f"[pipeline] improvement in {method}'s simulator: MPI {m['mpi']:.3f}  API "
            f"{m['api']:.3f} ({int(accept.sum())} of {P} deployed)")
    log(f"[pipeline] real returns of the start and deployed policies measured in "
        f"{time.perf_counter() - t0:.0f}s")
    return out


def pipeline_sizes(spec, profile: str) -> dict:
    """The profile's sizes with the spec's (a ``PipelineSpec``, or an object with its fields):
    ``--recipe`` (``improve.recipes``: the task's SAC iterations, SAC fields, simulated env and
    guard floor scale), then what is given: the sizes, SAC fields (``--set``, checked by
    ``fine_tuning_overrides``), the fine-tuning's simulated env (``--branch-length``,
    ``--uncertainty-penalty``) and ``guard_floor_scale`` (else 1). ValueError before any work."""
    sizes = dict(PROFILES[profile])
    recipe = getattr(spec, "recipe", None)
    scale = check_floor_scale(getattr(spec, "guard_floor_scale", None))
    if recipe is not None:
        rs = recipe_settings(recipe, spec.task)  # checks the name
        sizes.update(recipe=recipe, improve_iterations=rs["iterations"],
                     sac={**sizes["sac"], **rs["sac"]}, improve_recipe={
                         k: rs[k] for k in ("branch_length", "uncertainty_penalty")})
        scale = rs["guard_floor_scale"] if scale is None else scale
    sizes["guard_floor_scale"] = 1.0 if scale is None else scale
    for k in ("transitions_per_policy", "value_episodes", "steps", "eval_every",
              "improve_iterations"):
        if getattr(spec, k, None) is not None:
            sizes[k] = getattr(spec, k)
    sizes["sac"] = {**sizes["sac"],
                    **fine_tuning_overrides(parse_overrides(getattr(spec, "set", None)))}
    penalty = getattr(spec, "uncertainty_penalty", None)
    if penalty is not None and not (np.isfinite(penalty) and penalty >= 0):
        raise ValueError(f"uncertainty-penalty: expected a finite float >= 0, got {penalty}")
    sizes["improve_recipe"] = {**sizes["improve_recipe"], **{
        k: getattr(spec, k) for k in ("branch_length", "uncertainty_penalty")
        if getattr(spec, k, None) is not None}}
    return sizes


def evaluate_run(run_dir: str, test_path: str, setting: EvalSetting,
                 level: float | None = DEFAULT_LEVEL) -> dict:
    """The pipeline's evaluation of one method's run: its final checkpoint on the test data
    in ``setting`` (``app.evaluation.evaluate_checkpoint``: the numbers of the run's own
    summary.json and of `rl2s evaluate` in the same setting), with each test policy's value
    interval at ``level`` calibrated on the training policies ("trust": optimistic, the
    simulator was fitted on their data; None: none)."""
    return evaluate_checkpoint(os.path.join(run_dir, "checkpoints"), test_path,
                               setting=setting, level=level)


def _train_spec(spec: PipelineSpec, method: str, run_dir: str, datasets: dict, sizes: dict,
                profile: str) -> TrainSpec:
    """The pipeline's training run of ``method``: its train data, test data evaluated every
    ``sizes["eval_every"]`` steps in the pipeline's evaluation setting."""
    return TrainSpec(
        data=datasets["train"]["path"], steps=sizes["steps"], out=run_dir, method=method,
        profile=profile, seed=spec.seed, save_every=sizes["eval_every"],
        eval_data=datasets["test"]["path"], eval_every=sizes["eval_every"],
        eval_episodes=spec.eval_episodes, eval_horizon=spec.eval_horizon,
        eval_seed=spec.eval_seed, truth=spec.truth, quiet=spec.quiet)


def run_pipeline(spec: PipelineSpec) -> int:
    """The whole pipeline for one task: collect, train the four methods, evaluate, fine-tune
    the test policies in each simulator through the deployment guard (``guard_margin(spec)``:
    the flag's margin, the recipe's or the default; none with ``no_guard``), report."""
    margin = guard_margin(spec)
    t_start = time.perf_counter()
    backend = jax.default_backend()
    profile = spec.profile if spec.profile != "auto" else ("gpu" if backend == "gpu" else "cpu")
    sizes = pipeline_sizes(spec, profile)
    methods = spec.methods.split(",")
    bad = [m for m in methods if m not in ("rl2s", "gail", "bc", "rl2s-bc")]
    if bad:
        raise ValueError(f"methods: expected a comma list of rl2s, gail, bc, rl2s-bc; got {bad}")
    out = spec.out or os.path.join("results", spec.task)
    os.makedirs(out, exist_ok=True)
    print(f"[pipeline] task {spec.task}, backend {backend}, profile {profile} -> {out}\n"
          f"[pipeline] {sizes}")
    data_key = {k: sizes[k] for k in ("transitions_per_policy", "value_episodes")}
    data_key.update(seed=spec.seed, task=spec.task)
    if spec.zoo:
        data_key["zoo"] = spec.zoo
    if spec.episode_length is not None:
        data_key["episode_length"] = spec.episode_length
    summary = {"task": spec.task, "profile": profile, "backend": backend,
               "machine": machine_info(), "sizes": sizes,
               "guard_margin": margin, "guard_floor_scale": sizes["guard_floor_scale"],
               "methods_run": methods, "command": " ".join(["rl2s"] + sys.argv[1:]),
               "datasets": {}}
    state_path = os.path.join(out, "pipeline.json")
    previous = {}
    if os.path.exists(state_path):
        with open(state_path) as f:
            previous = json.load(f)
    for split in ("train", "test"):
        path = os.path.join(out, f"{split}.npz")
        if os.path.exists(path) and previous.get("data_key") == data_key:
            ds = load_dataset(path)
            print(f"[pipeline] {split} data: reusing {path}")
        else:
            ds = collect_dataset(spec.task, split, sizes["transitions_per_policy"],
                                 seed=spec.seed, value_episodes=sizes["value_episodes"],
                                 episode_length=spec.episode_length, progress=not spec.quiet,
                                 zoo_path=spec.zoo)
            save_dataset(path, ds)
            print(f"\n== {split} data: {path}\n{dataset_summary(ds)}")
        summary["datasets"][split] = {"path": path, "transitions": ds.n_transitions,
                                      "policies": ds.n_policies}
    summary["data_key"] = data_key
    write_json(state_path, summary)
    evals, curves, runs = {}, {}, {}
    setting = EvalSetting.from_flags(spec.eval_episodes, spec.eval_horizon, spec.eval_seed,
                                     spec.truth)
    summary["setting"] = setting.to_dict()
    for method in methods:
        run_dir = os.path.join(out, method)
        print(f"\n[pipeline] training {method} -> {run_dir}")
        runs[method] = run_training(_train_spec(spec, method, run_dir, summary["datasets"],
                                                sizes, profile))
        evals[method] = evaluate_run(run_dir, summary["datasets"]["test"]["path"], setting)
        curves[method] = load_curve(os.path.join(run_dir, "eval.jsonl"))
    summary["train_runs"] = {m: {k: r[k] for k in ("steps", "seconds", "avd_train",
                                                   "mvd_train")} for m, r in runs.items()}
    if sizes["improve_iterations"]:
        improvement = improve_in_simulators(
            spec.task, summary["datasets"]["test"]["path"],
            {m: os.path.join(out, m, "checkpoints") for m in methods}, sizes,
            horizon=saved_field(runs[methods[0]]["config"], "vd.horizon"), seed=spec.seed,
            guard_margin=margin, guard_episodes=spec.guard_episodes,
            guard_floors={m: training_error_floor(r) for m, r in runs.items()},
            guard_floor_scale=sizes["guard_floor_scale"],
            train_path=summary["datasets"]["train"]["path"])
        for m, imp in improvement.items():
            evals[m]["metrics"].update(mpi=imp["mpi"], api=imp["api"])
            evals[m]["improvement"] = imp
    summary["seconds"] = round(time.perf_counter() - t_start, 1)
    text = write_report(out, summary, evals, curves)
    imp = improvement_text(evals)
    st = next(iter(evals.values()))
    print(f"\n[pipeline] test policies ({profile} profile, {backend}), "
          f"{summary['seconds']:.0f}s, "
          f"{EvalSetting(**st['setting']).describe(st['true_value_source'])}:\n{text}\n{imp}"
          f"\n-> {out}/report.md, report.json, *.png")
    return 0
