"""The protocol's value intervals (issue 64): after training, every lane (method x seed) gives
each test policy a split-conformal interval at ``level`` (``evaluate.trust``), calibrated on
held-out policies whose truth is measured here: ``perturbed_policies`` of the training
policies, run in the real env. Never the test policies; and not the zoo's "validation"
policies either, which in the protocol's zoo split are training policies of these simulators
(their errors are optimistic).

Cost: one real-env value measurement of the calibration policies per task, and per family one
program over its lanes on the test and calibration policies (``trust.lane_feature_arrays``):
one ensemble rollout (values and support together) at ``--trust-episodes`` episodes plus
each elite alone, vmapped over the elites, at ``--trust-member-episodes``.

With --trust-evaluated N (``run_trust``'s n_evaluated; default 0: none) also a second
evaluated set: N ``perturbed_policies`` of the TEST policies (their own key), their truth
measured as the calibration policies' and their features in rollouts of their own
(``family_trust``); each lane's intervals on them are calibrated on the calibration
policies, as the test policies' are. They are built from the test policies, so they only
measure: they calibrate and select nothing.

Also the interval guard beside the floor guard (``guard_phase``, ``improve.gain_intervals``)
and its offline cross-fit reading (``crossfit_interval_guard``, experiments/interval_guard.py).

Writes result["lanes"][lane]["trust"] (each test policy's interval and flag),
result["trust"][method] (the issue's block: level, coverage, width_over_range, worst_flagged,
runs, command; the plain seed-spread interval scaled to the same coverage beside it) and
result["trust_calibration"]; with --trust-evaluated, also each lane's and method's
"evaluated" block and result["trust_evaluated"] (the set's truths and origins). JSON-valid:
an infinite quantile (too few calibration policies for the level) leaves None with
"q_infinite": true, and unbounded intervals None ends."""
from __future__ import annotations

import json
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.app.specs import guard_choice_flags
from rl2s_jax.data.collect import measure_values
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate import trust as tr
from rl2s_jax.improve import gain_intervals as gi
from rl2s_jax.improve.finetune import median_gain
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.paper.protocol import log
from rl2s_jax.stats import mean_or_none
from rl2s_jax.train.step import simulator
from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids, policies_for

PERTURB_NOISE = 0.1  # the calibration policies' noise (trust.perturbed_policies' default)


def add_trust_arguments(ap) -> None:
    """paper.py's --trust-* flags and the deployment guard's --guard-*."""
    ap.add_argument("--guard-margin", type=float, help="MPI / API of the policies deployed "
                    "where every elite member predicts a gain above this fraction "
                    "(ablation '<variant>+guard')")
    ap.add_argument("--guard-floor-scale", type=float, default=1.0, help="a gain must also "
                    "exceed this x the lane's training MVD (0: the margin alone)")
    ap.add_argument("--guard-snapshots", action="store_true", help="with --guard-margin: "
                    "guard every --sac-chunk snapshot too (ablation '<variant>+guard-snapshots')")
    guard_choice_flags(ap, "paper")  # --guard, --guard-calibration: rl2s improve's too
    ap.add_argument("--trust-calibration", type=int, default=20, help="perturbed training "
                    "policies measured in the real env to calibrate the test policies' value "
                    "intervals (0: no intervals; fewer than trust.min_calibration(level): "
                    "unbounded intervals)")
    ap.add_argument("--trust-episodes", type=int, help="simulated episodes per policy for "
                    "the intervals' features (default: --eval-episodes)")
    ap.add_argument("--trust-member-episodes", type=int, default=16, help="simulated "
                    "episodes per policy of each elite alone (their spread; common random "
                    "numbers make a few enough; at most --trust-episodes)")
    ap.add_argument("--trust-level", type=float, default=tr.DEFAULT_LEVEL)
    ap.add_argument("--trust-evaluated", type=int, default=0, metavar="N", help="also N "
                    "perturbed/interpolated TEST policies measured in the real env and "
                    "evaluated with intervals (calibrated on the calibration set as the test "
                    "policies'): coverage and width on a second evaluated set (0: none)")


