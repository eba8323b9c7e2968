"""`make hopper`'s pipeline end to end, in a smoke variant (few transitions, 2 train_steps,
one adversarial and one likelihood method; tests/test_checkpoint.py trains all four).

The data sizes are conftest's hopper_train_ds (80 transitions per policy, 40-step episodes,
16 value episodes): the train split's MJX collection is then the same program as that
fixture's, which the persistent compilation cache holds once the fixture has run."""
import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from rl2s_jax.cli import main
from rl2s_jax.zoo.zoo import load_zoo, save_zoo


def test_hopper_pipeline_smoke(tmp_path, capsys):
    # the shipped zoo with 6 of its test policies (--zoo): the same training split (and its
    # compiled collection), a quarter of the test work
    shipped = load_zoo("hopper")
    small = dataclasses.replace(shipped, test_ids=shipped.test_ids[::3][:6])
    save_zoo(small, str(tmp_path / "zoo"))
    out = tmp_path / "hopper"
    args = ["pipeline", "--task", "hopper", "--profile", "cpu", "--out", str(out), "--steps",
            "2", "--eval-every", "1", "--transitions-per-policy", "80", "--value-episodes", "16",
            "--improve-iterations", "2", "--methods", "rl2s,bc", "--zoo", str(tmp_path / "zoo"),
            "--episode-length", "40", "--quiet"]
    assert main(args) == 0, capsys.readouterr().err
    text = capsys.readouterr().out
    for method in ("rl2s", "bc"):
        assert f"\n{method} " in text  # a row of the terminal table
        assert (out / method / "checkpoints").is_dir()
    report = json.loads((out / "report.json").read_text())
    assert set(report["methods"]) == {"rl2s", "bc"}
    # where it ran: CPU results move with the CPU, so the report names it
    assert report["machine"]["backend"] == "cpu" and report["machine"]["jax"] == jax.__version__
    assert f"with {report['machine']['cpu_isa']}" in (out / "report.md").read_text()
    for m in report["methods"].values():
        for k in ("avd", "mvd", "kendall_tau", "spearman", "ndcg@1", "ndcg@10", "regret@1",
                  "mpi", "api"):
            assert k in m
        assert m["mvd"] >= m["avd"] >= 0 and m["mpi"] <= m["api"]
    assert [r["step"] for r in report["curves"]["rl2s"]] == [1, 2]
    n_test = len(small.test_ids)
    assert len(report["evaluations"]["bc"]["vd"]) == n_test == 6  # the --zoo's test split
    # each test policy's 90% value interval, calibrated on the 17 training policies (issue 64)
    trust = report["evaluations"]["bc"]["trust"]
    assert len(report["evaluations"]["bc"]["interval"]) == n_test and "coverage" in trust
    assert trust["calibration"]["n_train"] == 17 and trust["calibration"]["optimistic"]
    assert "bc: 90% value intervals cover" in (out / "report.md").read_text()
    imp = report["evaluations"]["rl2s"]["improvement"]
    assert len(imp["I"]) == n_test and imp["mpi"] == min(imp["I"])
    np.testing.assert_allclose(imp["I"], (np.asarray(imp["c1"]) - imp["c0"])
                               / np.abs(imp["c0"]), rtol=1e-6)
    # the deployment guard by default: a kept start has C1 = C0 (paired), deployed ones
    # passed the members' margin; the terminal and report.md say which is which
    assert report["guard_margin"] == imp["guard_margin"] == 0.02
    for j, dep in enumerate(imp["deployed"]):
        if dep:
            assert imp["predicted_gain"][j] > 0.02
        else:
            assert imp["c1"][j] == imp["c0"][j] and imp["I"][j] == 0.0
    floor = imp["guard_floor"]  # the simulator's MVD on the training policies
    assert floor == pytest.approx(report["train_runs"]["rl2s"]["mvd_train"]) and floor > 0
    assert imp["guard_horizon"] == 40  # the real episodes' length (= the VD horizon here)
    assert imp["recipe"] == report["sizes"]["improve_recipe"] == {"branch_length": None,
                                                                  "uncertainty_penalty": 0.0}
    assert (f"Improvement in rl2s's simulator (guard margin 0.02, floor {floor:.3g}: every "
            "member's gain must exceed the simulator's MVD on the training policies)") in text
    for png in ("vd_curves.png", "vd_per_policy.png", "true_vs_sim.png", "improvement.png"):
        assert os.path.getsize(out / png) > 1000
    md = (out / "report.md").read_text()
    assert "| rl2s |" in md and "kendall_tau" in md
    assert "| predicted gain (every member at least) |" in md
    assert imp["iterations"] == 2 and ("Fine-tuned by SAC for 2 iterations per policy in whole "
                                       "episodes from the data's start states.") in md
    # a rerun with the same sizes reuses the data and the finished runs; its report replaces
    # the earlier one only with --force (refused at the door without it)
    rerun = [a if a != "2" or args[i - 1] != "--improve-iterations" else "0"
             for i, a in enumerate(args)]
    with pytest.raises(SystemExit):
        main([*rerun, "--no-guard"])
    assert "--force replaces them" in capsys.readouterr().err
    assert main([*rerun, "--no-guard", "--force"]) == 0
    assert "reusing" in capsys.readouterr().out
    assert json.loads((out / "report.json").read_text())["guard_margin"] is None
    # a training MVD measured at another horizon is no floor at the guard's: the pipeline
    # measures the simulator's MVD on the training policies at the real episodes' length
    from rl2s_jax.app.evaluation import evaluate_checkpoint
    from rl2s_jax.app.pipeline import PROFILES, improve_in_simulators
    ckpt, train = str(out / "rl2s" / "checkpoints"), str(out / "train.npz")
    sizes = {**PROFILES["cpu"], "improve_iterations": 2, "value_episodes": 16}
    imp = improve_in_simulators("hopper", str(out / "test.npz"), {"rl2s": ckpt}, sizes,
                                horizon=40, guard_episodes=4, train_path=train, log=lambda _: 0,
                                guard_floors={"rl2s": {"mvd": 1e-3, "horizon": 20,
                                                       "gamma": 0.999}},
                                guard_floor_scale=0.5)["rl2s"]   # the floor: 0.5 x the MVD
    on_train = evaluate_checkpoint(ckpt, train, n_episodes=4, horizon=40)
    assert imp["guard_floor"] == pytest.approx(0.5 * on_train["metrics"]["mvd"])
    assert imp["guard_floor"] > 0 and imp["guard_floor_scale"] == 0.5
    assert imp["guard_horizon"] == 40


