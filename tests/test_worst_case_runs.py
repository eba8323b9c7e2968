"""experiments/worst_case_runs.py on synthetic paper.py results (fast, no JAX): the rows, the
merge into an existing out file, bar (a)'s max / median and bar (b)'s paired difference."""
import json

import numpy as np
import pytest
from experiment_scripts import load_script

EPS = {"rl2s": 0.25, "gail": 1.0, "bc": 1.0, "rl2s-bc": 0.25}


wc = load_script("worst_case_runs")


def _paper(mvd: dict, seed_ids=(0, 1, 2), data_seed=0, ids_key=True, command_extra="",
           anchor="all"):
    """A paper.py result: per_seed mvd / kendall_tau, selected, lanes with eps, the command,
    the adversarial family's anchor in train_config (None: no train_config, an old run)."""
    ids = list(seed_ids)
    command = (f"python experiments/paper.py --task hopper --seeds {len(ids)} "
               f"--data-seed {data_seed}{command_extra}")
    result = {"task": "hopper", "seeds": len(ids), "command": command,
              "hardware": "NVIDIA H100 80GB HBM3", "per_seed": {}, "selected": {}, "lanes": {}}
    if anchor is not None:
        result["train_config"] = {"adversarial": {"method": "rl2s", "adv_nll_on": anchor},
                                  "mle": {"method": "rl2s-bc"}}
    if ids_key:
        result["seed_ids"] = ids
    for m, vals in mvd.items():
        result["per_seed"][m] = {"mvd": list(vals), "kendall_tau": [0.9 + 0.01 * s for s in ids],
                                 "avd": [1.0] * len(ids)}
        result["selected"][m] = {"step": [600] * len(ids), "mvd": [v + 1 for v in vals],
                                 "kendall_tau": [0.8] * len(ids)}
        for s in ids:
            eps = EPS[m] if m in EPS else float(m.split("@")[1])   # paper.py's rl2s@0.5
            result["lanes"][f"{m}/{s}"] = {"family": "x", "eps": eps, "seed": s}
    result["per_seed"]["oracle"] = {"mvd": [5.0], "kendall_tau": [1.0]}
    return result


def _write(tmp_path, name, obj):
    path = tmp_path / name
    path.write_text(json.dumps(obj))
    return str(path)


def test_rows_seed_ids_data_seed_eps_and_selection(tmp_path):
    p = _write(tmp_path, "a.json", _paper({"rl2s": [10.0, 20.0], "gail": [30.0, 40.0]},
                                          seed_ids=(3, 4), data_seed=7))
    out = str(tmp_path / "wc.json")
    assert wc.main(["--task", "hopper", p, "--out", out]) == 0
    runs = json.load(open(out))["runs"]
    assert [(r["data_seed"], r["seed"], r["method"], r["eps"], r["mvd"]) for r in runs] == [
        (7, 3, "rl2s", 0.25, 10.0), (7, 4, "rl2s", 0.25, 20.0),
        (7, 3, "gail", 1.0, 30.0), (7, 4, "gail", 1.0, 40.0)]
    r = runs[1]
    assert r["tau"] == pytest.approx(0.94) and r["mvd_selected"] == 21.0
    assert r["tau_selected"] == 0.8 and r["step_selected"] == 600
    assert r["source"] == p and r["device"] == "NVIDIA H100 80GB HBM3"
    # no seed_ids: --first-seed of the command; the default data seed is paper.py's 0
    res = _paper({"rl2s": [1.0, 2.0]}, seed_ids=(5, 6), ids_key=False,
                 command_extra=" --first-seed 5")
    res["command"] = res["command"].replace(" --data-seed 0", "")
    rows = wc.lane_rows(res, "x")
    assert [(r["data_seed"], r["seed"]) for r in rows] == [(0, 5), (0, 6)]


def test_eps_lanes_are_rl2s_rows_at_their_eps(tmp_path):
    p = _write(tmp_path, "a.json", _paper({"rl2s": [10.0, 20.0], "rl2s@0.5": [11.0, 12.0],
                                           "gail": [30.0, 40.0]}, seed_ids=(0, 1)))
    out = str(tmp_path / "wc.json")
    assert wc.main(["--task", "hopper", p, "--out", out]) == 0
    got = json.load(open(out))
    assert sorted((r["method"], r["eps"], r["mvd"]) for r in got["runs"]) == [
        ("gail", 1.0, 30.0), ("gail", 1.0, 40.0), ("rl2s", 0.25, 10.0), ("rl2s", 0.25, 20.0),
        ("rl2s", 0.5, 11.0), ("rl2s", 0.5, 12.0)]
    assert set(got["summary"]["methods"]) == {"rl2s@eps=0.25", "rl2s@eps=0.5", "gail"}


