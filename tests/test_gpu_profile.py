"""experiments/gpu_profile.py on a tiny synthetic streams dir (fast, no JAX): the phase windows
on the stream's clock, the logged parts laid end to end, the busy GPU-seconds of the run's own
GPU against a hand computation and a fine-grid integral, the idle spans, the summary without
the trust phase, and the refusals of bad input."""
import json

import numpy as np
import pytest
from experiment_scripts import load_script

gp = load_script("gpu_profile")

PROGRESS = """[s1] 0 start 10:00:00 GPU 0: zoo --task ant
[s0] 0 start 10:00:00 GPU 1: paper hopper --seeds 3 --no-oracle
[s1] 0 rc 0 end 10:00:30
[s0] 0 rc 0 end 10:01:00
ALLDONE 10:01:00
"""
LOG = """NVIDIA H200, 143771 MiB
[paper] task hopper on NVIDIA H200 (gpu, jax 0.11.2), profile gpu, 3 seeds (0..2) -> x.json
[paper] train data: 17 policies x 20000 transitions
[paper] data: 10.5s (elapsed 14s)
[paper] adversarial: 6 lanes over 1 device(s) rl2s/0 (eps 0.25), config method rl2s; init 2.0s; \
the rl2s lanes pre-train for all (fork at step 1000)
[paper] adversarial step 600: 600 steps of 3 trunk lanes in 10.0s; test evaluation 3.0s
  rl2s     seed 0  AVD     44.8  MVD    401.5  tau  0.905
[paper] adversarial step 1200: 600 steps of 3 trunk lanes forked into 6 at step 1000 in 12.0s; \
test evaluation 2.0s
[paper] train_adversarial: 30.0s (elapsed 45s)
[paper] trust: 8.0s (elapsed 54s)
[paper] trust rl2s: level 0.9, coverage 0.917
[paper] hopper: 3 seeds on NVIDIA H200, 55s in all; timings {'data': 10.5, 'eval_adversarial': \
5.0, 'train_adversarial': 30.0, 'trust_calibration': 5.0, 'trust_adversarial': 2.0, 'trust': 8.0, \
'total': 55.0}
"""
# The stream runs 60 s and paper.py's clock 55 s, so its zero is at +5 s: data [8.5, 19],
# train_adversarial [20, 50] (init 20-22, steps 22-32, evaluation 32-35, steps 35-47,
# evaluation 47-49, the rest 49-50), trust [51, 59] (calibration 51-56, adversarial 56-58,
# the rest 58-59), gaps 19-20 and 50-51, start 0-8.5, end 59-60.
EXPECTED = [
    ("start: Python, imports, JAX's backend", None, 0.0, 8.5),
    ("data", None, 8.5, 19.0),
    ("train_adversarial", None, 20.0, 50.0),
    ("train_adversarial", "init (data to the device, lanes)", 20.0, 22.0),
    ("train_adversarial", "steps 1-600: 3 trunk lanes", 22.0, 32.0),
    ("train_adversarial", "test evaluation at step 600", 32.0, 35.0),
    ("train_adversarial", "steps 601-1200: 3 trunk lanes forked into 6 at step 1000", 35.0, 47.0),
    ("train_adversarial", "test evaluation at step 1200", 47.0, 49.0),
    ("train_adversarial", "the rest (final rows, bootstrap intervals)", 49.0, 50.0),
    ("trust", None, 51.0, 59.0),
    ("trust", "calibration policies' real values", 51.0, 56.0),
    ("trust", "adversarial family's interval programs", 56.0, 58.0),
    ("trust", "the rest (interval blocks per method)", 58.0, 59.0),
]
# GPU 1's samples at +1, +3, ..., +61 s: sample k holds over [2k, 2k + 2]. 0% up to +8, 40%
# over [8, 10], 100% over [10, 18], 70% over [18, 20], then a varied pattern.
U1 = [0, 0, 0, 0, 40, 100, 100, 100, 100, 70] + [(37 * k) % 101 for k in range(10, 31)]


def _stamp(seconds: float) -> str:
    whole = int(seconds)
    return f"2026/11/28 10:{whole // 60:02d}:{whole % 60:02d}.{round((seconds % 1) * 1000):03d}"


@pytest.fixture(scope="module")
def streams(tmp_path_factory):
    d = tmp_path_factory.mktemp("streams")
    (d / "progress.log").write_text(PROGRESS)
    (d / "s0_0_paper_hopper.log").write_text(LOG)
    rows = []
    for k, u in enumerate(U1):
        rows.append(f"{_stamp(1 + 2 * k)}, 0, 100 %, 5000 MiB")  # another GPU, always busy
        rows.append(f"{_stamp(1 + 2 * k)}, 1, {u} %, {0 if k < 3 else 9000} MiB")
    (d / "gpu_util.csv").write_text("\n".join(rows) + "\n")
    out = d / "profile.json"
    assert gp.main([str(d), "--json", str(out)]) == 0
    return d, json.loads(out.read_text())


def _grid_busy(a: float, b: float) -> float:
    """The utilization integrated on a 1-ms grid, each instant taking its nearest sample."""
    t = np.arange(a, b, 0.001) + 0.0005
    times = 1 + 2 * np.arange(len(U1))
    nearest = np.abs(t[:, None] - times[None, :]).argmin(axis=1)
    return float(np.sum(np.array(U1, float)[nearest] / 100) * 0.001)


