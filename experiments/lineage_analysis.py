"""Issue 66: does a simulator rank the test policies of learner lineages its training data
holds as well as the oracle does, and is the loss in the pairs that touch the others?

A zoo's policies are snapshots of a few learner runs (``Zoo.lineage``: learner and seed).
Which test policies come from a run with no training policy is known without any truth (the
data a simulator learns from names its policies): Hopper and Walker2d have 9 such test policies
of 20, Ant one (ant-051), HalfCheetah none. Per data seed and method: Kendall tau over all
test policies and over the seen-lineage ones alone, each beside the oracle's (the real dynamics
through the same evaluation), and the share of swapped (discordant) pairs among the pairs of
seen policies against the pairs touching an unseen one (``ranking_swaps.lineage_split``).

    for t in hopper walker2d ant halfcheetah; do
      python experiments/lineage_analysis.py docs/results/worst_case/${t}_data0_anchor_all.json \
        docs/results/worst_case/${t}_data0.json docs/results/data_seeds/${t}_data7.json \
        docs/results/data_seeds/${t}_data23*.json \
        --oracle docs/results/data_seeds/oracle_${t}_data0.json \
        --oracle docs/results/data_seeds/oracle_${t}_data7.json
    done

Results of one task; several per data seed are joined as ranking_analysis.py joins them (a
method's lanes from the first file that has them). The oracle's per-policy values come from a
result's ``oracle_sim_value`` (paper.py run with the oracle) or an ``oracle_check.py
--data-seed`` file (``--oracle``, matched by data seed, its ``oracle_row``; policies matched
by name).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from rl2s_jax._files import write_json  # noqa: E402
from rl2s_jax.evaluate.ranking_swaps import lanes_of, lineage_split  # noqa: E402
from rl2s_jax.paper.data_seeds import group_by_data_seed, oracle_row  # noqa: E402
from rl2s_jax.stats import mean_or_none  # noqa: E402
from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids  # noqa: E402

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")


def oracle_values(results: list[dict], oracles: dict, data_seed: int, names) -> list | None:
    """The oracle's simulated values per oracle seed ([S][P], in ``names``' order) of one data
    seed: a result's ``oracle_sim_value``, else the ``--oracle`` file of that data seed, else
    None. ValueError when the oracle file's policies are not the result's."""
    for r in results:
        if r.get("oracle_sim_value"):
            return [list(v) for v in r["oracle_sim_value"]]
    o = oracles.get(data_seed)
    if o is None:
        return None
    theirs = list(o["policy_names"])
    if sorted(theirs) != sorted(names):
        raise ValueError(f"--oracle (data seed {data_seed}): policy_names: expected the "
                         f"result's {len(names)} test policies, got {len(theirs)} others")
    v = oracle_row(o)["oracle_value"]
    return [[v[theirs.index(n)] for n in names]]


def same_truth(results: list[dict], data_seed: int) -> np.ndarray:
    """The true values [P] of one data seed's results (the first that records them), after
    checking that every result measured the same truths (``true_value_undiscounted`` equal to
    1e-6 relative): joined runs must share their data. ValueError naming the field otherwise."""
    undisc = [np.asarray(r["true_value_undiscounted"], np.float64) for r in results
              if "true_value_undiscounted" in r]
    if any(not np.allclose(u, undisc[0], rtol=1e-6, atol=1e-6) for u in undisc[1:]):
        raise ValueError(f"true_value_undiscounted: the data seed {data_seed} results measured "
                         f"other truths (another collection): analyse them apart")
    for r in results:
        if "true_value" in r:
            return np.asarray(r["true_value"], np.float64)
    raise ValueError(f"true_value: no data seed {data_seed} result records it")


def mean_over_lanes(splits: list[dict]) -> dict:
    """``lineage_split``'s numbers averaged over a method's lanes (None where a lane has
    None), with "lanes"."""
    return {k: mean_or_none(x[k] for x in splits) for k in splits[0]} | {"lanes": len(splits)}


def analyse(results: list[dict], oracles: dict, methods=METHODS) -> dict:
    """{data seed: {"seen": [P] bool, "n_unseen", "methods": {method or "oracle": means over
    its lanes of ``lineage_split``'s numbers, "lanes"}}} for the results of one task."""
    groups = group_by_data_seed(results)
    zoo = load_zoo(results[0]["task"])
    out = {}
    for ds, rs in groups.items():
        names = rs[0]["test_policy_names"]
        if any(r["test_policy_names"] != names for r in rs):
            raise ValueError(f"test_policy_names: the data seed {ds} results test other policies")
        seen = np.array(zoo.seen_lineage(names_to_zoo_ids(names)))
        truth = same_truth(rs, ds)
        of = lanes_of(rs, methods)
        lanes = {m: [ln["sim_value"] for ln in ls] for m, ls in of.items()}
        orc = oracle_values(rs, oracles, ds, names)
        if orc is not None:
            lanes["oracle"] = orc
        per = {}
        for m, sims in lanes.items():
            per[m] = mean_over_lanes([lineage_split(truth, s, seen) for s in sims])
        out[ds] = {"seen": seen.tolist(), "n_unseen": int((~seen).sum()),
                   "unseen": [n for n, ok in zip(names, seen, strict=True) if not ok],
                   "methods": per,
                   "intervals": {m: iv for m, ls in of.items()
                                 if (iv := interval_cells(ls, truth, seen)) is not None}}
    return out


def interval_cells(lanes: list[dict], truth, seen) -> dict | None:
    """Issue 64's intervals of a method's lanes by lineage: per (lane, policy) of the seen and
    of the unseen-lineage policies, whether its interval covers the truth, its width and
    |trust sim_value - truth| over the range of the truths, and its "trusted" flag (an
    unbounded end: infinite width). None unless every lane has intervals."""
    t = np.asarray(truth, np.float64)
    rng = float(np.ptp(t))
    out = {k: {"covered": [], "width": [], "error": [], "flagged": []} for k in ("seen", "unseen")}
    for ln in lanes:
        tr = ln.get("trust") or {}
        if "interval" not in tr:
            return None
        lo, hi = (np.array([-np.inf if iv[0] is None else iv[0] for iv in tr["interval"]]),
                  np.array([np.inf if iv[1] is None else iv[1] for iv in tr["interval"]]))
        cells = {"covered": (t >= lo) & (t <= hi), "width": (hi - lo) / rng,
                 "error": np.abs(np.asarray(tr["sim_value"]) - t) / rng,
                 "flagged": ~np.asarray(tr["trusted"], bool)}
        for k, mask in (("seen", seen), ("unseen", ~seen)):
            for name, v in cells.items():
                out[k][name] += np.asarray(v)[mask].tolist()
    return out


def pooled_interval_lines(analyses: dict) -> list[str]:
    """Per method, its ``interval_cells`` over every data seed with intervals, seen / unseen:
    coverage, median width / range, share flagged, mean error / range."""
    by_m: dict[str, dict] = {}
    for e in analyses.values():
        for m, iv in e.get("intervals", {}).items():
            acc = by_m.setdefault(m, {k: {n: [] for n in iv[k]} for k in iv})
            for k in iv:
                for n, v in iv[k].items():
                    acc[k][n] += v
    lines = []
    for m, iv in by_m.items():
        if not iv["unseen"]["covered"]:
            continue
        cell = lambda fn, n: " / ".join(f"{fn(iv[k][n]):.3f}" for k in ("seen", "unseen"))  # noqa
        lines.append(f"  {m:8s} coverage {cell(np.mean, 'covered')} | median width / range "
                     f"{cell(np.median, 'width')} | flagged {cell(np.mean, 'flagged')} | "
                     f"error / range {cell(np.mean, 'error')} (n {len(iv['seen']['covered'])} / "
                     f"{len(iv['unseen']['covered'])})")
    return ["intervals over the data seeds with them, seen / unseen lineage:", *lines] if lines \
        else []


def report(task: str, a: dict) -> str:
    f = lambda x: "  n/a" if x is None else f"{x:.3f}"  # noqa: E731
    lines = []
    for ds, e in a.items():
        lines.append(f"{task}, data seed {ds}: {len(e['seen'])} test policies, "
                     f"{e['n_unseen']} of lineages absent from training "
                     f"({', '.join(e['unseen']) or 'none'})")
        lines.append("  method    lanes  tau    tau(seen)  swapped: seen pairs / pairs "
                     "touching unseen")
        orc = e["methods"].get("oracle")
        for m, r in e["methods"].items():
            bar = ("" if m == "oracle" or orc is None or r["tau_seen"] is None
                   or orc["tau_seen"] is None else
                   f"   seen: {r['tau_seen'] - orc['tau_seen']:+.3f} vs the oracle")
            lines.append(f"  {m:8s} {r['lanes']:5d}  {f(r['tau'])}  {f(r['tau_seen'])}      "
                         f"{f(r['swap_rate_seen'])} / {f(r['swap_rate_touching'])}{bar}")
    return "\n".join(lines + pooled_interval_lines(a))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", help="paper.py <task>.json files of one task")
    ap.add_argument("--oracle", action="append", default=[], metavar="ORACLE_JSON",
                    help="oracle_check.py --data-seed output (repeatable, one per data seed)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--json", help="also write the analysis here")
    args = ap.parse_args(argv)
    results = []
    for path in args.results:
        with open(path) as fh:
            results.append(json.load(fh))
    oracles = {}
    for path in args.oracle:
        with open(path) as fh:
            o = json.load(fh)
        if "data_seed" not in o or "rows" not in o:
            raise SystemExit(f"--oracle {path}: expected oracle_check.py --data-seed output "
                             f"(data_seed, rows)")
        oracles[int(o["data_seed"])] = o
    a = analyse(results, oracles, tuple(args.methods.split(",")))
    print(report(results[0]["task"], a))
    if args.json:
        write_json(args.json, a)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
