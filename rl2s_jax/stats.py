"""The statistics every stage shares, NumPy (and SciPy's t quantile) only: intervals over seeds
(Student t), bootstrap intervals of a statistic, of a simulator's ranking scores over its
episodes and of the improvement of fine-tuned policies, the paired differences of two methods
(per policy, per seed, per candidate), and the rank tests of the cause tests (signed-rank by
sign flips, rank-sum). Bad input raises ``ValueError`` naming the argument."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.stats import t as student_t  # jax's own dependency

__all__ = [
    "bootstrap_ci",
    "bootstrap_intervals",
    "improvement_intervals",
    "mean_per_unit",
    "mean_or_none",
    "median_ci95",
    "paired_gain",
    "paired_gain_difference",
    "paired_seed_difference",
    "rank_sum_p",
    "sign_flip_p",
    "t_interval",
]


def t_interval(values, level: float = 0.95) -> tuple[float, float, float] | None:
    """The mean of ``values`` [N] (e.g. one paired difference per seed, each seed a draw of
    the whole pipeline) and its Student-t interval (N - 1 degrees of freedom):
    (mean, lo, hi), or None with fewer than 2 values. Non-finite values raise."""
    x = np.asarray(values, np.float64).ravel()
    if not np.all(np.isfinite(x)):
        raise ValueError(f"values: expected finite numbers, got {x.tolist()}")
    if not 0 < level < 1:
        raise ValueError(f"level: expected a probability in (0, 1), got {level!r}")
    if x.size < 2:
        return None
    mid = float(x.mean())
    half = float(student_t.ppf(0.5 + level / 2, x.size - 1)) * float(x.std(ddof=1)) / math.sqrt(
        x.size)
    return mid, mid - half, mid + half


def mean_or_none(values) -> float | None:
    """The mean of ``values`` as a float, or None where any of them is None (a quantity some
    run could not give, e.g. the width of an unbounded interval)."""
    v = list(values)
    return None if any(x is None for x in v) else float(np.mean(v))


def mean_per_unit(values) -> tuple[np.ndarray, list]:
    """[(unit, value)] -> (the mean value per unit [U], the units in first-seen order). A
    unit is e.g. a (data seed, seed): its reruns share data and seed, so they are averaged
    before any interval over units."""
    units: dict = {}
    for unit, v in values:
        units.setdefault(unit, []).append(v)
    return np.array([np.mean(v) for v in units.values()], np.float64), list(units)


def bootstrap_ci(x, statistic: Callable = np.mean, *, n_boot: int = 2000, seed: int = 0,
                 level: float = 0.95) -> list[float] | None:
    """Percentile bootstrap interval [lo, hi] of ``statistic`` (np.mean, np.median: called
    with ``axis=1``) of x [N]: n_boot resamples of x with replacement (rng ``seed``); None for
    an empty x."""
    x = np.asarray(x, np.float64).ravel()
    if not isinstance(n_boot, int) or n_boot < 2:
        raise ValueError(f"n_boot: expected an int >= 2, got {n_boot!r}")
    if not 0 < level < 1:
        raise ValueError(f"level: expected a probability in (0, 1), got {level!r}")
    if not x.size:
        return None
    reps = statistic(x[np.random.default_rng(seed).integers(0, x.size, (n_boot, x.size))],
                     axis=1)
    q = (1 - level) / 2
    return [float(np.quantile(reps, q)), float(np.quantile(reps, 1 - q))]


def median_ci95(x, n_boot: int = 2000, seed: int = 0) -> list[float]:
    """95% bootstrap interval [lo, hi] of the median of x [N] (gains: those of policies that
    start near 0 are ratios of thousands, so a mean would be theirs alone)."""
    return bootstrap_ci(x, np.median, n_boot=n_boot, seed=seed)


def paired_gain_difference(a: dict, b: dict, n_boot: int = 2000) -> dict | None:
    """Method A's real gain minus B's, paired: a, b {seed: [N] gains of the same N policies
    (e.g. those below the zoo's top quartile)}, over the seeds both have (None without one).
    -> {"median", "ci95" (``median_ci95``), "rl2s_higher" (A gained more), "pairs" (seed,
    policy), "seeds", "over_seeds": {"per_seed": the difference of the two medians on each seed
    (``median_gain`` of one seed), "mean", "t95" (``t_interval``; None with one seed)}}.
    """
    common = sorted(set(a) & set(b))
    if not common:
        return None
    if any(np.shape(a[k]) != np.shape(b[k]) for k in common):
        raise ValueError(f"a, b: expected the same policies per seed, got shapes "
                         f"{[(np.shape(a[k]), np.shape(b[k])) for k in common]}")
    d = np.concatenate([np.asarray(a[k], np.float64) - b[k] for k in common])
    by_seed = [float(np.median(a[k]) - np.median(b[k])) for k in common]
    t = t_interval(by_seed)
    return {"median": float(np.median(d)), "ci95": median_ci95(d, n_boot),
            "rl2s_higher": int((d > 0).sum()), "pairs": int(d.size), "seeds": common,
            "over_seeds": {"per_seed": by_seed, "mean": None if t is None else t[0],
                           "t95": None if t is None else list(t[1:])}}


def paired_seed_difference(a, b) -> tuple[float, float, float, int, int] | None:
    """A's value minus B's, seed by seed: a, b [S] one value per seed (None where that seed
    did not run). -> (mean, lo, hi, seeds where A is lower, seeds both ran) with the 95%
    ``t_interval`` over the seeds both ran; None when a and b differ in length or fewer than
    two seeds have both."""
    if len(a) != len(b):
        return None
    diffs = [x - y for x, y in zip(a, b, strict=True) if x is not None and y is not None]
    t = t_interval(diffs)
    return None if t is None else (*t, sum(d < 0 for d in diffs), len(diffs))


def paired_gain(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error of candidate k's paired gain over candidate 0, from episode
    returns r [K + 1, P, E] (episode e of every candidate from the same start and noise).
    -> ([K, P], [K, P])."""
    gain = r[1:] - r[:1]
    return gain.mean(-1), gain.std(-1, ddof=1) / np.sqrt(r.shape[2])


def _finite_1d(x, name: str) -> np.ndarray:
    """``x`` as a finite float64 [P] array with P >= 1, else ValueError naming ``name``."""
    try:
        arr = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a 1-D array of numbers: {e}") from None
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be 1-D with at least 1 value, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got non-finite values at "
                         f"{np.flatnonzero(~np.isfinite(arr)).tolist()}")
    return arr


def bootstrap_intervals(true_values, sim_returns, score: Callable, true_se=None, *,
                        n_boot: int = 1000, seed: int = 0, level: float = 0.95) -> dict:
    """Bootstrap intervals of every score of a simulator over its evaluation episodes.

    true_values: [P] true values; sim_returns: [P, n] the simulated return of each of n
    episodes per policy (the simulated value is their mean); score(truth [P], sim [P]) ->
    {metric: float} (e.g. ``evaluate.ranking_metrics`` with its ks); true_se: [P] standard
    errors of the true values, or None when they are known exactly.

    Each of n_boot replicates resamples every policy's n simulated episodes with replacement;
    when true_se is given, it also draws the true values from N(true, true_se^2) (a parametric
    bootstrap: the per-episode true returns are not stored). Returns
    {"level", "n_boot", "n_episodes", "metrics": {metric: {"lo", "hi", "std"}} over both
    noises, "sim_only": {metric: {"lo", "hi", "std"}} over the simulated episodes alone}.
    ``sim_only["kendall_tau"]["std"]`` is how much evaluation noise alone moves tau.
    """
    t = _finite_1d(true_values, "true_values")
    r = np.array(sim_returns, dtype=np.float64)
    if r.ndim != 2 or r.shape[0] != t.size or r.shape[1] < 1:
        raise ValueError(f"sim_returns must be [P, n] with P = {t.size} (the true values') and "
                         f"n >= 1 episodes, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("sim_returns must be finite")
    se = None
    if true_se is not None:
        se = _finite_1d(true_se, "true_se")
        if se.shape != t.shape or (se < 0).any():
            raise ValueError(f"true_se must be [P = {t.size}] and >= 0, got {se.tolist()}")
    if not isinstance(n_boot, int) or n_boot < 2:
        raise ValueError(f"n_boot must be an int >= 2, got {n_boot!r}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    rng = np.random.default_rng(seed)
    P, n = r.shape
    rows = np.arange(P)[:, None]
    both, sim_only = [], []
    for _ in range(n_boot):
        sim = r[rows, rng.integers(0, n, size=(P, n))].mean(1)
        sim_only.append(score(t, sim))
        truth = t if se is None else t + se * rng.standard_normal(P)
        both.append(sim_only[-1] if se is None else score(truth, sim))
    q = (1.0 - level) / 2.0

    def summary(reps):
        return {k: {"lo": float(np.quantile(v, q)), "hi": float(np.quantile(v, 1.0 - q)),
                    "std": float(np.std(v, ddof=1))}
                for k, v in ((k, np.array([m[k] for m in reps])) for k in reps[0])}

    return {"level": level, "n_boot": n_boot, "n_episodes": n, "metrics": summary(both),
            "sim_only": summary(sim_only)}


def _improvement_inputs(c0, c0_se, c1, c1_se, diff_se, level):
    """improvement_intervals' arguments as [R, P] float64 arrays (diff_se None or [R, P]),
    checked: one shape, finite, no zero c0 (its improvement is undefined)."""
    c0, s0, c1, s1 = (np.atleast_2d(np.asarray(x, np.float64)) for x in (c0, c0_se, c1, c1_se))
    if not c0.shape == s0.shape == c1.shape == s1.shape:
        raise ValueError(f"c0, c0_se, c1, c1_se: expected one shape, got {c0.shape}, "
                         f"{s0.shape}, {c1.shape}, {s1.shape}")
    sd = None if diff_se is None else np.atleast_2d(np.asarray(diff_se, np.float64))
    if sd is not None and sd.shape != c0.shape:
        raise ValueError(f"diff_se: expected the shape of c0 {c0.shape}, got {sd.shape}")
    for name, c in (("c0", c0), ("c1", c1)):
        if c.ndim != 2 or c.shape[1] < 1:
            raise ValueError(f"{name}: expected shape [P >= 1] or [R, P >= 1], got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError(f"{name}: expected finite returns, got {c}")
    if np.any(c0 == 0):
        raise ValueError(f"c0: improvement is undefined for a zero return, got zeros at "
                         f"{np.flatnonzero(c0.reshape(-1) == 0).tolist()}")
    if not 0 < level < 1:
        raise ValueError(f"level: expected in (0, 1), got {level}")
    return c0, s0, c1, s1, sd


def improvement_intervals(c0, c0_se, c1, c1_se, *, diff_se=None, level: float = 0.95,
                          n_boot: int = 2000, seed: int = 0) -> dict[str, list[float]]:
    """Bootstrap intervals of MPI and API from real returns with their standard errors
    (all [R, P]: R seeds of the fine-tuning x P policies, or [P]).

    Each replicate resamples the P policies with replacement (the same draw for every seed)
    and redraws each measured return from N(C, SE^2) (the measurement's own noise), then takes
    MPI = min I and API = mean I over the drawn policies, I = (C1 - C0) / |C0|, averaged over
    the seeds. With ``diff_se`` (paired measurement, ``improve.measure_improvement``) C1 is
    redrawn as C0 + (C1 - C0) + diff_se * z, keeping the pairing. The interval is the
    replicates' central ``level`` quantile range. -> {"mpi": [low, high], "api": [low, high]}."""
    c0, s0, c1, s1, sd = _improvement_inputs(c0, c0_se, c1, c1_se, diff_se, level)
    rng = np.random.default_rng(seed)
    R, P = c0.shape
    idx = rng.integers(0, P, (n_boot, P))
    z0, z1 = rng.standard_normal((2, n_boot, R, P))
    d0 = c0[None] + s0[None] * z0
    d1 = (c1[None] + s1[None] * z1 if sd is None
          else d0 + (c1 - c0)[None] + sd[None] * z1)
    take = np.broadcast_to(idx[:, None], z0.shape)
    b0 = np.take_along_axis(d0, take, axis=-1)
    b1 = np.take_along_axis(d1, take, axis=-1)
    imp = (b1 - b0) / np.maximum(np.abs(b0), 1e-8)
    mpi, api = imp.min(-1).mean(-1), imp.mean(-1).mean(-1)
    q = [(1 - level) / 2, (1 + level) / 2]
    return {"mpi": np.quantile(mpi, q).tolist(), "api": np.quantile(api, q).tolist()}


def sign_flip_p(per_episode: np.ndarray) -> float:
    """One-sided p-value that the per-episode gains [E] are positive: the sign-flip
    randomisation test on their ranks (Wilcoxon's signed-rank test), with the normal
    approximation to its null. Ranks keep one wild episode from deciding the answer."""
    x = per_episode[per_episode != 0]
    if x.size == 0:
        return 1.0
    order = np.argsort(np.abs(x))
    ranks = np.empty(x.size)
    ranks[order] = np.arange(1, x.size + 1)
    _, inv, counts = np.unique(np.abs(x), return_inverse=True, return_counts=True)
    if (counts > 1).any():  # average ranks over ties
        ranks = (np.bincount(inv, weights=ranks) / counts)[inv]
    stat = float(ranks[x > 0].sum() - ranks.sum() / 2)
    z = stat / math.sqrt(float((ranks ** 2).sum()) / 4)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def rank_sum_p(x: np.ndarray, y: np.ndarray) -> float:
    """One-sided p-value that the values x [n] tend to exceed y [m]: the Wilcoxon rank-sum
    (Mann-Whitney) test with average ranks for ties and the normal approximation to its null,
    tie-corrected."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    n, m = x.size, y.size
    if n == 0 or m == 0:
        return 1.0
    both = np.concatenate([x, y])
    _, inv, counts = np.unique(both, return_inverse=True, return_counts=True)
    first = np.cumsum(counts) - counts  # 0-based rank of each distinct value's first copy
    ranks = (first + (counts + 1) / 2.0)[inv]
    u = ranks[:n].sum() - n * (n + 1) / 2.0
    N = n + m
    var = n * m / 12.0 * ((N + 1) - (counts ** 3 - counts).sum() / (N * (N - 1)))
    if var <= 0:
        return 1.0
    z = (u - n * m / 2.0) / math.sqrt(var)
    return 0.5 * math.erfc(z / math.sqrt(2.0))
