"""Issue 66: the ranking of test policies whose learner lineage the training data holds, against
the pairs touching the others (``Zoo.seen_lineage``, ``ranking_swaps.lineage_split``,
experiments/lineage_analysis.py)."""
import itertools
import json

import numpy as np
import pytest
from experiment_scripts import load_script

from rl2s_jax.evaluate.ranking_swaps import lineage_split
from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids


def _tau(t, s):
    """Kendall's tau-a by counting pairs (no ties in these tests)."""
    pairs = list(itertools.combinations(range(len(t)), 2))
    return sum(np.sign(t[i] - t[j]) * np.sign(s[i] - s[j]) for i, j in pairs) / len(pairs)


def test_lineage_split_counts_pairs_by_hand():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=9)
    sim = truth + rng.normal(scale=0.8, size=9)
    seen = np.array([1, 1, 0, 1, 1, 0, 1, 0, 1], bool)
    r = lineage_split(truth, sim, seen)
    both = [(i, j) for i, j in itertools.combinations(range(9), 2) if seen[i] and seen[j]]
    touch = [(i, j) for i, j in itertools.combinations(range(9), 2) if not (seen[i] and seen[j])]
    disc = lambda ps: sum((truth[i] - truth[j]) * (sim[i] - sim[j]) < 0 for i, j in ps)  # noqa
    assert (r["pairs_seen"], r["pairs_touching"]) == (len(both), len(touch)) == (15, 21)
    assert r["discordant_seen"] == disc(both) and r["discordant_touching"] == disc(touch)
    assert r["swap_rate_seen"] == pytest.approx(disc(both) / 15)
    assert r["swap_rate_touching"] == pytest.approx(disc(touch) / 21)
    assert r["tau"] == pytest.approx(_tau(truth, sim))
    assert r["tau_seen"] == pytest.approx(_tau(truth[seen], sim[seen]))
    assert r["discordant_seen"] + r["discordant_touching"] > 0  # the check has something to count
    none_seen = lineage_split(truth, sim, np.zeros(9, bool))
    assert none_seen["tau_seen"] is None and none_seen["swap_rate_seen"] is None
    with pytest.raises(ValueError, match="truth, sim, seen: expected equal shapes"):
        lineage_split(truth, sim, seen[:5])


def test_seen_lineage_of_the_shipped_zoos():
    """Ant's one test policy of a learner run with no training policy is ant-051 (PPO seed 5);
    a training policy's lineage is always seen."""
    zoo = load_zoo("ant")
    test = zoo.split_ids("test")
    unseen = [n for n, ok in zip(zoo.policy_names(test), zoo.seen_lineage(test), strict=True)
              if not ok]
    assert unseen == ["ant-051"] and zoo.lineage(51) == ("ppo", 5)
    assert all(zoo.seen_lineage(zoo.split_ids("train")))
    assert zoo.seen_lineage(names_to_zoo_ids(["ant-051", "ant-002"])) == [False, True]


def _result(task, names, truth, lanes, data_seed, **extra):
    return {"task": task, "test_policy_names": names, "true_value": list(truth),
            "true_value_undiscounted": list(truth), "data_seed": data_seed,
            "lanes": {k: {"sim_value": list(v)} for k, v in lanes.items()}, **extra}


