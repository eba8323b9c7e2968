"""Lanes over the devices of several processes through ``jax.distributed`` give the
single-process results (issue 40, item 2); ``initialize_distributed`` reads its settings."""
from __future__ import annotations

import os
import pickle
import socket
import subprocess
import sys
import textwrap
import time

import jax
import numpy as np
import pytest

from rl2s_jax import sharding

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCH_VARS = (sharding.COORDINATOR_VAR, sharding.NUM_PROCESSES_VAR, sharding.PROCESS_ID_VAR,
               *sharding.SLURM_VARS)

# One program, run as one plain process (one device) and as two processes of two forced host
# devices each. The plain process collects the data, builds 4 lanes (test_sharding's config,
# no pre-training) and hands them to the two through <out>/lanes.pkl (each would build the same
# from the same keys; building them once spares two compilations of init). Each run trains the
# lanes split over lane_mesh(4), evaluates them and writes what every process gathered to
# <out>/<run>.<process index>.
LANES_PROGRAM = textwrap.dedent("""
    import os, pickle, sys
    sys.path[:0] = [{root!r} + "/tests"]
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU collectives
    from rl2s_jax import sharding
    distributed = sharding.initialize_distributed()  # before any other JAX work
    import jax.numpy as jnp
    from test_train import _policies
    from rl2s_jax.evaluate.lane_scores import lane_returns
    from rl2s_jax.train.lanes import train_lanes
    from rl2s_jax import train as T

    out, run = sys.argv[1:3]
    me = jax.process_index()
    assert distributed == (jax.process_count() == 2) and sharding.is_writer() == (me == 0)
    policies = _policies([-2.0, 0.0, 1.0, 2.0])
    cfg = T.TrainConfig.small(task="pointmass", method="rl2s", vd_horizon=20, vd_every=2,
                              disc_warmup_steps=1)
    if not distributed:
        # the two processes compile alike without a cache: a hit on one would leave the
        # other a whole compilation behind, past gloo's 30 s wait for its peers
        from rl2s_jax import compile_cache
        from rl2s_jax.data.collect import collect
        from rl2s_jax.envs.tasks import get_task
        from rl2s_jax.model.simulator import start_pool

        compile_cache.enable()
        task = get_task("pointmass")
        ds = collect(task.make_env(), policies, key=jax.random.PRNGKey(0),
                     transitions_per_policy=400, envs_per_policy=2,
                     episode_length=task.episode_length, task="pointmass", value_episodes=2,
                     progress=False)
        data = T.make_train_data(ds, policies, cfg)
        keys = jnp.stack([jax.random.PRNGKey(s) for s in range(4)])
        eps = jnp.asarray([0.25, 0.5, 1.0, 0.25])
        states = jax.jit(jax.vmap(lambda k, e, d: T.init(k, cfg, d, eps=e),
                                  in_axes=(0, 0, None)))(keys, eps, data)
        lanes = jax.device_get({{"states": states, "data": data, "pool": start_pool(ds)}})
        with open(out + "/lanes.tmp", "wb") as f:
            pickle.dump(lanes, f)
        os.replace(out + "/lanes.tmp", out + "/lanes.pkl")
    with open(out + "/lanes.pkl", "rb") as f:
        lanes = pickle.load(f)
    mesh = sharding.lane_mesh(4)
    if distributed:  # the mesh takes both processes' devices, two each
        assert mesh.size == 4 and sorted(d.process_index for d in mesh.devices) == [0, 0, 1, 1]
        assert [d.process_index for d in sharding.lane_mesh(6).devices] == [0, 1]
        try:
            sharding.lane_mesh(3)
            raise AssertionError("lane_mesh(3) over 2 processes")
        except ValueError as e:
            assert "2 processes" in str(e), e
    states = sharding.shard_lanes(lanes["states"], mesh)
    data = sharding.replicate(lanes["data"], mesh)
    trained, _ = train_lanes(states, data, 4, cfg, {{}})
    leaf = trained.gen["layers"][0]["w"]
    if distributed:  # each process holds its own two lanes, one per device
        assert len(leaf.sharding.device_set) == 4 and not leaf.is_fully_addressable
        assert sorted(s.index[0].start for s in leaf.addressable_shards) == [2 * me, 2 * me + 1]
    ekeys = jnp.stack([jax.random.PRNGKey(9 + s) for s in range(4)])
    returns, _ = lane_returns(T.simulator(trained), policies, lanes["pool"], ekeys,
                              n_episodes=4, horizon=20, gamma=0.99)
    host = sharding.to_host({{"params": trained, "returns": returns}})
    flat = {{jax.tree_util.keystr(p): x
             for p, x in jax.tree_util.tree_leaves_with_path(host)}}
    with open(f"{{out}}/{{run}}.{{me}}", "wb") as f:
        pickle.dump(flat, f)
    print("LANES DONE", me, jax.process_count(), mesh.size)
""")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _load(path) -> dict:
    with open(path, "rb") as f:
        return pickle.load(f)


