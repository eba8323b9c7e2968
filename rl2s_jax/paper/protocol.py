"""The paper's protocol (``experiments/paper.py``): its sizes per profile and task, the zoo's
train / test data, the oracle row, one vmapped training program per model family with its
evaluation curves (the adversarial family pre-trains once per seed and forks its methods'
lanes from there, ``train.lanes.fork``; the likelihood family's BC lanes join from that
pre-training, ``paper.fork``), model selection and bootstrap intervals, and the
result JSON (the summary over seeds, the printed table, the atomic write). The improvement
phases are ``paper.improvement_phases``; the lanes themselves (vmapped runs: training,
evaluation, fine-tuning) ``train.lanes``, ``evaluate.lane_scores`` and ``improve.lane_finetune``."""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax._timing import PartTimer, timed
from rl2s_jax.app.pipeline import collect_dataset
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.data.values import true_values, true_values_se, truth_used
from rl2s_jax.evaluate.lane_scores import (
    EVAL_METRICS,
    evaluate_lanes,
    intervals_over_seeds,
    oracle_noise_ceiling,
    oracle_rows,
)
from rl2s_jax.evaluate.metrics import ranking_metrics
from rl2s_jax.evaluate.scores import evaluate_simulator
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.paper.fork import Join, Trunk, join_refusal, take_lanes, train_chunk
from rl2s_jax.sharding import is_writer, lane_mesh, replicate, shard_lanes
from rl2s_jax.stats import bootstrap_intervals
from rl2s_jax.train.config import DEFAULT_EPS, TrainConfig
from rl2s_jax.train.cvar import n_worst
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.lanes import (
    heldout_start_pool,
    init_lanes,
    select_point,
)
from rl2s_jax.train.loop import worst_vd_jumps
from rl2s_jax.train.step import simulator
from rl2s_jax.zoo.zoo import load_zoo, zoo_dir

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
# (family, config method, its lanes' methods): one vmapped program per family.
FAMILIES = (("adversarial", "rl2s", ("rl2s", "gail")), ("mle", "rl2s-bc", ("rl2s-bc", "bc")))
# mpi/api: C0 from the data's true values, C1 measured apart; *_paired: C0 and C1 measured
# paired (the same starts and noise draws, --improve-episodes each)
IMPROVE_METRICS = ("mpi", "api", "mpi_paired", "api_paired")
METRICS = EVAL_METRICS + IMPROVE_METRICS

# Sizes per profile. gpu: 3 seeds, 1200 steps (the 1000 pre-training steps of the fitted
# model family, then 200 WGAIL; RESULTS@bf0c7b2, "Ant and Hopper: the likelihood model was
# underfit"), every test policy fine-tuned in the simulators of 2 seeds, SAC's KL weight 0.1
# (it costs most of the in-simulator gain; the control's recipe at 0.01 wins most of it: the
# flags in RESULTS, "Policy improvement inside the simulators").
# Measured on one H100 (RESULTS@bf0c7b2, "The protocol on the new model family"), per task,
# each family alone: data 83-97 s, the adversarial program (6 lanes) 355-375 s, the
# likelihood program 190-210 s, SAC 18-22 s, the real measurement of the fine-tuned policies
# 38 s (Hopper; more with 43 test policies), Hopper's oracle at 128 / 128 episodes 261 s.
# Two processes sharing the GPU run no faster than one after the other. cpu: small, for a
# 2-core machine.
PROFILES = {
    "gpu": dict(seeds=3, transitions_per_policy=20_000, value_episodes=16, steps=1200,
                eval_every=600, eval_episodes=32, improve_policies=0, improve_seeds=2,
                improve_episodes=32,
                improve_iterations=2000, sac_envs=16, sac=dict(kl_weight=0.1)),
    "cpu": dict(seeds=3, transitions_per_policy=2000, value_episodes=4, steps=300,
                eval_every=100, eval_episodes=8, improve_policies=10, improve_seeds=1,
                improve_episodes=4,
                improve_iterations=300, sac_envs=4, sac=dict(hidden=(64, 64), batch_size=128)),
}

