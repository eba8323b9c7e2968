"""Which pairs of policies a simulator swaps, and what the swapped policies look like to the
simulator (issue 66, item 2; ``experiments/ranking_analysis.py`` prints it).

A swap of policies i, j is a discordant pair of the true values V and the simulated ones; it is
*within noise* when |V_i - V_j| < 2 sqrt(se_i^2 + se_j^2) (se: the truths' standard errors),
*real* otherwise. Each of the N = P (P - 1) / 2 pairs it swaps costs 2 / N of Kendall's tau.

A lane (one method, one seed) of a paper.py result may carry issue 64's trust report
(``lanes[<method>/<seed>]["trust"]``, ``paper.trust_phase.lane_trust``), per test policy:
``support`` (the ensemble's one-step disagreement over the policy's simulated visits, in units
of its mean over the training data: how far they leave the data), ``member_sd`` (the elites'
spread of its simulated value), ``sim_value`` (the value they spread around) and ``trusted``.
``trust_features`` reads them; ``carrier_ranks`` and ``worst_in_top`` ask whether they point
at the policies the ranking's loss hangs on. ``oracle_standard_errors``: the truths' SEs from
an oracle_check.py run of the same data seed (for results that predate ``true_value_se``);
``lanes_of``, ``compare_truths`` and ``relations``: the script's reading of lanes, of two data
seeds' truths and of where the real swaps fall. ``lineage_split``: the ranking of the policies
whose learner lineage the training data holds against the pairs touching the others
(``experiments/lineage_analysis.py``). Pure NumPy.
"""
from __future__ import annotations

import numpy as np

from rl2s_jax.evaluate.metrics import kendall_tau, spearman

TRUST_FIELDS = ("support", "member_sd", "sim_value", "trusted")


def discordant_pairs(truth: np.ndarray, sim: np.ndarray):
    """Every pair i < j of P policies (``np.triu_indices``) and whether the simulator orders it
    against the truth (a tie on either side is no swap). -> (i [N], j [N], discordant [N])."""
    i, j = np.triu_indices(truth.size, k=1)
    return i, j, np.sign(truth[i] - truth[j]) * np.sign(sim[i] - sim[j]) < 0


