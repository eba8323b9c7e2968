"""Assemble docs/results/<task>.json from the GPU runs of one zoo: the protocol
(experiments/paper.py), the oracle control (experiments/oracle_check.py) and the improvement
control (experiments/improve_control.py), each optional.

    python experiments/merge_results.py --task hopper [--paper P.json [--paper Q.json]]
        [--oracle O.json | --oracle-paper R.json] [--control C.json] [--out docs/results]
        [--keep] [--data-seed-run P.json ...] [--evaluated-run E.json ...]

--data-seed-run files go to by_data_seed only (``rl2s_jax.paper.data_seeds``); the trust
block (issue 64) becomes the task's "trust", marked with its data seed, or pooled over the
data seeds of several (``data_seeds.pooled_trust``), unless the task's own --paper run has one.

Several --paper files are runs of one protocol split over calls or GPUs on the same data:
other families (paper.py --families adversarial / mle) or other seeds (--first-seed K, e.g.
seeds 3-4 beside a run of seeds 0-2). merge_runs joins them (a method's seeds in seed
order) and refuses runs of different sizes, zoo, data or training settings, a method's seed
in two runs, and methods left with different seeds.

The oracle's row with the most episodes at the longest horizon becomes the "oracle" method
(per_seed lists of one value, its bootstrap intervals) unless the paper run has its own; the
control's MPI/API, their 95% intervals and issue 39's median gain of the policies below the
zoo's top quartile (``improve.finetune.median_gain``), the deployed count, the env-step budget
per policy and the command become "control". --oracle-paper takes the oracle
row (per seed, intervals, noise ceiling) from another paper.py run that measured it with the
same test policies and episode counts (its own data collection: the ceiling of the protocol's
sizes, not of this run's draw), so a protocol split over calls need not measure it again.
zoo_sha256 is the shipped zoo's, checked against the paper run's when both exist.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys

import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.evaluate.lane_scores import intervals_over_seeds
from rl2s_jax.improve.finetune import median_gain
from rl2s_jax.paper.data_seeds import (
    data_seed_of,
    data_seed_trust,
    evaluated_trust,
    oracle_into_data_seed,
    oracle_row,
    record_data_seeds,
)
from rl2s_jax.paper.protocol import summarise
from rl2s_jax.paper.trust_phase import trust_from_lanes
from rl2s_jax.zoo.zoo import load_zoo

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def zoo_sha256(task: str) -> str:
    with open(os.path.join(ROOT, "rl2s_jax", "zoo", "shipped", task, "zoo.npz"), "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


ORACLE_SIZES = ("test_policies", "eval_episodes", "value_episodes", "episode_length")


# entries keyed by method, lane or family: a part adds its own keys (the first part's oracle
# stays when both ran one)
MERGED_BY_METHOD = ("per_seed", "selected", "lane_intervals", "intervals", "lanes",
                    "train_config", "improvement", "fork")
SAME_IN_PARTS = ("task", "model", "profile", "zoo_sha256", "true_value")


def seed_ids_of(result: dict) -> list[int]:
    """The seeds a paper.py result ran (``seed_ids``; results older than --first-seed ran
    0 .. seeds - 1)."""
    return [int(s) for s in result.get("seed_ids") or range(int(result["seeds"]))]


def _join_seeds(merged: dict, part: dict, methods: set, has: dict, ids: list[int]) -> None:
    """Append ``part``'s seeds of ``methods`` (run by ``merged`` on other seeds) to merged's
    per-seed lists, in place; ``has`` maps each method to the seeds merged holds."""
    twice = {m: sorted(set(has[m]) & set(ids)) for m in sorted(methods)}
    twice = {m: v for m, v in twice.items() if v}
    if twice:
        raise ValueError(f"per_seed: method(s) and seed(s) {twice} in more than one run")
    for m in sorted(methods):
        if merged["per_seed"][m].get("mpi") and part["per_seed"][m].get("mpi"):
            raise ValueError(f"improvement: method {m!r} was fine-tuned in two seed-split "
                             f"runs; fine-tune in one of them only")
        for k, vals in part["per_seed"][m].items():
            merged["per_seed"][m].setdefault(k, []).extend(vals)
        for k, vals in part.get("selected", {}).get(m, {}).items():
            merged.setdefault("selected", {}).setdefault(m, {}).setdefault(k, []).extend(vals)
        merged.setdefault("lane_intervals", {}).setdefault(m, []).extend(
            part.get("lane_intervals", {}).get(m, []))
        has[m] = has[m] + ids
    for family, cfg in part.get("train_config", {}).items():
        if merged.get("train_config", {}).get(family, cfg) != cfg:
            raise ValueError(f"train_config.{family}: the runs trained with different "
                             f"settings")


def _order_by_seed(merged: dict, has: dict) -> None:
    """Sort each method's per-seed lists by seed (in place)."""
    for m, ids in has.items():
        order = np.argsort(ids, kind="stable")
        take = lambda v, order=order: [v[i] for i in order] if len(v) == len(order) else v
        merged["per_seed"][m] = {k: take(v) for k, v in merged["per_seed"][m].items()}
        if m in merged.get("selected", {}):
            merged["selected"][m] = {k: take(v) for k, v in merged["selected"][m].items()}
        if m in merged.get("lane_intervals", {}):
            merged["lane_intervals"][m] = take(merged["lane_intervals"][m])
            merged.setdefault("intervals", {})[m] = intervals_over_seeds(
                merged["lane_intervals"][m])


