"""`rl2s evaluate`: a checkpoint (or the oracle, or a physics model: ``evaluate_physics``)
scored on a Dataset file; several checkpoints of one task (independently trained simulators)
scored alike, with where they disagree.

Every evaluation here runs with one ``EvalSetting`` (evaluate/setting.py: episodes, horizon,
seed, which true value), the one `rl2s train` scores its test policies with, so the two agree
on one checkpoint; the report prints the setting and stores it ("setting")."""

from __future__ import annotations

import os

import jax
import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.app.specs import EvaluateSpec
from rl2s_jax.app.value_intervals import NO_INTERVAL, trust_for
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import TASKS
from rl2s_jax.evaluate.metrics import spearman
from rl2s_jax.evaluate.scores import evaluate_oracle, evaluate_simulator, one_step_errors
from rl2s_jax.evaluate.setting import EVAL_EPISODES, EvalSetting
from rl2s_jax.evaluate.trust import format_trust
from rl2s_jax.physics.hybrid import load_hybrid
from rl2s_jax.physics.physics_simulator import one_step_mse, physics_simulator
from rl2s_jax.train.checkpoint import Checkpointer
from rl2s_jax.train.config import saved_field
from rl2s_jax.zoo.zoo import policies_for


def _setting(setting: EvalSetting | None, n_episodes, horizon, seed, truth) -> EvalSetting:
    """``setting``, or one of the flags (None: the defaults); both given is refused."""
    if setting is None:
        return EvalSetting.from_flags(n_episodes, horizon, seed, truth)
    if any(v is not None for v in (n_episodes, horizon, seed, truth)):
        raise ValueError("setting: give an EvalSetting or episodes / horizon / seed / truth, "
                         "not both")
    return setting


def checkpoint_setting(config: dict, ds, setting: EvalSetting) -> EvalSetting:
    """``setting`` with the horizon filled for a checkpoint of ``config`` on ``ds``: given,
    else the config's ``vd.horizon`` (at most the data's episode_length: the real episodes end
    there); the same horizon training measured its VD with."""
    return setting.resolve(ds.meta.get("episode_length"), saved_field(config, "vd.horizon"),
                           config.get("profile"))


def _sources(setting: EvalSetting, n_episodes) -> dict:
    return {"horizon_source": setting.horizon_source,
            "episodes_source": ("--episodes" if n_episodes is not None
                                else "the evaluation setting"
                                if setting.episodes != EVAL_EPISODES
                                else f"the default {EVAL_EPISODES}"),
            "setting": setting.to_dict()}


def evaluate_checkpoint(ckpt: str, data_path: str, *, zoo: str | None = None,
                        policy_file: str | None = None, seed: int | None = None,
                        n_episodes: int | None = None, horizon: int | None = None,
                        step: int | None = None, n_boot: int = 0,
                        setting: EvalSetting | None = None, truth: str | None = None,
                        level: float | None = None, calibration: list[str] | None = None
                        ) -> dict:
    """Load a checkpoint's simulator and a Dataset (policies from ``zoo``, ``policy_file`` or
    the data's meta.source: ``zoo.policies_for``) and evaluate; no training data needed.
    ``setting`` (or the flags ``n_episodes``, ``horizon``, ``seed``, ``truth``; None: the
    defaults, ``EvalSetting``), its horizon by default the checkpoint's
    (``checkpoint_setting``); the report stores the setting used ("setting") and where the
    horizon and episodes came from (``horizon_source``, ``episodes_source``). ``level``: each
    policy's value interval at that level ("trust", "interval", "trusted": app/value_intervals.py
    ``trust_for``, calibrated on ``calibration`` files or the checkpoint's training data)."""

    setting = _setting(setting, n_episodes, horizon, seed, truth)
    ds = load_dataset(data_path)
    sim, meta = load_hybrid(ckpt, step)  # newest intact step unless given; a hybrid's physics
    if ds.meta.get("task") != sim.task:
        raise ValueError(f"data: {data_path} is task {ds.meta.get('task')!r} but the "
                         f"checkpoint models {sim.task!r}")
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    setting = checkpoint_setting(meta.get("config") or {}, ds, setting)
    report = evaluate_simulator(sim, ds, policies, key=setting.key(),
                                n_episodes=setting.episodes, horizon=setting.horizon,
                                n_boot=n_boot, truth=setting.truth)
    report.update(one_step_errors(sim, ds))
    report.update(checkpoint=ckpt, step=meta["step"], method=meta["config"]["method"],
                  data=data_path, seed=setting.seed, backend=jax.default_backend(),
                  **_sources(setting, n_episodes))
    if level:
        report.update(trust_for([ckpt], data_path, report, level=level, step=step, zoo=zoo,
                                calibration=calibration, policy_file=policy_file))
    return report


