"""Ranking over data collections (issue 66): each protocol run (experiments/paper.py's result)
of a task recorded under its data seed in ``docs/results/<task>.json``'s ``"by_data_seed"``
(``{"<data seed>": {"rl2s": {"kendall_tau", "mvd", "seeds"}, "gail", "bc", "rl2s-bc",
"oracle": {"kendall_tau", "seeds"}, "noise_ceiling": {"mean", "lo", "hi", "n_truth", "n_sim"},
"command", "hardware", "test_policy_names", "zoo_sha256", "complete": false where a run was
cut off}}``; a method, the oracle or the ceiling not measured is absent), and the rows of
the table "Ranking over data seeds" that experiments/paper_tables.py renders from it; issue
64's "trust" blocks pooled over data seeds (``pooled_trust``) and their table."""
from __future__ import annotations

import numpy as np

from rl2s_jax.evaluate import trust as tr
from rl2s_jax.paper.trust_phase import lane_trusts_by_method, method_evaluated
from rl2s_jax.stats import mean_or_none, t_interval

BY_DATA_SEED_METHODS = ("rl2s", "gail", "bc", "rl2s-bc")


def data_seed_of(run: dict) -> int:
    """The data seed of a paper.py result: its ``data_seed``, else its command's --data-seed
    (every paper.py part of a merged command alike), else 0 (paper.py's default)."""
    if "data_seed" in run:
        return int(run["data_seed"])
    found = set()
    for part in str(run.get("command", "")).split("&&"):
        words = " ".join(part.split("=")).split()  # --data-seed=7 or --data-seed 7
        found.add(int(words[words.index("--data-seed") + 1]) if "--data-seed" in words else 0)
    if len(found) > 1:
        raise ValueError(f"command: its paper.py parts ran different --data-seed values "
                         f"{sorted(found)}")
    return found.pop() if found else 0


def _mean_over_seeds(per_seed: dict, key: str) -> float | None:
    vals = [v for v in per_seed.get(key) or [] if v is not None]
    return float(np.mean(vals)) if vals else None


def group_by_data_seed(results: list[dict]) -> dict[int, list[dict]]:
    """paper.py results of one task by data seed (``data_seed_of``), in data seed order.
    ValueError naming "task" when they are of several tasks."""
    tasks = {r.get("task") for r in results}
    if len(tasks) > 1:
        raise ValueError(f"task: expected the results of one task, got {sorted(map(str, tasks))}")
    groups: dict[int, list[dict]] = {}
    for r in results:
        groups.setdefault(data_seed_of(r), []).append(r)
    return dict(sorted(groups.items()))