# Per-task changes to a profile. Ant's returns spread so widely between episodes (per-episode
# sd ~830 against ~90 between neighbouring test policies) that with 16 truth / 32 simulated
# episodes even the real dynamics rank at tau 0.78; with 256 / 256 the oracle reaches 0.88
# (RESULTS@bf0c7b2: "Many episodes on Ant and Hopper"); Hopper's oracle reaches 0.99 at
# 128 / 128 (0.96 at 32), and 16 episodes leave Walker2d an evaluation-noise tau std of 0.038
# ("The oracle"), so it gets 64 / 64.
TASK_SIZES = {"gpu": {"ant": dict(value_episodes=256, eval_episodes=256),
                      "hopper": dict(value_episodes=128, eval_episodes=128),
                      "walker2d": dict(value_episodes=64, eval_episodes=64)}}


# --policy-split: the zoo's train / test split, or its training policies split again
POLICY_SPLITS = ("zoo", "validation", "lineage")


def profile_sizes(profile: str, task: str) -> dict:
    """A profile's sizes with the task's changes (TASK_SIZES) applied."""
    return {**PROFILES[profile], **TASK_SIZES.get(profile, {}).get(task, {})}


def log(msg: str) -> None:
    print(msg, flush=True)


def positive_int(text: str) -> int:
    """argparse type: an int >= 1, else an error naming what was expected."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an int >= 1, got {text}")
    return value


def none_if_nan(x):
    """float(x), None when it is not finite (JSON has no NaN)."""
    x = float(x)
    return x if np.isfinite(x) else None


# ------------------------------------------------------------------ data


def data_timer(timings: dict | None, t_start: float | None = None) -> PartTimer | None:
    """The data phase's PartTimer: each part's seconds added to ``timings["data_<part>"]``
    (rounded to 0.1 s) and printed as "[paper] data_<part>: X.Xs (elapsed Ys)", Y counted from
    ``t_start`` (a ``time.perf_counter()``; None: now), the lines that
    experiments/gpu_profile.py reads as the data phase's parts. None without ``timings``."""
    if timings is None:
        return None
    t0 = time.perf_counter() if t_start is None else t_start

    def on_part(name: str, seconds: float) -> None:
        key = f"data_{name}"
        timings[key] = round(timings.get(key, 0.0) + seconds, 1)
        log(f"[paper] {key}: {seconds:.1f}s (elapsed {time.perf_counter() - t0:.0f}s)")

    return PartTimer(on_part)


def load_or_collect(task: str, sizes: dict, data_dir: str, seed: int,
                    episode_length: int | None, progress: bool, policy_split: str = "zoo", *,
                    timings: dict | None = None, t_start: float | None = None):
    """The train and test Datasets of the zoo's split: reused from data_dir when collected with
    the same sizes (``transitions_per_policy``, ``value_episodes`` of ``sizes``), else
    collected as ONE ``collect_dataset(task, "all", ...)`` run (one MJX program for all the
    zoo's policies) and split with ``Dataset.select_policies``. ``policy_split`` "validation":
    the zoo's training policies split again (``validation_datasets``), the test policies unused;
    "lineage": likewise, one learner lineage of them held out (``Zoo.held_out_lineage``).
    ``timings`` (paper.py's): each part's seconds as "data_<part>" (``data_timer``): "load"
    when reused; else "setup", ``collect``'s COLLECT_PARTS and "split_save" (the split, the
    compressed .npz files written). The data is the same with or without it.
    -> ({"train": Dataset, "test": Dataset}, reused)"""
    if policy_split not in POLICY_SPLITS:
        raise ValueError(f"policy_split: expected one of {', '.join(POLICY_SPLITS)}, got "
                         f"{policy_split!r}")
    if policy_split != "zoo":
        datasets, reused = load_or_collect(task, sizes, data_dir, seed, episode_length, progress,
                                           timings=timings, t_start=t_start)
        return validation_datasets(datasets["train"], load_zoo(task), policy_split), reused
    timer = data_timer(timings, t_start)
    paths = {split: os.path.join(data_dir, f"{task}_{split}.npz") for split in ("train", "test")}
    key_path = os.path.join(data_dir, f"{task}_data.json")
    data_key = {"task": task, "seed": seed, "episode_length": episode_length,
                "transitions_per_policy": sizes["transitions_per_policy"],
                "value_episodes": sizes["value_episodes"]}
    if all(os.path.exists(p) for p in paths.values()) and os.path.exists(key_path):
        with open(key_path) as f:
            same = json.load(f) == data_key
        if same:
            with timed(timer, "load"):
                datasets = {split: load_dataset(p) for split, p in paths.items()}
            return datasets, True
    everything = collect_dataset(task, "all", sizes["transitions_per_policy"], seed=seed,
                                 value_episodes=sizes["value_episodes"],
                                 episode_length=episode_length, progress=progress, timer=timer)
    with timed(timer, "split_save"):
        zoo = load_zoo(task)
        os.makedirs(data_dir, exist_ok=True)
        out = {}
        for split, path in paths.items():
            out[split] = zoo_split_part(everything, zoo, split)
            save_dataset(path, out[split])
        write_json(key_path, data_key, indent=None)
    return out, False


