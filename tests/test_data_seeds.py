"""Ranking over data collections (issue 66): merge_results.py's by_data_seed, the table
"Ranking over data seeds" and experiments/ranking_analysis.py's swap arithmetic. Pure Python
and NumPy on tiny synthetic results: no JAX program runs."""

import json

import numpy as np
import pytest
from experiment_scripts import load_script

from rl2s_jax.paper import data_seeds as dseeds
from rl2s_jax.paper.data_seeds import data_seed_of

NAMES = ["p0", "p1", "p2"]


def _run(methods, taus, mvds, data_seed=None, names=NAMES, **extra):
    """A paper.py result of one data seed: per_seed lists of tau and MVD per method."""
    cmd = "python experiments/paper.py --task hopper --seeds 2" + (
        "" if data_seed is None else f" --data-seed {data_seed}")
    per = {m: {"kendall_tau": list(t), "mvd": list(v)}
           for m, t, v in zip(methods, taus, mvds, strict=True)}
    return {"task": "hopper", "command": cmd, "hardware": "H200", "test_policy_names": names,
            "per_seed": per, "methods": {}, "zoo_sha256": "abc", **extra}


def test_data_seed_of_reads_the_field_or_the_command():
    assert dseeds.data_seed_of({"data_seed": 23, "command": "x --data-seed 7"}) == 23
    assert dseeds.data_seed_of({"command": "python experiments/paper.py --data-seed 7"}) == 7
    assert dseeds.data_seed_of({"command": "paper.py --data-seed=9 && paper.py --data-seed 9"}
                               ) == 9
    assert dseeds.data_seed_of({"command": "python experiments/paper.py --task ant"}) == 0
    with pytest.raises(ValueError, match="different --data-seed"):
        dseeds.data_seed_of({"command": "paper.py --data-seed 7 && paper.py"})


def test_merge_results_records_each_data_seed(tmp_path):
    """--data-seed-run: one entry per data seed, a method's numbers (means over its seeds)
    from the first run of that data seed that has it, the oracle and noise ceiling only where
    measured; --keep leaves the zoo the result was measured on; a later --paper run of another
    data seed is added beside the entries recorded before."""
    mr = load_script("merge_results")
    out = tmp_path / "out"
    out.mkdir()
    old = {"task": "hopper", "methods": {}, "per_seed": {}, "zoo_sha256": "old-zoo"}
    (out / "hopper.json").write_text(json.dumps(old))
    adv7 = _run(("rl2s", "gail"), ([0.8, 0.9], [0.7, 0.7]), ([100.0, 200.0], [50.0, 70.0]), 7)
    mle7 = _run(("rl2s", "bc", "rl2s-bc"), ([0.1, 0.1], [0.6, 0.8], [0.5, 0.5]),
                ([1.0, 1.0], [10.0, 30.0], [5.0, 5.0]), 7)
    mle7["command"] += " --families mle"
    orc0 = _run(("rl2s", "gail", "bc", "rl2s-bc", "oracle"), ([0.9, 0.9],) * 5,
                ([1.0, 3.0],) * 5, noise_ceiling={"n_truth": 128, "n_sim": 128, "kendall_tau": {
                    "mean": 0.97, "lo": 0.9, "hi": 1.0}})
    paths = []
    for i, r in enumerate((adv7, mle7, orc0)):
        paths += ["--data-seed-run", str(tmp_path / f"r{i}.json")]
        (tmp_path / f"r{i}.json").write_text(json.dumps(r))
    assert mr.main(["--task", "hopper", "--keep", "--out", str(out), *paths]) == 0
    got = json.loads((out / "hopper.json").read_text())
    assert got["zoo_sha256"] == "old-zoo"  # --keep: not the shipped zoo's stamp
    seven = got["by_data_seed"]["7"]
    assert seven["rl2s"] == {"kendall_tau": pytest.approx(0.85), "mvd": 150.0, "seeds": 2}
    assert seven["gail"]["kendall_tau"] == pytest.approx(0.7)
    assert seven["bc"] == {"kendall_tau": pytest.approx(0.7), "mvd": 20.0, "seeds": 2}
    assert "oracle" not in seven and "noise_ceiling" not in seven
    assert seven["command"] == f"{adv7['command']} && {mle7['command']}"
    assert seven["test_policy_names"] == NAMES
    zero = got["by_data_seed"]["0"]
    assert zero["oracle"] == {"kendall_tau": 0.9, "seeds": 2}
    assert zero["noise_ceiling"] == {"mean": 0.97, "lo": 0.9, "hi": 1.0, "n_truth": 128,
                                     "n_sim": 128}
    assert list(got["by_data_seed"]) == ["0", "7"]
    # a protocol run of data seed 23 through --paper: recorded, the earlier seeds kept
    run23 = {**_run(("rl2s", "gail"), ([0.5, 0.7], [0.6, 0.6]), ([9.0, 9.0],) * 2, 23),
             "sizes": {}, "zoo_sha256": mr.zoo_sha256("hopper")}
    (tmp_path / "p23.json").write_text(json.dumps(run23))
    assert mr.main(["--task", "hopper", "--paper", str(tmp_path / "p23.json"), "--out",
                    str(out)]) == 0
    got = json.loads((out / "hopper.json").read_text())
    assert list(got["by_data_seed"]) == ["0", "7", "23"]
    assert got["by_data_seed"]["23"]["rl2s"]["kendall_tau"] == pytest.approx(0.6)
    assert got["by_data_seed"]["7"] == seven
    # oracle_check.py --data-seed 7: into data seed 7's entry, not the task's own oracle row
    orc = {"data_seed": 7, "policy_names": NAMES, "command": "oracle_check.py --data-seed 7",
           "hardware": "H200", "jax_version": "0.11", "policies": 3,
           "rows": [{"horizon": 1000, "n_episodes": 64, "metrics": {"kendall_tau": 0.95}}]}
    (tmp_path / "orc7.json").write_text(json.dumps(orc))
    assert mr.main(["--task", "hopper", "--keep", "--out", str(out), "--oracle",
                    str(tmp_path / "orc7.json")]) == 0
    got = json.loads((out / "hopper.json").read_text())
    assert got["by_data_seed"]["7"]["oracle"]["kendall_tau"] == 0.95
    assert "oracle" not in got["per_seed"]  # the task's rows are data seed 23's run
    # data seed 7 recorded again (a repeat run): its methods replaced, its oracle kept
    adv7b = _run(("rl2s",), ([0.2, 0.4],), ([1.0, 1.0],), 7)
    (tmp_path / "adv7b.json").write_text(json.dumps(adv7b))
    assert mr.main(["--task", "hopper", "--keep", "--out", str(out), "--data-seed-run",
                    str(tmp_path / "adv7b.json")]) == 0
    again = json.loads((out / "hopper.json").read_text())["by_data_seed"]["7"]
    assert again["rl2s"]["kendall_tau"] == pytest.approx(0.3) and "gail" not in again
    assert again["oracle"] == got["by_data_seed"]["7"]["oracle"]
    # another test split is refused, naming the field
    other = _run(("rl2s",), ([0.5, 0.5],), ([1.0, 1.0],), 5, names=["p0", "p1", "q9"])
    (tmp_path / "other.json").write_text(json.dumps(other))
    with pytest.raises(SystemExit, match="by-data-seed: by_data_seed: data seed 5 has other"):
        mr.main(["--task", "hopper", "--keep", "--out", str(out), "--data-seed-run",
                 str(tmp_path / "other.json")])


