"""experiments/gpu_share.py: the summary's throughput ratios and the processes' barrier."""
import json

import pytest
from experiment_scripts import load_script

share = load_script("gpu_share")


def _case(tmp_path, name, ms):
    (tmp_path / f"{name}.json").write_text(json.dumps({"step_ms": ms}))


def test_summary_throughput_is_steps_per_second_over_one_process_alone(tmp_path):
    _case(tmp_path, "alone_0", 10.0)
    _case(tmp_path, "pair_0", 20.0)   # time-sliced: each half as fast, 1.0x together
    _case(tmp_path, "pair_1", 20.0)
    _case(tmp_path, "mps_pair_0", 12.5)  # overlapping: 2 * 10 / 12.5 = 1.6x
    _case(tmp_path, "mps_pair_1", 12.5)
    _case(tmp_path, "notes", 1.0)     # not a case: ignored
    table = share.summarize(str(tmp_path))
    assert list(table) == ["alone", "pair", "mps_pair"]
    assert table["alone"]["throughput"] == pytest.approx(1.0)
    assert table["pair"] == {"processes": 2, "step_ms": 20.0, "throughput": pytest.approx(1.0)}
    assert table["mps_pair"]["throughput"] == pytest.approx(1.6)


def test_summary_without_the_process_alone_names_it(tmp_path):
    _case(tmp_path, "pair_0", 20.0)
    with pytest.raises(SystemExit, match="alone_0.json"):
        share.summarize(str(tmp_path))


def test_barrier_waits_for_every_process(tmp_path):
    (tmp_path / "ready_1").touch()  # the other process is there: returns at once
    share.wait_barrier(str(tmp_path), 2, 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ready_0", "ready_1"]
    with pytest.raises(SystemExit, match="3 processes expected"):
        share.wait_barrier(str(tmp_path), 3, 0, timeout_s=0.2)


def test_bad_counts_are_refused_before_any_compile(capsys):
    with pytest.raises(SystemExit):
        share.main(["--barrier", "/tmp/x", "--lanes", "0"])
    assert "--lanes: expected a whole number >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        share.main(["--barrier", "/tmp/x", "--n", "2", "--id", "2"])
    assert "0 <= --id < --n" in capsys.readouterr().err
