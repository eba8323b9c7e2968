"""Minari in and out: a Minari dataset written by minari's own DataCollector on a tiny Gymnasium
env round-trips through our Dataset (every transition, episode boundary and policy), ours
round-trips through Minari, bad input is refused by name, and `rl2s import` / `rl2s export`.
No network: everything is built under tmp_path. An export of a registered task's data names
the task's real env (a Gymnasium EnvSpec) in its metadata; other exports have none."""
import json
import warnings

import gymnasium as gym
import numpy as np
import pytest

from rl2s_jax.cli import main
from rl2s_jax.data.dataset import TRANSITION_FIELDS, VALUE_FIELDS, DatasetError, load_dataset
from rl2s_jax.data.minari import from_minari, task_env_spec, to_minari
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.improve.gym_env import TaskGymEnv, task_env_id

minari = pytest.importorskip("minari")

POLICIES = ("push", "random")
ENV_ID = "rl2s_test/Drift-v0"
LIMIT = 12


class Drift(gym.Env):
    """A point in 2-D pushed by a 1-D action; terminates when |x0| > 1 (time limit: LIMIT)."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.uniform(-0.5, 0.5, 2).astype(np.float32)
        return self.x.copy(), {}

    def step(self, action):
        a = float(np.asarray(action).reshape(-1)[0])
        self.x = (self.x + np.array([0.25 * a, 0.1 * self.x[0]], np.float32)).astype(np.float32)
        return self.x.copy(), float(1.0 - self.x[0] ** 2), bool(abs(self.x[0]) > 1.0), False, {}


class PolicyOfEpisode(minari.EpisodeMetadataCallback):
    """Episode metadata as a collector of several policies would write it."""

    def __call__(self, episode):
        return {**super().__call__(episode), "policy_name": POLICIES[episode["id"] % 2]}


@pytest.fixture(scope="module")
def minari_root(tmp_path_factory):
    """A local Minari root holding 'rl2s_test/drift-v0': 7 episodes by minari's DataCollector,
    alternating the 'push' and 'random' policies (terminations and time-limit truncations)."""
    root = tmp_path_factory.mktemp("minari")
    mp = pytest.MonkeyPatch()
    mp.setenv("MINARI_DATASETS_PATH", str(root))
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=f"{__name__}:Drift", max_episode_steps=LIMIT)
    env = minari.DataCollector(gym.make(ENV_ID), episode_metadata_callback=PolicyOfEpisode)
    rng = np.random.default_rng(0)
    for episode in range(7):
        env.reset(seed=episode)
        done = False
        while not done:
            if POLICIES[episode % 2] == "push":
                action = np.array([0.8 + 0.2 * rng.random()], np.float32)
            else:
                action = rng.uniform(-1, 1, 1).astype(np.float32)
            _, _, term, trunc, _ = env.step(action)
            done = term or trunc
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # eval_env / ref score notes of minari
        env.create_dataset("rl2s_test/drift-v0", algorithm_name="scripted", author="tests",
                           author_email="tests@example.com", code_permalink="tests",
                           description="tiny test data")
    env.close()
    yield root
    mp.undo()


def _episodes(mds):
    return list(mds.iterate_episodes())


def test_minari_to_dataset_to_minari_keeps_everything(minari_root, tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(minari_root))
    src = minari.load_dataset("rl2s_test/drift-v0")
    eps = _episodes(src)
    assert any(e.terminations[-1] for e in eps) and any(e.truncations[-1] for e in eps)

    ds = from_minari(minari_root / "rl2s_test" / "drift-v0")
    assert ds.n_transitions == src.total_steps == sum(len(e) for e in eps)
    assert ds.meta["policy_names"] == list(POLICIES) and ds.meta["episode_length"] == LIMIT
    assert ds.meta["task"] is None and not ds.has_values
    # Row by row against the Minari episodes.
    starts = np.flatnonzero(np.r_[True, np.diff(ds.episode_id) != 0])
    assert len(starts) == len(eps)
    for lo, e in zip(starts, eps, strict=True):
        rows = slice(lo, lo + len(e))
        np.testing.assert_array_equal(ds.obs[rows], e.observations[:-1])
        np.testing.assert_array_equal(ds.next_obs[rows], e.observations[1:])
        np.testing.assert_array_equal(ds.action[rows], e.actions)
        np.testing.assert_array_equal(ds.reward[rows], e.rewards.astype(np.float32))
        np.testing.assert_array_equal(ds.done[rows], e.terminations)
        np.testing.assert_array_equal(ds.truncated[rows], e.truncations)
        np.testing.assert_array_equal(ds.t[rows], np.arange(len(e)))
        assert set(ds.policy_id[rows]) == {e.id % 2} and set(ds.episode_id[rows]) == {e.id}
    # The same dataset by id (local root only) and by its data/ directory.
    for source in ("rl2s_test/drift-v0", minari_root / "rl2s_test" / "drift-v0" / "data"):
        np.testing.assert_array_equal(from_minari(source).obs, ds.obs)

    back = to_minari(ds, tmp_path / "back")
    assert back.total_episodes == src.total_episodes and back.total_steps == src.total_steps
    for a, b in zip(eps, _episodes(back), strict=True):
        assert a.id == b.id
        for field in ("observations", "actions", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
        np.testing.assert_array_equal(a.rewards.astype(np.float32), b.rewards)
    meta = list(back.storage.get_episode_metadata(back.episode_indices))
    assert [m["policy_name"] for m in meta] == [POLICIES[e.id % 2] for e in eps]


@pytest.fixture(scope="module")
def pm_dataset(pm_files):
    """Pointmass data of 3 policies with true values, whose source names a zoo."""
    return load_dataset(pm_files["test"])


def test_dataset_to_minari_to_dataset_is_identical(pm_dataset, tmp_path):
    ds = pm_dataset
    mds = to_minari(ds, tmp_path / "pm-v3", author="me")
    assert mds.id == "pm-v3"
    back = from_minari(tmp_path / "pm-v3")
    for k in TRANSITION_FIELDS + VALUE_FIELDS:
        got, want = np.asarray(getattr(back, k)), np.asarray(getattr(ds, k))
        assert got.dtype == want.dtype, k
        np.testing.assert_array_equal(got, want, err_msg=k)
    for k in ("task", "gamma", "episode_length", "policy_names", "n_policies"):
        assert back.meta[k] == ds.meta[k], k
    src = back.meta["source"]  # keeps what `rl2s train` needs to find the policies
    assert src["zoo"] == ds.meta["source"]["zoo"] and src["zoo_ids"] == [3, 4, 5]
    assert src["minari"]["dataset_id"] == "pm-v3"
    assert src["minari"]["env_id"] == task_env_id("pointmass")


def test_export_of_a_registered_task_names_its_env(pm_dataset, tmp_path):
    """The metadata's env_spec parses back (gymnasium's EnvSpec.from_json) to the task's real
    env at the data's episode length, and Minari's recover_environment makes that env."""
    ds = pm_dataset
    mds = to_minari(ds, tmp_path / "pm-v0")
    raw = json.loads((tmp_path / "pm-v0" / "data" / "metadata.json").read_text())["env_spec"]
    spec = gym.envs.registration.EnvSpec.from_json(raw)
    task = get_task("pointmass")
    assert spec.id == task_env_id("pointmass") and spec.kwargs == {"task": "pointmass"}
    assert spec.max_episode_steps == ds.meta["episode_length"] == task.episode_length
    env = mds.recover_environment()  # gymnasium.make(env_spec)
    assert env.spec.max_episode_steps == ds.meta["episode_length"]
    assert isinstance(env.unwrapped, TaskGymEnv) and env.unwrapped.task is task
    assert env.observation_space.shape == (ds.obs_size,)
    assert env.action_space.shape == (ds.action_size,)
    # The data's own time limit where it has one, else the task's; none without a task.
    assert task_env_spec({"task": "pointmass", "episode_length": 20}).max_episode_steps == 20
    assert task_env_spec({"task": "pointmass"}).max_episode_steps == task.episode_length
    assert task_env_spec({"task": None}) is None and task_env_spec({"task": "drift"}) is None


def _write_minari(data_dir, action_space, episode_metadata=None, steps=(3, 2)):
    """A small Minari dataset written with minari's storage directly (episodes of random data)."""
    from minari.data_collector import EpisodeBuffer
    from minari.dataset.minari_storage import MinariStorage

    data_dir.mkdir(parents=True)
    storage = MinariStorage.new(data_dir, action_space=action_space,
                                observation_space=gym.spaces.Box(-1, 1, (2,), np.float32))
    storage.update_metadata({"dataset_id": f"{data_dir.parent.name}-v0",
                             "minari_version": minari.__version__})
    rng = np.random.default_rng(0)
    storage.update_episodes([EpisodeBuffer(
        id=i, observations=rng.uniform(-1, 1, (n + 1, 2)).astype(np.float32),
        actions=np.stack([action_space.sample() for _ in range(n)]),
        rewards=rng.normal(size=n), terminations=np.arange(n) == n - 1,
        truncations=np.zeros(n, bool), infos={}) for i, n in enumerate(steps)])
    if episode_metadata is not None:
        storage.update_episode_metadata(episode_metadata)
    return data_dir