def data_seed_entry(runs: list[dict]) -> tuple[int, dict]:
    """One data seed's row of ``by_data_seed`` from paper.py results of that data seed (other
    families, reruns): per method of BY_DATA_SEED_METHODS its Kendall tau and MVD, the means
    over the seeds of the first run that has it; the oracle's tau and the noise ceiling
    (``{"mean", "lo", "hi"}``) where a run measured them itself (not an oracle row that
    merge_results.py took from another collection: ``result["oracle"]``), else absent;
    ``"complete": false`` when a run that gave a method's numbers (or, with no method, the
    oracle's) was cut off (paper.py's ``complete``).
    -> (data seed, entry). ValueError naming the field where the runs differ (data seed,
    task, test policies) or when none has a method (but an oracle-only entry of a cut-off
    run: the oracle runs before training)."""
    if not runs:
        raise ValueError("runs: expected at least one paper.py result")
    seeds = {data_seed_of(r) for r in runs}
    if len(seeds) > 1:
        raise ValueError(f"data_seed: the runs are of different data seeds {sorted(seeds)}")
    for k in ("task", "test_policy_names"):
        if any(r.get(k) != runs[0].get(k) for r in runs[1:]):
            raise ValueError(f"{k}: the runs of one data seed differ")
    entry, used, method_runs = {}, [], {}
    own = [r for r in runs if not isinstance(r.get("oracle"), dict)]  # else merged from elsewhere
    for m in (*BY_DATA_SEED_METHODS, "oracle"):
        run = next((r for r in (own if m == "oracle" else runs)
                    if _mean_over_seeds(r.get("per_seed", {}).get(m, {}), "kendall_tau")
                    is not None), None)
        if run is None:
            continue
        method_runs[m] = run
        per = run["per_seed"][m]
        entry[m] = {"kendall_tau": _mean_over_seeds(per, "kendall_tau"),
                    "seeds": len(per["kendall_tau"])}
        if m != "oracle":
            entry[m]["mvd"] = _mean_over_seeds(per, "mvd")
        if not any(run is u for u in used):
            used.append(run)
    if not set(entry) - {"oracle"} and not ("oracle" in entry and any(
            r.get("complete") is False for r in used)):
        raise ValueError(f"per_seed: no run has any of {', '.join(BY_DATA_SEED_METHODS)}")
    ceiling = next((r["noise_ceiling"] for r in own if r.get("noise_ceiling")), None)
    if ceiling:
        entry["noise_ceiling"] = {k: ceiling["kendall_tau"][k] for k in ("mean", "lo", "hi")}
        entry["noise_ceiling"].update(n_truth=ceiling.get("n_truth"),
                                      n_sim=ceiling.get("n_sim"))
    entry.update(command=" && ".join(dict.fromkeys(r.get("command", "?") for r in used)),
                 hardware=used[0].get("hardware"),
                 test_policy_names=list(runs[0].get("test_policy_names") or []),
                 zoo_sha256=used[0].get("zoo_sha256"))
    methods_from = [r for r in used if any(r is method_runs.get(m) for m in BY_DATA_SEED_METHODS)]
    if any(r.get("complete") is False for r in (methods_from or used)):
        entry["complete"] = False  # a run cut off (e.g. its time limit) gave the methods'
        # numbers (an oracle measured before the cut is whole)
    return seeds.pop(), entry


def record_data_seeds(result: dict, runs: list[dict]) -> None:
    """Add the runs to ``result["by_data_seed"]`` (in place), one entry per data seed (the
    runs of one data seed in the given order: a method's numbers come from the first that has
    it), replacing an earlier entry of that data seed but keeping its oracle and noise ceiling
    where the new runs measured none (they come from oracle_check.py --data-seed or another
    run of the same test split, and a rerun of that data seed leaves them true). ValueError
    when a data seed's test policies differ from the other entries' (a ranking is compared on
    one test split) or the runs are of several tasks (``group_by_data_seed``)."""
    table = dict(result.get("by_data_seed") or {})
    for ds, group in group_by_data_seed(runs).items():
        _, entry = data_seed_entry(group)
        for other, e in table.items():
            if other != str(ds) and e.get("test_policy_names") != entry["test_policy_names"]:
                raise ValueError(f"by_data_seed: data seed {ds} has other test policies than "
                                 f"data seed {other}'s entry")
        earlier = table.get(str(ds)) or {}
        if earlier.get("test_policy_names") == entry["test_policy_names"]:
            entry.update({k: earlier[k] for k in ("oracle", "noise_ceiling")
                          if k in earlier and k not in entry})
        table[str(ds)] = entry
    result["by_data_seed"] = {k: table[k] for k in sorted(table, key=int)}


def oracle_row(orc: dict) -> dict:
    """oracle_check.py's row at the longest horizon with the most episodes: the one the task
    JSONs, their tables and the analyses read."""
    return max(orc["rows"], key=lambda r: (r["horizon"], r["n_episodes"]))


def oracle_into_data_seed(result: dict, orc: dict) -> None:
    """oracle_check.py's output of a data seed (``data_seed``, run with --data-seed) into that
    seed's by_data_seed entry: its tau at the longest horizon with the most episodes and its
    noise ceiling. An output without ``data_seed`` (its own collection) is left out;
    ValueError when its test policies differ from the entry's."""
    if "data_seed" not in orc:
        return
    entry = (result.get("by_data_seed") or {}).get(str(orc["data_seed"]))
    if entry is None:
        raise ValueError(f"oracle: no protocol run of data seed {orc['data_seed']} recorded "
                         f"to attach it to")
    if list(orc.get("policy_names") or []) != entry["test_policy_names"]:
        raise ValueError(f"oracle: its policies differ from data seed {orc['data_seed']}'s "
                         f"test policies")
    row = oracle_row(orc)
    entry["oracle"] = {"kendall_tau": row["metrics"]["kendall_tau"], "seeds": 1,
                       "command": orc.get("command")}
    if row.get("noise_ceiling"):
        nc = row["noise_ceiling"]
        entry["noise_ceiling"] = {**{k: nc["kendall_tau"][k] for k in ("mean", "lo", "hi")},
                                  "n_truth": nc.get("n_truth"), "n_sim": nc.get("n_sim")}



