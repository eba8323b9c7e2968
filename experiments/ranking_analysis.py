"""Why a task's ranking falls, policy by policy (issue 66, item 2): for one task and one or more
paper.py results (data seeds), per test policy its true value with its standard error and its
simulated value per method and seed; which pairs of policies each simulator swaps (discordant
pairs) and whether each swap lies within the truth's own noise; the share of the tau lost to
within-noise swaps against real ones; the swaps against the simulated episode lengths
(termination) and, where a lane records it, a per-policy ``support``; where a lane carries issue
64's trust report (``lanes[<method>/<seed>]["trust"]``: support, member_sd, sim_value, trusted;
``rl2s_jax.evaluate.ranking_swaps``), their means over a method's lanes per policy, their
Spearman correlation with the real swaps per policy, the rank (1 = largest) by member_sd,
relative member_sd (member_sd / max(|trust sim_value|, 1)) and support of the policy carrying
most of a method's real swaps, and how often a lane's worst-|error| policy (the trust report's
"worst": largest |trust sim_value - V|) has the lane's largest / two largest member_sd.

    python experiments/ranking_analysis.py RESULT.json [RESULT.json ...] [--methods rl2s,gail]
        [--json OUT.json] [--n-rep 2000] [--truth-se ORACLE.json ...]

Results of one data seed (``data_seed`` or the command's --data-seed) are read together (a
method's lanes from the first file that has them, e.g. the adversarial and mle runs); each data
seed is analysed on its own, and two or more on the same test policies are compared (their
truths are independent measurements).

A swap of policies i, j is *within noise* when |V_i - V_j| < 2 sqrt(se_i^2 + se_j^2) (V: the
true values, se: their standard errors); every other discordant pair is a *real* swap. With P
policies and N = P (P - 1) / 2 pairs, tau = (C - D) / N (``metrics.kendall_tau``), so a swap
costs 2 / N: tau lost = 2 D / N = 2 D_noise / N + 2 D_real / N.

The standard errors: the result's ``true_value_se`` (paper.py writes it since issue 66); older
results have none, and then the zoo's: its ``return_se`` (16 episodes of the undiscounted return,
``zoo.info["value_episodes"]``) scaled to the result's ``value_episodes`` (x sqrt(16 / n)) and
to the discounted value (x |V| / |V undiscounted|, at most 1), a proxy, for a result on the
shipped zoo or on a zoo whose returns of these policies agree with the result's undiscounted
truth within 6 SE (a zoo grown by ``--extend`` keeps its policies). With two data seeds the
spread of the truth between them checks the SEs: z = (V_a - V_b) / sqrt(se_a^2 + se_b^2) has
RMS about 1 when they are right. --truth-se ORACLE.json (one per data seed, matched by its
``data_seed``): the SEs of an oracle_check.py --data-seed run of the same task, data seed and
test policies instead (``ranking_swaps.oracle_standard_errors``: its ``true_value_se`` is the
discounted value's; refused, naming the file and field, when its truths disagree with the
result's); its tau (the row of the longest horizon with the most episodes, as merge_results.py
takes it) is printed beside the methods' with issue 66's bar, RL2S's tau - the oracle's, and
its own swaps (its ``oracle_value`` as one lane, same truth and SEs). ``tau_without``: the
mean tau over a method's lanes without each policy in turn (which policy the loss hangs on).
``noise ceiling``: ``metrics.noise_ceiling`` with these SEs on both sides (the simulated side's
episodes the result's ``eval_episodes``, its per-episode spread assumed the truth's): the tau an
exact simulator would be measured at.

Needs no GPU: the numbers come from the JSONs (``lanes[<method>/<seed>]["sim_value"]``,
``true_value``, ``true_length``, ``lanes[...]["sim_length"]``, ``lanes[...]["trust"]``). --json
adds, per method, "trust" (the means above), "most_real_swaps" (``carrier_ranks``) and
"worst_in_top" (None without trust), and per data seed "relations" (the Spearman correlations)
and "oracle" (None without --truth-se).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from rl2s_jax._files import write_json  # noqa: E402
from rl2s_jax.evaluate.metrics import noise_ceiling  # noqa: E402
from rl2s_jax.evaluate.ranking_swaps import (  # noqa: E402
    carrier_ranks,
    compare_truths,
    lanes_of,
    leave_one_out,
    oracle_standard_errors,
    relations,
    swaps,
    trust_features,
    worst_in_top,
)
from rl2s_jax.paper.data_seeds import (  # noqa: E402
    ORACLE_MARGIN,
    ORACLE_MARGIN_DEFAULT,
    data_seed_of,
    group_by_data_seed,
    oracle_row,
)

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def zoo_se(result: dict) -> np.ndarray:
    """The proxy SEs [P] of the result's true values from the shipped zoo (module docstring).
    ValueError when the result was measured on another zoo or names an unknown policy."""
    from rl2s_jax.zoo.zoo import load_zoo  # local: loads the zoo only for results without SEs

    task = result["task"]
    with open(os.path.join(ROOT, "rl2s_jax", "zoo", "shipped", task, "zoo.npz"), "rb") as f:
        sha = hashlib.sha256(f.read()).hexdigest()
    zoo = load_zoo(task)
    every = list(range(len(zoo.returns)))
    ids = dict(zip(zoo.policy_names(every), every, strict=True))
    names = result["test_policy_names"]
    missing = [n for n in names if n not in ids]
    if missing:
        raise ValueError(f"test_policy_names: not in the shipped zoo: {missing}")
    rows = [ids[n] for n in names]
    n_zoo = int((zoo.info or {}).get("value_episodes") or 16)
    n_truth = int(result["sizes"]["value_episodes"])
    v, u = np.asarray(result["true_value"]), np.asarray(result["true_value_undiscounted"])
    zse = np.asarray(zoo.return_se)[rows]
    if result.get("zoo_sha256") != sha and np.any(  # a grown zoo keeps its policies: check
            np.abs(np.asarray(zoo.returns)[rows] - u) > 6.0 * zse * np.sqrt(1 + n_zoo / n_truth)
            + 1.0):
        raise ValueError(f"zoo_sha256: the result has no true_value_se and was measured on "
                         f"zoo {result.get('zoo_sha256')}, whose policies' returns differ from "
                         f"the shipped zoo's ({sha[:12]})")
    ratio = np.where(np.abs(u) > 1e-9, np.abs(v) / np.maximum(np.abs(u), 1e-9), 1.0)
    return zse * np.sqrt(n_zoo / n_truth) * np.minimum(ratio, 1.0)


def standard_errors(result: dict, oracle: dict | None = None,
                    where: str = "") -> tuple[np.ndarray, str]:
    """(se [P], where it came from): an oracle run's (read from ``where``) where given, else
    the result's true_value_se, else the zoo's proxy."""
    if oracle is not None:
        se, how = oracle_standard_errors(result, oracle, data_seed_of(result), where)
        scaled = (f", scaled to {how['n_truth']}" if how["n_oracle"] != how["n_truth"] else "")
        return se, (f"the oracle's true_value_se ({where}; discounted, {how['n_oracle']} "
                    f"episodes{scaled}; its truths vs the result's: max |z| "
                    f"{how['max_abs_z']:.2f})")
    se = result.get("true_value_se")
    if se is not None:
        return np.asarray(se, np.float64), "true_value_se (the data's)"
    return zoo_se(result), "zoo return_se, scaled (a proxy)"


def method_analysis(method: str, ls: list[dict], truth, se) -> dict:
    """One method's lanes ``ls`` against the truth [P] and its SEs [P]: per lane its swaps,
    their means, swaps per policy, tau without each policy, mean simulated lengths, support
    (an older lane's own "support", else its trust's), the trust means (``trust_features``:
    None without trust), the ranks of the policies with most real swaps by support /
    member_sd / relative member_sd (``carrier_ranks``) and ``worst_in_top``."""
    P = truth.size
    rows, noise_count, real_count = [], np.zeros(P, int), np.zeros(P, int)
    for lane in ls:
        sw = swaps(truth, se, lane["sim_value"])
        for a, b in sw["noise"]:
            noise_count[[a, b]] += 1
        for a, b in sw["real"]:
            real_count[[a, b]] += 1
        rows.append({"seed": lane["seed"], "tau": sw["tau"], "noise": len(sw["noise"]),
                     "real": len(sw["real"]), "tau_lost_noise": sw["tau_lost_noise"],
                     "tau_lost_real": sw["tau_lost_real"], "real_pairs": sw["real"]})
    sims = np.array([lane["sim_value"] for lane in ls], np.float64)
    lengths = [lane.get("sim_length") for lane in ls]
    trust = trust_features(ls, P, method)
    support = (np.mean([lane["support"] for lane in ls], 0).tolist()
               if all("support" in lane for lane in ls) else trust and trust["support"])
    feats = {k: trust[k] for k in ("member_sd", "support", "relative_member_sd")} if trust \
        else {}
    return {
        "seeds": rows, "sim_value": sims.tolist(),
        "tau": float(np.mean([r["tau"] for r in rows])),
        "tau_lost_noise": float(np.mean([r["tau_lost_noise"] for r in rows])),
        "tau_lost_real": float(np.mean([r["tau_lost_real"] for r in rows])),
        "tau_without": leave_one_out(truth, sims).tolist(),
        "sim_length": (np.mean(np.array(lengths, np.float64), 0).tolist()
                       if all(x is not None for x in lengths) else None),
        "support": support, "trust": trust,
        "noise_swaps_per_policy": noise_count.tolist(),
        "real_swaps_per_policy": real_count.tolist(),
        "most_real_swaps": carrier_ranks(real_count, feats) if trust else None,
        "worst_in_top": worst_in_top(ls, truth, P, method)}


def oracle_entry(oracle: dict, where: str, a: dict, se) -> dict:
    """The oracle's tau (its row of the longest horizon with the most episodes), its noise
    ceiling, issue 66's bar (RL2S's tau - the oracle's, against the task's margin) and, where
    the row has its ``oracle_value``, its own swaps as one lane (``method_analysis``: tau
    lost within noise / to real swaps, tau without each policy) against the same truth."""
    row = oracle_row(oracle)
    tau, margin = float(row["metrics"]["kendall_tau"]), ORACLE_MARGIN.get(
        a["task"], ORACLE_MARGIN_DEFAULT)
    rl2s = a["methods"].get("rl2s")
    own = None
    if row.get("oracle_value") is not None:
        order = [list(oracle["policy_names"]).index(n) for n in a["policies"]]
        lane = {"seed": 0, "sim_value": np.asarray(row["oracle_value"])[order].tolist()}
        own = {k: v for k, v in method_analysis("oracle", [lane], np.asarray(
            a["true_value"]), se).items() if k.startswith("tau")}
    return {"file": where, "kendall_tau": tau, "horizon": row["horizon"],
            "n_episodes": row["n_episodes"], "margin": margin, "own": own,
            "rl2s_minus_oracle": None if rl2s is None else rl2s["tau"] - tau,
            "noise_ceiling": (row.get("noise_ceiling") or {}).get("kendall_tau")}


def analyse_seed(results: list[dict], methods=METHODS, n_rep: int = 2000,
                 oracle: dict | None = None, oracle_path: str = "") -> dict:
    """One data seed's analysis (results: its paper.py JSONs; oracle: its oracle_check.py
    run, read from oracle_path; module docstring)."""
    first = results[0]
    for r in results[1:]:
        if r.get("test_policy_names") != first.get("test_policy_names"):
            raise ValueError("test_policy_names: the results of one data seed differ")
    truth = np.asarray(first["true_value"], np.float64)
    se, source = standard_errors(first, oracle, oracle_path)
    names = list(first["test_policy_names"])
    lanes = lanes_of(results, methods)
    if not lanes:
        raise ValueError(f"lanes: no lane of {', '.join(methods)} with sim_value")
    n_sim = int(first["sizes"]["eval_episodes"])
    n_truth = int(first["sizes"]["value_episodes"])
    ceiling = noise_ceiling(truth, se * np.sqrt(n_truth), n_truth=n_truth, n_sim=n_sim,
                            n_rep=n_rep)["kendall_tau"]
    per_method = {m: method_analysis(m, ls, truth, se) for m, ls in lanes.items()}
    noise_count = np.sum([r["noise_swaps_per_policy"] for r in per_method.values()], 0)
    real_count = np.sum([r["real_swaps_per_policy"] for r in per_method.values()], 0)
    P = truth.size
    a = {"data_seed": data_seed_of(first), "task": first.get("task"), "policies": names,
            "true_value": truth.tolist(), "se": se.tolist(), "se_source": source,
            "true_length": first.get("true_length"), "n_truth": n_truth, "n_sim": n_sim,
            "pairs": P * (P - 1) // 2, "noise_ceiling": ceiling, "methods": per_method,
            "noise_swaps_per_policy": noise_count.tolist(),
            "real_swaps_per_policy": real_count.tolist(),
            "commands": [r.get("command") for r in results]}
    a["oracle"] = oracle and oracle_entry(oracle, oracle_path, a, se)
    return a


def report(a: dict) -> str:
    """The printed analysis of one data seed."""
    nc, ms = a["noise_ceiling"], a["methods"]
    lines = [f"{a['task']}, data seed {a['data_seed']}: {len(a['policies'])} test policies "
             f"({a['pairs']} pairs); truth from {a['n_truth']} episodes (SE: {a['se_source']}),"
             f" simulated from {a['n_sim']}",
             f"  noise ceiling (an exact simulator at these SEs): tau {nc['mean']:.3f} "
             f"[{nc['lo']:.3f}, {nc['hi']:.3f}]",
             *oracle_lines(a),
             "  method   seeds  tau    lost: within-noise swaps / real swaps (mean over seeds)"]
    for m, r in ms.items():
        best = int(np.argmax(r["tau_without"]))
        lines.append(f"  {m:<8} {len(r['seeds']):>5}  {r['tau']:.3f}  {r['tau_lost_noise']:.3f}"
                     f" / {r['tau_lost_real']:.3f}   without {a['policies'][best]}: tau "
                     f"{r['tau_without'][best]:.3f}")
    lines += [carrier_line(a, m, r) for m, r in ms.items()]
    head = "  ".join(f"{m:>7}" for m in ms)
    tm = next((m for m, r in ms.items() if r["trust"]), None)
    lines += ["", f"  {'policy':<16} {'true':>7} {'se':>5}  {head}  {'len true/sim':>13}  "
              "swaps noise/real" + (f"  {tm}'s trust: support member_sd relative trusted"
                                    if tm else "")]
    order = np.argsort(a["true_value"])
    rl2s_len = next((r["sim_length"] for r in ms.values() if r["sim_length"]), None)
    for i in order:
        sims = "  ".join(f"{np.mean(np.asarray(r['sim_value'])[:, i]):>7.0f}" for r in ms.values())
        tl = a["true_length"][i] if a.get("true_length") else float("nan")
        sl = rl2s_len[i] if rl2s_len else float("nan")
        t = ms[tm]["trust"] if tm else None
        lines.append(f"  {a['policies'][i]:<16} {a['true_value'][i]:>7.0f} {a['se'][i]:>5.0f}  "
                     f"{sims}  {tl:>6.0f}/{sl:<6.0f}  {a['noise_swaps_per_policy'][i]:>5}/"
                     f"{a['real_swaps_per_policy'][i]:<4}" + (
                         f"  {t['support'][i]:>21.2f} {t['member_sd'][i]:>9.1f} "
                         f"{t['relative_member_sd'][i]:>8.3f} {t['trusted'][i]:>7.2f}" if t
                         else ""))
    pairs: dict = {}
    for r in ms.values():
        for s in r["seeds"]:
            for p in s["real_pairs"]:
                pairs[tuple(p)] = pairs.get(tuple(p), 0) + 1
    lanes = sum(len(r["seeds"]) for r in ms.values())
    top = sorted(pairs.items(), key=lambda kv: -kv[1])[:8]
    lines += ["", f"  real swaps most often (of {lanes} lanes): " + ", ".join(
        f"{a['policies'][i]}-{a['policies'][j]} {n}" for (i, j), n in top)]
    rel = relations(a)
    lines.append("  Spearman of real swaps per policy with: " + ", ".join(
        f"{k} {'n/a' if v is None else format(v, '+.2f')}" for k, v in rel.items()))
    return "\n".join(lines + coverage_lines(a))


def oracle_lines(a: dict) -> list[str]:
    """The oracle's tau, its noise ceiling and the bar (RL2S - oracle), where given."""
    o = a.get("oracle")
    if not o:
        return []
    nc, gap = o["noise_ceiling"], o["rl2s_minus_oracle"]
    bar = ("no rl2s lanes" if gap is None else f"RL2S - oracle {gap:+.3f}: "
           f"{'met' if gap >= -o['margin'] else 'MISSED'} (bar -{o['margin']:.2f})")
    own = o["own"] and (f"; its own swaps cost {o['own']['tau_lost_noise']:.3f} within noise"
                        f" / {o['own']['tau_lost_real']:.3f} real")
    return [f"  oracle (the real dynamics through the same evaluation, {o['n_episodes']} "
            f"episodes; {o['file']}): tau {o['kendall_tau']:.3f}" + (
                f", its noise ceiling {nc['mean']:.3f} [{nc['lo']:.3f}, {nc['hi']:.3f}]"
                if nc else "") + f"{own or ''}; {bar}"]


