"""experiments/eps_curve.py on synthetic worst_case files (fast, no JAX): the points, the paired
differences against eps 0.25, bc ignored, GAIL beside an rl2s eps 1 point, the outputs, a
missing task skipped and a malformed row refused."""
import json

import numpy as np
import pytest
from experiment_scripts import load_script

ec = load_script("eps_curve")
KEYS = [(0, 0), (0, 1), (1, 0), (1, 1)]   # (data_seed, seed)


def _rows(method, eps, mvd, tau, keys=KEYS):
    return [{"data_seed": ds, "seed": s, "method": method, "eps": eps, "mvd": m, "tau": t,
             "source": "x"} for (ds, s), m, t in zip(keys, mvd, tau, strict=True)]


def _write(tmp_path, task, runs):
    (tmp_path / f"{task}_worst_case.json").write_text(json.dumps({"task": task, "runs": runs}))


def _boot(x):
    x = np.asarray(x, np.float64)
    b = x[np.random.default_rng(0).integers(0, len(x), (2000, len(x)))].mean(axis=1)
    return list(np.percentile(b, [2.5, 97.5]))


def test_points_paired_and_outputs(tmp_path, capsys):
    base = ([100.0, 200.0, 300.0, 400.0], [0.9, 0.8, 0.7, 0.6])
    small = ([90.0, 150.0, 310.0], [0.95, 0.85, 0.7])          # no run at (1, 1)
    gail = ([120.0, 260.0, 280.0, 500.0], [0.9, 0.7, 0.75, 0.5])
    _write(tmp_path, "hopper", _rows("rl2s", 0.25, *base) + _rows("rl2s", 0.1, *small, KEYS[:3])
           + _rows("gail", 1.0, *gail) + _rows("bc", 1.0, [1e6] * 4, [0.0] * 4)
           + _rows("rl2s-bc", 0.25, [1e6] * 4, [0.0] * 4))
    other = [{**r, "variant": "adv_nll_on=selected", "mvd": 1e6}
             for r in _rows("rl2s", 0.25, *base) + _rows("rl2s", 0.5, *base)]
    _write(tmp_path, "walker2d", _rows("rl2s", 0.25, *base) + _rows("rl2s", 1.0, *gail)
           + _rows("gail", 1.0, *base) + other)
    js, png = tmp_path / "out" / "c.json", tmp_path / "out" / "c.png"
    assert ec.main(["--tasks", "hopper", "walker2d", "ant", "--results", str(tmp_path),
                    "--json", str(js), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "ant: no" in out and "skipped" in out and "GAIL (eps 1)" in out
    doc = json.loads(js.read_text())
    assert doc["command"].startswith("python experiments/eps_curve.py --tasks hopper")
    assert doc["variant"] is None  # the other configuration's rows are not on the curve
    assert list(doc["tasks"]) == ["hopper", "walker2d"]
    assert png.read_bytes()[:4] == b"\x89PNG"

    pts = doc["tasks"]["hopper"]["points"]
    assert [(p["label"], p["method"], p["eps"], p["n"]) for p in pts] == [
        ("rl2s eps 0.1", "rl2s", 0.1, 3), ("rl2s eps 0.25", "rl2s", 0.25, 4),
        ("GAIL (eps 1)", "gail", 1.0, 4)]                        # bc, rl2s-bc ignored
    for p, (mvd, tau) in zip(pts, (small, base, gail), strict=True):
        assert p["mean_mvd"] == pytest.approx(np.mean(mvd))
        assert p["median_mvd"] == pytest.approx(np.median(mvd))
        assert p["max_mvd"] == max(mvd) and p["mean_tau"] == pytest.approx(np.mean(tau))
        assert p["ci95_mean_mvd"] == pytest.approx(_boot(mvd))
        assert p["ci95_mean_tau"] == pytest.approx(_boot(tau))
        lo, hi = p["ci95_mean_mvd"]
        assert lo <= p["mean_mvd"] <= hi
    assert pts[0]["data_seeds"] == [0, 1]

    pair = doc["tasks"]["hopper"]["paired_vs_0.25"]
    assert set(pair) == {"rl2s eps 0.1", "GAIL (eps 1)"}
    d_mvd = [90 - 100, 150 - 200, 310 - 300]                   # the three shared pairs
    d_tau = [0.95 - 0.9, 0.85 - 0.8, 0.7 - 0.7]
    assert pair["rl2s eps 0.1"]["mvd"]["n_pairs"] == 3
    assert pair["rl2s eps 0.1"]["mvd"]["mean_diff"] == pytest.approx(-50 / 3)
    assert pair["rl2s eps 0.1"]["tau"]["mean_diff"] == pytest.approx(np.mean(d_tau))
    assert pair["rl2s eps 0.1"]["mvd"]["ci95"] == pytest.approx(_boot(d_mvd))
    g = pair["GAIL (eps 1)"]
    assert g["mvd"]["n_pairs"] == 4 and g["mvd"]["mean_diff"] == pytest.approx(40.0)
    assert g["tau"]["mean_diff"] == pytest.approx(-0.05 / 4 - 0.1 / 4)

    # an rl2s point at eps 1 and GAIL stay two labelled points
    w = doc["tasks"]["walker2d"]["points"]
    assert [(p["label"], p["eps"]) for p in w] == [
        ("rl2s eps 0.25", 0.25), ("rl2s eps 1", 1.0), ("GAIL (eps 1)", 1.0)]
    assert w[1]["mean_mvd"] == pytest.approx(np.mean(gail[0]))
    assert w[2]["mean_mvd"] == pytest.approx(np.mean(base[0]))

    # --variant: that configuration's rows alone
    assert ec.main(["--tasks", "walker2d", "--results", str(tmp_path), "--json", str(js),
                    "--png", str(png), "--variant", "adv_nll_on=selected"]) == 0
    doc = json.loads(js.read_text())
    assert doc["variant"] == "adv_nll_on=selected"
    assert [(p["label"], p["mean_mvd"]) for p in doc["tasks"]["walker2d"]["points"]] == [
        ("rl2s eps 0.25", 1e6), ("rl2s eps 0.5", 1e6)]


def test_a_rerun_pairs_within_its_own_run(tmp_path):
    """A data seed and seed run twice (worst_case_runs.py's rerun 0 and 1): the eps lane of
    rerun 1 pairs with rerun 1's eps 0.25 lane, and both reruns count as runs of the point."""
    keys = [(0, 0), (0, 1)]
    # rerun 1 first: pairing by (data_seed, seed) alone would meet rerun 0's 0.25 lane last
    runs = ([{**r, "rerun": 1} for r in _rows("rl2s", 0.25, [150.0, 260.0], [0.7, 0.6], keys)
             + _rows("rl2s", 0.05, [140.0, 270.0], [0.75, 0.5], keys)]
            + _rows("rl2s", 0.25, [100.0, 200.0], [0.9, 0.8], keys)
            + _rows("rl2s", 0.05, [150.0], [0.8], keys[:1]))  # rerun 0 has it on seed 0 alone
    _write(tmp_path, "hopper", runs)
    js, png = tmp_path / "c.json", tmp_path / "c.png"
    assert ec.main(["--tasks", "hopper", "--results", str(tmp_path), "--json", str(js),
                    "--png", str(png)]) == 0
    res = json.loads(js.read_text())["tasks"]["hopper"]
    base = next(p for p in res["points"] if p["eps"] == 0.25)
    assert base["n"] == 4 and base["mean_mvd"] == pytest.approx(177.5)
    # reruns share data and seed: the interval is over the 2 seeds' means (125, 230), not 4 runs
    assert base["n_seeds"] == 2 and base["ci95_mean_mvd"] == pytest.approx(_boot([125.0, 230.0]))
    d = res["paired_vs_0.25"]["rl2s eps 0.05"]
    # seed 0's pairs -10 (rerun 1) and +50 (rerun 0) average to 20 first; seed 1's: +10
    assert d["mvd"]["n_pairs"] == 3 and d["mvd"]["n_seeds"] == 2
    assert d["mvd"]["mean_diff"] == pytest.approx((20 + 10) / 2)
    assert d["tau"]["mean_diff"] == pytest.approx(((0.05 - 0.1) / 2 - 0.1) / 2)
    # the 0.25 point's run-to-run noise: |150 - 100|, |260 - 200| over the first runs' mean 150
    assert res["rerun_noise"] == {"rl2s eps 0.25": {
        "n_pairs": 2, "mean_abs_diff": 55.0, "max_abs_diff": 60.0,
        "relative": pytest.approx(55 / 150)}, "rl2s eps 0.05": {
        "n_pairs": 1, "mean_abs_diff": 10.0, "max_abs_diff": 10.0,
        "relative": pytest.approx(10 / 150)}}
    runs[0]["rerun"] = -1
    _write(tmp_path, "hopper", runs)
    with pytest.raises(SystemExit, match=r"runs\[0\] field 'rerun'"):
        ec.main(["--tasks", "hopper", "--results", str(tmp_path), "--json", str(js),
                 "--png", str(png)])


def test_bad_input(tmp_path):
    js, png = tmp_path / "c.json", tmp_path / "c.png"
    argv = ["--tasks", "hopper", "walker2d", "--results", str(tmp_path), "--json", str(js),
            "--png", str(png)]
    with pytest.raises(SystemExit, match="no curve"):               # no file at all
        ec.main(argv)
    _write(tmp_path, "hopper", _rows("rl2s", 0.25, [1.0] * 4, [0.5] * 4))
    rows = _rows("rl2s", 0.25, [1.0] * 4, [0.5] * 4)
    del rows[2]["tau"]
    _write(tmp_path, "walker2d", rows)
    with pytest.raises(SystemExit, match=r"walker2d_worst_case.json: runs\[2\] has no field 'tau'"):
        ec.main(argv)
    rows[2]["tau"], rows[1]["mvd"] = 0.5, "big"
    _write(tmp_path, "walker2d", rows)
    with pytest.raises(SystemExit, match=r"runs\[1\] field 'mvd'"):
        ec.main(argv)
    _write(tmp_path, "walker2d", _rows("rl2s", None, [1.0] * 4, [0.5] * 4))
    with pytest.raises(SystemExit, match=r"runs\[0\] field 'eps'"):
        ec.main(argv)
    assert not js.exists() and not png.exists()                     # nothing written
