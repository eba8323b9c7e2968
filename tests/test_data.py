"""Dataset file format, validation (every kind of bad input), summaries and selection."""

import hashlib
import json
import sys
import types

import jax
import numpy as np
import pytest

from rl2s_jax.data.dataset import (
    VALUE_FIELDS,
    Dataset,
    DatasetError,
    concat_datasets,
    load_dataset,
    save_dataset,
    validate_dataset,
)
from rl2s_jax.data.summary import dataset_summary, episode_returns


def make_fake_dataset(n_policies=3, episodes_per_policy=3, obs_size=4, action_size=2,
                      episode_length=8, with_values=True, open_last=True, seed=0, task=None):
    """Episodes of random length in [2, episode_length], round-robin over policies; an episode
    of full length ends truncated, a shorter one done, and each policy's last one is left open
    when ``open_last``. Episode ids start at 100 (ids are labels, not indices)."""
    rng = np.random.default_rng(seed)
    cols = {k: [] for k in ("policy_id", "episode_id", "t", "done", "truncated")}
    ep = 100
    for e in range(episodes_per_policy):
        for p in range(n_policies):
            full = rng.random() < 0.3
            length = episode_length if full else int(rng.integers(2, episode_length))
            is_open = open_last and e == episodes_per_policy - 1
            cols["policy_id"].append(np.full(length, p))
            cols["episode_id"].append(np.full(length, ep))
            cols["t"].append(np.arange(length))
            end = np.zeros(length, bool)
            end[-1] = not is_open
            cols["done"].append(end & (not full))
            cols["truncated"].append(end & full)
            ep += 1
    c = {k: np.concatenate(v) for k, v in cols.items()}
    n = len(c["t"])
    fields = dict(
        obs=rng.normal(size=(n, obs_size)).astype(np.float32),
        action=rng.uniform(-1, 1, size=(n, action_size)).astype(np.float32),
        next_obs=rng.normal(size=(n, obs_size)).astype(np.float32),
        reward=rng.normal(size=n).astype(np.float32),
        done=c["done"], truncated=c["truncated"],
        policy_id=c["policy_id"].astype(np.int32), episode_id=c["episode_id"].astype(np.int32),
        t=c["t"].astype(np.int32),
    )
    if with_values:
        fields.update(
            value=rng.normal(10, 1, n_policies).astype(np.float32),
            value_se=rng.uniform(0, 1, n_policies).astype(np.float32),
            value_discounted=rng.normal(5, 1, n_policies).astype(np.float32),
            value_discounted_se=rng.uniform(0, 1, n_policies).astype(np.float32),
        )
    meta = dict(task=task, obs_size=obs_size, action_size=action_size, n_policies=n_policies,
                gamma=0.99 if with_values else None, episode_length=episode_length,
                policy_names=[f"pi_{p}" for p in range(n_policies)],
                source={"collector": "fake", "seed": seed})
    return Dataset(**fields, meta=meta)


def _write_raw(path, arrays, meta, format_version=1):
    """Write an npz bypassing save_dataset's validation (to produce bad files)."""
    out = dict(arrays)
    if meta is not None:
        out["meta"] = np.array(meta if isinstance(meta, str) else json.dumps(meta))
    if format_version is not None:
        out["format_version"] = np.array(format_version)
    with open(path, "wb") as f:
        np.savez_compressed(f, **out)


def _digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def _ep_rows(ds, k):
    """Row indices of the k-th episode (in row order)."""
    ep = np.asarray(ds.episode_id)
    starts = np.flatnonzero(np.r_[True, ep[1:] != ep[:-1]])
    ends = np.r_[starts[1:], len(ep)]
    return np.arange(starts[k], ends[k])


def test_fake_dataset_is_valid():
    ds = make_fake_dataset()
    validate_dataset(ds)
    validate_dataset(ds.arrays(), ds.meta)
    assert ds.n_policies == 3 and ds.obs_size == 4 and ds.action_size == 2 and ds.has_values
    assert ds.n_transitions == len(ds.reward)