def check_trust_arguments(args) -> None:
    """SystemExit naming the flag, before any work."""
    for name, v in (("margin", args.guard_margin), ("floor-scale", args.guard_floor_scale)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise SystemExit(f"guard-{name}: expected a finite float >= 0, got {v}")
    if args.guard_snapshots and args.guard_margin is None:
        raise SystemExit("guard-snapshots: needs --guard-margin (the guard's margin)")
    if args.guard_calibration and args.guard_margin is None:
        raise SystemExit("guard-calibration: needs --guard-margin (the members' predicted "
                         "gains the interval guard reads are recorded by the guard)")
    if args.guard == "interval" and not args.guard_calibration:
        raise SystemExit("guard: 'interval' needs --guard-calibration VAL.json (fine-tuned "
                         "validation policies with known real gains)")
    for p in args.guard_calibration or ():
        if not os.path.isfile(p):
            raise SystemExit(f"guard-calibration: no such file {p}")
    if args.trust_calibration < 0:
        raise SystemExit(f"trust-calibration: expected an int >= 0, got {args.trust_calibration}")
    if args.trust_evaluated < 0:
        raise SystemExit(f"trust-evaluated: expected an int >= 0, got {args.trust_evaluated}")
    if args.trust_evaluated and not args.trust_calibration:
        raise SystemExit("trust-evaluated: needs --trust-calibration > 0 (the evaluated "
                         "policies' intervals are calibrated on the calibration set)")
    for name in ("trust_episodes", "trust_member_episodes"):
        v = getattr(args, name)
        if v is not None and v < 2:
            raise SystemExit(f"{name.replace('_', '-')}: expected an int >= 2, got {v}")
    try:
        tr.check_level(args.trust_level)
    except ValueError as err:
        raise SystemExit(f"trust-{err}") from None


def calibration_policies(task: str, pols, *, n: int, seed: int, n_episodes: int,
                         horizon: int, episode_length: int, gamma: float):
    """``n`` perturbed ``pols`` (the training policies for the calibration set, the test
    policies for the evaluated set) and their true discounted values over the first
    ``horizon`` steps (real env, ``n_episodes`` each; episodes of ``episode_length``).
    -> (stacked params [n], truth [n], origins)"""
    params, origins = tr.perturbed_policies(pols, jax.random.PRNGKey(seed), n,
                                            noise=PERTURB_NOISE)
    v = measure_values(get_task(task).make_env(), params, key=jax.random.PRNGKey(seed + 1),
                       n_episodes=n_episodes, episode_length=min(horizon, episode_length),
                       gamma=gamma)
    return params, np.asarray(v["value_discounted"], np.float64), origins


def evaluated_what(n: int) -> str:
    """What the evaluated set of ``n`` policies is, for its blocks."""
    return (f"{n} perturbed/interpolated test policies (trust.perturbed_policies of the test "
            f"policies, noise {PERTURB_NOISE}), intervals calibrated on the calibration set; "
            f"only measured, never used to calibrate or select")


def lane_trust(feats: dict, cal_feats: dict, cal_truth, names, truth, level: float) -> dict:
    """One lane's report: ``trust_report`` of its test policies calibrated on the
    calibration policies (all held out), compact, with "q_infinite" and "unbounded"."""
    cal = tr.calibrate(cal_feats, cal_truth, ["heldout"] * len(cal_truth), level)
    t = tr.trust_report(feats, cal, names, truth)
    pol = t["policies"]
    return {"level": level, "q": cal["q"], "q_infinite": not np.isfinite(cal["q"]),
            "n_calibration": cal["n"], "sim_value": [p["sim_value"] for p in pol],
            "interval": [p["interval"] for p in pol], "trusted": [p["trusted"] for p in pol],
            "why": [p["why"] for p in pol], "sigma": [p["sigma"] for p in pol],
            "support": [p["support"] for p in pol], "member_sd": [p["member_sd"] for p in pol],
            "unbounded": [not np.all(np.isfinite(p["interval"])) for p in pol],
            "coverage": t["coverage"], "mean_width": t["mean_width"],
            "width_over_range": t["width_over_range"], "worst": t["worst"]}


def evaluated_report(feats: dict, cal_feats: dict, cal_truth, truth, level: float) -> dict:
    """One lane's report on the evaluated set (``combine_features`` of its N policies, their
    true values truth [N]): ``lane_trust``'s, named "evaluated-<i>". -> {"n", "q", "coverage",
    "mean_width", "width_over_range", "worst", "sim_value" [N], "interval" [N, 2],
    "trusted" [N]} (raw floats)."""
    rep = lane_trust(feats, cal_feats, cal_truth, [f"evaluated-{i}" for i in range(len(truth))],
                     truth, level)
    return {"n": len(truth), **{k: rep[k] for k in (
        "q", "coverage", "mean_width", "width_over_range", "worst", "sim_value", "interval",
        "trusted")}}


def median_width_over_range(rep: dict) -> float | None:
    """A lane's ``evaluated_report`` (JSON-safe): the median interval width over the range of
    the truths (the range as mean_width / width_over_range); None where an interval is
    unbounded or the report lacks them. The mean width can be one policy's: a member's
    diverging value gives one interval hundreds of times the others'."""
    ivals, mean_w, wor = rep.get("interval"), rep.get("mean_width"), rep.get("width_over_range")
    if not ivals or not mean_w or not wor:
        return None
    widths = np.array([hi - lo if lo is not None and hi is not None else np.inf
                       for lo, hi in ivals], np.float64)
    med = float(np.median(widths))
    return med / (mean_w / wor) if math.isfinite(med) else None


def method_evaluated(lane_entries: list[dict]) -> dict | None:
    """A method's "evaluated" block from its lanes' JSON-safe "trust" entries: means over the
    lanes with an ``evaluated_report`` (as ``method_block``'s; None where a lane's is None;
    "median_width_over_range" too, where every lane's report holds its intervals); None when
    no lane has one; "skipped" when they evaluated sets of other sizes."""
    reps = [e["evaluated"] for e in lane_entries
            if isinstance(e.get("evaluated"), dict) and "skipped" not in e["evaluated"]]
    if not reps:
        return None
    if len({r["n"] for r in reps}) > 1:
        return {"skipped": f"the lanes evaluated sets of {sorted({r['n'] for r in reps})} "
                           f"policies"}
    mean = lambda key: mean_or_none(r[key] for r in reps)  # noqa: E731
    return {"n": reps[0]["n"], "coverage": mean("coverage"),
            "width_over_range": mean("width_over_range"), "mean_width": mean("mean_width"),
            "median_width_over_range": mean_or_none(median_width_over_range(r) for r in reps),
            "worst_flagged": float(np.mean([r["worst"]["flagged"] for r in reps])),
            "runs": len(reps), "what": evaluated_what(reps[0]["n"])}


def format_evaluated(b: dict) -> str:
    """One line of a method's "evaluated" block."""
    if "skipped" in b:
        return b["skipped"]
    f = lambda x: "n/a" if x is None else f"{x:.3f}"
    return (f"{b['n']} perturbed test policies: coverage {f(b['coverage'])}, width/range "
            f"{f(b['width_over_range'])}, worst policy flagged in {f(b['worst_flagged'])} of "
            f"{b['runs']} runs")


def seed_spread(values, truth, level: float, coverage: float) -> dict:
    """The plain seed-spread interval of one method's runs: run s's value +- k x the std over
    the method's seeds (``trust.spread_interval`` pooled over runs; k the normal quantile of
    ``level``, and k chosen WITH the truth to reach ``coverage``, the conformal intervals'
    pooled coverage, for the width comparison). values [S, P], truth [P]."""
    v = np.asarray(values, np.float64)
    if v.shape[0] < 2:
        return {"skipped": "one seed: no seed spread"}
    sd = v.std(0, ddof=1)
    s = tr.spread_interval(v.ravel(), np.tile(sd, v.shape[0]), np.tile(truth, v.shape[0]),
                           level, coverage)
    rng = float(np.ptp(truth)) or np.nan
    return {"coverage": s["coverage"], "width_over_range": s["mean_width"] / rng, "z": s["z"],
            "scaled_width_over_range": s["scaled_mean_width"] / rng,
            "scaled_infinite": not np.isfinite(s["scaled_mean_width"])}


def method_block(runs: list[dict], values, truth, level: float, command: str) -> dict:
    """The issue's per-method "trust" block over ``runs`` (``lane_trust`` of its lanes):
    means over runs of coverage and width_over_range, worst_flagged (share of runs whose
    largest-|error| test policy is flagged), and the seed-spread comparison."""
    cov = float(np.mean([r["coverage"] for r in runs]))
    wor = mean_or_none(r["width_over_range"] for r in runs)
    spread = seed_spread(values, truth, level, cov)
    return {"level": level, "coverage": cov, "width_over_range": wor,
            "worst_flagged": float(np.mean([r["worst"]["flagged"] for r in runs])),
            "runs": len(runs), "command": command,
            "mean_width": float(np.mean([r["mean_width"] for r in runs])),
            "unbounded_runs": int(sum(r["q_infinite"] for r in runs)),
            "coverage_per_run": [r["coverage"] for r in runs], "seed_spread": spread,
            "narrower_than_seed_spread": (
                None if wor is None or "skipped" in spread or spread["scaled_infinite"]
                else bool(wor < spread["scaled_width_over_range"]))}


def format_block(b: dict) -> str:
    """One line of a method's "trust" block (values as json_safe left them)."""
    f = lambda x: "n/a" if x is None else f"{x:.3f}"
    sp = b["seed_spread"]
    spread = (sp["skipped"] if "skipped" in sp else
              f"seed-spread interval scaled to it {f(sp['scaled_width_over_range'])}")
    return (f"level {b['level']:g}, coverage {f(b['coverage'])}, width/range "
            f"{f(b['width_over_range'])} ({spread}), worst policy flagged in "
            f"{f(b['worst_flagged'])} of {b['runs']} runs"
            f"{', unbounded in ' + str(b['unbounded_runs']) if b['unbounded_runs'] else ''}"
            + ("" if "seeds_combined" not in b else
               f"; the {b['seeds_combined']['seeds']} seeds as one: coverage "
               f"{f(b['seeds_combined']['coverage'])}, width/range "
               f"{f(b['seeds_combined']['width_over_range'])}"))


def lane_trusts_by_method(result: dict) -> dict[str, list[dict]]:
    """{method: its lanes' "trust" entries in seed order} of a result's lanes
    ("<method>/<seed>"), skipped lanes left out."""
    by_method: dict[str, list] = {}
    for lane, e in sorted(result.get("lanes", {}).items(),
                          key=lambda kv: (kv[0].rsplit("/", 1)[0],
                                          int(kv[0].rsplit("/", 1)[1]))):
        if e.get("trust") and "skipped" not in e["trust"]:
            by_method.setdefault(lane.rsplit("/", 1)[0], []).append(e["trust"])
    return by_method


def trust_from_lanes(result: dict) -> dict:
    """result["trust"] recomputed from its lanes' "trust" entries (as ``run_trust`` wrote
    them, JSON-safe), each method's lanes in seed order: for results joined from several
    runs (``merge_results.py``), where a method's seeds come from more than one; with the
    method's "evaluated" block (``method_evaluated``) where its lanes have one."""
    out = {}
    for m, runs in lane_trusts_by_method(result).items():
        raw = [{**r, "mean_width": math.inf if r["mean_width"] is None else r["mean_width"]}
               for r in runs]
        out[m] = tr.json_safe(method_block(raw, [r["sim_value"] for r in runs],
                                           np.asarray(result["true_value"], np.float64),
                                           runs[0]["level"], result.get("command", "")))
        if (ev := method_evaluated(runs)) is not None:
            out[m]["evaluated"] = tr.json_safe(ev)
    return out


def _stack(a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x, y]), a, b)