@pytest.fixture(scope="module")
def lane_runs(tmp_path_factory):
    """The program as one plain process and, once it has handed over the lanes, as two
    processes at the same time. -> {"plain": flat results, "dist": [process 0's, process
    1's]}"""
    out = tmp_path_factory.mktemp("distributed")
    script = LANES_PROGRAM.format(root=ROOT)
    base = {k: v for k, v in os.environ.items()
            if k not in LAUNCH_VARS and k != "JAX_COMPILATION_CACHE_DIR"}
    # LLVM unoptimised in all three: a third of the compile time, the same program on each side
    fast = "--xla_backend_optimization_level=0"
    base.update(JAX_PLATFORMS="cpu", XLA_FLAGS=fast)
    logs = {}

    def start(name, run, **env):  # output to a file: a full pipe would stall the process
        logs[name] = open(out / f"{name}.log", "w")  # closed in the finally below
        return subprocess.Popen([sys.executable, "-c", script, str(out), run], cwd=ROOT,
                                env={**base, **env}, stdout=logs[name],
                                stderr=subprocess.STDOUT)

    runs = {"plain": start("plain", "plain")}
    try:
        deadline = time.monotonic() + 300
        while not (out / "lanes.pkl").exists() and runs["plain"].poll() is None:
            assert time.monotonic() < deadline, "no lanes.pkl from the plain run in 300 s"
            time.sleep(0.5)
        for attempt in range(2):  # gloo gives up when the two arrive > 30 s apart (a loaded
            # machine can starve one of them): such a pair runs once more
            if not (out / "lanes.pkl").exists():
                break
            coordinator = f"localhost:{_free_port()}"
            for i in range(2):
                devices = "--xla_force_host_platform_device_count=2"
                if i in logs:
                    logs[i].close()
                runs[i] = start(i, "dist", XLA_FLAGS=f"{fast} {devices}",
                                **{sharding.COORDINATOR_VAR: coordinator,
                                   sharding.NUM_PROCESSES_VAR: "2",
                                   sharding.PROCESS_ID_VAR: str(i)})
            for i in range(2):
                runs[i].wait(timeout=300)
            timed_out = any(runs[i].returncode and "DEADLINE_EXCEEDED" in
                            (out / f"{i}.log").read_text() for i in range(2))
            if not timed_out or attempt:
                break
        for p in runs.values():
            p.wait(timeout=300)
    finally:
        for name, p in runs.items():
            if p.poll() is None:
                p.kill()
            logs[name].close()
    said = {name: (out / f"{name}.log").read_text() for name in runs}
    for name, p in runs.items():
        assert p.returncode == 0 and "LANES DONE" in said[name], (name, said[name][-3000:])
    assert len(runs) == 3 and "LANES DONE 0 1 1" in said["plain"]
    assert all(f"LANES DONE {i} 2 4" in said[i] for i in range(2))
    return {"plain": _load(out / "plain.0"), "dist": [_load(out / f"dist.{i}") for i in range(2)]}


def test_lanes_over_two_processes_equal_the_single_process_run(lane_runs):
    """WGAIL lanes (eps 0.25 / 0.5 / 1 / 0.25) split over the 4 devices of 2 processes
    (jax.distributed on the CPU, gloo) train and evaluate to the numbers of the one-process,
    one-device program, and both processes gather the same whole lane axis."""
    plain, (first, second) = lane_runs["plain"], lane_runs["dist"]
    assert plain.keys() == first.keys() == second.keys()
    for path in plain:
        np.testing.assert_array_equal(first[path], second[path], err_msg=path)
        a, b = plain[path], first[path]
        assert a.shape == b.shape and a.shape[:1] == (4,), (path, a.shape, b.shape)
        if a.dtype.kind != "f":  # steps, keys, counters, ranks, masks
            np.testing.assert_array_equal(a, b, err_msg=path)
        elif ".disc" in path:
            # the critic's Adam (beta1 0.5, lr 1e-3) turns float reassociation (4 lanes
            # vmapped on one device against one lane per device) in near-zero gradients into
            # differences of up to an Adam step per step in some of its weights; its Adam
            # moments, nearly its last gradients, move by a good part of their size there
            moments = ".disc_opt" in path
            np.testing.assert_allclose(a, b, rtol=1e-4, err_msg=path,
                                       atol=0.2 * np.abs(a).max() if moments else 5e-3)
        else:  # the simulator and the rest: float tolerance in nearly every element
            share = np.isclose(a, b, rtol=1e-4, atol=1e-5).mean()
            assert share > 0.999, (path, share)
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-3, err_msg=path)
    np.testing.assert_allclose(plain["['returns']"], first["['returns']"], rtol=1e-4,
                               atol=1e-4)