def test_merge_keeps_other_keys_and_rows_replaces_same_key(tmp_path):
    out = tmp_path / "wc.json"
    old = {"task": "hopper", "note": "kept", "worst_policy": {"x": 1},
           "runs": [{"data_seed": 0, "seed": 0, "method": "rl2s", "eps": 0.25, "mvd": 999.0,
                     "tau": 0.1},
                    {"data_seed": 9, "seed": 0, "method": "rl2s", "eps": 0.25, "mvd": 50.0,
                     "tau": 0.5}]}
    out.write_text(json.dumps(old))
    p = _write(tmp_path, "a.json", _paper({"rl2s": [10.0]}, seed_ids=(0,)))
    wc.main(["--task", "hopper", p, "--out", str(out), "--source-label", "label"])
    doc = json.load(open(out))
    assert doc["note"] == "kept" and doc["worst_policy"] == {"x": 1} and "summary" in doc
    assert [(r["data_seed"], r["mvd"]) for r in doc["runs"]] == [(0, 10.0), (9, 50.0)]
    assert doc["runs"][0]["source"] == "label"


def test_bar_a_against_hand_computation(tmp_path):
    a = [10.0, 12.0, 14.0, 16.0, 18.0]
    b = [11.0, 13.0, 15.0, 17.0, 40.0]  # median of all ten: (14 + 15) / 2 = 14.5; max 40
    paths = [_write(tmp_path, f"{ds}.json", _paper({"rl2s": v}, seed_ids=range(5), data_seed=ds))
             for ds, v in ((0, a), (1, b))]
    out = str(tmp_path / "wc.json")
    wc.main(["--task", "hopper", *paths, "--out", out])
    s = json.load(open(out))["summary"]
    st, bar = s["methods"]["rl2s"], s["bar_a"]["rl2s"]
    assert st["n"] == 10 and st["median_mvd"] == 14.5 and st["max_mvd"] == 40.0
    assert st["mean_mvd"] == pytest.approx(np.mean(a + b))
    assert bar["max_over_median"] == pytest.approx(40.0 / 14.5) and bar["verdict"] == "fail"
    ok = wc.bar_a(wc.method_stats(wc.group_runs(
        [{**r, "mvd": min(r["mvd"], 29.0)} for r in json.load(open(out))["runs"]])["rl2s"]))
    assert ok["verdict"] == "pass"  # 29 <= 2 x 14.5
    few = wc.bar_a(wc.method_stats(wc.lane_rows(_paper({"rl2s": a}, range(5)), "x")))
    assert few["verdict"].startswith("not enough runs") and "{'0': 5}" in few["verdict"]


def test_paired_difference_against_numpy(tmp_path):
    rng = np.random.default_rng(1)
    r_mvd, g_mvd = rng.uniform(50, 100, (2, 5)), rng.uniform(60, 120, (2, 5))
    paths = [_write(tmp_path, f"{ds}.json",
                    _paper({"rl2s": r_mvd[ds].tolist(), "gail": g_mvd[ds].tolist()},
                           seed_ids=range(5), data_seed=ds)) for ds in (0, 1)]
    out = str(tmp_path / "wc.json")
    wc.main(["--task", "hopper", *paths, "--out", out])
    b = json.load(open(out))["summary"]["bar_b"]["rl2s - gail"]
    diff = (r_mvd - g_mvd).ravel()
    assert b["n_pairs"] == 10 and b["mean_diff"] == pytest.approx(diff.mean())
    lo, hi = b["ci95_bootstrap"]
    assert lo <= diff.mean() <= hi
    assert np.mean(b["ci95_t"]) == pytest.approx(diff.mean())
    assert b["verdict"] == ("pass" if diff.mean() <= 0 or lo <= 0 <= hi else "fail")
    # only the shared (data_seed, seed) keys pair
    one = wc.paired_difference([{"data_seed": 0, "seed": 0, "mvd": 3.0},
                                {"data_seed": 0, "seed": 1, "mvd": 5.0}],
                               [{"data_seed": 0, "seed": 1, "mvd": 1.0}])
    assert one["n_pairs"] == 1 and one["mean_diff"] == 4.0