def test_merge_results_carries_a_data_seed_runs_trust(tmp_path):
    """--data-seed-run: its trust block becomes the task's "trust" (marked with its data seed)
    where the task has none of its own; the task's own trust is kept; two runs' blocks are
    refused."""
    mr = load_script("merge_results")
    out = tmp_path / "out"
    out.mkdir()
    block = {"level": 0.9, "coverage": 0.85, "width_over_range": 0.2, "worst_flagged": 1.0,
             "runs": 2, "command": "paper.py --data-seed 23"}
    run = {**_run(("rl2s",), ([0.9, 0.8],), ([1.0, 1.0],), 23), "trust": {"rl2s": block},
           "trust_calibration": {"origins": [0, 1]}}
    (tmp_path / "r.json").write_text(json.dumps(run))
    (out / "hopper.json").write_text(json.dumps({"task": "hopper", "per_seed": {}}))
    args = ["--task", "hopper", "--keep", "--out", str(out), "--data-seed-run",
            str(tmp_path / "r.json")]
    assert mr.main(args) == 0
    got = json.loads((out / "hopper.json").read_text())
    assert got["trust"] == {"rl2s": {**block, "data_seed": 23}}
    assert got["trust_calibration"] == {"origins": [0, 1], "data_seed": 23}
    own = {"rl2s": {**block, "coverage": 0.5}}
    (out / "hopper.json").write_text(json.dumps({"task": "hopper", "per_seed": {}, "trust": own}))
    assert mr.main(args) == 0
    assert json.loads((out / "hopper.json").read_text())["trust"] == own
    (tmp_path / "r2.json").write_text(json.dumps({**run, "test_policy_names": NAMES}))
    (out / "hopper.json").write_text(json.dumps({"task": "hopper", "per_seed": {}}))
    with pytest.raises(SystemExit, match="trust: two --data-seed-runs of one data seed"):
        mr.main([*args, "--data-seed-run", str(tmp_path / "r2.json")])


def _trust_run(ds: int, truth, sims, covered, flagged) -> dict:
    """A paper.py result of data seed ``ds`` with rl2s lanes' trust entries: sims [S, P]."""
    truth = np.asarray(truth, float)
    lanes = {f"rl2s/{s}": {"trust": {
        "level": 0.9, "coverage": covered[s], "width_over_range": 0.1 * (s + 1),
        "worst": {"flagged": flagged[s]}, "q_infinite": False, "sim_value": list(sims[s])}}
        for s in range(len(sims))}
    return {**_run(("rl2s",), ([0.9] * len(sims),), ([1.0] * len(sims),), ds),
            "true_value": truth.tolist(), "lanes": lanes,
            "trust": {"rl2s": {"coverage": float(np.mean(covered)), "runs": len(sims)}}}


