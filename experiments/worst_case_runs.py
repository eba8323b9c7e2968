"""Every lane's worst case, for issue 41: one row per (method, seed lane) of
`experiments/paper.py` result JSONs, merged into docs/results/<task>_worst_case.json, with the
issue's two bars checked.

    python experiments/worst_case_runs.py --task halfcheetah RESULT.json [RESULT.json ...]
        [--out docs/results/halfcheetah_worst_case.json] [--source-label LABEL ...]

A row is {data_seed, seed, method, eps, mvd, tau} (the final evaluation's test MVD and Kendall
tau: ``per_seed[method]``, per seed of ``seed_ids``, else the command's ``--first-seed`` + 0 ..
seeds-1), plus mvd / tau / step_selected (``selected[method]``: model selection on the training
policies), its source (the file, or --source-label: one for all files or one per file), commit
and device. eps: ``lanes["<method>/<seed>"]["eps"]`` (``--eps-lanes``' "rl2s@EPS" lanes are
rl2s rows at their eps); data seed: ``data_seed`` or the command's ``--data-seed`` (else 0).

A row whose TrainConfig differs from the bars' (``--set KEY=VALUE`` other than eps; for rl2s /
gail also the NLL anchor they ran with, BAR_CONFIG: "all", the default since 2026-11-27, so the
committed "selected" runs are variants) carries ``variant`` ("KEY=VALUE,...", else null), is
summarised under 'method+VARIANT' and enters no bar; ``summary.variants`` pairs the variants.
A method without values in a run paper.py marked incomplete is left out with a note.

A key (data_seed, seed, method, eps, variant) that an earlier file of the call gave is a rerun
(same configuration, data and seed; another run, e.g. one with eps lanes): ``rerun`` counts
them in the files' order (0: the first); rows pair only within one run, by pair_key (data_seed,
seed, rerun). A file with an earlier one's values is refused (the same run twice). The out
file keeps its other keys and rows; a row with the same key and rerun is replaced. ``summary``
is rebuilt from all rows: per method (and eps) n, data seeds, mean / median / max MVD, max /
median; bar (a): no RL2S run's MVD above twice the median of RL2S's runs, judged once >= 5
seeds for each of >= 2 data seeds; bar (b), per GAIL and BC: RL2S's MVD minus theirs, paired,
averaged over a (data seed, seed)'s reruns, its mean over those with a 95% bootstrap interval
(2000 replicates, rng seed 0) and t-interval; it holds when the mean is <= 0 or the interval
holds 0. Bad input stops before anything is written.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys

import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.stats import bootstrap_ci, mean_per_unit, t_interval
from rl2s_jax.train.config import saved_field

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")  # rl2s_jax.paper.protocol.METHODS (no JAX here)
ADVERSARIAL = ("rl2s", "gail")  # the methods the NLL anchor (adv_nll_on) enters
BAR_CONFIG = {"adv_nll_on": "all"}  # TrainConfig's defaults since 2026-11-27: the bars' runs
MIN_SEEDS, MIN_DATA_SEEDS, N_BOOT = 5, 2, 2000


def _flag(result: dict, flag: str, default: int) -> int | None:
    """The int value of paper.py's ``--flag`` in result["command"] (parts joined by '&&' by
    merge_results.py; a part without it has ``default``); None when the parts differ."""
    parts = [p for p in result["command"].split("&&") if "paper.py" in p] or [""]
    values = {int(m.group(1)) if (m := re.search(rf"{flag}[= ](-?\d+)", p)) else default
              for p in parts}
    return values.pop() if len(values) == 1 else None


def _variant(result: dict, method: str = "rl2s") -> str | None:
    """How the run's TrainConfig for ``method`` differs from the bars' (BAR_CONFIG, the
    defaults; eps aside): paper.py's ``--set KEY=VALUE`` overrides, and for the adversarial
    methods the anchor they ran with (the saved ``train_config["adversarial"]``'s
    adversarial.nll_on, else the --set, else "selected": runs from before the option);
    sorted "KEY=VALUE" joined by ',', None when none differs."""
    sets = dict(m.group(1).split("=", 1) for p in result.get("command", "").split("&&")
                for m in re.finditer(r"--set[= ](\S+=\S+)", p))
    sets.pop("eps", None)
    anchor = sets.pop("adv_nll_on", None) or sets.pop("adversarial.nll_on", None)
    if method.split("@")[0] in ADVERSARIAL:
        config = (result.get("train_config") or {}).get("adversarial") or {}
        sets["adv_nll_on"] = saved_field(config, "adversarial.nll_on") or anchor or "selected"
    return ",".join(sorted(f"{k}={v}" for k, v in sets.items()
                           if BAR_CONFIG.get(k) != v)) or None


def lane_rows(result: dict, source: str, skipped: list | None = None) -> list[dict]:
    """-> one row per (method, seed) of a paper.py result. A method without values in a result
    that paper.py marked incomplete (``complete`` false: stopped mid-run) is left out and named
    in ``skipped``. Raises ValueError naming the missing or inconsistent field."""
    for key in ("per_seed", "task"):
        if key not in result:
            raise ValueError(f"missing field {key!r}")
    if "data_seed" in result:
        data_seed = int(result["data_seed"])
    elif "command" in result:
        data_seed = _flag(result, "--data-seed", 0)
        if data_seed is None:
            raise ValueError("command: its paper.py parts ran different --data-seed values")
    else:
        raise ValueError("missing field 'data_seed' (or 'command' with --data-seed)")
    if result.get("seed_ids") is not None:
        ids = [int(s) for s in result["seed_ids"]]
    elif "seeds" in result and "command" in result:
        first = _flag(result, "--first-seed", 0)
        if first is None:
            raise ValueError("missing field 'seed_ids' (the command's parts differ in "
                             "--first-seed)")
        ids = list(range(first, first + int(result["seeds"])))
    else:
        raise ValueError("missing field 'seed_ids' (or 'seeds' and 'command')")
    methods = [m for m in METHODS if m in result["per_seed"]]
    methods += sorted(set(result["per_seed"]) - set(METHODS) - {"oracle"})
    if not methods:
        raise ValueError("per_seed: no method")
    extra = {k: result[k] for k in ("commit",) if result.get(k)}
    if result.get("device") or result.get("hardware"):
        extra["device"] = result.get("device") or result["hardware"]
    rows = []
    for m in methods:
        extra["variant"] = _variant(result, m)
        per, sel = result["per_seed"][m], result.get("selected", {}).get(m, {})
        if result.get("complete") is False and not per.get("mvd"):
            if skipped is not None:
                skipped.append(m)
            continue
        for k in ("mvd", "kendall_tau"):
            if k not in per:
                raise ValueError(f"missing field 'per_seed.{m}.{k}'")
            if len(per[k]) != len(ids):
                raise ValueError(f"per_seed.{m}.{k}: expected {len(ids)} values (seeds {ids}), "
                                 f"got {len(per[k])}")
        for k, v in sel.items():
            if k in ("mvd", "kendall_tau", "step") and len(v) != len(ids):
                raise ValueError(f"selected.{m}.{k}: expected {len(ids)} values, got {len(v)}")
        for i, s in enumerate(ids):
            row = {"data_seed": data_seed, "seed": s, "method": m.split("@")[0],  # rl2s@0.1
                   "eps": result.get("lanes", {}).get(f"{m}/{s}", {}).get("eps"),
                   "mvd": per["mvd"][i], "tau": per["kendall_tau"][i]}
            for k, name in (("mvd", "mvd_selected"), ("kendall_tau", "tau_selected"),
                            ("step", "step_selected")):
                if k in sel:
                    row[name] = sel[k][i]
            rows.append({**row, "source": source, **extra})
    return rows


def row_key(r: dict) -> tuple:
    """The run's key, its rerun aside."""
    return (r["data_seed"], r["seed"], r["method"], r["eps"], r.get("variant"))


