"""The paper's protocol on one task: RL2S, GAIL, BC and RL2S-BC x seeds, judged on the held-out
test policies by value difference (AVD/MVD), ranking (Kendall tau, nDCG@k, Spearman, regret@1)
and policy improvement (MPI/API), written to OUT/<task>.json.

    python experiments/paper.py --task hopper [--seeds 3] [--steps N] [--eval-every N]
        [--transitions-per-policy N] [--value-episodes N] [--eval-episodes N]
        [--improve-iterations N] [--improve-policies N] [--improve-seeds 1] [--sac-envs N]
        [--sac-critic-warmup N] [--sac-updates-per-step N] [--sac-set field=value ...]
        [--zoo-recipe] [--improve-recipe control] [--control] [--control-seeds N]
        [--improve-variants full,branched,full+penalty,branched+penalty,full+stop]
        [--branch-length H] [--uncertainty-penalty L] [--uncertainty-threshold U]
        [--out DIR] [--data-dir DIR] [--profile auto|cpu|gpu] [--model ensemble|legacy]
        [--set field=value ...] [--families adversarial,mle] [--first-seed K] [--no-fork]
        [--trust-calibration 20] [--guard interval --guard-calibration VAL.json ...]

This script parses and checks the flags; the phases are ``rl2s_jax.paper.protocol`` (data,
oracle, training and evaluation) and ``rl2s_jax.paper.improvement_phases`` (improvement and its
controls). Each prints its wall time (the data phase its parts' too: "data_<part>") and
rewrites OUT/<task>.json, so a run cut off by a time limit keeps what it finished ("complete":
false). What each phase and flag does: docs/EVALUATION.md, "The paper's protocol".
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial

import jax
import numpy as np

from rl2s_jax import compile_cache
from rl2s_jax.app.improvement import fine_tuning_overrides
from rl2s_jax.app.report import machine_info
from rl2s_jax.app.training import make_config, parse_overrides
from rl2s_jax.data.summary import episode_lengths
from rl2s_jax.data.values import true_values_se as value_se
from rl2s_jax.envs.tasks import task_names
from rl2s_jax.improve.lane_finetune import parse_variants, uses_uncertainty, variant_settings
from rl2s_jax.improve.recipes import IMPROVE_RECIPES, paper_flags
from rl2s_jax.paper.improvement_phases import (
    lane_floors,
    lane_simulators,
    run_control,
    run_improvement,
    run_oracle_improvement,
    setup_fine_tuning,
)
from rl2s_jax.paper.protocol import (
    FAMILIES,
    METHODS,
    METRICS,
    POLICY_SPLITS,
    PROFILES,
    lane_eps,
    load_or_collect,
    log,
    positive_int,
    profile_sizes,
    run_oracle,
    table,
    train_family,
    write_result,
    zoo_sha256,
)
from rl2s_jax.paper.trust_phase import (
    add_trust_arguments,
    check_trust_arguments,
    guard_phase,
    trust_phase,
)
from rl2s_jax.policy.sac import SACConfig
from rl2s_jax.sharding import initialize_distributed
from rl2s_jax.train.config import LEGACY_MODEL
from rl2s_jax.train.cvar import n_worst
from rl2s_jax.zoo.build import fine_tuning_recipe
from rl2s_jax.zoo.zoo import policies_for


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    pos = positive_int
    ap.add_argument("--task", required=True, choices=task_names())
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--seeds", type=pos)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. +seeds-1: "
                    "more seeds in another call on the same data (merge_results.py joins them)")
    ap.add_argument("--steps", type=pos, help="train_steps per lane")
    ap.add_argument("--eval-every", type=pos, help="steps between test evaluations "
                    "(divides --steps)")
    ap.add_argument("--eval-episodes", type=pos, help="simulated episodes per test policy")
    ap.add_argument("--transitions-per-policy", type=pos)
    ap.add_argument("--value-episodes", type=pos, help="real episodes per policy for true "
                    "values (C0) and for C1")
    ap.add_argument("--episode-length", type=pos, help="shorter episodes (smoke runs)")
    ap.add_argument("--data-seed", type=int, default=0)
    ap.add_argument("--policy-split", choices=POLICY_SPLITS, default="zoo", help="validation / "
                    "lineage: training policies split again (every 4th / one lineage held out)")
    ap.add_argument("--improve-iterations", type=int, help="SAC iterations (0: skip)")
    ap.add_argument("--improve-policies", type=int, help="test policies fine-tuned, spread "
                    "evenly over their true returns (0 or more than there are: all)")
    ap.add_argument("--improve-seeds", type=int, help="seeds whose simulators are used")
    ap.add_argument("--improve-episodes", type=pos, help="real episodes per policy for C0 and "
                    "C1, paired (same starts and noise draws)")
    ap.add_argument("--sac-envs", type=pos, help="SAC envs per fine-tuned policy")
    ap.add_argument("--sac-critic-warmup", type=int, help="updates training only the critics "
                    "(default: a quarter of --improve-iterations)")
    ap.add_argument("--sac-updates-per-step", type=pos, default=1)
    ap.add_argument("--sac-chunk", type=pos, default=1000, help="SAC iterations per call")
    ap.add_argument("--sac-set", action="append", metavar="KEY=VALUE",
                    help="SACConfig override for every fine-tuning (methods and control)")
    ap.add_argument("--control", action="store_true", help="also fine-tune the same test "
                    "policies with the same SAC in the real env (the 'control' entry)")
    ap.add_argument("--control-seeds", type=pos, default=1, help="SAC seeds of the control")
    ap.add_argument("--improve-oracle-seeds", type=int, default=0, help="SAC seeds of the "
                    "same fine-tuning inside the oracle, the first variant's env")
    ap.add_argument("--improve-variants", default="full", help="comma list of simulated envs "
                    "full|branched [+penalty] [+stop]; the first gives MPI/API")
    ap.add_argument("--ablation-methods", default="rl2s", help="comma list of methods whose "
                    "lanes run the variants after the first (the first runs in all lanes)")
    ap.add_argument("--branch-length", type=pos, default=100, help="steps of a branched "
                    "rollout (variant 'branched')")
    ap.add_argument("--uncertainty-penalty", type=float, default=1.0, help="lambda of r - "
                    "lambda * u, u in units of its mean on the test data (variant 'penalty')")
    ap.add_argument("--uncertainty-threshold", type=float, default=3.0, help="end a rollout "
                    "when u exceeds this, same units (variant 'stop')")
    ap.add_argument("--halt-penalty", type=float, default=0.0, help="reward subtracted when "
                    "the stop rule ends a rollout (variant 'stop')")
    ap.add_argument("--model", choices=("ensemble", "legacy"), default="ensemble",
                    help="TrainConfig's ensemble or train.LEGACY_MODEL; --set overrides either")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="TrainConfig override for all lanes; eps=X sets the robust lanes' eps")
    ap.add_argument("--zoo-recipe", action="store_true", help="fine-tune at the zoo learner's "
                    "discount, reward scale and batch (zoo.build.fine_tuning_recipe)")
    ap.add_argument("--improve-recipe", choices=sorted(IMPROVE_RECIPES), help="a measured "
                    "recipe's flags, with the task's changes (improve.recipes); flags win")
    add_trust_arguments(ap)  # --trust-*, --guard-*
    ap.add_argument("--families", default="adversarial,mle", help="comma list of programs: "
                    "adversarial (rl2s, gail), mle (rl2s-bc, bc) (merge_results.py joins calls)")
    ap.add_argument("--eps-lanes", help="comma list of extra eps: RL2S lanes rl2s@EPS forked "
                    "from the pre-training (the eps curve; needs --improve-iterations 0)")
    ap.add_argument("--no-fork", dest="fork", action="store_false", help="gail and bc lanes "
                    "from step 0 too, not forked from the rl2s lanes' pre-training")
    ap.add_argument("--bootstrap", type=int, default=1000, help="bootstrap replicates for the "
                    "95%% intervals over evaluation episodes (0: none)")
    ap.add_argument("--no-oracle", dest="oracle", action="store_false", help="skip the control "
                    "(the real dynamics through the same evaluation path)")
    ap.add_argument("--out", default="results/paper")
    ap.add_argument("--data-dir", help="where train/test .npz live (default: --out)")
    ap.add_argument("--check-eval", action="store_true", help="record one lane's largest "
                    "difference from evaluate.evaluate_simulator (tests)")
    ap.add_argument("--progress", action="store_true", help="progress bars while collecting")
    return ap


def parse_args(argv: list[str]) -> argparse.Namespace:
    """build_parser's arguments, with --improve-recipe's flags as the defaults."""
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.improve_recipe:
        ap.set_defaults(**paper_flags(args.improve_recipe, args.task))
        args = ap.parse_args(argv)
    return args


def _sac_overrides(items) -> dict:
    """--sac-set KEY=VALUE pairs, checked against SACConfig's fields before any work."""
    try:
        out = fine_tuning_overrides(parse_overrides(items), flag="sac-set")
    except ValueError as err:
        raise SystemExit(str(err)) from None
    try:
        SACConfig.fine_tuning(**out).validate()
    except (TypeError, ValueError) as err:
        raise SystemExit(f"sac-set: {err}") from None
    return out