def test_pipeline_sizes_take_the_fine_tuning_recipe_and_refuse_bad_input():
    from rl2s_jax.app.pipeline import PROFILES, pipeline_sizes
    from rl2s_jax.cli import build_parser

    def sizes(*flags):
        args = build_parser().parse_args(["pipeline", "--task", "hopper", *flags])
        return pipeline_sizes(args, "cpu")

    base = sizes()
    assert base["improve_recipe"] == PROFILES["cpu"]["improve_recipe"]
    assert base["sac"] == PROFILES["cpu"]["sac"]
    s = sizes("--branch-length", "25", "--uncertainty-penalty", "0.5", "--set", "kl_weight=0.1",
              "--set", "hidden=[32,32]", "--improve-iterations", "7")
    assert s["improve_recipe"] == {"branch_length": 25, "uncertainty_penalty": 0.5}
    assert s["sac"]["kl_weight"] == 0.1 and s["sac"]["hidden"] == (32, 32)
    assert s["sac"]["n_envs"] == PROFILES["cpu"]["sac"]["n_envs"] and s["improve_iterations"] == 7
    assert PROFILES["cpu"]["sac"].get("kl_weight") is None  # the profile is not mutated
    with pytest.raises(ValueError, match="sac-set|set: unknown SACConfig field"):
        sizes("--set", "kl_wieght=0.1")
    with pytest.raises(ValueError, match="uncertainty-penalty: expected a finite float >= 0"):
        sizes("--uncertainty-penalty", "-1")
    with pytest.raises(SystemExit):  # argparse: branch-length must be positive
        sizes("--branch-length", "0")


def test_pipeline_recipe_gives_the_defaults_and_flags_win():
    """`rl2s pipeline --recipe control` fine-tunes with the task's measured recipe (as `rl2s
    improve --recipe` and paper.py --improve-recipe do: ``recipe_settings``): its iterations,
    SAC fields, branches, penalty, guard margin and floor scale (Walker2d's 0); flags given
    win; without a recipe the floor scale is 1."""
    from rl2s_jax.app.improvement import guard_margin
    from rl2s_jax.app.pipeline import PROFILES, pipeline_sizes
    from rl2s_jax.cli import build_parser
    from rl2s_jax.improve.recipes import recipe_settings

    def parsed(task, *flags):
        return build_parser().parse_args(["pipeline", "--task", task, *flags])

    rs = recipe_settings("control", "walker2d")
    args = parsed("walker2d", "--recipe", "control")
    s = pipeline_sizes(args, "cpu")
    assert s["recipe"] == "control" and s["improve_iterations"] == rs["iterations"] == 4000
    assert s["sac"] == {**PROFILES["cpu"]["sac"], **rs["sac"]} and s["sac"]["n_envs"] == 128
    assert s["improve_recipe"] == {"branch_length": 100, "uncertainty_penalty": 1.0}
    assert s["guard_floor_scale"] == 0.0 and guard_margin(args) == rs["guard_margin"]
    assert pipeline_sizes(parsed("hopper", "--recipe", "control"), "cpu")[
        "guard_floor_scale"] == 1.0
    given = pipeline_sizes(parsed("walker2d", "--recipe", "control", "--improve-iterations", "7",
                                  "--set", "kl_weight=0.1", "--branch-length", "5",
                                  "--guard-floor-scale", "0.5"), "cpu")
    assert (given["improve_iterations"], given["sac"]["kl_weight"]) == (7, 0.1)
    assert given["improve_recipe"]["branch_length"] == 5 and given["guard_floor_scale"] == 0.5
    assert given["sac"]["n_envs"] == 128  # the recipe's, where no flag was given
    plain = pipeline_sizes(parsed("walker2d"), "cpu")
    assert plain["guard_floor_scale"] == 1.0 and "recipe" not in plain
    assert plain["improve_iterations"] == PROFILES["cpu"]["improve_iterations"]
    with pytest.raises(ValueError, match="guard-floor-scale: expected"):
        pipeline_sizes(parsed("walker2d", "--guard-floor-scale", "-1"), "cpu")
    with pytest.raises(SystemExit):  # argparse: no such recipe
        parsed("walker2d", "--recipe", "nope")