def pair_key(r: dict) -> tuple:
    """What pairs rows of one run: (data_seed, seed, rerun)."""
    return (r["data_seed"], r["seed"], r.get("rerun", 0))


def merge_rows(old: list[dict], new: list[dict]) -> list[dict]:
    """old rows whose key no new row has, and the new rows; sorted by data seed, method
    (METHODS' order), seed."""
    run_key = lambda r: (*row_key(r), r.get("rerun", 0))
    keys = {run_key(r) for r in new}
    rows = [r for r in old if run_key(r) not in keys] + new
    order = {m: i for i, m in enumerate(METHODS)}
    return sorted(rows, key=lambda r: (r["data_seed"], order.get(r["method"], len(order)),
                                       r["method"], r["seed"], r.get("rerun", 0),
                                       -1 if r["eps"] is None else r["eps"]))


def group_runs(rows: list[dict]) -> dict[str, list[dict]]:
    """{label: rows}: the label is the method, 'method+VARIANT' for a run with TrainConfig
    overrides, and '@eps=X' after either when a method has rows of several eps."""
    eps_of: dict[str, set] = {}
    for r in rows:
        eps_of.setdefault(r["method"], set()).add(r["eps"])
    out: dict[str, list[dict]] = {}
    for r in rows:
        label = r["method"] + (f"+{r['variant']}" if r.get("variant") else "")
        if len(eps_of[r["method"]]) > 1:
            label += f"@eps={r['eps']}"
        out.setdefault(label, []).append(r)
    return out


