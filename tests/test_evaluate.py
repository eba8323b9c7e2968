"""Policy-evaluation metrics: hand-worked cases, ties, degenerate inputs, scipy cross-checks and
bad input."""

import itertools
import math

import numpy as np
import pytest

from rl2s_jax.evaluate.metrics import (
    kendall_tau,
    ndcg_at_k,
    ranking_metrics,
    regret_at_k,
    spearman,
    value_differences,
)
from rl2s_jax.stats import bootstrap_intervals

L3 = math.log2(3)  # discount of rank 2 is 1 / log2(3); rank 1 is 1 / log2(2) = 1, rank 3 is 1/2

# The worked example used below: P = 4.
#   true = [4, 3, 2, 1]  ->  rel = (true - 1) / 3 = [1, 2/3, 1/3, 0]
#   sim  = [2, 4, 3, 1]  ->  simulated ranking (descending): p1, p2, p0, p3
TRUE4 = [4.0, 3.0, 2.0, 1.0]
SIM4 = [2.0, 4.0, 3.0, 1.0]


# ----------------------------------------------------------------------------- value differences


def test_value_differences_hand_case():
    # |[4,3,2,1] - [2,4,3,1]| = [2, 1, 1, 0]; mean 4/4 = 1; max 2
    out = value_differences(TRUE4, SIM4)
    np.testing.assert_allclose(out["vd"], [2.0, 1.0, 1.0, 0.0])
    assert out["avd"] == pytest.approx(1.0)
    assert out["mvd"] == pytest.approx(2.0)
    assert isinstance(out["avd"], float) and isinstance(out["mvd"], float)


def test_value_differences_single_policy():
    out = value_differences([5.0], [3.5])
    assert out["avd"] == out["mvd"] == pytest.approx(1.5)


# ----------------------------------------------------------------------------- hand-worked ranks


def test_kendall_tau_hand_case():
    # pairs (i, j): sign(true_i - true_j), sign(sim_i - sim_j)
    #   (0,1): +, (2-4)=- -> discordant   (0,2): +, (2-3)=- -> discordant
    #   (0,3): +, (2-1)=+ -> concordant   (1,2): +, (4-3)=+ -> concordant
    #   (1,3): +, +       -> concordant   (2,3): +, +       -> concordant
    # tau = (4 - 2) / (4*3/2) = 2/6
    assert kendall_tau(TRUE4, SIM4) == pytest.approx(1 / 3)


def test_spearman_hand_case():
    # ascending ranks: true [4,3,2,1], sim [2,4,3,1]; d = [2,-1,-1,0], sum d^2 = 6
    # rho = 1 - 6 * 6 / (4 * (16 - 1)) = 1 - 36/60 = 0.4
    assert spearman(TRUE4, SIM4) == pytest.approx(0.4)


def test_ndcg_hand_case():
    # simulated order p1, p2, p0, p3 has rels 2/3, 1/3, 1, 0; ideal order rels 1, 2/3, 1/3, 0
    # @1: DCG = 2/3,                        IDCG = 1                    -> 2/3
    # @2: DCG = 2/3 + (1/3)/log2 3,         IDCG = 1 + (2/3)/log2 3
    # @3: DCG = 2/3 + (1/3)/log2 3 + 1/2,   IDCG = 1 + (2/3)/log2 3 + (1/3)/2
    # @4: same as @3 (rank 4 has rel 0 in both)
    assert ndcg_at_k(TRUE4, SIM4, 1) == pytest.approx(2 / 3)
    assert ndcg_at_k(TRUE4, SIM4, 2) == pytest.approx((2 / 3 + 1 / 3 / L3) / (1 + 2 / 3 / L3))
    at3 = (2 / 3 + 1 / 3 / L3 + 1 / 2) / (1 + 2 / 3 / L3 + 1 / 6)
    assert ndcg_at_k(TRUE4, SIM4, 3) == pytest.approx(at3)
    assert ndcg_at_k(TRUE4, SIM4, 4) == pytest.approx(at3)


