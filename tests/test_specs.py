"""One shape for every command (issue 65 item 6): each `rl2s` command is a typed spec of exactly
its flags (app/specs.py), made by ``spec_from_args`` and run by one app function that takes it;
cli.py only declares flags. Standard library only: nothing here loads JAX."""

import ast
import dataclasses
import math
import pathlib

import pytest

from rl2s_jax import cli
from rl2s_jax.app.specs import COMMANDS, SPECS, ImproveSpec, spec_from_args

APP = pathlib.Path(cli.__file__).parent / "app"
DOOR_ONLY = {"help", "force"}  # --force is the door's (app/paths.py), not the command's


def _subparsers():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_spec_fields_are_exactly_the_flags_with_their_defaults(command):
    actions = {a.dest: a for a in _subparsers()[command]._actions if a.dest not in DOOR_ONLY}
    fields = {f.name: f for f in dataclasses.fields(SPECS[command])}
    assert set(fields) == set(actions), (f"{command}: spec fields without a flag "
                                         f"{sorted(set(fields) - set(actions))}, flags without "
                                         f"a field {sorted(set(actions) - set(fields))}")
    for name, action in actions.items():
        f = fields[name]
        if action.required:
            assert f.default is dataclasses.MISSING or action.const is True, name
        else:
            assert f.default == action.default, (f"{command} --{name}: spec default "
                                                 f"{f.default!r}, flag default "
                                                 f"{action.default!r}")


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_each_command_has_one_app_function_taking_its_spec(command):
    """The function COMMANDS names is defined in its app module with one parameter annotated
    with the command's spec class (read from the source: importing it would load JAX)."""
    spec_class, module, function = COMMANDS[command]
    path = APP / f"{module.rsplit('.', 1)[1]}.py"
    defs = {n.name: n for n in ast.walk(ast.parse(path.read_text()))
            if isinstance(n, ast.FunctionDef)}
    assert function in defs, f"{module} has no {function}"
    args = defs[function].args
    assert [a.arg for a in args.args] == ["spec"]
    assert ast.unparse(args.args[0].annotation) == spec_class


def test_run_training_takes_the_train_spec():
    """run_training, the Python door to `rl2s train` (pipeline, examples), takes the same
    TrainSpec as run_train, not the flags again as keywords: (spec, log) and nothing else; a
    TrainSpec's ``set`` is the flag's strings or a dict, anything else is refused."""
    defs = {n.name: n for n in ast.walk(ast.parse((APP / "training.py").read_text()))
            if isinstance(n, ast.FunctionDef)}
    args = defs["run_training"].args
    assert [a.arg for a in args.args + args.kwonlyargs] == ["spec", "log"]
    assert ast.unparse(args.args[0].annotation) == "TrainSpec"
    TrainSpec = SPECS["train"]
    assert TrainSpec("d.npz", 3, "run", set={"vd_horizon": 5}).set == {"vd_horizon": 5}
    assert TrainSpec("d.npz", 3, "run", set=["vd_horizon=5"]).set == ["vd_horizon=5"]
    with pytest.raises(ValueError, match="set: expected"):
        TrainSpec("d.npz", 3, "run", set=5)


def test_the_command_line_only_maps_flags():
    """cli.py defines no command bodies: its functions are the parser's helpers and the door."""
    tree = ast.parse(pathlib.Path(cli.__file__).read_text())
    names = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert names == {"_positive", "_gamma", "_policy_ids", "_policy_source",
                     "_recipe_and_guard_options", "_improve_guard_options", "_sim_env_options",
                     "build_parser", "main",
                     "_main", "_run"}


def test_spec_from_args_and_checks_that_name_the_field():
    args = cli.build_parser().parse_args(
        ["improve", "--ckpt", "c", "--data", "d.npz", "--out", "o", "--policies", "0,2",
         "--guard-margin", "0.1"])
    spec = spec_from_args(ImproveSpec, args)
    assert (spec.ckpt, spec.policies, spec.guard_margin, spec.episodes) == ("c", [0, 2], 0.1, 16)
    base = dict(ckpt="c", data="d.npz", out="o")
    for kwargs, message in (
            (dict(episodes=1), "episodes: expected >= 2"),
            (dict(iterations=0), "iterations: expected an int >= 1, got 0"),
            (dict(guard_margin=math.inf), "guard-margin: expected a finite float >= 0"),
            (dict(no_guard=True, guard_snapshots=True),
             "no-guard: turns the deployment guard off; drop --guard-snapshots"),
            (dict(recipe="fast"), "recipe: expected one of ['control'], got 'fast'"),
            (dict(guard_floor_scale=-1.0), "guard-floor-scale: expected a finite float >= 0")):
        with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
            ImproveSpec(**base, **kwargs)
    assert ImproveSpec(**base, episodes=1, no_measure=True).episodes == 1
    with pytest.raises(ValueError, match=r"heldout: expected a fraction in \(0, 1\), got 1.5"):
        SPECS["diagnose"](data="d.npz", out="o", heldout=1.5)
    with pytest.raises(ValueError, match="time-limit: expected seconds > 0, got -1"):
        SPECS["zoo"](task="pointmass", time_limit=-1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.seed = 3


def test_a_bad_spec_field_is_one_line_and_status_2(capsys):
    """A check of the spec (not of argparse) reaches the user as the command's one-line error."""
    assert cli.main(["diagnose", "--data", "d.npz", "--out", "/tmp/rl2s-spec-test-never",
                     "--heldout", "2"]) == 2
    assert capsys.readouterr().err.strip() == ("rl2s diagnose: error: heldout: expected a "
                                               "fraction in (0, 1), got 2.0")