PHYSICS_NO_INTERVALS = ("a physics model is one deterministic model: no ensemble of seeds whose "
                        "spread gives value intervals (the identification's parameter "
                        "intervals are not carried into the values); pass --level 0")


def evaluate_physics(physics: str, data_path: str, *, zoo: str | None = None,
                     policy_file: str | None = None, seed: int | None = None,
                     n_episodes: int | None = None, horizon: int | None = None,
                     n_boot: int = 0, setting: EvalSetting | None = None,
                     truth: str | None = None, level: float | None = None,
                     calibration: list[str] | None = None) -> dict:
    """``evaluate_checkpoint`` with a physics model in place of a learned simulator: ``physics``
    is a calibrated.json of `rl2s diagnose --physics` or "nominal" (the data's task's MJX
    model; physics/physics_simulator.py). The same ``EvalSetting``, start states, rollout
    (``evaluate_simulator``), metrics against the data's true values and report, plus the
    physics' ``heldout_mse`` (``one_step_mse``); its default horizon is the oracle's
    (``EvalSetting.resolve``). No value intervals: with ``level`` the report's "trust" says
    why (``PHYSICS_NO_INTERVALS``); ``calibration`` unused."""
    setting = _setting(setting, n_episodes, horizon, seed, truth)
    ds = load_dataset(data_path)
    sim = physics_simulator(physics, ds.meta.get("task"), ds.obs_size, ds.action_size)
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    setting = setting.resolve(ds.meta.get("episode_length"))
    report = evaluate_simulator(sim, ds, policies, key=setting.key(),
                                n_episodes=setting.episodes, horizon=setting.horizon,
                                n_boot=n_boot, truth=setting.truth)
    report.update(one_step_mse(sim, ds))
    report.update(method="physics", physics=physics, delays=list(sim.delays),
                  data=data_path, seed=setting.seed, backend=jax.default_backend(),
                  **_sources(setting, n_episodes))
    if level:
        report["trust"] = {"skipped": PHYSICS_NO_INTERVALS}
    return report


def evaluate_oracle_data(data_path: str, *, zoo: str | None = None,
                         policy_file: str | None = None, seed: int | None = None,
                         n_episodes: int | None = None, horizon: int | None = None,
                         n_boot: int = 0, setting: EvalSetting | None = None,
                         truth: str | None = None, level: float | None = None,
                         calibration: list[str] | None = None) -> dict:
    """``evaluate_checkpoint`` with the task's real dynamics (``evaluate_oracle``): the control,
    in the same ``EvalSetting`` (no value intervals: with ``level`` the report's "trust" says
    why, ``NO_INTERVAL["oracle"]``; ``calibration`` unused);
    with no checkpoint its default horizon is the one training on
    this backend measures VD with (``EvalSetting.resolve``), so that the oracle and a
    simulator trained here score the same horizon."""
    setting = _setting(setting, n_episodes, horizon, seed, truth)
    ds = load_dataset(data_path)
    if ds.meta.get("task") not in TASKS:
        raise ValueError(f"oracle: {data_path} is data of no registered task (meta.task "
                         f"{ds.meta.get('task')!r}), so there are no real dynamics to run; "
                         f"its true values are in the data (rl2s evaluate --ckpt scores a "
                         f"simulator against them)")
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    setting = setting.resolve(ds.meta.get("episode_length"))
    report = evaluate_oracle(ds.meta.get("task"), ds, policies, key=setting.key(),
                             n_episodes=setting.episodes, horizon=setting.horizon,
                             n_boot=n_boot, truth=setting.truth)
    report.update(method="oracle", data=data_path, seed=setting.seed,
                  **_sources(setting, n_episodes))
    if level:
        report["trust"] = {"skipped": NO_INTERVAL["oracle"]}
    return report


