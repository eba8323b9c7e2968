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
at the policies the ranking's loss hangs on. Pure NumPy.
"""
from __future__ import annotations

import numpy as np

from rl2s_jax.evaluate.metrics import kendall_tau

TRUST_FIELDS = ("support", "member_sd", "sim_value", "trusted")


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
    i, j = np.triu_indices(t.size, k=1)
    discordant = np.sign(t[i] - t[j]) * np.sign(s[i] - s[j]) < 0
    within = np.abs(t[i] - t[j]) < 2.0 * np.sqrt(e[i] ** 2 + e[j] ** 2)
    n = i.size
    noise = [(int(a), int(b)) for a, b in zip(i[discordant & within], j[discordant & within],
                                              strict=True)]
    real = [(int(a), int(b)) for a, b in zip(i[discordant & ~within], j[discordant & ~within],
                                             strict=True)]
    return {"pairs": n, "tau": kendall_tau(t, s), "noise": noise, "real": real,
            "tau_lost_noise": 2.0 * len(noise) / n, "tau_lost_real": 2.0 * len(real) / n}


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
