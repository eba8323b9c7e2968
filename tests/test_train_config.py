"""TrainConfig's nested shape (issue 65 item 6): the generator's DynamicsSpec and the
adversarial, VD and outcome groups; the flat saved format of before still loads to the same
config; the saved format carries a version and round-trips; --set takes dotted names and,
for one release, the flat ones; an unknown name is refused in one line with a did-you-mean."""

import dataclasses
import json
import pathlib
from types import SimpleNamespace

import pytest

from rl2s_jax.app.training import make_config, parse_overrides
from rl2s_jax.model.dynamics import DynamicsSpec
from rl2s_jax.train.config import (
    CONFIG_VERSION,
    FLAT_NAMES,
    GROUPS,
    LEGACY_MODEL,
    TrainConfig,
    known_names,
    saved_field,
)

# TrainConfig.to_dict() of the flat format, written by the old writer (the branch's code
# before the groups); see its "about"
FLAT_SAMPLES = json.loads((pathlib.Path(__file__).parent / "data"
                           / "train_config_flat_v0.json").read_text())["configs"]


def _flat(cfg: TrainConfig) -> dict:
    """A config in the flat format's names and JSON values."""
    back = {v: k for k, v in FLAT_NAMES.items()}
    return json.loads(json.dumps({back.get(k, k): v for k, v in cfg.to_dotted().items()}))


@pytest.mark.parametrize("name", sorted(FLAT_SAMPLES))
def test_flat_configs_of_before_load_field_by_field(name):
    """Every saved flat config loads; each of its 59 (or, saved before two fields, 57) values
    is the new config's at the field's dotted name, the fields it lacks take the values its run
    had (``physics``, ``scan_unroll``, ``batches_up_front`` and ``flat_optimizer``, added after
    the flat format: None, no hybrid; 1, no unrolling; false, batches drawn in each update;
    false, the optimisers per leaf); and the nested config writes back the same flat values."""
    flat = FLAT_SAMPLES[name]
    cfg = TrainConfig.from_saved(flat).validate()
    dotted = cfg.to_dotted()
    assert len(dotted) == 63
    for key, value in flat.items():
        got = dotted[FLAT_NAMES.get(key, key)]
        assert json.loads(json.dumps(got)) == value, key
    assert _flat(cfg) == {"gen_activation": "relu", "matmul_dtype": "float32", "physics": None,
                          "scan_unroll": 1, "batches_up_front": False, "flat_optimizer": False,
                          **flat}


def test_flat_configs_of_before_are_todays_named_configs():
    expected = {
        "default": TrainConfig(), "small": TrainConfig.small(),
        "legacy_model": TrainConfig().override(LEGACY_MODEL),
        "before_activation_field": TrainConfig.small(),
        "history_learned": TrainConfig.small().override({
            "task": "pointmass", "method": "gail",
            "dynamics": DynamicsSpec(hidden=(64, 64), noise="global", log_std_bounds="learned",
                                     activation="relu", obs_history=2, action_history=3,
                                     time_inputs=("step",), context_dim=4, context_hidden=(16,),
                                     matmul_dtype="bfloat16"),
            "outcome.reward": "learned", "outcome.termination": "hazard",
            "outcome.hazard_window": 3, "outcome.reward_hidden": (32,), "vd.horizon": 77,
            "vd.every": 3, "vd.episodes": 5, "adversarial.disc_hidden": (8, 8),
            "adversarial.sim_envs": 7, "adversarial.nll_on": "both"})}
    assert set(expected) == set(FLAT_SAMPLES)
    for name, cfg in expected.items():
        assert TrainConfig.from_saved(FLAT_SAMPLES[name]) == cfg, name


def test_the_saved_format_has_a_version_and_round_trips():
    cfg = TrainConfig.from_saved(FLAT_SAMPLES["history_learned"])
    saved = json.loads(json.dumps(cfg.to_dict()))
    assert saved["version"] == CONFIG_VERSION == 2
    assert saved["dynamics"]["obs_history"] == 2 and "obs_history" not in saved
    assert set(saved) - {"version"} == {f.name for f in dataclasses.fields(TrainConfig)}
    assert TrainConfig.from_dict(saved) == cfg == TrainConfig.from_saved(saved)
    assert hash(TrainConfig.from_dict(saved)) == hash(cfg)  # a static jit argument
    assert saved_field(saved, "vd.horizon") == 77 == saved_field(FLAT_SAMPLES["history_learned"],
                                                                 "vd.horizon")
    assert saved_field(saved, "gamma") == cfg.gamma and saved_field({}, "vd.every", 5) == 5
    with pytest.raises(ValueError, match="version 3"):
        TrainConfig.from_dict({**saved, "version": 3})
    with pytest.raises(ValueError, match="unknown config field 'bogus'"):
        TrainConfig.from_dict({**saved, "bogus": 1})


