"""experiments/xml_ladder.py: the ladder's last rung is Gymnasium v5's model (no physical
difference left), its rungs are edits of the task's XML text (numbers not edited stay as
written), and on a small Ant-v5 dataset the task's model errs and the last rung does not."""
import json

import mujoco
import numpy as np
import pytest
from experiment_scripts import load_script

from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.physics import gymnasium_v5 as g5
from rl2s_jax.physics.mjx_model import load_mj
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

xl = load_script("xml_ladder")


@pytest.mark.parametrize("task", sorted(xl.LADDERS))
def test_the_last_rung_is_v5s_model(task):
    rungs = xl.rung_xmls(task)
    assert [r[0] for r in rungs][1:] == ["+ " + label for label, _ in xl.LADDERS[task]]
    first = mujoco.MjModel.from_xml_string(rungs[0][1])
    nominal = load_mj(task)  # the task's XML unedited: its own model, number for number
    for field in ("body_mass", "geom_size", "jnt_range", "geom_friction", "geom_margin"):
        np.testing.assert_array_equal(getattr(first, field), getattr(nominal, field))
    before = {d["quantity"] for d in g5.model_differences(task, model=first)}
    assert {"opt.integrator", "opt.iterations"} <= before
    last = mujoco.MjModel.from_xml_string(rungs[-1][1])
    left = {(d["quantity"], d["element"]) for d in g5.model_differences(task, model=last)}
    # no physics left: MJX's float32 (a fact of the task), Walker2d's rootz reference (the
    # coordinate convention the observation map handles)
    assert left <= {("precision", ""), ("qpos0", "rootz")}, left


@pytest.fixture(scope="module")
def ant_v5(tmp_path_factory):
    """One Ant zoo policy in Ant-v5: 60 transitions in 30-step episodes."""
    ds = g5.collect_gymnasium("ant", index_params(load_zoo("ant").params, np.array([0])),
                              transitions_per_policy=60, episode_length=30, value_episodes=1,
                              gamma=0.9, seed=2, policy_names=["ant-000"],
                              source={"zoo": "ant", "zoo_ids": [0]})
    path = tmp_path_factory.mktemp("v5") / "v5.npz"
    save_dataset(path, ds)
    return path


def test_the_ladder_closes_the_error_on_ant_v5_data(ant_v5, tmp_path):
    out = tmp_path / "ladder.json"
    assert xl.main(["--data", str(ant_v5), "--task", "ant", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    errors = [r["one_step"] for r in res["rows"]]
    assert len(errors) == len(xl.LADDERS["ant"]) + 1
    assert errors[0] > 1e-2 and errors[-1] < 1e-4, errors
    assert errors[1] < errors[0]  # RK4 alone already helps
    assert {d["quantity"] for d in res["left_differences"]} == {"precision"}


def test_bad_input_is_named(ant_v5, tmp_path):
    with pytest.raises(SystemExit, match="--data: expected a Dataset"):
        xl.main(["--data", str(tmp_path / "missing.npz"), "--task", "ant"])
    with pytest.raises(SystemExit, match="its task is 'ant', expected 'walker2d'"):
        xl.main(["--data", str(ant_v5), "--task", "walker2d"])
