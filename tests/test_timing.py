"""rl2s_jax._timing (issue 63: where the data phase's seconds go): the union of compile spans
against a NumPy grid, a part's compile / run split on a fresh jit, and the data phase's parts
through ``collect`` and ``paper.protocol.load_or_collect`` on a tiny pointmass zoo: the parts
named in order, logged as the lines experiments/gpu_profile.py reads, and the data the same
bit for bit with and without the timer."""
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import load_script
from jax._src import monitoring as jax_monitoring

from rl2s_jax._timing import PartTimer, timed, union_seconds


def test_union_of_spans_against_a_grid():
    rng = np.random.default_rng(0)
    for _ in range(50):
        starts = rng.uniform(0, 10, 6)
        spans = list(zip(starts, starts + rng.uniform(0, 3, 6), strict=True))
        a, b = sorted(rng.uniform(-1, 12, 2))
        grid = np.arange(a, b, 1e-3) + 5e-4
        covered = np.zeros(grid.shape, bool)
        for s, e in spans:
            covered |= (grid >= s) & (grid < e)
        assert union_seconds(spans, a, b) == pytest.approx(covered.sum() * 1e-3, abs=3e-3)
    assert union_seconds([(0.0, 2.0), (1.0, 3.0), (0.5, 1.5)], 0.0, 10.0) == pytest.approx(3.0)
    assert union_seconds([], 0.0, 1.0) == 0.0


def test_a_part_splits_compilation_from_the_rest():
    calls = []
    timer = PartTimer(on_part=lambda name, s: calls.append((name, s)))
    x = jnp.arange(1000.0)
    f = jax.jit(lambda v: jnp.cumsum(jnp.sin(v) * 3.0 + 0.123456))  # new: compiles here
    with timer.part("prog", split_compile=True):
        t0 = time.time()
        f(x).block_until_ready()
        first = time.time() - t0
        time.sleep(0.2)  # host time, not compilation
    assert [c[0] for c in calls] == ["prog_compile", "prog_run"]
    compile_s, run_s = timer.seconds["prog_compile"], timer.seconds["prog_run"]
    assert 0 < compile_s <= first and run_s >= 0.2
    with timer.part("prog", split_compile=True):  # compiled already: nothing to compile
        f(x).block_until_ready()
    assert timer.seconds["prog_compile"] == pytest.approx(compile_s, abs=1e-3)  # added 0
    with timer.part("host"):
        time.sleep(0.05)
    assert list(timer.seconds) == ["prog_compile", "prog_run", "host"]
    assert timer.seconds["host"] >= 0.05


def test_a_raising_part_records_nothing_and_stops_listening():
    timer = PartTimer()
    before = len(jax_monitoring.get_event_time_span_listeners())
    with pytest.raises(RuntimeError), timer.part("bad", split_compile=True):
        raise RuntimeError("boom")
    assert timer.seconds == {}
    assert len(jax_monitoring.get_event_time_span_listeners()) == before
    with timed(None, "nothing", split_compile=True):  # no timer: a plain block
        pass


@pytest.fixture(scope="module")
def pm_zoo():
    """A pointmass zoo of 4 policies (train 0-1, test 2-3)."""
    from rl2s_jax.policy import policy as pol
    from rl2s_jax.zoo import zoo as zoo_mod

    ps = []
    for i, b in enumerate([-2.0, 0.0, 1.0, 2.0]):
        p = pol.init_policy(jax.random.PRNGKey(i), 2, 1, hidden=(8,))
        p["layers"][-1]["b"] = p["layers"][-1]["b"].at[:1].set(b)
        ps.append(p)
    return zoo_mod.Zoo(task="pointmass", params=pol.stack_params(ps),
                       returns=np.zeros(4, np.float32), return_se=np.zeros(4, np.float32),
                       origins=[{}] * 4, train_ids=[0, 1], test_ids=[2, 3], info={})


def _fields(ds):
    return {k: v for k, v in ds.arrays().items() if v is not None}


def test_collect_times_its_parts_and_keeps_the_data(pm_zoo, env_cache):
    from rl2s_jax.data.collect import COLLECT_PARTS, collect

    kw = dict(key=jax.random.PRNGKey(3), transitions_per_policy=60, envs_per_policy=2,
              episode_length=20, chunk_steps=10, task="pointmass", value_episodes=3,
              progress=False)
    plain = collect(env_cache("pointmass"), pm_zoo.params, **kw)
    timer = PartTimer()
    timed_ds = collect(env_cache("pointmass"), pm_zoo.params, timer=timer, **kw)
    assert tuple(timer.seconds) == COLLECT_PARTS
    assert all(s >= 0 for s in timer.seconds.values())
    a, b = _fields(plain), _fields(timed_ds)
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        assert a[k].dtype == b[k].dtype, k
    assert plain.meta == timed_ds.meta


def test_load_or_collect_logs_the_data_parts(pm_zoo, tmp_path, monkeypatch, capsys):
    from rl2s_jax.app import pipeline
    from rl2s_jax.paper import protocol

    for mod in (pipeline, protocol):
        monkeypatch.setattr(mod, "load_zoo", lambda task: pm_zoo)
    sizes = {"transitions_per_policy": 40, "value_episodes": 2}
    args = ("pointmass", sizes)
    timings = {}
    timed_ds, reused = protocol.load_or_collect(*args, str(tmp_path / "a"), 5, 20, False,
                                                timings=timings, t_start=time.perf_counter())
    assert not reused
    want = ["data_setup", "data_rollout_compile", "data_rollout_run", "data_rollout_host",
            "data_values_compile", "data_values_run", "data_split_save"]
    assert list(timings) == want
    phase = load_script("gpu_profile").PHASE
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("[paper]")]
    assert [phase.match(ln).group(1) for ln in lines] == want
    for ln in lines:
        name, seconds = phase.match(ln).group(1, 2)
        assert float(seconds) == pytest.approx(timings[name], abs=0.051)
    plain, _ = protocol.load_or_collect(*args, str(tmp_path / "b"), 5, 20, False)
    assert capsys.readouterr().out == ""  # no timings: no lines
    for split in ("train", "test"):
        a, b = _fields(plain[split]), _fields(timed_ds[split])
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{split} {k}")
    timings = {}
    _, reused = protocol.load_or_collect(*args, str(tmp_path / "a"), 5, 20, False,
                                         timings=timings)
    assert reused and list(timings) == ["data_load"]