def swaps(truth, se, sim) -> dict:
    """The discordant pairs of one simulator: truth, se, sim [P]. -> {"pairs": N, "tau",
    "noise": [(i, j)] swaps within the truth's noise, "real": [(i, j)] the others,
    "tau_lost_noise", "tau_lost_real" (2 D / N each)}; i < j index the policies."""
    t, e, s = (np.asarray(x, np.float64) for x in (truth, se, sim))
    if not (t.shape == e.shape == s.shape and t.ndim == 1 and t.size >= 2):
        raise ValueError(f"truth, se, sim: expected equal shapes [P >= 2], got {t.shape}, "
                         f"{e.shape}, {s.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(s)) and np.all(e >= 0)):
        raise ValueError("truth, se, sim: expected finite values and se >= 0")
    i, j, discordant = discordant_pairs(t, s)
    within = np.abs(t[i] - t[j]) < 2.0 * np.sqrt(e[i] ** 2 + e[j] ** 2)
    n = i.size
    noise = [(int(a), int(b)) for a, b in zip(i[discordant & within], j[discordant & within],
                                              strict=True)]
    real = [(int(a), int(b)) for a, b in zip(i[discordant & ~within], j[discordant & ~within],
                                             strict=True)]
    return {"pairs": n, "tau": kendall_tau(t, s), "noise": noise, "real": real,
            "tau_lost_noise": 2.0 * len(noise) / n, "tau_lost_real": 2.0 * len(real) / n}


def lineage_split(truth, sim, seen) -> dict:
    """How a simulator ranks the policies whose learner lineage its training data holds
    (``seen``) against the pairs that touch the others. truth, sim [P], seen [P] bool.
    -> {"tau": over all, "tau_seen": over the seen policies alone (None below 2),
    "pairs_seen" / "pairs_touching": pair counts, "discordant_seen" / "discordant_touching":
    the discordant pairs among them, "swap_rate_seen" / "swap_rate_touching": their shares}."""
    t, s = np.asarray(truth, np.float64), np.asarray(sim, np.float64)
    m = np.asarray(seen, bool)
    if not (t.shape == s.shape == m.shape and t.ndim == 1 and t.size >= 2):
        raise ValueError(f"truth, sim, seen: expected equal shapes [P >= 2], got {t.shape}, "
                         f"{s.shape}, {m.shape}")
    i, j, discordant = discordant_pairs(t, s)
    both = m[i] & m[j]
    rate = lambda k, n: float(k / n) if n else None
    out = {"tau": kendall_tau(t, s),
           "tau_seen": kendall_tau(t[m], s[m]) if m.sum() >= 2 else None,
           "pairs_seen": int(both.sum()), "pairs_touching": int((~both).sum()),
           "discordant_seen": int((discordant & both).sum()),
           "discordant_touching": int((discordant & ~both).sum())}
    out["swap_rate_seen"] = rate(out["discordant_seen"], out["pairs_seen"])
    out["swap_rate_touching"] = rate(out["discordant_touching"], out["pairs_touching"])
    return out


def leave_one_out(truth, sims) -> np.ndarray:
    """Mean tau over the lanes [L, P] of sims without each policy in turn -> [P]."""
    t, s = np.asarray(truth, np.float64), np.asarray(sims, np.float64)
    keep = lambda i: np.arange(t.size) != i
    return np.array([np.mean([kendall_tau(t[keep(i)], lane[keep(i)]) for lane in s])
                     for i in range(t.size)])


def lane_trust(lane: dict, n_policies: int, where: str) -> dict | None:
    """One lane's trust fields as float arrays [P] (``trusted`` as 0 / 1), plus
    "relative_member_sd" = member_sd / max(|sim_value|, 1); None when the lane has no trust
    entry. ValueError naming ``where`` when a field is missing or not P finite numbers."""
    t = lane.get("trust")
    if not t:
        return None
    out = {}
    for k in TRUST_FIELDS:
        v = np.asarray(t.get(k, []), np.float64)
        if v.shape != (n_policies,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{where}.trust.{k}: expected {n_policies} finite values (one "
                             f"per test policy), got {t.get(k)!r:.80}")
        out[k] = v
    out["relative_member_sd"] = out["member_sd"] / np.maximum(np.abs(out["sim_value"]), 1.0)
    return out


def trust_features(lanes: list[dict], n_policies: int, method: str) -> dict | None:
    """Means over one method's lanes (dicts with "seed" and the lane's fields) of
    ``lane_trust``'s arrays -> {"support", "member_sd", "relative_member_sd", "trusted" (the
    share of lanes that trust each policy)} as lists [P]; None unless every lane has trust."""
    per = [lane_trust(ln, n_policies, f"lanes[{method}/{ln['seed']}]") for ln in lanes]
    if not per or any(p is None for p in per):
        return None
    return {k: np.mean([p[k] for p in per], 0).tolist()
            for k in ("support", "member_sd", "relative_member_sd", "trusted")}


def rank_desc(values) -> np.ndarray:
    """Each entry's rank by value, 1 = the largest; ties share the best rank (1 + the number
    of entries strictly larger). values [P] -> int [P]."""
    v = np.asarray(values, np.float64)
    return 1 + (v[None, :] > v[:, None]).sum(1)


def carrier_ranks(real_per_policy, features: dict) -> dict:
    """The policies carrying most real swaps (all tied at the maximum) and their ranks by each
    feature (1 = the largest): real_per_policy [P] counts, features name -> [P]. -> {"policies":
    [indices], "real_swaps": the maximum, "rank_by_<name>": [ranks of those policies]};
    "policies" is empty when no policy has a real swap."""
    r = np.asarray(real_per_policy)
    top = np.flatnonzero(r == r.max()).tolist() if r.max() > 0 else []
    out = {"policies": top, "real_swaps": int(r.max())}
    for name, v in features.items():
        out[f"rank_by_{name}"] = [int(rank_desc(v)[i]) for i in top]
    return out


def worst_in_top(lanes: list[dict], truth, n_policies: int, method: str) -> dict | None:
    """How often a lane's worst policy (largest |trust sim_value - truth|, the trust report's
    "worst") is its largest (top 1) or among its two largest (top 2) by member_sd, ties
    counted in favour (``rank_desc``). -> {"lanes", "top1", "top2", "worst": [index per
    lane]}; None unless every lane has trust."""
    t = np.asarray(truth, np.float64)
    per = [lane_trust(ln, n_policies, f"lanes[{method}/{ln['seed']}]") for ln in lanes]
    if not per or any(p is None for p in per):
        return None
    worst = [int(np.argmax(np.abs(p["sim_value"] - t))) for p in per]
    ranks = [int(rank_desc(p["member_sd"])[w]) for p, w in zip(per, worst, strict=True)]
    return {"lanes": len(per), "top1": sum(k <= 1 for k in ranks),
            "top2": sum(k <= 2 for k in ranks), "worst": worst}


def _oracle_truth_episodes(oracle: dict, where: str) -> int:
    """The truth episodes of an oracle_check.py run: its rows' noise_ceiling n_truth, else its
    command's --value-episodes (oracle_check.py's default 16 when absent)."""
    for row in oracle.get("rows") or []:
        if (row.get("noise_ceiling") or {}).get("n_truth"):
            return int(row["noise_ceiling"]["n_truth"])
    words = " ".join(str(oracle.get("command", "")).split("=")).split()
    if "--value-episodes" not in words:
        return 16
    try:
        return int(words[words.index("--value-episodes") + 1])
    except (IndexError, ValueError):
        raise ValueError(f"{where}: command: expected --value-episodes N, got "
                         f"{oracle.get('command')!r}") from None


def _check_agree(where: str, field: str, names, theirs, ours, se) -> float:
    """max |z| of two measurements of the truths; ValueError (naming the first policy) beyond
    4 combined SEs (+1e-3 for round-off)."""
    gap = np.abs(np.asarray(theirs, np.float64) - np.asarray(ours, np.float64))
    bad = np.flatnonzero(gap > 4.0 * se + 1e-3)
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{where}: {field}: {len(bad)} policies differ from the result's by "
                         f"more than 4 combined SEs (first {names[i]}: {theirs[i]:.1f} vs "
                         f"{ours[i]:.1f}, SE {se[i]:.1f}): another measurement of the truth "
                         f"(another GPU or collection?), so its SEs are not these truths'")
    return float(np.max(np.where(se > 0, gap / np.maximum(se, 1e-12), 0.0)))


def oracle_standard_errors(result: dict, oracle: dict, data_seed: int, where: str):
    """The SEs [P] of a paper.py result's true values from an oracle_check.py --data-seed run
    (``oracle``, read from ``where``) of the same task, data seed and test policies: its
    ``true_value_se`` (the discounted value's: ``ds.value_discounted_se``) in the result's
    policy order, scaled to the result's truth episodes (x sqrt(n_oracle / n_result)).
    -> (se [P], {"n_oracle", "n_truth", "max_abs_z"}). ValueError naming ``where`` and the
    field, before any work, when the task, data seed or policy names differ or the truths
    disagree: the discounted (rows' ``true_value``) and undiscounted values, each within 4
    combined SEs (the undiscounted SE taken as se x |V undiscounted| / |V|, at least se)."""
    if oracle.get("task") != result.get("task"):
        raise ValueError(f"{where}: task: expected {result.get('task')!r} (the result's), got "
                         f"{oracle.get('task')!r}")
    if oracle.get("data_seed") != data_seed:
        raise ValueError(f"{where}: data_seed: expected {data_seed} (the result's), got "
                         f"{oracle.get('data_seed')!r}")
    names, theirs = list(result["test_policy_names"]), list(oracle.get("policy_names") or [])
    if sorted(names) != sorted(theirs) or len(set(theirs)) != len(theirs):
        raise ValueError(f"{where}: policy_names: expected the result's {len(names)} test "
                         f"policies; missing {sorted(set(names) - set(theirs))}, extra "
                         f"{sorted(set(theirs) - set(names))}, {len(theirs)} names")
    order = [theirs.index(n) for n in names]
    P = len(names)

    def field(k, values):
        v = np.asarray(values if values is not None else [], np.float64)
        if v.shape != (P,) or not np.all(np.isfinite(v)) or (k == "true_value_se"
                                                               and np.any(v < 0)):
            raise ValueError(f"{where}: {k}: expected {P} finite values (SEs >= 0), got "
                             f"{values!r:.80}")
        return v[order]

    n_oracle, n_truth = _oracle_truth_episodes(oracle, where), int(
        result["sizes"]["value_episodes"])
    se = field("true_value_se", oracle.get("true_value_se")) * np.sqrt(n_oracle / n_truth)
    both = np.sqrt(se ** 2 * (1.0 + n_truth / n_oracle))  # the oracle's SE and the result's
    v, u = np.asarray(result["true_value"]), np.asarray(result["true_value_undiscounted"])
    z = [_check_agree(where, f"rows[{k}].true_value", names,
                      field(f"rows[{k}].true_value", row.get("true_value")), v, both)
         for k, row in enumerate(oracle.get("rows") or []) if "true_value" in row]
    ratio = np.maximum(np.abs(u) / np.maximum(np.abs(v), 1e-9), 1.0)
    z.append(_check_agree(where, "true_value_undiscounted", names, field(
        "true_value_undiscounted", oracle.get("true_value_undiscounted")), u, both * ratio))
    return se, {"n_oracle": n_oracle, "n_truth": n_truth, "max_abs_z": max(z)}


def compare_truths(a: dict, b: dict) -> dict | None:
    """Two data seeds' truths of the same policies: the z of their differences (RMS ~1 when
    the SEs are right) and the tau of one truth against the other. None: other policies."""
    if a["policies"] != b["policies"]:
        return None
    va, vb = np.asarray(a["true_value"]), np.asarray(b["true_value"])
    z = (va - vb) / np.sqrt(np.asarray(a["se"]) ** 2 + np.asarray(b["se"]) ** 2)
    return {"data_seeds": [a["data_seed"], b["data_seed"]], "rms_z": float(np.sqrt(np.mean(
        z ** 2))), "max_abs_z": float(np.max(np.abs(z))), "tau_truth_vs_truth": kendall_tau(
        va, vb)}


def relations(a: dict) -> dict:
    """Where the real swaps fall, per policy (summed over methods and seeds), against the
    simulators' relative value error |sim - V| / max(|V|, 1), their episode-length error
    |sim length - true length| and, where recorded, their support and (from the lanes' trust)
    member_sd and relative member_sd, each the mean over the methods of their means over lanes,
    and the true value itself (a control): Spearman rank correlations (``metrics.spearman``;
    None where a feature is missing or constant)."""
    real = np.asarray(a["real_swaps_per_policy"], np.float64)
    truth = np.asarray(a["true_value"])
    feats = {}
    sims = np.concatenate([np.asarray(m["sim_value"]) for m in a["methods"].values()])
    feats["relative value error"] = np.mean(np.abs(sims - truth), 0) / np.maximum(
        np.abs(truth), 1.0)
    lens = [m["sim_length"] for m in a["methods"].values() if m["sim_length"] is not None]
    if lens and a.get("true_length") is not None:
        feats["episode length error"] = np.abs(np.mean(lens, 0) - np.asarray(a["true_length"]))
    sup = [m["support"] for m in a["methods"].values() if m["support"] is not None]
    if sup:
        feats["support"] = np.mean(sup, 0)
    trust = [m["trust"] for m in a["methods"].values() if m["trust"] is not None]
    for k in ("member_sd", "relative_member_sd") if trust else ():
        feats[k.replace("_", " ")] = np.mean([t[k] for t in trust], 0)
    feats["truth SE / value"] = np.asarray(a["se"]) / np.maximum(np.abs(truth), 1.0)
    feats["true value"] = truth  # a control: swaps and member_sd may both follow the value
    out = {}
    for k, v in feats.items():
        ok = np.ptp(real) > 0 and np.ptp(v) > 0
        out[k] = spearman(real, v) if ok else None
    return out


def lanes_of(results: list[dict], methods) -> dict[str, list[dict]]:
    """method -> its lanes (dicts with "seed", "sim_value", ...) from the first result that has
    the method, in seed order."""
    out = {}
    for m in methods:
        for r in results:
            lanes = [dict(v, seed=int(k.split("/")[1])) for k, v in r.get("lanes", {}).items()
                     if k.split("/")[0] == m and v.get("sim_value") is not None]
            if lanes:
                out[m] = sorted(lanes, key=lambda x: x["seed"])
                break
    return out