def _finite(x) -> bool:
    return x is not None and math.isfinite(x)


def method_stats(runs: list[dict]) -> dict:
    """n, data seeds, seeds per data seed, mean / median / max MVD and max / median (over
    the runs with a finite MVD; n_missing counts the others)."""
    mvd = np.array([r["mvd"] for r in runs if _finite(r["mvd"])], np.float64)
    per_ds: dict[int, set] = {}
    for r in runs:
        per_ds.setdefault(r["data_seed"], set()).add(r["seed"])
    stats = {"n": len(runs), "n_missing": len(runs) - len(mvd),
             "eps": sorted({r["eps"] for r in runs}, key=lambda e: -1 if e is None else e),
             "data_seeds": sorted(per_ds),
             "seeds_per_data_seed": {str(k): len(v) for k, v in sorted(per_ds.items())}}
    if len(mvd):
        med = float(np.median(mvd))
        stats.update(mean_mvd=float(mvd.mean()), median_mvd=med, max_mvd=float(mvd.max()),
                     max_over_median=float(mvd.max() / med) if med > 0 else None)
    return stats


def _enough(seeds_per_data_seed: dict) -> str | None:
    """None when >= MIN_SEEDS seeds for each of >= MIN_DATA_SEEDS data seeds, else why not."""
    full = [k for k, n in seeds_per_data_seed.items() if n >= MIN_SEEDS]
    if len(full) >= MIN_DATA_SEEDS:
        return None
    return (f"not enough runs: need >= {MIN_SEEDS} seeds for each of >= {MIN_DATA_SEEDS} data "
            f"seeds, have seeds per data seed {seeds_per_data_seed}")


def bar_a(stats: dict) -> dict:
    """No run's MVD above twice the median of the runs (a missing MVD fails)."""
    ratio = stats.get("max_over_median")
    holds = stats["n_missing"] == 0 and ratio is not None and ratio <= 2.0
    why = _enough(stats["seeds_per_data_seed"])
    return {"rule": "max MVD <= 2 x median MVD", "max_over_median": ratio,
            "holds_so_far": holds, "verdict": why or ("pass" if holds else "fail")}


def _minus(a: list[dict], b: list[dict]) -> list[dict]:
    """Rows {data_seed, seed, rerun, mvd}: a's MVD minus b's on their shared pair_key."""
    mb = {pair_key(r): r["mvd"] for r in b if _finite(r["mvd"])}
    return [{"data_seed": r["data_seed"], "seed": r["seed"], "rerun": r.get("rerun", 0),
             "mvd": r["mvd"] - mb[pair_key(r)]}
            for r in a if _finite(r["mvd"]) and pair_key(r) in mb]


def paired_difference(a: list[dict], b: list[dict], seed: int = 0) -> dict:
    """MVD of a minus MVD of b over their shared pair_key with finite MVDs, averaged first
    over a (data_seed, seed) unit's reruns (they share data and seed: not independent), then
    over units: mean, 95% bootstrap (N_BOOT replicates, rng ``seed``) and t intervals."""
    pairs = sorted(_minus(a, b), key=pair_key)
    d, units = mean_per_unit(((p["data_seed"], p["seed"]), p["mvd"]) for p in pairs)
    per_ds = {str(ds): sum(u[0] == ds for u in units) for ds, _ in units}
    out = {"n_pairs": len(pairs), "n_units": len(d),
           "seeds_per_data_seed": per_ds, "mean_diff": None, "ci95_bootstrap": None,
           "ci95_t": None}
    if not len(d):
        return out
    out.update(mean_diff=float(d.mean()), ci95_bootstrap=bootstrap_ci(d, n_boot=N_BOOT, seed=seed))
    if (t := t_interval(d)) is not None:
        out["ci95_t"] = list(t[1:])
    return out


