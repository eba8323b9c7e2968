"""Ablation of the dynamics model on one task (issue 10, items 2-4): the single generator trained
from scratch that preceded the model family ("legacy", RL2S) vs the ensemble trained by maximum
likelihood ("bc") vs RL2S started from the MLE-pretrained ensemble ("rl2s") vs the same run
evaluated with the moving average of its weights ("rl2s+ema"). Judged on the held-out TEST
policies by Kendall tau, nDCG@1, AVD and MVD, at the last step ("final") and at the
evaluation point chosen WITHOUT the test policies ("selected": highest Kendall tau of the
TRAINING policies' simulated values, started from the start states of their held-out
episodes, against their true values; ties to the lower training AVD).

    python experiments/ablation_model.py --task hopper --out DIR [--data-dir DIR]
        [--variants legacy,bc,rl2s] [--seeds 3] [--steps 1200] [--eval-every 200]
        [--eval-episodes 16] [--ema-decay 0.99] [--profile auto|cpu|gpu] [--set key=value ...]
        [--rollouts random:1,mean:0,...]
    python experiments/ablation_model.py --summarize DIR [DIR ...]

Every variant is one vmapped program over the seeds (``train.lanes.train_lanes``: the MLE
pre-training and the adversarial phase are separate compiled pieces) and writes
OUT/ablation_<task>_<variant>.json after every evaluation (a run cut off by a time limit keeps
what it finished); ``--rollouts MODE:NOISE[:TERMINATION],...`` also evaluates each variant's
simulator with other rollout settings (member mode random / mean / fixed, noise scale, and for
a variant trained with a learned hazard, ``termination`` rule / hazard / both; rows
"<variant>@<mode>:<noise>[:<termination>]"), which costs no training. A variant may carry its
own settings, "bc:multistep_steps=5+multistep_weight=0.5" (its row is that whole name). The
last variant also writes OUT/ablation_<task>.json and .md, the table of
every variant's JSON found in OUT. ``--summarize`` rebuilds that table from the JSONs of
several directories (variants run in separate device calls). Data: the zoo's train / test split
as experiments/paper.py collects it (``paper.protocol.load_or_collect``, reused from
--data-dir). The variants, the rollout settings and the table are ``rl2s_jax.paper.ablation``;
the diagnostics (--open-loop, --visited-error, the hazard and termination checks)
``rl2s_jax.evaluate.errors``.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.app.training import make_config, parse_overrides
from rl2s_jax.data.summary import episode_lengths
from rl2s_jax.data.values import true_values
from rl2s_jax.envs.tasks import get_task, task_names
from rl2s_jax.evaluate.errors import (
    TERMINATION_RULES,
    hazard_check,
    open_loop_check,
    terminal_states,
    termination_causes,
    visited_error_check,
)
from rl2s_jax.evaluate.lane_scores import lane_returns
from rl2s_jax.evaluate.metrics import ranking_metrics
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.model.termination import LEARNED
from rl2s_jax.paper.ablation import (
    METRICS,
    VARIANTS,
    check_variants,
    parse_rollouts,
    parse_variant,
    rollout_row,
    split_validation,
    write_summary,
)
from rl2s_jax.paper.protocol import (
    TASK_SIZES,
    load_or_collect,
    log,
    positive_int,
    profile_sizes,
)
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.lanes import heldout_start_pool, init_lanes, train_lanes
from rl2s_jax.train.step import simulator
from rl2s_jax.zoo.zoo import policies_for

SIZES = {"gpu": dict(seeds=3, steps=1200, eval_every=200, eval_episodes=16),
         "cpu": dict(seeds=2, steps=40, eval_every=20, eval_episodes=4)}


def _metrics(truth, values) -> dict | None:
    try:
        r = ranking_metrics(np.asarray(truth, np.float64), np.asarray(values, np.float64),
                            ks=(1,))
    except ValueError:  # non-finite simulated values: the lane diverged
        return None
    return {k: float(r[k]) for k in METRICS}


def evaluate(states, seeds, weights: bool, *, test, select, cfg, n_episodes,
             rollout: tuple[str, float] | None = None, validation=None) -> list[dict]:
    """Test and selection metrics of every lane, with the moving average (weights=True) or the
    trained weights, rolled out with the config's settings or ``rollout`` (member mode, noise
    scale). test / select / validation (optional): (policies, start pool, true values)."""
    sims = simulator(states, average=weights)
    if rollout is not None:
        sims = sims.replace(member_mode=rollout[0], noise_scale=rollout[1],
                            termination=rollout[2] if len(rollout) > 2 else sims.termination)
    out = [{} for _ in seeds]
    sets = [("test", test, 1000), ("select", select, 2000)]
    if validation is not None:
        sets.append(("validation", validation, 3000))
    for name, (pols, pool, truth), base in sets:
        keys = jnp.stack([jax.random.PRNGKey(base + s) for s in seeds])
        returns, lengths = lane_returns(sims, pols, pool, keys, n_episodes=n_episodes,
                                        horizon=cfg.vd.horizon, gamma=cfg.gamma)
        lengths = np.asarray(lengths, np.float64).mean(-1)
        for i, v in enumerate(np.asarray(returns, np.float64).mean(-1)):
            out[i][name] = _metrics(truth, v)
            if name == "test":  # per policy: what the simulator got wrong, and how long it ran
                out[i]["test_values"] = [round(float(x), 2) for x in v]
                out[i]["test_lengths"] = [round(float(x), 1) for x in lengths[i]]
    return out


def run_variant(variant: str, args, profile: str, sizes: dict, train_ds, test_ds,
                valid_ds=None) -> dict:
    base, own = parse_variant(variant)
    method, model = VARIANTS[base]
    overrides = {**parse_overrides(args.set), **model, **own}  # a legacy variant stays legacy
    if base == "rl2s":
        overrides.setdefault("ema_decay", args.ema_decay)
    cfg = make_config(train_ds, method, profile, overrides=overrides)
    data = make_train_data(train_ds, policies_for(train_ds), cfg)
    test = (policies_for(test_ds), start_pool(test_ds),
            true_values(test_ds, cfg.vd.horizon, cfg.gamma))
    select = (data.policies, heldout_start_pool(train_ds), np.asarray(data.true_value))
    validation = None if valid_ds is None else (
        policies_for(valid_ds), start_pool(valid_ds),
        true_values(valid_ds, cfg.vd.horizon, cfg.gamma))
    rows = {(False, None): variant} | ({(True, None): f"{variant}+ema"} if cfg.ema_decay
                                       else {})
    rollouts = parse_rollouts(args.rollouts)
    if cfg.outcome.termination not in LEARNED and any(len(r) > 2 and r[2] in LEARNED
                                              for r in rollouts):
        raise SystemExit(f"rollouts: a learned termination needs a variant trained with one "
                         f"({variant!r} has termination {cfg.outcome.termination!r}; add "
                         f"':termination=both')")
    rows |= {(False, r): rollout_row(variant, r) for r in rollouts}
    seeds = list(range(sizes["seeds"]))
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", variant)  # a file name any tool copies back
    path = os.path.join(args.out, f"ablation_{args.task}_{safe}.json")
    res = {"task": args.task, "variant": variant, "config": cfg.to_dict(), "sizes": sizes,
           "hardware": jax.devices()[0].device_kind, "jax_version": jax.__version__,
           "command": " ".join(["python", "experiments/ablation_model.py", *args.argv]),
           "timings": {}, "complete": False,
           "curves": {row: {str(s): [] for s in seeds} for row in rows.values()},
           "heldout_nll": {str(s): [] for s in seeds},
           "test_true_values": [float(x) for x in test[2]],
           "test_true_lengths": [round(float(x), 1) for x in episode_lengths(test_ds)]}
    t0 = time.perf_counter()
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    states = jax.block_until_ready(init_lanes(keys, cfg, data))
    res["timings"]["init"] = round(time.perf_counter() - t0, 1)
    log(f"[ablation] {variant}: method {method}, {len(seeds)} seeds, E={cfg.ensemble_size}, "
        f"pretrain {cfg.adversarial.pretrain_steps if cfg.is_adversarial else '-'}, "
        f"ema {cfg.ema_decay}; "
        f"init {res['timings']['init']}s")
    compiled, t_train, t_eval = {}, 0.0, 0.0
    n = sizes["eval_every"]
    for _ in range(sizes["steps"] // n):
        t1 = time.perf_counter()
        states, m = jax.block_until_ready(train_lanes(states, data, n, cfg, compiled))
        t_train += time.perf_counter() - t1
        t1 = time.perf_counter()
        step = int(states.step[0])
        for (weights, rollout), row in rows.items():
            for s, r in zip(seeds, evaluate(states, seeds, weights, test=test, select=select,
                                            cfg=cfg, n_episodes=sizes["eval_episodes"],
                                            rollout=rollout, validation=validation),
                            strict=True):
                res["curves"][row][str(s)].append({"step": step, **r,
                                                   "finite": bool(m["finite"][s])})
                t, sl = r["test"] or {}, r["select"] or {}
                f = lambda d, k: "n/a" if k not in d else f"{d[k]:.3f}"
                log(f"  {row:<9} seed {s} step {step:>5}  test tau {f(t, 'kendall_tau')}"
                    f"  nDCG@1 {f(t, 'ndcg@1')}  AVD {f(t, 'avd')}  MVD {f(t, 'mvd')}  | "
                    f"select tau {f(sl, 'kendall_tau')}  AVD {f(sl, 'avd')}"
                    + ("" if validation is None else
                       f"  | validation tau {f(r['validation'] or {}, 'kendall_tau')}  AVD "
                       f"{f(r['validation'] or {}, 'avd')}"))
        if data.n_heldout:
            elite = np.asarray(states.rank) < cfg.n_elites
            nll = np.where(elite, np.asarray(states.heldout_nll), 0).sum(1) / cfg.n_elites
            for s in seeds:
                res["heldout_nll"][str(s)].append([step, float(nll[s])])
        t_eval += time.perf_counter() - t1
        res["timings"].update(train=round(t_train, 1), eval=round(t_eval, 1))
        log(f"[ablation] {variant} step {step}: train {t_train:.1f}s, eval {t_eval:.1f}s")
        _write(path, res)
    sims = simulator(states, average=False)  # the trained weights, for the diagnostics
    if cfg.outcome.termination in LEARNED:  # the hazard's calibration on the test policies' rows
        res["hazard_check"] = hazard_check(sims, test_ds)
        log(f"[ablation] {variant}: hazard on the test rows {res['hazard_check']}")
    if args.open_loop:
        res["open_loop"] = open_loop_check(sims, test_ds, get_task(args.task),
                                           ks=args.open_loop, n_windows=256)
        log(f"[ablation] {variant}: open loop on the test policies' logged actions "
            + "; ".join(f"k={k}: tau {v['tau']} spread {v['spread_ratio']} end "
                        f"{v['real_end']} vs {v['model_end']}"
                        for k, v in res["open_loop"].items() if k != "windows_per_policy"))
    if args.visited_error:
        res["visited_error"] = v = visited_error_check(
            sims, test_ds, test, get_task(args.task), n_episodes=args.visited_error,
            horizon=cfg.vd.horizon, train_ds=train_ds)
        mean = lambda d, k: [round(float(np.mean(x)), 4) for x in d[k]]
        log(f"[ablation] {variant}: one-step error against the real dynamics (per seed, mean "
            f"over the test policies): visited states rmse {mean(v['visited'], 'rmse')} "
            f"reward bias {mean(v['visited'], 'reward_bias')} | logged states rmse "
            f"{mean(v['logged'], 'rmse')} reward bias {mean(v['logged'], 'reward_bias')} | "
            f"training policies' logged states rmse {mean(v['train_logged'], 'rmse')}")
    if args.task in TERMINATION_RULES:  # why the simulated episodes end, vs the logged ones
        task = get_task(args.task)
        keys = jnp.stack([jax.random.PRNGKey(3000 + s) for s in seeds])
        terminal, ended = terminal_states(sims, test[0], test[1], keys, task=task,
                                          n_episodes=sizes["eval_episodes"],
                                          horizon=cfg.vd.horizon)
        done_rows = np.asarray(test_ds.done, bool)
        res["termination"] = {
            "simulated": {str(s): termination_causes(args.task, terminal[i], ended[i])
                          for i, s in enumerate(seeds)},
            "logged": termination_causes(args.task, np.asarray(test_ds.next_obs)[done_rows],
                                         np.ones(int(done_rows.sum()), bool))}
        log(f"[ablation] {variant}: termination causes {res['termination']}")
    res["complete"] = True
    _write(path, res)
    return res


def _write(path: str, res: dict) -> None:
    write_json(path, res)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    pos = positive_int
    ap.add_argument("--task", choices=task_names())
    ap.add_argument("--variants", default="legacy,bc,rl2s",
                    help=f"comma-separated, from {', '.join(VARIANTS)}, each optionally with "
                    "its own settings: bc:multistep_steps=5+multistep_weight=0.5")
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--seeds", type=pos)
    ap.add_argument("--steps", type=pos)
    ap.add_argument("--eval-every", type=pos)
    ap.add_argument("--eval-episodes", type=pos)
    ap.add_argument("--transitions-per-policy", type=pos)
    ap.add_argument("--value-episodes", type=pos)
    ap.add_argument("--episode-length", type=pos)
    ap.add_argument("--ema-decay", type=float, default=0.99)
    ap.add_argument("--set", action="append", metavar="KEY=VALUE")
    ap.add_argument("--rollouts", metavar="MODE:NOISE[:TERMINATION],...",
                    help="also evaluate every variant with these rollout settings (member mode "
                    "random|mean|fixed : noise scale [: rule|hazard|both]), e.g. "
                    "random:1,mean:0,random:0:rule")
    ap.add_argument("--open-loop", metavar="K,K,...",
                    type=lambda t: tuple(sorted({pos(x) for x in t.split(",") if x})),
                    help="also roll each trained simulator from the test policies' logged "
                    "states under their logged actions for K steps and compare the K-step "
                    "returns per policy (open_loop in the JSON), e.g. 1,10,50")
    ap.add_argument("--visited-error", type=pos, metavar="N",
                    help="also measure each trained simulator's one-step error against the "
                    "real dynamics (the oracle) on the states its own N episodes per test "
                    "policy visit and on logged states (visited_error in the JSON)")
    ap.add_argument("--validation-policies", type=int, metavar="N",
                    help="hold N training policies (spread over their values) out of the "
                    "model's data and rank them as validation policies (a choice made on "
                    "them never sees the test policies); the test rows are then of a model "
                    "fitted on the other training policies")
    ap.add_argument("--out", default="results/ablation")
    ap.add_argument("--data-dir")
    ap.add_argument("--summarize", nargs="+", metavar="DIR",
                    help="only rebuild the table of the ablation JSONs in these directories "
                    "(written into --out)")
    args = ap.parse_args(argv)
    args.argv = argv
    os.makedirs(args.out, exist_ok=True)
    if args.summarize:
        paths = sorted(p for d in args.summarize
                       for p in glob.glob(os.path.join(d, "ablation_*_*.json")))
        if not paths:
            raise SystemExit(f"summarize: no ablation_<task>_<variant>.json in {args.summarize}")
        tasks = {json.load(open(p))["task"] for p in paths}
        for task in sorted(tasks):
            mine = [p for p in paths if json.load(open(p))["task"] == task]
            print(write_summary(args.out, task, mine))
        return 0
    if not args.task:
        raise SystemExit("task: required (or --summarize)")
    parse_rollouts(args.rollouts)  # bad input stops here, before any work
    variants = check_variants(args.task, args.variants)
    if args.validation_policies is not None:  # the zoo's split sizes, before any collection
        from rl2s_jax.zoo.zoo import load_zoo
        n_train = len(load_zoo(args.task).split_ids("train"))
        if not 2 <= args.validation_policies <= n_train - 2:
            raise SystemExit(f"validation-policies: expected 2 ... {n_train - 2} (the "
                             f"training split has {n_train} policies), got "
                             f"{args.validation_policies}")
    backend = jax.default_backend()
    profile = args.profile if args.profile != "auto" else ("gpu" if backend == "gpu" else "cpu")
    profile_data = profile_sizes(profile, args.task)
    # the task's evaluation episodes follow paper.py's (TASK_SIZES: Ant's 256 on the gpu
    # profile, where fewer leave its ranking at the evaluation noise's own ceiling)
    task_sizes = TASK_SIZES.get(profile, {}).get(args.task, {})
    sizes = {**SIZES[profile], **{k: v for k, v in task_sizes.items() if k in SIZES[profile]}}
    for k in sizes:
        if getattr(args, k, None) is not None:
            sizes[k] = getattr(args, k)
    if sizes["steps"] % sizes["eval_every"]:
        raise SystemExit(f"steps: expected a multiple of --eval-every ({sizes['eval_every']})")
    data_sizes = {k: profile_data[k] for k in ("transitions_per_policy", "value_episodes")}
    for k in data_sizes:
        if getattr(args, k, None) is not None:
            data_sizes[k] = getattr(args, k)
    t0 = time.perf_counter()
    datasets, reused = load_or_collect(args.task, data_sizes, args.data_dir or args.out, 0,
                                       args.episode_length, False)
    log(f"[ablation] {args.task} on {jax.devices()[0].device_kind} ({backend}, jax "
        f"{jax.__version__}), profile {profile}, sizes {sizes}, data {data_sizes} "
        f"({'reused' if reused else 'collected'} in {time.perf_counter() - t0:.1f}s)")
    train_ds, valid_ds = datasets["train"], None
    if args.validation_policies is not None:
        train_ds, valid_ds = split_validation(train_ds, args.validation_policies)
        log(f"[ablation] validation policies {valid_ds.meta['policy_names']}; fitting on "
            f"{train_ds.n_policies}")
    for v in variants:
        t1 = time.perf_counter()
        run_variant(v, args, profile, sizes, train_ds, datasets["test"], valid_ds)
        log(f"[ablation] {v}: {time.perf_counter() - t1:.1f}s")
    mine = sorted(glob.glob(os.path.join(args.out, f"ablation_{args.task}_*.json")))
    print(write_summary(args.out, args.task, mine))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