@pytest.mark.parametrize("with_values", [True, False])
def test_round_trip_is_bit_identical(tmp_path, with_values):
    ds = make_fake_dataset(with_values=with_values)
    path = save_dataset(tmp_path / "d.npz", ds)
    with np.load(path) as z:
        keys = set(z.files)
        assert int(z["format_version"]) == 1 and z["meta"].shape == ()
    assert ("value" in keys) == with_values and all((k in keys) == with_values
                                                    for k in VALUE_FIELDS)
    back = load_dataset(path)
    assert back.meta == ds.meta and back.has_values == with_values
    a, b = ds.arrays(), back.arrays()
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape
        assert a[k].tobytes() == b[k].tobytes(), k
    if not with_values:
        assert all(getattr(back, k) is None for k in VALUE_FIELDS)


def test_dataset_is_a_pytree_with_static_meta():
    ds = make_fake_dataset()
    leaves = jax.tree.leaves(ds)
    assert len(leaves) == 13 and all(hasattr(x, "shape") for x in leaves)
    total = jax.jit(lambda d: d.reward.sum())(ds)
    np.testing.assert_allclose(total, ds.reward.sum(), rtol=1e-5)


def test_int64_ids_are_accepted_and_narrowed(tmp_path):
    ds = make_fake_dataset()
    a = ds.arrays()
    for k in ("policy_id", "episode_id", "t"):
        a[k] = a[k].astype(np.int64)
    _write_raw(tmp_path / "d.npz", a, ds.meta)
    back = load_dataset(tmp_path / "d.npz")
    assert back.episode_id.dtype == np.int32 and back.t.dtype == np.int32
    np.testing.assert_array_equal(back.episode_id, ds.episode_id)


def _rename(a, m, old, new):
    a[new] = a.pop(old)


def _set(a, field, rows, value):
    a[field] = a[field].copy()
    a[field][rows] = value


def _shift_ep(a, m, k, field, delta, from_offset=0):
    rows = _ep_rows(make_fake_dataset(), k)[from_offset:]
    _set(a, field, rows, a[field][rows] + delta)


