"""Ranking over data collections (issue 66): each protocol run (experiments/paper.py's result)
of a task recorded under its data seed in ``docs/results/<task>.json``'s ``"by_data_seed"``
(``{"<data seed>": {"rl2s": {"kendall_tau", "mvd", "seeds"}, "gail", "bc", "rl2s-bc",
"oracle": {"kendall_tau", "seeds"}, "noise_ceiling": {"mean", "lo", "hi", "n_truth", "n_sim"},
"command", "hardware", "test_policy_names", "zoo_sha256", "complete": false where a run was
cut off}}``; a method, the oracle or the ceiling not measured is absent), and the rows of
the table "Ranking over data seeds" that experiments/paper_tables.py renders from it.
Pure Python and NumPy."""
from __future__ import annotations

import numpy as np

from rl2s_jax.stats import t_interval

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


def data_seed_entry(runs: list[dict]) -> tuple[int, dict]:
    """One data seed's row of ``by_data_seed`` from paper.py results of that data seed (other
    families, reruns): per method of BY_DATA_SEED_METHODS its Kendall tau and MVD, the means
    over the seeds of the first run that has it; the oracle's tau and the noise ceiling
    (``{"mean", "lo", "hi"}``) where a run measured them itself (not an oracle row that
    merge_results.py took from another collection: ``result["oracle"]``), else absent;
    ``"complete": false`` when a run used was cut off (paper.py's ``complete``).
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
    entry, used = {}, []
    own = [r for r in runs if not isinstance(r.get("oracle"), dict)]  # else merged from elsewhere
    for m in (*BY_DATA_SEED_METHODS, "oracle"):
        run = next((r for r in (own if m == "oracle" else runs)
                    if _mean_over_seeds(r.get("per_seed", {}).get(m, {}), "kendall_tau")
                    is not None), None)
        if run is None:
            continue
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
    if any(r.get("complete") is False for r in used):
        entry["complete"] = False  # a run cut off (e.g. its time limit): what it measured
    return seeds.pop(), entry


def record_data_seeds(result: dict, runs: list[dict]) -> None:
    """Add the runs to ``result["by_data_seed"]`` (in place), one entry per data seed (the
    runs of one data seed in the given order: a method's numbers come from the first that has
    it), replacing an earlier entry of that data seed. ValueError when a data seed's test
    policies differ from the other entries' (a ranking is compared on one test split)."""
    groups: dict[int, list[dict]] = {}
    for r in runs:
        groups.setdefault(data_seed_of(r), []).append(r)
    table = dict(result.get("by_data_seed") or {})
    for ds, group in groups.items():
        _, entry = data_seed_entry(group)
        for other, e in table.items():
            if other != str(ds) and e.get("test_policy_names") != entry["test_policy_names"]:
                raise ValueError(f"by_data_seed: data seed {ds} has other test policies than "
                                 f"data seed {other}'s entry")
        table[str(ds)] = entry
    result["by_data_seed"] = {k: table[k] for k in sorted(table, key=int)}


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
    row = max(orc["rows"], key=lambda r: (r["horizon"], r["n_episodes"]))
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
