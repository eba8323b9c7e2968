"""One typed spec per `rl2s` command: a frozen dataclass of exactly the command's options (the
flags' dests, with the flags' defaults), checked when it is made, naming the field as its flag.
``rl2s_jax.cli`` builds one from the parsed flags (``spec_from_args``) and hands it to the
command's one app function (``COMMANDS``); from Python, make the spec and call the same
function, e.g. ``run_collect(CollectSpec(task="pointmass", transitions_per_policy=50,
out="d.npz"))``. ``--force`` is not a spec field: it is the door's (app/paths.py), checked
before any spec is made. ``guard_choice_flags``: --guard and --guard-calibration, one
definition for `rl2s improve` and experiments/paper.py (next to their checks here).

Standard library only: ``import rl2s_jax.cli`` loads this and must load no JAX.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os

from rl2s_jax._names import IMPROVE_RECIPE_NAMES

# command -> (its spec class's name, the app module, the function that runs it -> exit status)
COMMANDS = {
    "zoo": ("ZooSpec", "rl2s_jax.app.zoo_building", "run_zoo"),
    "collect": ("CollectSpec", "rl2s_jax.app.datasets", "run_collect"),
    "inspect": ("InspectSpec", "rl2s_jax.app.datasets", "run_inspect"),
    "import": ("ImportSpec", "rl2s_jax.app.datasets", "run_import"),
    "export": ("ExportSpec", "rl2s_jax.app.datasets", "run_export"),
    "train": ("TrainSpec", "rl2s_jax.app.training", "run_train"),
    "evaluate": ("EvaluateSpec", "rl2s_jax.app.evaluation", "run_evaluate"),
    "improve": ("ImproveSpec", "rl2s_jax.app.improvement", "run_improve"),
    "pipeline": ("PipelineSpec", "rl2s_jax.app.pipeline", "run_pipeline"),
    "diagnose": ("DiagnoseSpec", "rl2s_jax.app.diagnosis", "run_diagnose"),
}


GUARDS = ("floor", "interval")  # improve.finetune.deployment_guard, improve.gain_intervals
# The front ends that offer the guards (rl2s improve, experiments/paper.py) -> what --guard
# picks there, and which files --guard-calibration reads there: the rest of their help is one.
GUARD_CONTEXTS = {
    "improve": ("the guard that deploys",
                "a saved calibration {task, level, q, floor, n}, or results of paper.py "
                "--policy-split validation --guard-margin M on the task pooled at level 0.9"),
    "paper": ("the guard whose figures are the result's (both are recorded with "
              "--guard-calibration)",
              "results of paper.py --policy-split validation --guard-margin M on this task "
              "pooled at --trust-level (needs --guard-margin)"),
}


def guard_choice_flags(p: argparse.ArgumentParser, context: str) -> None:
    """--guard {floor, interval} (default floor) and --guard-calibration FILE [FILE ...] on a
    front end's parser; ``context``: a key of ``GUARD_CONTEXTS``, the front end."""
    if context not in GUARD_CONTEXTS:
        raise ValueError(f"context: expected one of {sorted(GUARD_CONTEXTS)}, got {context!r}")
    picks, files = GUARD_CONTEXTS[context]
    p.add_argument("--guard", choices=GUARDS, default="floor", help=f"{picks}: floor (every "
                   "elite member's gain above the margin and floor) or interval (the lower end "
                   "of the predicted relative gain's conformal interval above 0; needs "
                   "--guard-calibration)")
    p.add_argument("--guard-calibration", nargs="+", metavar="FILE", help="the interval "
                   "guard's conformal calibration (fine-tuned policies with known real gains, "
                   f"never the guarded ones): {files}")


def _flag(name: str) -> str:
    return name.replace("_", "-")


def _check_ints(spec, names, low: int = 1) -> None:
    """Each named field None or an int >= ``low``, else ValueError naming its flag."""
    for name in names:
        v = getattr(spec, name)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < low):
            raise ValueError(f"{_flag(name)}: expected an int >= {low}, got {v!r}")


def _check_required(spec, names) -> None:
    for name in names:
        if getattr(spec, name) is None:
            raise ValueError(f"{_flag(name)}: required")


def check_floor_scale(scale: float | None) -> float | None:
    """``scale`` (the guard's floor as a multiple of the training MVD; None: not given), or a
    ValueError naming --guard-floor-scale unless it is finite and >= 0."""
    if scale is not None and not (math.isfinite(scale) and scale >= 0):
        raise ValueError(f"guard-floor-scale: expected a finite float >= 0, got {scale!r}")
    return scale