def test_pooled_trust_over_data_seeds_against_numpy(tmp_path):
    """pooled_trust: means over every run of both data seeds, and the seed-spread interval
    pooled on each data seed's truth range, scaled to the pooled coverage (NumPy reference);
    merge_results records it for two --data-seed-runs."""
    rng = np.random.default_rng(3)
    t7, t23 = np.array([0.0, 50.0, 100.0]), np.array([10.0, 40.0, 210.0])
    s7, s23 = t7 + rng.normal(0, 9, (2, 3)), t23 + rng.normal(0, 20, (3, 3))
    runs = [_trust_run(7, t7, s7, [1.0, 2 / 3], [1.0, 0.0]),
            _trust_run(23, t23, s23, [1 / 3, 1.0, 1.0], [1.0, 1.0, 0.0])]
    b = dseeds.pooled_trust(runs)["rl2s"]
    cov = np.mean([1.0, 2 / 3, 1 / 3, 1.0, 1.0])
    assert b["coverage"] == pytest.approx(cov) and b["runs"] == 5
    assert b["worst_flagged"] == pytest.approx(3 / 5)
    assert b["width_over_range"] == pytest.approx(np.mean([0.1, 0.2, 0.1, 0.2, 0.3]))
    v, sd, tr = [], [], []
    for t, sims in ((t7, s7), (t23, s23)):
        r = t.max() - t.min()
        v += list((sims / r).ravel())
        sd += list(np.tile(sims.std(0, ddof=1) / r, len(sims)))
        tr += list(np.tile(t / r, len(sims)))
    need = np.sort(np.abs(np.subtract(v, tr)) / sd)
    k = need[int(np.ceil(cov * need.size)) - 1]
    want = np.mean(2 * k * np.array(sd))
    assert b["seed_spread"]["scaled_width_over_range"] == pytest.approx(want)
    assert b["narrower_than_seed_spread"] == (b["width_over_range"]
                                             < b["seed_spread"]["scaled_width_over_range"])
    assert b["data_seeds"] == [7, 23] and b["by_data_seed"]["7"]["runs"] == 2
    assert "evaluated" not in b  # no run evaluated a set
    for r, cov_e in zip(runs, ([0.5, 1.0], [0.25, 0.75, 1.0]), strict=True):
        for lane, c in zip(sorted(r["lanes"]), cov_e, strict=True):
            r["lanes"][lane]["trust"]["evaluated"] = {
                "n": 4, "coverage": c, "width_over_range": 0.2, "mean_width": 3.0,
                "worst": {"flagged": c == 1.0}}
    ev = dseeds.pooled_trust(runs)["rl2s"]["evaluated"]
    assert ev["coverage"] == pytest.approx(np.mean([0.5, 1.0, 0.25, 0.75, 1.0]))
    assert ev["runs"] == 5 and ev["worst_flagged"] == pytest.approx(2 / 5) and ev["n"] == 4
    # each data seed's seeds as one estimate: pooled as a mean over the data seeds, where
    # every data seed has one; the table shows it against the bars
    assert "seeds_combined" not in dseeds.pooled_trust(runs)["rl2s"]
    for r, (c, w, fl) in zip(runs, ((0.9, 0.2, 1.0), (0.7, 0.4, 0.0)), strict=True):
        r["trust"]["rl2s"]["seeds_combined"] = {"seeds": len(r["lanes"]), "coverage": c,
                                                "width_over_range": w, "worst_flagged": fl}
    sc = dseeds.pooled_trust(runs)["rl2s"]["seeds_combined"]
    assert sc["coverage"] == pytest.approx(0.8) and sc["width_over_range"] == pytest.approx(0.3)
    assert sc["worst_flagged"] == pytest.approx(0.5) and sc["seeds"] == [2, 3]
    assert sc["data_seeds"] == [7, 23]
    assert dseeds.combined_cell(sc) == "0.800 ✗, 0.300 ✗"
    assert dseeds.combined_cell({**sc, "coverage": 0.85, "width_over_range": 0.25}) == \
        "0.850 ✓, 0.250 ✓"
    row = dseeds.trust_rows({"hopper": {"trust": dseeds.pooled_trust(runs)}}, ["hopper"])[2]
    assert "| 0.800 ✗, 0.300 ✗ |" in row and dseeds.combined_cell(None) == "-"
    with pytest.raises(ValueError, match="one run per data seed"):
        dseeds.pooled_trust([runs[0], runs[0]])
    mr = load_script("merge_results")
    (tmp_path / "hopper.json").write_text(json.dumps({"task": "hopper", "per_seed": {}}))
    args = ["--task", "hopper", "--keep", "--out", str(tmp_path)]
    for r in runs:
        (tmp_path / f"r{data_seed_of(r)}.json").write_text(json.dumps(
            {**r, "trust_calibration": {"n": data_seed_of(r)}}))
        args += ["--data-seed-run", str(tmp_path / f"r{data_seed_of(r)}.json")]
    assert mr.main(args) == 0
    got = json.loads((tmp_path / "hopper.json").read_text())
    assert got["trust"]["rl2s"]["coverage"] == pytest.approx(cov)
    assert got["trust_calibration"] == {"by_data_seed": {"7": {"n": 7}, "23": {"n": 23}}}



def test_evaluated_run_pools_a_repeats_evaluated_sets(tmp_path):
    """merge_results --evaluated-run: a repeat of a --data-seed-run (same test policies and
    per-seed numbers) with --trust-evaluated lanes gives each method's trust "evaluated",
    pooled over its lanes as trust_phase.method_evaluated pools them, naming its data seeds;
    a run of other simulators or of a data seed with no --data-seed-run is refused."""
    from rl2s_jax.paper.trust_phase import method_evaluated

    t7, t23 = np.array([0.0, 50.0, 100.0]), np.array([10.0, 40.0, 210.0])
    runs = [_trust_run(7, t7, np.tile(t7, (2, 1)), [1.0, 1.0], [1.0, 0.0]),
            _trust_run(23, t23, np.tile(t23, (2, 1)), [1.0, 0.5], [1.0, 1.0])]
    result = {"trust": dseeds.pooled_trust(runs)}
    again = json.loads(json.dumps(runs[1]))
    covs = [0.25, 0.75]
    for lane, c in zip(sorted(again["lanes"]), covs, strict=True):
        again["lanes"][lane]["trust"]["evaluated"] = {
            "n": 4, "coverage": c, "width_over_range": 0.1 + c, "mean_width": 2.0,
            "worst": {"flagged": c > 0.5}}
    dseeds.evaluated_trust(result, runs, [again])
    ev = result["trust"]["rl2s"]["evaluated"]
    want = method_evaluated([again["lanes"][k]["trust"] for k in sorted(again["lanes"])])
    assert ev == {**want, "data_seeds": [23]}
    assert ev["coverage"] == pytest.approx(0.5) and ev["width_over_range"] == pytest.approx(0.6)
    assert ev["worst_flagged"] == pytest.approx(0.5) and ev["runs"] == 2
    other = json.loads(json.dumps(again))
    other["per_seed"]["rl2s"]["kendall_tau"][0] = 0.1
    with pytest.raises(ValueError, match="evaluated-run: per_seed: differs from the data seed 23"):
        dseeds.evaluated_trust(result, runs, [other])
    with pytest.raises(ValueError, match="no --data-seed-run of data seed 23"):
        dseeds.evaluated_trust(result, runs[:1], [again])
    mr = load_script("merge_results")
    (tmp_path / "hopper.json").write_text(json.dumps({"task": "hopper", "per_seed": {}}))
    paths = []
    for name, r in (("r7", runs[0]), ("r23", runs[1]), ("e23", again)):
        (tmp_path / f"{name}.json").write_text(json.dumps(r))
        paths.append(str(tmp_path / f"{name}.json"))
    assert mr.main(["--task", "hopper", "--keep", "--out", str(tmp_path), "--data-seed-run",
                    paths[0], "--data-seed-run", paths[1], "--evaluated-run", paths[2]]) == 0
    got = json.loads((tmp_path / "hopper.json").read_text())
    assert got["trust"]["rl2s"]["evaluated"]["data_seeds"] == [23]
    row = dseeds.trust_rows({"hopper": got}, ["hopper"])[2]
    assert row.endswith("| 0.500 ✗, 0.600 ✗ (23) |")
    assert dseeds.evaluated_cell(None) == "-"


