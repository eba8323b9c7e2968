"""The interval guard (issue 64 item 3, improve/gain_intervals.py, paper/trust_phase.py): a
fine-tuned policy is deployed where the lower end of its predicted gain's conformal interval
is above zero; the math against plain NumPy, both guards side by side on a synthetic protocol
result, the flags refused before any work. No JAX programs: fast."""

import json
import math

import numpy as np
import pytest

from rl2s_jax.evaluate import trust as tr
from rl2s_jax.improve import gain_intervals as gi


def _members(rng, M=3, P=5):
    start = rng.uniform(100, 200, (M, P))
    gain = rng.normal(10, 5, (M, P))
    return start, gain


def test_gain_features_and_calibration_by_hand():
    rng = np.random.default_rng(0)
    start, gain = _members(rng)
    f = gi.gain_features(start, gain)
    rel = gain / np.abs(start.mean(0))
    np.testing.assert_allclose(f["gain"], rel.mean(0))
    np.testing.assert_allclose(f["member_sd"], rel.std(0, ddof=1))
    real = f["gain"] + rng.normal(0, 0.02, 5)
    cal = gi.calibrate_gains(f["gain"], f["member_sd"], real, level=0.6)
    floor = 0.02 * np.ptp(f["gain"])
    scores = np.sort(np.abs(f["gain"] - real) / (f["member_sd"] + floor))
    assert cal["floor"] == pytest.approx(floor)
    assert cal["q"] == pytest.approx(scores[math.ceil(6 * 0.6) - 1])
    acc, lower = gi.interval_guard(f, cal)
    np.testing.assert_allclose(lower, f["gain"] - cal["q"] * (f["member_sd"] + floor))
    np.testing.assert_array_equal(acc, lower > 0)
    # too few calibration policies for the level: an infinite q deploys nothing
    few = gi.calibrate_gains(f["gain"][:2], f["member_sd"][:2], real[:2], level=0.9)
    assert math.isinf(few["q"]) and not gi.interval_guard(f, few)[0].any()
    with pytest.raises(ValueError, match="member_gain: expected the shape"):
        gi.gain_features(start, gain[:2])
    with pytest.raises(ValueError, match="real_gain: the calibration policies need finite"):
        gi.calibrate_gains([0.1], [0.0], [np.nan])


def test_the_interval_guard_can_deploy_what_the_floor_refuses():
    """A gain the members agree on, calibrated on policies whose errors are small, is
    deployed though one member's gain is under a large floor; a disputed gain is not."""
    start = np.full((3, 2), 100.0)
    gain = np.array([[10.0, 30.0], [11.0, -5.0], [12.0, 10.0]])
    cal = {"level": 0.9, "q": 2.0, "floor": 0.001, "n": 20}
    acc, _ = gi.interval_guard(gi.gain_features(start, gain), cal)
    assert acc.tolist() == [True, False]
    from rl2s_jax.improve.finetune import deployment_guard
    assert deployment_guard(start, start + gain, 0.02, floor=10.5).tolist() == [False, False]


def _entry(method, seed, start, gain, c0, c1, accepted):
    c0, c1 = np.asarray(c0, float), np.asarray(c1, float)
    return {"method": method, "seed": seed, "policy_ids": [0, 1, 2],
            "c0_paired": c0.tolist(), "c1": c1.tolist(),
            "I_paired": ((c1 - c0) / np.abs(c0)).tolist(), "guard_accepted": accepted,
            "guard_member_start": start.tolist(), "guard_member_gain": gain.tolist()}