def test_bad_input_names_file_and_field_writes_nothing(tmp_path):
    res = _paper({"rl2s": [1.0, 2.0, 3.0]})
    del res["per_seed"]["rl2s"]["mvd"]
    p = _write(tmp_path, "bad.json", res)
    out = tmp_path / "wc.json"
    with pytest.raises(SystemExit, match=r"bad\.json: missing field 'per_seed\.rl2s\.mvd'"):
        wc.main(["--task", "hopper", p, "--out", str(out)])
    short = _write(tmp_path, "short.json", _paper({"rl2s": [1.0, 2.0]}))
    with pytest.raises(SystemExit, match=r"short\.json: per_seed\.rl2s\.mvd: expected 3"):
        wc.main(["--task", "hopper", short, "--out", str(out)])
    with pytest.raises(SystemExit, match=r"a\.json: task is 'hopper'"):
        wc.main(["--task", "ant", _write(tmp_path, "a.json", _paper({"rl2s": [1.0] * 3})),
                 "--out", str(out)])
    assert not out.exists()


def test_set_overrides_are_a_variant_kept_apart_from_the_bars(tmp_path):
    base = _write(tmp_path, "a.json", _paper({"rl2s": [10.0, 20.0], "gail": [30.0, 40.0]},
                                             seed_ids=(0, 1)))
    abl = _write(tmp_path, "b.json", _paper({"rl2s": [1.0, 2.0]}, seed_ids=(0, 1),
                                            command_extra=" --set adv_nll_on=selected --set "
                                            "eps=0.1 --set nll_beta=0", anchor=None))
    out = str(tmp_path / "wc.json")
    assert wc.main(["--task", "hopper", base, abl, "--out", out]) == 0
    doc = json.load(open(out))
    variants = {(r["method"], r["seed"]): r["variant"] for r in doc["runs"]}
    label = "adv_nll_on=selected,nll_beta=0"
    assert [v for (m, _), v in variants.items() if m == "rl2s"].count(label) == 2
    assert len(doc["runs"]) == 6  # the ablation's rows did not replace the default ones
    assert doc["summary"]["methods"][f"rl2s+{label}"]["mean_mvd"] == 1.5
    assert doc["summary"]["methods"]["rl2s"]["mean_mvd"] == 15.0
    assert set(doc["summary"]["bar_a"]) == {"rl2s"}
    assert set(doc["summary"]["bar_b"]) == {"rl2s - gail"}


def test_variant_comparisons_pair_within_the_run_and_against_the_default(tmp_path):
    base = _write(tmp_path, "a.json", _paper({"rl2s": [10.0, 20.0], "gail": [30.0, 40.0],
                                              "bc": [5.0, 7.0]}, seed_ids=(0, 1)))
    abl = _write(tmp_path, "b.json", _paper({"rl2s": [1.0, 2.0], "gail": [4.0, 10.0]},
                                            seed_ids=(0, 1), anchor="both"))
    out = str(tmp_path / "wc.json")
    assert wc.main(["--task", "hopper", base, abl, "--out", out]) == 0
    v = json.load(open(out))["summary"]["variants"]
    name = "rl2s+adv_nll_on=both@eps=0.25"
    expected = {f"{name} - gail+adv_nll_on=both": np.mean([1 - 4, 2 - 10]),
                f"{name} - bc": np.mean([1 - 5, 2 - 7]),
                f"{name} - rl2s@eps=0.25": np.mean([1 - 10, 2 - 20]),
                f"({name} - gail+adv_nll_on=both) - (rl2s@eps=0.25 - gail)":
                    np.mean([(1 - 4) - (10 - 30), (2 - 10) - (20 - 40)]),
                "gail+adv_nll_on=both - gail": np.mean([4 - 30, 10 - 40])}
    assert set(v) == set(expected)
    for k, mean in expected.items():
        assert v[k]["n_pairs"] == 2 and v[k]["mean_diff"] == pytest.approx(mean), k


def test_the_anchor_a_run_trained_with_decides_its_variant(tmp_path):
    """The bars take the default anchor's runs ("all"): a run whose train_config says
    "selected", or an old run without train_config or --set (before the option: "selected"),
    is a variant for rl2s and gail; the likelihood methods, which no anchor enters, stay
    in the bars."""
    mvd = {"rl2s": [1.0], "gail": [2.0], "bc": [3.0], "rl2s-bc": [4.0]}
    cases = {"all": None, "selected": "adv_nll_on=selected", None: "adv_nll_on=selected"}
    for anchor, expected in cases.items():
        res = _paper(mvd, seed_ids=(0,), anchor=anchor)
        got = {m: wc._variant(res, m) for m in mvd}
        assert got == {"rl2s": expected, "gail": expected, "bc": None, "rl2s-bc": None}, anchor
    old = _paper(mvd, seed_ids=(0,), anchor=None, command_extra=" --set adv_nll_on=all")
    assert wc._variant(old, "rl2s") is None and wc._variant(old, "rl2s@0.1") is None