def carrier_line(a: dict, m: str, r: dict) -> str:
    """A method's policies with most real swaps over its lanes (up to 3) and its tau (and the
    oracle's, where known) without the first of them."""
    real = np.asarray(r["real_swaps_per_policy"])
    top = [int(i) for i in np.argsort(-real, kind="stable")[:3] if real[i] > 0]
    if not top:
        return f"  {m:<8} no real swaps"
    own = (a.get("oracle") or {}).get("own")
    return (f"  {m:<8} real swaps in {int(real.sum()) // 2} pairs over its lanes, most with "
            + ", ".join(f"{a['policies'][i]} {real[i]}" for i in top)
            + f"; without {a['policies'][top[0]]}: tau {r['tau_without'][top[0]]:.3f}"
            + (f" (the oracle's {own['tau_without'][top[0]]:.3f})" if own else ""))


def coverage_lines(a: dict) -> list[str]:
    """Per method with trust: the policies with most real swaps and their ranks (1 = largest,
    of P) by member_sd, relative member_sd and support; how often a lane's worst-|error|
    policy has the lane's largest / second-largest member_sd."""
    P, out = len(a["policies"]), []
    for m, r in a["methods"].items():
        c, w = r["most_real_swaps"], r["worst_in_top"]
        if c is None:
            continue
        who = ", ".join(
            f"{a['policies'][i]} (rank by member_sd {c['rank_by_member_sd'][k]}, relative "
            f"{c['rank_by_relative_member_sd'][k]}, support {c['rank_by_support'][k]} of {P})"
            for k, i in enumerate(c["policies"])) or "none"
        out.append(f"  {m}: most real swaps ({c['real_swaps']} over its lanes): {who}; the "
                   f"worst-|error| policy has the largest member_sd in {w['top1']} of "
                   f"{w['lanes']} lanes, one of the two largest in {w['top2']}")
    return [""] + out if out else []


