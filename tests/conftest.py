"""Shared fixtures: MJX envs are slow to build on the CPU (~30 s), so each is built once."""

import functools
import os

import pytest

# XLA's CPU compiler with its older fusion emitters: the same programs compile in about two
# thirds of the time (measured on the 2-core machine: a Hopper collection step 17 s -> 11 s, a
# train chunk 8.1 s -> 6.1 s, tests/test_train.py 151 s -> 114 s; runtimes unchanged, results
# equal to round-off), and XLA compilation is most of the suite's time. jaxlib 0.10 only: 0.11
# has no such flag (XLA aborts on an unknown one). Set here, before JAX starts its backend, so
# the test processes and the subprocesses they start inherit it;
# RL2S_TEST_FUSION_EMITTERS=new keeps XLA's default.
# With them, LLVM's optimisation level 1 for the generated code (XLA's default is 2): the tests'
# programs are small and short-lived, so compiling dominates running them. Cold cache, 2-core
# machine: the Hopper pipeline smoke 161 s -> 125 s (XLA compile time 110 s -> ~70 s);
# a pointmass SAC-from-scratch and a real-env fine-tuning test 28 s -> 21 s, run time included
# (level 0 compiles faster still but runs these two in 40 s).
FAST_CPU_COMPILE = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=1")


def _fast_cpu_compile() -> None:
    import jaxlib

    flags = os.environ.get("XLA_FLAGS", "")
    if (jaxlib.__version__.startswith("0.10.")
            and os.environ.get("RL2S_TEST_FUSION_EMITTERS", "") != "new"):
        extra = [f for f in FAST_CPU_COMPILE if f.split("=")[0] not in flags]
        os.environ["XLA_FLAGS"] = " ".join([flags, *extra]).strip()


_fast_cpu_compile()


def pytest_configure(config):
    """The persistent compilation cache, as the CLI uses it (RL2S_COMPILATION_CACHE=off turns
    it off): a second run of the suite skips most XLA compilation."""
    from rl2s_jax import compile_cache

    compile_cache.enable()


# `make test`'s two xdist workers (--dist loadfile): each file is one unit of work, kept whole
# on one worker so its module fixtures are built once, except that the files using
# hopper_train_ds are one unit, in this order: the fixture's MJX programs then compile once,
# and the pipeline's train-split collection (the same programs) hits the persistent cache.
# Units go out costliest first, so that neither worker is left with a long one at the end;
# files not named here follow in pytest's order. The costs: each file's seconds in make test
# on the 2-core machine, cold cache (measured; only the order matters).
UNITS = (
    ("hopper_train_ds", ("test_checkpoint.py", "test_collect.py", "test_oracle.py",
                         "test_pipeline.py")),                                       # ~410 s
    *((name, (name,)) for name in (
        "test_train.py", "test_improve.py", "test_ensemble.py", "test_diagnose.py",  # 170-110
        "test_history.py", "test_sharding.py", "test_taskless.py", "test_tasks.py",  # 85-75
        "test_improve_run.py", "test_zoo.py", "test_ablation.py", "test_distributed.py",
        "test_diagnose_model.py", "test_gym_env.py", "test_termination.py",          # 70-40
        "test_own_policies.py", "test_context.py", "test_assess.py")),               # 35-30
)
_RANK = {f: (i, j) for i, (_, files) in enumerate(UNITS) for j, f in enumerate(files)}
_UNIT = {f: unit for unit, files in UNITS for f in files}


def pytest_collection_modifyitems(config, items):
    """The tests in UNITS' order (within a file, pytest's): the order xdist hands out units."""
    index = {id(item): i for i, item in enumerate(items)}
    items.sort(key=lambda it: (*_RANK.get(it.path.name, (len(UNITS), 0)), index[id(it)]))


try:
    from xdist.scheduler import LoadFileScheduling
except ImportError:  # no xdist: no scheduler to make
    LoadFileScheduling = None

if LoadFileScheduling is not None:
    class _UnitScheduling(LoadFileScheduling):
        """loadfile with UNITS as the units of work, in the collection's order."""

        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return _UNIT.get(os.path.basename(path), path)

    @pytest.hookimpl(tryfirst=True, optionalhook=True)  # optional: -p no:xdist
    def pytest_xdist_make_scheduler(config, log):
        if config.getvalue("dist") != "loadfile":
            return None
        config.option.loadscopereorder = False  # xdist >= 3.8 would sort by test count
        return _UnitScheduling(config, log)