def _metrics_line(m: dict) -> str:
    return "  ".join(f"{k} {v:.3f}" for k, v in m.items())


def _truth(r: dict) -> str:
    """Which true values a report used, in words."""
    asked = (r.get("setting") or {}).get("truth", "auto")
    used = r.get("true_value_source", "?")
    words = {"measured": "measured (the data's fresh value episodes)",
             "logged": "logged (the logged episodes' discounted return over the horizon)"}
    return words.get(used, used) + (" (--truth auto)" if asked == "auto" else "")


def format_report(r: dict) -> str:
    """A one-screen table of an evaluate report."""
    m = r["metrics"]
    what = {"oracle": "the real dynamics (oracle)",
            "physics": f"the physics model {r.get('physics')}"}.get(
        r.get("method"), f"{r.get('method', '?')} checkpoint step {r.get('step', '?')}")

    def source(key):
        return f" ({r[key]})" if key in r else ""
    head = [f"{what} on {r.get('data', '')}: {len(r['vd'])} policies, horizon {r['horizon']}"
            f"{source('horizon_source')}, {r['n_episodes']} episodes"
            f"{source('episodes_source')}, gamma {r['gamma']:g}, seed {r.get('seed', '?')}, "
            f"true values: {_truth(r)}",
            _metrics_line(m)]
    if "heldout_nll" in r:
        head.append(f"one-step error on these {r['one_step_rows']} transitions: heldout_nll "
                    f"{r['heldout_nll']:.3f} nats (s' - s, data units), heldout_mse "
                    f"{r['heldout_mse']:.4f} (per dim, in this data's std of s' - s)")
    elif "heldout_mse" in r:  # a physics model: deterministic, no NLL
        head.append(f"one-step error on these {r['one_step_rows']} transitions: heldout_mse "
                    f"{r['heldout_mse']:.3g} (per dim, in this data's std of s' - s)")
    if "intervals" in r:
        iv = r["intervals"]
        head.append(f"{iv['level']:.0%} bootstrap intervals over {iv['n_episodes']} episodes: "
                    + "  ".join(f"{k} [{iv['metrics'][k]['lo']:.3f}, "
                                f"{iv['metrics'][k]['hi']:.3f}]"
                                for k in ("kendall_tau", "ndcg@1", "avd", "mvd")
                                if k in iv["metrics"])
                    + f"; evaluation noise alone moves tau by "
                      f"{iv['sim_only']['kendall_tau']['std']:.3f} (std)")
    rows = [f"{'policy':<14}{'true value':>12}{'sim value':>12}{'VD':>10}{'sim len':>9}"
            + _interval_head(r)]
    for i, (name, t, s, v, n) in enumerate(zip(r["policy_names"], r["true_value"],
                                               r["sim_value"], r["vd"], r["sim_length"],
                                               strict=True)):
        rows.append(f"{str(name):<14}{t:>12.2f}{s:>12.2f}{v:>10.2f}{n:>9.1f}"
                    + _interval_cell(r, i))
    return "\n".join(head + rows + _trust_lines(r))


def _interval_head(r: dict) -> str:
    return (f"  {r['trust']['level']:.0%} interval{'':>12}trusted" if "interval" in r
            else "")


def _interval_cell(r: dict, i: int) -> str:
    """Policy i's value interval and flag (empty without intervals)."""
    if "interval" not in r:
        return ""
    lo, hi = r["interval"][i]
    return f"  [{_num(lo):>9}, {_num(hi):>9}]  {'yes' if r['trusted'][i] else 'NO'}"


