"""`rl2s evaluate` with several `--ckpt` (independently trained simulators of one task): each
scored alike, and per policy how far they disagree (app/evaluation.simulator_agreement), the
refusals before any work, and one `--ckpt` giving the report it always gave."""
import contextlib
import io
import json
import os
import shutil

import numpy as np
import pytest

from rl2s_jax import cli
from rl2s_jax.app import evaluation as ev
from rl2s_jax.train.config import TrainConfig

QUICK = ["--episodes", "2", "--horizon", "10", "--bootstrap", "0"]
# The top-level keys of one checkpoint's report (its JSON before several --ckpt existed).
SINGLE_KEYS = {"true_value", "sim_value", "sim_length", "sim_return_sd", "vd", "horizon", "gamma",
               "n_episodes", "policy_names", "metrics", "heldout_nll", "heldout_mse",
               "one_step_rows", "checkpoint", "step", "method", "data", "seed", "backend",
               "horizon_source", "episodes_source", "setting", "true_value_source"}


def _checkpoint(train_path: str, path, seed: int) -> str:
    """An initialised BC simulator of pm_files' train data (as conftest's pm_checkpoint),
    its weights drawn with ``seed``: another 'training seed' of the same simulator."""
    import jax

    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.train.checkpoint import Checkpointer
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init
    from rl2s_jax.zoo.zoo import policies_for

    ds = load_dataset(train_path)
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=50)
    data = make_train_data(ds, policies_for(ds), cfg)
    ck = Checkpointer(path)
    ck.save(init(jax.random.PRNGKey(seed), cfg, data),
            {"data": {"obs_size": ds.obs_size, "action_size": ds.action_size}})
    ck.close()
    return str(path)


def _with_config(src: str, dst, changes: dict) -> str:
    """A copy of checkpoint ``src`` whose saved config has ``changes`` (``TrainConfig.override``'s
    names; only its JSON meta is edited: enough for the refusals, which read nothing else)."""
    shutil.copytree(src, dst)
    (meta,) = [os.path.join(r, "metadata") for r, _, fs in os.walk(dst)
               if os.path.basename(r) == "meta" and "metadata" in fs]
    with open(meta) as f:
        m = json.load(f)
    m["config"] = TrainConfig.from_saved(m["config"]).override(changes).to_dict()
    with open(meta, "w") as f:
        json.dump(m, f)
    return str(dst)


@pytest.fixture(scope="module")
def seeds(pm_files, pm_checkpoint, tmp_path_factory):
    """Two more seeds beside pm_checkpoint, the three runs' two-checkpoint JSON report and
    stdout, and pm_checkpoint's single report."""
    root = tmp_path_factory.mktemp("seeds")
    ckpts = [pm_checkpoint, _checkpoint(pm_files["train"], root / "s1" / "checkpoints", 1),
             _checkpoint(pm_files["train"], root / "s2" / "checkpoints", 2)]
    out = {"ckpts": ckpts, "data": pm_files["test"], "root": root}
    path = root / "three.json"
    argv = ["evaluate", "--data", pm_files["test"], *QUICK, "--json", str(path)]
    for c in ckpts:
        argv += ["--ckpt", c]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert cli.main(argv) == 0
        single = root / "single.json"
        assert cli.main(["evaluate", "--ckpt", ckpts[1], "--data", pm_files["test"], *QUICK,
                         "--json", str(single)]) == 0
    out.update(stdout=buf.getvalue(), report=json.loads(path.read_text()),
               single=json.loads(single.read_text()))
    return out


def test_agreement_worked_by_hand():
    """3 simulators, 3 policies. a: 10, 12, 14 (mean 12, std 2); b: 0, 0, 3 (mean 1, std
    sqrt 3); c: 5, 5, 5 (std 0) with true 9: the shared bias of 4 the spread cannot see, and
    the largest error. Mean |error|: a 5/3, b 1, c 4; spread ranks a2 b1 c0 against error
    ranks a1 b0 c2: d = 1, 1, -2, rho = 1 - 6 * 6 / (3 * 8) = -0.5."""
    sims = np.array([[10.0, 0.0, 5.0], [12.0, 0.0, 5.0], [14.0, 3.0, 5.0]])
    truth = np.array([11.0, 0.0, 9.0])
    a = ev.simulator_agreement(sims, truth, ["a", "b", "c"], top_k=2)
    p = {q["name"]: q for q in a["policies"]}
    assert [p[n]["mean"] for n in "abc"] == pytest.approx([12.0, 1.0, 5.0])
    assert [p[n]["spread"] for n in "abc"] == pytest.approx([2.0, np.sqrt(3.0), 0.0])
    assert [p[n]["spread"] for n in "abc"] == pytest.approx(list(sims.std(0, ddof=1)))
    assert [(p[n]["min"], p[n]["max"]) for n in "abc"] == [(10, 14), (0, 3), (5, 5)]
    assert [p[n]["spread_rank"] for n in "abc"] == [1, 2, 3]
    assert a["most_disputed"] == ["a", "b"] and a["n_simulators"] == 3
    assert p["a"]["abs_error"] == [1.0, 1.0, 3.0] and p["c"]["abs_error"] == [4.0] * 3
    assert [p[n]["mean_abs_error"] for n in "abc"] == pytest.approx([5 / 3, 1.0, 4.0])
    assert [p[n]["true_value"] for n in "abc"] == [11.0, 0.0, 9.0]
    ranks = [np.argsort(np.argsort(x)) for x in (sims.std(0, ddof=1),
                                                 np.abs(sims - truth).mean(0))]
    assert a["spearman_spread_error"] == pytest.approx(-0.5)
    assert a["spearman_spread_error"] == pytest.approx(np.corrcoef(*ranks)[0, 1])
    assert a["worst"] == "c" and a["worst_rank"] == 3
    assert a["worst_per_simulator"] == [{"policy": "c", "spread_rank": 3}] * 3

    bare = ev.simulator_agreement(sims, None, ["a", "b", "c"])
    assert bare["spearman_spread_error"] is None and bare["worst"] is None
    assert "abs_error" not in bare["policies"][0] and bare["most_disputed"] == ["a", "b", "c"]
    tie = ev.simulator_agreement([[0.0, 1.0, 0.0], [2.0, 3.0, 0.0]])  # a and b: std sqrt 2
    assert [q["spread_rank"] for q in tie["policies"]] == [1, 1, 3]
    with pytest.raises(ValueError, match="sim_values"):
        ev.simulator_agreement([[1.0, 2.0]])


