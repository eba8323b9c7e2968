"""Nothing lost (issue 65, item 1): no command replaces earlier results without --force, every
app-layer write is atomic, a resumed train keeps its earlier summary's results, Ctrl-C ends
with one line and status 130, and outputs are probed for real at the door."""

import ast
import json
import os
import pathlib
import time

import pytest
from test_cli_doors import refused, tiny_dataset

from rl2s_jax import _files, cli
from rl2s_jax.app import paths

PKG = pathlib.Path(__file__).resolve().parents[1] / "rl2s_jax"


# --------------------------------------------------------------------------- atomic writes

def test_atomic_write_replaces_whole_or_not_at_all(tmp_path):
    path = tmp_path / "r.json"
    _files.write_json(path, {"a": [1, 2]})
    assert json.loads(path.read_text()) == {"a": [1, 2]}
    plain = tmp_path / "plain"
    plain.write_text("x")
    assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777
    for stop in (KeyboardInterrupt, OSError):
        with pytest.raises(stop):
            with _files.atomic_open(path) as f:
                f.write("half a fi")
                raise stop("stopped mid-write")
    with pytest.raises(TypeError):
        _files.write_json(path, {"a": object()})  # fails before anything is written
    assert json.loads(path.read_text()) == {"a": [1, 2]}
    assert sorted(os.listdir(tmp_path)) == ["plain", "r.json"]  # no temporary files left
    with pytest.raises(ValueError, match="mode"):
        with _files.atomic_open(path, "a"):
            pass


def _raw_writes(tree: ast.AST) -> list[int]:
    """Lines of writes that bypass rl2s_jax/_files.py: open(..., "w"/"wb"), json.dump(...),
    np.savez*(PATH, ...) with a path rather than a file object, Matplotlib's savefig."""
    lines = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        fn = node.func
        name = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
        mode = [a.value for a in node.args[1:2] if isinstance(a, ast.Constant)]
        if name == "open" and mode and mode[0] in ("w", "wb"):
            lines.append(node.lineno)
        elif name == "dump" and getattr(fn.value, "id", "") == "json":
            lines.append(node.lineno)
        elif name.startswith("savez") and node.args and not isinstance(node.args[0], ast.Name):
            lines.append(node.lineno)
        elif name == "savefig":  # a figure goes through _files.save_figure
            lines.append(node.lineno)
    return lines


def test_app_and_data_layers_write_atomically():
    """Every whole-file write of the package goes through rl2s_jax/_files.py (appends to
    logs are not whole-file writes)."""
    raw = {str(p.relative_to(PKG)): lines for p in sorted(PKG.rglob("*.py"))
           if p.name != "_files.py" and (lines := _raw_writes(ast.parse(p.read_text())))}
    assert not raw, f"writes that are not atomic: {raw}"
    assert sorted(_raw_writes(ast.parse("import json\njson.dump(x, open('p', 'w'))\n"
                                        "np.savez(os.path.join(d, 'z.npz'), a=1)\n"
                                        "fig.savefig('f.png', dpi=9)"))) == [2, 2, 3, 4]
    experiments = PKG.parent / "experiments"
    figures = {p.name: [n for n in _raw_writes(ast.parse(p.read_text()))
                        if "savefig" in p.read_text().splitlines()[n - 1]]
               for p in sorted(experiments.glob("*.py"))}
    assert not {k: v for k, v in figures.items() if v}, f"figures not atomic: {figures}"