def validation_datasets(train, zoo, policy_split: str = "validation") -> dict:
    """The protocol's training Dataset split again, as ``load_or_collect``'s splits: {"train":
    its "fit" policies, "test": its "validation" policies} (``Zoo.split_ids``; policy_split
    "lineage": "lineage-fit" / "lineage-validation", one learner lineage held out), each with
    its zoo ids in ``meta["source"]``, so that a recipe is chosen on policies the simulators
    never saw without touching the test policies."""
    prefix = "lineage-" if policy_split == "lineage" else ""
    return {split: zoo_split_part(train, zoo, f"{prefix}{name}")
            for split, name in (("train", "fit"), ("test", "validation"))}


def zoo_split_part(ds, zoo, split: str):
    """The policies of the zoo's ``split`` (``Zoo.split_ids``) out of ``ds``, found through its
    ``meta["source"]["zoo_ids"]``, with that split and its zoo ids in the part's
    ``meta["source"]`` (how ``policies_for`` finds a Dataset's policies)."""
    ids = [int(i) for i in ds.meta["source"]["zoo_ids"]]
    want = zoo.split_ids(split)
    part = ds.select_policies([ids.index(i) for i in want])
    part.meta["source"] = {**part.meta["source"], "split": split,
                           "zoo_ids": [int(i) for i in want]}
    return part


def zoo_sha256(task: str) -> str | None:
    """sha256 of rl2s_jax/zoo/shipped/<task>/zoo.npz, the zoo the result was measured on."""
    path = os.path.join(zoo_dir(task), "zoo.npz")
    if not os.path.exists(path):
        return None
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


# ------------------------------------------------------------------ the oracle row


def run_oracle(result: dict, task: str, test_ds, test_pols, seeds, cfg: TrainConfig,
               sizes: dict, *, phase: Callable[[str, float], None],
               save: Callable[[], None]) -> None:
    """The control row (``evaluate.lane_scores.oracle_rows``: the real dynamics through the lanes'
    evaluation path, per seed, at cfg's horizon and gamma) and the noise ceiling of these
    sizes, into ``result``; ``phase("oracle", t0)`` records its time, ``save()`` writes."""
    t0 = time.perf_counter()
    orc = oracle_rows(task, test_ds, test_pols, seeds, n_episodes=sizes["eval_episodes"],
                      horizon=cfg.vd.horizon, gamma=cfg.gamma, n_boot=sizes["bootstrap"])
    result["per_seed"]["oracle"] = {**orc["per_seed"], "mpi": [], "api": []}
    result["lane_intervals"] = {"oracle": orc["intervals"]}
    result["intervals"] = {"oracle": intervals_over_seeds(orc["intervals"])}
    result["oracle_sim_value"] = orc["sim_value"]
    result["oracle_sim_length"] = orc["sim_length"]
    result["noise_ceiling"] = oracle_noise_ceiling(
        test_ds, true_values(test_ds, cfg.vd.horizon, cfg.gamma), orc["sim_return_sd"],
        n_sim=sizes["eval_episodes"], horizon=cfg.vd.horizon, gamma=cfg.gamma)
    phase("oracle", t0)
    save()
    log(f"[paper] oracle (real dynamics, horizon {cfg.vd.horizon}): "
        + "  ".join(f"{k} {np.mean(v):.3f}" for k, v in orc["per_seed"].items()
                    if k in ("kendall_tau", "ndcg@1", "spearman", "avd", "mvd")))
    nc = result["noise_ceiling"]
    log(f"[paper] noise ceiling (an exact simulator, {nc['n_truth']} truth / "
        f"{nc['n_sim']} simulated episodes): kendall_tau {nc['kendall_tau']['mean']:.3f} "
        f"[{nc['kendall_tau']['lo']:.2f}, {nc['kendall_tau']['hi']:.2f}]  ndcg@1 "
        f"{nc['ndcg@1']['mean']:.3f}")