def test_ndcg_p3_hand_case():
    # true = [3, 1, 2] -> rel [1, 0, 1/2]; sim = [1, 3, 2] -> order p1, p2, p0 (rels 0, 1/2, 1)
    # @3: DCG = 0 + (1/2)/log2 3 + 1/2;  IDCG = 1 + (1/2)/log2 3 + 0
    t, s = [3.0, 1.0, 2.0], [1.0, 3.0, 2.0]
    assert ndcg_at_k(t, s, 1) == pytest.approx(0.0)
    assert ndcg_at_k(t, s, 3) == pytest.approx((0.5 / L3 + 0.5) / (1 + 0.5 / L3))


def test_regret_hand_case():
    # max true 4, min true 1, range 3
    # @1: top-1 by sim = {p1}         -> best true 3 -> (4 - 3) / 3 = 1/3
    # @2: top-2 by sim = {p1, p2}     -> best true 3 -> 1/3
    # @3: top-3 by sim = {p1, p2, p0} -> best true 4 -> 0
    assert regret_at_k(TRUE4, SIM4, 1) == pytest.approx(1 / 3)
    assert regret_at_k(TRUE4, SIM4, 2) == pytest.approx(1 / 3)
    assert regret_at_k(TRUE4, SIM4, 3) == pytest.approx(0.0)
    assert regret_at_k(TRUE4, SIM4, 4) == pytest.approx(0.0)
    # worst case: the simulator's top-1 is the truly worst policy -> regret 1
    assert regret_at_k([1.0, 2.0, 3.0], [3.0, 2.0, 1.0], 1) == pytest.approx(1.0)


# ----------------------------------------------------------------------------- perfect / reversed


@pytest.mark.parametrize("p", [2, 3, 7])
def test_perfect_and_reversed_rankings(p):
    rng = np.random.default_rng(p)
    true = rng.normal(size=p)
    sim = 10.0 * true + 3.0  # any strictly increasing map is a perfect ranking
    assert kendall_tau(true, sim) == pytest.approx(1.0)
    assert spearman(true, sim) == pytest.approx(1.0)
    for k in range(1, p + 2):
        assert ndcg_at_k(true, sim, k) == pytest.approx(1.0)
        assert regret_at_k(true, sim, k) == pytest.approx(0.0)
    assert kendall_tau(true, -sim) == pytest.approx(-1.0)
    assert spearman(true, -sim) == pytest.approx(-1.0)
    assert regret_at_k(true, -sim, 1) == pytest.approx(1.0)  # top-1 is the worst policy
    assert ndcg_at_k(true, -sim, 1) == pytest.approx(0.0)  # ... whose rel is 0


def test_k_is_capped_at_p():
    assert ndcg_at_k(TRUE4, SIM4, 10) == ndcg_at_k(TRUE4, SIM4, 4)
    assert regret_at_k(TRUE4, SIM4, 10) == 0.0


# ----------------------------------------------------------------------------- ties and degenerate


def test_kendall_ties_count_as_neither():
    # true = [1, 2, 3], sim = [1, 1, 2]
    #   (0,1): sim tied -> neither   (0,2): -, - -> concordant   (1,2): -, - -> concordant
    # tau = (2 - 0) / 3; ties stay in the denominator (tau-a; scipy's tau-b would be 2/sqrt(6))
    assert kendall_tau([1.0, 2.0, 3.0], [1.0, 1.0, 2.0]) == pytest.approx(2 / 3)
    # tie in true only: true = [1, 1, 2], sim = [3, 2, 1] -> (0,1) neither, two discordant
    assert kendall_tau([1.0, 1.0, 2.0], [3.0, 2.0, 1.0]) == pytest.approx(-2 / 3)


def test_spearman_average_ranks_for_ties():
    # true = [1, 2, 2, 3] -> ranks [1, 2.5, 2.5, 4]; sim = [1, 2, 3, 4] -> ranks [1, 2, 3, 4]
    # centred: [-1.5, 0, 0, 1.5] and [-1.5, -.5, .5, 1.5]; cov = 2.25 + 2.25 = 4.5
    # norms^2: 4.5 and 5 -> rho = 4.5 / sqrt(22.5)
    assert spearman([1.0, 2.0, 2.0, 3.0], [1.0, 2.0, 3.0, 4.0]) == pytest.approx(
        4.5 / math.sqrt(22.5))