def _trust_lines(r: dict) -> list[str]:
    t = r.get("trust")
    if t is None:
        return []
    return [f"value intervals skipped: {t['skipped']}"] if "skipped" in t else [format_trust(t)]


# ------------------------------------------------------------ several simulators of one data set

AGREEMENT_NOTE = ("spread: the std over the simulators of a policy's simulated value. It flags "
                  "the values they disagree on; it cannot flag an error they all share.")


def simulator_agreement(sim_values, true_values=None, names=None, top_k: int = 3) -> dict:
    """How far S simulators of one data set agree on each policy's value (no true value needed).

    sim_values: [S >= 2, P] each simulator's simulated value of each policy; true_values: [P]
    or None. -> {"n_simulators", "top_k", "most_disputed": the top_k policies by spread,
    "policies": per policy (data order) {name, mean, spread (std over simulators, ddof=1), min,
    max, spread_rank (1 = the most disputed; ties share a rank), and with true values:
    true_value, abs_error [S], mean_abs_error}, "spearman_spread_error" (Spearman's rho of
    spread and mean |error| over the policies; None without true values or when either is
    constant), "worst" (the policy of the largest |error| of any simulator) and "worst_rank"
    (its spread_rank), "worst_per_simulator" [S] {policy, spread_rank}} (the last three None
    without true values). A non-finite spread counts as the most disputed."""
    sims = np.asarray(sim_values, np.float64)
    if sims.ndim != 2 or sims.shape[0] < 2 or sims.shape[1] < 1:
        raise ValueError(f"sim_values: expected [simulators >= 2, policies >= 1], got shape "
                         f"{sims.shape}")
    n_sims, n_pol = sims.shape
    names = [str(n) for n in (names if names is not None else range(n_pol))]
    if len(names) != n_pol:
        raise ValueError(f"names: {len(names)} names for {n_pol} policies")
    if not isinstance(top_k, int) or top_k < 1:
        raise ValueError(f"top_k: expected an int >= 1, got {top_k!r}")
    spread = sims.std(0, ddof=1)
    key = np.where(np.isfinite(spread), spread, np.inf)
    rank = [int((key > key[i]).sum()) + 1 for i in range(n_pol)]
    order = np.argsort(-key, kind="stable")
    policies = [{"name": names[i], "mean": float(sims[:, i].mean()), "spread": float(spread[i]),
                 "min": float(sims[:, i].min()), "max": float(sims[:, i].max()),
                 "spread_rank": rank[i]} for i in range(n_pol)]
    out = {"n_simulators": n_sims, "top_k": top_k,
           "most_disputed": [names[i] for i in order[:top_k]], "policies": policies,
           "spearman_spread_error": None, "worst": None, "worst_rank": None,
           "worst_per_simulator": None}
    if true_values is None:
        return out
    truth = np.asarray(true_values, np.float64)
    if truth.shape != (n_pol,):
        raise ValueError(f"true_values: expected shape ({n_pol},), got {truth.shape}")
    err = np.abs(sims - truth)  # [S, P]
    mean_err = err.mean(0)
    for i, p in enumerate(policies):
        p.update(true_value=float(truth[i]), abs_error=err[:, i].tolist(),
                 mean_abs_error=float(mean_err[i]))
    ok = np.isfinite(spread) & np.isfinite(mean_err)
    if ok.sum() >= 2 and np.ptp(spread[ok]) > 0 and np.ptp(mean_err[ok]) > 0:
        out["spearman_spread_error"] = spearman(spread[ok], mean_err[ok])
    big = np.where(np.isfinite(err), err, np.inf)
    worst = int(big.max(0).argmax())
    out.update(worst=names[worst], worst_rank=rank[worst],
               worst_per_simulator=[{"policy": names[int(j)], "spread_rank": rank[int(j)]}
                                    for j in big.argmax(1)])
    return out


