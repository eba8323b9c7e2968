"""experiments/quality_within.py (issue 63: is a faster variant's quality unchanged?) on tiny
synthetic paper.py results: the control's t-interval over seeds against NumPy, the
inside / outside decision and the verdict, the paired difference over the shared seeds, the
timings, and the refusals before any work."""
import copy
import json

import numpy as np
import pytest
from experiment_scripts import load_script

qw = load_script("quality_within")

T_975_DF2 = 4.302652729911275  # Student t's 0.975 quantile, 2 degrees of freedom
NAMES = ["hopper-002", "hopper-003", "hopper-006"]


def _result(tau, mvd, *, seeds=(0, 1, 2), avd=None, timings=None, **extra):
    """A paper.py result of two methods (rl2s, bc; bc's numbers rl2s's plus offsets) and the
    oracle, one value per seed."""
    def per(t, m, a):
        return {"kendall_tau": list(t), "mvd": list(m),
                "avd": list(a if a is not None else [10.0] * len(t)),
                "ndcg@1": [1.0] * len(t)}
    r = {"task": "hopper", "data_seed": 23, "policy_split": "zoo", "seeds": len(seeds),
         "seed_ids": list(seeds), "test_policy_names": list(NAMES),
         "command": "python experiments/paper.py --task hopper --data-seed 23",
         "timings": timings or {"data": 100.0, "train_adversarial": 300.0,
                                "train_mle": 150.0, "oracle": 140.0, "trust": 80.0,
                                "total": 770.0},
         "complete": True,
         "per_seed": {"rl2s": per(tau, mvd, avd),
                      "bc": per([t - 0.05 for t in tau], [m + 50 for m in mvd], avd),
                      "oracle": per([0.99] * len(tau), [50.0] * len(tau), None)},
         "intervals": {"rl2s": {"kendall_tau": {"lo": 0.8, "hi": 0.99, "std": 0.02}}}}
    r.update(extra)
    return r


CONTROL = _result([0.90, 0.92, 0.95], [200.0, 100.0, 300.0])


def _t95(x):
    x = np.asarray(x, float)
    half = T_975_DF2 * x.std(ddof=1) / np.sqrt(x.size)
    return x.mean() - half, x.mean() + half


def test_control_interval_is_a_t_interval_over_seeds():
    j = qw.judge(CONTROL, CONTROL)
    for m, k in (("rl2s", "kendall_tau"), ("rl2s", "mvd"), ("bc", "mvd")):
        row = j["methods"][m][k]
        x = CONTROL["per_seed"][m][k]
        assert row["control_mean"] == pytest.approx(np.mean(x))
        assert row["control_t95"] == pytest.approx(list(_t95(x)))
        assert row["control_seeds"] == 3
    assert j["methods"]["rl2s"]["kendall_tau"]["published"] == [0.8, 0.99]
    assert j["methods"]["bc"]["kendall_tau"]["published"] is None
    assert "oracle" not in j["methods"]  # the real dynamics: not judged
    assert j["unchanged"] and not j["outside"]


def test_inside_and_outside_decide_the_verdict():
    lo, hi = _t95(CONTROL["per_seed"]["rl2s"]["kendall_tau"])
    # the variant's mean just inside the upper end, then just above it
    inside = _result([hi - 1e-6] * 3, [200.0, 100.0, 300.0])
    j = qw.judge(CONTROL, inside)
    assert j["methods"]["rl2s"]["kendall_tau"]["inside"] and j["unchanged"]
    above = _result([hi + 1e-6] * 3, [200.0, 100.0, 300.0])
    j = qw.judge(CONTROL, above)
    assert j["methods"]["rl2s"]["kendall_tau"]["inside"] is False
    # bc's numbers are rl2s's shifted as the control's are: just outside too
    assert j["outside"] == ["rl2s kendall_tau", "bc kendall_tau"] and not j["unchanged"]
    assert "quality CHANGED" in qw.report("v.json", above, j)
    # the published episode interval is read apart: 0.8-0.99 holds the same mean
    assert j["methods"]["rl2s"]["kendall_tau"]["inside_published"]
    # MVD below the lower end fails too; AVD far off does not (not one of the judged)
    mlo, _ = _t95(CONTROL["per_seed"]["rl2s"]["mvd"])
    j = qw.judge(CONTROL, _result([0.92] * 3, [mlo - 1.0] * 3, avd=[999.0] * 3))
    assert j["outside"] == ["rl2s mvd", "bc mvd"]
    assert j["methods"]["rl2s"]["avd"]["inside"] is False
    j = qw.judge(CONTROL, _result([0.92] * 3, [200.0] * 3, avd=[999.0] * 3))
    assert j["unchanged"]
    assert "quality unchanged" in qw.report("v.json", _result([0.92] * 3, [200.0] * 3), j)


def test_missing_methods_and_values_leave_it_not_judged():
    v = _result([0.92] * 3, [200.0] * 3)
    del v["per_seed"]["bc"]
    j = qw.judge(CONTROL, v)
    assert j["missing"] == ["bc"] and not j["unchanged"]
    v = _result([0.92] * 3, [200.0] * 3)
    v["per_seed"]["bc"]["mvd"] = [None, None, None]  # a non-finite lane on every seed
    j = qw.judge(CONTROL, v)
    assert j["no_value"] == ["bc mvd"] and not j["outside"] and not j["unchanged"]
    assert "not judged in full" in qw.report("v.json", v, j)


