"""Checked inputs (issue 65, item 3): a data file's meta.task that is not registered is refused
unless --no-task; a policy file is checked against the data it claims to have collected (the
logged actions' likelihood under each of its policies, zoo/likelihood.py)."""
import types
import warnings

import numpy as np
import pytest
from scipy.special import log_ndtr

from rl2s_jax import cli
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.policy import policy as pol
from rl2s_jax.zoo.likelihood import (
    PolicyFileWarning,
    policy_file_mismatch,
    policy_log_likelihoods,
)
from rl2s_jax.zoo.zoo import policies_for


@pytest.fixture(scope="module")
def misspelt(pm_files, tmp_path_factory):
    """pm_files' train data with meta.task 'pointmas' (misspelt)."""
    ds = load_dataset(pm_files["train"])
    path = str(tmp_path_factory.mktemp("misspelt") / "train.npz")
    save_dataset(path, ds.replace(meta={**ds.meta, "task": "pointmas"}))
    return path


def test_an_unregistered_task_name_is_refused_naming_the_nearest(misspelt, tmp_path, capsys):
    out = tmp_path / "run"
    assert cli.main(["train", "--data", misspelt, "--method", "bc", "--steps", "1", "--out",
                     str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "data: meta.task 'pointmas' is not a registered task (did you mean 'pointmass'?)" \
        in err and "registered: hopper, walker2d" in err and "--no-task" in err
    assert not out.exists()  # refused before any work


def test_no_task_learns_reward_and_termination_from_the_data(misspelt):
    from rl2s_jax.app.training import make_config
    from rl2s_jax.envs.tasks import data_task

    cfg = make_config(load_dataset(misspelt), "bc", "cpu", no_task=True)
    assert (cfg.task, cfg.outcome.reward, cfg.outcome.termination) == ("pointmas", "learned",
                                                                        "hazard")
    assert data_task(None) is None and data_task("pointmass") == "pointmass"
    with pytest.raises(ValueError, match="^data: meta.task 'zzz' is not a registered task; "):
        data_task("zzz")  # nothing near: no did-you-mean


def test_import_refuses_an_unregistered_task_before_reading(tmp_path, capsys):
    out = tmp_path / "x.npz"
    assert cli.main(["import", "--minari", str(tmp_path / "absent"), "--out", str(out),
                     "--task", "walker"]) == 2
    err = capsys.readouterr().err
    assert "task: meta.task 'walker' is not a registered task (did you mean 'walker2d'?)" \
        in err and "leave --task out" in err and not out.exists()


def _np_loglik(params, k, obs, action):
    """log pi_k(action | obs) in NumPy: the squashed Gaussian of policy.sample_action, an
    action at the box's edge (|a| > 1 - 1e-5) censored: P(pre-tanh action beyond the edge)."""
    p = {key: np.asarray(v, np.float64)[k] for key, v in params.items() if key != "layers"}
    x = np.clip((obs - p["obs_mean"]) / p["obs_std"], -10, 10)
    layers = params["layers"]
    for i, layer in enumerate(layers):
        x = x @ np.asarray(layer["w"], np.float64)[k] + np.asarray(layer["b"], np.float64)[k]
        if i < len(layers) - 1:
            x = x / (1 + np.exp(-x))  # swish
    loc, raw_scale = np.split(x, 2, axis=-1)
    scale = np.logaddexp(0, raw_scale) + pol.MIN_SCALE
    edge = np.abs(action) > 1 - 1e-5
    raw = np.arctanh(np.clip(action, -1 + 1e-5, 1 - 1e-5))
    inside = (-0.5 * ((raw - loc) / scale) ** 2 - np.log(scale) - 0.5 * np.log(2 * np.pi)
              - np.log(1 - np.tanh(raw) ** 2))
    beyond = log_ndtr(np.sign(action) * (loc - raw) / scale)
    return np.sum(np.where(edge, beyond, inside), -1)


def test_policy_log_likelihoods_against_numpy(pm_files):
    real = load_dataset(pm_files["train"])
    params = policies_for(real)
    action = np.asarray(real.action, np.float64).copy()
    action[::7] = np.sign(action[::7])  # saturated (float32 tanh gives +-1): censored rows
    ds = types.SimpleNamespace(obs=np.asarray(real.obs), action=action.astype(np.float32),
                               policy_id=np.asarray(real.policy_id),
                               n_transitions=real.n_transitions, n_policies=real.n_policies,
                               action_size=real.action_size)
    r = policy_log_likelihoods(ds, params)
    obs, pid = np.asarray(ds.obs, np.float64), ds.policy_id
    want = np.array([[_np_loglik(params, k, obs[pid == p], action[pid == p]).mean()
                      for k in range(ds.n_policies)] for p in range(ds.n_policies)])
    np.testing.assert_allclose(r["loglik"], want, rtol=1e-3, atol=1e-3)
    assert r["rows"].tolist() == np.bincount(pid).tolist()
    edge = np.abs(action[:, 0]) > 1 - 1e-5
    uniform = np.where(edge, np.log(1e-5 / 2), -np.log(2))
    np.testing.assert_allclose(r["uniform"], [uniform[pid == p].mean()
                                              for p in range(ds.n_policies)], rtol=1e-5)
    # every policy explains its own rows best: the premise of the check
    assert (r["loglik"].argmax(1) == np.arange(ds.n_policies)).all()


def test_the_right_file_passes_silently_and_a_permuted_one_warns(pm_files, tmp_path):
    ds = load_dataset(pm_files["train"])
    params, names = policies_for(ds), list(ds.meta["policy_names"])
    right, permuted = tmp_path / "right.npz", tmp_path / "permuted.npz"
    pol.save_policies(right, params, names)
    pol.save_policies(permuted, pol.index_params(params, np.array([1, 2, 0])), names)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policies_for(ds, policy_file=str(right))
    with pytest.warns(PolicyFileWarning) as got:
        policies_for(ds, policy_file=str(permuted))
    (w,) = got
    line = str(w.message)
    assert line.startswith(f"policy-file: {permuted}: 3 of 3 policies do not explain")
    assert f"{names[0]} (better explained by {names[2]})" in line and "\n" not in line
    # one policy, wrong: the reference is a uniform action
    rows = np.asarray(ds.policy_id) == 0
    one = types.SimpleNamespace(  # what the check reads of a Dataset: policy 0's rows
        obs=np.asarray(ds.obs)[rows], action=np.asarray(ds.action)[rows],
        policy_id=np.zeros(rows.sum(), np.int32), n_transitions=int(rows.sum()),
        n_policies=1, action_size=ds.action_size)
    assert policy_file_mismatch(one, pol.index_params(params, np.array([0]))) is None
    assert "worse than a uniform random action" in policy_file_mismatch(
        one, pol.index_params(params, np.array([2])))


def test_the_command_line_prints_the_warning_as_one_line(pm_files, monkeypatch, capsys):
    def warns(spec):
        warnings.warn("policy-file: f.npz: 1 of 3 policies do not explain ...",
                      PolicyFileWarning, stacklevel=1)
        return 0
    monkeypatch.setattr("rl2s_jax.app.datasets.run_inspect", warns)
    assert cli.main(["inspect", "--data", pm_files["train"]]) == 0
    err = capsys.readouterr().err
    assert err == "rl2s inspect: warning: policy-file: f.npz: 1 of 3 policies do not explain ...\n"