def check_checkpoints(ckpts: list[str], data_path: str, n_episodes: int | None = None,
                      horizon: int | None = None) -> list[dict]:
    """The refusals of ``evaluate_checkpoints``, from the checkpoints' JSON meta and the data
    alone (nothing compiled): 2+ distinct paths, one task (the data's), the same horizon.
    -> each checkpoint's meta."""
    setting = EvalSetting.from_flags(n_episodes, horizon)
    if len(ckpts) < 2:
        raise ValueError(f"ckpt: several simulators need 2 or more checkpoints, got {len(ckpts)}")
    seen: dict[str, str] = {}
    for c in ckpts:
        real = os.path.realpath(c)
        if real in seen:
            raise ValueError(f"ckpt: {c} given twice ({seen[real]}); several simulators need "
                             f"distinct checkpoints (each counts once in the spread)")
        seen[real] = c
    metas = []
    for c in ckpts:
        if not os.path.isdir(c):
            raise FileNotFoundError(f"ckpt: no checkpoint directory {c}")
        ck = Checkpointer(c, max_to_keep=None, create=False)
        try:
            metas.append(ck.meta())
        finally:
            ck.close()
    tasks = [(m.get("config") or {}).get("task") for m in metas]
    for c, t in zip(ckpts[1:], tasks[1:], strict=True):
        if t != tasks[0]:
            raise ValueError(f"ckpt: {ckpts[0]} is task {tasks[0]!r} but {c} models {t!r}; "
                             f"several simulators must be of one task")
    ds = load_dataset(data_path)
    if ds.meta.get("task") != tasks[0]:
        raise ValueError(f"data: {data_path} is task {ds.meta.get('task')!r} but the "
                         f"checkpoints model {tasks[0]!r}")
    values = [checkpoint_setting(m.get("config") or {}, ds, setting).horizon for m in metas]
    if len(set(values)) > 1:
        raise ValueError("horizon: the checkpoints' own defaults differ ("
                         + ", ".join(f"{c}: {v}" for c, v in zip(ckpts, values, strict=True))
                         + "); pass --horizon so that all simulators score the same thing")
    return metas


def evaluate_checkpoints(ckpts: list[str], data_path: str, *, top_k: int = 3,
                         **kw) -> dict:
    """``evaluate_checkpoint`` of each of several checkpoints of one task (same data,
    policies, seed and settings; ``kw`` as there, without ``step``) and their
    ``simulator_agreement``. Refused before any evaluation by ``check_checkpoints``.
    -> {"checkpoints": [each single report], "agreement": {...}} and with ``level`` the
    intervals of all the checkpoints together ("trust", "interval", "trusted": ``trust_for``,
    the seeds' spread in them)."""
    if kw.get("step") is not None:
        raise ValueError("step: --step with several checkpoints is ambiguous (their steps "
                         "differ); leave it out to use each one's newest intact step")
    kw.pop("step", None)
    level, calibration = kw.pop("level", None), kw.pop("calibration", None)
    check_checkpoints(ckpts, data_path, kw.get("n_episodes"), kw.get("horizon"))
    reports = [evaluate_checkpoint(c, data_path, **kw) for c in ckpts]
    truth = np.asarray(reports[0]["true_value"], np.float64)
    agreement = simulator_agreement([r["sim_value"] for r in reports],
                                    truth if np.all(np.isfinite(truth)) else None,
                                    reports[0]["policy_names"], top_k=min(top_k, len(truth)))
    out = {"checkpoints": reports, "agreement": agreement}
    if level:  # one interval per policy from all the seeds together
        out.update(trust_for(ckpts, data_path, reports[0], level=level, calibration=calibration,
                             zoo=kw.get("zoo"), policy_file=kw.get("policy_file")))
    return out


SUMMARY_METRICS = ("kendall_tau", "spearman", "ndcg@1", "regret@1", "avd", "mvd")


def _num(x: float) -> str:
    """2 decimals, or 3 significant digits below 1 (a spread of 0.004 is not 0.00)."""
    return f"{x:.2f}" if abs(x) >= 1 or x == 0 or not np.isfinite(x) else f"{x:.3g}"