def test_history_lengths_live_in_one_place():
    """The history inputs are the DynamicsSpec's fields alone: no other field of TrainConfig
    or its groups holds them."""
    names = known_names()
    assert [n for n in names if "history" in n] == ["dynamics.action_history",
                                                    "dynamics.obs_history"]
    assert [n for n in names if n.endswith(("time_inputs", "context_dim"))] == [
        "dynamics.time_inputs", "dynamics.context_dim"]
    assert set(GROUPS) <= {f.name for f in dataclasses.fields(TrainConfig)}
    assert isinstance(TrainConfig().dynamics, DynamicsSpec)


def test_set_takes_dotted_and_flat_names_and_refuses_unknown_ones():
    """--set dynamics.obs_history=2 and the flat obs_history=2 build the same config, through
    make_config as `rl2s train` does; an unknown name is one line naming the closest one."""
    ds = SimpleNamespace(meta={"task": "pointmass", "episode_length": 100, "gamma": 0.99})
    dotted = make_config(ds, "bc", "cpu", overrides=parse_overrides(
        ["dynamics.obs_history=2", "vd.horizon=40", "adversarial.sim_envs=4",
         "outcome.hazard_window=2", "batch_size=32", "dynamics.hidden=[16, 16]"]))
    flat = make_config(ds, "bc", "cpu", overrides=parse_overrides(
        ["obs_history=2", "vd_horizon=40", "sim_envs=4", "hazard_window=2", "batch_size=32",
         "gen_hidden=[16, 16]"]))
    assert dotted == flat
    assert (dotted.dynamics.obs_history, dotted.vd.horizon, dotted.adversarial.sim_envs,
            dotted.outcome.hazard_window, dotted.dynamics.hidden) == (2, 40, 4, 2, (16, 16))
    assert make_config(ds, "bc", "cpu") != dotted
    for bad, hint in (("dynamics.obs_histroy", "dynamics.obs_history"),
                      ("obs_histroy", "dynamics.obs_history"), ("vd_horizn", "vd.horizon"),
                      ("vd.horizn", "vd.horizon"), ("adversarial.nll_wieght",
                                                   "adversarial.nll_weight")):
        with pytest.raises(ValueError) as err:
            make_config(ds, "bc", "cpu", overrides={bad: 2})
        assert str(err.value) == (f"set: unknown config field {bad!r}; did you mean "
                                  f"{hint!r}?")
    with pytest.raises(ValueError, match=r"^set: unknown config field 'zzz'; known: [^\n]*$"):
        make_config(ds, "bc", "cpu", overrides={"zzz": 1})


def test_override_takes_a_group_whole_or_as_a_dict_and_keeps_the_rest():
    base = TrainConfig.small()
    spec = dataclasses.replace(base.dynamics, obs_history=3)
    assert base.override({"dynamics": spec}).dynamics == spec
    both = base.override({"dynamics": spec, "dynamics.action_history": 1})
    assert (both.dynamics.obs_history, both.dynamics.action_history) == (3, 1)
    as_dict = base.override({"vd": {"every": 2}})
    assert as_dict.vd == dataclasses.replace(base.vd, every=2) and as_dict.dynamics == \
        base.dynamics
    assert base.override({"time_inputs": ["step"]}).dynamics.time_inputs == ("step",)


@pytest.mark.parametrize("key, value, field", [
    ("dynamics.obs_history", -1, "dynamics.obs_history"),
    ("vd.episodes", 0, "vd.episodes"),
    ("adversarial.sim_envs", 0, "adversarial.sim_envs"),
    ("adversarial.nll_on", "some", "adversarial.nll_on"),
    ("outcome.reward", "guess", "outcome.reward"),
    ("outcome.hazard_steps", -1, "outcome.hazard_steps"),
    ("dynamics", {"hidden": ()}, "dynamics.hidden"),
    ("vd", "x", "vd: expected a VDConfig"),
])
def test_a_bad_group_field_is_named_by_its_dotted_name(key, value, field):
    cfg = TrainConfig.small(task="pointmass")
    bad = (dataclasses.replace(cfg, vd=value) if key == "vd"
           else cfg.override({key: value}))
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        bad.validate()


def test_rl2s_train_refuses_an_unknown_set_name_in_one_line_before_any_work(tmp_path, capsys):
    from test_cli_doors import tiny_dataset

    from rl2s_jax import cli

    data = tiny_dataset(tmp_path / "d.npz")
    out = tmp_path / "run"
    assert cli.main(["train", "--data", data, "--steps", "1", "--out", str(out), "--quiet",
                     "--set", "dynamics.obs_history=1", "--set", "obs_histroy=2"]) == 2
    err = capsys.readouterr().err
    assert err == ("rl2s train: error: set: unknown config field 'obs_histroy'; did you mean "
                   "'dynamics.obs_history'?\n")
    assert not out.exists()
