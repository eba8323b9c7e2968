"""`make paper`: experiments/paper_tables.py on synthetic results (fast, no JAX) and one CPU
smoke run of experiments/paper.py on Hopper at absurdly small sizes."""
import dataclasses
import json
import os
import sys

import numpy as np
import pytest
from experiment_scripts import load_script

from rl2s_jax.improve.finetune import deployment_guard
from rl2s_jax.improve.recipes import recipe_settings
from rl2s_jax.paper import tables as results_tables
from rl2s_jax.zoo.zoo import load_zoo

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
METRICS = ("kendall_tau", "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10", "spearman", "regret@1",
           "avd", "mvd", "mpi", "api")


_load = load_script


# ------------------------------------------------------------------ paper_tables.py


def _synthetic(task, tau, ndcg1, mvd, mpi, seeds=3):
    """A result JSON as paper.py writes it: per-seed lists (mpi/api for one seed only)."""
    per = {}
    for m in ("rl2s", "gail", "bc", "rl2s-bc"):
        per[m] = {k: [0.5 + 0.01 * i for i in range(seeds)] for k in METRICS}
        per[m]["mvd"] = [mvd[m] + d for d in (-10.0, 0.0, 10.0)][:seeds]
        per[m]["avd"] = [100.0, 110.0, 120.0][:seeds]
        per[m]["mpi"], per[m]["api"] = [-0.5], [0.1]
    per["rl2s"]["kendall_tau"] = [tau - 0.05, tau, tau + 0.05][:seeds]
    per["rl2s"]["ndcg@1"] = [ndcg1] * seeds
    per["rl2s"]["mpi"] = [mpi]
    return {"task": task, "methods": {}, "seeds": seeds, "hardware": "NVIDIA H100 80GB HBM3",
            "jax_version": "0.11.2", "command": f"python experiments/paper.py --task {task}",
            "timings": {"total": 412.3}, "complete": True, "per_seed": per}