def test_ndcg_and_regret_average_over_sim_ties():
    # true = [2, 1, 0] -> rel [1, 1/2, 0]; sim = [1, 1, 0]: p0 and p1 tie for rank 1..2,
    # each taken first half the time.
    t, s = [2.0, 1.0, 0.0], [1.0, 1.0, 0.0]
    # nDCG@1: E[rel at rank 1] = (1 + 1/2)/2 = 3/4; IDCG@1 = 1
    assert ndcg_at_k(t, s, 1) == pytest.approx(0.75)
    # nDCG@3: DCG = 3/4 * (1 + 1/log2 3) + 0 * 1/2; IDCG = 1 + (1/2)/log2 3
    assert ndcg_at_k(t, s, 3) == pytest.approx(0.75 * (1 + 1 / L3) / (1 + 0.5 / L3))
    # regret@1: E[best true of top-1] = (2 + 1)/2 = 1.5 -> (2 - 1.5) / 2 = 1/4
    assert regret_at_k(t, s, 1) == pytest.approx(0.25)
    assert regret_at_k(t, s, 2) == pytest.approx(0.0)


def test_constant_simulator_scores_like_a_random_ranking():
    t, s = [1.0, 2.0, 3.0, 4.0], [0.0, 0.0, 0.0, 0.0]
    assert kendall_tau(t, s) == 0.0
    assert spearman(t, s) == 0.0
    # nDCG@1 = mean rel = (0 + 1/3 + 2/3 + 1) / 4 = 1/2
    assert ndcg_at_k(t, s, 1) == pytest.approx(0.5)
    # regret@1: E[true of a random policy] = 2.5 -> (4 - 2.5) / 3 = 1/2
    assert regret_at_k(t, s, 1) == pytest.approx(0.5)
    # regret@2: best of a random pair: pairs' maxima 2,3,4,3,4,4 -> mean 20/6
    #   -> (4 - 20/6) / 3 = 2/9
    assert regret_at_k(t, s, 2) == pytest.approx(2 / 9)


def test_all_true_values_equal():
    t, s = [5.0, 5.0, 5.0], [1.0, 3.0, 2.0]
    assert ndcg_at_k(t, s, 1) == 1.0
    assert regret_at_k(t, s, 1) == 0.0
    assert kendall_tau(t, s) == 0.0
    assert spearman(t, s) == 0.0
    # a single policy is the all-equal case too
    assert ndcg_at_k([1.0], [2.0], 1) == 1.0
    assert regret_at_k([1.0], [2.0], 3) == 0.0


def _brute_force_tie_average(true, sim, k):
    """Mean nDCG@k and regret@k over every order of the policies that is consistent with sim
    (descending), i.e. over all ways of breaking sim's ties."""
    true, sim = np.asarray(true, float), np.asarray(sim, float)
    p = true.size
    rel = (true - true.min()) / (true.max() - true.min())
    disc = 1.0 / np.log2(np.arange(2, k + 2))
    idcg = np.sort(rel)[::-1][:k] @ disc
    orders = {tuple(np.lexsort((perm, -sim))) for perm in itertools.permutations(range(p))}
    ndcg = [rel[list(o)][:k] @ disc / idcg for o in orders]
    regret = [(true.max() - true[list(o)][:k].max()) / (true.max() - true.min()) for o in orders]
    return float(np.mean(ndcg)), float(np.mean(regret))


@pytest.mark.parametrize("seed", range(6))
def test_tie_handling_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    true = rng.integers(0, 4, size=6).astype(float)
    true[0], true[1] = 0.0, 3.0  # not all equal
    sim = rng.integers(0, 3, size=6).astype(float)  # many ties
    for k in (1, 2, 3, 5):
        want_ndcg, want_regret = _brute_force_tie_average(true, sim, k)
        assert ndcg_at_k(true, sim, k) == pytest.approx(want_ndcg)
        assert regret_at_k(true, sim, k) == pytest.approx(want_regret)


