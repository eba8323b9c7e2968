"""Which test policy sets each lane's MVD (issue 41, item 1: the cause of a catastrophic seed).

From `experiments/paper.py` result JSONs (each lane's simulated value of every test policy,
``lanes[<method>/<seed>]["sim_value"]``, against ``true_value``), per lane: the test policy
with the largest |simulated - true| value (the lane's MVD), its true and simulated value, and
the second-largest error (what the MVD would be without that policy); pooled over the files:
how often each policy is the worst, and the spread of its simulated value over the lanes;
per run and method, whether the policy the seeds disagree on most (the std over seeds of its
simulated value) is the worst one (``seed_spread``: a signal that needs no true value); per
adversarial lane, how far it moved each policy's value from the same seed's bc lane
(``likelihood_shift``: no true value needed either).

    python experiments/worst_policy.py docs/results/protocol_4gpu_h200/halfcheetah.json ...
        [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter

import numpy as np


def lane_worst(result: dict, source: str = "") -> list[dict]:
    """-> one row per lane with a sim_value: {source, lane, policy, true, sim, mvd,
    second}. Raises ValueError naming the field when a lane's values do not match the test
    policies."""
    truth = np.asarray(result["true_value"], np.float64)
    names = result.get("test_policy_names") or [f"test-{i}" for i in range(len(truth))]
    if len(names) != len(truth):
        raise ValueError(f"test_policy_names: expected {len(truth)} names (true_value's), got "
                         f"{len(names)}")
    rows = []
    for lane, info in sorted(result.get("lanes", {}).items()):
        if "sim_value" not in info:
            continue
        sim = np.asarray(info["sim_value"], np.float64)
        if sim.shape != truth.shape:
            raise ValueError(f"lanes.{lane}.sim_value: expected {truth.shape[0]} values, got "
                             f"{sim.shape}")
        err = np.abs(sim - truth)
        order = np.argsort(err)
        i = int(order[-1])
        rows.append({"source": source, "lane": lane, "policy": names[i],
                     "true": float(truth[i]), "sim": float(sim[i]), "mvd": float(err[i]),
                     "second": float(err[order[-2]]) if len(err) > 1 else 0.0})
    return rows


def seed_spread(result: dict, source: str = "") -> list[dict]:
    """Whether the seeds' disagreement points at the worst policy: per method with 2+ seeds,
    ``app.evaluation.simulator_agreement`` of its seeds' simulated values (each test policy's
    spread, the std over the seeds, against its errors). -> [{source, method, seeds, rho
    (Spearman of spread and mean |error| over the policies), worst (the policy of the largest
    error), worst_rank (its rank by spread, 1 = the most disputed), top_spread (the most
    disputed policy)}]."""
    from rl2s_jax.app.evaluation import simulator_agreement

    truth = np.asarray(result["true_value"], np.float64)
    names = result.get("test_policy_names") or [f"test-{i}" for i in range(len(truth))]
    by_method: dict[str, list] = {}
    for lane, info in sorted(result.get("lanes", {}).items()):
        if "sim_value" in info:
            by_method.setdefault(lane.split("/")[0], []).append(info["sim_value"])
    out = []
    for method, values in by_method.items():
        if len(values) < 2 or len(truth) < 2:
            continue
        a = simulator_agreement(values, truth, names, top_k=1)
        out.append({"source": source, "method": method, "seeds": len(values),
                    "rho": a["spearman_spread_error"], "worst": a["worst"],
                    "worst_rank": a["worst_rank"], "top_spread": a["most_disputed"][0]})
    return out


def likelihood_shift(result: dict, source: str = "", reference: str = "bc") -> list[dict]:
    """How far the adversarial phase moved each policy's value, a signal that needs no true
    value: per lane "<method>/<seed>" with a ``reference`` lane of the same seed (paper.py's
    bc lanes continue the pre-training the adversarial lanes start from), each test policy's
    score |sim - sim_reference| / the lane's median of it. -> [{source, lane, top (the
    policy of the largest score), top_score, worst (the policy of the lane's MVD),
    worst_score, mvd}]."""
    truth = np.asarray(result["true_value"], np.float64)
    names = result.get("test_policy_names") or [f"test-{i}" for i in range(len(truth))]
    lanes = result.get("lanes", {})
    out = []
    for lane, info in sorted(lanes.items()):
        method, _, seed = lane.partition("/")
        ref = lanes.get(f"{reference}/{seed}", {})
        if method == reference or "sim_value" not in info or "sim_value" not in ref:
            continue
        sim = np.asarray(info["sim_value"], np.float64)
        shift = np.abs(sim - np.asarray(ref["sim_value"], np.float64))
        score = shift / max(float(np.median(shift)), 1e-9)
        top, worst = int(np.argmax(score)), int(np.argmax(np.abs(sim - truth)))
        out.append({"source": source, "lane": lane, "top": names[top],
                    "top_score": float(score[top]), "worst": names[worst],
                    "worst_score": float(score[worst]), "mvd": float(abs(sim - truth)[worst])})
    return out


def summary(rows: list[dict]) -> dict:
    """Pooled: {lanes, worst_counts [(policy, n)] most frequent first, median_mvd,
    median_second, by_policy {policy: {n, true_min, true_max, sim_min, sim_max, mvd_max}}}
    (the true value differs between data collections)."""
    counts = Counter(r["policy"] for r in rows)
    by = {}
    for p, n in counts.most_common():
        mine = [r for r in rows if r["policy"] == p]
        by[p] = {"n": n, "true_min": min(r["true"] for r in mine),
                 "true_max": max(r["true"] for r in mine), "sim_min": min(r["sim"] for r in mine),
                 "sim_max": max(r["sim"] for r in mine), "mvd_max": max(r["mvd"] for r in mine)}
    return {"lanes": len(rows), "worst_counts": counts.most_common(),
            "median_mvd": float(np.median([r["mvd"] for r in rows])) if rows else None,
            "median_second": float(np.median([r["second"] for r in rows])) if rows else None,
            "by_policy": by}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="+", help="paper.py result JSONs (<task>.json)")
    ap.add_argument("--json", help="write the rows and the summary here")
    args = ap.parse_args(argv)
    rows, spreads, shifts = [], [], []
    for path in args.files:
        with open(path) as f:
            result = json.load(f)
        try:
            rows += lane_worst(result, path)
            spreads += seed_spread(result, path)
            shifts += likelihood_shift(result, path)
        except (KeyError, ValueError) as err:
            raise SystemExit(f"{path}: {err}") from None
    print(f"{'source':<50} {'lane':<10} {'worst policy':<18} {'true':>8} {'sim':>8} "
          f"{'MVD':>7} {'2nd':>6}")
    for r in rows:
        print(f"{r['source'][-50:]:<50} {r['lane']:<10} {r['policy']:<18} {r['true']:>8.0f} "
              f"{r['sim']:>8.0f} {r['mvd']:>7.0f} {r['second']:>6.0f}")
    s = summary(rows)
    print(f"{s['lanes']} lanes; worst policy: "
          + ", ".join(f"{p} {n}x" for p, n in s["worst_counts"])
          + f"; median MVD {s['median_mvd']:.0f}, median second-worst error "
          f"{s['median_second']:.0f}")
    for p, b in s["by_policy"].items():
        true = (f"{b['true_min']:.0f}" if b["true_min"] == b["true_max"]
                else f"{b['true_min']:.0f} .. {b['true_max']:.0f}")
        print(f"  {p}: true {true}, simulated {b['sim_min']:.0f} .. {b['sim_max']:.0f} over "
              f"the {b['n']} lanes it is worst in")
    if spreads:
        first = sum(x["worst_rank"] == 1 for x in spreads)
        top3 = sum(x["worst_rank"] <= 3 for x in spreads)
        print(f"the seeds' disagreement: the worst policy is the most disputed one in {first} "
              f"of {len(spreads)} (run, method) pairs, in the 3 most disputed in {top3}; "
              f"median Spearman of spread and error "
              f"{np.median([x['rho'] for x in spreads if x['rho'] is not None]):.2f}")
    if shifts:
        print("the move away from the likelihood model (|sim - sim_bc| / its median; no truth "
              "needed), per lane: the top policy and its score; the worst policy's score; MVD")
        for x in sorted(shifts, key=lambda x: -x["mvd"]):
            print(f"  {x['source'][-40:]:<40} {x['lane']:<12} top {x['top']:<18} "
                  f"{x['top_score']:>6.1f}  worst {x['worst']:<18} {x['worst_score']:>6.1f}  "
                  f"MVD {x['mvd']:.0f}")
    if args.json:
        from rl2s_jax._files import write_json
        write_json(args.json, {"command": "python experiments/worst_policy.py "
                               + " ".join(args.files), "rows": rows, "summary": s,
                               "seed_spread": spreads, "likelihood_shift": shifts})
    return 0


if __name__ == "__main__":
    sys.exit(main())
