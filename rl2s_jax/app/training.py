"""`rl2s train`: from a Dataset file to a trained, checkpointed simulator (files in, files out)."""

from __future__ import annotations

import json
import os
import re
import sys
import time

import jax
import numpy as np

from rl2s_jax._files import read_jsonl, write_json, write_text
from rl2s_jax.app.report import machine_info
from rl2s_jax.app.specs import TrainSpec
from rl2s_jax.app.value_intervals import NO_INTERVAL
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import TASKS, data_task
from rl2s_jax.evaluate.scores import evaluate_simulator
from rl2s_jax.evaluate.setting import EvalSetting, profile_horizon
from rl2s_jax.physics.hybrid import hybrid_config, physics_meta, residual_data
from rl2s_jax.train.checkpoint import Checkpointer
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.learned import heldout_errors, learned_lines
from rl2s_jax.train.loop import TrainingDiverged, fit
from rl2s_jax.train.step import init, simulator
from rl2s_jax.zoo.zoo import policies_for

# The cpu profile's members: TrainConfig.small's 2x64 at 5 updates per step had not fitted
# Hopper (held-out error 0.385 change stds; these: 0.140, experiments/model_fit.py on the CPU).
CPU_MODEL = {"dynamics.hidden": (128, 128, 128), "dynamics.activation": "silu",
             "batch_size": 256, "updates_per_step": 25, "early_stop_patience": 0,
             "gen_weight_decay": 0.0}


def make_config(ds, method: str, profile: str, eps: float | None = None,
                overrides: dict | None = None, no_task: bool = False):
    """The TrainConfig for ``ds``: 'gpu' = the paper's sizes with the ensemble model family
    (7 members of 4x512 SiLU, 5 elites, batch 1024, 1000 pre-training steps; TrainConfig's
    defaults), 'cpu' = ``TrainConfig.small`` with the members fitted as the gpu profile fits
    them (3 of 3x128 SiLU, batch 256, 25 updates per step, no early stopping or weight decay:
    docs/RESULTS.md, "make hopper"), 100 pre-training steps and 5 critic warm-up steps.
    ``overrides``: name -> value (``--set``; ``TrainConfig.override``'s names: dotted
    "dynamics.obs_history", or for one release the flat format's "obs_history").

    Data of no registered task (``meta.task`` null) or ``no_task`` (--no-task): the reward is
    learned from the data's rewards (``outcome.reward`` "learned") and episodes end by the
    hazard learned from its done flags (``outcome.termination`` "hazard"), unless ``overrides`` say
    otherwise; its time limit is ``data_episode_length``. A ``meta.task`` that is not
    registered is refused without ``no_task`` (``envs.tasks.data_task``).

    ``overrides["physics"]`` (``--physics``): a hybrid of that calibrated.json's physics and a
    learned residual (``physics.hybrid.hybrid_config``: checked against the data, VD off)."""

    data_task(ds.meta["task"], no_task)
    ep_len = ds.meta.get("episode_length") or 1000
    base = {"task": ds.meta["task"], "method": method, "eps": eps,
            "gamma": float(ds.meta.get("gamma") or 0.999)}
    if ds.meta["task"] not in TASKS or no_task:
        base.update({"outcome.reward": "learned", "outcome.termination": "hazard",
                     "data_episode_length": ds.meta.get("episode_length")})
    if profile == "cpu":
        cfg = TrainConfig.small().override({
            "vd.horizon": profile_horizon("cpu", ep_len), "adversarial.pretrain_steps": 100,
            "adversarial.disc_warmup_steps": 5, **CPU_MODEL, **base})
    elif profile == "gpu":
        cfg = TrainConfig().override({"vd.horizon": profile_horizon("gpu", ep_len), **base})
    else:
        raise ValueError(f"profile: expected 'cpu' or 'gpu', got {profile!r}")
    cfg = cfg.override(overrides, what="set")
    if cfg.physics is not None:
        cfg = hybrid_config(cfg, ds)
    return cfg.validate()