def test_data_seed_entry_refuses_mixed_runs():
    a = _run(("rl2s",), ([0.5, 0.5],), ([1.0, 1.0],), 7)
    with pytest.raises(ValueError, match="data_seed: the runs are of different data seeds"):
        dseeds.data_seed_entry([a, _run(("bc",), ([0.5, 0.5],), ([1.0, 1.0],), 8)])
    with pytest.raises(ValueError, match="test_policy_names"):
        dseeds.data_seed_entry([a, _run(("bc",), ([0.5],), ([1.0],), 7, names=["x"])])
    # an oracle row merged from another collection (merge_results' "oracle" provenance) and
    # its ceiling are not this data seed's
    other = {**_run(("rl2s", "oracle"), ([0.5], [0.9]), ([1.0], [1.0]), 7),
             "oracle": {"source": "another run"}, "noise_ceiling": {"kendall_tau": {
                 "mean": 0.9, "lo": 0.8, "hi": 1.0}}}
    _, entry = dseeds.data_seed_entry([other])
    assert "oracle" not in entry and "noise_ceiling" not in entry
    with pytest.raises(ValueError, match="per_seed: no run has any of"):
        dseeds.data_seed_entry([_run(("oracle",), ([0.5],), ([1.0],), 7)])
    # a run cut off after its oracle (paper.py measures it before training): oracle only
    cut = {**_run(("rl2s", "oracle"), ([], [0.9, 0.8]), ([], [1.0, 1.0]), 23), "complete": False}
    _, entry = dseeds.data_seed_entry([cut])
    assert entry["oracle"] == {"kendall_tau": pytest.approx(0.85), "seeds": 2}
    assert "rl2s" not in entry and entry["complete"] is False
    assert "not measured" in dseeds.oracle_bar("hopper", entry)
    # with a whole run of the methods beside it the entry is complete (its oracle is whole)
    full = _run(("rl2s",), ([0.7, 0.8],), ([1.0, 1.0],), 23)
    _, entry = dseeds.data_seed_entry([full, cut])
    assert entry["oracle"]["kendall_tau"] == pytest.approx(0.85) and "complete" not in entry
    _, entry = dseeds.data_seed_entry([{**full, "complete": False}, cut])
    assert entry["complete"] is False


def test_oracle_check_output_fills_its_data_seed():
    """oracle_check.py --data-seed: its longest-horizon, most-episode row's tau and ceiling."""
    result = {"by_data_seed": {"7": {"rl2s": {"kendall_tau": 0.8, "seeds": 3},
                                     "test_policy_names": NAMES}}}
    row = lambda h, n, tau: {"horizon": h, "n_episodes": n, "metrics": {"kendall_tau": tau},
                             "noise_ceiling": {"n_truth": 256, "n_sim": n, "kendall_tau": {
                                 "mean": tau + 0.01, "lo": 0.8, "hi": 1.0}}}
    orc = {"data_seed": 7, "policy_names": NAMES, "command": "oracle_check.py --data-seed 7",
           "rows": [row(1000, 64, 0.90), row(1000, 256, 0.93), row(500, 512, 0.50)]}
    dseeds.oracle_into_data_seed(result, orc)
    entry = result["by_data_seed"]["7"]
    assert entry["oracle"]["kendall_tau"] == 0.93
    assert entry["noise_ceiling"]["mean"] == pytest.approx(0.94)
    assert entry["noise_ceiling"]["n_sim"] == 256
    before = json.dumps(result)
    dseeds.oracle_into_data_seed(result, {k: v for k, v in orc.items() if k != "data_seed"})
    assert json.dumps(result) == before  # no data seed: its own collection, left out
    with pytest.raises(ValueError, match="no protocol run of data seed 8"):
        dseeds.oracle_into_data_seed(result, {**orc, "data_seed": 8})
    with pytest.raises(ValueError, match="its policies differ"):
        dseeds.oracle_into_data_seed(result, {**orc, "policy_names": ["p0"]})


def test_ranking_over_data_seeds_table():
    """Per task and method the tau of each data seed, the mean over data seeds with its 95%
    t-interval (checked against NumPy and the t quantile 12.706 for 2 values), 'not measured'
    where nothing ran, and the oracle bar at 0.03 (Ant 0.05)."""
    def entry(tau, oracle=None, ceiling=None):
        e = {"rl2s": {"kendall_tau": tau, "mvd": 1.0, "seeds": 3},
             "gail": {"kendall_tau": tau - 0.1, "mvd": 1.0, "seeds": 3}}
        if oracle is not None:
            e["oracle"] = {"kendall_tau": oracle, "seeds": 1}
        if ceiling is not None:
            e["noise_ceiling"] = {"mean": ceiling, "lo": 0.9, "hi": 1.0}
        return e

    results = {"hopper": {"by_data_seed": {"0": entry(0.90, 0.94), "7": entry(0.94)}},
               "ant": {"by_data_seed": {"7": entry(0.80, 0.84, 0.93)}},
               "walker2d": {"per_seed": {}}}
    rows = dseeds.data_seed_rows(results, ("hopper", "walker2d", "halfcheetah", "ant"))
    assert rows[0].startswith("| task | method | data seed 0 | data seed 7 | over data seeds")
    by = {(r.split(" | ")[0][2:], r.split(" | ")[1]): r for r in rows[2:]}
    assert not any(k[0] == "walker2d" for k in by)  # no by_data_seed: no rows
    x = np.array([0.90, 0.94])
    half = 12.7062047 * x.std(ddof=1) / np.sqrt(2)
    lo, hi = x.mean() - half, min(x.mean() + half, 1.0)  # clipped to tau's range
    assert (f"| hopper | rl2s | 0.900 (3 seeds) | 0.940 (3 seeds) | {x.mean():.3f} "
            f"[{lo:.3f}, {hi:.3f}] (2 data seeds) | 0: MISSED (-0.040 vs -0.03); 7: not "
            "measured (no oracle) |") == by[("hopper", "rl2s")]
    assert "| hopper | bc | not measured | not measured | not measured |" in by[("hopper", "bc")]
    assert by[("hopper", "oracle / noise ceiling")].startswith(
        "| hopper | oracle / noise ceiling | 0.940 (1 seed) / not measured | not measured / "
        "not measured | 0.940 (1 data seed) |")
    # Ant's margin is 0.05: -0.04 meets it
    assert by[("ant", "rl2s")].endswith("| 7: met (-0.040 vs -0.05) |")
    assert "| not measured | 0.800 (3 seeds) | 0.800 (1 data seed) |" in by[("ant", "rl2s")]
    assert "0.840 (1 seed) / 0.930 [0.90, 1.00]" in by[("ant", "oracle / noise ceiling")]
    assert dseeds.data_seed_rows({"hopper": {}}, ("hopper",)) == []