def read_oracles(paths: list[str], data_seeds: list[int]) -> dict[int, tuple[dict, str]]:
    """data seed -> (oracle_check.py output, its path), one per data seed of the results."""
    out: dict[int, tuple[dict, str]] = {}
    for p in paths:
        with open(p) as f:
            orc = json.load(f)
        d = orc.get("data_seed")
        if d not in data_seeds or d in out:
            raise ValueError(f"{p}: data_seed: expected one of the results' data seeds "
                             f"{data_seeds}, once each (an oracle_check.py --data-seed run), "
                             f"got {d!r}")
        out[d] = (orc, p)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", nargs="+", help="paper.py <task>.json files of one task")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--n-rep", type=int, default=2000, help="noise ceiling replicates")
    ap.add_argument("--json", help="also write the analysis here")
    ap.add_argument("--truth-se", action="append", default=[], metavar="ORACLE_JSON",
                    help="the truths' SEs from this oracle_check.py --data-seed run (one per "
                    "data seed)")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods or set(methods) - set(METHODS):
        raise SystemExit(f"methods: expected a comma list of {', '.join(METHODS)}, got "
                         f"{args.methods!r}")
    results = []
    for p in args.results:
        with open(p) as f:
            results.append(json.load(f))
    try:
        groups = group_by_data_seed(results)
        oracles = read_oracles(args.truth_se, list(groups))
        seeds = {d: analyse_seed(rs, methods, args.n_rep, *oracles.get(d, (None, "")))
                 for d, rs in groups.items()}
    except ValueError as err:
        raise SystemExit(str(err)) from None
    out = {"data_seeds": seeds, "truth_between_data_seeds": []}
    for d in seeds.values():
        d["relations"] = relations(d)
        print(report(d) + "\n")
    keys = list(seeds)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            c = compare_truths(seeds[a], seeds[b])
            if c:
                out["truth_between_data_seeds"].append(c)
                print(f"truth, data seed {a} vs {b}: RMS z {c['rms_z']:.2f} (max |z| "
                      f"{c['max_abs_z']:.2f}; ~1 when the SEs are right), tau of one truth "
                      f"against the other {c['tau_truth_vs_truth']:.3f}")
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