def test_paired_difference_averages_a_seeds_reruns_first():
    """Reruns share data and seed: a seed with three runs weighs as one seed, and the
    intervals and the seed count are over seeds (hand-worked: seed 0's diffs 10, 30, 50 ->
    30; seed 1's -20 and seed 2's -4; pooled over runs the mean would be 13.2)."""
    a = [{"data_seed": 0, "seed": 0, "rerun": k, "mvd": 100.0 + d} for k, d in
         enumerate((10.0, 30.0, 50.0))] + [{"data_seed": 0, "seed": 1, "mvd": 80.0},
                                            {"data_seed": 0, "seed": 2, "mvd": 96.0}]
    b = [{"data_seed": 0, "seed": s, "rerun": k, "mvd": 100.0} for s, k in
         ((0, 0), (0, 1), (0, 2), (1, 0), (2, 0))]
    d = wc.paired_difference(a, b)
    units = np.array([30.0, -20.0, -4.0])
    assert d["n_pairs"] == 5 and d["n_units"] == 3 and d["seeds_per_data_seed"] == {"0": 3}
    assert d["mean_diff"] == pytest.approx(units.mean())
    half = 4.302652729911275 * units.std(ddof=1) / np.sqrt(3)  # t(0.975, 2)
    assert d["ci95_t"] == pytest.approx([units.mean() - half, units.mean() + half])
    boot = units[np.random.default_rng(0).integers(0, 3, (wc.N_BOOT, 3))].mean(axis=1)
    assert d["ci95_bootstrap"] == pytest.approx(np.percentile(boot, [2.5, 97.5]))


def test_incomplete_run_leaves_out_methods_without_values(tmp_path, capsys):
    res = _paper({"rl2s": [10.0, 20.0], "bc": []}, seed_ids=(0, 1))
    res["per_seed"]["bc"] = {"mvd": [], "kendall_tau": []}
    res["complete"] = False
    out = str(tmp_path / "wc.json")
    assert wc.main(["--task", "hopper", _write(tmp_path, "a.json", res), "--out", out]) == 0
    assert {r["method"] for r in json.load(open(out))["runs"]} == {"rl2s"}
    assert "incomplete run; no values for bc" in capsys.readouterr().out
    res["complete"] = True  # a finished run without values is bad input, as before
    with pytest.raises(SystemExit, match="per_seed.bc.mvd: expected 2 values"):
        wc.main(["--task", "hopper", _write(tmp_path, "b.json", res), "--out", out])


def test_a_rerun_of_the_same_keys_is_a_run_of_its_own_paired_within_itself(tmp_path):
    first = _write(tmp_path, "a.json", _paper({"rl2s": [10.0, 20.0], "gail": [30.0, 40.0]},
                                              seed_ids=(0, 1)))
    again = _write(tmp_path, "b.json", _paper({"rl2s": [11.0, 24.0], "rl2s@0.05": [9.0, 23.0],
                                               "gail": [15.0, 21.0]}, seed_ids=(0, 1)))
    out = str(tmp_path / "wc.json")
    assert wc.main(["--task", "hopper", first, again, "--out", out]) == 0
    doc = json.load(open(out))
    got = {(r["method"], r["eps"], r["seed"], r["rerun"]): r["mvd"] for r in doc["runs"]}
    assert got[("rl2s", 0.25, 0, 0)] == 10.0 and got[("rl2s", 0.25, 0, 1)] == 11.0
    assert got[("rl2s", 0.05, 1, 0)] == 23.0   # a key b.json alone has: its first run
    assert len(doc["runs"]) == 10
    # rl2s pairs with gail of its own run: (10-30, 20-40) and (11-15, 24-21)
    b = doc["summary"]["bar_b"]["rl2s@eps=0.25 - gail"]
    assert b["n_pairs"] == 4 and b["mean_diff"] == pytest.approx((-20 - 20 - 4 + 3) / 4)
    assert doc["summary"]["methods"]["rl2s@eps=0.25"]["n"] == 4
    # rebuilding from the same files gives the same rows; a file given twice is refused
    assert wc.main(["--task", "hopper", first, again, "--out", out]) == 0
    assert len(json.load(open(out))["runs"]) == 10
    with pytest.raises(SystemExit, match=r"a\.json: run .* the same run twice"):
        wc.main(["--task", "hopper", first, first, "--out", out])