def test_guard_comparison_by_hand():
    """Both guards' blocks from a synthetic result: deployed, losses, MPI with kept policies
    at 0, median gain over the policies below the zoo's top quartile (by hand), the
    control's; the interval verdicts written into the lanes."""
    from rl2s_jax.paper.trust_phase import guard_comparison

    start = np.full((2, 3), 100.0)
    gain = np.array([[20.0, 1.0, -30.0], [22.0, 40.0, -28.0]])  # agreed, disputed, loss
    c0 = [100.0, 100.0, 100.0]
    result = {"test_policy_names": ["hopper-004", "hopper-007", "hopper-009"],
              "improvement": {
                  "rl2s/0": _entry("rl2s", 0, start, gain, c0, [130.0, 90.0, 60.0],
                                   [True, True, False]),
                  "rl2s/1": _entry("rl2s", 1, start, gain, c0, [110.0, 95.0, 70.0],
                                   [True, False, False])},
              "control": {"c0": [c0], "c1": [[150.0, 120.0, 100.0]]}}
    zoo = np.arange(10, dtype=float) * 10  # top quartile: returns >= 67.5 -> ids 7, 9 out
    cal = {"level": 0.9, "q": 1.0, "floor": 0.001, "n": 20}
    g = guard_comparison(result, cal, zoo, chosen="interval")
    assert g["chosen"] == "interval" and not g["calibration"]["q_infinite"]
    assert result["improvement"]["rl2s/0"]["guard_accepted_interval"] == [True, False, False]
    fl, iv = g["floor"]["rl2s"], g["interval"]["rl2s"]
    assert (fl["deployed"], fl["deployed_losses"]) == (3, 1)  # 0/0, 0/1 (I = -0.1), 1/0
    assert (iv["deployed"], iv["deployed_losses"]) == (2, 0)
    # MPI: per lane the min over policies of I where deployed, else 0; mean over lanes
    assert fl["mpi"] == pytest.approx(np.mean([min(0.3, -0.1, 0.0), min(0.1, 0.0, 0.0)]))
    assert iv["mpi"] == pytest.approx(0.0)
    # median gain: only zoo id 4 is below the top quartile; its seed-mean deployed gain
    assert iv["median_gain"] == pytest.approx(np.mean([0.3, 0.1]))
    assert fl["median_gain"] == pytest.approx(np.mean([0.3, 0.1]))
    assert iv["control_median_gain"] == pytest.approx(0.5) and fl["lanes_x_policies"] == 6


def test_gain_calibration_reads_validation_runs_only():
    gain_calibration = gi.calibration_from_runs
    start = np.full((2, 3), 100.0)
    gain = np.array([[20.0, 1.0, -30.0], [22.0, 40.0, -28.0]])
    run = {"task": "hopper", "policy_split": "validation", "command": "c",
           "improvement": {"rl2s/0": _entry("rl2s", 0, start, gain, [100.0] * 3,
                                            [120.0, 100.0, 70.0], [True] * 3)}}
    cal = gain_calibration([run, run], "hopper", 0.5)
    f = gi.gain_features(start, gain)
    ref = gi.calibrate_gains(np.tile(f["gain"], 2), np.tile(f["member_sd"], 2),
                             [0.2, 0.0, -0.3] * 2, 0.5)
    assert cal["q"] == pytest.approx(ref["q"]) and cal["n"] == 6 and cal["sources"] == ["c"] * 2
    with pytest.raises(ValueError, match="validation split"):
        gain_calibration([{**run, "policy_split": "zoo"}], "hopper", 0.5)
    bare = {**run, "improvement": {"rl2s/0": {"I_paired": [0.1]}}}
    with pytest.raises(ValueError, match="no guard_member_gain"):
        gain_calibration([bare], "hopper", 0.5)
    assert tr.min_calibration(0.5) == 1


def test_paper_guard_and_trust_flags_refused_before_any_work(tmp_path):
    from experiment_scripts import load_script

    paper = load_script("paper")
    base = ["--task", "hopper", "--out", str(tmp_path)]
    for extra, msg in ((["--guard", "interval", "--guard-margin", "0"], "guard: 'interval' needs"),
                       (["--guard-calibration", "v.json"], "guard-calibration: needs --guard-m"),
                       (["--guard-calibration", "v.json", "--guard-margin", "0"],
                        "guard-calibration: no such file v.json"),
                       (["--trust-calibration", "-1"], "trust-calibration: expected"),
                       (["--trust-level", "1.5"], "trust-level: expected")):
        with pytest.raises(SystemExit, match=msg):
            paper.check_arguments(paper.parse_args(base + extra))


