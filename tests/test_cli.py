"""The `rl2s` command line: collect -> inspect round trip, and bad input refused."""

import jax
import numpy as np
import pytest

from rl2s_jax import cli
from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo import zoo as zoo_mod


@pytest.fixture(scope="module")
def pm_zoo(tmp_path_factory):
    d = tmp_path_factory.mktemp("zoo")
    params = pol.stack_params([pol.init_policy(k, 2, 1) for k in jax.random.split(
        jax.random.PRNGKey(0), 4)])
    zoo_mod.save_zoo(zoo_mod.Zoo(task="pointmass", params=params, returns=np.zeros(4),
                         return_se=np.zeros(4), origins=[{}] * 4, train_ids=[0, 1],
                         test_ids=[2, 3]), str(d))
    return str(d)


def test_collect_then_inspect(pm_zoo, tmp_path, capsys):
    out = tmp_path / "d.npz"
    rc = cli.main(["collect", "--task", "pointmass", "--split", "test", "--zoo", pm_zoo,
                   "--transitions-per-policy", "120", "--value-episodes", "2",
                   "--out", str(out)])
    assert rc == 0 and out.exists()
    capsys.readouterr()
    assert cli.main(["inspect", "--data", str(out)]) == 0
    text = capsys.readouterr().out
    assert "pointmass" in text and "240" in text  # 2 test policies x 120 transitions
    assert "pointmass-002" in text and "pointmass-003" in text


def test_inspect_refuses_bad_file(pm_zoo, tmp_path, capsys):
    good = tmp_path / "good.npz"
    assert cli.main(["collect", "--task", "pointmass", "--zoo", pm_zoo, "--value-episodes",
                     "0", "--transitions-per-policy", "30", "--out", str(good)]) == 0
    with np.load(good) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["observations"] = arrays.pop("obs")
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    capsys.readouterr()
    assert cli.main(["inspect", "--data", str(bad)]) != 0
    err = capsys.readouterr().err
    assert "observations" in err and "obs" in err
    assert cli.main(["inspect", "--data", str(tmp_path / "missing.npz")]) != 0


def test_collect_refuses_bad_arguments(pm_zoo, tmp_path):
    with pytest.raises(SystemExit):
        cli.main(["collect", "--task", "pointmass", "--transitions-per-policy", "0",
                  "--out", str(tmp_path / "x.npz")])
    with pytest.raises(SystemExit):
        cli.main(["collect", "--task", "nope", "--transitions-per-policy", "5",
                  "--out", str(tmp_path / "x.npz")])
    # a zoo of another task is refused with a clear message, before any work
    assert cli.main(["collect", "--task", "pointmass", "--zoo", "hopper",
                     "--transitions-per-policy", "5", "--out", str(tmp_path / "x.npz")]) == 2
    assert not (tmp_path / "x.npz").exists()
