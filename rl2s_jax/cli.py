"""The `rl2s` command line: zoo | collect | inspect | import | export | train | evaluate |
improve | pipeline | diagnose.

Argument parsing only: each command's flags become its typed spec (``app.specs``:
``spec_from_args``), and the command's one app function runs it (``app.specs.COMMANDS``). The
app modules are imported only then, on purpose: importing them loads JAX, brax and MuJoCo
(seconds), which ``rl2s --help`` and a bad argument should not wait for. The outputs a
command names are checked right after parsing, before any work, and earlier results there are
replaced only with ``--force`` (``OUTPUTS``, ``FORCED``, app/paths.py); Ctrl-C ends a command
with one line and status 130.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

from rl2s_jax.app.paths import FORCED, outputs_error, stopped_message
from rl2s_jax.app.specs import COMMANDS, SPECS, guard_choice_flags, spec_from_args


def _positive(name):
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{name}: expected a positive integer, got {text!r}") from None
        if value < 1:
            raise argparse.ArgumentTypeError(f"{name}: expected a positive integer, got {value}")
        return value
    return parse


def _gamma(text):
    value = float(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"gamma: expected a value in (0, 1], got {value}")
    return value


def _policy_ids(text):
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"policies: expected comma-separated indices such as 0,3,5, got {text!r}") from None


def _policy_source(p) -> None:
    p.add_argument("--zoo", help="zoo of the data's policies (default: what meta.source names)")
    p.add_argument("--policy-file", metavar="FILE", help="the data's policies in its policy_id "
                   "order, a save_policies file (docs/DATA.md), instead of a zoo")


def _recipe_and_guard_options(p, recipes) -> None:
    """--recipe (one of ``recipes``) and the deployment guard's options (on by default:
    rl2s_jax/app/improvement.py says why)."""
    p.add_argument("--recipe", choices=sorted(recipes), help="a measured fine-tuning recipe "
                   "for the task as the defaults, flags given win (improve/recipes.py)")
    p.add_argument("--guard-margin", type=float, metavar="M",
                   help="deploy a fine-tuned policy only where every elite member of the "
                   "simulator predicts a gain above M x |start value| (simulated); elsewhere "
                   "keep the start policy (default: 0.02)")
    p.add_argument("--guard-floor-scale", type=float, metavar="K", help="and above K x the "
                   "simulator's training MVD (default: the --recipe's, else 1; 0: no floor)")
    p.add_argument("--guard-episodes", type=_positive("guard-episodes"), default=16,
                   help="simulated episodes per policy and member for the guard")
    p.add_argument("--no-guard", action="store_true", help="deploy every fine-tuned policy")


def _improve_guard_options(p) -> None:
    """`rl2s improve`'s guard over snapshots and its choice of deployment guard (the interval
    guard: improve/gain_intervals.py; --guard and --guard-calibration are paper.py's too:
    ``guard_choice_flags``)."""
    p.add_argument("--guard-snapshots", action="store_true", help="keep the actor every "
                   "tenth of the iterations; of the snapshots that pass the guard, deploy the "
                   "one whose smallest predicted gain is largest (default: the final actor)")
    guard_choice_flags(p, "improve")


def _sim_env_options(p, default: str = "whole episodes from its start states") -> None:
    """The simulated env SAC fine-tunes in (MBPO branches, MOPO penalty)."""
    p.add_argument("--branch-length", type=_positive("branch-length"), help="MBPO: rollouts "
                   f"of this many steps from every real state of the data (default: {default})")
    p.add_argument("--uncertainty-penalty", type=float, metavar="LAMBDA",
                   help="MOPO: reward r - LAMBDA * u(s, a), u = the ensemble's disagreement in "
                   "units of its mean on the data (needs >= 2 elites)")


_EVALUATE_CKPT_HELP = ("checkpoint directory (DIR/checkpoints); repeat it for several simulators "
                       "of one task: each scored, and the policies whose values they disagree "
                       "on most")
_PHYSICS_HELP = ("a physics model in place of --ckpt: a calibrated.json of `rl2s diagnose "
                 "--physics`, or 'nominal' (the data's task's MuJoCo model)")


def build_parser() -> argparse.ArgumentParser:
    from rl2s_jax._names import IMPROVE_RECIPE_NAMES as IMPROVE_RECIPES
    from rl2s_jax._names import task_names
    from rl2s_jax.evaluate.setting import setting_flags, trust_flags

    parser = argparse.ArgumentParser(prog="rl2s", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("zoo", help="train SAC/PPO over seeds (resumable) and build a task's "
                       "policy zoo")
    p.add_argument("--task", required=True, choices=task_names())
    p.add_argument("--algo", choices=("sac", "ppo", "both"),
                   help="learner(s) (default: the task's, zoo/build.py DEFAULT_ALGO); both "
                   "pools the snapshots of SAC and PPO")
    p.add_argument("--seeds", type=_positive("seeds"), default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--env-steps", type=_positive("env-steps"),
                   help="env steps per seed and learner (default: ZOO_SAC / ZOO_PPO); a larger "
                   "value extends a finished run (its zoo at --out replaced with --force)")
    p.add_argument("--snapshots", type=_positive("snapshots"),
                   help="snapshots per seed along training (fixed when a run starts; default: "
                   "the task's plan, 40 for the MJX tasks)")
    p.add_argument("--set", action="append", metavar="LEARNER.FIELD=VALUE",
                   help="override a SACConfig/PPOConfig field, e.g. --set sac.batch_size=1024")
    p.add_argument("--work", help="run directory: checkpoints (resumed from), measured returns "
                   "(default: runs/zoo/<task>)")
    p.add_argument("--time-limit", type=float, metavar="SECONDS",
                   help="stop training, after a checkpoint, before this many seconds from the "
                   "start; the same command continues (leave time for compile and measuring)")
    p.add_argument("--final", action="store_true",
                   help="when the time limit stops training, build the zoo from the snapshots "
                   "trained so far (the last GPU call of a run)")
    p.add_argument("--checkpoint-every", type=float, default=120.0, metavar="SECONDS",
                   help="seconds of training between checkpoints (and one at every stop)")
    p.add_argument("--export", metavar="FILE", help="write the run (checkpoints) into one .npz "
                   "(or FILE.partNN) to resume on another machine with --import")
    p.add_argument("--export-max-mib", type=float, default=15.0,
                   help="largest export file; a bigger full state is exported without replay "
                   "buffers and env states, then split into parts if still too big")
    p.add_argument("--import", dest="import_file", metavar="FILE",
                   help="resume from an export for learners with no checkpoint in --work")
    p.add_argument("--value-episodes", type=_positive("value-episodes"), default=16)
    p.add_argument("--zoo-size", type=_positive("zoo-size"), default=60)
    p.add_argument("--extend", metavar="ZOO", help="grow a zoo (task or directory): learners from "
                   "another --seed add test policies filling its holes (ids, train split kept)")
    p.add_argument("--min-test", type=_positive("min-test"), default=20, help="for --extend")
    p.add_argument("--out", help="directory (default: rl2s_jax/zoo/shipped/<task>)")
    p.add_argument("--plots-only", action="store_true",
                   help="only redraw curves.png / returns_hist.png from --out's zoo.json and "
                   "train_log.jsonl")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("collect", help="collect a Dataset from a zoo split")
    p.add_argument("--task", required=True, choices=task_names())
    p.add_argument("--split", choices=("train", "test", "all"), default="train")
    p.add_argument("--transitions-per-policy", type=_positive("transitions-per-policy"),
                   required=True)
    p.add_argument("--envs-per-policy", type=_positive("envs-per-policy"))
    p.add_argument("--episode-length", type=_positive("episode-length"))
    p.add_argument("--gamma", type=_gamma, default=0.999)
    p.add_argument("--value-episodes", type=int, default=16,
                   help="fresh episodes per policy for its true value (0: skip)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--zoo", help="zoo directory (default: the shipped one)")
    p.add_argument("--out", required=True)

    p = sub.add_parser("inspect", help="validate a dataset file and print its summary")
    p.add_argument("--data", required=True)

    p = sub.add_parser("import", help="convert a local Minari dataset into a Dataset file")
    p.add_argument("--minari", required=True, metavar="PATH",
                   help="Minari dataset directory (or its data/), or the id of a dataset in "
                   "the local Minari root; nothing is downloaded")
    p.add_argument("--out", required=True, help="Dataset file to write (.npz)")
    p.add_argument("--task", help="registered task the data comes from (default: none, or "
                   "the one an rl2s export recorded)")
    p.add_argument("--gamma", type=_gamma, help="discount recorded in meta")
    p.add_argument("--policy-key", help="episode-metadata key naming each episode's policy "
                   "(default: policy_id, policy_name or policy; none: one policy)")

    p = sub.add_parser("export", help="write a Dataset file as a Minari dataset")
    p.add_argument("--minari", action="store_true", required=True,
                   help="the format to write (Minari, hdf5)")
    p.add_argument("--data", required=True, help="Dataset file (.npz)")
    p.add_argument("--out", required=True, help="new directory for the Minari dataset")
    p.add_argument("--dataset-id", help="Minari id, (namespace/)name-vN (default: the "
                   "directory name, -v0 added)")

    p = sub.add_parser("train", help="learn a simulator from a dataset (rl2s|gail|bc|rl2s-bc)")
    p.add_argument("--data", required=True, help="training Dataset (.npz)")
    p.add_argument("--method", choices=("rl2s", "gail", "bc", "rl2s-bc"), default="rl2s")
    p.add_argument("--steps", type=_positive("steps"), required=True,
                   help="total train_steps (a resumed run continues up to this)")
    p.add_argument("--out", required=True, help="run directory: checkpoints/, metrics.jsonl, "
                   "summary.json; resumes if it holds a checkpoint")
    p.add_argument("--eps", type=float, help="CVaR fraction (default 0.25 rl2s/rl2s-bc, 1 gail/bc)")
    p.add_argument("--no-task", action="store_true", help="learn reward and done from the data")
    p.add_argument("--physics", help="a hybrid: DIR/calibrated.json + a learned residual (bc)")
    _policy_source(p)
    p.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto",
                   help="network and batch sizes: gpu = paper sizes, cpu = small")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save-every", type=_positive("save-every"))
    p.add_argument("--chunk", type=_positive("chunk"), default=10,
                   help="train_steps per compiled scan between host logging")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a TrainConfig field, e.g. --set dynamics.obs_history=2")
    p.add_argument("--eval-data", help="Dataset of test policies: VD and ranking every "
                   "--eval-every steps -> OUT/eval.jsonl")
    p.add_argument("--eval-policies", metavar="FILE", help="the --eval-data policies in its "
                   "policy_id order, a save_policies file (as evaluate's --policy-file)")
    p.add_argument("--eval-every", type=_positive("eval-every"),
                   help="steps between test evaluations (default: --save-every or steps/10)")
    setting_flags(p, "eval-")
    p.add_argument("--resume-step", type=int, help="resume from this saved step (default: "
                   "the newest intact one); later steps are moved to checkpoints/superseded/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("evaluate", help="VD and ranking of a checkpoint's simulator on a "
                       "dataset's policies (fresh process, no training data)")
    p.add_argument("--ckpt", action="append", help=_EVALUATE_CKPT_HELP)
    p.add_argument("--oracle", action="store_true", help="evaluate the task's real dynamics "
                   "through the same path instead of a checkpoint (the ceiling)")
    p.add_argument("--physics", metavar="SRC", help=_PHYSICS_HELP)
    p.add_argument("--data", required=True, help="Dataset of the policies to evaluate")
    p.add_argument("--bootstrap", type=int, default=1000, help="bootstrap replicates for the "
                   "95%% intervals over episodes (0: none)")
    _policy_source(p)
    setting_flags(p, "")
    p.add_argument("--step", type=int, help="checkpoint step (default: the newest intact one; "
                   "broken newer steps are skipped with a warning)")
    p.add_argument("--json", help="write the report here")
    trust_flags(p)

    p = sub.add_parser("improve", help="fine-tune a Dataset's policies with SAC inside a "
                       "saved simulator; write them as a zoo, measure the real gain")
    p.add_argument("--ckpt", help="checkpoint directory (DIR/checkpoints)")
    p.add_argument("--physics", metavar="SRC", help=_PHYSICS_HELP)
    p.add_argument("--data", required=True, help="Dataset whose policies are fine-tuned (its "
                   "zoo or policy file gives the policies, its states the simulated starts)")
    p.add_argument("--policies", type=_policy_ids, help="indices into the data's policies, "
                   "e.g. 0,3,5 (default: all)")
    p.add_argument("--out", required=True, help="directory: zoo.npz/zoo.json, summary.json, "
                   "summary.md, policy_*.png")
    p.add_argument("--iterations", type=_positive("iterations"),
                   help="SAC iterations per policy (default: 1000, or the recipe's)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="a SACConfig field")
    p.add_argument("--episodes", type=_positive("episodes"), default=16, help="real episodes")
    _sim_env_options(p)
    p.add_argument("--uncertainty-threshold", type=float, help="MOReL: end a rollout when "
                   "u(s, a) exceeds this (same units); --halt-penalty: subtracted then")
    p.add_argument("--halt-penalty", type=float, default=0.0)
    _recipe_and_guard_options(p, IMPROVE_RECIPES)
    _improve_guard_options(p)
    _policy_source(p)
    p.add_argument("--step", type=int, help="checkpoint step (default: latest)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-measure", action="store_true", help="skip the real returns")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("pipeline", help="the whole pipeline for one task (make <task>)")
    p.add_argument("--task", required=True, choices=task_names())
    p.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="directory (default: results/<task>)")
    p.add_argument("--methods", default="rl2s,gail,bc,rl2s-bc")
    p.add_argument("--zoo", help="zoo directory to collect from (default: the task's shipped)")
    p.add_argument("--steps", type=_positive("steps"), help="train_steps per method")
    p.add_argument("--eval-every", type=_positive("eval-every"))
    setting_flags(p, "eval-")
    p.add_argument("--transitions-per-policy", type=_positive("transitions-per-policy"))
    p.add_argument("--value-episodes", type=_positive("value-episodes"))
    p.add_argument("--improve-iterations", type=int, help="SAC iterations per test policy in "
                   "each simulator (default: the --recipe's, else the profile's; 0: skip)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a fine-tuning SACConfig field, e.g. --set kl_weight=0.1")
    _sim_env_options(p, "the profile's")
    _recipe_and_guard_options(p, IMPROVE_RECIPES)
    p.add_argument("--episode-length", type=_positive("episode-length"),
                   help="shorter episodes than the task's (smoke runs)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")

    p = sub.add_parser("diagnose", help="where a simulator is wrong, why, and the fix's gain")
    p.add_argument("--data", required=True, help="Dataset (.npz), any task or none")
    p.add_argument("--ckpt", help="a simulator's checkpoint (default: fit the base model)")
    p.add_argument("--reference", help="a clean Dataset: name only what goes beyond it")
    p.add_argument("--out", required=True, help="directory for report.md, report.json, PNGs")
    p.add_argument("--seeds", type=int, default=3, help="model seeds for the gain (>= 1)")
    p.add_argument("--heldout", type=float, default=0.3, help="fraction of episodes held out")
    p.add_argument("--lags", type=_positive("lags"), default=5, help="past steps tests see")
    p.add_argument("--k-max", type=_positive("k-max"), default=20, help="k-step error's k")
    p.add_argument("--model-steps", type=_positive("model-steps"), help="steps of each model")
    p.add_argument("--value-episodes", type=_positive("value-episodes"), default=8)
    p.add_argument("--alpha", type=float, default=0.01, help="significance level")
    p.add_argument("--zoo", help="zoo of the data's policies, for the value views")
    p.add_argument("--seed", type=int, default=0, help="split and test seed")
    p.add_argument("--physics", action="store_true", help="name the wrong MuJoCo quantity "
                   "(the data's task, or --sim-xml FILE: your MJCF, obs = qpos ++ qvel)")
    p.add_argument("--sim-xml")
    p.add_argument("--sim-frames", type=_positive("sim-frames"))  # MJCF steps per step
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    for name in FORCED:
        sub.choices[name].add_argument("--force", action="store_true", help="replace the "
                                       "outputs an earlier run left there (default: refused)")
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        rc = _main(argv)
        sys.stdout.flush()  # a closed pipe shows here, not in the flush at exit
    except BrokenPipeError:
        # stdout closed early (`rl2s inspect ... | head -1`): quiet, as Python's docs advise
        # (library/signal.html, SIGPIPE): devnull takes stdout, so exit's flush finds no pipe.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)
    return rc


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    started = time.time()
    error = outputs_error(args)  # before any work: app/paths.py
    if error:
        parser.exit(2, f"rl2s {args.command}: error: {error}\n")
    try:  # from here on Ctrl-C is one line, the stack's imports included
        return _run(args)
    except KeyboardInterrupt:
        print(f"\nrl2s {args.command}: {stopped_message(args, started)}", file=sys.stderr)
        return 130


def _run(args) -> int:
    import warnings

    # brax warns on every env it builds that it is unmaintained; we use only its envs.
    warnings.filterwarnings("ignore", category=UserWarning, module="brax")
    warnings.filterwarnings("ignore", category=DeprecationWarning, module="brax")
    from rl2s_jax import compile_cache
    from rl2s_jax.train.checkpoint import CheckpointWarning

    compile_cache.enable()
    default_show = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        from rl2s_jax.zoo.likelihood import PolicyFileWarning  # where one warns: JAX is loaded
        if issubclass(category, (CheckpointWarning, PolicyFileWarning)):  # ours: one line
            print(f"rl2s {args.command}: warning: {message}", file=sys.stderr)
        else:
            default_show(message, category, filename, lineno, file, line)

    with warnings.catch_warnings():
        warnings.showwarning = show
        warnings.simplefilter("always", CheckpointWarning)
        try:
            spec = spec_from_args(SPECS[args.command], args)  # checked: errors name the field
            _, module, function = COMMANDS[args.command]
            return getattr(importlib.import_module(module), function)(spec)
        except (ValueError, FileNotFoundError, FloatingPointError) as err:
            print(f"rl2s {args.command}: error: {err}", file=sys.stderr)
            return 2

if __name__ == "__main__":
    sys.exit(main())
