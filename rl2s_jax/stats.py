"""The statistics every stage shares, NumPy (and SciPy's t quantile) only: intervals over seeds
(Student t), bootstrap intervals of a statistic, the paired differences of two methods, and the
rank tests of the cause tests (signed-rank by sign flips, rank-sum). Bad input raises
``ValueError`` naming the argument."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.stats import t as student_t  # jax's own dependency

__all__ = [
    "bootstrap_ci",
    "mean_per_unit",
    "median_ci95",
    "paired_gain_difference",
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