@functools.cache
def cached_env(name: str):
    from rl2s_jax.envs.tasks import get_task

    return get_task(name).make_env()


@pytest.fixture(scope="session")
def env_cache():
    return cached_env


@pytest.fixture(scope="session")
def hopper_train_ds(env_cache):
    """A small Hopper Dataset of the shipped zoo's 17 training policies (80 transitions and
    16 true-value episodes each, 40-step episodes); meta.source names the zoo so `rl2s train`
    finds the policies. Its MJX programs (collection and value measurement) are the
    costliest of the suite to compile, so the tests that need Hopper data share it
    (test_oracle needs the 16 value episodes: true values it can resolve), and
    test_pipeline collects its train split with exactly these sizes (a persistent-cache
    hit)."""
    import jax

    from rl2s_jax.data.collect import collect
    from rl2s_jax.policy import policy as pol
    from rl2s_jax.zoo import zoo as zoo_mod

    zoo = zoo_mod.load_zoo("hopper")
    ids = list(zoo.train_ids)
    return collect(env_cache("hopper"), pol.index_params(zoo.params, ids),
                   key=jax.random.PRNGKey(0), transitions_per_policy=80, envs_per_policy=2,
                   episode_length=40, task="hopper", value_episodes=16, progress=False,
                   policy_names=zoo.policy_names(ids),
                   source={"zoo": "hopper", "zoo_ids": ids})


@pytest.fixture(scope="session")
def pointmass_ppo():
    """PPO snapshots on pointmass (one seed, ~40k env steps, ~10 s on the CPU) and their real
    returns: {"params": stacked [5, ...] (0 = the random initial policy), "returns": [5]}.
    Early snapshots are mediocre (they push the mass off an edge), the last near optimal."""
    import jax
    import numpy as np

    from rl2s_jax.data.collect import measure_values
    from rl2s_jax.policy.ppo import PPOConfig, make_ppo, train_snapshots

    env = cached_env("pointmass")
    cfg = PPOConfig(num_envs=64, unroll_length=16, num_minibatches=4, episode_length=50,
                    gamma=0.95, learning_rate=1e-3)
    params = jax.jit(lambda k: train_snapshots(make_ppo(env, cfg), k, 4, 10))(
        jax.random.PRNGKey(0))
    returns = measure_values(env, params, key=jax.random.PRNGKey(1), n_episodes=64,
                             episode_length=50)["value"]
    return {"params": params, "returns": np.asarray(returns)}


@pytest.fixture(scope="session")
def pointmass_checkpoint(tmp_path_factory):
    """A pointmass zoo (4 policies), a test Dataset of its policies (meta.source names the
    zoo) and a checkpoint of a briefly trained BC simulator of it:
    {"zoo": dir, "data": .npz path, "ckpt": checkpoint dir, "dataset": Dataset}."""
    import jax
    import numpy as np

    from rl2s_jax.data.collect import collect
    from rl2s_jax.data.dataset import save_dataset
    from rl2s_jax.policy import policy as pol
    from rl2s_jax.train.checkpoint import Checkpointer
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.loop import fit
    from rl2s_jax.train.step import init
    from rl2s_jax.zoo import zoo as zoo_mod

    root = tmp_path_factory.mktemp("pointmass_run")
    ps = []
    for i, b in enumerate([-2.0, 0.0, 1.0, 2.0]):
        p = pol.init_policy(jax.random.PRNGKey(i), 2, 1, hidden=(8,))
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:1].set(b)
        ps.append(p)
    params = pol.stack_params(ps)
    zoo_dir = str(root / "zoo")
    zoo_mod.save_zoo(zoo_mod.Zoo(task="pointmass", params=params, returns=np.zeros(4),
                         return_se=np.zeros(4), origins=[{}] * 4, train_ids=[],
                         test_ids=[0, 1, 2, 3]), zoo_dir)
    ids = [0, 1, 2, 3]
    ds = collect(cached_env("pointmass"), params, key=jax.random.PRNGKey(0),
                 transitions_per_policy=400, envs_per_policy=2, episode_length=50,
                 task="pointmass", value_episodes=8, progress=False,
                 policy_names=[f"pointmass-{i:03d}" for i in ids],
                 source={"zoo": zoo_dir, "split": "test", "zoo_ids": ids})
    data_path = str(root / "test.npz")
    save_dataset(data_path, ds)
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=50, vd_every=5)
    data = make_train_data(ds, params, cfg)
    state, _ = fit(init(jax.random.PRNGKey(0), cfg, data), data, 20, chunk=20, progress=False)
    ckpt = str(root / "run" / "checkpoints")
    ck = Checkpointer(ckpt)
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1, "task": "pointmass"}})
    ck.close()
    return {"zoo": zoo_dir, "data": data_path, "ckpt": ckpt, "dataset": ds}


