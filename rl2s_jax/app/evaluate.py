"""`rl2s evaluate`: a checkpoint (or the oracle) scored on a Dataset file; several checkpoints
of one task (independently trained simulators) scored alike, with where they disagree.

A checkpoint is evaluated by default with the settings training evaluated it with (its
config's vd_horizon and vd_episodes, ``checkpoint_settings``), so the two agree; the report
names the settings used and where each came from."""

from __future__ import annotations

import os

import jax
import numpy as np

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import TASKS
from rl2s_jax.evaluate.metrics import spearman
from rl2s_jax.evaluate.simulator import evaluate_oracle, evaluate_simulator, one_step_errors
from rl2s_jax.train.checkpoint import Checkpointer, load_checkpoint
from rl2s_jax.zoo.zoo import policies_for

DEFAULT_EPISODES = 16  # simulated episodes per policy where nothing else sets them


def _check_settings(n_episodes, horizon) -> None:
    for name, v in (("episodes", n_episodes), ("horizon", horizon)):
        if v is not None and (not isinstance(v, int) or v < 1):
            raise ValueError(f"{name}: expected an int >= 1 (or None: the default), got {v!r}")


def checkpoint_settings(config: dict, ds, n_episodes: int | None = None,
                        horizon: int | None = None) -> dict:
    """The horizon and episodes to evaluate a checkpoint with, and where each comes from.

    By default the ones the checkpoint was evaluated with during training: its config's
    ``vd_horizon`` (at most the data's episode_length: the real episodes end there) and
    ``vd_episodes``; given values win. -> {"horizon", "horizon_source", "n_episodes",
    "episodes_source"}."""
    _check_settings(n_episodes, horizon)
    out = {"horizon": horizon, "horizon_source": "--horizon",
           "n_episodes": n_episodes, "episodes_source": "--episodes"}
    if horizon is None:
        vd, ep = config.get("vd_horizon"), ds.meta.get("episode_length")
        if vd is None:
            out.update(horizon=int(ep or 1000), horizon_source="the data's episode_length")
        elif ep is not None and int(vd) > int(ep):
            out.update(horizon=int(ep), horizon_source=f"the data's episode_length; the "
                       f"checkpoint's vd_horizon {vd} is longer")
        else:
            out.update(horizon=int(vd), horizon_source="the checkpoint's vd_horizon")
    if n_episodes is None:
        vd = config.get("vd_episodes")
        out.update(n_episodes=int(vd or DEFAULT_EPISODES),
                   episodes_source=("the checkpoint's vd_episodes" if vd
                                    else f"the default {DEFAULT_EPISODES}"))
    return out


def evaluate_checkpoint(ckpt: str, data_path: str, *, zoo: str | None = None,
                        policy_file: str | None = None, seed: int = 0,
                        n_episodes: int | None = None, horizon: int | None = None,
                        step: int | None = None, n_boot: int = 0) -> dict:
    """Load a checkpoint's simulator and a Dataset (policies from ``zoo``, ``policy_file`` or
    the data's meta.source: ``zoo.policies_for``) and evaluate; no training data needed.
    Episodes and horizon default to the checkpoint's (``checkpoint_settings``); the report
    says which were used and where they came from (``horizon_source``, ``episodes_source``)."""

    _check_settings(n_episodes, horizon)
    ds = load_dataset(data_path)
    sim, meta = load_checkpoint(ckpt, step)  # the newest intact step unless step is given
    if ds.meta.get("task") != sim.task:
        raise ValueError(f"data: {data_path} is task {ds.meta.get('task')!r} but the "
                         f"checkpoint models {sim.task!r}")
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    settings = checkpoint_settings(meta.get("config") or {}, ds, n_episodes, horizon)
    report = evaluate_simulator(sim, ds, policies, key=jax.random.PRNGKey(seed),
                                n_episodes=settings["n_episodes"], horizon=settings["horizon"],
                                n_boot=n_boot)
    report.update(one_step_errors(sim, ds))
    report.update(checkpoint=ckpt, step=meta["step"], method=meta["config"]["method"],
                  data=data_path, seed=seed, backend=jax.default_backend(),
                  horizon_source=settings["horizon_source"],
                  episodes_source=settings["episodes_source"])
    return report


def evaluate_oracle_data(data_path: str, *, zoo: str | None = None,
                         policy_file: str | None = None, seed: int = 0,
                         n_episodes: int | None = None, horizon: int | None = None,
                         n_boot: int = 0) -> dict:
    """``evaluate_checkpoint`` with the task's real dynamics (``evaluate_oracle``): the control.
    Defaults: the data's episode_length and ``DEFAULT_EPISODES`` episodes."""
    _check_settings(n_episodes, horizon)
    ds = load_dataset(data_path)
    if ds.meta.get("task") not in TASKS:
        raise ValueError(f"oracle: {data_path} is data of no registered task (meta.task "
                         f"{ds.meta.get('task')!r}), so there are no real dynamics to run; "
                         f"its true values are in the data (rl2s evaluate --ckpt scores a "
                         f"simulator against them)")
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    report = evaluate_oracle(ds.meta.get("task"), ds, policies, key=jax.random.PRNGKey(seed),
                             n_episodes=n_episodes or DEFAULT_EPISODES, horizon=horizon,
                             n_boot=n_boot)
    report.update(method="oracle", data=data_path, seed=seed,
                  horizon_source=("--horizon" if horizon else "the data's episode_length"
                                  if ds.meta.get("episode_length") else "the default 1000"),
                  episodes_source=("--episodes" if n_episodes
                                   else f"the default {DEFAULT_EPISODES}"))
    return report