def test_save_figure_is_atomic(tmp_path):
    """save_figure writes the format the suffix names, whole; a figure that fails half-way
    through leaves the earlier file as it was and no temporary file."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = tmp_path / "f.png"
    _files.save_figure(fig, path, dpi=20)
    png = path.read_bytes()
    assert png.startswith(b"\x89PNG")
    _files.save_figure(fig, tmp_path / "f.svg")
    assert b"<svg" in (tmp_path / "f.svg").read_bytes()[:500]

    def torn(f, **kwargs):  # a render that dies half-way through its bytes
        f.write(b"\x89PNG half")
        raise RuntimeError("render failed")

    fig.savefig = torn
    with pytest.raises(RuntimeError):
        _files.save_figure(fig, path, dpi=20)
    assert path.read_bytes() == png and sorted(os.listdir(tmp_path)) == ["f.png", "f.svg"]
    plt.close(fig)


def test_jsonl_reader_skips_a_torn_last_line(tmp_path):
    """An append torn by a crash leaves a partial last line: read_jsonl skips it, the report's
    curve loader and a resumed run's log truncation too (which rewrites the log whole); a bad
    line before the last is an error naming the line."""
    from rl2s_jax.app.report import load_curve
    from rl2s_jax.app.training import _truncate_metrics

    path = tmp_path / "metrics.jsonl"
    path.write_text('{"step": 1, "a": 0.5}\n\n{"step": 2, "a": NaN}\n{"step": 3, "a"')
    rows = _files.read_jsonl(path)
    assert rows[0] == {"step": 1, "a": 0.5} and rows[1]["step"] == 2 and len(rows) == 2
    assert [r["step"] for r in load_curve(str(path))] == [1, 2]
    _truncate_metrics(str(path), 5)
    assert path.read_text() == '{"step": 1, "a": 0.5}\n{"step": 2, "a": NaN}\n'
    path.write_text('{"step": 1}\n{"step": 2\n{"step": 3}\n')
    with pytest.raises(ValueError, match="line 2"):
        _files.read_jsonl(path)


# --------------------------------------------------------------------------- --force

def test_existing_outputs_refused_without_force(tmp_path, capsys):
    data = tiny_dataset(tmp_path / "d.npz")
    before = pathlib.Path(data).read_bytes()
    for argv in (["collect", "--task", "pointmass", "--transitions-per-policy", "5"],
                 ["import", "--minari", str(tmp_path / "m")]):
        err, seconds = refused([*argv, "--out", data], capsys)
        assert err == f"rl2s {argv[0]}: error: --out: '{data}' exists; --force replaces it\n"
        assert seconds < 5
    (tmp_path / "r.json").write_text("{}")
    err, _ = refused(["evaluate", "--oracle", "--data", data, "--json",
                      str(tmp_path / "r.json")], capsys)
    assert "--json: " in err and "--force replaces it" in err
    (tmp_path / "mds").mkdir()
    (tmp_path / "mds" / "data").mkdir()
    err, _ = refused(["export", "--minari", "--data", data, "--out", str(tmp_path / "mds")],
                     capsys)
    assert f"--out: '{tmp_path / 'mds'}' exists; --force replaces it" in err
    for command, names in (("improve", ["summary.json"]), ("diagnose", ["report.md"]),
                           ("pipeline", ["report.json", "report.md"]), ("zoo", ["zoo.json"])):
        d = tmp_path / command
        d.mkdir()
        for n in names:
            (d / n).write_text("{}")
        argv = {"improve": ["--ckpt", "c", "--data", data], "diagnose": ["--data", data],
                "pipeline": ["--task", "pointmass"], "zoo": ["--task", "pointmass"]}[command]
        err, _ = refused([command, *argv, "--out", str(d)], capsys)
        assert err == (f"rl2s {command}: error: --out: '{d}' holds an earlier run's "
                       f"{', '.join(names)}; --force replaces them\n")
    assert pathlib.Path(data).read_bytes() == before


def test_force_replaces_and_new_paths_pass(tmp_path):
    parser = cli.build_parser()
    data = tiny_dataset(tmp_path / "d.npz")
    for argv in (["collect", "--task", "pointmass", "--transitions-per-policy", "5",
                  "--out", data, "--force"],
                 ["collect", "--task", "pointmass", "--transitions-per-policy", "5",
                  "--out", str(tmp_path / "new.npz")],
                 ["train", "--data", data, "--steps", "1", "--out", str(tmp_path)],
                 ["diagnose", "--data", data, "--out", str(tmp_path)],  # no report there
                 ["zoo", "--task", "pointmass", "--out", str(tmp_path), "--plots-only"]):
        assert paths.outputs_error(parser.parse_args(argv)) is None, argv


def test_every_forced_command_has_force():
    subs = next(a for a in cli.build_parser()._actions if a.dest == "command").choices
    have = {name for name, p in subs.items()
            if "--force" in {s for a in p._actions for s in a.option_strings}}
    assert have == set(paths.FORCED)
    assert {"collect", "import", "export", "evaluate", "improve", "pipeline", "diagnose",
            "zoo"} <= have and "train" not in have


def test_export_force_replaces_the_directory(tmp_path, capsys):
    pytest.importorskip("minari")
    data = tiny_dataset(tmp_path / "d.npz")
    out = tmp_path / "mds"
    out.mkdir()
    (out / "old.txt").write_text("earlier")
    assert cli.main(["export", "--minari", "--data", data, "--out", str(out), "--force"]) == 0
    assert not (out / "old.txt").exists() and (out / "data").is_dir()
    assert sorted(os.listdir(tmp_path)) == ["d.npz", "mds"]  # no staging left
    assert "'mds-v0'" in capsys.readouterr().out


# --------------------------------------------------------------------------- the door probes

def test_unwritable_places_are_found_by_trying(tmp_path, capsys):
    """os.access says yes for /proc (as root); a probe file there fails. The probe leaves
    nothing behind."""
    data = tiny_dataset(tmp_path / "d.npz")
    err, seconds = refused(["evaluate", "--oracle", "--data", data, "--json",
                            "/proc/rl2s/x.json"], capsys)
    assert err.startswith("rl2s evaluate: error: --json: cannot write to '/proc/rl2s/x.json': "
                          "no file can be created in '/proc'") and seconds < 5
    err, _ = refused(["diagnose", "--data", data, "--out", "/proc/rl2s-report"], capsys)
    assert "--out: cannot write to '/proc/rl2s-report'" in err
    assert paths.output_problem(str(tmp_path), "dir") is None
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]


# --------------------------------------------------------------------------- Ctrl-C

def _interrupt(monkeypatch, name, before=None):
    """Ctrl-C inside the command's app function ``rl2s_jax.app.<name>`` (it gets the spec)."""
    def stop(spec):
        if before:
            before(spec)
        raise KeyboardInterrupt
    monkeypatch.setattr(f"rl2s_jax.app.{name}", stop)