def merge_runs(parts: list[dict]) -> dict:
    """One result from runs of the same protocol split over calls: runs that trained
    different families (``--families``) and runs of other seeds (``--first-seed``) on the
    same data. The per-method entries joined (a method's seeds in seed order, its intervals
    over seeds recomputed), curves concatenated, timings summed (process-seconds: parts that
    ran side by side on several GPUs overlap, so ``total`` is not a wall time;
    ``timings_per_run`` keeps each part's), complete when every part is.
    Raises ValueError naming the field where the runs differ (task, sizes of the data, zoo,
    training settings, ...), when two of them ran the same method and seed, or when the
    methods do not end up with the same seeds."""
    if not parts:
        raise ValueError("parts: expected at least one result")
    merged = json.loads(json.dumps(parts[0]))
    has = {m: seed_ids_of(merged) for m in merged["per_seed"] if m != "oracle"}
    for part in parts[1:]:
        for k in SAME_IN_PARTS:
            if part.get(k) != merged.get(k):
                raise ValueError(f"{k}: the runs differ ({merged.get(k)!r} vs {part.get(k)!r})")
        for k in ("train_policies", "test_policies", "transitions_per_policy", "steps",
                  "eval_every", "eval_episodes", "episode_length"):
            if part["sizes"].get(k) != merged["sizes"].get(k):
                raise ValueError(f"sizes.{k}: the runs differ ({merged['sizes'].get(k)!r} vs "
                                 f"{part['sizes'].get(k)!r})")
        part = json.loads(json.dumps(part))
        ids = seed_ids_of(part)
        methods = set(part["per_seed"]) - {"oracle"}
        _join_seeds(merged, part, methods & set(has), has, ids)
        for m in methods - set(has):
            has[m] = ids
        for k in MERGED_BY_METHOD:
            into = merged.setdefault(k, {})
            into.update({m: v for m, v in part.get(k, {}).items() if m not in into})
        for variant, entry in part.get("ablation", {}).items():  # {variant: {settings,
            into = merged.setdefault("ablation", {}).setdefault(variant, {})  # lanes, methods}}
            if "settings" in into and into["settings"] != entry.get("settings"):
                raise ValueError(f"ablation.{variant}.settings: the runs differ "
                                 f"({into['settings']!r} vs {entry.get('settings')!r})")
            for k, v in entry.items():
                if isinstance(v, dict) and k != "settings":
                    into.setdefault(k, {}).update({m: x for m, x in v.items()
                                                   if m not in into[k]})
                else:
                    into.setdefault(k, v)
        if part.get("sac_config") and merged.get("sac_config") not in (None,
                                                                         part["sac_config"]):
            raise ValueError("sac_config: the runs fine-tuned with different SAC settings")
        merged.setdefault("sac_config", part.get("sac_config"))
        merged["curves"] = merged.get("curves", []) + part.get("curves", [])
        merged["families"] = merged.get("families", []) + [
            f for f in part.get("families", []) if f not in merged.get("families", [])]
        t = merged["timings"]
        for k, v in part.get("timings", {}).items():
            t[k] = round(t.get(k, 0.0) + v, 1)
        merged["complete"] = bool(merged.get("complete")) and bool(part.get("complete"))
        merged["command"] = f"{merged['command']} && {part['command']}"
    merged["timings_per_run"] = [dict(p.get("timings", {})) for p in parts]
    seed_sets = {m: sorted(ids) for m, ids in has.items()}
    if len({tuple(v) for v in seed_sets.values()}) > 1:
        raise ValueError(f"seeds: the methods ran different seeds {seed_sets}")
    _order_by_seed(merged, has)
    ids = next(iter(seed_sets.values()), seed_ids_of(merged))
    merged["seeds"], merged["seed_ids"] = len(ids), ids
    merged.setdefault("sizes", {})["seeds"] = len(ids)
    merged["methods"], merged["std"], merged["n"] = {}, {}, {}
    merged.pop("methods_selected", None)
    summarise(merged)
    return merged