# Each case: (id, mutation of (arrays, meta) in place, field named in the error, extra text).
BAD = [
    ("missing_field", lambda a, m: a.pop("obs"), "obs", "missing"),
    ("misnamed_field", lambda a, m: _rename(a, m, "obs", "observations"), "observations",
     "unknown field 'observations'"),
    ("reward_2d", lambda a, m: a.update(reward=a["reward"][:, None]), "reward", "shape"),
    ("n_mismatch", lambda a, m: a.update(action=a["action"][:-1]), "action", "N ="),
    ("obs_size_vs_meta", lambda a, m: a.update(obs=np.pad(a["obs"], ((0, 0), (0, 1)))), "obs",
     "obs_size from meta"),
    ("action_size_vs_meta", lambda a, m: m.update(action_size=3), "action",
     "action_size from meta"),
    ("obs_float64", lambda a, m: a.update(obs=a["obs"].astype(np.float64)), "obs", "float32"),
    ("done_int", lambda a, m: a.update(done=a["done"].astype(np.int8)), "done", "bool"),
    ("policy_id_float", lambda a, m: a.update(policy_id=a["policy_id"].astype(np.float32)),
     "policy_id", "int32"),
    ("episode_id_int64_overflow",
     lambda a, m: a.update(episode_id=a["episode_id"].astype(np.int64) + 2**40), "episode_id",
     "fit in int32"),
    ("obs_nan", lambda a, m: _set(a, "obs", (5, 1), np.nan), "obs", "non-finite"),
    ("reward_inf", lambda a, m: _set(a, "reward", 7, np.inf), "reward", "non-finite"),
    ("value_nan", lambda a, m: _set(a, "value", 0, np.nan), "value", "non-finite"),
    ("t_not_restarting", lambda a, m: _shift_ep(a, m, 1, "t", 1), "t", "t == 0"),
    ("t_skipping", lambda a, m: _shift_ep(a, m, 1, "t", 1, from_offset=1), "t",
     "increasing by 1"),
    ("episodes_interleaved",
     lambda a, m: _set(a, "episode_id", _ep_rows(make_fake_dataset(), 2), 100), "episode_id",
     "reappears"),
    ("done_mid_episode", lambda a, m: _set(a, "done", _ep_rows(make_fake_dataset(), 0)[0], True),
     "done", "last row"),
    ("truncated_mid_episode",
     lambda a, m: _set(a, "truncated", _ep_rows(make_fake_dataset(), 0)[0], True), "truncated",
     "last row"),
    ("done_and_truncated",
     lambda a, m: (_set(a, "done", _ep_rows(make_fake_dataset(), 0)[-1], True),
                   _set(a, "truncated", _ep_rows(make_fake_dataset(), 0)[-1], True)),
     "done", "both"),
    ("policy_id_too_big", lambda a, m: _set(a, "policy_id", _ep_rows(make_fake_dataset(), 1), 3),
     "policy_id", "[0, 3)"),
    ("policy_id_negative", lambda a, m: _set(a, "policy_id", _ep_rows(make_fake_dataset(), 1), -1),
     "policy_id", "[0, 3)"),
    ("policy_changes_in_episode",
     lambda a, m: _set(a, "policy_id", _ep_rows(make_fake_dataset(), 0)[-1], 2), "policy_id",
     "one policy per episode"),
    ("t_beyond_time_limit", lambda a, m: m.update(episode_length=3), "t", "episode_length"),
    ("empty_n0", lambda a, m: a.update({k: v[:0] for k, v in a.items()
                                        if k not in VALUE_FIELDS}), "obs", "N = 0"),
    ("partial_values", lambda a, m: a.pop("value_se"), "value_se", "all four value fields"),
    ("value_wrong_length", lambda a, m: a.update(value=a["value"][:2]), "value", "shape [3]"),
    ("negative_se", lambda a, m: _set(a, "value_discounted_se", 1, -0.5), "value_discounted_se",
     ">= 0"),
    ("values_without_gamma", lambda a, m: m.update(gamma=None), "meta.gamma", "value_discounted"),
    ("meta_missing_key", lambda a, m: m.pop("gamma"), "meta", "'gamma'"),
    ("meta_bad_obs_size", lambda a, m: m.update(obs_size="4"), "meta.obs_size", "positive int"),
    ("meta_names_length", lambda a, m: m["policy_names"].pop(), "meta.policy_names", "3 strings"),
]