def test_phase_windows_and_parts(streams):
    _, prof = streams
    (run,) = prof["runs"]
    assert (run["task"], run["gpu"], run["paper_clock_zero_s"]) == ("hopper", 1, 5.0)
    got = [(r["phase"], r.get("part"), r["a"], r["b"]) for r in run["rows"]
           if r["a"] is not None and not r["phase"].startswith("end")]
    assert got == EXPECTED
    between = next(r for r in run["rows"] if r["phase"].startswith("between"))
    assert between["wall_s"] == pytest.approx(2.0)
    assert run["rows"][-1]["wall_s"] == pytest.approx(1.0)  # end: 59-60
    assert run["total"]["wall_s"] == pytest.approx(60.0)
    assert run["first_memory_sample_s"] == pytest.approx(7.0)


def test_busy_seconds_match_a_hand_computation(streams):
    _, prof = streams
    rows = {(r["phase"], r.get("part")): r for r in prof["runs"][0]["rows"]}
    data = rows[("data", None)]
    # [8.5, 10] at 40%, [10, 18] at 100%, [18, 19] at 70%: 0.6 + 8 + 0.7
    assert data["busy_gpu_s"] == pytest.approx(9.3)
    assert data["idle_s"] == pytest.approx(10.5 - 9.3)
    assert data["util_pct"] == pytest.approx(100 * 9.3 / 10.5, abs=0.05)
    start = rows[("start: Python, imports, JAX's backend", None)]  # [8, 8.5] at 40%
    assert start["busy_gpu_s"] == pytest.approx(0.2)
    for (phase, part), r in rows.items():
        if r["a"] is not None:
            assert r["busy_gpu_s"] == pytest.approx(_grid_busy(r["a"], r["b"]), abs=0.01), \
                (phase, part)
    assert prof["runs"][0]["total"]["busy_gpu_s"] == pytest.approx(_grid_busy(0, 60), abs=0.02)


def test_idle_spans_and_summary(streams):
    _, prof = streams
    run, summary = prof["runs"][0], prof["summary"]
    assert run["idle_spans"] == [{"a": 0.0, "b": 8.0, "seconds": 8.0,
                                  "where": "start: Python, imports, JAX's backend"}]
    trust = next(r for r in run["rows"] if r["phase"] == "trust" and "part" not in r)
    assert run["trust_wall_s"] == pytest.approx(8.0)
    assert summary["one_gpu"]["protocol_wall_s"] == pytest.approx(60.0 - 8.0)
    assert summary["one_gpu"]["protocol_busy_gpu_s"] == pytest.approx(
        run["total"]["busy_gpu_s"] - trust["busy_gpu_s"], abs=0.1)
    assert summary["oracle_wall_s"] == 0.0
    assert summary["by_phase"]["train_adversarial / steps 1-600"]["wall_s"] == pytest.approx(10.0)


def test_bad_input_is_refused_with_its_file(streams, tmp_path):
    d, _ = streams
    (tmp_path / "progress.log").write_text(PROGRESS.replace(" GPU 1: paper", ": paper"))
    (tmp_path / "gpu_util.csv").write_text((d / "gpu_util.csv").read_text())
    with pytest.raises(SystemExit, match="no GPU pin"):
        gp.main([str(tmp_path)])
    (tmp_path / "progress.log").write_text(PROGRESS)
    (tmp_path / "s0_0_paper_hopper.log").write_text(LOG.rsplit("[paper] hopper:", 1)[0])
    with pytest.raises(SystemExit, match="s0_0_paper_hopper.log.*'total'"):
        gp.main([str(tmp_path)])
    with pytest.raises(SystemExit, match="expected progress.log"):
        gp.main([str(tmp_path / "nowhere")])


def test_trust_parts_name_the_real_env_measurements():
    """The trust phase's logged parts end to end: the calibration and the evaluated set's
    real-env values, then each family's programs, the rest up to the phase's end."""
    log = {"timings": {"trust_calibration": 5.0, "trust_evaluated": 3.0,
                       "trust_adversarial": 2.0}, "families": {}}
    assert gp._parts("trust", log, 10.0, 30.0) == [
        ("calibration policies' real values", 10.0, 15.0),
        ("evaluated (perturbed test) policies' real values", 15.0, 18.0),
        ("adversarial family's interval programs", 18.0, 20.0),
        ("the rest (interval blocks per method)", 20.0, 30.0)]


def test_data_parts_are_parts_of_the_data_phase(tmp_path):
    """paper.py's "[paper] data_<part>" lines are the data phase's parts, not phases of their
    own: laid end to end from its start with their labels, the rest up to its end; a log
    without them leaves the data phase whole."""
    parts = ("[paper] data_setup: 1.0s (elapsed 6s)\n[paper] data_rollout_compile: 2.0s "
             "(elapsed 8s)\n[paper] data_rollout_run: 3.5s (elapsed 11s)\n[paper] "
             "data_split_save: 1.5s (elapsed 13s)\n")
    timings = "'data_setup': 1.0, 'data_rollout_compile': 2.0, 'data_rollout_run': 3.5, " \
              "'data_split_save': 1.5, 'data': 10.5,"
    text = LOG.replace("[paper] data: 10.5s", parts + "[paper] data: 10.5s").replace(
        "'data': 10.5,", timings)
    (tmp_path / "run.log").write_text(text)
    log = gp.parse_log(str(tmp_path / "run.log"))
    assert [p[0] for p in log["phases"]] == ["data", "train_adversarial", "trust"]
    assert gp._parts("data", log, 8.5, 19.0) == [
        ("setup (zoo, env)", 8.5, 9.5),
        ("transitions compile (trace, lower, XLA or cache)", 9.5, 11.5),
        ("transitions run (chunks, each copied to the host)", 11.5, 15.0),
        ("split and save (compressed .npz files)", 15.0, 16.5),
        ("the rest (logs, between parts)", 16.5, 19.0)]
    assert gp._parts("data", {"timings": {"data": 10.5}, "families": {}}, 8.5, 19.0) == []
