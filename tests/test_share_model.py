"""experiments/share_model.py: the fluid model of processes sharing one GPU, on tasks whose
answer is worked out by hand, and the segments it reads from a profile."""
import json

import pytest
from experiment_scripts import load_script

model = load_script("share_model")


def _task(data_s, train_s):
    """A data phase that leaves the GPU idle, then a training phase that keeps it busy."""
    return [{"phase": "data", "wall_s": data_s, "busy_gpu_s": 0.0, "data": True},
            {"phase": "train", "wall_s": train_s, "busy_gpu_s": train_s, "data": False}]


def test_two_tasks_worked_out_by_hand():
    tasks = [_task(10.0, 10.0), _task(10.0, 10.0)]
    # one after another: 20 + 20
    assert model.simulate(tasks, 1, False)["total_s"] == pytest.approx(40.0)
    # staggered: B collects (idle GPU) while A trains (asks 1): no slowdown; then B trains
    r = model.simulate(tasks, 2, True)
    assert r["total_s"] == pytest.approx(30.0) and r["starts_s"] == pytest.approx([0.0, 10.0])
    # both at once: both collect for 10 s, then both train time-sliced at 0.92 / 2 each
    r = model.simulate(tasks, 2, False, efficiency=0.92)
    assert r["total_s"] == pytest.approx(10.0 + 10.0 / 0.46)
    assert r["ends_s"] == pytest.approx([r["total_s"]] * 2)
    # a GPU half used by each: the asks sum to 1, nothing slows
    half = [{"phase": "x", "wall_s": 8.0, "busy_gpu_s": 4.0, "data": False}]
    assert model.simulate([half, half], 2, False)["total_s"] == pytest.approx(8.0)


def test_segments_from_a_profile_and_the_command(tmp_path, capsys):
    rows = [{"phase": "start: Python", "wall_s": 10.0, "busy_gpu_s": 0.0},
            {"phase": "data", "wall_s": 100.0, "busy_gpu_s": 30.0},
            {"phase": "oracle", "wall_s": 50.0, "busy_gpu_s": 20.0},       # left out
            {"phase": "train_adversarial", "wall_s": 200.0, "busy_gpu_s": 150.0},  # has parts
            {"phase": "train_adversarial", "part": "init", "wall_s": 20.0, "busy_gpu_s": None},
            {"phase": "train_adversarial", "part": "steps", "wall_s": 180.0,
             "busy_gpu_s": 150.0},
            {"phase": "trust", "wall_s": 40.0, "busy_gpu_s": 10.0}]          # left out
    segs = model.task_segments(rows)
    assert [(s["phase"], s["data"]) for s in segs] == [
        ("start: Python", True), ("data", True), ("train_adversarial / init", False),
        ("train_adversarial / steps", False)]
    assert sum(s["wall_s"] for s in segs) == 310.0 and segs[2]["busy_gpu_s"] == 0.0
    path = tmp_path / "profile.json"
    path.write_text(json.dumps({"runs": [{"task": "hopper", "rows": rows},
                                         {"task": "ant", "rows": rows}]}))
    assert model.main([str(path), "--json", str(tmp_path / "m.json")]) == 0
    out = json.loads((tmp_path / "m.json").read_text())
    assert out["tasks"] == ["ant", "hopper"] and out["one_after_another"]["total_s"] == 620.0
    assert out["two_at_once"]["total_s"] < 620.0
    with pytest.raises(SystemExit, match="tasks: expected a comma list of hopper, ant"):
        model.main([str(path), "--tasks", "walker2d"])
    with pytest.raises(SystemExit):
        model.main([str(path), "--efficiency", "1.5"])
    assert "--efficiency: expected a float in (0, 1], got 1.5" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        model.main([str(path), "--also", "2"])
    assert "--also: expected a comma list of whole numbers >= 3, got '2'" in \
        capsys.readouterr().err
    assert model.main([str(path), "--also", "3", "--json", str(tmp_path / "m3.json")]) == 0
    assert "3_at_once" in json.loads((tmp_path / "m3.json").read_text())