def test_lineage_analysis_script(tmp_path, capsys):
    """Per data seed and method the mean over lanes of lineage_split; the oracle from a result's
    oracle_sim_value or from an --oracle file (policies matched by name); joined results must
    share their truths; the printed seen-only gap to the oracle."""
    mod = load_script("lineage_analysis")
    names = ["ant-002", "ant-051", "ant-005", "ant-009"]  # ant-051: the unseen lineage
    truth = np.array([1.0, 4.0, 2.0, 3.0])
    a, b = [1.0, 2.5, 2.0, 3.0], [1.0, 4.0, 3.5, 3.0]
    r0 = _result("ant", names, truth, {"rl2s/0": a, "rl2s/1": b}, 0)
    r7 = _result("ant", names, truth, {"rl2s/0": b}, 7,
                 oracle_sim_value=[[1.0, 4.0, 2.0, 3.0]])
    order = [3, 0, 1, 2]
    oracle0 = {"data_seed": 0, "policy_names": [names[i] for i in order],
               "rows": [{"horizon": 1000, "n_episodes": 64,  # oracle_row: the most episodes
                         "oracle_value": [float(v) for v in np.array(b)[order]]},
                        {"horizon": 1000, "n_episodes": 16, "oracle_value": [4.0, 3.0, 2.0, 1.0]}]}
    out = mod.analyse([r0, r7], {0: oracle0}, ("rl2s",))
    seen = np.array([True, False, True, True])
    want = [lineage_split(truth, s, seen) for s in (a, b)]
    got = out[0]["methods"]["rl2s"]
    assert got["lanes"] == 2 and out[0]["unseen"] == ["ant-051"]
    for k in ("tau", "tau_seen", "swap_rate_seen", "swap_rate_touching"):
        assert got[k] == pytest.approx(np.mean([w[k] for w in want]))
    assert out[0]["methods"]["oracle"]["tau"] == pytest.approx(lineage_split(truth, b, seen)[
        "tau"])  # the file's values reordered to the result's policies
    assert out[7]["methods"]["oracle"]["tau"] == pytest.approx(1.0)
    print(mod.report("ant", out))
    text = capsys.readouterr().out
    assert "ant, data seed 0: 4 test policies, 1 of lineages absent from training (ant-051)" in text
    gap = got["tau_seen"] - out[0]["methods"]["oracle"]["tau_seen"]
    assert f"seen: {gap:+.3f} vs the oracle" in text
    other = dict(r0, true_value_undiscounted=[1.0, 4.0, 2.0, 9.0])
    with pytest.raises(ValueError, match="true_value_undiscounted: the data seed 0 results"):
        mod.analyse([r0, other], {}, ("rl2s",))
    with pytest.raises(ValueError, match="policy_names: expected the result's 4 test"):
        mod.analyse([r0], {0: dict(oracle0, policy_names=names[:3])}, ("rl2s",))
    path = tmp_path / "r.json"
    path.write_text(json.dumps(r7))
    assert mod.main([str(path), "--json", str(tmp_path / "a.json")]) == 0
    assert json.loads((tmp_path / "a.json").read_text())["7"]["n_unseen"] == 1


def test_lineage_analysis_reads_the_intervals_by_lineage():
    """interval_cells: per (lane, policy), seen and unseen apart, covered / width / error over
    the truth's range and the flag, an unbounded end an infinite width; None for lanes without
    intervals; pooled_interval_lines pools them over data seeds."""
    mod = load_script("lineage_analysis")
    truth = np.array([0.0, 10.0, 20.0])
    seen = np.array([True, False, True])
    lane = {"trust": {"interval": [[-1.0, 1.0], [None, 30.0], [21.0, 23.0]],
                      "sim_value": [0.5, 14.0, 22.0], "trusted": [True, False, True]}}
    c = mod.interval_cells([lane, lane], truth, seen)
    assert c["seen"]["covered"] == [True, False, True, False]
    assert c["seen"]["width"] == pytest.approx([0.1, 0.1, 0.1, 0.1])
    assert c["seen"]["error"] == pytest.approx([0.025, 0.1, 0.025, 0.1])
    assert c["unseen"] == {"covered": [True, True], "width": [np.inf, np.inf],
                           "error": pytest.approx([0.2, 0.2]), "flagged": [True, True]}
    assert mod.interval_cells([lane, {"trust": {"skipped": "x"}}], truth, seen) is None
    lines = mod.pooled_interval_lines({7: {"intervals": {"rl2s": c}}, 23: {"intervals": {
        "rl2s": c}}})
    assert lines[1].startswith("  rl2s     coverage 0.500 / 1.000 | median width / range "
                               "0.100 / inf | flagged 0.000 / 1.000") and "(n 8 / 4)" in lines[1]