def parse_families(text: str) -> tuple:
    """--families: a comma list of FAMILIES' names -> their FAMILIES rows, in FAMILIES' order."""
    names = {f for f in (x.strip() for x in text.split(",")) if f}
    known = [f for f, _, _ in FAMILIES]
    if not names or names - set(known):
        raise SystemExit(f"families: expected a comma list of {', '.join(known)}, got {text!r}")
    return tuple(row for row in FAMILIES if row[0] in names)


def add_eps_lanes(families: tuple, text: str, sizes_improve) -> tuple:
    """--eps-lanes 0.05,0.1,0.5: RL2S lanes at these eps ("rl2s@0.05", ...) join the
    adversarial family after its rl2s lanes, forked from their pre-training (the eps curve,
    issue 41). SystemExit naming the flag on bad values, without the adversarial family, or
    with fine-tuning (the eps lanes are measured, not fine-tuned in)."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        values = []
    if not values or not all(0.0 < v <= 1.0 for v in values):
        raise SystemExit(f"eps-lanes: expected a comma list of floats in (0, 1], got {text!r}")
    if not any(f == "adversarial" for f, _, _ in families):
        raise SystemExit("eps-lanes: the eps lanes are RL2S lanes: include the adversarial "
                         "family (--families adversarial[,mle])")
    if sizes_improve != 0:  # None: the profile's default, which fine-tunes
        raise SystemExit("eps-lanes: set --improve-iterations 0 (no fine-tuning in eps lanes)")
    extra = tuple(f"rl2s@{v:g}" for v in dict.fromkeys(values))
    return tuple((f, c, (ms[0], *extra, *ms[1:]) if f == "adversarial" else ms)
                 for f, c, ms in families)


def identical_eps(eps_values, n_policies: int) -> list[list[float]]:
    """Groups of eps values that select the same number of training policies
    (``cvar.n_worst``: max(2, ceil(eps P))), whose lanes are then the same program with the
    same keys: identical results. -> the groups of two or more, in the given order."""
    by_k: dict[int, list[float]] = {}
    for e in dict.fromkeys(float(v) for v in eps_values):
        by_k.setdefault(int(n_worst(e, n_policies)), []).append(e)
    return [g for g in by_k.values() if len(g) > 1]


def resolve_sizes(args, profile: str) -> dict:
    sizes = {k: v for k, v in profile_sizes(profile, args.task).items() if k != "sac"}
    for k in list(sizes):
        if getattr(args, k, None) is not None:
            sizes[k] = getattr(args, k)
    if sizes["steps"] % sizes["eval_every"]:
        raise SystemExit(f"steps: expected a multiple of --eval-every ({sizes['eval_every']})")
    sizes["improve_seeds"] = max(0, min(sizes["improve_seeds"], sizes["seeds"]))
    if sizes["improve_policies"] is not None and sizes["improve_policies"] <= 0:
        sizes["improve_policies"] = None
    it = max(0, sizes["improve_iterations"])
    sizes["improve_iterations"] = it
    sizes["sac_critic_warmup"] = (args.sac_critic_warmup if args.sac_critic_warmup is not None
                                  else it // 4)
    sizes.update(sac_updates_per_step=args.sac_updates_per_step, sac_chunk=args.sac_chunk,
                 episode_length=args.episode_length)
    sizes["bootstrap"] = max(0, args.bootstrap)
    sizes["oracle"] = args.oracle
    return sizes


def check_arguments(args) -> tuple:
    """The flags that resolve_sizes leaves, checked before any work (SystemExit naming the
    flag). -> (variants, ablation methods, SAC overrides, FAMILIES rows)"""
    try:
        variants = parse_variants(args.improve_variants)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    ablation_methods = [m.strip() for m in args.ablation_methods.split(",") if m.strip()]
    if not ablation_methods or set(ablation_methods) - set(METHODS):
        raise SystemExit(f"ablation-methods: expected a comma list of {', '.join(METHODS)}, "
                         f"got {args.ablation_methods!r}")
    sac_overrides = _sac_overrides(args.sac_set)
    if args.zoo_recipe:
        recipe = fine_tuning_recipe(args.task)
        if not recipe:
            raise SystemExit(f"zoo-recipe: task {args.task!r} has no zoo SAC learner "
                             f"(zoo.build.ZOO_SAC) to take the recipe from")
        sac_overrides = {**recipe, **sac_overrides}
    families = parse_families(args.families)
    if args.eps_lanes:
        families = add_eps_lanes(families, args.eps_lanes, sizes_improve=args.improve_iterations)
    check_trust_arguments(args)  # --trust-*, --guard-*
    if args.first_seed < 0:
        raise SystemExit(f"first-seed: expected an int >= 0, got {args.first_seed}")
    return variants, ablation_methods, sac_overrides, families


def check_uncertainty(variants, sizes: dict, cfg, family: str) -> None:
    """The penalty / stop variants need u, the ensemble's disagreement: >= 2 elites."""
    uses_u = [v for v in variants if uses_uncertainty(v)]
    if (uses_u and sizes["improve_iterations"] and sizes["improve_seeds"]
            and min(cfg.ensemble_size, cfg.n_elites) < 2):
        raise SystemExit(f"improve-variants: {', '.join(uses_u)} need u = the ensemble's "
                         f"disagreement, i.e. >= 2 elites; the {family} model has "
                         f"ensemble_size {cfg.ensemble_size}, n_elites {cfg.n_elites} "
                         f"(--model legacy has one member)")