def bar_b(diff: dict) -> dict:
    """RL2S's paired mean MVD at most the other's, or the bootstrap interval holds 0."""
    if not diff["n_pairs"]:
        return {**diff, "holds_so_far": None, "verdict": "no paired runs"}
    lo, hi = diff["ci95_bootstrap"]
    holds = diff["mean_diff"] <= 0 or lo <= 0 <= hi
    why = _enough(diff["seeds_per_data_seed"])
    return {**diff, "holds_so_far": holds, "verdict": why or ("pass" if holds else "fail")}


def _pick(rows: list[dict], method: str, variant: str | None, eps=None) -> list[dict]:
    return [r for r in rows if r["method"] == method and r.get("variant") == variant
            and (eps is None or r["eps"] == eps)]


def variant_comparisons(rows: list[dict]) -> dict:
    """Per TrainConfig variant of the rl2s rows (no bar), paired by pair_key:
    rl2s+V against its own run's gail+V, the default bc, and the default rl2s at the same eps
    (the variant's effect, run-to-run noise included); gail+V against the default gail (that
    noise alone where V leaves gail's training unchanged); and the effect net of it,
    (rl2s+V - gail+V) - (rl2s - gail)."""
    out = {}
    for v in sorted({r["variant"] for r in rows if r["method"] == "rl2s" and r.get("variant")}):
        gail_v, gail = _pick(rows, "gail", v), _pick(rows, "gail", None)
        for eps in sorted({r["eps"] for r in _pick(rows, "rl2s", v)},
                          key=lambda e: -1 if e is None else e):
            a, base = _pick(rows, "rl2s", v, eps), _pick(rows, "rl2s", None, eps)
            name = f"rl2s+{v}@eps={eps}"
            for other, b in ((f"gail+{v}", gail_v), ("bc", _pick(rows, "bc", None)),
                             (f"rl2s@eps={eps}", base)):
                out[f"{name} - {other}"] = paired_difference(a, b)
            out[f"({name} - gail+{v}) - (rl2s@eps={eps} - gail)"] = paired_difference(
                _minus(a, gail_v), _minus(base, gail))
        out[f"gail+{v} - gail"] = paired_difference(gail_v, gail)
    return {k: d for k, d in out.items() if d["n_pairs"]}


def summarise(rows: list[dict]) -> dict:
    """The out file's ``summary``: per label method_stats, bar (a) for each rl2s label, bar
    (b) for each rl2s label against each gail and bc label, the variants' comparisons."""
    groups = group_runs(rows)
    summary = {"methods": {k: method_stats(v) for k, v in groups.items()},
               "bar_a": {}, "bar_b": {}, "variants": variant_comparisons(rows)}
    for k in [k for k in groups if k.split("@")[0] == "rl2s"]:
        summary["bar_a"][k] = bar_a(summary["methods"][k])
        for other in groups:
            if other.split("@")[0] in ("gail", "bc"):
                summary["bar_b"][f"{k} - {other}"] = bar_b(
                    paired_difference(groups[k], groups[other]))
    return summary


def _f(x, fmt=".1f") -> str:
    return "n/a" if x is None else format(x, fmt)


