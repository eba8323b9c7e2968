"""Policy-evaluation metrics: how well simulated policy values match the true ones.

Pure NumPy, host-side. Every function takes two 1-D arrays over the same P policies,
``true_values`` (returns measured in the real environment) and ``sim_values`` (returns the
learned simulator predicts), and returns Python floats (``value_differences`` also returns the
per-policy array); intervals over seeds are ``rl2s_jax.stats``'. Bad input raises
``ValueError`` naming the offending argument.

Ties. Values are compared exactly (no tolerance). Where a metric needs an ordering of the
policies by simulated value (nDCG@k, regret@k), policies with equal simulated values are
ordered uniformly at random and the metric is its *expectation* over those orderings, computed
in closed form. This makes every metric independent of the order the policies are listed in,
and gives a simulator that cannot tell policies apart the score of a random ranking.
"""
from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

__all__ = [
    "kendall_tau",
    "ndcg_at_k",
    "ranking_metrics",
    "regret_at_k",
    "spearman",
    "value_differences",
]


# ----------------------------------------------------------------------------- validation


def _as_values(x, name: str) -> np.ndarray:
    """``x`` as a finite float64 [P] array with P >= 1, else ValueError naming ``name``."""
    try:
        arr = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a 1-D array of numbers: {e}") from None
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D (one value per policy), got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} must contain at least 1 policy, got 0")
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(f"{name} must be finite; non-finite at policy index(es) "
                         f"{idx[:10].tolist()}{' ...' if idx.size > 10 else ''}")
    return arr


def _pair(true_values, sim_values, min_policies: int = 1) -> tuple[np.ndarray, np.ndarray]:
    t = _as_values(true_values, "true_values")
    s = _as_values(sim_values, "sim_values")
    if t.shape != s.shape:
        raise ValueError(f"true_values and sim_values must have the same length, got "
                         f"{t.size} (true_values) and {s.size} (sim_values)")
    if t.size < min_policies:
        raise ValueError(f"true_values and sim_values must cover at least {min_policies} "
                         f"policies for a ranking metric, got {t.size}")
    return t, s


def _as_k(k, name: str = "k") -> int:
    if isinstance(k, bool) or not isinstance(k, int | np.integer):
        raise ValueError(f"{name} must be an integer >= 1, got {k!r}")
    if k < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {int(k)}")
    return int(k)


def _tie_groups(sorted_vals: np.ndarray) -> np.ndarray:
    """Start index of each run of equal values in an already sorted [P] array."""
    return np.flatnonzero(np.r_[True, sorted_vals[1:] != sorted_vals[:-1]])


# ----------------------------------------------------------------------------- metrics


def value_differences(true_values, sim_values) -> dict:
    """Absolute value differences.

    true_values, sim_values: [P].  -> {"vd": [P] |true - sim| per policy,
    "avd": mean(vd) (float), "mvd": max(vd) (float)}.
    """
    t, s = _pair(true_values, sim_values)
    vd = np.abs(t - s)
    return {"vd": vd, "avd": float(vd.mean()), "mvd": float(vd.max())}


def kendall_tau(true_values, sim_values) -> float:
    """Kendall rank correlation, RL2S paper eq. 17 (tau-a).

    true_values, sim_values: [P], P >= 2.  Over all P(P-1)/2 pairs i < j, a pair is concordant
    when sign(true_i - true_j) == sign(sim_i - sim_j) != 0 and discordant when the two signs are
    opposite and non-zero; a pair tied in either array counts as neither.
    -> (concordant - discordant) / (P(P-1)/2), in [-1, 1]. Equal to scipy's tau-b when there
    are no ties; with ties it is smaller in magnitude (ties stay in the denominator), and it
    is 0.0 when either array is constant.
    """
    t, s = _pair(true_values, sim_values, min_policies=2)
    p = t.size
    i, j = np.triu_indices(p, k=1)
    agree = np.sign(t[i] - t[j]) * np.sign(s[i] - s[j])  # +1 concordant, -1 discordant, 0 tie
    return float(agree.sum() / (p * (p - 1) / 2))


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """1-based ascending ranks; tied values all get the mean of the ranks they span. -> [P]"""
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    first = np.cumsum(counts) - counts  # 0-based rank of each distinct value's first copy
    return (first + (counts + 1) / 2.0)[inverse]