def main(argv=None) -> int:
    args = parse_args(argv := list(sys.argv[1:] if argv is None else argv))
    t_start = time.perf_counter()
    initialize_distributed()  # multi-host, when the coordinator variables are set
    compile_cache.enable()  # each program compiles once per machine (RL2S_COMPILATION_CACHE)
    backend = jax.default_backend()
    profile = args.profile if args.profile != "auto" else ("gpu" if backend == "gpu" else "cpu")
    sizes = resolve_sizes(args, profile)
    variants, ablation_methods, sac_overrides, families = check_arguments(args)
    S = sizes["seeds"]
    seed_ids = list(range(args.first_seed, args.first_seed + S))
    out, data_dir = args.out, args.data_dir or args.out
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{args.task}.json")
    device, timings = jax.devices()[0].device_kind, {}

    def phase(name, t0):
        timings[name] = round(time.perf_counter() - t0, 1)
        log(f"[paper] {name}: {timings[name]:.1f}s (elapsed "
            f"{time.perf_counter() - t_start:.0f}s)")

    log(f"[paper] task {args.task} on {device} ({backend}, jax {jax.__version__}), profile "
        f"{profile}, {S} seeds ({seed_ids[0]}..{seed_ids[-1]}) -> {path}\n[paper] sizes {sizes}")
    result = {"task": args.task, "model": args.model, "methods": {}, "std": {}, "n": {},
              "seeds": S, "seed_ids": seed_ids, "data_seed": args.data_seed,
              "improve_seeds": sizes["improve_seeds"], "hardware": device, "backend": backend,
              "machine": machine_info(), "policy_split": args.policy_split,
              "jax_version": jax.__version__, "profile": profile, "sizes": sizes,
              "command": " ".join(["python", "experiments/paper.py", *argv]),
              "families": [f for f, _, _ in families],
              "timings": timings, "complete": False,
              "per_seed": {m: {k: [] for k in METRICS}
                           for _, _, methods in families for m in methods},
              "curves": [], "lanes": {}}
    save = partial(write_result, path, result)

    # ---- 1. data
    t0 = time.perf_counter()
    datasets, reused = load_or_collect(args.task, sizes, data_dir, args.data_seed,
                                       args.episode_length, args.progress, args.policy_split,
                                       timings=timings, t_start=t_start)  # data_<part> lines
    for split, ds in datasets.items():
        log(f"[paper] {split} data: {ds.n_policies} policies x {ds.n_transitions // ds.n_policies}"
            f" transitions{' (reused from ' + data_dir + ')' if reused else ''}")
    phase("data", t0)
    train_ds, test_ds = datasets["train"], datasets["test"]
    result["sizes"].update(train_policies=train_ds.n_policies, test_policies=test_ds.n_policies)
    if args.eps_lanes:
        robust = parse_overrides(args.set).get("eps")
        eps_all = [lane_eps(m, robust) for _, _, ms in families for m in ms
                   if m.split("@")[0] == "rl2s"]
        for group in identical_eps(eps_all, train_ds.n_policies):
            log(f"[paper] eps {', '.join(f'{e:g}' for e in group)} all select "
                f"{int(n_worst(group[0], train_ds.n_policies))} of {train_ds.n_policies} "
                "training policies: their lanes will be identical")
    train_pols, test_pols = policies_for(train_ds), policies_for(test_ds)
    result["test_policy_names"] = list(test_ds.meta.get("policy_names") or [])
    result["true_value_undiscounted"] = np.asarray(test_ds.value, np.float64).tolist()
    result["true_length"] = np.round(episode_lengths(test_ds), 1).tolist()  # logged episodes
    result["zoo_sha256"] = zoo_sha256(args.task)

    # ---- 1b. the control: the real dynamics through the same evaluation path
    if sizes["oracle"]:
        cfg = make_config(train_ds, "rl2s", profile, overrides=parse_overrides(args.set))
        run_oracle(result, args.task, test_ds, test_pols, seed_ids, cfg, sizes, phase=phase,
                   save=save)

    # ---- 2. training, one vmapped program per family
    overrides = {**(LEGACY_MODEL if args.model == "legacy" else {}), **parse_overrides(args.set)}
    robust_eps = overrides.pop("eps", None)
    finals, configs = {}, {}
    share = {} if args.fork else None  # the adversarial trunk, for the bc lanes to join
    for family, cfg_method, methods in families:
        t0 = time.perf_counter()
        cfg = configs[family] = make_config(train_ds, cfg_method, profile, overrides=overrides)
        check_uncertainty(variants, sizes, cfg, family)
        finals[family] = train_family(
            result, family, cfg, methods, train_ds=train_ds, test_ds=test_ds,
            train_pols=train_pols, test_pols=test_pols, seeds=seed_ids, sizes=sizes,
            robust_eps=robust_eps, check_eval=args.check_eval, fork=args.fork, share=share)
        phase(f"train_{family}", t0)
        save()
    share = None  # an unused trunk (--families adversarial) need not stay on the device
    result["true_value_se"] = np.asarray(value_se(test_ds, cfg.vd.horizon, cfg.gamma)).tolist()
    trust_phase(args, result, finals, datasets, configs, sizes, phase=phase, save=save)

    # ---- 3. improvement
    it = sizes["improve_iterations"]
    oracle_seeds = max(0, args.improve_oracle_seeds)
    if it and (sizes["improve_seeds"] or args.control or oracle_seeds):
        ft = setup_fine_tuning(result, args.task, test_ds, test_pols, sizes,
                               next(iter(configs.values())).vd.horizon,
                               {**PROFILES[profile]["sac"], **sac_overrides})
    settings_of = partial(variant_settings, branch_length=args.branch_length,
                          uncertainty_penalty=args.uncertainty_penalty,
                          uncertainty_threshold=args.uncertainty_threshold,
                          halt_penalty=args.halt_penalty)
    if it and sizes["improve_seeds"]:
        lanes, sims = lane_simulators(finals, seed_ids[0] + sizes["improve_seeds"])
        mvds = (lane_floors(finals, seed_ids[0] + sizes["improve_seeds"], sims, train_ds,
                            train_pols, ft) if args.guard_margin is not None else None)
        run_improvement(result, ft, lanes, sims, test_ds, variants, settings_of=settings_of,
                        ablation_methods=ablation_methods, guard_margin=args.guard_margin,
                        guard_snapshots=args.guard_snapshots, phase=phase, save=save,
                        guard_floors=mvds, guard_floor_scale=args.guard_floor_scale)
    if it and oracle_seeds:
        run_oracle_improvement(result, ft, test_ds, variants[0], settings_of(variants[0]),
                               oracle_seeds, phase)
        save()
    if it and args.control:
        run_control(result, ft, args.control_seeds, phase)
    guard_phase(args, result, args.trust_level)  # both guards side by side
    timings["total"] = round(time.perf_counter() - t_start, 1)
    result["complete"] = True
    save()
    log(f"\n[paper] {args.task}: {S} seeds on {device}, {timings['total']:.0f}s in all; "
        f"timings {timings}\n{table(result)}\n-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
