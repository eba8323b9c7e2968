"""rl2s_jax.stats, the one statistics module: intervals and tests against hand-worked cases,
textbook quantiles, exact enumeration and plain NumPy."""

import itertools
import math

import numpy as np
import pytest

from rl2s_jax.stats import (
    bootstrap_ci,
    bootstrap_intervals,
    improvement_intervals,
    median_ci95,
    paired_gain,
    paired_gain_difference,
    paired_seed_difference,
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


def _spread(reps, q):
    """{metric: {"lo", "hi", "std"}} of a list of {metric: float}, as a plain loop."""
    return {k: {"lo": np.quantile([r[k] for r in reps], q),
                "hi": np.quantile([r[k] for r in reps], 1 - q),
                "std": np.std([r[k] for r in reps], ddof=1)} for k in reps[0]}


def test_bootstrap_intervals_against_a_plain_loop():
    """bootstrap_intervals: each replicate resamples every policy's episodes (one row of
    draws per policy) then, with true_se, redraws the truth; the same generator's draws taken
    one by one in a loop give the same intervals of the score."""
    rng = np.random.default_rng(1)
    true, se = rng.normal(size=4), np.abs(rng.normal(size=4))
    returns = true[:, None] + rng.normal(size=(4, 3))

    def score(t, s):
        return {"gap": float(np.abs(t - s).max()), "first": float(s[0])}

    draws = np.random.default_rng(7)
    both, alone = [], []
    for _ in range(60):
        idx = draws.integers(0, 3, size=(4, 3))
        sim = np.array([returns[p, idx[p]].mean() for p in range(4)])
        alone.append(score(true, sim))
        both.append(score(true + se * draws.standard_normal(4), sim))
    got = bootstrap_intervals(true, returns, score, se, n_boot=60, seed=7, level=0.9)
    for key, reps in (("metrics", both), ("sim_only", alone)):
        want = _spread(reps, 0.05)
        for k in want:
            assert got[key][k] == pytest.approx(want[k], rel=1e-12), (key, k)
    assert (got["n_boot"], got["n_episodes"], got["level"]) == (60, 3, 0.9)
    with pytest.raises(ValueError, match="true_values"):
        bootstrap_intervals([np.nan, 1.0, 2.0, 3.0], returns, score)


def test_improvement_intervals_against_a_plain_loop():
    """improvement_intervals: per replicate, policies drawn with replacement (the same for
    every seed), returns redrawn from N(C, SE^2) (paired: C1 = C0 draw + (C1 - C0) + diff_se
    z), I = (C1 - C0) / |C0|, MPI / API averaged over seeds; quantiles as a plain loop."""
    rng = np.random.default_rng(2)
    c0 = rng.normal(5.0, 1.0, (2, 3))
    c1, s0, s1, sd = c0 + rng.normal(size=(2, 3)), *np.abs(rng.normal(size=(3, 2, 3)))
    for diff_se in (None, sd):
        draws = np.random.default_rng(4)
        idx = draws.integers(0, 3, (50, 3))
        z0, z1 = draws.standard_normal((2, 50, 2, 3))
        mpi, api = [], []
        for b in range(50):
            per_seed = []
            for r in range(2):
                d0 = c0[r] + s0[r] * z0[b, r]
                d1 = (c1[r] + s1[r] * z1[b, r] if diff_se is None
                      else d0 + (c1[r] - c0[r]) + sd[r] * z1[b, r])
                i = (d1[idx[b]] - d0[idx[b]]) / np.abs(d0[idx[b]])
                per_seed.append((i.min(), i.mean()))
            mpi.append(np.mean([m for m, _ in per_seed]))
            api.append(np.mean([a for _, a in per_seed]))
        got = improvement_intervals(c0, s0, c1, s1, diff_se=diff_se, n_boot=50, seed=4,
                                    level=0.8)
        assert got["mpi"] == pytest.approx(np.quantile(mpi, [0.1, 0.9]), rel=1e-12)
        assert got["api"] == pytest.approx(np.quantile(api, [0.1, 0.9]), rel=1e-12)
    with pytest.raises(ValueError, match="c0: improvement is undefined"):
        improvement_intervals(np.zeros(3), s0[0], c1[0], s1[0])


def test_paired_gain_and_seed_difference_by_hand():
    """paired_gain: candidate k's per-episode gain over candidate 0, its mean and standard
    error (ddof 1) per policy, as a loop; paired_seed_difference: the per-seed differences
    over seeds both ran, their t-interval (4.303 for 3 seeds), seeds where A is lower."""
    r = np.random.default_rng(3).normal(size=(3, 2, 5))
    mean, se = paired_gain(r)
    for k in range(2):
        for p in range(2):
            g = [r[k + 1, p, e] - r[0, p, e] for e in range(5)]
            assert mean[k, p] == pytest.approx(sum(g) / 5, rel=1e-12)
            sd = math.sqrt(sum((x - sum(g) / 5) ** 2 for x in g) / 4)
            assert se[k, p] == pytest.approx(sd / math.sqrt(5), rel=1e-12)
    d = np.array([-1.0, 2.0, -0.5])
    mid, lo, hi, lower, n = paired_seed_difference([1.0, 4.0, None, 2.5], [2.0, 2.0, 7.0, 3.0])
    half = 4.302653 * d.std(ddof=1) / math.sqrt(3)
    assert (mid, lower, n) == (pytest.approx(d.mean()), 2, 3)
    assert (lo, hi) == (pytest.approx(d.mean() - half, rel=1e-6),
                        pytest.approx(d.mean() + half, rel=1e-6))
    assert paired_seed_difference([1.0, 2.0], [1.0, 2.0, 3.0]) is None
    assert paired_seed_difference([1.0, None], [2.0, 3.0]) is None


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


def test_mean_or_none():
    """The mean as a float; None as soon as one value is None (an unbounded width)."""
    from rl2s_jax.stats import mean_or_none

    assert mean_or_none([0.1, 0.2, 0.6]) == pytest.approx(0.3)
    assert isinstance(mean_or_none(iter([1, 2])), float)
    assert mean_or_none([0.1, None, 0.6]) is None
