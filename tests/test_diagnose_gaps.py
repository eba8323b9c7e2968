"""diagnose.gaps: error breakdowns find planted structure; plots and markdown are written."""
import json
import os

import numpy as np
import pytest

from rl2s_jax.data import episodes as ep_mod
from rl2s_jax.data.dataset import Dataset
from rl2s_jax.diagnose.gap_views import VALUES_NO_INTERVAL, gaps_markdown, plot_gaps
from rl2s_jax.diagnose.gaps import error_breakdown

OBS, A, P, L, E = 4, 2, 4, 50, 40  # obs size, action size, policies, episode length, episodes


@pytest.fixture(scope="module")
def eps():
    rng = np.random.default_rng(0)
    n = E * L
    obs = rng.normal(size=(n, OBS)).astype(np.float32)
    arrays = {
        "obs": obs,
        "action": rng.uniform(-1, 1, size=(n, A)).astype(np.float32),
        "next_obs": (obs + 0.1 * rng.normal(size=(n, OBS))).astype(np.float32),
        "reward": rng.normal(size=n).astype(np.float32),
        "done": np.zeros(n, bool),
        "truncated": np.tile(np.arange(L) == L - 1, E),
        "policy_id": np.repeat(np.arange(E) % P, L).astype(np.int32),
        "episode_id": np.repeat(np.arange(E), L).astype(np.int32),
        "t": np.tile(np.arange(L), E).astype(np.int32),
    }
    meta = {"task": None, "obs_size": OBS, "action_size": A, "n_policies": P, "gamma": 0.99,
            "episode_length": L, "policy_names": [f"pi{i}" for i in range(P)], "source": {}}
    return ep_mod.from_dataset(Dataset.from_arrays(arrays, meta))


@pytest.fixture(scope="module")
def rows(eps):
    return eps.rows(np.flatnonzero(np.arange(E) % 8 < 4))  # half the episodes, all 4 policies


def _base(rows, scale=0.1, seed=1):
    rng = np.random.default_rng(seed)
    return scale * rng.normal(size=(rows.size, OBS)), np.full((rows.size, OBS), scale)


def test_error_on_one_dim(eps, rows):
    resid, std = _base(rows, scale=0.01)
    resid[:, 2] += np.random.default_rng(2).normal(size=rows.size)
    b = error_breakdown(eps, rows, resid, std, obs_names=["x", "y", "v", "w"])
    shares = [d["share"] for d in b["by_dim"]]
    assert shares[2] > 0.99 and abs(sum(shares) - 1) < 1e-9
    assert any("obs 2 (v) carries" in s for s in b["summary"])
    # the rmse numbers against NumPy
    np.testing.assert_allclose([d["rmse"] for d in b["by_dim"]],
                               np.sqrt((resid ** 2).mean(axis=0)), rtol=1e-12)
    np.testing.assert_allclose(b["overall"]["rmse"], np.sqrt((resid ** 2).mean()), rtol=1e-12)
    np.testing.assert_allclose([d["bias"] for d in b["by_dim"]], resid.mean(axis=0))
    np.testing.assert_allclose([d["mean_z2"] for d in b["by_dim"]],
                               ((resid / std) ** 2).mean(axis=0))
    json.dumps(b, allow_nan=False)  # JSON-able, no NaN


def test_error_growing_with_t(eps, rows):
    resid, std = _base(rows)
    resid *= (1 + eps.t[rows] / 5.0)[:, None]
    b = error_breakdown(eps, rows, resid, std, n_bins=5)
    bins = b["by_step"]["bins"]
    assert len(bins) == 5 and bins[0]["t_lo"] == 0 and bins[-1]["t_hi"] == L - 1
    rm = [s["rmse"] for s in bins]
    assert all(np.diff(rm) > 0)
    assert sum(s["n"] for s in bins) == rows.size
    t = eps.t[rows]
    for s in bins:  # each bin's rmse against NumPy
        m = (t >= s["t_lo"]) & (t <= s["t_hi"])
        assert s["n"] == m.sum()
        np.testing.assert_allclose(s["rmse"], np.sqrt((resid[m] ** 2).mean()), rtol=1e-12)
    line = [s for s in b["summary"] if "rises with step" in s]
    assert line and f"steps {bins[-1]['t_lo']}-{bins[-1]['t_hi']}" in line[0]