def family_trust(lanes, states, *, policies, n_test: int, pool, u_data, roll: dict,
                 evaluated=None) -> list:
    """Per lane of one family: (its test policies' ``policy_features``, the calibration
    policies'), the first ``n_test`` of ``policies`` and the rest, [+ the ``evaluated``
    policies' (or None) from a rollout of their own (keys folded with 1)]. Their own rollout
    leaves the test and calibration rollout the program it is without them: one stacked
    rollout of more policies is another XLA program, whose rounding moved HalfCheetah's
    elites-alone values (member_sd by a median 6-37% per lane, GPU, data seed 23)."""
    sims = simulator(states)
    keys = jnp.stack([jax.random.PRNGKey(3000 + s) for _, s in lanes])
    u_units = tr.lane_data_disagreement(sims, u_data)
    feats = tr.lane_features(sims, policies, pool, keys, u_units, **roll)
    parts = [tuple({k: v[..., sl] for k, v in f.items()}
                   for sl in (slice(None, n_test), slice(n_test, None))) for f in feats]
    if evaluated is None:
        return parts
    ev_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
    ev = tr.lane_features(sims, evaluated, pool, ev_keys, u_units, **roll)
    return [(*p, e) for p, e in zip(parts, ev, strict=True)]


def seeds_combined(per_lane: list, cal_truth, names, truth, level: float) -> dict:
    """One method's seeds as one estimate (``rl2s evaluate --ckpt A --ckpt B``): their mean
    value with the seed spread in the difficulty (``combine_features``), calibrated on the
    same combined calibration policies. per_lane: the method's (test, calibration)
    ``policy_features``. -> {"seeds", "coverage", "width_over_range", "worst_flagged", "q",
    "q_infinite", "interval", "trusted"} (raw floats)."""
    rep = lane_trust(tr.combine_features([t for t, _ in per_lane]),
                     tr.combine_features([c for _, c in per_lane]), cal_truth, names, truth,
                     level)
    return {"seeds": len(per_lane), "coverage": rep["coverage"],
            "width_over_range": rep["width_over_range"],
            "worst_flagged": float(rep["worst"]["flagged"]), "q": rep["q"],
            "q_infinite": rep["q_infinite"], "interval": rep["interval"],
            "trusted": rep["trusted"]}