@pytest.mark.parametrize("mutate,field,text", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_file_is_refused_and_left_untouched(tmp_path, mutate, field, text):
    ds = make_fake_dataset()
    arrays, meta = ds.arrays(), json.loads(json.dumps(ds.meta))
    mutate(arrays, meta)
    path = tmp_path / "bad.npz"
    _write_raw(path, arrays, meta)
    before = _digest(path)
    with pytest.raises(DatasetError) as e:
        load_dataset(path)
    assert e.value.field == field
    msg = str(e.value)
    assert f"field '{field}'" in msg and text in msg and str(path) in msg
    assert _digest(path) == before
    # The same check through validate_dataset, without a file.
    with pytest.raises(DatasetError):
        validate_dataset(arrays, meta)


def test_misnamed_field_hints_the_right_name(tmp_path):
    ds = make_fake_dataset()
    arrays = ds.arrays()
    arrays["observations"] = arrays.pop("obs")
    with pytest.raises(DatasetError, match="expected one of obs, action.*did you mean 'obs'"):
        validate_dataset(arrays, ds.meta)


@pytest.mark.parametrize("case", ["missing_meta", "unparsable_meta", "meta_not_object",
                                  "missing_version", "wrong_version"])
def test_bad_meta_or_version(tmp_path, case):
    ds = make_fake_dataset()
    meta, version, field = ds.meta, 1, "meta"
    if case == "missing_meta":
        meta = None
    elif case == "unparsable_meta":
        meta = "{task: hopper"
    elif case == "meta_not_object":
        meta = "[1, 2]"
    else:
        version, field = (None if case == "missing_version" else 2), "format_version"
    path = tmp_path / "d.npz"
    _write_raw(path, ds.arrays(), meta, format_version=version)
    with pytest.raises(DatasetError, match=f"field '{field}'"):
        load_dataset(path)


@pytest.mark.parametrize("case", ["not_found", "directory", "empty_file", "text_file", "npy_file",
                                  "corrupt_zip", "empty_npz"])
def test_unreadable_files(tmp_path, case):
    path = tmp_path / "d.npz"
    if case == "directory":
        path.mkdir()
    elif case == "empty_file":
        path.write_bytes(b"")
    elif case == "text_file":
        path.write_text("obs,action\n1,2\n")
    elif case == "npy_file":
        with open(path, "wb") as f:
            np.save(f, np.zeros(3))
    elif case == "corrupt_zip":
        save_dataset(path, make_fake_dataset())
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif case == "empty_npz":
        with open(path, "wb") as f:
            np.savez_compressed(f)
    before = _digest(path) if path.is_file() else None
    with pytest.raises(DatasetError) as e:
        load_dataset(path)
    assert e.value.field is None and str(path) in str(e.value)
    if before is not None:
        assert _digest(path) == before


def test_task_sizes_mismatch(tmp_path):
    ds = make_fake_dataset(task="fake-task")
    path = save_dataset(tmp_path / "d.npz", ds, task_sizes=lambda name: None)
    load_dataset(path, task_sizes=lambda name: (4, 2))
    with pytest.raises(DatasetError, match=r"field 'obs': expected shape \[N, 5\] .*'fake-task'"):
        load_dataset(path, task_sizes=lambda name: (5, 2))
    with pytest.raises(DatasetError, match="field 'action'"):
        load_dataset(path, task_sizes=lambda name: (4, 3))


def test_default_task_sizes_uses_registry_when_present(tmp_path, monkeypatch):
    ds = make_fake_dataset(task="fake-task")
    path = save_dataset(tmp_path / "d.npz", ds, task_sizes=lambda name: None)

    def get_task(name):
        if name != "fake-task":
            raise ValueError(f"unknown task {name}")
        return types.SimpleNamespace(obs_size=11, action_size=2)

    monkeypatch.setitem(sys.modules, "rl2s_jax.envs.tasks",
                        types.SimpleNamespace(get_task=get_task))
    with pytest.raises(DatasetError, match="registered task 'fake-task'"):
        load_dataset(path)
    # An unregistered task, or no registry at all: the check is skipped.
    path2 = save_dataset(tmp_path / "d2.npz", make_fake_dataset(task="other"))
    load_dataset(path2)
    monkeypatch.setitem(sys.modules, "rl2s_jax.envs.tasks", None)  # import raises ImportError
    load_dataset(path)


def test_save_refuses_invalid_dataset(tmp_path):
    ds = make_fake_dataset()
    bad = ds.replace(reward=ds.reward.astype(np.float64))
    with pytest.raises(DatasetError, match="field 'reward'"):
        save_dataset(tmp_path / "d.npz", bad)
    assert not any(tmp_path.iterdir())


def test_episode_returns_matches_loop():
    ds = make_fake_dataset(n_policies=4, episodes_per_policy=5)
    for gamma in (None, 0.9):
        returns, pol, complete = episode_returns(ds, gamma)
        want_r, want_p, want_c = [], [], []
        for i in range(ds.n_transitions):
            g = 1.0 if gamma is None else gamma ** int(ds.t[i])
            if i == 0 or ds.episode_id[i] != ds.episode_id[i - 1]:
                want_r.append(0.0)
                want_p.append(int(ds.policy_id[i]))
            want_r[-1] += g * float(ds.reward[i])
            if i == ds.n_transitions - 1 or ds.episode_id[i + 1] != ds.episode_id[i]:
                want_c.append(bool(ds.done[i] or ds.truncated[i]))
        np.testing.assert_allclose(returns, want_r, rtol=1e-12)
        np.testing.assert_array_equal(pol, want_p)
        np.testing.assert_array_equal(complete, want_c)
    assert (~complete).sum() == 4  # each policy's last episode is open


def test_dataset_summary_numbers():
    ds = make_fake_dataset(n_policies=3, episodes_per_policy=3)
    text = dataset_summary(ds)
    per_pol = np.bincount(ds.policy_id)
    assert f"transitions (N): {ds.n_transitions}" in text
    assert "policies (P): 3" in text
    assert "episodes: 9 (6 complete" in text and "3 open)" in text
    returns, pol, complete = episode_returns(ds)
    ends = np.r_[np.flatnonzero(np.diff(ds.episode_id)), ds.n_transitions - 1]
    n_trunc = int(ds.truncated[ends].sum())
    assert n_trunc > 0 and f"{6 - n_trunc} done, {n_trunc} truncated" in text
    assert f"min {per_pol.min()}, max {per_pol.max()}" in text
    mean0 = returns[(pol == 0) & complete].mean()
    assert f"{mean0:.3f}" in text
    assert f"{float(ds.value[2]):.3f} ± {float(ds.value_se[2]):.3f}" in text
    assert "pi_1" in text
    assert "±" not in dataset_summary(make_fake_dataset(with_values=False))


def test_select_policies_renumbers():
    ds = make_fake_dataset(n_policies=4)
    sub = ds.select_policies([2, 0])
    validate_dataset(sub)
    old = ds.policy_id
    keep = (old == 2) | (old == 0)
    np.testing.assert_array_equal(sub.policy_id, np.where(old[keep] == 2, 0, 1))
    np.testing.assert_array_equal(sub.obs, ds.obs[keep])
    np.testing.assert_array_equal(sub.value, ds.value[[2, 0]])
    assert sub.meta["policy_names"] == ["pi_2", "pi_0"] and sub.n_policies == 2
    assert sub.meta["source"]["selected_policies"] == [2, 0]
    assert ds.meta["n_policies"] == 4 and "selected_policies" not in ds.meta["source"]
    assert sub.select_policies([1]).meta["source"]["selected_policies"] == [0]
    with pytest.raises(ValueError):
        ds.select_policies([0, 4])


def test_concat_datasets_continues_episodes_and_averages_values():
    a, b = make_fake_dataset(seed=1), make_fake_dataset(seed=2)
    both = concat_datasets([a, b])
    validate_dataset(both)
    n_a = a.n_transitions
    np.testing.assert_array_equal(both.obs[:n_a], a.obs)
    np.testing.assert_array_equal(both.obs[n_a:], b.obs)
    # part b's episodes keep their boundaries and come after all of a's
    ep_a, ep_b = both.episode_id[:n_a], both.episode_id[n_a:]
    assert ep_b.min() > ep_a.max()
    np.testing.assert_array_equal(np.diff(ep_b) != 0, np.diff(b.episode_id) != 0)
    np.testing.assert_allclose(both.value, (a.value + b.value) / 2, rtol=1e-6)
    np.testing.assert_allclose(both.value_se, np.hypot(a.value_se, b.value_se) / 2, rtol=1e-6)
    assert both.meta["source"]["parts"] == 2 and "parts" not in a.meta["source"]
    mixed = concat_datasets([a, make_fake_dataset(seed=3, with_values=False)])
    assert not mixed.has_values and mixed.meta["gamma"] is None
    validate_dataset(mixed)
    with pytest.raises(ValueError, match=r"datasets\[1\]: meta 'n_policies'"):
        concat_datasets([a, make_fake_dataset(n_policies=2)])
    with pytest.raises(ValueError, match="datasets: expected a non-empty"):
        concat_datasets([])