def test_metrics_do_not_depend_on_policy_order():
    rng = np.random.default_rng(3)
    true = rng.integers(0, 5, size=9).astype(float)
    sim = rng.integers(0, 3, size=9).astype(float)
    perm = rng.permutation(9)
    a = ranking_metrics(true, sim)
    b = ranking_metrics(true[perm], sim[perm])
    assert a == pytest.approx(b)


# ----------------------------------------------------------------------------- scipy cross-checks


@pytest.mark.parametrize("seed", range(5))
def test_against_scipy_without_ties(seed):
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(seed)
    p = int(rng.integers(2, 30))
    true = rng.normal(size=p)
    sim = true + rng.normal(size=p)
    assert kendall_tau(true, sim) == pytest.approx(stats.kendalltau(true, sim).statistic)
    assert spearman(true, sim) == pytest.approx(stats.spearmanr(true, sim).statistic)


@pytest.mark.parametrize("seed", range(5))
def test_against_scipy_with_ties(seed):
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(100 + seed)
    p = 12
    true = rng.integers(0, 4, size=p).astype(float)
    sim = rng.integers(0, 4, size=p).astype(float)
    assert spearman(true, sim) == pytest.approx(stats.spearmanr(true, sim).statistic)
    # scipy's tau-b = (C - D) / sqrt((n0 - n1)(n0 - n2)); ours (tau-a) = (C - D) / n0, where
    # n0 = P(P-1)/2 and n1, n2 count the pairs tied in true and in sim.
    n0 = p * (p - 1) / 2
    n1 = sum(c * (c - 1) / 2 for c in np.unique(true, return_counts=True)[1])
    n2 = sum(c * (c - 1) / 2 for c in np.unique(sim, return_counts=True)[1])
    tau_b = stats.kendalltau(true, sim).statistic
    assert kendall_tau(true, sim) * n0 == pytest.approx(tau_b * math.sqrt((n0 - n1) * (n0 - n2)))


# ----------------------------------------------------------------------------- bundle


def test_ranking_metrics_bundle():
    out = ranking_metrics(TRUE4, SIM4)
    assert set(out) == {"kendall_tau", "spearman", "avd", "mvd",
                        "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10",
                        "regret@1", "regret@3", "regret@5", "regret@10"}
    assert all(isinstance(v, float) for v in out.values())
    assert out["kendall_tau"] == pytest.approx(1 / 3)
    assert out["spearman"] == pytest.approx(0.4)
    # The bundle uses the paper's gain 2^B - 1: at @1 the simulator's top policy has B = 2/3.
    assert out["ndcg@1"] == pytest.approx(2 ** (2 / 3) - 1)
    assert out["ndcg@10"] == pytest.approx(ndcg_at_k(TRUE4, SIM4, 4, gain="exp2"))
    assert out["regret@1"] == pytest.approx(1 / 3)
    assert out["regret@3"] == pytest.approx(0.0)
    assert out["avd"] == pytest.approx(1.0) and out["mvd"] == pytest.approx(2.0)
    assert set(ranking_metrics(TRUE4, SIM4, ks=[2])) == {
        "kendall_tau", "spearman", "ndcg@2", "regret@2", "avd", "mvd"}


# ----------------------------------------------------------------------------- bad input


ALL_PAIRWISE = [value_differences, kendall_tau, spearman, ranking_metrics,
                lambda t, s: ndcg_at_k(t, s, 1), lambda t, s: regret_at_k(t, s, 1)]


@pytest.mark.parametrize("fn", ALL_PAIRWISE)
def test_mismatched_lengths(fn):
    with pytest.raises(ValueError, match="same length.*true_values.*sim_values"):
        fn([1.0, 2.0, 3.0], [1.0, 2.0])