def test_paper_tables_renders_the_data_seed_table(tmp_path):
    pt = load_script("paper_tables")
    r = {"task": "hopper", "methods": {}, "per_seed": {"rl2s": {"kendall_tau": [0.9]}},
         "by_data_seed": {"7": {"rl2s": {"kendall_tau": 0.9, "mvd": 1.0, "seeds": 1}}}}
    text = pt.render({"hopper": r}, "x")
    assert "### Ranking over data seeds" in text
    table = text.split("### Ranking over data seeds")[1].split("###")[0]
    assert "| hopper | rl2s | 0.900 (1 seed) | 0.900 (1 data seed) |" in table
    assert "### Ranking over data seeds" not in pt.render({"hopper": {**r, "by_data_seed": {}}},
                                                          "x")


# ------------------------------------------------------------------ ranking_analysis.py


def test_swaps_split_discordant_pairs_by_the_truths_noise():
    """A hand-made case: truth [0, 1, 10, 20], se 1 each (noise band 2 sqrt(2) = 2.83): the
    simulator swaps (0, 1) (|dV| 1: within noise) and (2, 3) (|dV| 10: real); 6 pairs, tau
    (4 - 2) / 6, each swap costs 2 / 6. Checked against a plain NumPy double loop."""
    ra = load_script("ranking_analysis")
    truth, se, sim = [0.0, 1.0, 10.0, 20.0], [1.0, 1.0, 1.0, 1.0], [1.0, 0.0, 21.0, 19.0]
    sw = ra.swaps(truth, se, sim)
    assert sw["noise"] == [(0, 1)] and sw["real"] == [(2, 3)]
    assert sw["pairs"] == 6 and sw["tau"] == pytest.approx(2 / 6)
    assert sw["tau_lost_noise"] == pytest.approx(2 / 6)
    assert sw["tau_lost_real"] == pytest.approx(2 / 6)
    rng = np.random.default_rng(3)
    t, e, s = rng.normal(0, 5, 9), rng.uniform(0.5, 3, 9), rng.normal(0, 5, 9)
    noise, real = [], []
    for i in range(9):
        for j in range(i + 1, 9):
            if (t[i] - t[j]) * (s[i] - s[j]) < 0:
                band = 2 * np.sqrt(e[i] ** 2 + e[j] ** 2)
                (noise if abs(t[i] - t[j]) < band else real).append((i, j))
    sw = ra.swaps(t, e, s)
    assert sw["noise"] == noise and sw["real"] == real
    assert 1 - sw["tau"] == pytest.approx(sw["tau_lost_noise"] + sw["tau_lost_real"])
    tied = ra.swaps(truth, se, [0.0, 0.0, 20.0, 20.0])  # a tie is no swap (tau-a)
    assert tied["noise"] == [] and tied["real"] == []
    with pytest.raises(ValueError, match="truth, se, sim: expected equal shapes"):
        ra.swaps(truth, se[:3], sim)
    with pytest.raises(ValueError, match="se >= 0"):
        ra.swaps(truth, [-1.0, 1.0, 1.0, 1.0], sim)


def test_ranking_analysis_per_data_seed_and_between_truths(tmp_path, capsys):
    """Two data seeds' results with true_value_se: per method the tau lost to each kind of
    swap, the swaps per policy, the tau without each policy, and the truths' z between seeds."""
    ra = load_script("ranking_analysis")

    def result(ds, truth, sims):
        lanes = {f"rl2s/{s}": {"sim_value": v, "sim_length": [10.0] * 4}
                 for s, v in enumerate(sims)}
        return {"task": "hopper", "command": f"paper.py --data-seed {ds}", "lanes": lanes,
                "true_value": truth, "true_value_se": [1.0] * 4, "true_length": [9.0] * 4,
                "test_policy_names": ["a", "b", "c", "d"],
                "sizes": {"eval_episodes": 16, "value_episodes": 16}}

    r0 = result(0, [0.0, 1.0, 10.0, 20.0], [[1.0, 0.0, 21.0, 19.0], [1.0, 0.0, 10.0, 20.0]])
    r7 = result(7, [0.0, 2.0, 10.0, 23.0], [[0.0, 1.0, 10.0, 20.0]])
    paths = []
    for i, r in enumerate((r0, r7)):
        paths.append(str(tmp_path / f"r{i}.json"))
        (tmp_path / f"r{i}.json").write_text(json.dumps(r))
    assert ra.main([*paths, "--methods", "rl2s", "--n-rep", "50", "--json",
                    str(tmp_path / "a.json")]) == 0
    out = json.loads((tmp_path / "a.json").read_text())
    zero = out["data_seeds"]["0"]
    m = zero["methods"]["rl2s"]
    assert m["tau"] == pytest.approx((2 / 6 + 4 / 6) / 2)
    assert m["tau_lost_noise"] == pytest.approx(2 / 6) and m["tau_lost_real"] == pytest.approx(
        1 / 6)
    assert zero["noise_swaps_per_policy"] == [2, 2, 0, 0]
    assert zero["real_swaps_per_policy"] == [0, 0, 1, 1]
    # without a: the first lane keeps its swap c-d (tau 1/3 of 3 pairs), the second none (1);
    # without c: each keeps one swap (1/3)
    assert m["tau_without"][0] == pytest.approx((1 / 3 + 1) / 2)
    assert m["tau_without"][2] == pytest.approx(1 / 3)
    assert zero["se_source"].startswith("true_value_se")
    assert m["trust"] is None and m["most_real_swaps"] is None and m["worst_in_top"] is None
    assert "member sd" not in zero["relations"] and "support" not in zero["relations"]
    z = np.array([0.0, -1.0, 0.0, -3.0]) / np.sqrt(2.0)
    between = out["truth_between_data_seeds"][0]
    assert between["rms_z"] == pytest.approx(np.sqrt(np.mean(z ** 2)))
    assert between["tau_truth_vs_truth"] == 1.0
    printed = capsys.readouterr().out
    assert "hopper, data seed 0: 4 test policies (6 pairs)" in printed
    assert "real swaps most often (of 2 lanes): c-d 1" in printed
    with pytest.raises(SystemExit, match="methods: expected a comma list"):
        ra.main([paths[0], "--methods", "nope"])