def test_paired_difference_over_the_shared_seeds():
    v = _result([0.93, 0.96, 0.90], [150.0, 260.0, 50.0], seeds=(1, 2, 3))
    row = qw.judge(CONTROL, v)["methods"]["rl2s"]["kendall_tau"]
    d = np.array([0.93 - 0.92, 0.96 - 0.95])  # seeds 1 and 2
    half = 12.706204736174698 * d.std(ddof=1) / np.sqrt(2)  # t 0.975, 1 degree of freedom
    assert row["paired"]["seeds"] == 2 and row["paired"]["mean"] == pytest.approx(d.mean())
    assert row["paired"]["t95"] == pytest.approx([d.mean() - half, d.mean() + half])
    assert row["variant_mean"] == pytest.approx(np.mean([0.93, 0.96, 0.90]))
    assert row["paired"]["variant_lower"] == 0
    assert qw.judge(CONTROL, _result([0.9] * 3, [1.0] * 3, seeds=(5, 6, 7)))[
        "methods"]["rl2s"]["mvd"]["paired"] is None  # no shared seeds


def test_timings_side_by_side_with_the_protocol_total():
    v = _result([0.92] * 3, [200.0] * 3,
                timings={"data": 50.0, "data_setup": 1.0, "data_rollout_compile": 30.0,
                         "train_adversarial": 150.0, "train_mle": 150.0,
                         "trust": 80.0, "total": 450.0})
    v["sizes"], control = {"steps": 600, "seeds": 3}, {**CONTROL, "sizes": {"steps": 1200,
                                                                          "seeds": 3}}
    j = qw.judge(control, v)
    assert j["sizes_differ"] == {"steps": [1200, 600]}
    assert "sizes differ: steps 1200 (control) -> 600" in qw.report("v.json", v, j)
    rows = j["timings"]
    assert list(rows)[:4] == ["data", "data_setup", "data_rollout_compile", "train_adversarial"]
    assert rows["data_rollout_compile"] == [None, 30.0]
    assert rows["train_adversarial"] == [300.0, 150.0]
    assert rows["oracle"] == [140.0, None]
    assert rows["protocol"] == [770.0 - 140.0 - 80.0, 450.0 - 80.0]


def _write(path, obj):
    path.write_text(json.dumps(obj))
    return str(path)


@pytest.mark.parametrize("field, value", [
    ("task", "walker2d"), ("data_seed", 7), ("policy_split", "validation"),
    ("test_policy_names", NAMES[::-1])])
def test_refuses_a_variant_of_other_data_before_any_work(tmp_path, capsys, field, value):
    v = copy.deepcopy(CONTROL)
    v[field] = value
    out = tmp_path / "out.json"
    with pytest.raises(SystemExit, match=rf"v\.json: {field}: expected the control's"):
        qw.main([_write(tmp_path / "c.json", CONTROL), _write(tmp_path / "ok.json", CONTROL),
                 _write(tmp_path / "v.json", v), "--json", str(out)])
    assert not out.exists() and capsys.readouterr().out == ""  # nothing judged or written


def test_refuses_what_is_not_a_paper_result(tmp_path):
    c = _write(tmp_path / "c.json", CONTROL)
    bad = {k: v for k, v in CONTROL.items() if k != "per_seed"}
    with pytest.raises(SystemExit, match=r"not a paper.py result: no 'per_seed'"):
        qw.main([c, _write(tmp_path / "v.json", bad)])
    with pytest.raises(SystemExit, match=r"command: expected 'python experiments/paper.py"):
        qw.main([c, _write(tmp_path / "v.json", {**CONTROL, "command": "python x.py"})])
    with pytest.raises(SystemExit, match="could not read it"):
        (tmp_path / "raw.json").write_text("{not json")
        qw.main([c, str(tmp_path / "raw.json")])
    with pytest.raises(SystemExit, match="expected a paper.py result"):
        qw.main([c, _write(tmp_path / "v.json", [1, 2])])
    one = _result([0.9], [100.0], seeds=(0,))
    with pytest.raises(SystemExit, match=r"c1\.json: seeds: expected a control of >= 2"):
        qw.main([_write(tmp_path / "c1.json", one), c])


def test_main_on_a_committed_control_against_itself(tmp_path, capsys):
    """The committed Hopper data-seed-23 run judged against itself: every mean inside, every
    paired difference 0, the JSON written."""
    path = "docs/results/data_seeds/hopper_data23.json"
    out = tmp_path / "q.json"
    assert qw.main([path, path, "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "quality unchanged" in printed and "train_adversarial" in printed
    j = json.loads(out.read_text())["variants"][path]
    assert j["unchanged"] and set(j["methods"]) == {"rl2s", "gail", "rl2s-bc", "bc"}
    assert all(r["paired"]["mean"] == 0.0 for m in j["methods"].values() for r in m.values())