@pytest.mark.parametrize("fn", ALL_PAIRWISE)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite(fn, bad):
    with pytest.raises(ValueError, match="true_values must be finite"):
        fn([1.0, bad, 3.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="sim_values must be finite"):
        fn([1.0, 2.0, 3.0], [bad, 2.0, 3.0])


@pytest.mark.parametrize("fn", [kendall_tau, spearman, ranking_metrics])
def test_rankings_need_two_policies(fn):
    with pytest.raises(ValueError, match="at least 2 policies"):
        fn([1.0], [1.0])


@pytest.mark.parametrize("fn", ALL_PAIRWISE)
def test_bad_shapes_and_types(fn):
    with pytest.raises(ValueError, match="true_values must be 1-D"):
        fn([[1.0, 2.0]], [1.0, 2.0])
    with pytest.raises(ValueError, match="sim_values must be 1-D"):
        fn([1.0, 2.0], 3.0)
    with pytest.raises(ValueError, match="true_values must contain at least 1 policy"):
        fn([], [])
    with pytest.raises(ValueError, match="sim_values must be a 1-D array of numbers"):
        fn([1.0, 2.0], ["a", "b"])


@pytest.mark.parametrize("fn", [ndcg_at_k, regret_at_k])
@pytest.mark.parametrize("k", [0, -1, 1.5, True, "2", None])
def test_bad_k(fn, k):
    with pytest.raises(ValueError, match=r"k must be an integer >= 1"):
        fn(TRUE4, SIM4, k)


def test_numpy_integer_k_is_accepted():
    assert ndcg_at_k(TRUE4, SIM4, np.int64(1)) == pytest.approx(2 / 3)


@pytest.mark.parametrize("ks", [(1, 0), (2.0,), 3, "13"])
def test_bad_ks(ks):
    with pytest.raises(ValueError, match="ks"):
        ranking_metrics(TRUE4, SIM4, ks=ks)


# ----------------------------------------------------------------------------- paper gain


def test_ndcg_exp2_gain_matches_numpy_reference():
    rng = np.random.default_rng(3)
    true, sim = rng.normal(size=9), rng.normal(size=9)
    b = (true - true.min()) / (true.max() - true.min())
    rel = 2.0 ** b - 1.0
    for k in (1, 3, 9):
        disc = 1.0 / np.log2(np.arange(2, k + 2))
        want = rel[np.argsort(-sim)][:k] @ disc / (np.sort(rel)[::-1][:k] @ disc)
        assert ndcg_at_k(true, sim, k, gain="exp2") == pytest.approx(want)
    assert ndcg_at_k(true, sim, 3, gain="exp2") != pytest.approx(ndcg_at_k(true, sim, 3))
    with pytest.raises(ValueError, match="gain"):
        ndcg_at_k(true, sim, 3, gain="log")


# ----------------------------------------------------------------------------- intervals


def test_bootstrap_without_noise_is_the_point_estimate():
    # Every episode of a policy returns the same value and the truth is exact: each replicate
    # is the point estimate, so every interval collapses onto it.
    true = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    sim = np.array([1.5, 1.0, 3.5, 3.0, 6.0])
    out = bootstrap_intervals(true, np.repeat(sim[:, None], 6, 1), ranking_metrics, n_boot=50)
    point = ranking_metrics(true, sim)
    for k, v in point.items():
        assert out["metrics"][k]["lo"] == pytest.approx(v)
        assert out["metrics"][k]["hi"] == pytest.approx(v)
        assert out["sim_only"][k]["std"] == pytest.approx(0.0, abs=1e-12)
    assert out["n_episodes"] == 6 and out["n_boot"] == 50


def test_bootstrap_eval_noise_shrinks_with_episodes_and_truth_noise_adds():
    rng = np.random.default_rng(0)
    true = np.linspace(0.0, 10.0, 12)
    stds = {}
    for n in (4, 64):
        returns = true[:, None] + rng.normal(0.0, 3.0, size=(12, n))
        out = bootstrap_intervals(true, returns, ranking_metrics, n_boot=300, seed=1)
        stds[n] = out["sim_only"]["kendall_tau"]["std"]
        tau = out["metrics"]["kendall_tau"]
        assert tau["lo"] <= ranking_metrics(true, returns.mean(1))["kendall_tau"] <= tau["hi"]
    assert stds[64] < 0.7 * stds[4]  # 16x the episodes: the ranking noise falls
    noisy = bootstrap_intervals(true, returns, ranking_metrics, true_se=np.full(12, 2.0),
                                n_boot=300, seed=1)
    assert noisy["metrics"]["kendall_tau"]["std"] > noisy["sim_only"]["kendall_tau"]["std"]


@pytest.mark.parametrize("kwargs, field", [
    (dict(sim_returns=np.ones((3, 4))), "sim_returns"),
    (dict(sim_returns=np.ones(5)), "sim_returns"),
    (dict(true_se=-np.ones(5)), "true_se"),
    (dict(n_boot=1), "n_boot"),
    (dict(level=1.0), "level"),
])
def test_bootstrap_bad_input(kwargs, field):
    args = dict(true_values=np.arange(5.0), sim_returns=np.ones((5, 4)), score=ranking_metrics)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        bootstrap_intervals(**args)


def test_noise_ceiling_matches_the_two_policy_formula():
    """Two policies g apart, per-episode sd s: the truth orders them right with probability
    p1 = Phi(g / (s sqrt(2 / n_truth))), the simulator with p2 (n_sim); tau is +1 when both
    agree, so E[tau] = 2 (p1 p2 + (1 - p1)(1 - p2)) - 1. No noise: tau 1 exactly."""
    from math import erf, sqrt

    from rl2s_jax.evaluate.metrics import noise_ceiling
    phi = lambda x: 0.5 * (1.0 + erf(x / sqrt(2.0)))
    g, s, n1, n2 = 1.0, 4.0, 16, 64
    p1, p2 = phi(g / (s * sqrt(2 / n1))), phi(g / (s * sqrt(2 / n2)))
    ref = 2 * (p1 * p2 + (1 - p1) * (1 - p2)) - 1
    out = noise_ceiling([0.0, g], s, n_truth=n1, n_sim=n2, n_rep=20000, seed=3)
    assert out["kendall_tau"]["mean"] == pytest.approx(ref, abs=0.015)
    assert out["kendall_tau"]["lo"] == -1.0 and out["kendall_tau"]["hi"] == 1.0
    # an exact truth (its own sd 0): tau is +1 with probability p2 alone
    exact_truth = noise_ceiling([0.0, g], s, n_truth=n1, n_sim=n2, n_rep=20000, seed=4,
                                truth_episode_sd=0.0)
    assert exact_truth["kendall_tau"]["mean"] == pytest.approx(2 * p2 - 1, abs=0.015)
    exact = noise_ceiling(np.arange(6.0), 0.0, n_truth=1, n_sim=1, n_rep=5)
    assert exact["kendall_tau"] == {"mean": 1.0, "lo": 1.0, "hi": 1.0}
    assert exact["ndcg@1"]["mean"] == 1.0 and "avd" not in exact
    # more episodes on either side raise the ceiling
    vals, sd = np.linspace(0.0, 10.0, 12), np.full(12, 20.0)
    few = noise_ceiling(vals, sd, n_truth=16, n_sim=32, n_rep=400)["kendall_tau"]["mean"]
    many = noise_ceiling(vals, sd, n_truth=256, n_sim=256, n_rep=400)["kendall_tau"]["mean"]
    assert few < many - 0.2


@pytest.mark.parametrize("kwargs, match", [
    (dict(episode_sd=-1.0, n_truth=4, n_sim=4), "episode_sd"),
    (dict(episode_sd=[1.0, float("nan")], n_truth=4, n_sim=4), "episode_sd"),
    (dict(episode_sd=1.0, n_truth=0, n_sim=4), "n_truth"),
    (dict(episode_sd=1.0, n_truth=4, n_sim=4, truth_episode_sd=[-1.0, 1.0]), "truth_episode_sd"),
    (dict(episode_sd=1.0, n_truth=4, n_sim=2.5), "n_sim"),
])
def test_noise_ceiling_rejects_bad_input(kwargs, match):
    from rl2s_jax.evaluate.metrics import noise_ceiling
    with pytest.raises(ValueError, match=match):
        noise_ceiling([0.0, 1.0], **kwargs)