def run_trust(result: dict, finals: dict, *, task: str, train_ds, train_pols, test_ds,
              test_pols, truth, horizon: int, gamma: float, sizes: dict, n_calibration: int,
              seed: int, level: float = tr.DEFAULT_LEVEL, episodes: int | None = None,
              member_episodes: int | None = None, episode_length: int | None = None,
              n_evaluated: int = 0) -> None:
    """The value intervals of every lane of ``finals`` ({family: (lanes, TrainState)}) into
    ``result`` (module docstring). truth [P_test]: the test policies' true values; episodes
    (None: sizes["eval_episodes"]) and member_episodes (None: as many; at most episodes):
    ``trust.lane_feature_arrays``'. n_evaluated > 0: also that many perturbed test policies
    (``evaluated_set``), rolled out on their own (``family_trust``), only measured."""
    t0 = time.perf_counter()
    measure = dict(n_episodes=sizes["value_episodes"], horizon=horizon, gamma=gamma,
                   episode_length=episode_length or get_task(task).episode_length)
    cal_params, cal_truth, origins = calibration_policies(
        task, train_pols, n=n_calibration, seed=seed + 4000, **measure)
    result["trust_calibration"] = {
        "n": n_calibration, "true_value": cal_truth.tolist(), "origins": origins,
        "what": f"perturbed training policies (trust.perturbed_policies, noise "
                f"{PERTURB_NOISE}), true values over {sizes['value_episodes']} real episodes",
        "min_for_level": tr.min_calibration(level)}
    result["timings"]["trust_calibration"] = round(time.perf_counter() - t0, 1)
    truth = np.asarray(truth, np.float64)
    policies, ev_params, ev_truth = _stack(test_pols, cal_params), None, None
    if n_evaluated:
        ev_params, ev_truth = evaluated_set(result, task, test_pols, n=n_evaluated,
                                            seed=seed, measure=measure)
    names = list(test_ds.meta.get("policy_names") or range(len(truth)))
    n = episodes or sizes["eval_episodes"]
    roll = dict(n_episodes=n, horizon=horizon, gamma=gamma,
                member_episodes=min(member_episodes or n, n))
    by_method: dict[str, list] = {}
    for family, (lanes, states) in finals.items():
        t0 = time.perf_counter()
        per_lane = family_trust(lanes, states, policies=policies, n_test=len(truth),
                                pool=start_pool(test_ds), u_data=train_ds, roll=roll,
                                evaluated=ev_params)
        for (meth, s), (feats, cal_feats, *ev_feats) in zip(lanes, per_lane, strict=True):
            if not all(np.all(np.isfinite(v)) for f in (feats, cal_feats) for v in f.values()):
                # a diverged lane: no interval, and no part in its method's block
                result["lanes"][f"{meth}/{s}"]["trust"] = {
                    "skipped": "non-finite simulated values or support"}
                continue
            rep = lane_trust(tr.combine_features([feats]), tr.combine_features([cal_feats]),
                             cal_truth, names, truth, level)
            entry = result["lanes"][f"{meth}/{s}"]["trust"] = tr.json_safe(rep)
            if ev_feats:
                entry["evaluated"] = _lane_evaluated(ev_feats[0], cal_feats, cal_truth,
                                                     ev_truth, level)
            by_method.setdefault(meth, []).append((rep, (feats, cal_feats), entry))
        result["timings"][f"trust_{family}"] = round(time.perf_counter() - t0, 1)
    result["trust"] = {}
    for m, runs in by_method.items():
        reps = [r for r, _, _ in runs]
        block = method_block(reps, [r["sim_value"] for r in reps], truth, level,
                             result.get("command", ""))
        if len(runs) > 1:
            block["seeds_combined"] = seeds_combined([f for _, f, _ in runs], cal_truth, names,
                                                     truth, level)
        if (ev := method_evaluated([e for _, _, e in runs])) is not None:
            block["evaluated"] = ev
        result["trust"][m] = tr.json_safe(block)