def spearman(true_values, sim_values) -> float:
    """Spearman rank correlation.

    true_values, sim_values: [P], P >= 2.  -> Pearson correlation of the two arrays' average
    ranks (tied values share the mean of the ranks they span, as scipy.stats.spearmanr does),
    in [-1, 1]. Defined as 0.0 when either array is constant (its ranks have no variance;
    scipy returns nan there).
    """
    t, s = _pair(true_values, sim_values, min_policies=2)
    rt, rs = _average_ranks(t), _average_ranks(s)
    rt, rs = rt - rt.mean(), rs - rs.mean()
    denom = math.sqrt(float(rt @ rt) * float(rs @ rs))
    if denom == 0.0:
        return 0.0
    return float(np.clip(float(rt @ rs) / denom, -1.0, 1.0))


def ndcg_at_k(true_values, sim_values, k: int, gain: str = "linear") -> float:
    """Normalised discounted cumulative gain at k, RL2S paper eq. 18.

    true_values, sim_values: [P]; k: int >= 1, capped at P; gain: "linear" or "exp2".
    B_i = (true_i - min(true)) / (max(true) - min(true)) in [0, 1]; the gain rel_i is B_i itself
    ("linear") or the paper's 2^B_i - 1 ("exp2"; also in [0, 1]).
    DCG@k = sum_{r=1..k} rel_(r) / log2(r + 1), where (r) is the policy at rank r when sorted
    by sim_values descending; IDCG@k is the same sum with policies sorted by true_values
    descending. -> DCG@k / IDCG@k in [0, 1], 1 for a perfect top k.
    Policies tied in sim_values are taken in random order and DCG@k is its expectation: each
    policy of a tie group spanning ranks a..b gets the mean rel of the group at each of those
    ranks (the tie-averaged DCG, as sklearn.metrics.ndcg_score by default).
    Defined as 1.0 when all true values are equal (every ranking is then ideal).
    """
    t, s = _pair(true_values, sim_values)
    k = min(_as_k(k), t.size)
    lo, hi = t.min(), t.max()
    if gain not in ("linear", "exp2"):
        raise ValueError(f"gain must be 'linear' or 'exp2', got {gain!r}")
    if hi == lo:
        return 1.0
    rel = (t - lo) / (hi - lo)
    if gain == "exp2":
        rel = np.exp2(rel) - 1.0
    discount = np.zeros(t.size)
    discount[:k] = 1.0 / np.log2(np.arange(2, k + 2))

    order = np.argsort(-s, kind="stable")
    starts = _tie_groups(s[order])
    group_rel = np.add.reduceat(rel[order], starts) / np.diff(np.r_[starts, t.size])
    dcg = float(group_rel @ np.add.reduceat(discount, starts))
    idcg = float(np.sort(rel)[::-1] @ discount)  # > 0: the best policy has rel 1 at rank 1
    return min(dcg / idcg, 1.0)


def regret_at_k(true_values, sim_values, k: int) -> float:
    """Normalised regret@k, as in DOPE (Fu et al. 2021, "Benchmarks for Deep Off-Policy
    Evaluation").

    true_values, sim_values: [P]; k: int >= 1, capped at P.
    -> (max(true) - max of true over the top-k policies by sim_values) / (max(true) - min(true)),
    in [0, 1]; 0 is perfect (the truly best policy is among the simulator's top k).
    When policies tied in sim_values straddle the top-k cut-off, the ones admitted are drawn
    uniformly at random and the result is the expected regret. Defined as 0.0 when all true
    values are equal.
    """
    t, s = _pair(true_values, sim_values)
    k = min(_as_k(k), t.size)
    lo, hi = t.min(), t.max()
    if hi == lo:
        return 0.0
    cut = np.sort(s)[::-1][k - 1]  # k-th largest simulated value
    sure = s > cut  # certainly in the top k
    group = np.sort(t[s == cut])  # tied at the cut-off, ascending true value
    r = k - int(sure.sum())  # how many of the tied group get in, 1 <= r <= len(group)
    best_sure = t[sure].max() if sure.any() else -np.inf
    # The best of a uniform r-subset of g sorted values is group[j] with probability
    # C(j, r-1) / C(g, r), for j = r-1 .. g-1.
    g = group.size
    total = math.comb(g, r)
    expected_best = sum(math.comb(j, r - 1) / total * max(best_sure, float(group[j]))
                        for j in range(r - 1, g))
    return float(np.clip((hi - expected_best) / (hi - lo), 0.0, 1.0))