def attach_paper_oracle(result: dict, path: str, sha: str) -> None:
    """Copy the oracle row of the paper.py run at ``path`` into ``result`` (in place); exits
    naming the field where that run's protocol differs from ``result``'s."""
    orc = _read(path)
    if "oracle" not in orc.get("per_seed", {}):
        raise SystemExit(f"oracle-paper: {path} has no oracle row (run without --no-oracle)")
    if orc.get("task") != result.get("task"):
        raise SystemExit(f"oracle-paper: task {orc.get('task')!r}, expected "
                         f"{result.get('task')!r}")
    if orc.get("zoo_sha256") not in (None, sha):
        raise SystemExit(f"oracle-paper: measured on zoo {orc['zoo_sha256']}, the shipped zoo "
                         f"is {sha}")
    if "sizes" in result:
        for k in ORACLE_SIZES:
            if orc["sizes"].get(k) != result["sizes"].get(k):
                raise SystemExit(f"oracle-paper: sizes.{k} differs ({orc['sizes'].get(k)!r} "
                                 f"vs {result['sizes'].get(k)!r})")
    result["per_seed"]["oracle"] = orc["per_seed"]["oracle"]
    for k in ("methods", "std", "n"):
        if "oracle" in orc.get(k, {}):
            result.setdefault(k, {})["oracle"] = orc[k]["oracle"]
    result.setdefault("intervals", {})["oracle"] = orc.get("intervals", {}).get("oracle", {})
    if "noise_ceiling" in orc:
        result["noise_ceiling"] = orc["noise_ceiling"]
    result["oracle"] = {"source": orc.get("command"), "hardware": orc.get("hardware"),
                        "n_episodes": orc["sizes"].get("eval_episodes"),
                        "seeds": len(orc["per_seed"]["oracle"].get("kendall_tau", [])),
                        "metrics": orc["methods"].get("oracle"),
                        "data": "its own collection (another run)"}