def evaluated_set(result: dict, task: str, test_pols, *, n: int, seed: int, measure: dict):
    """``n`` perturbed test policies (keys data seed + 5000, + 5001: not the calibration
    set's) with their true values measured as the calibration set's; writes
    result["trust_evaluated"] and its timing. -> (stacked params [n], truth [n])"""
    t0 = time.perf_counter()
    params, truth, origins = calibration_policies(task, test_pols, n=n, seed=seed + 5000,
                                                  **measure)
    result["trust_evaluated"] = {
        "n": n, "true_value": truth.tolist(), "origins": origins,
        "what": f"{evaluated_what(n)}; true values over {measure['n_episodes']} real episodes"}
    result["timings"]["trust_evaluated"] = round(time.perf_counter() - t0, 1)
    return params, truth


def _lane_evaluated(ev_feats: dict, cal_feats: dict, cal_truth, ev_truth, level) -> dict:
    """A lane's JSON-safe ``evaluated_report``, or "skipped" where its evaluated features are
    not finite (the lane's test-policy report stands)."""
    if not all(np.all(np.isfinite(v)) for v in ev_feats.values()):
        return {"skipped": "non-finite simulated values or support"}
    return tr.json_safe(evaluated_report(tr.combine_features([ev_feats]),
                                         tr.combine_features([cal_feats]), cal_truth,
                                         ev_truth, level))