def test_paper_tables(tmp_path):
    pt = _load("paper_tables")
    res = tmp_path / "results"
    res.mkdir()
    good = _synthetic("hopper", 0.85, 0.97, {"rl2s": 50, "gail": 80, "bc": 90, "rl2s-bc": 60},
                      0.2)
    bad = _synthetic("ant", 0.30, 0.90, {"rl2s": 85, "gail": 80, "bc": 90, "rl2s-bc": 60},
                     -0.1)
    # the control row, with a 95% interval
    good["per_seed"]["oracle"] = {"kendall_tau": [0.95, 0.97, 0.99], "ndcg@1": [1.0] * 3,
                                  "avd": [5.0, 6.0, 7.0], "mpi": [], "api": []}
    good["intervals"] = {"oracle": {"kendall_tau": {"lo": 0.9, "hi": 1.0, "std": 0.02}}}
    (res / "hopper.json").write_text(json.dumps(good))
    (res / "ant.json").write_text(json.dumps(bad))
    (res / "hopper_cpu_profile.json").write_text("{}")  # not a task file: ignored
    out = tmp_path / "RESULTS.md"
    out.write_text("# Results\n\nearlier text\n")
    assert pt.main(["--results", str(res), "--out", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("# Results\n\nearlier text\n")
    assert text.count(pt.BEGIN) == 1 and text.count(pt.END) == 1
    # mean ± sample std (n seeds), paper number beside (n/a where none is known)
    # mean ± sample std (n seeds), the paper's number (../shared/PAPER.md) beside
    assert "| hopper | rl2s | 0.850 ± 0.050 (3 seeds) | 0.3474 |" in text
    assert "| ant | rl2s | 0.300 ± 0.050 (3 seeds) | 0.8000 |" in text
    assert "| hopper | gail | 0.510 ± 0.010 (3 seeds) | -0.1895 |" in text
    assert "| hopper | bc | 0.510 ± 0.010 (3 seeds) | -0.0632 |" in text
    assert ("| hopper | rl2s | 0.200 (1 seed) | 0.0293 | 0.100 (1 seed) | 2.9400 |"
            in text)  # MPI/API
    assert "| ant | rl2s | -0.100 (1 seed) | -0.0210 |" in text
    assert "| hopper | rl2s | 110.0 ± 10.0 (3 seeds) | n/a | 50.0 ± 10.0 (3 seeds) | n/a |" in text
    # the oracle row in Table 1 and the VD table, with its interval; none in Table 2
    assert "| hopper | oracle | 0.970 ± 0.020 (3 seeds) [0.900, 1.000] | n/a |" in text
    assert "| hopper | oracle | 6.0 ± 1.0 (3 seeds) | n/a |" in text
    assert "| oracle |" not in text.split("### Table 2")[1].split("### Value")[0]
    assert "| ant | oracle |" not in text
    assert "walker2d" not in text.split("Table 1")[1]  # no result, no rows
    assert "NVIDIA H100 80GB HBM3" in text and "python experiments/paper.py --task ant" in text
    # quality bars per task
    bar_lines = text.split("### Quality bars")[1].split("### The MVD bar")[0].splitlines()
    bars = {line.split("|")[1].strip(): line for line in bar_lines if line.startswith("| ")}
    assert bars["hopper"].count("met (") == 5 and "MISSED" not in bars["hopper"]
    assert "met (0.970 / 1.000)" in bars["hopper"]  # the oracle's tau / nDCG@1
    assert bars["ant"].count("MISSED (") == 4 and "n/a (n/a)" in bars["ant"]
    assert "MISSED (85.0 vs 80.0, 90.0)" in bars["ant"]
    # a second run replaces the block, never duplicates it; text around it stays
    with open(out, "a") as f:
        f.write("\nafter the block\n")
    good["per_seed"]["rl2s"]["kendall_tau"] = [0.9, 0.9, 0.9]
    good["noise_ceiling"] = {"n_truth": 16, "n_sim": 32, "kendall_tau": {
        "mean": 0.987, "lo": 0.9, "hi": 1.0}, "ndcg@1": {"mean": 1.0, "lo": 1.0, "hi": 1.0}}
    (res / "hopper.json").write_text(json.dumps(good))
    assert pt.main(["--results", str(res), "--out", str(out)]) == 0
    text2 = out.read_text()
    assert "met (0.970 / 1.000; noise alone allows tau 0.99)" in text2
    assert text2.count(pt.BEGIN) == 1 and text2.count(pt.END) == 1
    assert "| hopper | rl2s | 0.900 ± 0.000 (3 seeds) | 0.3474 |" in text2
    assert "0.850 ± 0.050" not in text2
    assert text2.startswith("# Results\n\nearlier text\n") and "after the block" in text2
    # a fresh file gets just the block
    fresh = tmp_path / "new" / "tables.md"
    assert pt.main(["--results", str(res), "--out", str(fresh)]) == 0
    assert fresh.read_text().startswith(pt.BEGIN)


def test_paper_tables_mvd_paired_by_seed():
    """The MVD bar as paired differences: per seed RL2S - other, mean, 95% t-interval over
    seeds (t quantile 4.303 for 3 seeds), seeds where RL2S is lower; n/a without 2 seeds."""
    rt = results_tables
    r = {"per_seed": {"rl2s": {"mvd": [100.0, 120.0, 90.0]},
                      "gail": {"mvd": [110.0, 100.0, 95.0]},
                      "bc": {"mvd": [None, 130.0, None]}}}
    d = np.array([-10.0, 20.0, -5.0])
    half = 4.302653 * d.std(ddof=1) / np.sqrt(3)
    mid, lo, hi, lower, n = rt.paired_mvd(r, "gail")
    assert (mid, lower, n) == (pytest.approx(d.mean()), 2, 3)
    assert (lo, hi) == (pytest.approx(d.mean() - half, abs=1e-4),
                        pytest.approx(d.mean() + half, abs=1e-4))
    assert rt.paired_mvd(r, "bc") is None  # one seed with both
    assert rt.paired_mvd({"per_seed": {"rl2s": {"mvd": [1.0, 2.0]},
                                       "gail": {"mvd": [1.0, 2.0, 3.0]}}}, "gail") is None
    rows = rt.paired_mvd_rows({"hopper": r})
    assert rows[-1] == (f"| hopper | {d.mean():+.1f} [{d.mean() - half:+.1f}, "
                        f"{d.mean() + half:+.1f}], lower on 2 of 3 seeds | n/a |")


def test_paper_tables_control_and_ablation(tmp_path):
    """Table 2's real-env control row and its bar, and MPI / API per --improve-variants
    variant, beside the oracle row of Table 1."""
    pt = _load("paper_tables")
    r = _synthetic("hopper", 0.85, 0.97, {"rl2s": 50, "gail": 80, "bc": 90, "rl2s-bc": 60}, 0.2)
    r["per_seed"]["oracle"] = {"kendall_tau": [0.95, 0.97, 0.99], "ndcg@1": [1.0] * 3,
                               "mpi": [], "api": []}
    r["control"] = {"seeds": 2, "mpi": 0.05, "mpi_std": 0.01, "api": 0.3, "api_std": 0.1}
    r["ablation"] = {"full": {"methods": {"rl2s": {"mpi": 0.2, "api": 0.1}}},
                     "branched+penalty": {"methods": {"rl2s": {"mpi": 0.25, "api": None}}}}
    text = pt.render({"hopper": r}, "res")
    table2 = text.split("### Table 2")[1].split("### Value")[0]
    assert ("| hopper | control (real env) | 0.050 ± 0.010 (2 seeds) | n/a | "
            "0.300 ± 0.100 (2 seeds) | n/a | n/a | n/a | n/a | n/a |") in table2
    r["control"]["paired"] = True  # measure_improvement's C0 and C1: the paired columns too
    assert ("| 0.300 ± 0.100 (2 seeds) | n/a | 0.050 ± 0.010 (2 seeds) | n/a | "
            "0.300 ± 0.100 (2 seeds) | n/a |") in pt.render({"hopper": r}, "res")
    assert "| hopper | oracle |" in text.split("### Table 1")[1].split("### Table 2")[0]
    ablation = text.split("### Improvement by simulated-env variant")[1].split("### Value")[0]
    assert "| hopper | full | rl2s | 0.200 | 0.100 |" in ablation
    assert "| hopper | branched+penalty | rl2s | 0.250 | n/a |" in ablation
    assert "| hopper | full | gail | n/a | n/a |" in ablation
    b = results_tables.bars(r)
    assert b["control"] == (True, "0.050") and b["oracle"] == (True, "0.970 / 1.000")
    r["control"]["mpi"] = 6e-7  # float residue of kept policies' zero gains: no gain
    assert results_tables.bars(r)["control"] == (False, "0.000")
    del r["ablation"]["full"]  # one variant: no ablation table
    assert "### Improvement by simulated-env variant" not in pt.render({"hopper": r}, "res")


def test_paper_tables_provenance():
    """Each task's command and hardware, and those of its oracle and control rows (runs of
    their own, merged in); a path into the untracked run logs is marked as in git history."""
    pt = _load("paper_tables")
    r = _synthetic("walker2d", 0.85, 0.97, {"rl2s": 50, "gail": 80, "bc": 90, "rl2s-bc": 60},
                   0.2)
    r["oracle"] = {"source": "python experiments/oracle_check.py --out "
                   "experiments/cpu_runs/2026-11-26/oracle_walker2d_64", "hardware": "cpu",
                   "n_episodes": 64}
    r["control"] = {"seeds": 2, "mpi": 0.0, "api": 0.5, "device": "cuda:0",
                    "command": "python experiments/improve_control.py --tasks walker2d",
                    "source": "experiments/gpu_runs/2026-11-25c/control_walker2d.json"}
    lines = pt.provenance("walker2d", r)
    assert lines[0] == ("- walker2d: `python experiments/paper.py --task walker2d` on NVIDIA "
                        "H100 80GB HBM3 (3 seeds, jax 0.11.2, 412 s)")
    assert lines[1] == ("  - oracle row: `python experiments/oracle_check.py --out experiments/"
                        "cpu_runs/2026-11-26/oracle_walker2d_64` on cpu (64 episodes) (its "
                        "output: in git history at bf0c7b2)")
    assert lines[2] == ("  - control row: `python experiments/improve_control.py --tasks "
                        "walker2d` on device cuda:0 (2 seeds; `experiments/gpu_runs/2026-11-25c/"
                        "control_walker2d.json`, in git history at bf0c7b2)")
    assert "\n".join(lines) in pt.render({"walker2d": r}, "res")
    r["complete"] = False
    del r["oracle"], r["control"]
    assert pt.provenance("walker2d", r) == [
        "- walker2d: `python experiments/paper.py --task walker2d` on NVIDIA H100 80GB HBM3 "
        "(3 seeds, jax 0.11.2, 412 s, INCOMPLETE run)"]


def test_results_md_regenerates_from_the_json(tmp_path, capsys):
    """docs/RESULTS.md is its hand-written text plus the block that docs/results/*.json give,
    byte for byte, and at most 400 lines; --check fails on a stale block, not on hand edits."""
    pt = _load("paper_tables")
    path = os.path.join(ROOT, "docs", "RESULTS.md")
    with open(path, encoding="utf-8") as f:
        text = f.read()
    assert len(text.splitlines()) <= 400
    assert text.count(pt.BEGIN) == 1 and text.count(pt.END) == 1
    assert pt.main(["--check"]) == 0  # the repository's defaults
    results = os.path.join(ROOT, "docs", "results")
    assert pt.render(pt.load_results(results), "docs/results") in text
    copy = tmp_path / "RESULTS.md"
    copy.write_text(text, encoding="utf-8")
    args = ["--results", results, "--out", str(copy)]
    assert pt.main([*args, "--check"]) == 0
    # a stale cell inside the block: --check fails and writes nothing; a run restores it
    block = text[text.index(pt.BEGIN):text.index(pt.END)]
    cell = block.split("| hopper | rl2s | ")[1].split(" |")[0]
    copy.write_text(text.replace(f"| hopper | rl2s | {cell} |", "| hopper | rl2s | 0.123 |"),
                    encoding="utf-8")
    assert pt.main([*args, "--check"]) == 1
    assert "the generated block is not what" in capsys.readouterr().err
    assert copy.read_text(encoding="utf-8") != text
    assert pt.main(args) == 0
    assert copy.read_text(encoding="utf-8") == text
    # the hand-written text is free: an edit outside the markers is kept and passes
    edited = text.replace("## Method and caveats", "## Method and caveats (edited)")
    assert edited != text
    copy.write_text(edited, encoding="utf-8")
    assert pt.main([*args, "--check"]) == 0
    assert pt.main(args) == 0 and copy.read_text(encoding="utf-8") == edited


def test_paper_tables_model_selection_rows():
    """paper.py's ``selected`` (per method: per-seed test metrics at the point chosen on the
    training policies, and the chosen steps) becomes its own table; none without it."""
    pt = _load("paper_tables")
    r = _synthetic("walker2d", 0.1, 0.5, {"rl2s": 50, "gail": 80, "bc": 90, "rl2s-bc": 60}, 0.0)
    assert "### Model selection" not in pt.render({"walker2d": r}, "res")
    r["selected"] = {"rl2s": {"step": [200, 200, 400], "kendall_tau": [0.8, 0.9, 0.7],
                              "ndcg@1": [1.0, 0.9, 0.8], "avd": [200.0, 210.0, 220.0],
                              "mvd": [600.0, 650.0, 700.0]}}
    text = pt.render({"walker2d": r}, "res")
    table = text.split("### Model selection without the test policies")[1]
    assert ("| walker2d | rl2s | 0.800 ± 0.100 (3 seeds) | 0.900 ± 0.100 (3 seeds) | "
            "210.0 ± 10.0 (3 seeds) | 650.0 ± 50.0 (3 seeds) | 200, 200, 400 |") in table
    assert "| walker2d | gail |" not in table


def test_paper_tables_policy_rows():
    """Share improved, median I and the API without the smallest-|C0| policy, pooled over
    the seeds, against hand-computed values; guard counts only where the guard ran."""
    pt = _load("paper_tables")
    lanes = {"rl2s/0": {"method": "rl2s", "I": [0.1, -0.2, 9.0], "c0": [100.0, 50.0, 1.0],
                        "guard_accepted": [True, False, False]},
             "rl2s/1": {"method": "rl2s", "I": [0.3, 0.0, None], "c0": [100.0, -5.0, 1.0],
                        "guard_accepted": [False, False, True]},
             "gail/0": {"method": "gail", "I": [-0.1, 0.2], "c0": [10.0, 20.0]}}
    rows = pt.policy_rows({"hopper": {"ablation": {"full": {"lanes": lanes},
                                                   "full+guard": {"methods": {}}}}})
    assert len(rows) == 4
    # rl2s: I pooled = [0.1, -0.2, 9.0, 0.3, 0.0] (None dropped): 3 of 5 above 0, median 0.1;
    # without the smallest |C0| per seed: mean(0.1, -0.2) = -0.05 and mean(0.3) = 0.3 ->
    # 0.125; the guard deployed 2 of 6
    assert rows[2] == "| hopper | full | rl2s | 5 (2 seeds) | 0.60 | +0.100 | 0.125 | 2 of 6 |"
    assert rows[3] == "| hopper | full | gail | 2 (1 seeds) | 0.50 | +0.050 | 0.200 | n/a |"
    only = pt.policy_rows({"ant": {"improvement": lanes, "improve_variant": "branched"}})
    assert only[2].startswith("| ant | branched | rl2s |")
    assert pt.policy_rows({"ant": {}}) == []


def test_paper_tables_guard_rows(tmp_path, capsys):
    """The guard's table: per method the seed means of the lanes' MPI / API with every policy
    deployed, with the final-actor guard and with the snapshot guard (paired: min / mean of
    I_snapshot_paired), and the deployed counts, against hand-computed values."""
    pt = _load("paper_tables")
    lane = lambda m, mpi, snap, paired, acc: {
        "method": m, "mpi": mpi, "api": 1.0 + mpi, "mpi_deployed": 0.0, "api_deployed": 0.5,
        "guard_accepted": acc, "guard_snapshot": snap, "mpi_snapshot": min(paired),
        "api_snapshot": sum(paired) / len(paired), "I_snapshot_paired": paired}
    lanes = {"rl2s/0": lane("rl2s", -0.2, [0, 3, 0], [0.0, 0.4, 0.0], [False, True, False]),
             "rl2s/1": lane("rl2s", -0.1, [1, 2, 5], [0.2, -0.1, 0.5], [False, False, False]),
             "gail/0": {"method": "gail", "mpi": -0.3, "api": 0.1, "mpi_deployed": -0.05,
                        "api_deployed": 0.02, "guard_accepted": [True, False]}}
    res = {"walker2d": {"ablation": {"full": {"lanes": lanes}}}}
    rows = pt.guard_rows(res)
    assert len(rows) == 4
    # rl2s: MPI (-0.2 - 0.1) / 2; paired MPI (0.0 - 0.1) / 2, API (0.4 / 3 + 0.6 / 3) / 2;
    # deployed 1 final, 1 + 3 snapshots of 6 policies
    assert rows[2] == ("| walker2d | full | rl2s | 2 | -0.150 | 0.850 | 0.000 | 0.500 | -0.050 "
                       "| 0.167 | -0.050 | 0.167 | 1 / 4 of 6 |")
    # a run without --guard-snapshots: the snapshot columns are n/a, one count
    assert rows[3] == ("| walker2d | full | gail | 1 | -0.300 | 0.100 | -0.050 | 0.020 | n/a "
                       "| n/a | n/a | n/a | 1 of 2 |")
    assert len(pt.guard_rows(res, snapshots_only=True)) == 3          # gail's row left out
    assert pt.guard_rows({"ant": {"improvement": {"rl2s/0": {"method": "rl2s"}}}}) == []
    # the CLI prints the table of several single-task runs; a task twice is refused
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
    (tmp_path / "a" / "walker2d.json").write_text(json.dumps(res["walker2d"]))
    assert pt.main(["--guard", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert rows[2] in capsys.readouterr().out
    (tmp_path / "b" / "walker2d.json").write_text(json.dumps(res["walker2d"]))
    with pytest.raises(SystemExit, match="walker2d.json is in two"):
        pt.main(["--guard", str(tmp_path / "a"), str(tmp_path / "b")])


def test_paper_tables_fallbacks():
    pt, rt = _load("paper_tables"), results_tables
    # no per_seed: methods / std / n are used; unknown numbers print n/a
    r = {"methods": {"rl2s": {"kendall_tau": 0.4}}, "std": {"rl2s": {"kendall_tau": 0.1}},
         "n": {"rl2s": {"kendall_tau": 2}}, "seeds": 3}
    assert rt.stats(r, "rl2s", "kendall_tau") == (0.4, 0.1, 2)
    assert rt.stats(r, "gail", "kendall_tau") == (None, None, 0)
    assert rt.fmt_cell(None, None, 0) == "n/a"
    b = rt.bars(r)
    assert b["tau"] == (False, "0.400") and b["mvd"] == (None, "n/a") and b["mpi"][0] is None
    assert "No results" in pt.render({}, "nowhere")


def _family_run(methods, families, offset, complete=True, seeds=range(3)):
    """A result as ``paper.py --families F [--first-seed K]`` writes it: only its methods'
    entries, each a value per seed (offset + 0.1 * seed)."""
    seeds = list(seeds)
    per = {m: {k: [] if k in ("mpi", "api") else [offset + 0.1 * s for s in seeds]
               for k in METRICS} for m in methods}  # not fine-tuned
    return {"task": "hopper", "model": "ensemble", "seeds": len(seeds), "seed_ids": seeds,
            "profile": "gpu",
            "zoo_sha256": "ab" * 32, "true_value": [1.0, 2.0], "families": families,
            "sizes": {"steps": 300, "eval_every": 100, "test_policies": 2,
                      "seeds": len(seeds)},
            "command": f"python experiments/paper.py --families {families[0]}",
            "timings": {"data": 10.0, f"train_{families[0]}": 5.0, "total": 20.0},
            "complete": complete, "per_seed": per, "methods": {}, "std": {}, "n": {},
            "selected": {m: {"step": [100 * (s + 1) for s in seeds],
                             "kendall_tau": [offset] * len(seeds)} for m in methods},
            "lane_intervals": {m: [{"avd": {"lo": s - 1.0, "hi": s + 1.0, "std": 0.5}}
                                   for s in seeds] for m in methods},
            "train_config": {families[0]: {"method": families[0]}},
            "lanes": {f"{m}/{s}": {"seed": s} for m in methods for s in seeds},
            "curves": [{"lane": f"{m}/{seeds[0]}", "step": 100} for m in methods]}


def test_merge_runs_joins_the_two_families():
    """Runs of one protocol that trained different families (two device calls) make one
    result: every method's entries, curves and timings; runs that differ are refused."""
    mr = _load("merge_results")
    adv = _family_run(("rl2s", "gail"), ["adversarial"], 0.5)
    mle = _family_run(("rl2s-bc", "bc"), ["mle"], 0.2, complete=False)
    merged = mr.merge_runs([adv, mle])
    assert set(merged["methods"]) == {"rl2s", "gail", "rl2s-bc", "bc"}
    assert merged["methods"]["bc"]["kendall_tau"] == pytest.approx(0.3)
    assert merged["methods"]["rl2s"]["kendall_tau"] == pytest.approx(0.6)
    assert merged["std"]["gail"]["avd"] == pytest.approx(0.1)
    assert set(merged["methods_selected"]) == {"rl2s", "gail", "rl2s-bc", "bc"}
    assert merged["methods_selected"]["bc"]["kendall_tau"] == pytest.approx(0.2)
    assert len(merged["lanes"]) == 12 and len(merged["curves"]) == 4
    assert merged["families"] == ["adversarial", "mle"]
    assert merged["timings"] == {"data": 20.0, "train_adversarial": 5.0, "train_mle": 5.0,
                                 "total": 40.0}
    assert merged["timings_per_run"] == [adv["timings"], mle["timings"]]
    assert merged["complete"] is False  # one part was cut off
    assert "--families adversarial && " in merged["command"]
    assert "methods" not in adv["per_seed"] and adv["methods"] == {}  # inputs untouched
    for field, change in (("zoo_sha256", "cd" * 32), ("true_value", [1.0])):
        with pytest.raises(ValueError, match=field):
            mr.merge_runs([adv, {**mle, field: change}])
    with pytest.raises(ValueError, match="seeds"):
        mr.merge_runs([adv, _family_run(("rl2s-bc", "bc"), ["mle"], 0.2, seeds=range(2))])
    old = {k: v for k, v in mle.items() if k != "seed_ids"}  # results before --first-seed
    assert mr.merge_runs([adv, {**old, "seeds": 3}])["seed_ids"] == [0, 1, 2]
    with pytest.raises(ValueError, match="seeds"):
        mr.merge_runs([adv, {**old, "seeds": 2}])
    with pytest.raises(ValueError, match="sizes.steps"):
        mr.merge_runs([adv, {**mle, "sizes": {**mle["sizes"], "steps": 400}}])
    with pytest.raises(ValueError, match="rl2s"):
        mr.merge_runs([adv, adv])


def test_merge_runs_joins_seeds_of_other_runs():
    """Seeds run in another call on the same data (--first-seed) join their methods: every
    per-seed list in seed order whatever the parts' order, means, std and intervals over all
    seeds; a seed twice, methods left with different seeds, other training settings or a
    method fine-tuned in two seed-split runs are refused."""
    mr = _load("merge_results")
    adv = _family_run(("rl2s", "gail"), ["adversarial"], 0.5)
    more = _family_run(("rl2s", "gail"), ["adversarial"], 0.5, seeds=(3, 4))
    mle = _family_run(("rl2s-bc", "bc"), ["mle"], 0.2, seeds=range(5))
    merged = mr.merge_runs([more, mle, adv])
    assert merged["seeds"] == 5 and merged["seed_ids"] == [0, 1, 2, 3, 4]
    assert merged["sizes"]["seeds"] == 5
    expect = [0.5 + 0.1 * s for s in range(5)]
    for m in ("rl2s", "gail"):
        assert merged["per_seed"][m]["avd"] == pytest.approx(expect)
        assert merged["selected"][m]["step"] == [100, 200, 300, 400, 500]
        assert [iv["avd"]["lo"] for iv in merged["lane_intervals"][m]] == [-1, 0, 1, 2, 3]
        assert merged["intervals"][m]["avd"]["lo"] == pytest.approx(1.0)
        assert merged["methods"][m]["avd"] == pytest.approx(np.mean(expect))
        assert merged["std"][m]["avd"] == pytest.approx(np.std(expect, ddof=1))
        assert merged["n"][m]["avd"] == 5
    assert merged["per_seed"]["bc"]["avd"] == pytest.approx([0.2 + 0.1 * s for s in range(5)])
    assert len(merged["lanes"]) == 20 and merged["families"] == ["adversarial", "mle"]
    assert more["per_seed"]["rl2s"]["avd"] == pytest.approx([0.8, 0.9])  # inputs untouched
    with pytest.raises(ValueError, match=r"\{'gail': \[2\], 'rl2s': \[2\]\} in more than one"):
        mr.merge_runs([adv, _family_run(("rl2s", "gail"), ["adversarial"], 0.5,
                                           seeds=(2, 3))])
    with pytest.raises(ValueError, match="seeds: the methods ran different seeds"):
        mr.merge_runs([adv, mle])
    other = {**more, "train_config": {"adversarial": {"method": "gail"}}}
    with pytest.raises(ValueError, match="train_config.adversarial"):
        mr.merge_runs([adv, other, mle])
    tuned = json.loads(json.dumps(more))
    tuned["per_seed"]["rl2s"]["mpi"] = [0.1]
    adv_tuned = json.loads(json.dumps(adv))
    adv_tuned["per_seed"]["rl2s"]["mpi"] = [0.2]
    with pytest.raises(ValueError, match="improvement: method 'rl2s'"):
        mr.merge_runs([adv_tuned, tuned, mle])
    # one part fine-tuned: its values are kept as they are (not reordered by seed)
    one = mr.merge_runs([adv_tuned, more, mle])
    assert one["per_seed"]["rl2s"]["mpi"] == [0.2]


def test_merge_results_takes_the_oracle_of_another_run(tmp_path):
    """--oracle-paper copies another run's oracle row (per seed, intervals, noise ceiling) into
    a protocol run without one, and refuses a run with other episode counts or no oracle."""
    mr = _load("merge_results")
    sha = mr.zoo_sha256("hopper")
    run = {**_family_run(("rl2s", "gail"), ["adversarial"], 0.5), "zoo_sha256": sha}
    run["sizes"].update(eval_episodes=128, value_episodes=128, episode_length=None)
    orc = json.loads(json.dumps(run))
    orc["per_seed"] = {"oracle": {"kendall_tau": [0.97, 0.99]}}
    orc["methods"] = {"oracle": {"kendall_tau": 0.98}}
    orc["intervals"] = {"oracle": {"kendall_tau": {"lo": 0.9, "hi": 1.0}}}
    orc["noise_ceiling"] = {"kendall_tau": {"mean": 0.97}}
    paths = {}
    for name, r in (("run", run), ("orc", orc), ("none", run),
                    ("other", {**orc, "sizes": {**orc["sizes"], "eval_episodes": 32}})):
        paths[name] = tmp_path / f"{name}.json"
        paths[name].write_text(json.dumps(r))
    out = tmp_path / "out"
    assert mr.main(["--task", "hopper", "--paper", str(paths["run"]), "--oracle-paper",
                    str(paths["orc"]), "--out", str(out)]) == 0
    merged = json.loads((out / "hopper.json").read_text())
    assert merged["per_seed"]["oracle"] == {"kendall_tau": [0.97, 0.99]}
    assert merged["per_seed"]["rl2s"] == run["per_seed"]["rl2s"]
    assert merged["intervals"]["oracle"]["kendall_tau"]["lo"] == 0.9
    assert merged["noise_ceiling"]["kendall_tau"]["mean"] == 0.97
    assert merged["oracle"]["n_episodes"] == 128 and merged["oracle"]["seeds"] == 2
    for name, field in (("other", "sizes.eval_episodes"), ("none", "no oracle row")):
        with pytest.raises(SystemExit, match=field):
            mr.main(["--task", "hopper", "--paper", str(paths["run"]), "--oracle-paper",
                     str(paths[name]), "--out", str(out)])
    with pytest.raises(SystemExit, match="at most one oracle source"):
        mr.main(["--task", "hopper", "--paper", str(paths["run"]), "--oracle", str(paths["orc"]),
                 "--oracle-paper", str(paths["orc"]), "--out", str(out)])
    # a run on the validation policies (--policy-split validation) is not the task's protocol
    (tmp_path / "val.json").write_text(json.dumps({**run, "policy_split": "validation"}))
    with pytest.raises(SystemExit, match="ran on the validation split"):
        mr.main(["--task", "hopper", "--paper", str(tmp_path / "val.json"), "--out", str(out)])


def test_merge_results_control_records_its_policies_and_median_gain(tmp_path):
    """--control (--keep): the control's zoo ids, issue 39's median gain on them (by hand) and
    its deployed count go into the task's result; the rest of the file is kept."""
    mr = _load("merge_results")
    zoo = load_zoo("hopper")
    ids = zoo.split_ids("test")[:2]
    zret = np.asarray(zoo.returns, np.float64)
    start = zret[ids]
    c0 = [[100.0, 200.0]]
    c1 = [[150.0, 190.0]]  # I = +0.5, -0.05
    ctl = {"task": "hopper", "zoo_ids": ids, "seeds": 1, "iterations": 10, "device": "cpu",
           "command": "improve_control.py", "configs": {"fine_tuning": {
               "c0": c0, "c1": c1, "I": [0.5, -0.05], "mpi": -0.05, "api": 0.225,
               "mpi_ci95": [0, 0], "api_ci95": [0, 0], "paired": True, "sac": {"n_envs": 4},
               "selected": [[2, 0]]}}}
    (tmp_path / "c.json").write_text(json.dumps(ctl))
    (tmp_path / "hopper.json").write_text(json.dumps({"task": "hopper", "methods": {"x": 1}}))
    assert mr.main(["--task", "hopper", "--keep", "--control", str(tmp_path / "c.json"),
                    "--out", str(tmp_path)]) == 0
    got = json.loads((tmp_path / "hopper.json").read_text())
    c = got["control"]
    assert got["methods"] == {"x": 1} and c["zoo_ids"] == ids and c["policies"] == 2
    below = start < np.quantile(zret, 0.75)
    assert c["n_below"] == int(below.sum())
    assert c["median_gain"] == pytest.approx(float(np.median(np.array([0.5, -0.05])[below])))
    assert c["deployed"] == 1 and c["budget_env_steps"] == 40
    (tmp_path / "t.json").write_text(json.dumps({**ctl, "split": "train"}))
    with pytest.raises(SystemExit, match="control: fine-tuned the train policies"):
        mr.main(["--task", "hopper", "--keep", "--control", str(tmp_path / "t.json"),
                 "--out", str(tmp_path)])


def test_merge_runs_joins_the_improvement_variants():
    """Each family's run fine-tuned its own lanes: the merged 'ablation' holds every method of
    every variant; runs fine-tuned with other settings are refused."""
    mr = _load("merge_results")

    def with_ablation(run, methods):
        settings = {"rollout_length": None}
        run["ablation"] = {
            "full": {"settings": settings,
                     "lanes": {f"{m}/0": {"mpi": -0.1} for m in methods},
                     "methods": {m: {"mpi": -0.1, "api": 0.5} for m in methods}},
            "full+guard": {"settings": settings,
                           "methods": {m: {"mpi": 0.0, "api": 0.4} for m in methods}}}
        run["sac_config"] = {"kl_weight": 0.1}
        return run

    adv = with_ablation(_family_run(("rl2s", "gail"), ["adversarial"], 0.5), ("rl2s", "gail"))
    mle = with_ablation(_family_run(("rl2s-bc", "bc"), ["mle"], 0.2), ("rl2s-bc", "bc"))
    merged = mr.merge_runs([adv, mle])
    for variant in ("full", "full+guard"):
        assert set(merged["ablation"][variant]["methods"]) == {"rl2s", "gail", "rl2s-bc", "bc"}
    assert set(merged["ablation"]["full"]["lanes"]) == {"rl2s/0", "gail/0", "rl2s-bc/0", "bc/0"}
    assert set(adv["ablation"]["full"]["methods"]) == {"rl2s", "gail"}  # inputs untouched
    other = json.loads(json.dumps(mle))
    other["ablation"]["full"]["settings"] = {"rollout_length": 10}
    with pytest.raises(ValueError, match="ablation.full.settings"):
        mr.merge_runs([adv, other])
    with pytest.raises(ValueError, match="sac_config"):
        mr.merge_runs([adv, {**mle, "sac_config": {"kl_weight": 0.01}}])


def test_paper_refuses_bad_seed_arguments(tmp_path, capsys):
    """--seeds 0 and a negative --first-seed stop with the field named, before any work."""
    paper = _load("paper")
    with pytest.raises(SystemExit):
        paper.build_parser().parse_args(["--task", "hopper", "--seeds", "0"])
    assert "--seeds: expected an int >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="first-seed: expected an int >= 0, got -1"):
        paper.main(["--task", "hopper", "--profile", "cpu", "--first-seed", "-1",
                    "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_paper_families_flag():
    paper = _load("paper")
    assert [f for f, _, _ in paper.parse_families("mle")] == ["mle"]
    assert [f for f, _, _ in paper.parse_families(" mle,adversarial ")] == ["adversarial", "mle"]
    for bad in ("", "rl2s", "adversarial,gan"):
        with pytest.raises(SystemExit, match="families"):
            paper.parse_families(bad)


def test_paper_eps_lanes_flag():
    """--eps-lanes adds rl2s@EPS lanes to the adversarial family after its rl2s lanes (the
    fork's trunk stays first); bad values, no adversarial family or fine-tuning are refused."""
    from rl2s_jax.paper.protocol import lane_eps
    paper = _load("paper")
    fams = paper.add_eps_lanes(paper.parse_families("adversarial,mle"), "0.05, 0.5,0.05", 0)
    assert fams[0][2] == ("rl2s", "rl2s@0.05", "rl2s@0.5", "gail")
    assert fams[1][2] == ("rl2s-bc", "bc")
    assert [lane_eps(m) for m in fams[0][2]] == [0.25, 0.05, 0.5, 1.0]
    assert lane_eps("rl2s", 0.1) == 0.1 and lane_eps("gail", 0.1) == 1.0
    assert lane_eps("rl2s@0.5", 0.1) == 0.5
    for text, fam, it, what in (("0", "adversarial", 0, "floats in"),
                                ("a,b", "adversarial", 0, "floats in"),
                                ("0.1", "mle", 0, "adversarial family"),
                                ("0.1", "adversarial", 100, "improve-iterations 0"),
                                ("0.1", "adversarial", None, "improve-iterations 0")):
        with pytest.raises(SystemExit, match=what):
            paper.add_eps_lanes(paper.parse_families(fam), text, it)
    # which eps give the same selection size max(2, ceil(eps P)), hence identical lanes
    assert paper.identical_eps([0.25, 0.05, 0.1, 0.5], 17) == [[0.05, 0.1]]
    assert paper.identical_eps([0.25, 0.05, 0.1, 0.5], 32) == []
    assert paper.identical_eps([0.25, 0.05, 0.3, 0.1, 0.5], 10) == [[0.25, 0.3], [0.05, 0.1]]


def test_paper_sizes_per_task():
    """Ant's, Hopper's and Walker2d's gpu sizes measure enough episodes for their noisy
    returns, HalfCheetah keeps the profile's; flags still win."""
    paper = _load("paper")
    args = paper.build_parser().parse_args(["--task", "ant"])
    sizes = paper.resolve_sizes(args, "gpu")
    assert (sizes["value_episodes"], sizes["eval_episodes"]) == (256, 256)
    assert sizes["seeds"] == paper.PROFILES["gpu"]["seeds"]
    hopper = paper.resolve_sizes(paper.build_parser().parse_args(["--task", "hopper"]), "gpu")
    assert (hopper["value_episodes"], hopper["eval_episodes"]) == (128, 128)
    walker = paper.resolve_sizes(paper.build_parser().parse_args(["--task", "walker2d"]), "gpu")
    assert (walker["value_episodes"], walker["eval_episodes"]) == (64, 64)
    cheetah = paper.resolve_sizes(paper.build_parser().parse_args(["--task", "halfcheetah"]),
                                  "gpu")
    assert (cheetah["value_episodes"], cheetah["eval_episodes"]) == (
        paper.PROFILES["gpu"]["value_episodes"], paper.PROFILES["gpu"]["eval_episodes"])
    cpu = paper.resolve_sizes(paper.build_parser().parse_args(["--task", "ant"]), "cpu")
    assert cpu["value_episodes"] == paper.PROFILES["cpu"]["value_episodes"]
    flags = paper.build_parser().parse_args(["--task", "ant", "--eval-episodes", "64"])
    assert paper.resolve_sizes(flags, "gpu")["eval_episodes"] == 64


def test_improve_recipe_sets_the_measured_flags_and_flags_given_win():
    """--improve-recipe control: issue 39's measured flags as the defaults, SAC at KL 0.01
    through --sac-set; a flag on the command line (and a later --sac-set) wins."""
    paper = _load("paper")
    args = paper.parse_args(["--task", "hopper", "--improve-recipe", "control"])
    sizes = paper.resolve_sizes(args, "gpu")
    assert (sizes["improve_iterations"], sizes["sac_envs"], sizes["sac_critic_warmup"],
            sizes["sac_updates_per_step"]) == (4000, 128, 2000, 32)
    _, _, sac, _ = paper.check_arguments(args)
    assert sac["kl_weight"] == 0.01 and sac["gamma"] == paper.fine_tuning_recipe("hopper")["gamma"]
    assert args.guard_margin == 0.02 and args.improve_variants == "branched+penalty"
    mine = paper.parse_args(["--task", "hopper", "--improve-recipe", "control",
                             "--improve-iterations", "10", "--sac-set", "kl_weight=0.1"])
    assert paper.resolve_sizes(mine, "gpu")["improve_iterations"] == 10
    assert paper.check_arguments(mine)[2]["kl_weight"] == 0.1
    plain = paper.parse_args(["--task", "hopper"])
    assert plain.guard_margin is None and not plain.zoo_recipe and plain.sac_set is None
    # a task's change to the recipe (HalfCheetah: no KL anchor, 8,000 iterations); its other
    # flags stay, and a flag or --sac-set given still wins
    cheetah = paper.parse_args(["--task", "halfcheetah", "--improve-recipe", "control"])
    assert paper.check_arguments(cheetah)[2]["kl_weight"] == 0
    assert (paper.resolve_sizes(cheetah, "gpu")["sac_envs"],
            paper.resolve_sizes(cheetah, "gpu")["improve_iterations"]) == (128, 8000)
    assert paper.resolve_sizes(paper.parse_args(
        ["--task", "halfcheetah", "--improve-recipe", "control", "--improve-iterations",
         "4000"]), "gpu")["improve_iterations"] == 4000
    assert paper.check_arguments(paper.parse_args(
        ["--task", "halfcheetah", "--improve-recipe", "control", "--sac-set",
         "kl_weight=0.01"]))[2]["kl_weight"] == 0.01
    with pytest.raises(SystemExit):
        paper.parse_args(["--task", "hopper", "--improve-recipe", "nope"])


def test_improve_recipe_guard_floor_scale_reaches_both_front_ends(monkeypatch):
    """A task's guard floor scale in the recipe (as a calibration sets it: Walker2d's 0, Ant's
    0.5) becomes paper.py's --guard-floor-scale and ``recipe_settings``' (rl2s improve); a flag
    given wins; the recipe's own is 1 (the training MVD)."""
    from rl2s_jax.improve import recipes

    paper = _load("paper")
    assert recipes.IMPROVE_RECIPES["control"]["guard_floor_scale"] == 1.0
    for task, scale in (("hopper", 1.0), ("walker2d", 0.0), ("ant", 0.5)):
        assert paper.parse_args(["--task", task, "--improve-recipe", "control"]
                                ).guard_floor_scale == scale
        assert recipe_settings("control", task)["guard_floor_scale"] == scale
    monkeypatch.setitem(recipes.IMPROVE_RECIPE_TASKS["control"], "hopper",
                        {"guard_floor_scale": 0.25})
    assert paper.parse_args(["--task", "hopper", "--improve-recipe", "control"]
                            ).guard_floor_scale == 0.25
    assert recipe_settings("control", "hopper")["guard_floor_scale"] == 0.25
    assert paper.parse_args(["--task", "walker2d", "--improve-recipe", "control",
                             "--guard-floor-scale", "1"]).guard_floor_scale == 1.0
    assert recipe_settings("control", "halfcheetah")["guard_floor_scale"] == 1.0


def test_no_task_changes_the_recipe_margin():
    """``app.improvement.guard_margin`` gives a recipe's margin from IMPROVE_RECIPES before the
    task is known (rl2s improve reads it from the checkpoint later), so a per-task margin would
    reach paper.py but not rl2s improve or rl2s pipeline: none may exist until that is built."""
    from rl2s_jax.improve import recipes

    for name, tasks in recipes.IMPROVE_RECIPE_TASKS.items():
        for task, change in tasks.items():
            assert "guard_margin" not in change, (name, task)


@pytest.mark.parametrize("task", ["hopper", "halfcheetah", "ant"])
def test_rl2s_improve_recipe_is_paper_py_recipe(task):
    """``recipe_settings`` (rl2s improve --recipe) resolves to what paper.py --improve-recipe
    runs: the same SAC fields, iterations, envs, updates, warm-up, branches and penalty; a task
    without a zoo learner (a user's own system) gets the rest without the zoo's discount."""
    paper = _load("paper")
    args = paper.parse_args(["--task", task, "--improve-recipe", "control"])
    sizes, (variants, _, sac, _) = paper.resolve_sizes(args, "gpu"), paper.check_arguments(args)
    rs = recipe_settings("control", task)
    assert rs["zoo_recipe"] and {k: rs["sac"][k] for k in sac} == sac
    assert (rs["iterations"], rs["sac"]["n_envs"], rs["sac"]["updates_per_step"],
            rs["sac"]["critic_warmup_updates"]) == (
        sizes["improve_iterations"], sizes["sac_envs"], sizes["sac_updates_per_step"],
        sizes["sac_critic_warmup"])
    assert variants == ["branched+penalty"] and rs["guard_margin"] == args.guard_margin
    assert (rs["branch_length"], rs["uncertainty_penalty"]) == (args.branch_length,
                                                                args.uncertainty_penalty)
    own = recipe_settings("control", "my_robot")
    assert not own["zoo_recipe"] and "gamma" not in own["sac"]
    assert own["sac"]["kl_weight"] == 0.01 and own["iterations"] == 4000
    with pytest.raises(ValueError, match="recipe: expected one of"):
        recipe_settings("nope", task)


# ------------------------------------------------------------------ paper.py smoke


def _validation_run(tmp_path) -> str:
    """A stand-in for a paper.py --policy-split validation run (the interval guard's
    calibration): one lane of 3 fine-tuned policies with members' gains and real gains."""
    start = [[100.0, 50.0, 80.0], [101.0, 52.0, 79.0]]
    entry = {"method": "rl2s", "seed": 0, "guard_member_start": start,
             "guard_member_gain": [[5.0, -2.0, 1.0], [6.0, -1.0, 3.0]],
             "I_paired": [0.04, -0.05, 0.02]}
    path = tmp_path / "validation.json"
    path.write_text(json.dumps({"task": "hopper", "policy_split": "validation",
                                "command": "val", "improvement": {"rl2s/0": entry}}))
    return str(path)


def _check_trust(r: dict, printed: str, n_test: int) -> None:
    """The smoke run's value intervals (3 calibration policies: too few for level 0.9, so
    unbounded, flagged, JSON-valid) and both guards side by side."""
    assert "[paper] trust: " in printed and "Infinity" not in json.dumps(r)
    assert r["trust_calibration"]["n"] == 3 and len(r["trust_calibration"]["true_value"]) == 3
    for m in ("rl2s", "gail", "bc", "rl2s-bc"):
        b = r["trust"][m]
        assert b["runs"] == 2 and b["level"] == 0.9 and b["command"] == r["command"]
        assert b["unbounded_runs"] == 2 and b["coverage"] == 1.0 and b["width_over_range"] is None
        for s in (1, 2):
            t = r["lanes"][f"{m}/{s}"]["trust"]
            assert t["q_infinite"] and len(t["interval"]) == n_test and all(t["unbounded"])
    g = r["guard"]
    assert g["chosen"] == "floor" and g["calibration"]["n"] == 3
    for kind in ("floor", "interval"):
        assert set(g[kind]) == {"rl2s", "gail", "bc", "rl2s-bc"}
        for b in g[kind].values():
            assert {"median_gain", "mpi", "deployed", "deployed_losses",
                    "control_median_gain"} <= set(b) and b["lanes_x_policies"] == 2
    for e in r["improvement"].values():
        assert len(e["guard_accepted_interval"]) == 2


@pytest.mark.slow
@pytest.mark.heavy
def test_paper_smoke_hopper(tmp_path, capsys):
    """The whole protocol at toy sizes: 2 seeds (1 and 2: --first-seed) x 4 methods as two
    vmapped programs, curves, final evaluation, SAC improvement of 2 test policies. ~5-10 min
    on 2 busy CPU cores (mostly MJX and XLA compiles)."""
    paper = _load("paper")
    out = tmp_path / "paper"
    args = ["--task", "hopper", "--profile", "cpu", "--seeds", "2", "--first-seed", "1",
            "--steps", "4",
            "--eval-every", "2", "--eval-episodes", "2", "--transitions-per-policy", "200",
            "--value-episodes", "2", "--episode-length", "50", "--improve-policies", "2",
            "--improve-iterations", "2", "--out", str(out), "--check-eval",
            "--guard-margin", "0", "--guard-snapshots", "--sac-chunk", "1",
            "--guard-floor-scale", "0.5", "--trust-calibration", "3", "--trust-episodes", "2",
            "--guard-calibration", _validation_run(tmp_path)]
    assert paper.main(args) == 0
    printed = capsys.readouterr().out
    for phase in ("data", "oracle", "train_adversarial", "train_mle", "improve_sac",
                  "improve_measure"):
        assert f"[paper] {phase}: " in printed
    r = json.loads((out / "hopper.json").read_text())
    from rl2s_jax.zoo.zoo import load_zoo
    zoo = load_zoo("hopper")  # the split's sizes come from the shipped zoo
    n_train, n_test = len(zoo.train_ids), len(zoo.test_ids)
    assert r["complete"] and r["seeds"] == 2 and r["hardware"] == "cpu"
    _check_trust(r, printed, n_test)
    assert r["machine"]["backend"] == "cpu" and "cpu_isa" in r["machine"]
    assert r["seed_ids"] == [1, 2]
    assert r["data_seed"] == 0 and len(r["true_value_se"]) == n_test  # issue 66's analysis
    assert r["command"].startswith("python experiments/paper.py --task hopper")
    assert set(r["methods"]) == {"rl2s", "gail", "bc", "rl2s-bc", "oracle"}
    assert len(r["zoo_sha256"]) == 64
    # the control: per seed, same protocol, with intervals that contain its own estimate
    orc = r["per_seed"]["oracle"]
    assert len(orc["kendall_tau"]) == 2 and orc["mpi"] == []
    nc = r["noise_ceiling"]   # what evaluation noise alone lets an exact simulator reach
    assert nc["n_truth"] == 2 and nc["n_sim"] == 2
    assert -1.0 <= nc["kendall_tau"]["lo"] <= nc["kendall_tau"]["mean"] <= 1.0
    for m in ("oracle", "rl2s"):
        # AVD averages |sim - true|: resampling episodes adds noise that |.| turns into a
        # rise (E|X| >= |E X|), so where the errors are mostly noise (the oracle) the whole
        # interval may lie above the estimate (found on an AVX-512 CPU); its upper end holds it
        iv = r["intervals"][m]["avd"]
        assert iv["lo"] <= iv["hi"] and r["methods"][m]["avd"] <= iv["hi"] + 1e-6, (m, iv)
    for m, vals in ((m, r["methods"][m]) for m in ("rl2s", "gail", "bc", "rl2s-bc")):
        assert set(vals) == set(METRICS) | {"mpi_paired", "api_paired"}, m  # C0 re-measured
        per = r["per_seed"][m]
        for k in METRICS:
            # improvement on the first seed only
            n = 1 if k in ("mpi", "api", "mpi_paired", "api_paired") else 2
            assert len(per[k]) == n and all(np.isfinite(per[k])), (m, k)
            assert vals[k] == pytest.approx(np.mean(per[k]))
            assert (r["std"][m][k] is None) == (n == 1)
        # the seeds are different runs
        assert per["avd"][0] != per["avd"][1], m
        assert vals["mvd"] >= vals["avd"] >= 0 and vals["mpi"] <= vals["api"]
    # gail/bc lanes ran with eps 1, rl2s/rl2s-bc with 0.25, in one program per family
    assert {k: v["eps"] for k, v in r["lanes"].items()} == {
        "rl2s/1": 0.25, "rl2s/2": 0.25, "gail/1": 1.0, "gail/2": 1.0,
        "rl2s-bc/1": 0.25, "rl2s-bc/2": 0.25, "bc/1": 1.0, "bc/2": 1.0}
    assert r["train_config"]["adversarial"]["method"] == "rl2s"
    assert r["train_config"]["mle"]["method"] == "rl2s-bc"
    # lengths beside values: the simulated episodes of every lane and the oracle (at most the
    # 50-step horizon) against the logged episodes' mean length
    assert len(r["true_length"]) == n_test and all(1 <= x <= 50 for x in r["true_length"])
    assert len(r["oracle_sim_length"]) == 2
    for lengths in [v["sim_length"] for v in r["lanes"].values()] + r["oracle_sim_length"]:
        assert len(lengths) == n_test and all(1 <= x <= 50 for x in lengths)
    # curves: every lane at every --eval-every steps; the final metrics are the last point
    steps = {}
    for row in r["curves"]:
        steps.setdefault(row["lane"], []).append(row["step"])
        assert {"step", "lane", "avd", "mvd", "tau"} <= set(row)
    assert steps == {lane: [2, 4] for lane in r["lanes"]}
    # the training policies' simulated values at the last point (held-out starts) beside their
    # true values: their mean |difference| is that point's selection AVD
    for lane, v in r["lanes"].items():
        err = np.abs(np.subtract(v["train_sim_value"], r["train_true_value"]))
        row = [row for row in r["curves"] if row["lane"] == lane and row["step"] == 4][0]
        assert row["select_avd"] == pytest.approx(err.mean(), rel=1e-5), lane
    last = [row for row in r["curves"] if row["lane"] == "rl2s/2" and row["step"] == 4][0]
    assert last["tau"] == r["per_seed"]["rl2s"]["kendall_tau"][1]
    # model selection: per lane the step with the best TRAINING-policy tau (held-out episode
    # starts; ties to the lower training AVD), reported with the test metrics of that step
    for lane in r["lanes"]:
        meth, seed = lane.split("/")
        rows = [row for row in r["curves"] if row["lane"] == lane]
        ok = [row for row in rows if row["select_tau"] is not None and row["tau"] is not None]
        chosen = r["selected"][meth]["step"][int(seed) - 1]
        if not ok:
            assert chosen is None
            continue
        best = max(ok, key=lambda row: (row["select_tau"], -row["select_avd"]))
        assert chosen == best["step"], lane
        assert r["selected"][meth]["kendall_tau"][int(seed) - 1] == best["tau"], lane
    assert set(r["methods_selected"]) == {"rl2s", "gail", "bc", "rl2s-bc"}
    # the vmapped evaluation is assess.evaluate_simulator's
    for check in r["eval_check"].values():
        assert check["max_abs_diff"] < 1e-3
    assert r["eval_check"]["adversarial"]["metrics"]["kendall_tau"] == pytest.approx(
        r["per_seed"]["rl2s"]["kendall_tau"][0], abs=1e-6)
    # improvement: 2 test policies, one per end of the true-return range
    imp = r["improvement"]
    assert set(imp) == {"rl2s/1", "gail/1", "bc/1", "rl2s-bc/1"}  # the first seed
    for v in imp.values():
        c0, c1 = np.asarray(v["c0"]), np.asarray(v["c1"])
        assert len(v["policy_ids"]) == 2
        np.testing.assert_allclose(v["I"], (c1 - c0) / np.abs(c0), rtol=1e-6)
        assert v["mpi"] == pytest.approx(min(v["I"])) and v["api"] == pytest.approx(
            np.mean(v["I"]))
        # paired: C0 re-measured on C1's episodes, the same for every lane
        cp = np.asarray(v["c0_paired"])
        np.testing.assert_allclose(v["I_paired"], (c1 - cp) / np.abs(cp), rtol=1e-6)
        assert v["mpi_paired"] == pytest.approx(min(v["I_paired"]))
        assert v["c0_paired"] == imp["rl2s/1"]["c0_paired"] and len(v["diff_se"]) == 2
    assert r["sizes"]["test_policies"] == n_test and r["sizes"]["train_policies"] == n_train
    for key in ("data", "train_adversarial", "train_mle", "improve_sac", "total"):
        assert r["timings"][key] >= 0
    c0 = imp["rl2s/1"]["c0"]
    assert c0 == [r["true_value_undiscounted"][i] for i in imp["rl2s/1"]["policy_ids"]]
    assert min(c0) == pytest.approx(min(r["true_value_undiscounted"]))
    # the deployment guard: deployed I is the lane's I where the simulator kept the fine-tuned
    # policy, else 0; its MPI / API are the ablation entry "full+guard"
    for v in imp.values():
        assert v["I_deployed"] == pytest.approx(np.where(v["guard_accepted"], v["I"], 0.0))
        assert v["mpi_deployed"] == pytest.approx(min(v["I_deployed"]))
    assert set(r["ablation"]["full+guard"]["methods"]) == {"rl2s", "gail", "bc", "rl2s-bc"}
    # the guard's floor: --guard-floor-scale (0.5) x each lane's training MVD, both recorded
    for v in imp.values():
        assert np.isfinite(v["guard_training_mvd"]) and v["guard_training_mvd"] > 0
        assert v["guard_floor"] == pytest.approx(0.5 * v["guard_training_mvd"])
    settings = r["ablation"]["full+guard"]["settings"]
    assert settings["guard_floor"] == "training MVD per lane"
    assert settings["guard_floor_scale"] == 0.5
    # recorded beside it, unused: the range floor (the spread of the lane's signed training
    # errors at the guard's horizon: 50 steps here) and its verdict on the same members' values
    for lane, v in imp.items():
        e = np.subtract(r["lanes"][lane]["train_sim_value"], r["train_true_value"])
        assert v["guard_floor_range"] == pytest.approx(e.max() - e.min(), rel=1e-6), lane
        gain = np.asarray(v["guard_member_gain"])  # --guard-margin 0: the floor alone
        assert v["guard_accepted_range"] == (gain > v["guard_floor_range"]).all(axis=0).tolist()
        # the members' start values are kept beside their gains: the guard's verdict re-reads
        start = np.asarray(v["guard_member_start"])
        assert start.shape == gain.shape and v["guard_accepted"] == deployment_guard(
            start, start + gain, 0.0, v["guard_floor"]).tolist()
    # the guard over snapshots (after iterations 1 and 2): a kept start has I = 0; a final
    # snapshot the guard accepts is eligible, so some snapshot deploys; the final one chosen
    # earns the final policy's return (the same episodes)
    for v in imp.values():
        idx = np.asarray(v["guard_snapshot"])
        assert set(idx) <= {0, 1, 2} and np.all(idx[np.asarray(v["guard_accepted"])] > 0)
        np.testing.assert_allclose(np.asarray(v["I_snapshot"])[idx == 0], 0.0)
        np.testing.assert_allclose(np.asarray(v["I_snapshot"])[idx == 2],
                                   np.asarray(v["I"])[idx == 2], rtol=1e-3, atol=1e-6)
        assert v["mpi_snapshot"] == pytest.approx(min(v["I_snapshot"]))
    assert set(r["ablation"]["full+guard-snapshots"]["methods"]) == {
        "rl2s", "gail", "bc", "rl2s-bc"}
    assert r["ablation"]["full+guard-snapshots"]["settings"]["snapshot_every"] == 1
    assert max(c0) == pytest.approx(max(r["true_value_undiscounted"]))
    # the data is reused when the sizes match (no collection)
    ds, reused = paper.load_or_collect("hopper", r["sizes"], str(out), 0, 50, False)
    assert reused and ds["test"].n_policies == n_test and ds["train"].n_policies == n_train
    # --policy-split validation: the same data, its training policies split again, with their
    # values and transitions; the test policies are not in it
    val, reused = paper.load_or_collect("hopper", r["sizes"], str(out), 0, 50, False,
                                        "validation")
    ids = list(ds["train"].meta["source"]["zoo_ids"])
    for split, name in (("train", "fit"), ("test", "validation")):
        want = zoo.split_ids(name)
        assert reused and val[split].meta["source"]["zoo_ids"] == want
        np.testing.assert_array_equal(val[split].value,
                                      np.asarray(ds["train"].value)[[ids.index(i) for i in want]])
    assert val["train"].n_transitions + val["test"].n_transitions == ds["train"].n_transitions
    with pytest.raises(ValueError, match="policy_split: expected"):
        paper.load_or_collect("hopper", r["sizes"], str(out), 0, 50, False, "tests")


def test_noise_ceiling_script_reads_the_oracle_seeds(tmp_path, capsys):
    """experiments/noise_ceiling.py: the oracle's tau per seed and seed against seed, the
    per-episode sd from the spread over seeds (sd x sqrt(episodes)), and a clear error when the
    result has no oracle or a single seed."""
    nc = _load("noise_ceiling")
    truth = [0.0, 1.0, 2.0, 3.0]
    sims = [[0.0, 1.1, 2.0, 2.9], [0.2, 0.9, 3.2, 3.0], [0.1, 1.0, 2.1, 3.3]]
    res = {"task": "ant", "true_value": truth, "oracle_sim_value": sims,
           "sizes": {"eval_episodes": 16, "value_episodes": 8}}
    a = nc.analyse(res, episodes=(4, 4096), target=0.99, n_rep=200)
    assert a["oracle_tau_per_seed"] == [1.0, pytest.approx(2 / 3), 1.0]
    assert a["oracle_tau_seed_vs_seed"] == [pytest.approx(2 / 3), 1.0, pytest.approx(2 / 3)]
    assert a["episode_sd"] == pytest.approx(np.std(sims, axis=0, ddof=1) * 4.0)
    assert a["n_truth_episodes"] == 8 and a["episodes_for_target"] == 4096
    path = tmp_path / "ant.json"
    path.write_text(json.dumps(res))
    assert nc.main([str(path), "--episodes", "4,4096", "--n-rep", "50", "--pairs", "2:3",
                    "--json", str(tmp_path / "nc.json")]) == 0
    assert json.loads((tmp_path / "nc.json").read_text())["n_truth_episodes"] == 8
    out = capsys.readouterr().out
    assert "oracle seed vs oracle seed" in out and "truth:simulator 2:3 episodes" in out
    with pytest.raises(SystemExit, match="pairs"):
        nc.main([str(path), "--pairs", "16-32"])
    with pytest.raises(SystemExit, match="oracle_sim_value"):
        nc.analyse({**res, "oracle_sim_value": sims[:1]})
    with pytest.raises(SystemExit, match="oracle row"):
        nc.analyse({"true_value": truth})


# ------------------------------------------------------------------ make paper's driver


def _run_paper_all(tmp_path, n_gpu: int, fail: str = "", tasks: str = "hopper walker2d "
                   "halfcheetah ant", args: tuple = (), env_extra: dict | None = None):
    """experiments/paper_all.sh with a stub nvidia-smi (n_gpu GPUs) and a stub python: paper.py
    logs its start (task, family or 'both', CUDA_VISIBLE_DEVICES, args), prints its data line
    after 0.2 s (the event logged first, so that no unit it releases can log its start before
    it) and ends 1 s later (time for a loaded CI machine to start the released unit); the
    unit ``fail`` ("task/family") fails at once, before
    its data line; merge_results.py and paper_tables.py log their calls.
    -> (rc, [event lines], process)"""
    import subprocess
    import textwrap
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    bin_dir, events = tmp_path / "bin", tmp_path / "events"
    bin_dir.mkdir(parents=True)
    smi = bin_dir / "nvidia-smi"
    smi.write_text("#!/usr/bin/env bash\n" + "".join(f"echo 'GPU {g}: stub'\n"
                                                      for g in range(n_gpu)))
    py = bin_dir / "stubpy"
    py.write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        [ "$1" = experiments/paper_tables.py ] && {{ echo tables >> {events}; exit 0; }}
        [ "$1" = experiments/merge_results.py ] && {{ echo "merge $*" >> {events}; exit 0; }}
        task=; fam=both; prev=
        for a in "$@"; do
          case $prev in --task) task=$a ;; --families) fam=$a ;; esac
          prev=$a
        done
        gpu=gpu=${{CUDA_VISIBLE_DEVICES:-none}}
        echo "start $task $fam $gpu mem=${{XLA_PYTHON_CLIENT_MEM_FRACTION:-none}} $*" >> {events}
        [ "$task/$fam" = "{fail}" ] && {{ echo "end $task $fam $gpu" >> {events}; exit 3; }}
        sleep 0.2
        echo "data $task $fam $gpu" >> {events}  # before the line the driver waits for
        echo "[paper] data: 0.2s"
        sleep 1
        echo "end $task $fam $gpu" >> {events}
        """))
    for f in (smi, py):
        f.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "PY": str(py),
           "TASKS": tasks}
    env.pop("RL2S_GPUS", None)
    env.pop("CUDA_VISIBLE_DEVICES", None)
    env.update(env_extra or {})
    proc = subprocess.run(["bash", "experiments/paper_all.sh", str(tmp_path / "out"), *args],
                          cwd=root, env=env, capture_output=True, text=True, timeout=30)
    ev = events.read_text().split("\n")[:-1] if events.exists() else []
    return proc.returncode, ev, proc


def _check_one_process_per_gpu(ev):
    """-> {(task, family): gpu} of the paper.py runs in the events; fails when a GPU ran two
    at once or a unit ran twice."""
    running, ran = {}, {}
    for e in ev:
        what, task, fam, gpu = (e.split() + [""] * 4)[:4]
        if what == "start":
            assert gpu not in running.values(), f"two processes on {gpu}: {ev}"
            assert (task, fam) not in ran, f"{task} {fam} ran twice: {ev}"
            running[(task, fam)] = ran[(task, fam)] = gpu
        elif what == "end":
            assert running.pop((task, fam)) == gpu
    assert not running
    return ran


TASKS4 = ("hopper", "walker2d", "halfcheetah", "ant")


def test_paper_all_spreads_task_family_units_over_the_gpus(tmp_path):
    """make paper's driver with 2 GPUs: every (task, family) runs exactly once, never two
    processes on one GPU, both GPUs busy at once, the costliest units first; a task's second
    unit starts only after its first unit's data phase (not its end), without the oracle and
    the control; each task is merged from its units (the collecting one first), then the
    tables; the wall time per unit is printed and in OUT/schedule.json."""
    out = tmp_path / "a" / "out"
    rc, ev, proc = _run_paper_all(tmp_path / "a", 2, args=("--seeds", "2", "--control"))
    assert rc == 0, proc.stderr
    ran = _check_one_process_per_gpu(ev)
    assert ran.keys() == {(t, f) for t in TASKS4 for f in ("adversarial", "mle")}
    assert set(ran.values()) == {"gpu=0", "gpu=1"}
    first_end = next(i for i, e in enumerate(ev) if e.startswith("end"))
    assert [e.split()[0] for e in ev[:first_end]].count("start") == 2  # both GPUs busy
    order = [line.split()[1:5] for line in proc.stdout.splitlines()
             if line.startswith("[paper_all] ") and " on GPU " in line]
    assert order[:2] == [["ant/adversarial", "on", "GPU", "0"],  # the costliest first
                         ["halfcheetah/adversarial", "on", "GPU", "1"]]
    starts = {tuple(e.split()[1:3]): e for e in ev if e.startswith("start")}
    for t in TASKS4:
        adv, mle = starts[(t, "adversarial")], starts[(t, "mle")]
        assert ev.index(f"data {t} adversarial {ran[(t, 'adversarial')]}") < ev.index(mle)
        assert f"--out {out}/units/{t}_adversarial " in adv and "--data-dir" in adv
        assert "--control" in adv and "--no-oracle" not in adv and "--seeds 2" in adv
        assert "--control" not in mle and "--no-oracle" in mle and "--seeds 2" in mle
        assert (f"merge experiments/merge_results.py --task {t} --paper {out}/units/"
                f"{t}_adversarial/{t}.json --paper {out}/units/{t}_mle/{t}.json --out {out}"
                in ev)
    for t in TASKS4:  # each task merged once its own units ended (beside the others' units)
        merged = next(i for i, e in enumerate(ev)
                      if e.startswith(f"merge experiments/merge_results.py --task {t} "))
        assert all(ev.index(f"end {t} {f} {ran[(t, f)]}") < merged
                   for f in ("adversarial", "mle"))
    first_merge = min(i for i, e in enumerate(ev) if e.startswith("merge"))
    last_end = max(i for i, e in enumerate(ev) if e.startswith("end"))
    assert first_merge < last_end  # a merge ran while other units were still running
    assert ev[-1] == "tables"
    sched = json.loads((out / "schedule.json").read_text())
    assert sched["gpus"] == 2 and len(sched["units"]) == 8 and len(sched["merges"]) == 4
    for u in sched["units"]:
        assert u["rc"] == 0 and f"gpu={u['gpu']}" == ran[(u["task"], u["family"])]
        assert u["wall_s"] >= 0.4 and u["data_s"] is not None
        assert f"{u['task']:<12} {u['family']:<12}" in proc.stdout
    assert sched["busy_s"].keys() == {"0", "1"} and sum(sched["busy_s"].values()) >= 3.6
    assert sched["total_s"] >= max(u["start_s"] + u["wall_s"] for u in sched["units"])
    assert "wall time per part, 2 GPU(s)" in proc.stdout and "in all: " in proc.stdout
    assert "[paper] data: " in (out / "paper_ant_mle.log").read_text()
    # one task on 2 GPUs: its second unit waits for the first's data line, not its end
    rc, ev, proc = _run_paper_all(tmp_path / "b", 2, tasks="hopper")
    assert rc == 0, proc.stderr
    _check_one_process_per_gpu(ev)
    mle = next(e for e in ev if e.startswith("start hopper mle"))
    assert (ev.index("data hopper adversarial gpu=0") < ev.index(mle)
            < ev.index("end hopper adversarial gpu=0"))
    assert "gpu=1" in mle


def test_paper_all_whole_task_units(tmp_path):
    """PAPER_UNITS=task: with 2 GPUs each task is one paper.py (both families, its data, its
    OUT/<task>.json), the costliest tasks first, one process per GPU, nothing to merge; an
    unknown --units value is refused by name before anything runs."""
    rc, ev, proc = _run_paper_all(tmp_path / "a", 2, env_extra={"PAPER_UNITS": "task"})
    assert rc == 0, proc.stderr
    ran = _check_one_process_per_gpu(ev)
    assert ran.keys() == {(t, "both") for t in TASKS4}
    assert set(ran.values()) == {"gpu=0", "gpu=1"}
    order = [line.split()[1] for line in proc.stdout.splitlines()
             if line.startswith("[paper_all] ") and " on GPU " in line]
    assert order[:2] == ["ant/all", "halfcheetah/all"]  # the costliest first
    assert not any(e.startswith("merge") for e in ev) and ev[-1] == "tables"
    out = tmp_path / "a" / "out"
    assert all(f"--out {out} " in e for e in ev if e.startswith("start"))
    sched = json.loads((out / "schedule.json").read_text())
    assert [u["family"] for u in sched["units"]] == [None] * 4 and sched["merges"] == []
    rc, ev, proc = _run_paper_all(tmp_path / "b", 2, env_extra={"PAPER_UNITS": "seed"})
    assert rc != 0 and "units: expected auto, family or task, got 'seed'" in proc.stderr
    assert not any(e.startswith("start") for e in ev)
    # run pinned to GPUs 5 and 7 (device.sh streams "@5,7 "): the units use those two
    rc, ev, proc = _run_paper_all(tmp_path / "c", 2, env_extra={
        "PAPER_UNITS": "task", "CUDA_VISIBLE_DEVICES": "5,7", "RL2S_GPUS": "2"})
    assert rc == 0, proc.stderr
    assert set(_check_one_process_per_gpu(ev).values()) == {"gpu=5", "gpu=7"}
    rc, ev, proc = _run_paper_all(tmp_path / "d", 2, env_extra={
        "PAPER_UNITS": "task", "CUDA_VISIBLE_DEVICES": "5", "RL2S_GPUS": "2"})
    assert rc != 0 and "gpus: 2 GPUs to schedule over, but CUDA_VISIBLE_DEVICES lists 1 (5)" \
        in proc.stderr and not any(e.startswith("start") for e in ev)


def test_paper_all_per_gpu_runs_k_processes_on_one_gpu(tmp_path):
    """On one GPU by default (PAPER_PER_GPU=auto) two processes at once: whole tasks,
    costliest first, two at a time (never three), each with half the memory fraction; every
    task once. PAPER_PER_GPU=1: one at a time, no fraction; a bad value refused."""
    rc, ev, proc = _run_paper_all(tmp_path / "a", 1)
    assert rc == 0, proc.stderr
    starts = [e.split() for e in ev if e.startswith("start")]
    assert {s[1] for s in starts[:2]} == {"ant", "halfcheetah"}  # costliest two, side by side
    assert sorted(s[1] for s in starts) == sorted(TASKS4)
    assert {s[2] for s in starts} == {"both"} and {s[3] for s in starts} == {"gpu=0"}
    assert {s[4] for s in starts} == {"mem=0.450"}
    running, most = 0, 0
    for e in ev:
        running += e.startswith("start") - e.startswith("end")
        most = max(most, running)
    assert most == 2 and running == 0
    assert json.loads((tmp_path / "a" / "out" / "schedule.json").read_text())["per_gpu"] == 2
    rc, ev, proc = _run_paper_all(tmp_path / "b", 1, env_extra={"PAPER_PER_GPU": "1"})
    assert rc == 0 and {e.split()[4] for e in ev if e.startswith("start")} == {"mem=none"}
    for bad in ("0", "two"):
        rc, ev, proc = _run_paper_all(tmp_path / f"c{bad}", 1,
                                      env_extra={"PAPER_PER_GPU": bad})
        assert rc != 0 and ("per-gpu: expected auto or a whole number >= 1, got "
                            f"'{bad}'") in proc.stderr and not ev


def test_paper_schedule_per_gpu_auto():
    """--per-gpu auto: two processes only on one GPU with two tasks or more (the measured
    case); one task, no GPU or several GPUs: one; a number is kept as given."""
    count = _load("paper_schedule").per_gpu_count
    assert count("auto", 1, 4) == count("auto", 1, 2) == 2
    assert count("auto", 1, 1) == count("auto", 0, 4) == count("auto", 2, 4) == 1
    assert count("3", 2, 4) == 3 and count(1, 1, 4) == 1


def test_paper_schedule_auto_units():
    """units="auto": whole tasks when tasks <= GPUs < 2 x tasks (4 GPUs, 4 tasks: one task per
    GPU, as measured), (task, family) pairs with fewer GPUs than tasks or twice as many."""
    sched = _load("paper_schedule")
    fams = lambda tasks, n: {u["family"] for u in sched.plan(list(tasks), n, [], "o")}
    assert fams(TASKS4, 4) == fams(TASKS4, 7) == {None}
    assert fams(TASKS4, 2) == fams(TASKS4, 3) == fams(TASKS4, 8) == {"adversarial", "mle"}
    assert fams(("hopper",), 2) == {"adversarial", "mle"} and fams(("hopper",), 1) == {None}
    assert [u["task"] for u in sched.plan(list(TASKS4), 4, [], "o")][0] == "ant"  # costliest


def test_paper_all_failures_and_the_paths_without_units(tmp_path):
    """A unit failing before its data line: the task's other unit then runs after it (it
    collects the data itself, never beside it, with the oracle and the control that went
    with the data), every other unit runs, that task is not
    merged, no tables, exit 1 naming the unit and its log. RL2S_GPUS overrides nvidia-smi.
    With one GPU (PAPER_PER_GPU=1) or none: one paper.py per task (both families), one after
    another, a failed task after the others, no merge."""
    rc, ev, proc = _run_paper_all(tmp_path / "a", 4, fail="walker2d/adversarial",
                                  env_extra={"RL2S_GPUS": "2"}, args=("--control",))
    out = tmp_path / "a" / "out"
    assert rc == 1 and "tables" not in ev
    ran = _check_one_process_per_gpu(ev)
    assert len(ran) == 8 and set(ran.values()) == {"gpu=0", "gpu=1"}
    heir = next(e for e in ev if e.startswith("start walker2d mle"))
    assert (ev.index(f"end walker2d adversarial {ran[('walker2d', 'adversarial')]}")
            < ev.index(heir))
    # it collects in the failed unit's place, so the oracle and the control go with it
    assert "--no-oracle" not in heir and "--control" in heir
    assert "--no-oracle" in next(e for e in ev if e.startswith("start hopper mle"))
    assert sorted(e.split()[3] for e in ev if e.startswith("merge")) == [
        "ant", "halfcheetah", "hopper"]
    assert (f"FAILED walker2d/adversarial (exit 3, log {out}/paper_walker2d_adversarial.log)"
            in proc.stderr)
    assert "FAILED" not in proc.stderr.replace("FAILED walker2d/adversarial", "")
    sched = json.loads((out / "schedule.json").read_text())
    assert [u["rc"] for u in sched["units"]].count(3) == 1
    rc, ev, proc = _run_paper_all(tmp_path / "b", 1, fail="walker2d/both",
                                  env_extra={"PAPER_PER_GPU": "1"})
    assert rc == 1 and "tables" not in ev and not any(e.startswith("merge") for e in ev)
    assert [e.split()[:4] for e in ev if e.startswith(("start", "end"))] == [
        [w, t, "both", "gpu=0"] for t in TASKS4 for w in ("start", "end")]
    assert "FAILED walker2d/all families" in proc.stderr and "paper_walker2d.log" in proc.stderr
    rc, ev, proc = _run_paper_all(tmp_path / "c", 0, fail="ant/both")  # no GPU
    assert rc == 1 and "tables" not in ev and not any(e.startswith("merge") for e in ev)
    assert [e.split()[:4] for e in ev if e.startswith(("start", "end"))] == [
        [w, t, "both", "gpu=none"] for t in TASKS4 for w in ("start", "end")]
    assert "[paper] data: " in proc.stdout  # shown as it runs, and logged
    assert "[paper] data: " in (tmp_path / "c" / "out" / "paper_hopper.log").read_text()
    rc, ev, proc = _run_paper_all(tmp_path / "d", 0, tasks="hopper")
    assert rc == 0 and ev[-1] == "tables"
    assert json.loads((tmp_path / "d" / "out" / "schedule.json").read_text())["units"][0][
        "family"] is None


def _run_device_jobs(tmp_path, *specs, fail_name="", limit=30):
    """`experiments/device.sh jobs` with stub nvidia-smi / python3 (pip a no-op; paper.py logs
    its start, prints its data phase after 0.5 s, ends 3 s later). -> (rc, [events], out)"""
    import subprocess
    import textwrap
    bin_dir, events, out = tmp_path / "bin", tmp_path / "events", tmp_path / "out"
    bin_dir.mkdir(parents=True)
    (bin_dir / "nvidia-smi").write_text("#!/usr/bin/env bash\necho '0, stub, 1 MiB'\n")
    (bin_dir / "python3").write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        [ "$1" = -m ] && exit 0
        prev=; for a in "$@"; do [ "$prev" = --out ] && name=$(basename "$a"); prev=$a; done
        echo "start $name gpu=$CUDA_VISIBLE_DEVICES args=$*" >> {events}
        sleep 0.5
        echo "[paper] data: 0.5s"
        echo "data $name" >> {events}
        sleep 3
        echo "end $name" >> {events}
        [ "$name" != "{fail_name}" ]
        """))
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "OUT": str(out),
           "LIMIT": str(limit), "RL2S_SITE": str(tmp_path / "site")}
    proc = subprocess.run(["bash", "experiments/device.sh", "jobs", *specs], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=60)
    ev = events.read_text().split("\n")[:-1] if events.exists() else []
    return proc.returncode, ev, proc