def _read(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def carry_trust(merged: dict, parts: list[dict]) -> None:
    """Issue 64's blocks of joined runs into ``merged``: "trust" per method recomputed from
    the joined lanes' intervals (a method's seeds may come from several runs), "guard" per
    guard and method from the run that fine-tuned it, "trust_calibration" the first run's;
    ValueError where the runs calibrated the intervals on other policies."""
    cals = [p["trust_calibration"] for p in parts if p.get("trust_calibration")]
    if any(c.get("origins") != cals[0].get("origins") for c in cals):
        raise ValueError("trust_calibration: the runs calibrated on other policies")
    if cals:  # the same policies; their truths measured again by each run (GPU round-off)
        merged["trust_calibration"] = dict(cals[0], truth_differs_by=float(max(
            np.max(np.abs(np.subtract(c["true_value"], cals[0]["true_value"])))
            for c in cals)))
        merged["trust"] = trust_from_lanes(merged)
        for m, block in merged["trust"].items():  # a method's seeds all run in one part
            own = [p["trust"][m] for p in parts if m in p.get("trust", {})]
            if len(own) == 1 and own[0].get("runs") == block["runs"] and "seeds_combined" in own[0]:
                block["seeds_combined"] = own[0]["seeds_combined"]
    guards = [p["guard"] for p in parts if p.get("guard")]
    if guards:
        merged["guard"] = {**guards[0], **{k: {m: b for g in guards for m, b in g[k].items()}
                                           for k in ("floor", "interval")}}


def parse_args(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--paper", action="append", help="paper.py's <task>.json (repeat for "
                    "runs of other --families or --first-seed on the same data)")
    ap.add_argument("--oracle")
    ap.add_argument("--oracle-paper", help="paper.py's <task>.json of a run with the oracle, "
                    "same test policies and episode counts: its oracle row")
    ap.add_argument("--control")
    ap.add_argument("--data-seed-run", action="append", default=[], metavar="P.json",
                    help="paper.py result(s) recorded under by_data_seed only (repeat; the "
                    "first run of a data seed that has a method gives its numbers); their "
                    "trust blocks become the task's \"trust\" (pooled over data seeds) where "
                    "it has none of its own")
    ap.add_argument("--evaluated-run", action="append", default=[], metavar="E.json",
                    help="a repeat of a --data-seed-run with paper.py --trust-evaluated N: its "
                    "lanes' evaluated sets become each method's trust \"evaluated\"")
    ap.add_argument("--guard-reading", metavar="G.json", help="experiments/interval_guard.py's "
                    "output: the floor and the interval guard on the task's recorded "
                    "improvement runs become its \"guard\" (issue 64 item 4)")
    ap.add_argument("--keep", action="store_true", help="without --paper: start from the "
                    "existing OUT/<task>.json (e.g. to replace only its control)")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "results"))
    args = ap.parse_args(argv)
    if args.oracle and args.oracle_paper:
        raise SystemExit("oracle, oracle-paper: expected at most one oracle source")
    return args


def base_result(args, sha: str) -> dict:
    """The result the merge starts from: the --paper runs joined (refused: another split, runs
    that do not join, another zoo), else OUT/<task>.json with --keep, else an empty one."""
    if args.paper:
        parts = []
        for p in args.paper:
            parts.append(_read(p))
            if parts[-1].get("policy_split", "zoo") != "zoo":
                raise SystemExit(f"paper: {p} ran on the {parts[-1]['policy_split']} split "
                                 "(--policy-split): not the task's protocol")
        if len(parts) == 1:
            result = parts[0]
        else:
            try:
                result = merge_runs(parts)
                carry_trust(result, parts)
            except ValueError as err:
                raise SystemExit(f"paper: {err}") from None
        if result.get("zoo_sha256") not in (None, sha):
            raise SystemExit(f"paper: measured on zoo {result['zoo_sha256']}, the shipped zoo "
                             f"is {sha}")
        return result
    if args.keep:
        return _read(os.path.join(args.out, f"{args.task}.json"))
    return {"task": args.task, "methods": {}, "std": {}, "n": {}, "per_seed": {},
            "note": "the protocol was not re-run on this zoo"}


def attach_oracle(result: dict, orc: dict, own_rows: bool) -> None:
    """oracle_check.py's row with the most episodes at the longest horizon as the "oracle"
    method of ``result`` (unless it has one, or ``orc`` is another data seed's or split's);
    own_rows False (no --paper): its command, hardware and jax version become the result's."""
    if "data_seed" in orc and (orc.get("policy_names") != result.get("test_policy_names")
                               or orc["data_seed"] != data_seed_of(result)):
        return  # another data seed's (or test split's) oracle: its by_data_seed entry only
    if "oracle" in result.get("per_seed", {}):
        return
    row = oracle_row(orc)
    result["per_seed"]["oracle"] = {k: [v] for k, v in row["metrics"].items()}
    result.setdefault("intervals", {})["oracle"] = (row.get("intervals") or {}).get(
        "metrics", {})
    if not own_rows:
        result.update(command=orc["command"], hardware=orc["hardware"], seeds=1,
                      jax_version=orc["jax_version"])
    result["oracle"] = {"source": orc["command"], "hardware": orc["hardware"],
                        "horizon": row["horizon"], "n_episodes": row["n_episodes"],
                        "policies": orc["policies"], "metrics": row["metrics"],
                        "eval_noise_tau_std": ((row.get("intervals") or {}).get(
                            "sim_only", {}).get("kendall_tau", {}).get("std"))}