def run_training(spec: TrainSpec, log=print) -> dict:
    """`rl2s train` from Python: load ``spec.data``, train a simulator with checkpoints in
    ``spec.out`` (resuming if it holds one), and return a summary dict (also written to
    out/summary.json); ``log`` takes its lines. ``spec.set``: "key=value" strings (the
    flag's) or a {key: value} mapping, TrainConfig's overrides.

    A resumed run starts from ``resume_step``, or by default from the newest intact
    checkpoint (broken newer ones are skipped with a CheckpointWarning). Saved steps after the
    one resumed from are moved to checkpoints/corrupt/ (broken) or checkpoints/superseded/
    (intact), since the run saves those steps anew.

    ``eval_data``: a Dataset of other (test) policies, evaluated every ``eval_every`` steps
    with VD and ranking metrics appended to out/eval.jsonl (the AVD/MVD-over-training curve),
    and at the last step: the summary's test numbers are the final checkpoint's, in the
    setting of the eval flags (``EvalSetting.from_flags``; its horizon by default the
    config's vd_horizon), the numbers `rl2s evaluate` gives that checkpoint in the same
    setting; its policies from ``eval_policies`` (a policy file, checked as ``policy_file`` is,
    before any training work), else from ``zoo`` or what its meta.source names. The training
    policies: from ``zoo``, ``policy_file`` or what the data's meta.source names
    (``zoo.policies_for``). The summary's ``learned`` block holds the simulator's reward and
    termination errors on the held-out episodes (``train.learned.heldout_errors``).
    """
    if not isinstance(spec, TrainSpec):
        raise TypeError(f"spec: expected a TrainSpec, got {type(spec).__name__}")
    if spec.eval_policies is not None and spec.eval_data is None:
        raise ValueError("eval-policies: these are the policies of a test Dataset; give it "
                         "with --eval-data TEST")
    ds = load_dataset(spec.data)
    profile = spec.profile
    if profile == "auto":
        profile = "gpu" if jax.default_backend() == "gpu" else "cpu"
    overrides = dict(spec.set) if isinstance(spec.set, dict) else parse_overrides(spec.set)
    if spec.physics is not None:  # a hybrid (rl2s_jax.physics.hybrid)
        overrides["physics"] = spec.physics
    cfg = make_config(ds, spec.method, profile, spec.eps, overrides, spec.no_task)
    _say_what_runs(spec, ds, cfg, log)
    policies = policies_for(ds, spec.zoo, policy_file=spec.policy_file, data_path=spec.data)
    eval_path = os.path.join(spec.out, "eval.jsonl")
    on_eval, last_test, eval_every = None, {}, spec.eval_every
    if spec.eval_data is not None:  # its data and policies checked before any training work
        setting = EvalSetting.from_flags(spec.eval_episodes, spec.eval_horizon, spec.eval_seed,
                                         spec.truth)
        on_eval = _test_evaluator(spec.eval_data, cfg, eval_path, setting, spec.zoo,
                                  last_test, spec.eval_policies)
        eval_every = eval_every or spec.save_every or max(1, spec.steps // 10)
    data = make_train_data(residual_data(ds, cfg.physics), policies, cfg)  # a hybrid's residual
    os.makedirs(spec.out, exist_ok=True)
    ck = Checkpointer(os.path.join(spec.out, "checkpoints"))
    meta = {"data": {"path": os.path.abspath(spec.data), "task": ds.meta["task"],
                     "obs_size": ds.obs_size, "action_size": ds.action_size,
                     "n_policies": ds.n_policies, "policy_names": ds.meta.get("policy_names"),
                     "gamma": ds.meta.get("gamma"),
                     "true_value": np.asarray(data.true_value).tolist()},
            "seed": spec.seed, "profile": profile, **physics_meta(cfg.physics)}
    metrics_path = os.path.join(spec.out, "metrics.jsonl")
    state = _start_state(spec, cfg, data, ck, (metrics_path, eval_path), log,
                         f"profile {profile}) on {spec.data}: {ds.n_transitions} transitions, "
                         f"{ds.n_policies} policies")
    t0 = time.perf_counter()
    start = int(state.step)
    jumps: list[str] = []
    try:
        state, _ = fit(state, data, spec.steps, chunk=spec.chunk, checkpointer=ck,
                       save_every=spec.save_every, meta=meta, metrics_path=metrics_path,
                       progress=not spec.quiet, eval_every=eval_every, on_eval=on_eval,
                       on_warning=lambda text: (jumps.append(text), log(text)))
    finally:
        ck.close()
    if on_eval is not None and last_test.get("step_test") != int(state.step):
        # the final checkpoint's test numbers, when no chunk here ended on an evaluation (a
        # rerun of a finished run replaces its row of that step)
        _truncate_metrics(eval_path, int(state.step) - 1)
        on_eval(state)
    summary = _summary(spec, profile, cfg, state, data, ds, start, time.perf_counter() - t0,
                       jumps, last_test)
    if start > 0:  # resumed: what the earlier summary held stays
        keep_earlier(summary, os.path.join(spec.out, "summary.json"), start)
    write_json(os.path.join(spec.out, "summary.json"), summary)
    return summary


def _say_what_runs(spec: TrainSpec, ds, cfg: TrainConfig, log) -> None:
    """Log where the reward and termination come from without a registered task, and warn
    when the run ends inside pre-training."""
    if not cfg.registered or spec.no_task:
        log(f"[train] {spec.data}: "
            f"{'--no-task' if spec.no_task else 'data of no registered task'} "
            f"(meta.task {ds.meta.get('task')!r}): reward {cfg.outcome.reward!r}, termination "
            f"{cfg.outcome.termination!r} (a reward head r(s, a, s') fitted on its rewards, the "
            f"hazard h(s, a) on its done flags; their held-out errors are in the summary)")
    pretrain = cfg.adversarial.pretrain_steps
    if cfg.pretrains and spec.steps <= pretrain:
        log(f"[train] warning: --steps {spec.steps} ends inside the {pretrain} "
            f"pre-training steps of {spec.method}: this run is maximum likelihood on every "
            f"policy (as bc) and never reaches the adversarial phase; "
            f"{pretrain - spec.steps + 1} more step(s) reach it (--steps "
            f"{pretrain + 1} or more, or --set adversarial.pretrain_steps=N)")


def _start_state(spec: TrainSpec, cfg: TrainConfig, data, ck: Checkpointer, logs, log,
                 what: str):
    """The TrainState to train from: the checkpoint resumed (``spec.resume_step`` or the
    newest intact one; the logs in ``logs`` cut back to its step), else a fresh ``init``
    (the logs removed; ``what``: the profile and data, for its log line)."""
    key = jax.random.PRNGKey(spec.seed)
    if spec.resume_step is not None and ck.latest_step() is None:
        ck.close()
        raise FileNotFoundError(f"resume_step: {spec.out}/checkpoints holds no saved step to "
                                f"resume step {spec.resume_step} from")
    if ck.latest_step() is None:
        for path in logs:
            if os.path.exists(path):
                os.remove(path)
        t0 = time.perf_counter()
        state = jax.jit(init, static_argnums=1)(key, cfg, data)
        log(f"[train] {spec.method} (eps {cfg.initial_eps}, {what}; init "
            f"{time.perf_counter() - t0:.1f}s")
        return state
    template = jax.eval_shape(lambda: init(key, cfg, data))
    try:
        state = ck.restore(template, spec.resume_step)
    except BaseException:
        ck.close()
        raise
    moved = ck.set_aside_after(int(state.step))
    for path in logs:
        _truncate_metrics(path, int(state.step))
    log(f"[train] resuming {spec.out} from step {int(state.step)}")
    for kind, steps_moved in moved.items():
        if steps_moved:
            log(f"[train] moved {kind} step(s) {steps_moved} to {ck.directory}/{kind}/")
    return state


def _summary(spec: TrainSpec, profile: str, cfg: TrainConfig, state, data, ds, start: int,
             seconds: float, jumps: list[str], last_test: dict) -> dict:
    """summary.json of a run that trained from step ``start`` to ``state.step``."""
    names = ds.meta.get("policy_names") or [str(i) for i in range(ds.n_policies)]
    vd = np.asarray(state.vd)
    return {
        "method": spec.method, "eps": float(state.eps), "profile": profile,
        "steps": int(state.step), "steps_run": int(state.step) - start,
        "seconds": round(seconds, 2), "backend": jax.default_backend(),
        "machine": machine_info(), "avd_train": float(np.mean(vd)),
        "mvd_train": float(np.max(vd)), "checkpoint": os.path.join(spec.out, "checkpoints"),
        "pretrain_steps_left": (max(0, cfg.adversarial.pretrain_steps + 1 - int(state.step))
                                if cfg.pretrains else 0),
        "vd_measured_by": {"source": "simulated, the last completed VD measurement of the "
                           "training policies", "episodes": cfg.vd.episodes,
                           "horizon": cfg.vd.horizon, "gamma": cfg.gamma},
        "worst_vd_jumps": jumps,
        "learned": None if cfg.physics else heldout_errors(simulator(state), data),
        **last_test,
        "selected": [n for n, s in zip(names, np.asarray(state.selected), strict=True) if s],
        "policies": {n: {"true_value": float(t), "sim_value": float(s), "vd": float(v)}
                     for n, t, s, v in zip(names, np.asarray(data.true_value),
                                           np.asarray(state.sim_value), vd, strict=True)},
        "config": state.config.to_dict()}


def keep_earlier(summary: dict, path: str, resumed_from: int) -> None:
    """Keep in ``summary`` (of a run resumed from step ``resumed_from``) what the run's
    earlier summary at ``path`` held up to that step and this one would drop: the last test
    evaluation (``--eval-data``'s keys, when this invocation made none) and the worst-VD
    warnings (earlier ones first). Their keys go in ``kept_from_earlier``. A rerun without
    the earlier flags must not erase results, and resuming stays a feature, so nothing is
    refused."""
    try:
        with open(path) as f:
            earlier = json.load(f)
    except (OSError, ValueError):
        return
    if not isinstance(earlier, dict):
        return
    if earlier.get("step_test", 0) > resumed_from:  # of steps set aside since: not kept
        earlier = {"worst_vd_jumps": earlier.get("worst_vd_jumps")}
    kept = [k for k in earlier if k not in summary and k != "kept_from_earlier"]
    summary.update({k: earlier[k] for k in kept})
    jumps = [j for j in earlier.get("worst_vd_jumps") or []
             if j not in summary["worst_vd_jumps"] and _jump_step(j) <= resumed_from]
    if jumps:
        summary["worst_vd_jumps"] = jumps + summary["worst_vd_jumps"]
        kept.append("worst_vd_jumps")
    if kept:
        summary["kept_from_earlier"] = kept


def _jump_step(text: str) -> int:
    """The step a worst-VD warning names ("... at step N ..."); 0 if it names none."""
    match = re.search(r"at step (\d+)", text)
    return int(match.group(1)) if match else 0


def _test_evaluator(eval_data: str, cfg, path: str, setting: EvalSetting,
                    zoo: str | None, last: dict, policy_file: str | None = None):
    """on_eval callback: VD and ranking of the eval Dataset's policies, appended to ``path``;
    the latest also in ``last`` (keys ending ``_test``, for summary.json) and returned (for
    the progress bar, beside the training policies' avd / mvd: keys ending ``_test``).
    The policies: ``policy_file`` (``--eval-policies``; as ``rl2s evaluate --policy-file``,
    refused unless it holds the eval data's policies), else ``zoo`` or the data's source."""

    if cfg.physics is not None:
        raise ValueError("eval_data: training's evaluation would roll the residual model "
                         "alone, not the hybrid; score the hybrid after training with "
                         "`rl2s evaluate --ckpt OUT/checkpoints`")
    ds = load_dataset(eval_data)
    if ds.meta.get("task") != cfg.task:
        raise ValueError(f"eval_data: {eval_data} is task {ds.meta.get('task')!r}, training is "
                         f"{cfg.task!r}")
    if policy_file is not None:
        pols = policies_for(ds, policy_file=policy_file, data_path=eval_data,
                            flag="eval-policies")
    else:
        try:
            pols = policies_for(ds, zoo, data_path=eval_data, flag="eval-policies")
        except ValueError as err:  # say which Dataset's policies are unknown
            raise ValueError(f"eval_data: {eval_data}: {err}") from None
    setting = setting.resolve(ds.meta.get("episode_length"), cfg.vd.horizon)
    key = setting.key()

    def on_eval(state):
        r = evaluate_simulator(simulator(state), ds, pols, key=key, n_episodes=setting.episodes,
                               horizon=setting.horizon, truth=setting.truth)  # data's gamma
        row = {"step": int(state.step), **r["metrics"], "vd": r["vd"],
               "setting": setting.to_dict(), "true_value_source": r["true_value_source"]}
        with open(path, "a") as f:  # appended: safe as metrics.jsonl is (train.loop.fit)
            f.write(json.dumps(row) + "\n")
        last.clear()
        last.update({f"{k}_test": v for k, v in r["metrics"].items()})
        last.update(step_test=int(state.step), eval_data=eval_data,
                    eval_policies=policy_file, setting_test=setting.to_dict(), measured_by_test={
            "source": f"simulated vs the eval data's {r['true_value_source']} true values",
            "episodes": setting.episodes, "horizon": setting.horizon, "gamma": r["gamma"],
            "seed": setting.seed, "truth": setting.truth,
            "true_value_source": r["true_value_source"]})
        return {f"{k}_test": r["metrics"][k] for k in ("avd", "mvd", "kendall_tau")
                if k in r["metrics"]}

    return on_eval


def run_train(spec: TrainSpec) -> int:
    """`rl2s train`'s body: ``run_training(spec)``, then its summary table; 1 where training
    diverged."""
    if not os.path.exists(spec.data):
        raise FileNotFoundError(f"data: no such file {spec.data}")
    try:
        summary = run_training(spec)
    except TrainingDiverged as err:
        print(f"rl2s train: {err}", file=sys.stderr)
        return 1
    print(format_summary(summary))
    return 0


def train_hybrid(data_path: str, physics: str, steps: int, out: str, *,
                 overrides: dict | None = None, log=print, **kw) -> dict:
    """`rl2s train --physics PHYSICS --method bc`: the hybrid of a calibrated.json's physics
    and a residual learned by likelihood (rl2s_jax.physics.hybrid), checkpointed in ``out``;
    ``overrides``: TrainConfig's (``--set``), ``kw``: TrainSpec's other fields. Load it with
    ``physics.hybrid.load_hybrid`` (as `rl2s evaluate` does). -> the summary."""
    spec = TrainSpec(data=data_path, steps=steps, out=out, method="bc", physics=physics,
                     set=dict(overrides or {}), **kw)
    return run_training(spec, log)


def _truncate_metrics(path: str, step: int) -> None:
    """Drop logged rows after ``step`` (they belong to a run that went past its checkpoint)."""
    if not os.path.exists(path):
        return
    rows = [row for row in read_jsonl(path) if row["step"] <= step]  # a torn last line goes
    write_text(path, "".join(json.dumps(row) + "\n" for row in rows))


def format_summary(s: dict) -> str:
    """A one-screen table of a run_training summary."""
    lines = [f"method {s['method']} (eps {s['eps']:g}), {s['steps']} steps "
             f"({s['steps_run']} here in {s['seconds']:.1f}s on {s['backend']}), profile "
             f"{s['profile']}",
             f"train policies: AVD {s['avd_train']:.3g}  MVD {s['mvd_train']:.3g}  "
             f"(VD at the last completed measurement: {_by(s.get('vd_measured_by'))})"]
    if "avd_test" in s:
        pf = f", policies of {s['eval_policies']}" if s.get("eval_policies") else ""
        lines.append(f"test policies ({s['eval_data']}{pf}, step {s['step_test']}): AVD "
                     f"{s['avd_test']:.3g}  MVD {s['mvd_test']:.3g}  Kendall tau "
                     f"{s['kendall_tau_test']:.3f}  ({_by(s['measured_by_test'])})")
    physics = (s.get("config") or {}).get("physics")
    if physics:
        lines.append(f"hybrid: the calibrated physics of {physics} + the learned residual (VD "
                     f"not measured in training; score it with rl2s evaluate --ckpt)")
    if s.get("learned"):
        lines.extend(learned_lines(s["learned"]))
    if s.get("pretrain_steps_left"):
        lines.append(f"note: still pre-training (maximum likelihood): "
                     f"{s['pretrain_steps_left']} more step(s) reach the adversarial phase")
    lines.append(f"{'policy':<14}{'true value':>12}{'sim value':>12}{'VD':>10}  selected")
    for name, p in s["policies"].items():
        mark = "*" if name in s["selected"] else ""
        lines.append(f"{name:<14}{p['true_value']:>12.2f}{p['sim_value']:>12.2f}"
                     f"{p['vd']:>10.2f}  {mark}")
    lines.append(f"why no interval: {NO_INTERVAL['training_policies']}")
    lines.append(f"checkpoint: {s['checkpoint']}")
    return "\n".join(lines)


def _by(m: dict | None) -> str:
    """How a number was measured, in words: episodes x horizon, discount, source."""
    if not m:
        return "settings unknown"
    extra = "".join(f", {word} {m[k]}" for k, word in (("seed", "seed"), (
        "true_value_source", "true values:")) if k in m)
    return f"{m['episodes']} episodes x {m['horizon']} steps, gamma {m['gamma']:g}{extra}"


def parse_overrides(items: list[str] | None) -> dict:
    """--set key=value pairs -> dict; values parsed as JSON where they parse (3, 1e-4, [64,64])."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"set: expected key=value, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out