@pytest.fixture(scope="session")
def pm_files(tmp_path_factory):
    """A pointmass zoo of 6 policies on disk, train (0-2) and test (3-5) datasets naming it."""
    import jax
    import numpy as np

    from rl2s_jax.data.collect import collect
    from rl2s_jax.data.dataset import save_dataset
    from rl2s_jax.envs.tasks import get_task
    from rl2s_jax.policy import policy as pol
    from rl2s_jax.zoo import zoo as zoo_mod

    root = tmp_path_factory.mktemp("pm")
    task = get_task("pointmass")
    ps = []
    for i, b in enumerate([-2.0, 0.0, 2.0, -1.0, 0.5, 1.0]):
        p = pol.init_policy(jax.random.PRNGKey(i), 2, 1, hidden=(8,))
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:1].set(b)
        ps.append(p)
    zoo = zoo_mod.Zoo(task="pointmass", params=pol.stack_params(ps),
                      returns=np.zeros(6, np.float32),
                      return_se=np.zeros(6, np.float32), origins=[{}] * 6,
                      train_ids=[0, 1, 2],
                      test_ids=[3, 4, 5], info={})
    zoo_mod.save_zoo(zoo, str(root / "zoo"))
    paths = {}
    for split, ids in (("train", [0, 1, 2]), ("test", [3, 4, 5])):
        ds = collect(task.make_env(), pol.index_params(zoo.params, ids),
                     key=jax.random.PRNGKey(len(split)), transitions_per_policy=300,
                     envs_per_policy=2, episode_length=task.episode_length, task="pointmass",
                     value_episodes=8, progress=False, policy_names=zoo.policy_names(ids),
                     source={"zoo": str(root / "zoo"), "zoo_ids": ids})
        paths[split] = str(root / f"{split}.npz")
        save_dataset(paths[split], ds)
    return paths


@pytest.fixture(scope="session")
def pm_checkpoint(pm_files, tmp_path_factory):
    """A pointmass simulator checkpoint (an initialised BC model of pm_files' train data, step
    0: no training needed where any simulator will do)."""
    import jax

    from rl2s_jax.data.dataset import load_dataset
    from rl2s_jax.train.checkpoint import Checkpointer
    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.data import make_train_data
    from rl2s_jax.train.step import init
    from rl2s_jax.zoo.zoo import policies_for

    ds = load_dataset(pm_files["train"])
    cfg = TrainConfig.small(task="pointmass", method="bc", vd_horizon=50)
    data = make_train_data(ds, policies_for(ds), cfg)
    path = tmp_path_factory.mktemp("pm_ckpt") / "checkpoints"
    ck = Checkpointer(path)
    ck.save(init(jax.random.PRNGKey(0), cfg, data),
            {"data": {"obs_size": ds.obs_size, "action_size": ds.action_size}})
    ck.close()
    return str(path)


@pytest.fixture(scope="session")
def pm_falls():
    """Pointmass data where two of four policies push the mass out (|p| > 2 ends):
    (Dataset, stacked policy params)."""
    import jax
    import numpy as np
    from test_train import _policies

    from rl2s_jax.data.collect import collect
    from rl2s_jax.envs.tasks import get_task

    task = get_task("pointmass")
    params = _policies([-2.0, 0.0, 1.0, 2.0])
    ds = collect(task.make_env(), params, key=jax.random.PRNGKey(0), transitions_per_policy=400,
                 envs_per_policy=2, episode_length=task.episode_length, task="pointmass",
                 value_episodes=4, progress=False)
    assert np.asarray(ds.done).any()
    return ds, params