def test_ctrl_c_one_line_and_130(tmp_path, monkeypatch, capsys):
    data = tiny_dataset(tmp_path / "d.npz")
    _interrupt(monkeypatch, "datasets.run_collect")
    assert cli.main(["collect", "--task", "pointmass", "--transitions-per-policy", "5",
                     "--out", str(tmp_path / "new.npz")]) == 130
    err = capsys.readouterr().err
    assert err.strip() == "rl2s collect: stopped; nothing was written"
    assert "Traceback" not in err

    def half_report(spec):
        os.makedirs(spec.out)
        time.sleep(0.01)
        pathlib.Path(spec.out, "report.json").write_text("{}")
    _interrupt(monkeypatch, "diagnosis.run_diagnose", half_report)
    out = tmp_path / "diag"
    assert cli.main(["diagnose", "--data", data, "--out", str(out)]) == 130
    assert capsys.readouterr().err.strip() == \
        f"rl2s diagnose: stopped; written before the stop: {out / 'report.json'}"

    run = tmp_path / "run"
    for step in ("50", "100", "150.orbax-checkpoint-tmp-1"):
        (run / "checkpoints" / step).mkdir(parents=True)
    _interrupt(monkeypatch, "training.run_train")
    assert cli.main(["train", "--data", data, "--steps", "9", "--out", str(run)]) == 130
    assert capsys.readouterr().err.strip() == \
        "rl2s train: stopped (its newest checkpoint is step 100); the same command resumes"
    _interrupt(monkeypatch, "zoo_building.run_zoo")
    assert cli.main(["zoo", "--task", "pointmass", "--out", str(tmp_path / "z"), "--work",
                     str(tmp_path / "w")]) == 130
    assert "the same command continues from" in capsys.readouterr().err


# --------------------------------------------------------------------------- train reruns

SMALL = {"vd_horizon": 50, "vd_episodes": 2, "updates_per_step": 2, "gen_hidden": [32],
         "disc_hidden": [32], "hazard_steps": 0}


def test_rerun_into_a_finished_run_keeps_its_results(pm_files, tmp_path):
    """Rerunning `rl2s train` without --eval-data (the same or more steps) keeps the test
    evaluation and the warnings the earlier summary held, and says it kept them."""
    from rl2s_jax.app.specs import TrainSpec
    from rl2s_jax.app.training import run_training

    run = tmp_path / "run"
    first = run_training(TrainSpec(pm_files["train"], 2, str(run), "bc", profile="cpu",
                                   set=SMALL, quiet=True, eval_data=pm_files["test"],
                                   eval_every=2, eval_episodes=2), log=lambda _: None)
    saved = json.loads((run / "summary.json").read_text())
    jump = "[train] warning: the worst training-policy VD rose from 1 to 9 at step 2 (9.0x)"
    later = "[train] warning: ... at step 3 (9.0x)"  # after the step resumed from: dropped
    saved["worst_vd_jumps"] = [jump, later]
    (run / "summary.json").write_text(json.dumps(saved))
    again = run_training(TrainSpec(pm_files["train"], 2, str(run), "bc", profile="cpu",
                                   set=SMALL, quiet=True), log=lambda _: None)
    on_disk = json.loads((run / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(again))
    for k in ("avd_test", "mvd_test", "kendall_tau_test", "step_test", "eval_data"):
        assert on_disk[k] == first[k], k
    assert on_disk["worst_vd_jumps"] == [jump]
    assert set(on_disk["kept_from_earlier"]) >= {"avd_test", "step_test", "worst_vd_jumps"}