def _hand_spearman(x, y):
    """Pearson of average ranks, in plain Python (ties share the mean of their ranks)."""
    def ranks(v):
        return [1 + sum(w < u for w in v) + (sum(w == u for w in v) - 1) / 2 for u in v]
    rx, ry = ranks(x), ranks(y)
    mx, my = sum(rx) / len(rx), sum(ry) / len(ry)
    cov = sum((a - mx) * (b - my) for a, b in zip(rx, ry, strict=True))
    return cov / (sum((a - mx) ** 2 for a in rx) * sum((b - my) ** 2 for b in ry)) ** 0.5


def test_ranking_analysis_relates_real_swaps_to_the_lanes_trust(tmp_path, capsys):
    """Lanes with issue 64's trust (support, member_sd, sim_value, trusted per policy): their
    means per policy, Spearman of real swaps with them, the swap carrier's ranks and the
    worst-|error| policy's rank by member_sd, each against a hand computation; a method
    without trust keeps the old output; a trust list of the wrong length is refused."""
    ra = load_script("ranking_analysis")
    truth = [0.0, 10.0, 20.0, 30.0]  # gaps 10 > 2 sqrt(2): every swap is real
    trust = [{"member_sd": [1.0, 4.0, 2.0, 3.0], "support": [1.0, 0.5, 2.0, 0.8],
              "sim_value": [0.0, 26.0, 20.0, 30.0], "trusted": [True, False, True, True]},
             {"member_sd": [3.0, 2.0, 1.0, 2.5], "support": [1.2, 0.7, 1.0, 0.6],
              "sim_value": [9.0, 10.0, 21.0, 45.0], "trusted": [True, True, False, True]}]
    sims = [[0.0, 25.0, 20.0, 30.0], [12.0, 10.0, 20.0, 30.0]]  # swaps b-c, then a-b
    lanes = {f"rl2s/{s}": {"sim_value": v, "trust": t}
             for s, (v, t) in enumerate(zip(sims, trust, strict=True))}
    lanes["bc/0"] = {"sim_value": truth}  # an older lane: no trust
    r = {"task": "hopper", "command": "paper.py --data-seed 7", "lanes": lanes,
         "true_value": truth, "true_value_se": [1.0] * 4, "test_policy_names": list("abcd"),
         "sizes": {"eval_episodes": 16, "value_episodes": 16}}
    path = tmp_path / "r.json"
    path.write_text(json.dumps(r))
    assert ra.main([str(path), "--methods", "rl2s,bc", "--n-rep", "20", "--json",
                    str(tmp_path / "a.json")]) == 0
    seven = json.loads((tmp_path / "a.json").read_text())["data_seeds"]["7"]
    m, bc = seven["methods"]["rl2s"], seven["methods"]["bc"]
    assert m["real_swaps_per_policy"] == [1, 2, 1, 0]
    mean = lambda k: [(x + y) / 2 for x, y in zip(trust[0][k], trust[1][k], strict=True)]
    rel = [(a / max(abs(u), 1) + b / max(abs(v), 1)) / 2 for a, u, b, v in zip(
        trust[0]["member_sd"], trust[0]["sim_value"], trust[1]["member_sd"],
        trust[1]["sim_value"], strict=True)]
    assert m["trust"]["member_sd"] == pytest.approx(mean("member_sd"))
    assert m["trust"]["support"] == pytest.approx(mean("support"))
    assert m["trust"]["relative_member_sd"] == pytest.approx(rel)
    assert m["trust"]["trusted"] == pytest.approx([1.0, 0.5, 0.5, 1.0])
    assert m["support"] == pytest.approx(mean("support"))
    # b carries most real swaps (2): member_sd means [2, 3, 1.5, 2.75] -> rank 1; support
    # means [1.1, 0.6, 1.5, 0.7] -> rank 4; relative [0.67, 0.18, 0.07, 0.08] -> rank 2
    assert m["most_real_swaps"] == {"policies": [1], "real_swaps": 2, "rank_by_member_sd": [1],
                                    "rank_by_support": [4], "rank_by_relative_member_sd": [2]}
    # worst |trust sim - V|: lane 0 b (16; member_sd 4, the largest), lane 1 d (15; 2.5, the
    # second largest; by the lane's own sim_value it would be a, 12, with the largest)
    assert m["worst_in_top"] == {"lanes": 2, "top1": 1, "top2": 2, "worst": [1, 3]}
    assert bc["trust"] is None and bc["most_real_swaps"] is None and bc["worst_in_top"] is None
    real = [1, 2, 1, 0]  # bc swaps nothing
    rels = seven["relations"]
    assert rels["member sd"] == pytest.approx(_hand_spearman(real, mean("member_sd")))
    assert rels["member sd"] == pytest.approx(1.5 / 22.5 ** 0.5)
    assert rels["support"] == pytest.approx(_hand_spearman(real, mean("support")))
    assert rels["relative member sd"] == pytest.approx(_hand_spearman(real, rel))
    assert rels["true value"] == pytest.approx(_hand_spearman(real, truth))
    printed = capsys.readouterr().out
    assert "rl2s's trust: support member_sd relative trusted" in printed
    assert ("rl2s: most real swaps (2 over its lanes): b (rank by member_sd 1, relative 2, "
            "support 4 of 4); the worst-|error| policy has the largest member_sd in 1 of 2 "
            "lanes, one of the two largest in 2") in printed
    lanes["rl2s/1"]["trust"] = {**trust[1], "support": [1.0, 2.0]}
    path.write_text(json.dumps(r))
    with pytest.raises(SystemExit, match=r"lanes\[rl2s/1\]\.trust\.support: expected 4"):
        ra.main([str(path), "--methods", "rl2s", "--n-rep", "20"])