def test_both_front_ends_share_the_guard_flags():
    """--guard and --guard-calibration are one definition (``app.specs.guard_choice_flags``)
    on `rl2s improve` and paper.py: the same values from the same flags, the same actions but
    for the front end's context in the help, a guard neither knows refused by both."""
    import argparse

    from experiment_scripts import load_script

    from rl2s_jax import cli
    from rl2s_jax.app.specs import GUARD_CONTEXTS, guard_choice_flags

    paper = load_script("paper")
    improve = ["improve", "--ckpt", "c", "--data", "d.npz", "--out", "o"]
    for flags, want in (([], ("floor", None)),
                        (["--guard-calibration", "a.json"], ("floor", ["a.json"])),
                        (["--guard", "interval", "--guard-calibration", "a.json", "b.json"],
                         ("interval", ["a.json", "b.json"]))):
        a = cli.build_parser().parse_args(improve + flags)
        b = paper.build_parser().parse_args(["--task", "hopper", "--out", "o", *flags])
        assert (a.guard, a.guard_calibration) == (b.guard, b.guard_calibration) == want
    for parse in (lambda f: cli.build_parser().parse_args(improve + f),
                  lambda f: paper.build_parser().parse_args(["--task", "hopper", *f])):
        with pytest.raises(SystemExit):
            parse(["--guard", "ceiling"])
    sub = next(a for a in cli.build_parser()._actions if a.dest == "command").choices["improve"]
    front_ends = {"improve": sub, "paper": paper.build_parser()}
    actions = {k: {a.dest: a for a in p._actions} for k, p in front_ends.items()}
    for dest in ("guard", "guard_calibration"):
        a, b = actions["improve"][dest], actions["paper"][dest]
        same = ("option_strings", "nargs", "choices", "default", "type", "metavar", "required")
        assert [getattr(a, k) for k in same] == [getattr(b, k) for k in same], dest
        shared = {}
        for k, act in (("improve", a), ("paper", b)):
            part = next((c for c in GUARD_CONTEXTS[k] if c in act.help), None)
            assert part is not None, f"{k} --{dest}: no {k} context in its help"
            shared[k] = act.help.replace(part, "<context>")
        assert shared["improve"] == shared["paper"], dest
    with pytest.raises(ValueError, match="context: expected one of"):
        guard_choice_flags(argparse.ArgumentParser(), "pipeline")


def test_crossfit_calibrates_each_fold_on_the_others(tmp_path):
    """crossfit_interval_guard: each policy's verdict from a calibration on the other fold's
    policies only (by hand with calibrate_gains); |c0| as the scale where the run kept no
    member starts; the script reads a bundle and writes both guards' blocks."""
    from experiment_scripts import load_script

    from rl2s_jax.paper.trust_phase import crossfit_interval_guard

    rng = np.random.default_rng(3)
    entries = []
    for seed in range(3):
        gain = rng.normal(5, 3, (2, 4))
        c0 = np.array([100.0, 80.0, 120.0, 90.0])
        e = _entry("rl2s", seed, np.zeros((2, 4)), gain, c0, c0 + rng.normal(4, 3, 4),
                   [True] * 4)
        del e["guard_member_start"]
        e.update(c0=c0.tolist(), zoo_ids=[3, 1, 7, 5], policy_ids=[0, 1, 2, 3])
        entries.append(e)
    out = crossfit_interval_guard(entries, level=0.5, folds=2)
    assert out["scale"].startswith("|C0|") and out["n"] == [6, 6]
    # zoo ids sorted 1, 3, 5, 7 -> folds 0, 1, 0, 1: at positions 1, 3 ([3, 1, 7, 5]) fold 0
    feats = [gi.gain_features(None, e["guard_member_gain"], np.abs(e["c0"])) for e in entries]
    for f, cols in ((0, [0, 2]), (1, [1, 3])):  # fold f is calibrated on these positions
        cal = gi.calibrate_gains([ft["gain"][j] for ft in feats for j in cols],
                                 [ft["member_sd"][j] for ft in feats for j in cols],
                                 [e["I_paired"][j] for e in entries for j in cols], 0.5)
        assert out["q"][f] == pytest.approx(cal["q"])
        mine = [1, 3] if f == 0 else [0, 2]
        for e, ft in zip(entries, feats, strict=True):
            low = gi.gain_lower_bound(ft["gain"], ft["member_sd"], cal)
            assert [e["guard_gain_lower"][j] for j in mine] == pytest.approx(low[mine].tolist())
            assert [e["guard_accepted_interval"][j] for j in mine] == (low[mine] > 0).tolist()
    run = {"task": "hopper", "test_policy_names": [f"hopper-{i:03d}" for i in (3, 1, 7, 5)],
           "improvement": {f"rl2s/{i}": {k: v for k, v in e.items() if not k.startswith(
               ("guard_gain", "guard_accepted_i", "zoo"))} for i, e in enumerate(entries)}}
    (tmp_path / "b.json").write_text(json.dumps({"runs": [run],
                                                 "summary": {"control": {"median_gain": 0.4}}}))
    ig = load_script("interval_guard")
    assert ig.main(["--task", "hopper", "--runs", str(tmp_path / "b.json"), "--level", "0.5",
                    "--out", str(tmp_path / "o.json")]) == 0
    o = json.loads((tmp_path / "o.json").read_text())
    assert o["interval"]["rl2s"]["deployed"] == sum(sum(e["guard_accepted_interval"])
                                                    for e in entries)
    assert o["floor"]["rl2s"]["deployed"] == 12 and o["floor"]["rl2s"]["control_median_gain"] == 0.4