def test_error_in_one_region(eps, rows):
    resid, std = _base(rows, scale=0.05)
    x0 = eps.obs[rows, 0]
    hot = x0 > np.quantile(x0, 0.8)
    resid[hot] += np.random.default_rng(3).normal(size=(hot.sum(), OBS))
    b = error_breakdown(eps, rows, resid, std, n_bins=5)
    w = b["by_region"]["worst"][0]
    assert (w["kind"], w["dim"], w["bin"]) == ("obs", 0, 4)
    assert w["lo"] == pytest.approx(np.quantile(x0, 0.8)) and w["ratio"] > 2
    assert w["n_rows"] == hot.sum()
    assert len(b["by_region"]["worst"]) == 5
    assert len(b["by_region"]["variables"]) == OBS + A
    v0 = b["by_region"]["variables"][0]
    assert v0["ratio"][4] == max(v0["ratio"]) and max(v0["ratio"][:4]) < 0.5
    assert any(s.startswith("worst region: obs 0 in") and "top quantile" in s
               for s in b["summary"])


def test_policy_with_huge_residuals(eps, rows):
    resid, std = _base(rows)
    bad = eps.policy[rows] == 3
    resid[bad] *= 30
    vd = {"policy": [0, 1, 2, 3], "true": [10.0, 20.0, 30.0, 40.0],
          "sim": [12.0, 19.0, 33.0, 160.3]}
    b = error_breakdown(eps, rows, resid, std, vd=vd, policy_names=[f"pi{i}" for i in range(P)])
    pols = b["by_policy"]
    assert pols[0]["policy"] == 3 and pols[0]["name"] == "policy 3 (pi3)"
    assert pols[0]["abs_vd"] == pytest.approx(120.3)
    np.testing.assert_allclose(pols[0]["rmse"], np.sqrt((resid[bad] ** 2).mean()))
    z2 = ((resid[bad] / std[bad]) ** 2).sum(1)
    nll = (0.5 * z2 + np.log(std[bad]).sum(1)).mean()
    np.testing.assert_allclose(pols[0]["nll"], nll)
    assert sum(p["n"] for p in pols) == rows.size
    assert any(s.startswith("policy 3 (pi3) has the largest one-step rmse") for s in b["summary"])
    assert any("largest |VD| 120" in s and "others median 2" in s for s in b["summary"])
    assert b["vd"]["matched_in_rows"] == [0, 1, 2, 3]


def test_calibration(eps, rows):
    rng = np.random.default_rng(4)
    std = rng.uniform(0.1, 2.0, size=(rows.size, OBS))
    resid = std * rng.normal(size=std.shape)
    b = error_breakdown(eps, rows, resid, std)
    n = rows.size  # mean of n chi2(1) draws: sd sqrt(2 / n)
    for d in b["by_dim"]:
        assert abs(d["mean_z2"] - 1) < 4 * np.sqrt(2 / n)
    assert abs(b["overall"]["mean_z2"] - 1) < 4 * np.sqrt(2 / (n * OBS))
    assert "about calibrated" in b["summary"][0]
    # over-confident: std half of the true noise -> z^2 ~ 4
    b2 = error_breakdown(eps, rows, resid, std / 2)
    assert b2["overall"]["mean_z2"] == pytest.approx(4, rel=0.1)
    assert "over-confident" in b2["summary"][0]