def test_zoo_standard_errors_scale_the_zoos_and_check_its_policies():
    """Without true_value_se: the zoo's return_se x sqrt(16 / value episodes) x |V| / |V
    undiscounted| (at most 1); a result of another zoo only where its returns agree."""
    from rl2s_jax.zoo.zoo import load_zoo

    ra = load_script("ranking_analysis")
    zoo = load_zoo("hopper")
    ids = list(zoo.test_ids)
    u = np.asarray(zoo.returns, np.float64)[ids]
    r = {"task": "hopper", "test_policy_names": zoo.policy_names(ids), "zoo_sha256": "old",
         "true_value_undiscounted": u.tolist(), "true_value": (0.5 * u).tolist(),
         "sizes": {"value_episodes": 64}}
    se, source = ra.standard_errors(r)
    n_zoo = int(zoo.info.get("value_episodes") or 16)
    ratio = np.where(np.abs(u) > 1e-9, 0.5, 1.0)
    want = np.asarray(zoo.return_se, np.float64)[ids] * np.sqrt(n_zoo / 64) * ratio
    np.testing.assert_allclose(se, want, rtol=1e-6)
    assert source.startswith("zoo return_se")
    r["true_value_undiscounted"] = (u + 1e4).tolist()
    with pytest.raises(ValueError, match="zoo_sha256: the result has no true_value_se"):
        ra.standard_errors(r)
    assert ra.standard_errors({**r, "true_value_se": [2.0]})[0].tolist() == [2.0]


def _oracle_case():
    """A data seed 7 result (64 truth episodes, its own SEs [3, 3, 1, 1]) and its oracle run
    (32 truth episodes, policies in reverse order, SEs [1, 1, 8, 8] for a-d)."""
    truth, und = [0.0, 5.0, 10.0, 20.0], [0.0, 6.0, 12.0, 25.0]
    r = {"task": "hopper", "command": "paper.py --data-seed 7", "true_value": truth,
         "true_value_undiscounted": und, "true_value_se": [3.0, 3.0, 1.0, 1.0],
         "test_policy_names": list("abcd"), "lanes": {"rl2s/0": {"sim_value": [
             5.0, 0.0, 21.0, 19.0]}}, "sizes": {"eval_episodes": 16, "value_episodes": 64}}
    ceiling = {"n_truth": 32, "kendall_tau": {"mean": 0.95, "lo": 0.9, "hi": 1.0}}
    orc = {"task": "hopper", "data_seed": 7, "policy_names": list("dcba"),
           "true_value_se": [8.0, 8.0, 1.0, 1.0], "true_value_undiscounted": und[::-1],
           "command": "oracle_check.py --data-seed 7",
           "rows": [{"horizon": 1000, "n_episodes": 16, "metrics": {"kendall_tau": 0.9},
                     "true_value": truth[::-1], "noise_ceiling": ceiling,
                     "oracle_value": [20.0, 10.0, 0.0, 1.0]}]}  # d-a: it swaps a-b
    return r, orc


def test_truth_se_from_the_oracle_run(tmp_path, capsys):
    """--truth-se: the oracle's true_value_se (discounted) in the result's policy order, x
    sqrt(32 / 64) to the result's truth episodes; it moves the within-noise / real split (a-b,
    |dV| 5, and c-d, |dV| 10, trade places); the oracle's tau, the bar and the oracle's own
    swaps (its oracle_value as one lane) are reported."""
    ra = load_script("ranking_analysis")
    r, orc = _oracle_case()
    se, source = ra.standard_errors(r, orc, "o.json")
    np.testing.assert_allclose(se, np.array([1.0, 1.0, 8.0, 8.0]) * np.sqrt(32 / 64))
    assert source.startswith("the oracle's true_value_se (o.json; discounted, 32 episodes, "
                             "scaled to 64; its truths vs the result's: max |z| 0.00)")
    orc["rows"][0]["true_value"] = [24.0, 10.0, 5.0, 0.0]  # d + 4
    z = 4 / (8 * np.sqrt(32 / 64) * np.sqrt(1 + 64 / 32))  # its SE and the result's combined
    assert f"max |z| {z:.2f}" in ra.standard_errors(r, orc, "o.json")[1]
    with pytest.raises(ValueError, match=r"o.json: data_seed: expected 7 \(the result's\)"):
        ra.standard_errors(r, {**orc, "data_seed": 0}, "o.json")
    del orc["rows"][0]["noise_ceiling"]  # the episodes from the command
    orc["command"] += " --value-episodes 64"
    np.testing.assert_allclose(ra.standard_errors(r, orc, "o.json")[0], [1.0, 1.0, 8.0, 8.0])
    r, orc = _oracle_case()
    paths = [tmp_path / "r.json", tmp_path / "o.json"]
    for p, d in zip(paths, (r, orc), strict=True):
        p.write_text(json.dumps(d))
    out = {}
    for extra in ([], ["--truth-se", str(paths[1])]):
        assert ra.main([str(paths[0]), "--methods", "rl2s", "--n-rep", "20", "--json",
                        str(tmp_path / "a.json"), *extra]) == 0
        out[bool(extra)] = json.loads((tmp_path / "a.json").read_text())["data_seeds"]["7"]
    assert out[False]["noise_swaps_per_policy"] == [1, 1, 0, 0]  # own SEs: a-b noise
    assert out[False]["real_swaps_per_policy"] == [0, 0, 1, 1] and out[False]["oracle"] is None
    assert out[True]["noise_swaps_per_policy"] == [0, 0, 1, 1]  # the oracle's: c-d noise
    assert out[True]["real_swaps_per_policy"] == [1, 1, 0, 0]
    assert out[True]["oracle"]["rl2s_minus_oracle"] == pytest.approx(2 / 6 - 0.9)
    own = out[True]["oracle"]["own"]  # the oracle as one lane, in the result's order
    assert own["tau"] == pytest.approx(4 / 6) and own["tau_lost_real"] == pytest.approx(2 / 6)
    assert own["tau_lost_noise"] == 0.0 and own["tau_without"][0] == 1.0
    printed = capsys.readouterr().out
    assert f" 16 episodes; {paths[1]}): tau 0.900, its noise ceiling 0.950" in printed
    assert "RL2S - oracle -0.567: MISSED (bar -0.03)" in printed
    assert "most with a 1, b 1; without a: tau 0.333 (the oracle's 1.000)" in printed