def _metrics_line(m: dict) -> str:
    return "  ".join(f"{k} {v:.3f}" for k, v in m.items())


def format_report(r: dict) -> str:
    """A one-screen table of an evaluate report."""
    m = r["metrics"]
    what = ("the real dynamics (oracle)" if r.get("method") == "oracle"
            else f"{r.get('method', '?')} checkpoint step {r.get('step', '?')}")

    def source(key):
        return f" ({r[key]})" if key in r else ""
    head = [f"{what} on {r.get('data', '')}: {len(r['vd'])} policies, horizon {r['horizon']}"
            f"{source('horizon_source')}, {r['n_episodes']} episodes"
            f"{source('episodes_source')}, gamma {r['gamma']:g}",
            _metrics_line(m)]
    if "heldout_nll" in r:
        head.append(f"one-step error on these {r['one_step_rows']} transitions: heldout_nll "
                    f"{r['heldout_nll']:.3f} nats (s' - s, data units), heldout_mse "
                    f"{r['heldout_mse']:.4f} (per dim, in this data's std of s' - s)")
    if "intervals" in r:
        iv = r["intervals"]
        head.append(f"{iv['level']:.0%} bootstrap intervals over {iv['n_episodes']} episodes: "
                    + "  ".join(f"{k} [{iv['metrics'][k]['lo']:.3f}, "
                                f"{iv['metrics'][k]['hi']:.3f}]"
                                for k in ("kendall_tau", "ndcg@1", "avd", "mvd")
                                if k in iv["metrics"])
                    + f"; evaluation noise alone moves tau by "
                      f"{iv['sim_only']['kendall_tau']['std']:.3f} (std)")
    rows = [f"{'policy':<14}{'true value':>12}{'sim value':>12}{'VD':>10}{'sim len':>9}"]
    for name, t, s, v, n in zip(r["policy_names"], r["true_value"], r["sim_value"], r["vd"],
                                r["sim_length"], strict=True):
        rows.append(f"{str(name):<14}{t:>12.2f}{s:>12.2f}{v:>10.2f}{n:>9.1f}")
    return "\n".join(head + rows)


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
    alone (nothing compiled): 2+ distinct paths, one task (the data's), the same horizon and
    episodes. -> each checkpoint's meta."""
    _check_settings(n_episodes, horizon)
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
    settings = [checkpoint_settings(m.get("config") or {}, ds, n_episodes, horizon)
                for m in metas]
    for name, key, flag in (("horizon", "horizon", "--horizon"),
                            ("episodes", "n_episodes", "--episodes")):
        values = [s[key] for s in settings]
        if len(set(values)) > 1:
            raise ValueError(f"{name}: the checkpoints' own defaults differ ("
                             + ", ".join(f"{c}: {v}" for c, v in zip(ckpts, values, strict=True))
                             + f"); pass {flag} so that all simulators score the same thing")
    return metas


def evaluate_checkpoints(ckpts: list[str], data_path: str, *, top_k: int = 3,
                         **kw) -> dict:
    """``evaluate_checkpoint`` of each of several checkpoints of one task (same data,
    policies, seed and settings; ``kw`` as there, without ``step``) and their
    ``simulator_agreement``. Refused before any evaluation by ``check_checkpoints``.
    -> {"checkpoints": [each single report], "agreement": {...}}."""
    if kw.get("step") is not None:
        raise ValueError("step: --step with several checkpoints is ambiguous (their steps "
                         "differ); leave it out to use each one's newest intact step")
    kw.pop("step", None)
    check_checkpoints(ckpts, data_path, kw.get("n_episodes"), kw.get("horizon"))
    reports = [evaluate_checkpoint(c, data_path, **kw) for c in ckpts]
    truth = np.asarray(reports[0]["true_value"], np.float64)
    agreement = simulator_agreement([r["sim_value"] for r in reports],
                                    truth if np.all(np.isfinite(truth)) else None,
                                    reports[0]["policy_names"], top_k=min(top_k, len(truth)))
    return {"checkpoints": reports, "agreement": agreement}


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
             f"episodes ({r0.get('episodes_source', '?')}), gamma {r0['gamma']:g}"]
    for r in reports:
        m = {k: v for k, v in r["metrics"].items() if k in SUMMARY_METRICS}
        nll = f"  heldout_nll {r['heldout_nll']:.3f}" if "heldout_nll" in r else ""
        lines.append(f"  {r['checkpoint']} ({r['method']} step {r['step']}): "
                     f"{_metrics_line(m)}{nll}")
    known = a["worst"] is not None
    head = f"{'policy':<16}{'sim mean':>11}{'spread':>10}{'min .. max':>22}"
    lines.append(head + (f"{'true':>11}{'mean |err|':>12}" if known else ""))
    for p in sorted(a["policies"], key=lambda p: p["spread_rank"]):
        row = (f"{p['name'][:15]:<16}{_num(p['mean']):>11}{_num(p['spread']):>10}"
               f"{_num(p['min']):>10} .. {_num(p['max']):<8}")
        if known:
            row += f"{_num(p['true_value']):>11}{_num(p['mean_abs_error']):>12}"
        lines.append(row)
    lines += [f"most disputed: {', '.join(a['most_disputed'])}", AGREEMENT_NOTE]
    if known:
        rho = a["spearman_spread_error"]
        lines.append(f"largest |error| of any simulator: {a['worst']} (spread rank "
                     f"{a['worst_rank']} of {len(a['policies'])}); Spearman of spread and "
                     f"mean |error|: {'n/a' if rho is None else f'{rho:.2f}'}")
    return "\n".join(lines)