@pytest.fixture
def launch_env(monkeypatch):
    """No launch variables, and jax.distributed.initialize recorded instead of called."""
    for var in LAUNCH_VARS:
        monkeypatch.delenv(var, raising=False)
    calls = []
    monkeypatch.setattr(jax.distributed, "initialize", lambda **kw: calls.append(kw))
    return calls


def test_initialize_distributed_reads_the_launch(launch_env, monkeypatch):
    assert sharding.initialize_distributed() is False and launch_env == []
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "node001:1234")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "4")
    monkeypatch.setenv("JAX_PROCESS_ID", "3")
    assert sharding.initialize_distributed() is True
    assert launch_env == [{"coordinator_address": "node001:1234", "num_processes": 4,
                           "process_id": 3}]
    assert sharding.initialize_distributed("host:1", num_processes=2, process_id=0) is True
    assert launch_env[-1] == {"coordinator_address": "host:1", "num_processes": 2,
                              "process_id": 0}
    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: True)
    assert sharding.initialize_distributed() is False and len(launch_env) == 2  # once only


def test_initialize_distributed_leaves_an_srun_step_to_jax(launch_env, monkeypatch):
    slurm = {"SLURM_JOB_ID": "77", "SLURM_STEP_NODELIST": "node[001-002]", "SLURM_NTASKS": "1",
             "SLURM_PROCID": "0", "SLURM_LOCALID": "0"}
    for k, v in slurm.items():
        monkeypatch.setenv(k, v)
    assert sharding.initialize_distributed() is False  # one task: one process
    monkeypatch.setenv("SLURM_NTASKS", "8")
    assert sharding.initialize_distributed() is True
    assert launch_env == [{"coordinator_address": None, "num_processes": None,
                           "process_id": None}]


@pytest.mark.parametrize("env, match", [
    ({"JAX_COORDINATOR_ADDRESS": "node001:1234"}, "JAX_NUM_PROCESSES, JAX_PROCESS_ID"),
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}, "JAX_COORDINATOR_ADDRESS"),
    ({"JAX_COORDINATOR_ADDRESS": "node001", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"},
     "JAX_COORDINATOR_ADDRESS: expected host:port"),
    ({"JAX_COORDINATOR_ADDRESS": "n:1", "JAX_NUM_PROCESSES": "two", "JAX_PROCESS_ID": "0"},
     "JAX_NUM_PROCESSES: expected an int >= 1"),
    ({"JAX_COORDINATOR_ADDRESS": "n:1", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"},
     "JAX_PROCESS_ID: expected an int >= 0 and < 2"),
])
def test_initialize_distributed_refuses_a_partial_launch(launch_env, monkeypatch, env, match):
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(ValueError, match=match):
        sharding.initialize_distributed()
    assert launch_env == []  # refused before jax.distributed.initialize


def test_initialize_distributed_refuses_bad_arguments(launch_env):
    with pytest.raises(ValueError, match="num_processes: expected an int >= 1, got True"):
        sharding.initialize_distributed("host:1", num_processes=True, process_id=0)
    with pytest.raises(ValueError, match="process_id: expected an int >= 0 and < 2"):
        sharding.initialize_distributed("host:1", num_processes=2, process_id=5)
    assert launch_env == []


def test_to_host_of_one_process():
    tree = {"a": jax.numpy.arange(3.0), "b": np.ones((2, 2), np.int32)}
    out = sharding.to_host(tree)
    assert all(isinstance(x, np.ndarray) for x in jax.tree_util.tree_leaves(out))
    np.testing.assert_array_equal(out["a"], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(out["b"], tree["b"])