def check_no_guard_alone(spec) -> None:
    """--no-guard with --guard-margin, --guard-snapshots or --guard-floor-scale is refused
    (``spec``: a spec or parsed flags of improve / pipeline)."""
    if spec.no_guard:
        given = [o for o, on in (
            ("--guard-margin", spec.guard_margin is not None),
            ("--guard-snapshots", getattr(spec, "guard_snapshots", False)),
            ("--guard-floor-scale", getattr(spec, "guard_floor_scale", None) is not None),
            ("--guard interval", getattr(spec, "guard", "floor") == "interval")) if on]
        if given:
            raise ValueError(f"no-guard: turns the deployment guard off; drop {given[0]}")


def _check_guard(spec) -> None:
    """The deployment guard's flags (improve, pipeline): --guard-floor-scale finite and >= 0,
    --no-guard alone, a known --recipe, --guard-margin finite and >= 0."""
    check_floor_scale(spec.guard_floor_scale)
    check_no_guard_alone(spec)
    if spec.recipe is not None and spec.recipe not in IMPROVE_RECIPE_NAMES:
        raise ValueError(f"recipe: expected one of {sorted(IMPROVE_RECIPE_NAMES)}, got "
                         f"{spec.recipe!r}")
    m = spec.guard_margin
    if m is not None and not (math.isfinite(m) and m >= 0):
        raise ValueError(f"guard-margin: expected a finite float >= 0, got {m!r}")


def _check_interval_guard(spec) -> None:
    """`rl2s improve --guard {floor,interval}` and --guard-calibration: the interval guard
    needs a calibration file (present; its content is read before any work by
    ``improve.gain_intervals.read_calibration``) and takes none of the floor guard's options,
    and the floor guard takes no calibration."""
    if spec.guard not in GUARDS:
        raise ValueError(f"guard: expected floor or interval, got {spec.guard!r}")
    if spec.guard == "floor":
        if spec.guard_calibration:
            raise ValueError("guard-calibration: the interval guard's calibration; add "
                             "--guard interval (the default floor guard takes none)")
        return
    if not spec.guard_calibration:
        raise ValueError("guard: 'interval' needs --guard-calibration FILE (a saved calibration "
                         "or paper.py validation-split results with known real gains)")
    given = [f for f, on in (("--guard-margin", spec.guard_margin is not None),
                             ("--guard-floor-scale", spec.guard_floor_scale is not None),
                             ("--guard-snapshots", spec.guard_snapshots)) if on]
    if given:
        raise ValueError(f"guard: 'interval' deploys where the lower end of the predicted "
                         f"gain's interval is above 0; {given[0]} is the floor guard's, drop it")
    if spec.physics is not None:
        raise ValueError("guard: 'interval' is calibrated on learned simulators' elite-member "
                         "spread, and a physics model has one member; use the floor guard")
    for p in spec.guard_calibration:
        if not os.path.isfile(p):
            raise ValueError(f"guard-calibration: no such file {p}")


def _check_physics(spec) -> None:
    """--physics (evaluate, improve) in place of --ckpt / --oracle, not beside them."""
    if spec.physics is None:
        return
    given = [f for f, on in (("--ckpt", spec.ckpt), ("--oracle", getattr(spec, "oracle", False)),
                             ("--step", spec.step is not None),
                             ("--calibration", getattr(spec, "calibration", None))) if on]
    if given:
        raise ValueError(f"physics: the physics model is the simulator in place of a "
                         f"checkpoint; drop {given[0]}")
    if not spec.physics:
        raise ValueError("physics: expected a calibrated.json path or 'nominal', got ''")
    given = [f for f, on in (("--uncertainty-penalty", getattr(spec, "uncertainty_penalty", 0)),
                             ("--uncertainty-threshold",
                              getattr(spec, "uncertainty_threshold", None) is not None),
                             ("--recipe", getattr(spec, "recipe", None))) if on]
    if given:
        raise ValueError(f"physics: {given[0]} uses a learned ensemble's disagreement (MOPO's "
                         f"penalty, MOReL's stop rule; --recipe control penalises it), and a "
                         f"physics model has none; drop it")


@dataclasses.dataclass(frozen=True)
class ZooSpec:
    """`rl2s zoo`: train (or continue) a task's zoo learners, then measure, choose, split."""

    task: str
    algo: str | None = None
    seeds: int = 4
    seed: int = 0
    env_steps: int | None = None
    snapshots: int | None = None
    set: list[str] | None = None
    work: str | None = None
    time_limit: float | None = None
    final: bool = False
    checkpoint_every: float = 120.0
    export: str | None = None
    export_max_mib: float = 15.0
    import_file: str | None = None
    value_episodes: int = 16
    zoo_size: int = 60
    extend: str | None = None
    min_test: int = 20
    out: str | None = None
    plots_only: bool = False
    quiet: bool = False

    def __post_init__(self):
        _check_ints(self, ("seeds", "env_steps", "snapshots", "value_episodes", "zoo_size",
                           "min_test"))
        if self.time_limit is not None and self.time_limit <= 0 and not self.plots_only:
            raise ValueError(f"time-limit: expected seconds > 0, got {self.time_limit}")