def trust_phase(args, result: dict, finals: dict, datasets: dict, configs: dict, sizes: dict,
                *, phase, save) -> None:
    """paper.py's step 2b: ``run_trust`` with its flags (nothing with --trust-calibration 0)."""
    if not args.trust_calibration:
        return
    t0 = time.perf_counter()
    cfg = next(iter(configs.values()))
    test_ds = datasets["test"]
    try:
        run_trust(result, finals, task=args.task, train_ds=datasets["train"],
                  train_pols=policies_for(datasets["train"]), test_ds=test_ds,
                  test_pols=policies_for(test_ds), truth=result["true_value"],
                  horizon=cfg.vd.horizon, gamma=cfg.gamma, sizes=sizes,
                  n_calibration=args.trust_calibration, seed=args.data_seed,
                  level=args.trust_level, episodes=args.trust_episodes,
                  member_episodes=args.trust_member_episodes,
                  episode_length=args.episode_length, n_evaluated=args.trust_evaluated)
    except Exception as err:  # the intervals must not cost the run's improvement phase
        result["trust"] = {"error": f"{type(err).__name__}: {err}"}
        log(f"[paper] trust: FAILED, the run goes on without intervals: {result['trust']}")
    phase("trust", t0)
    save()
    for m, b in result["trust"].items():
        if m != "error":
            log(f"[paper] trust {m}: {format_block(b)}")
            if "evaluated" in b:
                log(f"[paper] trust {m} evaluated: {format_evaluated(b['evaluated'])}")