# the bar of issue 66: RL2S's tau at most this far below the oracle's on each data seed
ORACLE_MARGIN = {"ant": 0.05}
ORACLE_MARGIN_DEFAULT = 0.03
NOT_MEASURED = "not measured"


def oracle_bar(task: str, entry: dict) -> str:
    """One data seed's bar cell: RL2S's tau within the task's margin of the oracle's."""
    margin = ORACLE_MARGIN.get(task, ORACLE_MARGIN_DEFAULT)
    rl2s, orc = entry.get("rl2s"), entry.get("oracle")
    if not rl2s or not orc:
        return f"{NOT_MEASURED} (no {'oracle' if rl2s else 'RL2S'})"
    gap = rl2s["kendall_tau"] - orc["kendall_tau"]
    return f"{'met' if gap >= -margin else 'MISSED'} ({gap:+.3f} vs -{margin:.2f})"


def _tau_cell(row: dict | None) -> str:
    if not row:
        return NOT_MEASURED
    return f"{row['kendall_tau']:.3f} ({row['seeds']} seed{'s' if row['seeds'] != 1 else ''})"


def _control_cell(entry: dict | None) -> str:
    """The oracle's tau and the noise ceiling of one data seed."""
    nc = (entry or {}).get("noise_ceiling")
    ceiling = (f"{nc['mean']:.3f} [{nc['lo']:.2f}, {nc['hi']:.2f}]" if nc else NOT_MEASURED)
    return f"{_tau_cell((entry or {}).get('oracle'))} / {ceiling}"


def over_data_seeds(values) -> str:
    """'mean [lo, hi] (n data seeds)': the 95% t-interval over data seeds (stats.t_interval;
    each data seed's mean over its seeds is one draw of the whole protocol), its ends clipped
    to tau's range [-1, 1]; one value: no interval; none: "not measured"."""
    vals = [v for v in values if v is not None]
    if not vals:
        return NOT_MEASURED
    t = t_interval(vals)
    if t is None:
        return f"{vals[0]:.3f} (1 data seed)"
    return f"{t[0]:.3f} [{max(t[1], -1.0):.3f}, {min(t[2], 1.0):.3f}] ({len(vals)} data seeds)"


def data_seed_rows(results: dict, tasks) -> list[str]:
    """The markdown table "Ranking over data seeds" of the tasks' ``by_data_seed`` (tasks in
    the given order; none recorded: []): per task and method the Kendall tau on each data
    seed (mean over that seed's seeds), the mean over data seeds with its 95% t-interval
    (clipped to [-1, 1]), RL2S's oracle bar per data seed, and a row of the oracle's tau and
    the noise ceiling per data seed."""
    have = {t: results[t]["by_data_seed"] for t in tasks
            if t in results and results[t].get("by_data_seed")}
    if not have:
        return []
    seeds = sorted({int(k) for tab in have.values() for k in tab})
    head = " | ".join(f"data seed {d}" for d in seeds)
    lines = [f"| task | method | {head} | over data seeds | RL2S within "
             f"{ORACLE_MARGIN_DEFAULT:.2f} (Ant {ORACLE_MARGIN['ant']:.2f}) of the oracle |",
             "|---|---|" + "---:|" * (len(seeds) + 1) + "---|"]
    for task, tab in have.items():
        for m in BY_DATA_SEED_METHODS:
            cells = [_tau_cell(tab.get(str(d), {}).get(m)) for d in seeds]
            mean = over_data_seeds([(tab[str(d)].get(m) or {}).get("kendall_tau")
                                            for d in seeds if str(d) in tab])
            bar = ("; ".join(f"{d}: {oracle_bar(task, tab[str(d)])}" for d in seeds
                             if str(d) in tab) if m == "rl2s" else "")
            lines.append(f"| {task} | {m} | {' | '.join(cells)} | {mean} | {bar} |")
        cells = [_control_cell(tab.get(str(d))) for d in seeds]
        mean = over_data_seeds([(tab[str(d)].get("oracle") or {}).get("kendall_tau")
                                        for d in seeds if str(d) in tab])
        lines.append(f"| {task} | oracle / noise ceiling | {' | '.join(cells)} | {mean} | |")
    return lines