def control_block(task: str, path: str) -> dict:
    """improve_control.py's output as the task's "control" (its first config; the test
    policies' only)."""
    ctl = _read(path)
    if ctl.get("split", "test") != "test":
        raise SystemExit(f"control: fine-tuned the {ctl['split']} policies; the task's "
                         "control is the test policies'")
    name, c = next(iter(ctl["configs"].items()))
    zret = np.asarray(load_zoo(task).returns)
    gain = median_gain(c["c0"], c["c1"], zret[ctl["zoo_ids"]], zret)
    return {"config": name, "seeds": ctl["seeds"], "iterations": ctl["iterations"],
            "policies": len(ctl["zoo_ids"]), "zoo_ids": ctl["zoo_ids"],
            "mpi": c["mpi"], "api": c["api"], "mpi_ci95": c["mpi_ci95"],
            "api_ci95": c["api_ci95"], "c0": c["c0"], "c1": c["c1"], "I": c["I"],
            "device": ctl["device"], "paired": bool(c.get("paired")),
            "median_gain": gain["median_gain"], "n_below": gain["n_below"],
            "deployed": (int((np.asarray(c["selected"]) > 0).sum())
                         if "selected" in c else None),
            "budget_env_steps": ctl["iterations"] * c["sac"]["n_envs"],
            "command": ctl.get("command"), "hardware": ctl.get("hardware")}


def guard_reading(task: str, path: str) -> dict:
    """interval_guard.py's output as the task's "guard": per guard ("floor", "interval") and
    method {"median_gain", "mpi", "deployed", "deployed_losses", "control_median_gain", ...},
    with the reading's level, cross-fit, runs, command and source file."""
    g = _read(path)
    if g.get("task") != task or not {"floor", "interval"} <= set(g):
        raise SystemExit(f"guard-reading: expected interval_guard.py's output for {task!r} "
                         f"(task, floor, interval), got {path}")
    return {"floor": g["floor"], "interval": g["interval"], "level": g.get("level"),
            "crossfit": g.get("crossfit"), "runs": g.get("runs"), "command": g.get("command"),
            "source": os.path.relpath(path, ROOT) if os.path.isabs(path) else path,
            "reading": "offline: each half of the fine-tuned policies (by zoo id) calibrated on "
                       "the other half's real gains (paper.trust_phase.crossfit_interval_guard)"}


def main(argv=None) -> int:
    args = parse_args(argv)
    sha = zoo_sha256(args.task)
    result = base_result(args, sha)
    if not (args.keep and result.get("zoo_sha256")):  # --keep: the zoo it was measured on
        result["zoo_sha256"] = sha
    previous = os.path.join(args.out, f"{args.task}.json")
    if "by_data_seed" not in result and os.path.exists(previous):
        result["by_data_seed"] = _read(previous).get("by_data_seed") or {}  # kept
    try:
        ds_runs = [_read(p) for p in args.data_seed_run]
        record_data_seeds(result, [*([result] if args.paper else []), *ds_runs])
        data_seed_trust(result, ds_runs)
        evaluated_trust(result, ds_runs, [_read(p) for p in args.evaluated_run])
        if args.oracle:
            oracle_into_data_seed(result, _read(args.oracle))
    except ValueError as err:
        raise SystemExit(f"by-data-seed: {err}") from None
    if args.oracle:
        attach_oracle(result, _read(args.oracle), own_rows=bool(args.paper))
    if args.oracle_paper and "oracle" not in result.get("per_seed", {}):
        attach_paper_oracle(result, args.oracle_paper, sha)
    if args.control:
        result["control"] = control_block(args.task, args.control)
    if args.guard_reading:
        result["guard"] = guard_reading(args.task, args.guard_reading)
    os.makedirs(args.out, exist_ok=True)
    write_json(previous, result)
    print(f"-> {previous}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