# ------------------------------------------------------------------ the interval guard

def guard_block(entries: list[dict], accepted: list, zoo_returns, names, control=None) -> dict:
    """One guard's figures for one method's lanes (``entries``: result["improvement"]'s,
    ``accepted`` [lane][P] its verdicts): "median_gain" (``finetune.median_gain`` over the
    seeds, kept policies at C0), "mpi" (mean over lanes of the guarded MPI, kept: 0),
    "deployed", "deployed_losses" (real I_paired < 0 among them), "control_median_gain"
    (the real-env control's, where ``control``)."""
    ids = names_to_zoo_ids([names[i] for i in entries[0]["policy_ids"]])
    zret = np.asarray(zoo_returns, np.float64)
    c0 = np.stack([np.asarray(e["c0_paired"], np.float64) for e in entries])
    c1 = np.stack([np.asarray(e["c1"], np.float64) for e in entries])
    real = np.stack([np.asarray(e["I_paired"], np.float64) for e in entries])
    acc = np.asarray(accepted, bool)
    out = {"median_gain": median_gain(c0, np.where(acc, c1, c0), zret[ids], zret)["median_gain"],
           "mpi": float(np.mean(np.where(acc, real, 0.0).min(1))),
           "deployed": int(acc.sum()), "deployed_losses": int((acc & (real < 0)).sum()),
           "lanes_x_policies": int(acc.size), "control_median_gain": None}
    if control is not None:
        out["control_median_gain"] = median_gain(control["c0"], control["c1"], zret[ids],
                                                 zret)["median_gain"]
    return out


