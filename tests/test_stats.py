"""rl2s_jax.stats, the one statistics module: intervals and tests against hand-worked cases,
textbook quantiles, exact enumeration and plain NumPy."""

import itertools
import math

import numpy as np
import pytest

from rl2s_jax.stats import (
    bootstrap_ci,
    median_ci95,
    paired_gain_difference,
    rank_sum_p,
    sign_flip_p,
    t_interval,
)


def test_bootstrap_ci_against_a_plain_loop():
    """bootstrap_ci: the quantiles of the statistic over resamples drawn as a plain loop with
    the same generator draws; an empty sample gives None; bad n_boot or level is refused."""
    x = np.random.default_rng(3).normal(size=17)
    idx = np.random.default_rng(5).integers(0, x.size, (400, x.size))
    means = [x[row].mean() for row in idx]
    assert bootstrap_ci(x, n_boot=400, seed=5) == pytest.approx(
        [np.quantile(means, 0.025), np.quantile(means, 0.975)])
    medians = [np.median(x[row]) for row in idx]
    assert bootstrap_ci(x, np.median, n_boot=400, seed=5, level=0.8) == pytest.approx(
        [np.quantile(medians, 0.1), np.quantile(medians, 0.9)])
    assert median_ci95(x, 400, seed=5) == bootstrap_ci(x, np.median, n_boot=400, seed=5)
    assert bootstrap_ci([], n_boot=10) is None
    with pytest.raises(ValueError, match="n_boot"):
        bootstrap_ci(x, n_boot=1)
    with pytest.raises(ValueError, match="level"):
        bootstrap_ci(x, level=1.5)


def test_t_interval_by_hand():
    """Mean and Student-t interval over seeds against the textbook quantiles (t(0.975; 1) =
    12.706, t(0.975; 2) = 4.303); fewer than two values give None; bad input raises."""
    mid, lo, hi = t_interval([1.0, 2.0, 3.0])      # mean 2, sd 1
    assert mid == 2.0 and hi - mid == pytest.approx(4.3027 / math.sqrt(3), rel=1e-4)
    assert mid - lo == pytest.approx(hi - mid)
    mid, lo, hi = t_interval([-0.01, 0.01])        # sd sqrt(2) * 0.01, n 2
    assert mid == pytest.approx(0.0) and hi == pytest.approx(12.706 * 0.01, rel=1e-4)
    assert t_interval([0.3]) is None and t_interval([]) is None
    with pytest.raises(ValueError, match="values"):
        t_interval([1.0, float("nan")])
    with pytest.raises(ValueError, match="level"):
        t_interval([1.0, 2.0], level=1.0)


def test_median_ci95_brackets_the_median_and_repeats():
    """median_ci95: a constant sample's interval is that constant; 0..100's brackets its
    median 50 within +-10; one seed gives one interval, a median far from the mean (one huge
    ratio, as a start near 0 gives) moves it not at all."""
    assert median_ci95(np.full(7, 0.3), 200) == pytest.approx([0.3, 0.3])
    lo, hi = median_ci95(np.arange(101.0), 500)
    assert 40 <= lo <= 50 <= hi <= 60
    assert median_ci95(np.arange(101.0), 500) == [lo, hi]
    skewed = np.arange(101.0)
    skewed[-1] = 1e9
    assert median_ci95(skewed, 500) == [lo, hi]


def test_paired_gain_difference_by_hand():
    """paired_gain_difference: the pairs over the seeds both methods ran (seed 9 only A has),
    the per-seed median difference and its t-interval against a plain loop; one common seed
    gives no interval; different policy counts per seed are refused."""
    a = {0: np.array([0.5, 0.1, 0.3]), 1: np.array([0.2, 0.9, 0.0]), 9: np.array([9.0] * 3)}
    b = {0: np.array([0.4, 0.3, 0.1]), 1: np.array([0.1, 0.1, 0.1])}
    got = paired_gain_difference(a, b, n_boot=300)
    d = [x - y for k in (0, 1) for x, y in zip(a[k], b[k], strict=True)]
    assert got["seeds"] == [0, 1] and got["pairs"] == 6
    assert got["median"] == pytest.approx(np.median(d))
    assert got["rl2s_higher"] == sum(x > 0 for x in d)          # 4: 0.1, 0.2, 0.1, 0.8
    per = [np.median(a[k]) - np.median(b[k]) for k in (0, 1)]   # 0.0, +0.1
    assert got["over_seeds"]["per_seed"] == pytest.approx(per)
    half = 12.706 * np.std(per, ddof=1) / np.sqrt(2)             # t(0.975; 1 dof)
    assert got["over_seeds"]["mean"] == pytest.approx(np.mean(per))
    assert got["over_seeds"]["t95"] == pytest.approx([np.mean(per) - half,
                                                      np.mean(per) + half], rel=1e-4)
    one = paired_gain_difference({0: a[0]}, b, n_boot=100)
    assert one["over_seeds"]["mean"] is None and one["pairs"] == 3
    assert paired_gain_difference({9: a[9]}, b) is None
    with pytest.raises(ValueError, match="same policies"):
        paired_gain_difference({0: a[0][:2]}, b)


def test_sign_flip_p_matches_exact_enumeration():
    rng = np.random.default_rng(0)
    x = rng.normal(0.4, 1.0, 14)
    ranks = np.argsort(np.argsort(np.abs(x))) + 1
    observed = ranks[x > 0].sum()
    exact = np.mean([ranks[np.array(s, bool)].sum() >= observed
                     for s in itertools.product([0, 1], repeat=x.size)])
    assert abs(sign_flip_p(x) - exact) < 0.03
    assert sign_flip_p(np.full(30, 1.0)) < 1e-5 and sign_flip_p(np.full(30, -1.0)) > 0.99


def test_rank_sum_p_matches_exact_enumeration():
    rng = np.random.default_rng(0)
    x, y = rng.normal(0.8, 1, 7), rng.normal(0, 1, 6)
    both = np.concatenate([x, y])
    ranks = np.argsort(np.argsort(both)) + 1.0
    observed = ranks[:7].sum()
    sums = np.array([ranks[list(c)].sum() for c in itertools.combinations(range(13), 7)])
    exact = float((sums >= observed).mean())
    assert abs(rank_sum_p(x, y) - exact) < 0.02
    assert rank_sum_p(x, y) < rank_sum_p(y, x)
    assert rank_sum_p(np.ones(3), np.ones(4)) == 1.0  # all tied: no evidence