def test_improvement_text_names_the_floor_and_its_scale():
    """The report's improvement line says which floor the guard used: the training MVD, or K x
    it where --guard-floor-scale K was not 1; no floor, no clause."""
    from rl2s_jax.app.report import improvement_text

    def text(**guard):
        imp = {"guard_margin": 0.02, "deployed": [True], "I": [0.5], "mpi": 0.5, "api": 0.5,
               "predicted_gain": [0.3], "c0": [100.0], "c1": [150.0], **guard}
        return improvement_text({"rl2s": {"policy_names": ["p0"], "improvement": imp}})

    assert ("floor 40: every member's gain must exceed the simulator's MVD"
            in text(guard_floor=40.0, guard_floor_scale=1.0))
    assert ("floor 20: every member's gain must exceed 0.5 x the simulator's MVD"
            in text(guard_floor=20.0, guard_floor_scale=0.5))
    assert "floor" not in text(guard_floor=0.0, guard_floor_scale=0.0)
    # how the policies were fine-tuned, where the entry says (older reports do not)
    assert ("Fine-tuned by SAC for 4000 iterations per policy in 100-step branches from the "
            "data's states, reward minus 1 x the ensemble's disagreement." in text(
                guard_floor=0.0, iterations=4000,
                recipe={"branch_length": 100, "uncertainty_penalty": 1.0}))
    assert ("Fine-tuned by SAC for 300 iterations per policy in whole episodes from the data's "
            "start states." in text(guard_floor=0.0, iterations=300,
                                    recipe={"branch_length": None, "uncertainty_penalty": 0.0}))
    assert "Fine-tuned" not in text(guard_floor=0.0)
    assert "| p0 | deployed | +0.300 | 100.0 | 150.0 | +0.500 |" in text(guard_floor=0.0)
    # the predicted gains have no interval, and the report says why (issue 64); no guard: none
    from rl2s_jax.app.value_intervals import NO_INTERVAL
    assert f"Why no interval: {NO_INTERVAL['floor_guard']}." in text(guard_floor=0.0)
    assert "Why no interval" not in text(guard_floor=0.0, guard_margin=None)


def test_cpu_from_cpuinfo_names_the_model_and_the_widest_instruction_set():
    """report.cpu_from_cpuinfo: the first processor's model name and its widest vector ISA."""
    from rl2s_jax.app.report import cpu_from_cpuinfo
    text = ("processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse4_2 avx avx2 "
            "avx512f avx512bw\n\nprocessor\t: 1\nmodel name\t: other\nflags\t: fpu\n")
    assert cpu_from_cpuinfo(text) == {"cpu": "AMD EPYC", "cpu_isa": "AVX512"}
    assert cpu_from_cpuinfo(text.replace(" avx512f avx512bw", ""))["cpu_isa"] == "AVX2"
    assert cpu_from_cpuinfo("") == {"cpu": None, "cpu_isa": None}


def test_pipeline_keys_are_the_recorded_runs_keys():
    """pipeline_keys: per method its own SAC and guard keys, one measurement key for all, the
    same as the runs recorded so far drew (PRNGKey(seed + 10 + i), (seed + 30 + i),
    (seed + 20)), so that a script repeating one method's fine-tuning repeats it exactly."""
    from rl2s_jax.app.pipeline import pipeline_keys

    for seed, i in ((0, 0), (0, 3), (5, 1)):
        k = pipeline_keys(seed, i)
        for name, base in (("improve", 10 + i), ("measure", 20), ("guard", 30 + i)):
            np.testing.assert_array_equal(k[name], jax.random.PRNGKey(seed + base))
    assert not np.array_equal(pipeline_keys(0, 0)["improve"], pipeline_keys(0, 1)["improve"])