def format_agreement(result: dict) -> str:
    """The report of ``evaluate_checkpoints``: a line per checkpoint, then the policies by
    spread, the most disputed first."""
    reports, a = result["checkpoints"], result["agreement"]
    r0 = reports[0]
    lines = [f"{len(reports)} simulators on {r0.get('data', '')}: {len(r0['vd'])} policies, "
             f"horizon {r0['horizon']} ({r0.get('horizon_source', '?')}), {r0['n_episodes']} "
             f"episodes ({r0.get('episodes_source', '?')}), gamma {r0['gamma']:g}, seed "
             f"{r0.get('seed', '?')}, true values: {_truth(r0)}"]
    for r in reports:
        m = {k: v for k, v in r["metrics"].items() if k in SUMMARY_METRICS}
        nll = f"  heldout_nll {r['heldout_nll']:.3f}" if "heldout_nll" in r else ""
        lines.append(f"  {r['checkpoint']} ({r['method']} step {r['step']}): "
                     f"{_metrics_line(m)}{nll}")
    known = a["worst"] is not None
    head = f"{'policy':<16}{'sim mean':>11}{'spread':>10}{'min .. max':>22}"
    lines.append(head + (f"{'true':>11}{'mean |err|':>12}" if known else "")
                 + _interval_head(result))
    names = [p["name"] for p in a["policies"]]
    for p in sorted(a["policies"], key=lambda p: p["spread_rank"]):
        row = (f"{p['name'][:15]:<16}{_num(p['mean']):>11}{_num(p['spread']):>10}"
               f"{_num(p['min']):>10} .. {_num(p['max']):<8}")
        if known:
            row += f"{_num(p['true_value']):>11}{_num(p['mean_abs_error']):>12}"
        lines.append(row + _interval_cell(result, names.index(p["name"])))
    lines += [f"most disputed: {', '.join(a['most_disputed'])}", AGREEMENT_NOTE]
    if known:
        rho = a["spearman_spread_error"]
        lines.append(f"largest |error| of any simulator: {a['worst']} (spread rank "
                     f"{a['worst_rank']} of {len(a['policies'])}); Spearman of spread and "
                     f"mean |error|: {'n/a' if rho is None else f'{rho:.2f}'}")
    return "\n".join(lines + _trust_lines(result))


def run_evaluate(spec: EvaluateSpec) -> int:
    """`rl2s evaluate`'s body: one checkpoint's (or the oracle's) report, or several
    checkpoints' and where they disagree; printed, and written to ``spec.json`` if given."""
    if not os.path.exists(spec.data):
        raise FileNotFoundError(f"data: no such file {spec.data}")
    if (spec.ckpt is not None) + spec.oracle + (spec.physics is not None) != 1:
        raise ValueError("ckpt: give one of --ckpt DIR, --oracle (the real dynamics) or "
                         "--physics SRC (a physics model)")
    kw = dict(zoo=spec.zoo, policy_file=spec.policy_file, seed=spec.seed, truth=spec.truth,
              n_episodes=spec.episodes, horizon=spec.horizon, n_boot=spec.bootstrap,
              level=spec.level or None, calibration=spec.calibration)
    several = bool(spec.ckpt and len(spec.ckpt) > 1)  # several simulators: where they disagree
    if several:
        report = evaluate_checkpoints(spec.ckpt, spec.data, step=spec.step, **kw)
    else:
        report = (evaluate_oracle_data(spec.data, **kw) if spec.oracle
                  else evaluate_physics(spec.physics, spec.data, **kw) if spec.physics
                  else evaluate_checkpoint(spec.ckpt[0], spec.data, step=spec.step, **kw))
    if not spec.level:
        report["trust"] = {"skipped": NO_INTERVAL["level_0"]}
    print(format_agreement(report) if several else format_report(report))
    if spec.json:
        os.makedirs(os.path.dirname(os.path.abspath(spec.json)), exist_ok=True)
        write_json(spec.json, report)
        print(f"-> {spec.json}")
    return 0