def pooled_trust(runs: list[dict]) -> dict:
    """Issue 64's "trust" block per method over data seeds: ``runs`` are paper.py results
    (one per data seed, each with its lanes' trust entries and true values). Per method the
    means over every run (method x seed x data seed) of coverage and width_over_range, the
    share of runs whose worst-error policy is flagged, and the seed-spread interval pooled the
    same way (each data seed's values, seed spread and truth over its own truth's range, so
    widths add up as width/range) scaled to the pooled coverage; "by_data_seed" keeps each
    data seed's own block; "evaluated" pools the lanes' ``--trust-evaluated`` sets the same
    way (``trust_phase.method_evaluated``) where they have them; "seeds_combined" the data
    seeds' seeds-as-one intervals (``seeds_combined_over``) where every data seed has one."""
    by_ds = {data_seed_of(r): r for r in runs}
    if len(by_ds) != len(runs):
        raise ValueError("runs: expected one run per data seed")
    per_run = {ds: lane_trusts_by_method(r) for ds, r in by_ds.items()}
    methods = [m for m in dict.fromkeys(k for r in runs for k in (r.get("trust") or {}))
               if all(per_run[ds].get(m) for ds in by_ds)]
    out = {}
    for m in methods:
        lanes = {ds: per_run[ds][m] for ds in by_ds}
        every = [t for ls in lanes.values() for t in ls]
        level = every[0]["level"]
        cov = float(np.mean([t["coverage"] for t in every]))
        wor = mean_or_none(t["width_over_range"] for t in every)
        v, sd, truth = [], [], []
        for ds, ls in lanes.items():
            t = np.asarray(by_ds[ds]["true_value"], np.float64)
            sims = np.asarray([x["sim_value"] for x in ls], np.float64) / np.ptp(t)
            v.append(sims.ravel())
            sd.append(np.tile(sims.std(0, ddof=1), len(ls)))
            truth.append(np.tile(t / np.ptp(t), len(ls)))
        s = tr.spread_interval(np.concatenate(v), np.concatenate(sd), np.concatenate(truth),
                               level, cov)
        scaled = s["scaled_mean_width"]
        out[m] = tr.json_safe({
            "level": level, "coverage": cov, "width_over_range": wor,
            "worst_flagged": float(np.mean([t["worst"]["flagged"] for t in every])),
            "runs": len(every), "data_seeds": sorted(by_ds),
            "unbounded_runs": int(sum(bool(t["q_infinite"]) for t in every)),
            "seed_spread": {"coverage": s["coverage"], "width_over_range": s["mean_width"],
                            "scaled_width_over_range": scaled,
                            "scaled_infinite": not np.isfinite(scaled)},
            "narrower_than_seed_spread": None if wor is None or not np.isfinite(scaled)
            else bool(wor < scaled),
            "command": " && ".join(dict.fromkeys(r.get("command", "?") for r in runs)),
            "by_data_seed": {str(ds): {k: (r.get("trust") or {}).get(m, {}).get(k) for k in
                                       ("coverage", "width_over_range", "worst_flagged", "runs")}
                             for ds, r in by_ds.items()}})
        evaluated = method_evaluated(every)  # --trust-evaluated's sets, over the lanes with one
        if evaluated is not None:
            out[m]["evaluated"] = tr.json_safe(evaluated)
        combined = [((r.get("trust") or {}).get(m) or {}).get("seeds_combined")
                    for r in by_ds.values()]
        if all(isinstance(c, dict) and "coverage" in c for c in combined):
            out[m]["seeds_combined"] = seeds_combined_over(combined, list(by_ds))
    return out