def guard_comparison(result: dict, cal: dict, zoo_returns, chosen: str = "floor") -> dict:
    """Both guards side by side on result["improvement"] (a run with --guard-margin): the
    floor guard's recorded verdicts ("guard_accepted") and the interval guard's
    (``gain_intervals.interval_guard`` with ``cal``), written into each lane entry
    ("guard_accepted_interval", "guard_gain_lower"). -> {"chosen", "calibration",
    "floor": {method: ``guard_block``}, "interval": {...}} (JSON-safe)."""
    by_method: dict[str, list] = {}
    for e in result["improvement"].values():
        if "guard_member_gain" not in e:
            raise ValueError("guard: the lanes record no guard_member_gain (--guard-margin)")
        acc, lower = gi.interval_guard(
            gi.gain_features(e["guard_member_start"], e["guard_member_gain"]), cal)
        e["guard_accepted_interval"] = acc.tolist()
        e["guard_gain_lower"] = tr.json_safe(lower.tolist())
        by_method.setdefault(e["method"], []).append(e)
    names, ctl = result["test_policy_names"], result.get("control")
    out = {"chosen": chosen, "calibration": {**cal, "q_infinite": not np.isfinite(cal["q"])}}
    for kind, key in (("floor", "guard_accepted"), ("interval", "guard_accepted_interval")):
        out[kind] = {m: guard_block(es, [e[key] for e in es], zoo_returns, names, ctl)
                     for m, es in by_method.items()}
    return tr.json_safe(out)


def guard_phase(args, result: dict, level: float) -> None:
    """paper.py after the improvement: with --guard-calibration, result["guard"]
    (``guard_comparison``) and a line per guard and method."""
    if not args.guard_calibration or not result.get("improvement"):
        return
    runs = []
    for path in args.guard_calibration:
        with open(path) as f:
            runs.append(json.load(f))
    cal = gi.calibration_from_runs(runs, args.task, level)
    result["guard"] = guard_comparison(result, cal, load_zoo(args.task).returns, args.guard)
    for kind in ("floor", "interval"):
        for m, b in result["guard"][kind].items():
            log(f"[paper] guard {kind} {m}: deployed {b['deployed']} ({b['deployed_losses']} "
                f"lose), median gain {b['median_gain']}, MPI {b['mpi']:.3f}, control median "
                f"gain {b['control_median_gain']}")


def crossfit_interval_guard(entries: list[dict], level: float, folds: int = 2) -> dict:
    """The interval guard read offline on runs without validation runs: the fine-tuned
    policies split into ``folds`` folds by their zoo id's rank (every ``folds``-th), each
    fold's verdicts calibrated on the OTHER folds' policies (all lanes pooled), so that no
    policy calibrates its own verdict. entries: lane entries of result["improvement"] with
    "zoo_ids" added (and "guard_member_start" or, before runs kept it, |c0| as the gain's
    scale). Writes each entry's "guard_accepted_interval", "guard_gain_lower".
    -> {"folds", "q" per fold, "n" per fold, "scale"}"""
    feats = []
    for e in entries:
        start = e.get("guard_member_start")
        feats.append(gi.gain_features(start, e["guard_member_gain"],
                                      None if start is not None else np.abs(e["c0"])))
    ids = sorted({z for e in entries for z in e["zoo_ids"]})
    fold_of = {z: i % folds for i, z in enumerate(ids)}
    out = {"folds": folds, "q": [], "n": [], "scale": (
        "mean member start" if all(e.get("guard_member_start") for e in entries)
        else "|C0| where the run kept no guard_member_start")}
    lowers = [np.full(len(e["zoo_ids"]), -np.inf) for e in entries]
    for f in range(folds):
        g, sd, real = [], [], []
        for e, ft in zip(entries, feats, strict=True):
            for j, z in enumerate(e["zoo_ids"]):
                if fold_of[z] != f and e["I_paired"][j] is not None:
                    g.append(ft["gain"][j]), sd.append(ft["member_sd"][j])
                    real.append(e["I_paired"][j])
        cal = gi.calibrate_gains(g, sd, real, level)
        out["q"].append(cal["q"])
        out["n"].append(cal["n"])
        for e, ft, low in zip(entries, feats, lowers, strict=True):
            mine = np.asarray([fold_of[z] == f for z in e["zoo_ids"]])
            low[mine] = gi.gain_lower_bound(ft["gain"], ft["member_sd"], cal)[mine]
    for e, low in zip(entries, lowers, strict=True):
        e["guard_accepted_interval"] = (low > 0).tolist()
        e["guard_gain_lower"] = tr.json_safe(low.tolist())
    return tr.json_safe(out)