@pytest.mark.parametrize("change, message", [
    (lambda o: o.update(policy_names=list("dcbe")),
     r"policy_names: expected the result's 4 test policies; missing \['a'\], extra \['e'\]"),
    (lambda o: o.update(task="ant"), "task: expected 'hopper'"),
    (lambda o: o.update(data_seed=0), r"data_seed: expected one of the results' data seeds"),
    (lambda o: o["rows"][0]["true_value"].__setitem__(1, 110.0),
     r"rows\[0\]\.true_value: 1 policies differ .* \(first c: 110.0 vs 10.0"),
    (lambda o: o["true_value_undiscounted"].__setitem__(3, 50.0),
     r"true_value_undiscounted: 1 policies differ .*\(first a: 50.0 vs 0.0"),
    (lambda o: o.update(true_value_se=[1.0, 1.0]), "true_value_se: expected 4 finite"),
])
def test_truth_se_refuses_another_runs_oracle(tmp_path, change, message):
    """An oracle of another task, data seed or policies, or whose truths differ from the
    result's, is refused before any work, naming the file and the field."""
    ra = load_script("ranking_analysis")
    r, orc = _oracle_case()
    change(orc)
    (tmp_path / "r.json").write_text(json.dumps(r))
    (tmp_path / "o.json").write_text(json.dumps(orc))
    with pytest.raises(SystemExit, match="o.json: " + message):
        ra.main([str(tmp_path / "r.json"), "--truth-se", str(tmp_path / "o.json")])


def test_oracle_check_data_seed_takes_the_protocols_test_split_only(tmp_path, monkeypatch):
    """--data-seed measures on the protocol's data: another --split or --zoo is refused before
    any work. (Run on the CPU at toy sizes, not here: hopper, --data-seed 3, 200 transitions,
    4 episodes, horizon 50: 20 test policies, its noise ceiling, data_seed 3 in the output.)"""
    oc = load_script("oracle_check")

    def no_work(*args, **kwargs):
        raise AssertionError("collected data before refusing the flags")

    monkeypatch.setattr(oc, "load_or_collect", no_work)
    monkeypatch.setattr(oc, "collect_dataset", no_work)
    for extra in (["--split", "train"], ["--zoo", str(tmp_path)]):
        with pytest.raises(SystemExit, match="data-seed: the protocol's test split"):
            oc.main(["--tasks", "hopper", "--data-seed", "3", "--out", str(tmp_path), *extra])


def test_readme_headline_is_the_data_seed_table():
    """README's headline taus are RL2S's means over the data seeds that docs/results/*.json
    record with RL2S (by_data_seed; an oracle-only entry does not count), rounded to 2
    digits; it names the data seeds every task has and each one only some have."""
    import os
    import re

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    means, seeds = {}, []
    for task in ("hopper", "walker2d", "halfcheetah", "ant"):
        with open(os.path.join(root, "docs", "results", f"{task}.json")) as f:
            tab = {k: e for k, e in json.load(f)["by_data_seed"].items() if "rl2s" in e}
        seeds.append(set(tab))
        means[task] = np.mean([e["rl2s"]["kendall_tau"] for e in tab.values()])
    readme = " ".join(open(os.path.join(root, "README.md")).read().split())
    want = (f"tau {means['hopper']:.2f} (Hopper), {means['walker2d']:.2f} (Walker2d), "
            f"{means['halfcheetah']:.2f} (HalfCheetah) and {means['ant']:.2f} (Ant")
    assert want in readme
    common = sorted(set.intersection(*seeds), key=int)
    listed = ", ".join(common[:-1]) + " and " + common[-1]  # "0, 7 and 23"
    assert re.search(rf"data seeds {listed}\b", readme)
    for extra in sorted(set.union(*seeds) - set(common), key=int):
        assert re.search(rf"data seed {extra}\b", readme), extra


def test_guard_reading_recorded_and_tabled(tmp_path):
    """merge_results --guard-reading: interval_guard.py's output becomes the task's "guard"
    (another task's refused, naming the flag); tables.interval_guard_rows prints each guard's
    median gain, deployed, lost and MPI per method beside the control."""
    from rl2s_jax.paper.tables import interval_guard_rows

    mr = load_script("merge_results")
    block = lambda med, dep: {"median_gain": med, "mpi": 0.0, "deployed": dep,
                              "deployed_losses": 0, "lanes_x_policies": 20,
                              "control_median_gain": 0.48}
    reading = {"task": "hopper", "level": 0.9, "runs": ["docs/results/improvement_x/hopper.json"],
               "command": "interval_guard.py --task hopper", "crossfit": {"folds": 2},
               "floor": {"rl2s": block(0.3, 7), "gail": block(0.1, 4)},
               "interval": {"rl2s": block(0.0, 2), "gail": block(0.05, 3)}}
    (tmp_path / "g.json").write_text(json.dumps(reading))
    (tmp_path / "hopper.json").write_text(json.dumps({"task": "hopper", "per_seed": {}}))
    args = ["--task", "hopper", "--keep", "--out", str(tmp_path), "--guard-reading",
            str(tmp_path / "g.json")]
    assert mr.main(args) == 0
    got = json.loads((tmp_path / "hopper.json").read_text())
    assert got["guard"]["floor"] == reading["floor"]
    assert got["guard"]["interval"]["gail"]["median_gain"] == 0.05
    rows = interval_guard_rows({"hopper": got}, ["hopper", "ant"])
    assert len(rows) == 4 and "| hopper | improvement_x | +0.48 | floor | +0.30 (7 of 20" in rows[2]
    assert rows[3].split(" | ")[3:6] == ["interval", "+0.00 (2 of 20, 0 lost, MPI 0.000)",
                                         "+0.05 (3 of 20, 0 lost, MPI 0.000)"]
    assert rows[3].endswith("| n/a |")  # BC not in the reading
    assert interval_guard_rows({"hopper": {"task": "hopper"}}, ["hopper"]) == []
    (tmp_path / "g.json").write_text(json.dumps({**reading, "task": "ant"}))
    with pytest.raises(SystemExit, match="guard-reading: expected interval_guard.py's output"):
        mr.main(args)


def test_group_by_data_seed():
    """Results by data seed in data seed order; results of two tasks refused naming "task"."""
    a, b, c = ({"task": "ant", "data_seed": d} for d in (23, 0, 23))
    assert dseeds.group_by_data_seed([a, b, c]) == {0: [b], 23: [a, c]}
    assert list(dseeds.group_by_data_seed([a, b])) == [0, 23]
    with pytest.raises(ValueError, match="task: expected the results of one task"):
        dseeds.group_by_data_seed([a, {"task": "hopper", "data_seed": 0}])