def test_device_tasks_gives_two_processes_on_one_gpu_more_time(tmp_path):
    """device.sh tasks: each paper.py is cut at 560 s alone, at 450 s x k where k share one
    GPU (paper_schedule.per_gpu_count's rule: auto is 2 on one GPU with two tasks; each then
    takes ~1.55x as long); LIMIT overrides; a bad PAPER_PER_GPU is refused."""
    import subprocess
    import textwrap

    bin_dir, events = tmp_path / "bin", tmp_path / "events"
    bin_dir.mkdir()
    (bin_dir / "python3").write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        [ "$1" = -c ] && exec {sys.executable} "$@"  # the per-GPU rule: paper_schedule's
        [ "$1" = experiments/paper_schedule.py ] && echo "$*" >> {events}
        exit 0
        """))
    (bin_dir / "python3").chmod(0o755)

    def py_of(tasks, **env):
        events.unlink(missing_ok=True)
        proc = subprocess.run(["bash", "experiments/device.sh", "tasks", tasks], cwd=ROOT,
                              env={**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}",
                                   "OUT": str(tmp_path / "out"), "RL2S_SITE": str(tmp_path),
                                   "RL2S_WORK": str(tmp_path / "w"), **env},
                              capture_output=True, text=True, timeout=60)
        (tmp_path / ".rl2s_wheels").touch()
        assert events.exists(), proc.stderr
        return events.read_text().split("--py ")[1].split(" --tasks")[0]

    (tmp_path / ".rl2s_wheels").touch()
    assert py_of("hopper,walker2d", RL2S_GPUS="1") == "timeout 900 python3"
    assert py_of("hopper", RL2S_GPUS="1") == "timeout 560 python3"
    assert py_of("hopper,walker2d", RL2S_GPUS="2") == "timeout 560 python3"
    assert py_of("hopper,walker2d", RL2S_GPUS="1", PAPER_PER_GPU="1") == "timeout 560 python3"
    assert py_of("hopper,walker2d", RL2S_GPUS="1", LIMIT="700") == "timeout 700 python3"
    # paper_schedule's own rule, not a copy: k processes per GPU as asked, wherever
    assert py_of("hopper,walker2d", RL2S_GPUS="2", PAPER_PER_GPU="2") == "timeout 900 python3"
    assert py_of("hopper,walker2d,ant", RL2S_GPUS="1", PAPER_PER_GPU="3") == \
        "timeout 1350 python3"
    proc = subprocess.run(["bash", "experiments/device.sh", "tasks", "hopper"], cwd=ROOT,
                          env={**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}",
                               "OUT": str(tmp_path / "out"), "RL2S_SITE": str(tmp_path),
                               "RL2S_GPUS": "1", "PAPER_PER_GPU": "0"},
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "per-gpu: expected auto or a whole number" in proc.stderr


def test_device_jobs_runs_side_by_side_and_waits_for_the_data(tmp_path):
    """device.sh jobs: jobs without AFTER start at once on their GPUs; a job with AFTER starts
    only once that job's data phase has ended; out/data dirs and args reach paper.py; a failed
    job fails the script after the others; a bad spec stops it before any job starts."""
    rc, ev, proc = _run_device_jobs(
        tmp_path / "a", "0 hop - --task hopper --families adversarial",
        "1 walk - --task walker2d", "2 hop_more hop --task hopper --first-seed 3")
    assert rc == 0, proc.stderr
    starts = {e.split()[1]: e for e in ev if e.startswith("start")}
    assert "gpu=0" in starts["hop"] and "gpu=2" in starts["hop_more"]
    assert "--data-dir /tmp/work" in starts["hop"] and "--first-seed 3" in starts["hop_more"]
    # waits for the data line, not the end (the log is written line by line)
    assert ev.index("data hop") < ev.index(starts["hop_more"]) < ev.index("end hop")
    assert ev.index(starts["walk"]) < ev.index("data hop")  # not waiting on anyone
    assert "ended with 0" in (tmp_path / "a" / "out" / "hop_more" / "paper.log").read_text()
    rc, ev, proc = _run_device_jobs(tmp_path / "b", "0 hop - --task hopper",
                                    "1 walk - --task walker2d", fail_name="hop")
    assert rc == 1 and "hop FAILED" in proc.stdout and "end walk" in ev
    for bad in ("x hop - --task hopper", "0 hop", "0 hop nobody --task hopper"):
        rc, ev, proc = _run_device_jobs(tmp_path / bad.replace(" ", "_"), bad)
        assert rc == 2 and "job spec" in proc.stderr and ev == [], bad


def test_device_waitdata_waits_for_the_data_key_file(tmp_path):
    """device.sh waitdata TASK MAX_S: returns 0 once $W/<TASK>_data.json (written last by
    load_or_collect) appears, not before; 1 when MAX_S passes without it."""
    import subprocess
    import time
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "python3").write_text("#!/usr/bin/env bash\n[ \"$1\" = -m ] && exit 0\n")
    (bin_dir / "python3").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "OUT": str(tmp_path / "o"),
           "RL2S_SITE": str(tmp_path / "site")}
    task = f"waitdata_test_{os.getpid()}"
    key = os.path.join("/tmp/work", f"{task}_data.json")  # device.sh's W
    cmd = ["bash", "experiments/device.sh", "waitdata", task]
    try:
        proc = subprocess.run([*cmd, "1"], cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode == 1 and "no /tmp/work/" in proc.stderr
        t0 = time.monotonic()
        waiter = subprocess.Popen([*cmd, "60"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                  text=True)
        time.sleep(3)
        assert waiter.poll() is None  # still waiting
        with open(key, "w") as f:
            f.write("{}")
        out, _ = waiter.communicate(timeout=60)
        assert waiter.returncode == 0 and f"waitdata: {task}'s data" in out
        assert time.monotonic() - t0 >= 3
    finally:
        if os.path.exists(key):
            os.remove(key)


def test_device_streams_pin_gpu_sets_and_set_a_runs_environment(tmp_path):
    """device.sh's stream driver (what `streams` runs detached): "@1,2 " pins a stream to GPUs
    1 and 2 (CUDA_VISIBLE_DEVICES, RL2S_GPUS their count), "@0 " to GPU 0; each stream's
    memory fraction is 0.9 over the most streams sharing one of its GPUs; leading NAME=VALUE
    words are the run's environment (RL2S_WORK: its data dir W) and shown in the progress;
    runs of one stream go one after another, each with its own OUT."""
    import subprocess
    import sys
    import textwrap
    bin_dir, events = tmp_path / "bin", tmp_path / "events"
    bin_dir.mkdir()
    (bin_dir / "nvidia-smi").write_text("#!/usr/bin/env bash\necho 'stub, 1 MiB'\n")
    (bin_dir / "python3").write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        [ "$1" = -m ] && exit 0
        [ "$1" = -c ] && exec {sys.executable} "$@"
        m=$XLA_PYTHON_CLIENT_MEM_FRACTION
        echo "$* gpu=$CUDA_VISIBLE_DEVICES n=$RL2S_GPUS mem=$m x=${{X:-}} out=${{OUT##*/}}" \\
            >> {events}
        """))
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    work = tmp_path / "w2"
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}",
           "RL2S_SITE": str(tmp_path / "site"), "STREAMS": str(tmp_path / "streams")}
    proc = subprocess.run(
        ["bash", "experiments/device.sh", "_streams_run",
         f"@1,2 X=7 RL2S_WORK={work} run a.log python3 two; run b.log python3 again",
         "@0 run c.log python3 one", "@0 run d.log python3 also"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    ev = sorted(events.read_text().split("\n")[:-1])
    assert ev == ["again gpu=1,2 n=2 mem=0.9 x= out=s0_1", "also gpu=0 n=1 mem=0.45 x= out=s2_0",
                  "one gpu=0 n=1 mem=0.45 x= out=s1_0", "two gpu=1,2 n=2 mem=0.9 x=7 out=s0_0"]
    assert work.is_dir()  # the run's W
    progress = (tmp_path / "streams" / "progress.log").read_text()
    assert f"GPU 1,2: X=7 RL2S_WORK={work} run a.log python3 two" in progress
    assert progress.rstrip().split("\n")[-1].startswith("ALLDONE")


def test_device_runner_lists_its_subcommands_on_a_bad_one():
    """experiments/device.sh with no or an unknown subcommand installs nothing, exits 2 and
    prints its help, which names every subcommand it dispatches."""
    import re
    import subprocess
    with open(os.path.join(ROOT, "experiments", "device.sh")) as f:
        text = f.read()
    dispatched = set(re.search(r"\n  ([a-z_|]+)\) setup_env", text).group(1).split("|"))
    for args in ([], ["bogus"]):
        proc = subprocess.run(["bash", "experiments/device.sh", *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=30)
        assert proc.returncode == 2
        for sub in dispatched | {"jobs"}:
            assert f"device.sh {sub} " in proc.stderr, sub


def test_select_point_rejects_a_point_whose_worst_training_vd_exploded():
    """The best selection tau wins, except at a point whose selection MVD is above twice the
    lane's lowest; when every point is that bad, none is rejected."""
    from rl2s_jax.train.lanes import select_point

    pt = lambda step, tau, mvd: {"step": step, "select": {"kendall_tau": tau, "avd": 1.0,
                                                          "mvd": mvd}, "test": {"step": step}}
    points = [pt(100, 0.70, 50.0), pt(200, 0.90, 400.0), pt(300, 0.80, 90.0)]
    assert select_point(points)["step"] == 300
    assert select_point([pt(100, 0.7, 50.0), pt(200, 0.9, 60.0)])["step"] == 200
    assert select_point([pt(100, 0.7, np.nan), pt(200, 0.9, np.inf)])["step"] == 200
    # a diverged point (non-finite tau) with a tiny MVD sets no bound for the others
    assert select_point([pt(100, np.nan, 1.0), pt(200, 0.9, 10.0)])["step"] == 200
    assert select_point([{"step": 1, "select": None, "test": None}]) is None


def test_paper_zoo_recipe_and_guard_floor_flags():
    """--zoo-recipe puts the zoo learner's discount, reward scale and batch (and a 2^19-row
    buffer) under the SAC settings, --sac-set still winning; a task without a SAC zoo plan is
    refused, naming the flag; the guard's floor defaults to 1 x the lanes' training MVD and a
    negative scale is refused."""
    from rl2s_jax.zoo.build import ZOO_SAC, fine_tuning_recipe

    paper = _load("paper")
    plan = ZOO_SAC["hopper"].config
    recipe = fine_tuning_recipe("hopper")
    assert recipe == {"gamma": plan.gamma, "reward_scaling": plan.reward_scaling,
                      "batch_size": plan.batch_size, "buffer_size": 1 << 19,
                      "learn_alpha": False}
    args = paper.build_parser().parse_args(["--task", "hopper", "--zoo-recipe", "--sac-set",
                                            "batch_size=64"])
    assert args.guard_floor_scale == 1.0
    sac = paper.check_arguments(args)[2]
    assert sac["gamma"] == plan.gamma and sac["reward_scaling"] == plan.reward_scaling
    assert sac["buffer_size"] == 1 << 19 and sac["batch_size"] == 64
    assert sac["learn_alpha"] is False
    assert "gamma" not in paper.check_arguments(
        paper.build_parser().parse_args(["--task", "hopper"]))[2]
    assert fine_tuning_recipe("no-such-task") == {}
    args = paper.build_parser().parse_args(["--task", "hopper", "--zoo-recipe"])
    args.task = "no-such-task"
    with pytest.raises(SystemExit, match="zoo-recipe"):
        paper.check_arguments(args)
    args = paper.build_parser().parse_args(["--task", "hopper", "--guard-floor-scale", "-1"])
    with pytest.raises(SystemExit, match="guard-floor-scale: expected a finite float >= 0"):
        paper.check_arguments(args)


# ------------------------------------------------------------------ bench_train.py (the race)


def test_bench_train_race_ratios_and_breakdown(tmp_path, monkeypatch):
    """The official-loop race's bookkeeping: the port's last JSON line per P is read, each full
    row at the config's VD horizon gets cycle = 1000 / our generator updates per second and
    the ratios against the port's (breakdown and other-horizon rows are skipped); an empty
    dir is refused by name; the breakdown rows each take one part away and validate; the
    official sizes are one ReLU generator at batch 256 with no NLL anchor or held-out rows."""
    monkeypatch.syspath_prepend(os.path.join(ROOT, "experiments"))
    bt = _load("bench_train")
    (tmp_path / "official_p17.json").write_text(
        'loading...\n{"cycle_s": 40.0, "generator_updates_per_s": 25.0, '
        '"sim_transitions_per_s": 100.0}\n')
    (tmp_path / "notes.json").write_text("{}")
    official = bt.read_official(str(tmp_path))
    assert list(official) == [17] and official[17]["cycle_s"] == 40.0
    rows = [dict(policies=17, vmapped_runs=1, vd_horizon=1000, gen_updates_per_s=500.0,
                 sim_transitions_per_s=1e4, variant="full"),
            dict(policies=17, vmapped_runs=8, vd_horizon=1000, gen_updates_per_s=2000.0,
                 sim_transitions_per_s=4e4, variant="full", matmul_dtype="bfloat16"),
            dict(policies=17, vmapped_runs=1, vd_horizon=250, gen_updates_per_s=900.0,
                 sim_transitions_per_s=1e4, variant="full"),
            dict(policies=17, vmapped_runs=1, vd_horizon=1000, gen_updates_per_s=900.0,
                 sim_transitions_per_s=1e4, variant="no VD"),
            dict(policies=64, vmapped_runs=1, vd_horizon=1000, gen_updates_per_s=400.0,
                 sim_transitions_per_s=1e4, variant="full")]
    race = bt.race_ratios(rows, official, horizon=1000)
    assert [(r["vmapped_runs"], r["matmul_dtype"]) for r in race] == [(1, "float32"),
                                                                       (8, "bfloat16")]
    assert race[0]["ours_cycle_s"] == pytest.approx(2.0)
    assert race[0]["cycle_ratio"] == pytest.approx(20.0)
    assert race[1]["cycle_ratio"] == pytest.approx(80.0)
    assert race[0]["gen_update_ratio"] == pytest.approx(20.0)
    assert race[0]["sim_ratio"] == pytest.approx(100.0)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SystemExit, match="official-dir: expected official_p<P>.json"):
        bt.read_official(str(empty))
    from rl2s_jax.train.config import TrainConfig
    cfg = TrainConfig(task="hopper", method="rl2s").override(bt.OFFICIAL_SIZES)
    cfg.validate()
    assert (cfg.ensemble_size, cfg.batch_size, cfg.dynamics.activation) == (1, 256, "relu")
    parts = dict(bt.breakdown_configs(cfg))
    assert list(parts) == ["no VD", "1 sim step", "1 critic update", "1 gen update"]
    for c in parts.values():
        c.validate()
    assert parts["no VD"].vd.every == 0 and parts["1 sim step"].adversarial.sim_steps == 1
    assert parts["1 critic update"].adversarial.disc_updates == 1
    assert parts["1 gen update"].updates_per_step == 1
    changed = {k for k, c in parts.items()
               for f in dataclasses.fields(cfg) if getattr(c, f.name) != getattr(cfg, f.name)}
    assert changed == set(parts)
    # --set: a bad override is refused by its name before any row is timed
    for bad, msg in (("scan_unrol=2", "did you mean 'scan_unroll'"),
                     ("scan_unroll=0", "scan_unroll: expected an int >= 1")):
        with pytest.raises(SystemExit, match=msg):
            bt.main(["--set", bad])


def test_worst_policy_names_the_policy_that_sets_each_lanes_mvd(tmp_path):
    """experiments/worst_policy.py: per lane the test policy of the largest |sim - true| (its
    MVD) and the second-largest error; pooled counts most frequent first, each policy's range
    of true and simulated values; a lane whose values do not match the test policies is
    refused by name; lanes without sim_value are skipped."""
    wp = _load("worst_policy")
    a = {"true_value": [0.0, 100.0, 200.0], "test_policy_names": ["p0", "p1", "p2"],
         "lanes": {"rl2s/0": {"sim_value": [5.0, 100.0, 900.0]},
                   "bc/0": {"sim_value": [-50.0, 110.0, 190.0]},
                   "gail/0": {"sim_value": [0.0, 100.0, 150.0]},
                   "old/0": {"seed": 0}}}
    rows = wp.lane_worst(a, "a.json")
    by = {r["lane"]: r for r in rows}
    assert set(by) == {"rl2s/0", "bc/0", "gail/0"}
    assert (by["rl2s/0"]["policy"], by["rl2s/0"]["mvd"], by["rl2s/0"]["second"]) == ("p2", 700.0,
                                                                                     5.0)
    assert (by["bc/0"]["policy"], by["bc/0"]["sim"], by["bc/0"]["second"]) == ("p0", -50.0, 10.0)
    b = {**a, "true_value": [0.0, 100.0, 210.0], "lanes": {"rl2s/1": {"sim_value": [0, 0, 10]}}}
    s = wp.summary(rows + wp.lane_worst(b, "b.json"))
    assert s["lanes"] == 4 and s["worst_counts"] == [("p2", 3), ("p0", 1)]
    assert s["by_policy"]["p2"] == {"n": 3, "true_min": 200.0, "true_max": 210.0,
                                    "sim_min": 10.0, "sim_max": 900.0, "mvd_max": 700.0}
    assert s["median_mvd"] == pytest.approx(125.0)  # 700, 50, 50, 200
    bad = {**a, "lanes": {"rl2s/0": {"sim_value": [1.0, 2.0]}}}
    with pytest.raises(ValueError, match="lanes.rl2s/0.sim_value: expected 3 values"):
        wp.lane_worst(bad)
    path = tmp_path / "a.json"
    path.write_text(json.dumps(a))
    out = tmp_path / "out.json"
    assert wp.main([str(path), "--json", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written["summary"]["worst_counts"] == [["p2", 2], ["p0", 1]]
    assert len(written["rows"]) == 3 and written["command"].endswith(str(path))


def test_worst_policy_seed_spread_points_at_the_disputed_policy():
    """seed_spread: per method with 2+ seeds, the std over seeds of each policy's simulated
    value; the worst policy (largest error over the seeds) and its rank by that spread, the
    most disputed policy and the Spearman correlation of spread and mean error (checked
    against numbers worked by hand); one-seed methods are skipped."""
    wp = _load("worst_policy")
    r = {"true_value": [0.0, 10.0, 20.0], "test_policy_names": ["a", "b", "c"],
         "lanes": {"rl2s/0": {"sim_value": [0.0, 12.0, 60.0]},
                   "rl2s/1": {"sim_value": [1.0, 8.0, -20.0]},
                   "gail/0": {"sim_value": [5.0, 15.0, 25.0]},
                   "bc/0": {"sim_value": [0.0, 30.0, 20.0]},
                   "bc/1": {"sim_value": [0.0, 50.0, 21.0]}}}
    out = {x["method"]: x for x in wp.seed_spread(r, "r.json")}
    assert set(out) == {"rl2s", "bc"}  # gail has one seed
    assert (out["rl2s"]["worst"], out["rl2s"]["worst_rank"], out["rl2s"]["top_spread"]) == (
        "c", 1, "c")
    assert out["rl2s"]["rho"] == pytest.approx(1.0)  # spreads .7, 2.8, 56.6; errors .5, 2, 40
    # bc: spreads 0, 14.1, .7; largest error b (40); mean errors 0, 30, .5 -> same order
    assert (out["bc"]["worst"], out["bc"]["worst_rank"], out["bc"]["seeds"]) == ("b", 1, 2)
    r["lanes"]["bc/1"]["sim_value"] = [12.0, 25.0, 20.0]  # spreads 8.5, 3.5, 0; b errs 20
    bc = next(x for x in wp.seed_spread(r) if x["method"] == "bc")
    assert (bc["worst"], bc["top_spread"], bc["worst_rank"]) == ("b", "a", 2)


def test_improvement_summary_by_hand(tmp_path):
    """experiments/improvement_summary.py on two made-up one-seed runs of hopper's first three
    test policies: the raw and guarded median gains, MPI / API, the deployed count, the paired
    RL2S - GAIL median and the guard rules' counts equal the numbers worked by hand."""
    from rl2s_jax.zoo.zoo import load_zoo
    summ = _load("improvement_summary")
    zoo = load_zoo("hopper")
    zret = np.asarray(zoo.returns, np.float64)
    test = list(zoo.split_ids("test"))
    order = sorted(test, key=lambda i: zret[i])[:3]  # three below the top quartile
    names = [f"hopper-{i:03d}" for i in test]
    ids = [test.index(i) for i in order]
    c0 = [100.0, 200.0, 400.0]

    def run(seed, c1_rl2s, c1_gail, acc_rl2s, gain_rl2s):
        lane = lambda m, c1, acc, g: {
            "method": m, "seed": seed, "policy_ids": ids, "c0_paired": c0, "c1": c1,
            "guard_accepted": acc, "guard_member_gain": g}
        return {"task": "hopper", "command": f"paper.py --first-seed {seed}", "hardware": "h",
                "sizes": {"improve_iterations": 10, "sac_envs": 4}, "test_policy_names": names,
                "improvement": {f"rl2s/{seed}": lane("rl2s", c1_rl2s, acc_rl2s, gain_rl2s),
                                f"gail/{seed}": lane("gail", c1_gail, [False] * 3,
                                                     [[-1.0] * 3, [1.0] * 3])}}
    runs = [run(0, [150.0, 180.0, 440.0], [100.0, 220.0, 400.0], [True, False, False],
                [[5.0, -1.0, 2.0], [3.0, 2.0, 1.0]]),
            run(1, [110.0, 200.0, 300.0], [120.0, 200.0, 400.0], [False, False, True],
                [[1.0, 1.0, -2.0], [1.0, 1.0, 1.0]])]
    # the range floor's verdicts, recorded by rl2s's lanes (gail's runs have none)
    runs[0]["improvement"]["rl2s/0"]["guard_accepted_range"] = [True, True, False]
    runs[1]["improvement"]["rl2s/1"]["guard_accepted_range"] = [True, False, False]
    # run 0 kept its training values: the discordant-pair floor is 4 - 2 = 2 (margin 2% of
    # 100): rl2s/0's members clear it on policy 0 only (gains 5, 3)
    runs[0]["improvement"]["rl2s/0"]["guard_floor_range"] = 1.0
    runs[0]["lanes"] = {"rl2s/0": {"family": "adversarial", "eps": 0.25,
                                   "sim_value": [100.0] * len(test),
                                   "train_sim_value": [1.0, 4.0, 2.0]}}
    runs[0]["train_true_value"] = [1.0, 2.0, 3.0]
    runs[0]["oracle_improvement"] = {"policy_ids": ids, "per_seed": [
        {"c0_paired": c0, "c1": [200.0, 300.0, 600.0]}]}  # I 1, .5, .5
    runs[1]["control"] = {"policy_ids": ids, "c0": [c0], "c1": [[110.0, 220.0, 440.0]]}
    runs[1]["guard_rescored"] = {"scale": 0.0, "by": "experiments/guard_calibration.py"}
    paths = []
    for k, r in enumerate(runs):
        paths.append(tmp_path / f"r{k}.json")
        paths[-1].write_text(json.dumps(r))
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o"), "--bootstrap", "50"]) == 0
    s = json.loads((tmp_path / "o" / "hopper.json").read_text())["summary"]
    rl2s, gail = s["methods"]["rl2s"], s["methods"]["gail"]
    # rl2s I per seed: [.5, -.1, .1] and [.1, 0, -.25]; seed means [.3, -.05, -.075]
    assert rl2s["median_gain_raw"] == pytest.approx(-0.05)
    assert rl2s["median_gain_raw_per_seed"] == pytest.approx([0.1, 0.0])
    # a perfect guard keeps each loss at 0: [.5, 0, .1] and [.1, 0, 0]; means [.3, 0, .05]
    assert rl2s["median_gain_perfect_guard"] == pytest.approx(0.05)
    # deployed: seed 0 policy 0 (I .5), seed 1 policy 2 (I -.25): means [.25, 0, -.125]
    assert rl2s["median_gain"] == pytest.approx(0.0) and rl2s["deployed"] == 2
    assert rl2s["mpi"] == pytest.approx((0.0 - 0.25) / 2)
    assert rl2s["api"] == pytest.approx((0.5 / 3 - 0.25 / 3) / 2)
    assert rl2s["worst_raw"] == pytest.approx(-0.25) and gail["deployed"] == 0
    # gail I: [0, .1, 0] and [.2, 0, 0]; rl2s - gail: [.5, -.2, .1, -.1, 0, -.25]
    pr = s["paired"]["rl2s-gail"]
    assert pr["median"] == pytest.approx(-0.05) and pr["rl2s_higher"] == 2
    assert pr["pairs"] == 6
    every = s["guard_rules"]["rl2s"]["every member predicts a gain"]
    assert every["deployed"] == 4 and every["worse_than_start"] == 0  # s0 p0, p2; s1 p0, p1
    prot = s["guard_rules"]["rl2s"]["protocol guard (training-MVD floor)"]
    assert prot["deployed"] == 2 and prot["worse_than_start"] == 1
    rng = s["guard_rules"]["rl2s"]["training-error range floor"]  # I .5, -.1 (s0), .1 (s1)
    assert rng["deployed"] == 3 and rng["worse_than_start"] == 1
    assert rng["real_gain_median"] == pytest.approx(0.1)
    assert "training-error range floor" not in s["guard_rules"]["gail"]
    assert rng["lanes"] == 2 and "protocol guard on the range floor's lanes" not in s[
        "guard_rules"]["rl2s"]
    pair = s["guard_rules"]["rl2s"]["discordant-pair floor"]
    assert (pair["deployed"], pair["lanes"], pair["worse_than_start"]) == (1, 1, 0)
    assert "discordant-pair floor" not in s["guard_rules"]["gail"]
    kept = json.loads((tmp_path / "o" / "hopper.json").read_text())["runs"][0]
    assert kept["lanes"]["rl2s/0"] == {"family": "adversarial", "sim_value": [100.0] * len(test),
                                       "train_sim_value": [1.0, 4.0, 2.0]}
    assert kept["train_true_value"] == [1.0, 2.0, 3.0]
    kept1 = json.loads((tmp_path / "o" / "hopper.json").read_text())["runs"][1]
    assert "lanes" not in kept1 and kept1["guard_rescored"]["scale"] == 0.0  # nothing invented
    assert s["budget_env_steps"] == 40
    # validation-policy runs: no --control (the task's is the test policies'), and no mixing
    val = tmp_path / "val.json"
    val.write_text(json.dumps({**runs[0], "policy_split": "validation"}))
    ctl0 = tmp_path / "ctl0.json"
    ctl0.write_text(json.dumps({"control": {"median_gain": 0.4}}))
    with pytest.raises(SystemExit, match="fine-tuned validation policies"):
        summ.main(["--task", "hopper", "--runs", str(val), "--control", str(ctl0), "--out",
                   str(tmp_path / "v")])
    with pytest.raises(SystemExit, match="--policy-split differs"):
        summ.main(["--task", "hopper", "--runs", str(val), str(paths[1]), "--out",
                   str(tmp_path / "v")])
    assert s["controls"]["oracle_sim"]["median_gain"] == pytest.approx(0.5)
    assert s["controls"]["real_env"]["median_gain"] == pytest.approx(0.1)
    assert s["controls"]["real_env"]["seeds"] == 1
    assert (tmp_path / "o" / "hopper.png").stat().st_size > 10_000  # the figure
    # --control: the gap read on the control's policies (here the first two of the three)
    ctl = tmp_path / "control.json"
    ctl.write_text(json.dumps({"control": {"median_gain": 0.4, "policies": 2},
                               "test_policy_names": [f"hopper-{i:03d}" for i in order]}))
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o"), "--bootstrap", "50", "--control", str(ctl)]) == 0
    common = json.loads((tmp_path / "o" / "hopper.json").read_text())["summary"][
        "on_control_policies"]
    assert common["zoo_ids"] == order[:2] and common["n_below"] == 2
    # seed-mean I on the two: rl2s [.3, -.05], gail [.1, .05], oracle [1, .5], real [.1, .1]
    assert common["rl2s"] == pytest.approx(0.125) and common["gail"] == pytest.approx(0.075)
    assert common["oracle_sim"] == pytest.approx(0.75)
    assert common["real_env"] == pytest.approx(0.1) and common["control"] == 0.4
    # with its C0 / C1 the control's median gain is recomputed on today's zoo: I .5 and 0
    ctl2 = tmp_path / "control2.json"
    ctl2.write_text(json.dumps({"control": {"median_gain": 0.4, "policies": 2,
                                            "c0": [[100.0, 200.0]], "c1": [[150.0, 200.0]]},
                                "test_policy_names": [f"hopper-{i:03d}" for i in order]}))
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o2"), "--bootstrap", "50", "--control", str(ctl2)]) == 0
    c2 = json.loads((tmp_path / "o2" / "hopper.json").read_text())["summary"]["control"]
    assert c2["median_gain"] == pytest.approx(0.25) and c2["median_gain_recorded"] == 0.4
    assert c2["n_below"] == 2
    # a control that records its zoo ids is read by them, not by the runs' first test names
    # (Ant's zoo grew: its control fine-tuned a policy the paper run's names lack)
    ctl3 = tmp_path / "control3.json"
    ctl3.write_text(json.dumps({"control": {"median_gain": 0.4, "policies": 2,
                                            "zoo_ids": order[1:]},
                                "test_policy_names": [f"hopper-{i:03d}" for i in order]}))
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o3"), "--bootstrap", "50", "--control", str(ctl3)]) == 0
    assert json.loads((tmp_path / "o3" / "hopper.json").read_text())["summary"][
        "on_control_policies"]["zoo_ids"] == order[1:]
    # --record writes issue 39's per-method record into the --control file, keeping the rest
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o"), "--bootstrap", "50", "--control", str(ctl),
                      "--record"]) == 0
    doc = json.loads(ctl.read_text())
    rec = doc["improvement_by_method"]
    assert doc["control"]["median_gain"] == 0.4 and rec["control"]["median_gain"] == 0.4
    assert rec["rl2s"]["median_gain"] == pytest.approx(0.0) and rec["rl2s"]["deployed"] == 2
    assert rec["rl2s"]["mpi"] == pytest.approx(-0.125) and rec["gail"]["budget_env_steps"] == 40
    assert rec["rl2s"]["commands"] == ["paper.py --first-seed 0", "paper.py --first-seed 1"]
    assert rec["verdict"] == "not enough seeds: 2 of 3"
    with pytest.raises(SystemExit):  # --record without the file to record into
        summ.main(["--task", "hopper", "--runs", str(paths[0]), "--record"])
    # issue 39's bars on it: the control's 0.4 >= 0.3; rl2s guarded 0 < 0.2, MPI -0.125 < 0,
    # API 1/24 < the paper's 2.94; rl2s >= gail (both 0); 2 seeds: no verdict yet
    bars = json.loads((tmp_path / "o" / "hopper.json").read_text())["summary"]["bars"]
    assert {k: b["holds"] for k, b in bars.items() if k != "verdict"} == {
        "control median gain": True, "rl2s median gain": False, "rl2s mpi": False,
        "rl2s api": False, "rl2s >= gail": True, "rl2s >= bc": None}  # no bc lanes: n/a
    assert bars["rl2s median gain"]["target"] == pytest.approx(0.2)
    assert bars["rl2s api"]["value"] == pytest.approx(1 / 24)
    assert bars["rl2s api"]["target"] == 2.94 and bars["verdict"] == "not enough seeds: 2 of 3"
    # guarded rl2s - gail: [.5, 0, 0, 0, 0, -.25]
    pg = json.loads((tmp_path / "o" / "hopper.json").read_text())["summary"]["paired"][
        "rl2s-gail guarded"]
    assert pg["median"] == 0.0 and pg["rl2s_higher"] == 1 and pg["pairs"] == 6
    # a task the paper has no API for: no target, the bar does not hold
    nopaper = summ.issue_bars(json.loads((tmp_path / "o" / "hopper.json").read_text())[
        "summary"], "pointmass")["rl2s api"]
    assert nopaper["target"] is None and nopaper["holds"] is False
    # 3 seeds, every judged bar met: a method not run leaves the verdict incomplete, not pass
    summ_ = {"control": {"median_gain": 0.4}, "paired": {}, "methods": {
        "rl2s": {"median_gain": 0.3, "mpi": 0.0, "api": 3.0, "seeds": [0, 1, 2]},
        "gail": {"median_gain": 0.1}}}
    assert summ.issue_bars(summ_, "hopper")["verdict"] == "incomplete: no bc lanes"
    summ_["methods"]["bc"] = {"median_gain": 0.5}
    summ_["paired"]["rl2s-bc guarded"] = {"ci95": [-0.3, -0.1]}
    assert summ.issue_bars(summ_, "hopper")["verdict"] == "fail"   # bc wins, no tie
    summ_["paired"]["rl2s-bc guarded"] = {"ci95": [-0.3, 0.1]}
    assert summ.issue_bars(summ_, "hopper")["verdict"] == "pass"   # a paired tie
    # a bc run on seed 0 only: paired with rl2s over seed 0 alone; a lane twice is refused
    bc = {**runs[0], "improvement": {"bc/0": {**runs[0]["improvement"]["gail/0"],
                                              "method": "bc", "c1": [100.0, 200.0, 480.0]}}}
    paths.append(tmp_path / "bc.json")
    paths[-1].write_text(json.dumps(bc))
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o"), "--bootstrap", "50"]) == 0
    s = json.loads((tmp_path / "o" / "hopper.json").read_text())["summary"]
    pb = s["paired"]["rl2s-bc"]  # seed 0: rl2s I [.5, -.1, .1] - bc I [0, 0, .2]
    assert pb["seeds"] == [0] and pb["pairs"] == 3 and pb["median"] == pytest.approx(-0.1)
    assert s["methods"]["bc"]["seeds"] == [0] and s["paired"]["rl2s-gail"]["pairs"] == 6
    # the range floor on the lanes that recorded it (bc's: none), the protocol guard on them
    del runs[1]["improvement"]["rl2s/1"]["guard_accepted_range"]
    paths[1].write_text(json.dumps(runs[1]))
    assert summ.main(["--task", "hopper", "--runs", *map(str, paths), "--out",
                      str(tmp_path / "o"), "--bootstrap", "50"]) == 0
    gr = json.loads((tmp_path / "o" / "hopper.json").read_text())["summary"]["guard_rules"]
    part, same = (gr["rl2s"][k] for k in ("training-error range floor",
                                           "protocol guard on the range floor's lanes"))
    assert (part["lanes"], part["deployed"], part["worse_than_start"]) == (1, 2, 1)  # seed 0
    assert (same["lanes"], same["deployed"], same["worse_than_start"]) == (1, 1, 0)
    assert gr["rl2s"]["protocol guard (training-MVD floor)"]["lanes"] == 2
    with pytest.raises(SystemExit, match="appears twice"):
        summ.main(["--task", "hopper", "--runs", *map(str, paths), str(paths[-1]), "--out",
                   str(tmp_path / "o"), "--bootstrap", "50"])


def test_worst_policy_likelihood_shift_scores_the_move_from_bc():
    """likelihood_shift: per adversarial lane with a bc lane of the same seed, each policy's
    |sim - sim_bc| over the lane's median of it; the top policy, the worst one's score (worked
    by hand); bc lanes and lanes without a same-seed bc are skipped."""
    wp = _load("worst_policy")
    r = {"true_value": [0.0, 10.0, 20.0, 30.0], "test_policy_names": ["a", "b", "c", "d"],
         "lanes": {"rl2s/0": {"sim_value": [1.0, 12.0, 60.0, 31.0]},
                   "bc/0": {"sim_value": [0.0, 10.0, 20.0, 30.0]},
                   "gail/1": {"sim_value": [0.0, 0.0, 0.0, 0.0]}}}
    out = wp.likelihood_shift(r, "r.json")
    assert len(out) == 1 and out[0]["lane"] == "rl2s/0"
    # shifts 1, 2, 40, 1: median 1.5; the top and the worst are c (error 40), score 40 / 1.5
    assert (out[0]["top"], out[0]["worst"], out[0]["mvd"]) == ("c", "c", 40.0)
    assert out[0]["top_score"] == pytest.approx(40 / 1.5) == out[0]["worst_score"]


def test_improve_control_describe_by_hand():
    """improve_control.describe on a made-up control of hopper's three lowest test policies
    and its top one: only the three below the zoo's top quartile count; their start as a
    fraction of the zoo's top, the final actors' KL (median, 10% / 90%), the median gains of
    the deployed and the final actors and the starts kept equal the numbers worked by hand."""
    from rl2s_jax.zoo.zoo import load_zoo
    ic = _load("improve_control")
    zret = np.asarray(load_zoo("hopper").returns, np.float64)
    test = sorted(load_zoo("hopper").split_ids("test"), key=lambda i: zret[i])
    ids = test[:3] + test[-1:]
    c = {"c0": [[100.0, 200.0, 400.0, 2000.0]], "c1": [[150.0, 200.0, 400.0, 1000.0]],
         "final_c1": [[150.0, 300.0, 300.0, 1000.0]], "selected": [[2, 0, 0, 1]],
         "final_kl": [0.1, 0.2, 0.3, 9.0]}
    out = ic.describe({"task": "hopper", "zoo_ids": ids, "configs": {"ft": c}}, zret)["ft"]
    assert out["n_below"] == 3 and out["kept_at_start"] == 2
    frac = zret[ids[:3]] / zret.max()
    assert out["start_of_top"] == pytest.approx([frac.min(), np.median(frac), frac.max()])
    assert out["final_kl"][0] == pytest.approx(0.2)  # the top policy's 9.0 does not count
    assert out["final_kl"][1:] == pytest.approx(np.quantile([0.1, 0.2, 0.3], [0.1, 0.9]))
    assert out["median_gain"] == pytest.approx(0.0)          # I .5, 0, 0
    assert out["median_gain_final"] == pytest.approx(0.5)    # I .5, .5, -.25
    c["sac"] = {"kl_weight": 0.0}  # no anchor in the loss: SAC measures the KL all the same
    assert ic.describe({"task": "hopper", "zoo_ids": ids, "configs": {"ft": c}},
                       zret)["ft"]["final_kl"][0] == pytest.approx(0.2)
    c["final_kl"] = [0.0] * 4  # a file from before SAC measured it at weight 0: read 0, unknown
    assert ic.describe({"task": "hopper", "zoo_ids": ids, "configs": {"ft": c}},
                       zret)["ft"]["final_kl"] is None


def test_improve_control_combine_joins_seeds_by_hand(tmp_path):
    """--combine: two runs of one control (--first-seed 0 and 1) become one of 2 seeds, fields
    joined in seed order, MPI / API over both (worked by hand); runs that differ or share a
    seed are refused, naming what."""
    ic = _load("improve_control")

    def run(k, c1):
        e = {"sac": {"kl_weight": 0.0}, "select": {"episodes": 4}, "paired": True,
             "c0": [[100.0, 200.0]], "c0_se": [[1.0, 1.0]], "c1": [c1], "c1_se": [[1.0, 1.0]],
             "diff_se": [[1.0, 1.0]], "selected": [[1, 0]], "final_c1": [c1],
             "final_c1_se": [[1.0, 1.0]], "final_diff_se": [[1.0, 1.0]],
             "validation_mean": [[[100.0, 200.0]], [[110.0 + k, 200.0]]],
             "validation_gain_se": [[[0.0, 0.0]], [[1.0, 1.0]]], "final_kl": [0.1 * (k + 1)] * 2}
        return {"task": "hopper", "zoo_ids": [3, 7], "seeds": 1, "first_seed": k,
                "seed_ids": [k], "iterations": 10, "n_episodes": 4, "zoo_recipe": None,
                "seconds": 5.0, "command": f"run {k}", "configs": {"ft": e}}

    a, b = run(0, [150.0, 200.0]), run(1, [100.0, 100.0])  # I: (.5, 0) and (0, -.5)
    paths = []
    for i, r in enumerate((b, a)):  # given out of order: joined in seed order
        paths.append(tmp_path / f"c{i}.json")
        paths[-1].write_text(json.dumps(r))
    assert ic.main(["--combine", *map(str, paths), "--out", str(tmp_path / "o")]) == 0
    c = json.loads((tmp_path / "o" / "control_hopper.json").read_text())
    e = c["configs"]["ft"]
    assert c["seeds"] == 2 and c["seed_ids"] == [0, 1] and c["command"] == ["run 0", "run 1"]
    assert e["c1"] == [[150.0, 200.0], [100.0, 100.0]] and e["final_kl"] == [0.1, 0.1, 0.2, 0.2]
    assert e["mpi"] == pytest.approx((0.0 - 0.5) / 2) and e["api"] == pytest.approx(0.0)
    assert e["final_mpi"] == pytest.approx(-0.25) and len(e["mpi_ci95"]) == 2
    assert np.asarray(e["validation_mean"]).shape == (2, 2, 2)
    assert e["validation_mean"][1][1] == [111.0, 200.0]
    other = run(1, [1.0, 1.0])
    other["iterations"] = 20
    with pytest.raises(ValueError, match="iterations differs"):
        ic.combine([a, other])
    with pytest.raises(ValueError, match="a seed in two files"):
        ic.combine([a, run(0, [1.0, 1.0])])
    bad = run(1, [1.0, 1.0])
    bad["configs"]["ft"]["sac"] = {"kl_weight": 0.01}
    with pytest.raises(ValueError, match="ft's sac settings differ"):
        ic.combine([a, bad])
    with pytest.raises(SystemExit, match="first-seed: expected >= 0"):
        ic.main(["--tasks", "hopper", "--first-seed", "-1", "--out", str(tmp_path / "n")])


def test_improve_control_ids_must_be_test_policies_of_one_task(tmp_path):
    """improve_control --ids: zoo ids that are not test policies of the one task named are
    refused before any work, with the field named."""
    from rl2s_jax.zoo.zoo import load_zoo
    ic = _load("improve_control")
    train = list(load_zoo("hopper").split_ids("train"))
    test = list(load_zoo("hopper").split_ids("test"))
    with pytest.raises(SystemExit, match="ids: expected test-policy zoo ids"):
        ic.main(["--tasks", "hopper", "--ids", str(train[0]), "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="ids: expected train-policy zoo ids"):
        ic.main(["--tasks", "hopper", "--split", "train", "--ids", str(test[0]), "--out",
                 str(tmp_path)])
    with pytest.raises(SystemExit, match="ids: expected"):
        ic.main(["--tasks", "hopper,ant", "--ids", str(test[0]), "--out", str(tmp_path)])
    fit = load_zoo("hopper").split_ids("fit")  # training policies, but not validation ones
    with pytest.raises(SystemExit, match="ids: expected validation-policy zoo ids"):
        ic.main(["--tasks", "hopper", "--split", "validation", "--ids", str(fit[0]), "--out",
                 str(tmp_path)])
    assert not any(tmp_path.iterdir())  # nothing written


def test_guard_calibration_rule_needs_evidence():
    """choose_scale: the smallest loss-free scale, then the largest that deploys as many on
    validation; nothing deployed anywhere, or a loss at every scale: 1."""
    gc = _load("guard_calibration")

    def grid(*rows):  # per scale 0, .5, 1: (deployed, losses) of two methods pooled
        return {k: {"validation": {"a": {"deployed": d, "losses": lo},
                                   "b": {"deployed": 0, "losses": 0}}}
                for k, (d, lo) in zip((0.0, 0.5, 1.0), rows, strict=True)}

    assert gc.choose_scale(grid((9, 2), (6, 0), (3, 0))) == 0.5
    assert gc.choose_scale(grid((9, 0), (6, 0), (3, 0))) == 0.0
    assert gc.choose_scale(grid((6, 0), (6, 0), (3, 0))) == 0.5   # 0 adds nothing on validation
    assert gc.choose_scale(grid((0, 0), (0, 0), (0, 0))) == 1.0   # no evidence at all
    assert gc.choose_scale(grid((9, 2), (6, 1), (3, 1))) == 1.0   # a loss everywhere


def test_guard_calibration_by_hand(tmp_path):
    """experiments/guard_calibration.py on made-up validation and test runs of hopper: per
    floor scale k the deployments, real losses and guarded median gain by hand (k scales the
    recorded training MVD, not a run's own scaled floor); k is the smallest scale without a
    validation loss over every method's lanes; --rescore writes the test runs' verdicts at k;
    runs of the wrong split, lanes without the members' starts and bad scales are refused."""
    gc = _load("guard_calibration")
    zoo = load_zoo("hopper")
    zret = np.asarray(zoo.returns, np.float64)
    val_ids, test = zoo.split_ids("validation"), list(zoo.split_ids("test"))
    low = sorted(test, key=lambda i: zret[i])[:3]  # below the top quartile

    def lane(m, ids, c0, c1, gain, floor):
        return {"method": m, "seed": 0, "policy_ids": ids, "c0_paired": c0, "c1": c1,
                "guard_member_start": [c0, c0], "guard_member_gain": gain,
                "guard_floor": floor}

    # rl2s: I .5, -.1; at margin .02 the bars are 2 / 4, at scale k k x 50: policy 1's members
    # (30, 30) clear k 0 and .5 (a loss) but not .75; bc's never lose
    val = {"task": "hopper", "policy_split": "validation",
           "test_policy_names": zoo.policy_names(val_ids), "improvement": {
               "rl2s/0": lane("rl2s", [0, 1], [100.0, 200.0], [150.0, 180.0],
                              [[60.0, 30.0], [40.0, 30.0]], 50.0),
               "bc/0": lane("bc", [0, 1], [100.0, 200.0], [110.0, 220.0],
                            [[20.0, 20.0], [20.0, 20.0]], 10.0)}}
    # test: I .5, -.1, .1; bars 2 / 4 / 8, at k x 40: policy 2's members (30, 20) fail from .75
    # (a run at --guard-floor-scale 0.5: its floor 20, its training MVD 40, which k scales)
    tst = {"task": "hopper", "command": "paper.py", "test_policy_names": zoo.policy_names(test),
           "improvement": {
        "rl2s/0": {**lane("rl2s", [test.index(i) for i in low], [100.0, 200.0, 400.0],
                          [150.0, 180.0, 440.0], [[80.0, 50.0, 30.0], [70.0, 60.0, 20.0]],
                          20.0), "guard_training_mvd": 40.0, "I_deployed": [0.5, 0, 0]}}}
    paths = {}
    for name, r in (("val", val), ("test", tst)):
        paths[name] = tmp_path / f"{name}.json"
        paths[name].write_text(json.dumps(r))
    out = tmp_path / "o"
    assert gc.main(["--task", "hopper", "--validation", str(paths["val"]), "--test",
                    str(paths["test"]), "--scales", "0,0.5,0.75,1", "--out", str(out),
                    "--rescore", str(tmp_path / "at_k")]) == 0
    doc = json.loads((out / "hopper.json").read_text())
    assert doc["chosen_scale"] == 0.75 and doc["margin"] == 0.02
    v = doc["by_scale"]
    assert (v["0.5"]["validation"]["rl2s"]["deployed"],
            v["0.5"]["validation"]["rl2s"]["losses"]) == (2, 1)
    assert (v["0.75"]["validation"]["rl2s"]["deployed"],
            v["0.75"]["validation"]["rl2s"]["losses"]) == (1, 0)
    assert v["1"]["validation"]["bc"]["deployed"] == 2 and v["1"]["validation"]["bc"][
        "losses"] == 0
    t0, t75 = v["0"]["test"]["rl2s"], v["0.75"]["test"]["rl2s"]
    assert (t0["deployed"], t0["losses"], t0["median_gain"]) == (3, 1, pytest.approx(0.1))
    assert (t75["deployed"], t75["losses"], t75["median_gain"]) == (2, 1, pytest.approx(0.0))
    assert (out / "hopper.png").stat().st_size > 10_000  # the figure
    assert doc["test_runs"] == [{"path": str(paths["test"]), "command": "paper.py",
                                 "device": None}]  # where each run came from
    assert doc["validation_runs"][0]["path"] == str(paths["val"])
    assert doc["command"].startswith("python experiments/guard_calibration.py --task hopper")
    # --rescore: the test run again with its guard at the chosen k (0.75 x 40)
    again = json.loads((tmp_path / "at_k" / "test.json").read_text())
    e = again["improvement"]["rl2s/0"]
    assert e["guard_accepted"] == [True, True, False] and "I_deployed" not in e
    assert (e["guard_floor"], e["guard_training_mvd"], e["guard_floor_scale"]) == (30, 40, 0.75)
    assert again["guard_rescored"]["scale"] == 0.75 and e["c1"] == [150.0, 180.0, 440.0]
    assert again["command"] == ("paper.py; guard verdicts rescored at floor 0.75 x the training "
                                "MVD, margin 0.02 (experiments/guard_calibration.py --rescore)")
    # two test runs of one name (paper.py writes <task>.json in each run's dir): both kept
    (tmp_path / "mle").mkdir()
    mle = {**tst, "improvement": {"bc/0": {**tst["improvement"]["rl2s/0"], "method": "bc"}}}
    (tmp_path / "mle" / "test.json").write_text(json.dumps(mle))
    assert gc.main(["--task", "hopper", "--validation", str(paths["val"]), "--test",
                    str(paths["test"]), str(tmp_path / "mle" / "test.json"), "--scales", "0.75",
                    "--out", str(out), "--rescore", str(tmp_path / "both")]) == 0
    assert sorted(p.name for p in (tmp_path / "both").iterdir()) == ["0_test.json",
                                                                      "1_test.json"]
    assert all(json.loads(p.read_text())["guard_rescored"]["from"] == str(src) for p, src in
               zip(sorted((tmp_path / "both").iterdir()),
                   (paths["test"], tmp_path / "mle" / "test.json"), strict=True))
    with pytest.raises(SystemExit, match="on 'validation'"):
        gc.main(["--task", "hopper", "--validation", str(paths["test"]), "--out", str(out)])
    del val["improvement"]["bc/0"]["guard_member_start"]
    (tmp_path / "old.json").write_text(json.dumps(val))
    with pytest.raises(SystemExit, match="bc/0 has no guard_member_start"):
        gc.main(["--task", "hopper", "--validation", str(tmp_path / "old.json"), "--out",
                 str(out)])
    with pytest.raises(SystemExit, match="scales: expected"):
        gc.main(["--task", "hopper", "--validation", str(paths["val"]), "--scales", "-1",
                 "--out", str(out)])


def test_device_kernels_runs_each_mode_and_step_and_refuses_an_unknown_mode(tmp_path):
    """device.sh kernels: kernel_trace.py per (mode, step) with the mode's XLA flags or
    --set; an unknown mode is refused before any run."""
    import subprocess
    import textwrap
    bin_dir, events = tmp_path / "bin", tmp_path / "events"
    bin_dir.mkdir()
    (bin_dir / "nvidia-smi").write_text("#!/usr/bin/env bash\necho stub\n")
    (bin_dir / "python3").write_text(textwrap.dedent(f"""\
        #!/usr/bin/env bash
        echo "XLA_FLAGS=$XLA_FLAGS $*" >> {events}
        """))
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    (tmp_path / ".rl2s_wheels").touch()
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}",
           "OUT": str(tmp_path / "out"), "RL2S_SITE": str(tmp_path)}

    def run(*modes):
        return subprocess.run(["bash", "experiments/device.sh", "kernels", *modes], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=60)

    proc = run("control", "bogus")
    assert proc.returncode == 2 and "bogus" in proc.stderr and not events.exists()
    assert run("no_cmdbuf", "flat").returncode == 0
    lines = events.read_text().splitlines()
    assert len(lines) == 10 and all("experiments/kernel_trace.py" in x for x in lines)
    assert all("--xla_gpu_enable_command_buffer= " in x for x in lines[:5])
    assert all("--set flat_optimizer=true" in x and "command_buffer" not in x
               for x in lines[5:])
    assert sum("--official-sizes" in x for x in lines) == 2
    assert sum("--vmap 6" in x for x in lines) == 4
    assert (tmp_path / "out" / "kernels.tgz").exists()