def seeds_combined_over(blocks: list[dict], data_seeds: list[int]) -> dict:
    """The "seeds_combined" blocks of several data seeds (``trust_phase.seeds_combined``: a
    data seed's seeds as one estimate, as ``rl2s evaluate --ckpt A --ckpt B`` gives it) pooled:
    means of coverage, width_over_range and worst_flagged over the data seeds (one estimate
    each; width None where one is), "data_seeds" the data seeds of ``blocks`` (in their
    order, as everywhere a block names them), "seeds" each one's seed count."""
    mean = lambda k: mean_or_none(b.get(k) for b in blocks)  # noqa: E731
    return {"coverage": mean("coverage"), "width_over_range": mean("width_over_range"),
            "worst_flagged": mean("worst_flagged"), "data_seeds": list(data_seeds),
            "seeds": [b.get("seeds") for b in blocks]}


def data_seed_trust(result: dict, runs: list[dict]) -> None:
    """Issue 64's "trust" of the --data-seed-runs into ``result`` (in place) where the result
    has none of its own (its --paper run's): one run's blocks marked with its ``data_seed``;
    runs of several data seeds pooled (``data_seeds.pooled_trust``: every run of every data
    seed, each data seed's block kept under "by_data_seed"); "trust_calibration" per data
    seed. A trust recorded this way before is replaced. ValueError when two runs of one data
    seed bring one (their lanes are not here to join: merge them with --paper)."""
    have = [r for r in runs if isinstance(r.get("trust"), dict) and r["trust"]
            and "error" not in r["trust"]]
    if not have:
        return
    seeds = [data_seed_of(r) for r in have]
    if len(set(seeds)) < len(seeds):
        raise ValueError("trust: two --data-seed-runs of one data seed have a trust block; "
                         "join them with --paper first")
    own = result.get("trust") or {}
    if any("data_seed" not in b and "data_seeds" not in b for b in own.values()
           if isinstance(b, dict)) or "error" in own:
        return  # the task's own rows' trust
    if len(have) == 1:
        result["trust"] = {m: {**b, "data_seed": seeds[0]} for m, b in have[0]["trust"].items()}
    else:
        result["trust"] = pooled_trust(have)
    cals = {str(ds): r["trust_calibration"] for ds, r in zip(seeds, have, strict=True)
            if r.get("trust_calibration")}
    if len(cals) == 1:
        result["trust_calibration"] = {**next(iter(cals.values())), "data_seed": seeds[0]}
    elif cals:
        result["trust_calibration"] = {"by_data_seed": cals}


def evaluated_trust(result: dict, runs: list[dict], evaluated: list[dict]) -> None:
    """Issue 64 item 4 into ``result["trust"]`` (in place): each method's "evaluated" block
    (``trust_phase.method_evaluated``) pooled over the lanes of the ``evaluated`` runs
    (paper.py --trust-evaluated N), each a repeat of the --data-seed-run of its data seed in
    ``runs``: the same test policies and per-seed method numbers, so its simulators are that
    run's; "data_seeds" names the data seeds it covers. ValueError naming the field when a
    run has no such twin."""
    by_ds = {data_seed_of(r): r for r in runs}
    lanes: dict[str, list] = {}
    seeds: dict[str, set] = {}
    for e in evaluated:
        ds = data_seed_of(e)
        twin = by_ds.get(ds)
        if twin is None:
            raise ValueError(f"evaluated-run: no --data-seed-run of data seed {ds} to repeat")
        if e.get("task") != twin.get("task") or (e.get("test_policy_names")
                                                 != twin.get("test_policy_names")):
            raise ValueError(f"evaluated-run: task / test_policy_names: not those of the data "
                             f"seed {ds} run")
        own = {m: v for m, v in (e.get("per_seed") or {}).items() if m != "oracle"}
        if not own or any(twin.get("per_seed", {}).get(m) != v for m, v in own.items()):
            raise ValueError(f"evaluated-run: per_seed: differs from the data seed {ds} run's "
                             f"(other simulators: rerun it as a repeat of that run)")
        for m, ls in lane_trusts_by_method(e).items():
            lanes.setdefault(m, []).extend(ls)
            seeds.setdefault(m, set()).add(ds)
    for m, ls in lanes.items():
        ev = method_evaluated(ls)
        block = (result.get("trust") or {}).get(m)
        if ev is not None and isinstance(block, dict):
            block["evaluated"] = {**tr.json_safe(ev), "data_seeds": sorted(seeds[m])}