# ------------------------------------------------------------------ training


def _fmt(x, f):
    return "n/a" if x is None else format(x, f)


def _evaluation_point(result, lanes, step, m, evals, selects, points, worst, header):
    """One evaluation of every lane: its model-selection point, the worst-VD warnings, the
    ``header`` line, its curve row (printed)."""
    for i, (meth, s) in enumerate(lanes):
        points[i].append({"step": step, "select": selects[i], "test": evals[i]})
        jumps, worst[i] = worst_vd_jumps(np.asarray(m["mvd_train"])[i:i + 1],
                                         np.ones(1, bool), worst[i])
        for _, before, after in jumps:  # per lane, between evaluations
            log(f"[paper] warning: {meth} seed {s}: the worst training-policy VD rose "
                f"from {before:.4g} to {after:.4g} by step {step}")
            result.setdefault("worst_vd_jumps", {}).setdefault(meth, []).append(
                {"seed": s, "step": step, "before": before, "after": after})
    log(header)
    for i, (meth, s) in enumerate(lanes):
        r = evals[i] or {}
        row = {"step": step, "lane": f"{meth}/{s}", "method": meth, "seed": s,
               "avd": r.get("avd"), "mvd": r.get("mvd"), "tau": r.get("kendall_tau"),
               "ndcg@1": r.get("ndcg@1"),
               "select_tau": (selects[i] or {}).get("kendall_tau"),
               "select_avd": (selects[i] or {}).get("avd"),
               "avd_train": none_if_nan(m["avd_train"][i]),
               "mvd_train": none_if_nan(m["mvd_train"][i]),
               "finite": bool(m["finite"][i])}
        result["curves"].append(row)
        log(f"  {meth:<8} seed {s}  AVD {_fmt(row['avd'], '8.1f')}  MVD "
            f"{_fmt(row['mvd'], '8.1f')}  tau {_fmt(row['tau'], '6.3f')}  nDCG@1 "
            f"{_fmt(row['ndcg@1'], '.3f')}  train AVD {_fmt(row['avd_train'], '.1f')}"
            f"  selected {int(m['n_selected'][i])}"
            f"{'' if row['finite'] else '  NON-FINITE'}")


def lane_eps(method: str, robust_eps=None) -> float:
    """A lane's initial eps: "rl2s@0.1" names its own; a robust method's (eps < 1) is
    ``robust_eps`` when given, else the method's default (DEFAULT_EPS)."""
    base, _, own = method.partition("@")
    if own:
        return float(own)
    default = DEFAULT_EPS[base]
    return float(robust_eps) if robust_eps is not None and default < 1 else default


def _final_rows(result, family, lanes, eps, points, evals, values, returns, lengths, truth,
                truth_se, n_boot):
    """Per lane: the selected point's test metrics, the final ones, their bootstrap intervals
    over episodes (``n_boot`` replicates, seed = the lane's), the simulated values (the test
    policies'; the training policies' at the last point, ``train_sim_value``)."""
    for i, (meth, s) in enumerate(lanes):
        chosen = select_point(points[i])
        sel = result.setdefault("selected", {}).setdefault(
            meth, {"step": [], **{k: [] for k in EVAL_METRICS}})
        sel["step"].append(None if chosen is None else chosen["step"])
        for k in EVAL_METRICS:
            sel[k].append(None if chosen is None else chosen["test"][k])
        r = evals[i]
        for k in EVAL_METRICS:
            result["per_seed"][meth][k].append(None if r is None else r[k])
        iv = None
        if r is not None and n_boot and np.all(np.isfinite(returns[i])):
            iv = bootstrap_intervals(truth, returns[i], ranking_metrics, truth_se,
                                     n_boot=n_boot, seed=s)["metrics"]
        result.setdefault("lane_intervals", {}).setdefault(meth, []).append(iv)
        result.setdefault("intervals", {})[meth] = intervals_over_seeds(
            result["lane_intervals"][meth])
        result["lanes"][f"{meth}/{s}"] = {
            "family": family, "eps": eps[i], "seed": s,
            "sim_value": np.asarray(values[i]).tolist(),
            "sim_length": np.round(lengths[i], 1).tolist(),
            "train_sim_value": ((points[i] or [{}])[-1].get("select") or {}).get("sim_value"),
            "finite": all(row["finite"] for row in result["curves"]
                          if row["lane"] == f"{meth}/{s}")}


