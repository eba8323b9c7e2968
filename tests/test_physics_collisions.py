"""Which parts of a robot touch the floor, as a physics candidate: the geoms grouped by type
and size, a group's contacts switched by compiling the model again, a planted swap of the
Ant's foot spheres for its ankle capsules named exactly, clean data naming none, and a
calibrated.json carrying the switch into the model it loads."""

import mujoco
import numpy as np
import pytest

from rl2s_jax.physics.mjx_model import collision_groups, physics_model, switch_collisions

SIDES = ("left", "right", "third", "fourth")
ANKLES = [f"{s}_ankle_geom" for s in SIDES]
FEET = [f"{s}_foot_geom" for s in SIDES]
POLICIES = [4, 7, 16, 21]


@pytest.fixture(scope="module")
def pm():
    return physics_model("ant")


def _contacts(mj, qpos) -> int:
    data = mujoco.MjData(mj)
    data.qpos[:] = qpos
    mujoco.mj_forward(mj, data)
    return int(data.ncon)


def test_groups_and_switched_contacts(pm):
    groups = {tuple(g["names"]): g["collides"] for g in collision_groups(pm.mj)}
    assert groups[tuple(ANKLES)] is False and groups[tuple(FEET)] is True
    assert groups[("torso_geom",)] is False and len(groups) == 4  # the floor is the world's
    assert all(len(g["bodies"]) == len(g["names"]) for g in collision_groups(pm.mj))
    # the torso low enough that the ankles' capsules cross the floor
    qpos = pm.mj.qpos0.copy()
    qpos[2] = 0.05
    on = switch_collisions(pm.mj, pm.xml_path, dict.fromkeys(ANKLES, True))
    assert _contacts(on, qpos) > _contacts(pm.mj, qpos)
    assert on.opt.iterations == pm.mj.opt.iterations  # the model's options kept
    off = switch_collisions(pm.mj, pm.xml_path, dict.fromkeys(FEET, False))
    assert _contacts(off, qpos) == 0
    assert np.array_equal(pm.mj.geom_contype, physics_model("ant").mj.geom_contype)  # a copy
    with pytest.raises(ValueError, match="collisions: expected geom names .* 'shin'"):
        switch_collisions(pm.mj, pm.xml_path, {"shin": True})


def _ant_data(pm, changes):
    from rl2s_jax.physics.measured import Planted, collect_measured
    from rl2s_jax.policy import policy as pol
    from rl2s_jax.zoo import zoo as zoo_mod

    params = pol.index_params(zoo_mod.load_zoo("ant").params, POLICIES)
    return collect_measured(pm, params, transitions_per_policy=300, episode_length=100,
                            changes=[Planted(*c) for c in changes], seed=1)


def test_planted_swap_of_foot_geoms_is_named(pm):
    """Data whose ankles' capsules touch the floor in place of the foot spheres: neither
    switch alone explains it (the capsules' ends overlap the spheres), the swap does."""
    from rl2s_jax.physics.identify import FitConfig, identify

    planted = {**dict.fromkeys(ANKLES, True), **dict.fromkeys(FEET, False)}
    ds = _ant_data(pm, [("geom_collides", n, int(on)) for n, on in planted.items()])
    assert {t["element"] for t in ds.meta["source"]["planted"]} == set(planted)
    found = identify(pm, ds, FitConfig(rows=256))
    top = found["top_cause"]
    assert top is not None and top["name"] == "geom_collides", found["parameters"]
    assert top["element"] == f"{', '.join(ANKLES)}; {', '.join(FEET)}"
    assert (top["nominal"], top["value"]) == ("no; yes", "yes; no")
    assert found["collisions"] == planted and found["unexplained"] < 1e-6
    few, total = found["parameters"][0]["drop_episodes"]
    assert 0 < few <= total == len(set(ds.episode_id.tolist())) // 2
    clean = identify(pm, _ant_data(pm, []), FitConfig(rows=256))
    assert clean["top_cause"] is None and clean["collisions"] == {}, clean["parameters"]


def test_calibrated_json_carries_the_switch(pm):
    from rl2s_jax.physics.hybrid import calibrated_model

    content = {"task": "ant", "xml": pm.xml_path, "n_frames": pm.n_frames,
               "theta": [0.0] * len(pm.candidates), "delays": [0] * pm.action_size,
               "integrator": "RK4", "collisions": dict.fromkeys(ANKLES, True),
               "labels": [c.label for c in pm.candidates]}
    cal, theta, _ = calibrated_model(content)
    ankles = [mujoco.mj_name2id(cal.mj, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ANKLES]
    assert (cal.mj.geom_contype[ankles] == 1).all() and (pm.mj.geom_contype[ankles] == 0).all()
    assert cal.mj.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert [c.label for c in cal.candidates] == content["labels"]  # theta keeps its meaning
    assert theta.shape == (len(pm.candidates),)


def test_report_says_when_a_drop_lies_in_few_episodes():
    """A quantity not kept whose drop lies in under half of the test episodes (a rare contact:
    the paired t-test cannot pass) says so in report.md's "kept" cell."""
    from rl2s_jax.app.physics_diagnosis import _kept
    from rl2s_jax.physics.identify import _drop_episodes

    before = dict.fromkeys(range(4), 1.0)
    assert _drop_episodes(before, {0: 0.0, 1: 1.0, 2: 1.0, 3: 1.0}) == [1, 4]  # one episode
    # one large drop and three tiny ones (the other quantities refitted): still one episode
    assert _drop_episodes(before, {0: 0.0, 1: 0.99, 2: 0.99, 3: 0.99}) == [1, 4]
    assert _drop_episodes(before, dict.fromkeys(range(4), 0.75)) == [4, 4]  # spread evenly
    assert _drop_episodes(before, dict.fromkeys(range(4), 1.5)) == [0, 4]  # no drop

    assert _kept({"significant": False, "drop_episodes": [2, 25]}) == (
        "no: 90% of its drop is in 2 of 25 test episodes (more episodes where it acts decide)")
    assert _kept({"significant": False, "drop_episodes": [20, 25]}) == "no"
    assert _kept({"significant": True, "drop_episodes": [2, 25]}) == "yes"
    assert _kept({"significant": False}) == "no"  # a report from before the field