def test_read_calibration_takes_a_saved_calibration_or_validation_runs(tmp_path):
    """read_calibration: a saved calibration as it is (q None: infinite), validation-split
    results as calibration_from_runs pools them; every refusal names --guard-calibration."""
    saved = {"task": "hopper", "level": 0.8, "q": None, "floor": 0.5, "n": 3}
    (tmp_path / "s.json").write_text(json.dumps(saved))
    cal = gi.read_calibration([str(tmp_path / "s.json")], "hopper")
    assert cal == {"level": 0.8, "q": math.inf, "floor": 0.5, "n": 3,
                   "source": [str(tmp_path / "s.json")]}
    start, gain = _members(np.random.default_rng(1), M=2, P=3)
    run = {"task": "hopper", "policy_split": "validation", "command": "c",
           "improvement": {"rl2s/0": _entry("rl2s", 0, start, gain, [100.0] * 3,
                                            [120.0, 100.0, 70.0], [True] * 3)}}
    (tmp_path / "v.json").write_text(json.dumps(run))
    cal = gi.read_calibration([str(tmp_path / "v.json")] * 2, "hopper", level=0.5)
    ref = gi.calibration_from_runs([run, run], "hopper", 0.5)
    assert {k: cal[k] for k in ("level", "q", "floor", "n")} == {
        k: ref[k] for k in ("level", "q", "floor", "n")}
    for bad, msg in (({**saved, "task": "ant"}, "calibrates task 'ant'"),
                     ({k: v for k, v in saved.items() if k != "floor"}, "lacks ['floor']"),
                     ({**saved, "floor": 0}, "floor > 0"), ({**saved, "level": 1.2}, "level in")):
        (tmp_path / "b.json").write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=r"^guard-calibration: .*" + msg.replace(
                "(", r"\(").replace("[", r"\[")):
            gi.read_calibration([str(tmp_path / "b.json")], "hopper")
    with pytest.raises(ValueError, match="guard-calibration: a saved calibration comes alone"):
        gi.read_calibration([str(tmp_path / "s.json"), str(tmp_path / "v.json")], "hopper")


def test_improve_report_of_the_interval_guard_with_an_infinite_q():
    """rl2s improve's summary.md under the interval guard (from a hand-made summary): the
    calibration line says q is infinite and why, an unbounded lower end prints -inf, nothing
    deploys; the floor guard's no-interval line is absent, the simulated return's present."""
    from rl2s_jax.app.improvement import summary_markdown
    from rl2s_jax.app.value_intervals import NO_INTERVAL

    g = {"kind": "interval", "accepted": [False, False], "gain": [0.2, -0.1],
         "gain_lower": [None, None], "predicted_gain": [0.1, -0.2],
         "predicted_gain_mean": [0.2, -0.1],
         "calibration": {"level": 0.9, "q": None, "q_infinite": True, "floor": 0.01, "n": 3,
                         "source": ["cal.json"]}}
    rows = [{"policy": p, "sim_return_curve": [1.0, 2.0], "deployed_fine_tuned": False}
            for p in ("a", "b")]
    md = summary_markdown({"task": "pointmass", "iterations": 5, "checkpoint": "ck",
                           "data": "d.npz", "mpi": None, "guard": g, "policies": rows})
    assert ("level 0.9, q inf (too few calibration policies for the level), floor 0.01, n 3 "
            "calibration policies, from cal.json): 0 of 2 fine-tuned policies deployed") in md
    assert "| a | kept (start) | +0.200 | -inf | n/a | n/a |" in md
    assert NO_INTERVAL["floor_guard"] not in md and NO_INTERVAL["sim_return"] in md