def train_family(result: dict, family: str, cfg: TrainConfig, methods, *, train_ds, test_ds,
                 train_pols, test_pols, seeds, sizes: dict, robust_eps=None,
                 check_eval: bool = False, fork: bool = True, share: dict | None = None):
    """One family's lanes (its ``methods`` x ``seeds``, key PRNGKey(seed), eps the method's
    default or ``robust_eps`` for the robust ones) trained as one vmapped program over the
    local devices, evaluated on the test policies and the training policies' held-out
    episodes every ``sizes["eval_every"]`` steps, into ``result`` (curves, per-seed final
    metrics, model selection, intervals, lanes, train_config, timings["eval_<family>"]).
    ``check_eval``: also ``evaluate_simulator`` on the first lane (result["eval_check"]).

    ``fork`` (an adversarial family with pre-training, one process): the lanes of a seed
    are identical through pre-training, so only the first method's lanes (the trunk) train
    and are evaluated until ``cfg.adversarial.pretrain_steps``; then ``train.lanes.fork``
    continues each other lane from its seed's trunk lane with its own eps, critic, simulated
    envs and buffer (drawn by its own ``init``): the same states as separate lanes, at
    1 / len(methods) of the pre-training work. result["fork"][family] says whether and where
    it forked.

    ``share`` (a dict passed to every family of one process; with ``fork``): the forking
    family leaves its trunk there (share["trunk"]: its evaluation points up to the fork and
    its pre-trained fields at ``pretrain_steps``), and a later family's BC lanes, whose
    likelihood steps from the same key are the trunk's pre-training, continue from it: the
    other lanes train alone until ``pretrain_steps``, the BC lanes report the trunk's
    evaluations until then and join there (``join_trunk``), when the trunk is compatible
    (``join_refusal``: one process, the same seeds, data, evaluation sizes and config but
    for the method); else they train from step 0 and a line says why.
    result["fork"][family] says where and from what they joined.
    -> (lanes [(method, seed)] * L, their final TrainState, leading lane axis L)"""
    t0 = time.perf_counter()
    data_host = data = make_train_data(train_ds, train_pols, cfg)
    truth = true_values(test_ds, cfg.vd.horizon, cfg.gamma)
    test_pool = start_pool(test_ds)
    select_pool, select_truth = heldout_start_pool(train_ds), np.asarray(data.true_value)
    lanes = [(m, s) for m in methods for s in seeds]
    points = [[] for _ in lanes]  # per lane: {"step", "select", "test"} (model selection)
    eps = [lane_eps(m, robust_eps) for m, _ in lanes]
    keys = jnp.stack([jax.random.PRNGKey(s) for _, s in lanes])
    states = init_lanes(keys, cfg, data, eps=jnp.asarray(eps, jnp.float32))
    mesh_all = mesh = lane_mesh(len(lanes))  # lanes over the local devices (one: unchanged)
    pending, note, record = None, "", None  # a fork (Trunk) or join (Join) to come
    joining = [i for i, (m, _) in enumerate(lanes) if m == "bc"]
    if fork and cfg.pretrains and len(methods) > 1 and jax.process_count() == 1:
        trunk, fork_step = None, cfg.adversarial.pretrain_steps
        if share is not None:
            trunk = share["trunk"] = {
                "family": family, "method": methods[0], "config": cfg, "seeds": list(seeds),
                "at_step": fork_step,
                "sizes": {k: sizes[k] for k in ("eval_every", "eval_episodes")},
                "inputs": (train_ds, test_ds, train_pols, test_pols), "points": {},
                "fields": None, "finite_before": None}
        pending = Trunk(jax.block_until_ready(shard_lanes(states, mesh_all)), len(seeds),
                         len(lanes), fork_step, trunk)
        record = {"trunk": methods[0], "at_step": fork_step,
                  "steps_saved_per_seed": (len(methods) - 1) * min(fork_step, sizes["steps"])}
        note = f"; the {methods[0]} lanes pre-train for all (fork at step {fork_step})"
    elif joining:
        trunk = (share or {}).pop("trunk", None) if fork else None
        why = ("the fork is off (--no-fork)" if not fork else join_refusal(
            trunk, cfg, lanes, joining, eps, seeds=seeds, sizes=sizes,
            inputs=(train_ds, test_ds, train_pols, test_pols)))
        if why is None:
            pending = Join(trunk, states, lanes, joining)
            at = pending.at
            record = {
                "trunk": trunk["method"], "trunk_family": trunk["family"],
                "joined": sorted({lanes[i][0] for i in joining}), "at_step": at,
                "steps_saved_per_seed": at * len({lanes[i][0] for i in joining})}
            note = (f"; the bc lanes join at step {at} from the {trunk['family']} family's "
                    f"{trunk['method']} lanes (their pre-training)")
        else:
            log(f"[paper] {family}: the bc lanes train from step 0, not from the adversarial "
                f"trunk's pre-training: {why}")
    result.setdefault("fork", {})[family] = record
    if pending is not None:
        mesh = lane_mesh(len(pending.now))
        states = take_lanes(states, pending.now)
    states = jax.block_until_ready(shard_lanes(states, mesh))
    data = replicate(data, mesh)
    log(f"[paper] {family}: {len(lanes)} lanes over {mesh_all.size} device(s) "
        f"{', '.join(f'{m}/{s} (eps {e:g})' for (m, s), e in zip(lanes, eps, strict=True))}"
        f", config method {cfg.method}; init {time.perf_counter() - t0:.1f}s{note}")
    n_sel = [int(n_worst(e, data_host.n_policies)) if cfg.vd.every else data_host.n_policies
             for e in eps]
    n = sizes["eval_every"]
    compiled, evals, t_eval = {}, None, 0.0
    worst = [None] * len(lanes)  # each lane's worst training VD at its last evaluation
    roll = dict(n_episodes=sizes["eval_episodes"], horizon=cfg.vd.horizon, gamma=cfg.gamma)
    lane_seeds = [s for _, s in lanes]
    for _ in range(sizes["steps"] // n):
        t1 = time.perf_counter()
        what = f"{len(states.step)} {'trunk ' if isinstance(pending, Trunk) else ''}lanes"
        if pending is not None and int(states.step[0]) + n > pending.at:
            what += (f" forked into {len(lanes)}" if isinstance(pending, Trunk) else
                     f", joined by {len(joining)} bc lanes") + f" at step {pending.at}"
        states, m, data, pending = train_chunk(states, data, n, cfg, compiled, pending,
                                                data_host, mesh_all)
        states, m = jax.block_until_ready((states, m))
        seconds = time.perf_counter() - t1
        t1 = time.perf_counter()
        sims = simulator(states)
        seeds_now = (lane_seeds if pending is None else
                     [lane_seeds[i] for i in pending.now])  # the lanes training now
        evals, values, returns, lengths = evaluate_lanes(
            sims, seeds_now, test_pols, test_pool, truth, key_base=1000, **roll)
        selects, train_values = evaluate_lanes(sims, seeds_now, data.policies, select_pool,
                                               select_truth, key_base=2000, **roll)[:2]
        selects = [r and {**r, "sim_value": v.tolist()}  # rides with the point through forks
                   for r, v in zip(selects, train_values, strict=True)]
        step = int(states.step[0])
        if pending is not None:  # the other lanes are their trunk lanes until the fork / join
            evals, values, returns, lengths, selects, m = pending.rows(
                step, evals, values, returns, lengths, selects, m, n_sel)
        t_eval += time.perf_counter() - t1
        header = (f"[paper] {family} step {step}: {n} steps of {what} in {seconds:.1f}s; "
                  f"test evaluation {time.perf_counter() - t1:.1f}s")
        _evaluation_point(result, lanes, step, m, evals, selects, points, worst, header)
    if pending is not None:  # training ended within pre-training: fork / join the final states
        states = pending.grow(states, None, mesh_all)
    _final_rows(result, family, lanes, eps, points, evals, values, returns, lengths, truth,
                true_values_se(test_ds, cfg.vd.horizon, cfg.gamma), sizes["bootstrap"])
    result["true_value"] = np.asarray(truth).tolist()
    # The paper's sizes are its own evaluation setting (evaluate/setting.py's fields), stored
    # beside its numbers; each lane draws its episodes with PRNGKey(1000 + its seed).
    result["setting"] = {"episodes": sizes["eval_episodes"], "horizon": cfg.vd.horizon,
                         "seed": "1000 + the lane's seed", "truth": "auto",
                         "true_value_source": truth_used(test_ds, cfg.vd.horizon, cfg.gamma)}
    result["train_true_value"] = select_truth.tolist()
    result.setdefault("train_config", {})[family] = cfg.to_dict()
    result["timings"][f"eval_{family}"] = round(t_eval, 1)
    if check_eval:
        r = evaluate_simulator(simulator(take_lanes(states, 0)), test_ds, test_pols,
                               key=jax.random.PRNGKey(1000 + lanes[0][1]),
                               n_episodes=sizes["eval_episodes"], horizon=cfg.vd.horizon,
                               gamma=cfg.gamma)
        diff = float(np.max(np.abs(np.asarray(r["sim_value"]) - values[0])))
        result.setdefault("eval_check", {})[family] = {
            "lane": f"{lanes[0][0]}/{lanes[0][1]}", "max_abs_diff": diff,
            "metrics": r["metrics"]}
        log(f"[paper] check: evaluate_simulator on lane {lanes[0]} differs from the "
            f"vmapped evaluation by at most {diff:.3g}")
    return lanes, states


# ------------------------------------------------------------------ results


def _mean_or_none(vals):
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else None


def method_means(per_method: dict) -> dict:
    """{method: {"mpi": [per lane], "api": [...], ...}} -> their means (None where no lane
    has one), for the methods that have any "mpi"."""
    return {m: {k: _mean_or_none(vals) for k, vals in v.items()}
            for m, v in per_method.items() if v["mpi"]}


def fmt_ms(mean, std) -> str:
    """'mean ±std' for a log line ('n/a' without a mean)."""
    return "n/a" if mean is None else f"{mean:.3f}" + ("" if std is None else f" ±{std:.2g}")


def summarise(result: dict) -> None:
    """Fill result["methods"] (mean over seeds), ["std"] (sample std, None for one value) and
    ["n"] (values averaged) from result["per_seed"]."""
    for m, per in result["per_seed"].items():  # the methods and "oracle"
        mean, std, n = {}, {}, {}
        for k in METRICS:
            vals = [v for v in per.get(k, []) if v is not None]
            n[k] = len(vals)
            mean[k] = float(np.mean(vals)) if vals else None
            std[k] = float(np.std(vals, ddof=1)) if len(vals) > 1 else None
        result["methods"][m], result["std"][m], result["n"][m] = mean, std, n
    for m, per in result.get("selected", {}).items():  # the test metrics at the chosen steps
        result.setdefault("methods_selected", {})[m] = {
            k: (float(np.mean([v for v in vals if v is not None]))
                if any(v is not None for v in vals) else None)
            for k, vals in per.items() if k != "step"}


def write_result(path: str, result: dict) -> None:
    """Summarise ``result`` and write it atomically (on the writing process only)."""
    summarise(result)
    if not is_writer():
        return
    write_json(path, result)


def table(result: dict) -> str:
    """The summary printed at the end: per method (and the oracle) mean ± std over seeds."""
    cols = ("kendall_tau", "ndcg@1", "ndcg@5", "spearman", "avd", "mvd", "mpi", "api")
    lines = [f"{'method':<9}" + "".join(f"{c:>16}" for c in cols)]
    known = METHODS + ("oracle",)
    for m in ([m for m in known if m in result["methods"]]
              + [m for m in result["methods"] if m not in known]):  # eps lanes: rl2s@0.1
        cells = []
        for c in cols:
            v, s = result["methods"][m].get(c), result["std"][m].get(c)
            cells.append("n/a" if v is None else f"{v:.3g}" + ("" if s is None else
                                                                f" ±{s:.2g}"))
        lines.append(f"{m:<9}" + "".join(f"{c:>16}" for c in cells))
    return "\n".join(lines)