def test_kstep(eps, rows):
    resid, std = _base(rows)
    ks = np.array([[0.1 * k for k in range(1, 21)], [0.1 * k + 0.02 for k in range(1, 21)]])
    b = error_breakdown(eps, rows, resid, std, kstep=ks)
    k = b["kstep"]
    assert k["k"] == list(range(1, 21)) and k["n_seeds"] == 2
    np.testing.assert_allclose(k["rmse"], ks.mean(0))
    np.testing.assert_allclose(k["std"], ks.std(0))
    assert k["growth"] == pytest.approx(ks.mean(0)[-1] / ks.mean(0)[0])
    assert any(s.startswith("k-step error grows") and "k=20" in s for s in b["summary"])
    b1 = error_breakdown(eps, rows, resid, std, kstep=ks[0])
    assert b1["kstep"]["std"] is None and b1["kstep"]["growth"] == pytest.approx(20)


def test_plots_and_markdown(eps, rows, tmp_path):
    import matplotlib.image as mpimg

    resid, std = _base(rows)
    vd = {"policy": ["pi0", "pi1", "pi2", "pi3"], "true": [1.0, 2, 3, 4],
          "sim": [1.5, 2, 2.5, 9]}
    b = error_breakdown(eps, rows, resid, std, vd=vd, kstep=np.linspace(0.1, 1, 10)[None] *
                        np.array([[1.0], [1.1], [0.9]]),
                        policy_names=[f"pi{i}" for i in range(P)])
    assert b["by_policy"][0].get("abs_vd") is not None  # matched by name
    files = plot_gaps(str(tmp_path), b, prefix="g")
    assert [os.path.basename(f) for f in files] == ["g_one_step.png", "g_rollout.png"]
    for f in files:
        assert os.path.getsize(f) > 10_000
        img = mpimg.imread(f)
        assert img.ndim == 3 and img.shape[0] > 300
    md = gaps_markdown(b, files)
    assert "![g_one_step.png](g_one_step.png)" in md and "| obs 0 |" in md
    assert "\\|VD\\|" in md and all(f"- {s}" in md for s in b["summary"])
    assert VALUES_NO_INTERVAL in md  # the simulated values say why they have no interval
    # without kstep / vd: only the one-step figure
    b2 = error_breakdown(eps, rows, resid, std)
    files2 = plot_gaps(str(tmp_path / "sub"), b2)
    assert [os.path.basename(f) for f in files2] == ["gaps_one_step.png"]
    assert "g_rollout" not in gaps_markdown(b2, files2)
    assert VALUES_NO_INTERVAL not in gaps_markdown(b2, files2)  # no values, no note


def test_bad_input(eps, rows):
    resid, std = _base(rows)
    n = rows.size
    with pytest.raises(ValueError, match="resid: expected shape"):
        error_breakdown(eps, rows, resid[:, :3], std)
    with pytest.raises(ValueError, match="std: expected shape"):
        error_breakdown(eps, rows, resid, std[:-1])
    with pytest.raises(ValueError, match="rows: expected indices"):
        error_breakdown(eps, rows + eps.n, resid, std)
    with pytest.raises(ValueError, match="rows: expected a non-empty 1-D integer"):
        error_breakdown(eps, rows.astype(float), resid, std)
    r = resid.copy()
    r[7, 1] = np.nan
    with pytest.raises(ValueError, match=f"resid: 1 of {n} rows hold NaN.*dataset row "
                                         f"{rows[7]}"):
        error_breakdown(eps, rows, r, std)
    with pytest.raises(ValueError, match="std: expected predicted stds > 0"):
        error_breakdown(eps, rows, resid, np.zeros_like(std))
    with pytest.raises(ValueError, match="kstep: expected shape"):
        error_breakdown(eps, rows, resid, std, kstep=np.ones((2, 3, 4)))
    with pytest.raises(ValueError, match=r"vd\['sim'\]: expected shape \[P\] = \[2\]"):
        error_breakdown(eps, rows, resid, std, vd={"policy": [0, 1], "true": [1, 2],
                                                   "sim": [1]})
    with pytest.raises(ValueError, match="obs_names: expected a list of 4"):
        error_breakdown(eps, rows, resid, std, obs_names=["a"])
    with pytest.raises(ValueError, match="eps: expected an Episodes"):
        error_breakdown({}, rows, resid, std)
