"""experiments/step_ops.py: the update loops of a compiled step found in XLA's HLO text (a
synthetic program: loops by trip count, the random-bit hash's loop left out, the body's
no-work ops left out), and on a small compiled step, fewer ops per update with
flat_optimizer (the mechanism issue 63's lever relies on)."""
import pytest
from experiment_scripts import load_script

so = load_script("step_ops")

HLO = """HloModule m

%body.1 (p: (s32[], f32[4])) -> (s32[], f32[4]) {
  %p = (s32[], f32[4]) parameter(0)
  %a = f32[4]{0} get-tuple-element(%p), index=1
  %f = f32[4]{0} fusion(%a), kind=kLoop, calls=%fused
  %d = f32[4]{0} dot(%f, %f), lhs_contracting_dims={0}
  %g = f32[4]{0} fusion(%d), kind=kLoop, calls=%fused2
  ROOT %t = (s32[], f32[4]) tuple(%i, %g)
}

%rounds (p: (s32[], u32[2])) -> (s32[], u32[2]) {
  %p = (s32[], u32[2]) parameter(0)
  %c = u32[2]{0} copy(%x)
  ROOT %t = (s32[], u32[2]) tuple(%i, %c)
}

ENTRY %main (x: f32[4]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %w = (s32[], f32[4]) while(%t0), condition=%c1, body=%body.1,
    metadata={op_name="jit(f)/while"}, backend_config={"known_trip_count":{"n":"50"}}
  %r = (s32[], u32[2]) while(%t1), condition=%c2, body=%rounds,
    metadata={op_name="jit(f)/jit(_uniform)/while"},
    backend_config={"known_trip_count":{"n":"5"}}
  %o = (s32[], f32[4]) while(%t0), condition=%c1, body=%body.1,
    backend_config={"known_trip_count":{"n":"7"}}
  ROOT %y = f32[4]{0} get-tuple-element(%w), index=1
}
""".replace(",\n    ", ", ")  # one line per instruction, as XLA writes them


def test_update_loops_reads_the_bodies_of_the_asked_trip_counts():
    rows = so.update_loops(HLO, {50, 5})
    assert len(rows) == 1  # the x5 loop is the random-bit hash's; x7 was not asked for
    assert rows[0]["trip_count"] == 50 and rows[0]["op_name"] == "jit(f)/while"
    assert rows[0]["kinds"] == {"fusion": 2, "dot": 1} and rows[0]["ops"] == 3
    assert [r["trip_count"] for r in so.update_loops(HLO, {7})] == [7]


@pytest.mark.slow
def test_flat_optimizer_leaves_fewer_ops_per_update():
    from rl2s_jax.train.config import TrainConfig

    ops = {}
    for flat in (False, True):
        cfg = TrainConfig.small(task="hopper", method="rl2s", flat_optimizer=flat,
                                updates_per_step=3, vd_every=0, eps=1.0)
        rows = so.step_loops(cfg, n_policies=4)
        ops[flat] = {r["trip_count"]: r["ops"] for r in rows}  # the largest body per count
        assert set(ops[flat]) == {3, 2}  # the generator updates, the critic updates
    assert ops[True][3] < ops[False][3] and ops[True][2] < ops[False][2], ops