def test_minari_bad_input_is_refused_by_name(pm_dataset, tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "empty_root"))
    with pytest.raises(DatasetError, match="never downloads"):
        from_minari("nobody/nothing-v0")
    box = gym.spaces.Box(-1, 1, (1,), np.float32)
    # Policy metadata on some episodes only.
    d = _write_minari(tmp_path / "partial" / "data", box, [{"policy_name": "a"}, {}])
    with pytest.raises(DatasetError, match=r"minari.episode_metadata.policy_name.*missing on 1 "
                       r"of 2 episodes, the first episode 1"):
        from_minari(d)
    # Without policy metadata: one policy, named after the dataset.
    one = from_minari(_write_minari(tmp_path / "plain" / "data", box))
    assert one.n_policies == 1 and one.meta["policy_names"] == ["plain-v0"]
    assert one.n_transitions == 5 and list(one.t) == [0, 1, 2, 0, 1]
    # Integer policy ids in the metadata are used as they are.
    ids = from_minari(_write_minari(tmp_path / "ids" / "data", box,
                                    [{"policy_id": 2}, {"policy_id": 0}]))
    assert list(ids.policy_id) == [2, 2, 2, 0, 0] and ids.n_policies == 3
    # A Discrete action space has no vector form for the simulator.
    d = _write_minari(tmp_path / "disc" / "data", gym.spaces.Discrete(3))
    with pytest.raises(DatasetError, match=r"minari.action_space.*Box.*Discrete"):
        from_minari(d)
    # Export: next_obs must continue as the next row's obs; the target must be new.
    a = pm_dataset.arrays()
    a["next_obs"] = a["next_obs"].copy()
    a["next_obs"][3] += 1.0
    broken = type(pm_dataset).from_arrays(a, pm_dataset.meta)
    with pytest.raises(DatasetError, match=r"next_obs.*differ at row 3"):
        to_minari(broken, tmp_path / "x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "file").write_text("")
    with pytest.raises(DatasetError, match="non-empty directory"):
        to_minari(pm_dataset, tmp_path / "full")
    with pytest.raises(DatasetError, match="dataset_id"):
        to_minari(pm_dataset, tmp_path / "y", dataset_id="no version")


def test_cli_import_then_export(minari_root, tmp_path, capsys):
    npz = tmp_path / "drift.npz"
    rc = main(["import", "--minari", str(minari_root / "rl2s_test" / "drift-v0"), "--out",
               str(npz), "--gamma", "0.99"])
    assert rc == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "policies (P): 2" in out and str(npz) in out
    ds = load_dataset(npz)
    assert ds.meta["gamma"] == 0.99 and ds.meta["policy_names"] == list(POLICIES)

    rc = main(["export", "--minari", "--data", str(npz), "--out", str(tmp_path / "again")])
    assert rc == 0, capsys.readouterr().err
    again = minari.MinariDataset(tmp_path / "again" / "data")
    assert again.id == "again-v0" and again.total_steps == ds.n_transitions
    assert ds.meta["task"] is None and again.env_spec is None  # no registered task: no env
    np.testing.assert_array_equal(from_minari(again).obs, ds.obs)

    rc = main(["import", "--minari", str(tmp_path / "missing"), "--out", str(tmp_path / "m.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "rl2s import: error:" in err and "never downloads" in err
    rc = main(["import", "--minari", str(minari_root / "rl2s_test" / "drift-v0"), "--out",
               str(tmp_path / "p.npz"), "--task", "pointmass"])
    assert rc == 0  # pointmass also has 2-d obs and 1-d actions: the sizes check passes
    rc = main(["import", "--minari", str(minari_root / "rl2s_test" / "drift-v0"), "--out",
               str(tmp_path / "h.npz"), "--task", "hopper"])
    err = capsys.readouterr().err
    assert rc == 2 and "obs_size" in err