# issue 64's bars at level 0.9
TRUST_BARS = {"coverage": 0.85, "width_over_range": 0.25, "worst_flagged": 0.8}


def _num(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _cell(x, ok: bool | None = None) -> str:
    """A value and its bar's mark: " ✓" met, " ✗" missed, none where there is no judging."""
    return _num(x) + ("" if ok is None else (" ✓" if ok else " ✗"))


def combined_cell(c: dict | None) -> str:
    """The table's cell of a pooled "seeds_combined" block: coverage and width / range against
    issue 64's bars, "-" where the runs had none."""
    if not c or c.get("coverage") is None:
        return "-"
    w = c.get("width_over_range")
    return (f"{_cell(c['coverage'], c['coverage'] >= TRUST_BARS['coverage'])}, "
            f"{_cell(w, None if w is None else w <= TRUST_BARS['width_over_range'])}")


def evaluated_cell(e: dict | None) -> str:
    """The table's cell of a method's "evaluated" block (``evaluated_trust``: the perturbed /
    interpolated test policies of paper.py --trust-evaluated): coverage and width / range
    against issue 64's bars, the median width / range where recorded, and the data seeds it
    covers, "-" where no run measured one."""
    if not e or e.get("coverage") is None:
        return "-"
    med = e.get("median_width_over_range")
    med = "" if med is None else f", median {_num(med)}"
    return f"{combined_cell(e)}{med} ({', '.join(map(str, e.get('data_seeds') or ['?']))})"


def trust_rows(results: dict, tasks) -> list[str]:
    """The markdown table of the tasks' "trust" blocks (``pooled_trust`` or one data seed's):
    per task and method the coverage, width / range, the seed-spread interval scaled to the
    same coverage, the share of runs whose worst-error policy is flagged, each against issue
    64's bar, the seeds as one estimate (``seeds_combined_over``; its bars too), the data
    seeds' own coverages and the evaluated set (``evaluated_cell``); no task has one: []."""
    lines = [f"| task | method | runs (data seeds) | coverage (>= {TRUST_BARS['coverage']}) | "
             f"width / range (<= {TRUST_BARS['width_over_range']}) | seed spread scaled to it | "
             f"worst flagged (>= {TRUST_BARS['worst_flagged']}) | seeds as one: coverage, "
             f"width / range | coverage per data seed | evaluated set: coverage, width / range, "
             f"median width / range (data seeds) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    for task in tasks:
        for m, b in ((results.get(task) or {}).get("trust") or {}).items():
            if not isinstance(b, dict) or "coverage" not in b:
                continue
            seeds = b.get("data_seeds") or [b.get("data_seed", "?")]
            per = b.get("by_data_seed") or {}
            sp = (b.get("seed_spread") or {}).get("scaled_width_over_range")
            w = b.get("width_over_range")
            cov_per = "; ".join(f"{d}: {_num(e.get('coverage'))}"
                                for d, e in sorted(per.items(), key=lambda kv: int(kv[0])))
            lines.append(
                f"| {task} | {m} | {b['runs']} ({', '.join(map(str, seeds))}) | "
                f"{_cell(b['coverage'], b['coverage'] >= TRUST_BARS['coverage'])} | "
                f"{_cell(w, None if w is None else w <= TRUST_BARS['width_over_range'])} | "
                f"{_cell(sp, b.get('narrower_than_seed_spread'))} | "
                f"{_cell(b['worst_flagged'], b['worst_flagged'] >= TRUST_BARS['worst_flagged'])}"
                f" | {combined_cell(b.get('seeds_combined'))} | {cov_per} | "
                f"{evaluated_cell(b.get('evaluated'))} |")
    return lines if len(lines) > 2 else []