def report(task: str, rows: list[dict], summary: dict) -> str:
    """The printed table: the runs, the per-method summary, the bars."""
    lines = [f"{task}: {len(rows)} runs",
             f"{'data_seed':>9} {'seed':>4} {'rerun':>5} {'method':<8} {'eps':>5} {'MVD':>9} "
             f"{'tau':>6} {'MVD sel':>9} {'tau sel':>7}"]
    for r in rows:
        lines.append(f"{r['data_seed']:>9} {r['seed']:>4} {r.get('rerun', 0):>5} {r['method']:<8} "
                     f"{_f(r['eps'], 'g'):>5} {_f(r['mvd']):>9} {_f(r['tau'], '.3f'):>6} "
                     f"{_f(r.get('mvd_selected')):>9} {_f(r.get('tau_selected'), '.3f'):>7}")
    lines.append(f"\n{'method':<10} {'n':>3} {'data seeds':<12} {'mean MVD':>9} {'median':>9} "
                 f"{'max':>9} {'max/med':>7}")
    for k, s in summary["methods"].items():
        lines.append(f"{k:<10} {s['n']:>3} {','.join(map(str, s['data_seeds'])):<12} "
                     f"{_f(s.get('mean_mvd')):>9} {_f(s.get('median_mvd')):>9} "
                     f"{_f(s.get('max_mvd')):>9} {_f(s.get('max_over_median'), '.2f'):>7}"
                     + (f"  ({s['n_missing']} without an MVD)" if s["n_missing"] else ""))
    for k, b in summary["bar_a"].items():
        lines.append(f"bar (a) {k}: max/median {_f(b['max_over_median'], '.2f')} (<= 2; holds "
                     f"so far: {b['holds_so_far']}): {b['verdict']}")
    for k, b in summary["bar_b"].items():
        ci = b["ci95_bootstrap"] and "[" + ", ".join(_f(x) for x in b["ci95_bootstrap"]) + "]"
        ct = b["ci95_t"] and "[" + ", ".join(_f(x) for x in b["ci95_t"]) + "]"
        lines.append(f"bar (b) {k}: paired MVD diff {_f(b['mean_diff'])} over {b['n_pairs']} "
                     f"pairs ({b['n_units']} seeds), 95% bootstrap {ci}, t {ct} (holds so far: "
                     f"{b['holds_so_far']}): {b['verdict']}")
    for k, d in summary.get("variants", {}).items():
        ci = d["ci95_bootstrap"] and "[" + ", ".join(_f(x) for x in d["ci95_bootstrap"]) + "]"
        lines.append(f"variant {k}: paired MVD diff {_f(d['mean_diff'])} over {d['n_pairs']} "
                     f"pairs ({d['n_units']} seeds), 95% bootstrap {ci}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("results", nargs="+", help="experiments/paper.py result JSONs")
    ap.add_argument("--out", help="default: docs/results/<task>_worst_case.json")
    ap.add_argument("--source-label", nargs="+", help="the rows' source instead of the file "
                    "path: one label for all files or one per file")
    args = ap.parse_args(argv)
    out = args.out or os.path.join("docs", "results", f"{args.task}_worst_case.json")
    labels = args.source_label or args.results
    labels = labels * len(args.results) if len(labels) == 1 else labels
    if len(labels) != len(args.results):
        raise SystemExit(f"--source-label: expected 1 or {len(args.results)} labels, got "
                         f"{len(labels)}")
    new, seen = [], {}
    for path, label in zip(args.results, labels, strict=True):
        skipped: list[str] = []
        try:
            with open(path) as f:
                result = json.load(f)
            if not isinstance(result, dict):
                raise ValueError("expected a JSON object")
            rows = lane_rows(result, label, skipped)
        except (OSError, ValueError, TypeError, KeyError) as err:
            raise SystemExit(f"{path}: {err}") from None
        if skipped:
            print(f"{path}: incomplete run; no values for {', '.join(skipped)} (left out)")
        if result["task"] != args.task:
            raise SystemExit(f"{path}: task is {result['task']!r}, not --task {args.task!r}")
        for r in rows:
            earlier = seen.setdefault(row_key(r), [])
            if any((q["mvd"], q["tau"]) == (r["mvd"], r["tau"]) for q in earlier):
                raise SystemExit(f"{path}: run {row_key(r)} has the MVD and tau of an earlier "
                                 f"file's: the same run twice?")
            r["rerun"] = len(earlier)
            earlier.append(r)
        new += rows
    doc = {}
    if os.path.exists(out):
        try:
            with open(out) as f:
                doc = json.load(f)
        except (OSError, ValueError) as err:
            raise SystemExit(f"{out}: {err}") from None
        if doc.get("task", args.task) != args.task:
            raise SystemExit(f"{out}: task is {doc['task']!r}, not --task {args.task!r}")
        for i, r in enumerate(doc.get("runs", [])):
            missing = [k for k in ("data_seed", "seed", "method", "eps", "mvd") if k not in r]
            if missing:
                raise SystemExit(f"{out}: runs[{i}] has no field {missing[0]!r}")
    doc.setdefault("task", args.task)
    doc["runs"] = merge_rows(doc.get("runs", []), new)
    doc["summary"] = {"command": " ".join(["python", "experiments/worst_case_runs.py",
                                           *(sys.argv[1:] if argv is None else argv)]),
                      **summarise(doc["runs"])}
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    write_json(out, doc)
    print(report(args.task, doc["runs"], doc["summary"]) + f"\n-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