@dataclasses.dataclass(frozen=True)
class CollectSpec:
    """`rl2s collect`: a Dataset from a zoo split, written to ``out``."""

    task: str
    transitions_per_policy: int
    out: str
    split: str = "train"
    envs_per_policy: int | None = None
    episode_length: int | None = None
    gamma: float = 0.999
    value_episodes: int = 16
    seed: int = 0
    zoo: str | None = None

    def __post_init__(self):
        _check_ints(self, ("transitions_per_policy", "envs_per_policy", "episode_length"))
        _check_ints(self, ("value_episodes",), low=0)
        if self.split not in ("train", "test", "all"):
            raise ValueError(f"split: expected train, test or all, got {self.split!r}")


@dataclasses.dataclass(frozen=True)
class InspectSpec:
    """`rl2s inspect`: validate a Dataset file and print its summary."""

    data: str


@dataclasses.dataclass(frozen=True)
class ImportSpec:
    """`rl2s import`: a local Minari dataset -> a Dataset file."""

    minari: str
    out: str
    task: str | None = None
    gamma: float | None = None
    policy_key: str | None = None


@dataclasses.dataclass(frozen=True)
class ExportSpec:
    """`rl2s export --minari`: a Dataset file -> a new Minari dataset directory."""

    data: str
    out: str
    minari: bool = True
    dataset_id: str | None = None

    def __post_init__(self):
        if self.minari is not True:
            raise ValueError("minari: the one format export writes; expected True")


@dataclasses.dataclass(frozen=True)
class TrainSpec:
    """`rl2s train`: learn a simulator from a Dataset into the run directory ``out``
    (``app.training.run_training(spec)``). ``set``: TrainConfig overrides, the flag's
    "key=value" strings or, from Python, a {key: value} dict."""

    data: str
    steps: int
    out: str
    method: str = "rl2s"
    eps: float | None = None
    no_task: bool = False
    zoo: str | None = None
    policy_file: str | None = None
    profile: str = "auto"
    seed: int = 0
    save_every: int | None = None
    chunk: int = 10
    set: list[str] | dict | None = None
    eval_data: str | None = None
    eval_policies: str | None = None
    eval_every: int | None = None
    eval_episodes: int | None = None
    eval_horizon: int | None = None
    eval_seed: int | None = None
    truth: str | None = None
    resume_step: int | None = None
    quiet: bool = False
    physics: str | None = None

    def __post_init__(self):
        _check_ints(self, ("steps", "save_every", "chunk", "eval_every", "eval_episodes",
                           "eval_horizon"))
        if self.method not in ("rl2s", "gail", "bc", "rl2s-bc"):
            raise ValueError(f"method: expected rl2s, gail, bc or rl2s-bc, got {self.method!r}")
        if self.profile not in ("auto", "cpu", "gpu"):
            raise ValueError(f"profile: expected auto, cpu or gpu, got {self.profile!r}")
        if not (self.set is None or isinstance(self.set, dict) or (
                isinstance(self.set, list | tuple) and all(isinstance(x, str) for x in self.set))):
            raise ValueError(f"set: expected 'key=value' strings or a {{key: value}} dict, got "
                             f"{self.set!r}")


@dataclasses.dataclass(frozen=True)
class EvaluateSpec:
    """`rl2s evaluate`: VD and ranking of one or more checkpoints' simulators (or, with
    ``oracle``, the real dynamics) on a Dataset's policies."""

    data: str
    ckpt: list[str] | None = None
    oracle: bool = False
    bootstrap: int = 1000
    zoo: str | None = None
    policy_file: str | None = None
    episodes: int | None = None
    horizon: int | None = None
    seed: int | None = None
    truth: str | None = None
    step: int | None = None
    json: str | None = None
    level: float = 0.9  # each policy's value interval at this level (0: none; evaluate/trust.py)
    calibration: list[str] | None = None  # Datasets the intervals are calibrated on
    physics: str | None = None  # a calibrated.json or "nominal" in place of a checkpoint

    def __post_init__(self):
        _check_physics(self)
        _check_ints(self, ("episodes", "horizon"))
        _check_ints(self, ("bootstrap",), low=0)
        if isinstance(self.level, bool) or not isinstance(self.level, int | float) \
                or not 0 <= self.level < 1:
            raise ValueError(f"level: expected a coverage level in [0, 1) such as 0.9 (0: no "
                             f"intervals), got {self.level!r}")