def test_two_or_more_checkpoints_json_and_table(seeds):
    r, a = seeds["report"], seeds["report"]["agreement"]
    assert [c["checkpoint"] for c in r["checkpoints"]] == seeds["ckpts"]
    assert all(set(c) == SINGLE_KEYS for c in r["checkpoints"])
    sims = np.array([c["sim_value"] for c in r["checkpoints"]])
    truth = np.array(r["checkpoints"][0]["true_value"])
    assert all(c["true_value"] == list(truth) for c in r["checkpoints"])
    assert {(c["horizon"], c["n_episodes"]) for c in r["checkpoints"]} == {(10, 2)}
    assert a["n_simulators"] == 3 and len(a["policies"]) == 3 == len(a["most_disputed"])
    spread = sims.std(0, ddof=1)
    assert spread.min() > 0  # three seeds of an untrained simulator do disagree
    np.testing.assert_allclose([q["spread"] for q in a["policies"]], spread)
    np.testing.assert_allclose([q["mean_abs_error"] for q in a["policies"]],
                               np.abs(sims - truth).mean(0))
    names = r["checkpoints"][0]["policy_names"]
    assert a["most_disputed"] == [names[i] for i in np.argsort(-spread)]
    # The same checkpoint alone scores as it does among the three (same data, seed, settings).
    assert seeds["single"]["sim_value"] == r["checkpoints"][1]["sim_value"]
    out = seeds["stdout"]
    assert "3 simulators on" in out and "spread" in out and "mean |err|" in out
    assert "cannot flag an error they all share" in out
    rows = [ln.split()[0] for ln in out.splitlines() if ln.split()[:1] and ln.split()[0] in names]
    assert rows[:3] == a["most_disputed"]  # the table: the most disputed first


def test_one_ckpt_gives_the_old_report(seeds):
    # and "trust" (value intervals, issue 64): skipped, these checkpoints name no training data
    assert set(seeds["single"]) == SINGLE_KEYS | {"trust"}
    assert "no calibration data" in seeds["single"]["trust"]["skipped"]
    assert seeds["single"]["checkpoint"] == seeds["ckpts"][1]


def test_refused_before_any_work(seeds, monkeypatch, tmp_path, capsys):
    def no_work(*a, **k):
        raise AssertionError("evaluated before refusing")
    monkeypatch.setattr(ev, "evaluate_checkpoint", no_work)
    c0, c1 = seeds["ckpts"][:2]
    hopper = _with_config(c1, tmp_path / "hopper", {"task": "hopper"})
    longer = _with_config(c1, tmp_path / "longer", {"vd.horizon": 30, "vd.episodes": 6})

    def refused(*extra):
        argv = ["evaluate", "--data", seeds["data"], "--bootstrap", "0", *extra]
        assert cli.main(argv) == 2
        return capsys.readouterr().err

    err = refused("--ckpt", c0, "--ckpt", hopper)
    assert "ckpt:" in err and "is task 'pointmass' but" in err and "models 'hopper'" in err
    err = refused("--ckpt", c0, "--ckpt", c0 + "/")
    assert "ckpt:" in err and "given twice" in err
    err = refused("--ckpt", c0, "--ckpt", c1, "--step", "0")
    assert "step:" in err and "ambiguous" in err
    err = refused("--ckpt", c0, "--ckpt", c1, "--oracle")
    assert "ckpt:" in err and "--oracle" in err
    err = refused("--ckpt", c0, "--ckpt", longer)
    assert "horizon:" in err and "pass --horizon" in err
    # episodes are the one setting's, not each checkpoint's vd.episodes: a horizon agrees them
    assert len(ev.check_checkpoints([c0, longer], seeds["data"], None, 10)) == 2