def ranking_metrics(true_values, sim_values, ks: Iterable[int] = (1, 3, 5, 10),
                    gain: str = "exp2") -> dict:
    """All the metrics at once.

    true_values, sim_values: [P], P >= 2; ks: ints >= 1 (each capped at P, the key keeps the
    k asked for); gain: nDCG's gain, by default the paper's 2^B - 1 (``ndcg_at_k``).
    -> {"kendall_tau", "spearman", "ndcg@k" and "regret@k" for each k in ks, "avd", "mvd"},
    all floats.
    """
    t, s = _pair(true_values, sim_values, min_policies=2)
    if isinstance(ks, str | bytes) or not isinstance(ks, Iterable):
        raise ValueError(f"ks must be an iterable of integers >= 1, got {ks!r}")
    ks = [_as_k(k, "ks entry") for k in ks]
    out = {"kendall_tau": kendall_tau(t, s), "spearman": spearman(t, s)}
    for k in ks:
        out[f"ndcg@{k}"] = ndcg_at_k(t, s, k, gain)
    for k in ks:
        out[f"regret@{k}"] = regret_at_k(t, s, k)
    vd = value_differences(t, s)
    out["avd"], out["mvd"] = vd["avd"], vd["mvd"]
    return out


# ----------------------------------------------------------------------------- intervals


def noise_ceiling(values, episode_sd, *, n_truth: int, n_sim: int, n_rep: int = 2000,
                  seed: int = 0, ks: Iterable[int] = (1,), level: float = 0.95,
                  truth_episode_sd=None) -> dict:
    """The ranking an EXACT simulator can be measured to reach when both sides are means of
    finitely many episodes: the ceiling that evaluation noise alone puts on tau and nDCG.

    values: [P] policy values; episode_sd: [P] (or a scalar) standard deviation of one
    episode's return; n_truth / n_sim: episodes behind each true / simulated value. Each of
    n_rep replicates draws truth = values + episode_sd / sqrt(n_truth) * z1 and sim = values +
    episode_sd / sqrt(n_sim) * z2 (Gaussian means) and scores ``ranking_metrics(truth, sim)``;
    truth_episode_sd ([P] or scalar) replaces episode_sd on the truth's side where the real
    episodes were measured apart (e.g. the Dataset's value SE x sqrt(value episodes)).
    -> {metric: {"mean", "lo", "hi"}} for kendall_tau, spearman, ndcg@k and regret@k.
    Unlike ``stats.bootstrap_intervals``' spread of tau around its own estimate, this is the bias
    the noise puts on tau: packed values with a large per-episode spread (Ant's falls) keep
    even the real dynamics below tau 1.
    """
    v = _as_values(values, "values")
    sd = np.broadcast_to(np.asarray(episode_sd, np.float64), v.shape)
    truth_sd = sd if truth_episode_sd is None else np.broadcast_to(
        np.asarray(truth_episode_sd, np.float64), v.shape)
    for name, x in (("episode_sd", sd), ("truth_episode_sd", truth_sd)):
        if not np.all(np.isfinite(x)) or (x < 0).any():
            raise ValueError(f"{name} must be finite and >= 0, [P = {v.size}] or a scalar")
    for name, n in (("n_truth", n_truth), ("n_sim", n_sim), ("n_rep", n_rep)):
        if not isinstance(n, int | np.integer) or n < 1:
            raise ValueError(f"{name} must be an int >= 1, got {n!r}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    rng = np.random.default_rng(seed)
    ks = tuple(ks)
    reps = []
    for _ in range(n_rep):
        truth = v + truth_sd / np.sqrt(n_truth) * rng.standard_normal(v.size)
        sim = v + sd / np.sqrt(n_sim) * rng.standard_normal(v.size)
        m = ranking_metrics(truth, sim, ks)
        reps.append({k: x for k, x in m.items() if k not in ("avd", "mvd")})
    q = (1.0 - level) / 2.0
    return {k: {"mean": float(np.mean(x)), "lo": float(np.quantile(x, q)),
                "hi": float(np.quantile(x, 1.0 - q))}
            for k, x in ((k, np.array([r[k] for r in reps])) for k in reps[0])}