@dataclasses.dataclass(frozen=True)
class ImproveSpec:
    """`rl2s improve`: fine-tune a Dataset's policies with SAC inside a saved simulator, deploy
    them through the guard, write them as a zoo and measure the real gain."""

    data: str
    out: str
    ckpt: str | None = None
    physics: str | None = None  # a calibrated.json or "nominal" in place of the checkpoint
    policies: list[int] | None = None
    iterations: int | None = None
    set: list[str] | None = None
    episodes: int = 16
    branch_length: int | None = None
    uncertainty_penalty: float | None = None
    uncertainty_threshold: float | None = None
    halt_penalty: float = 0.0
    recipe: str | None = None
    guard_margin: float | None = None
    guard_floor_scale: float | None = None
    guard_episodes: int = 16
    no_guard: bool = False
    guard_snapshots: bool = False
    guard: str = "floor"  # or "interval" (the lower end of the predicted gain's interval > 0)
    guard_calibration: list[str] | None = None  # the interval guard's calibration file(s)
    zoo: str | None = None
    policy_file: str | None = None
    step: int | None = None
    seed: int = 0
    no_measure: bool = False
    quiet: bool = False

    def __post_init__(self):
        _check_physics(self)
        if self.ckpt is None and self.physics is None:
            raise ValueError("ckpt: required (a checkpoint directory), or --physics SRC")
        _check_guard(self)
        _check_interval_guard(self)
        _check_ints(self, ("iterations", "episodes", "branch_length", "guard_episodes"))
        if self.episodes < 2 and not self.no_measure:
            raise ValueError(f"episodes: expected >= 2 (for standard errors), got "
                             f"{self.episodes}")


@dataclasses.dataclass(frozen=True)
class PipelineSpec:
    """`rl2s pipeline`: collect, train the methods, evaluate, fine-tune, report, for a task."""

    task: str
    profile: str = "auto"
    seed: int = 0
    out: str | None = None
    methods: str = "rl2s,gail,bc,rl2s-bc"
    zoo: str | None = None
    steps: int | None = None
    eval_every: int | None = None
    eval_episodes: int | None = None
    eval_horizon: int | None = None
    eval_seed: int | None = None
    truth: str | None = None
    transitions_per_policy: int | None = None
    value_episodes: int | None = None
    improve_iterations: int | None = None
    set: list[str] | None = None
    branch_length: int | None = None
    uncertainty_penalty: float | None = None
    recipe: str | None = None
    guard_margin: float | None = None
    guard_floor_scale: float | None = None
    guard_episodes: int = 16
    no_guard: bool = False
    episode_length: int | None = None
    quiet: bool = False

    def __post_init__(self):
        _check_ints(self, ("steps", "eval_every", "eval_episodes", "eval_horizon",
                           "transitions_per_policy", "value_episodes", "branch_length",
                           "guard_episodes", "episode_length"))
        _check_ints(self, ("improve_iterations",), low=0)
        _check_guard(self)
        if self.profile not in ("auto", "cpu", "gpu"):
            raise ValueError(f"profile: expected auto, cpu or gpu, got {self.profile!r}")


@dataclasses.dataclass(frozen=True)
class DiagnoseSpec:
    """`rl2s diagnose`: where a simulator of a Dataset is wrong, why, and the extension's
    gain, into the directory ``out``."""

    data: str
    out: str
    ckpt: str | None = None
    reference: str | None = None
    seeds: int = 3
    heldout: float = 0.3
    lags: int = 5
    k_max: int = 20
    model_steps: int | None = None
    value_episodes: int = 8
    alpha: float = 0.01
    zoo: str | None = None
    seed: int = 0
    physics: bool = False  # the MuJoCo model's diagnosis instead (app/physics_diagnosis.py)
    sim_xml: str | None = None
    sim_frames: int | None = None
    quiet: bool = False

    def __post_init__(self):
        _check_ints(self, ("sim_frames",))
        if not 0.0 < self.heldout < 1.0:
            raise ValueError(f"heldout: expected a fraction in (0, 1), got {self.heldout}")
        if isinstance(self.seeds, bool) or not isinstance(self.seeds, int) or self.seeds < 1:
            raise ValueError(f"seeds: expected an int >= 1, got {self.seeds}")
        _check_ints(self, ("lags", "k_max", "model_steps", "value_episodes"))


SPECS = {name: globals()[cls] for name, (cls, _, _) in COMMANDS.items()}


def spec_from_args(spec_class, args: argparse.Namespace):
    """The spec of a parsed command: each field from the Namespace attribute of its name
    (every field is one of the command's flags' dests)."""
    return spec_class(**{f.name: getattr(args, f.name)
                         for f in dataclasses.fields(spec_class)})


__all__ = ["COMMANDS", "GUARDS", "GUARD_CONTEXTS", "SPECS", "check_floor_scale",
           "check_no_guard_alone", "guard_choice_flags", "spec_from_args",
           *(cls for cls, _, _ in COMMANDS.values())]
