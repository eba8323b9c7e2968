"""The diagnosis pipeline: residuals -> where the model is wrong -> why -> extended model ->
measured gain, written as report.json, report.md and plots.

    report = diagnose(load_dataset("D.npz"), "out/", seeds=(0, 1, 2))
    report["top_cause"], report["gain"]["after"]["heldout_nll"]
"""
from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from rl2s_jax._files import save_figure, write_json, write_text
from rl2s_jax.app.specs import DiagnoseSpec
from rl2s_jax.data.dataset import Dataset, load_dataset
from rl2s_jax.data.episodes import Episodes, from_dataset, pool_episodes, split_episodes
from rl2s_jax.data.values import true_values
from rl2s_jax.diagnose.causes import diagnose_causes
from rl2s_jax.diagnose.extension import extension_for, train_command, train_set
from rl2s_jax.diagnose.gap_views import gaps_markdown, plot_gaps
from rl2s_jax.diagnose.gaps import error_breakdown, jsonable
from rl2s_jax.diagnose.model import (
    FittedModels,
    ModelSpec,
    episode_history,
    fit_models,
    heldout_metrics,
    kstep_errors,
    normalized_delta,
    predict,
    rollout_values,
)
from rl2s_jax.envs.tasks import TASKS
from rl2s_jax.evaluate.metrics import kendall_tau
from rl2s_jax.train.checkpoint import load_meta, load_simulator
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.zoo.zoo import policies_for


def _checkpoint_residuals(ckpt: str, base: FittedModels, eps: Episodes, rows: np.ndarray):
    """Residuals of a saved simulator, in the base model's normalised delta units: its
    predictive mean and std (for an ensemble stepping a random elite: the elites' mixture, so
    the std includes their disagreement; ``Simulator.predictive``); a simulator with history
    inputs sees each row's logged past."""
    sim = load_simulator(ckpt)
    if np.asarray(sim.norm.obs_mean).shape[0] != eps.obs_size:
        raise ValueError(f"ckpt: the simulator's obs size {np.asarray(sim.norm.obs_mean).shape[0]}"
                         f" differs from the data's {eps.obs_size}")
    hist = episode_history(eps, rows, obs_history=sim.obs_history,
                           action_history=sim.action_history, time_inputs=sim.time_inputs,
                           episode_length=sim.episode_length)
    mean, std_n = jax.jit(lambda s, o, a, h: s.predictive(o, a, h))(
        sim, eps.obs[rows].astype(np.float32), eps.action[rows].astype(np.float32), hist)
    d_std = np.asarray(base.norm.delta_std, np.float64)
    s_std, s_mean = (np.asarray(x, np.float64) for x in (sim.norm.delta_std, sim.norm.delta_mean))
    pred = s_mean + s_std * np.asarray(mean, np.float64)
    resid = (eps.delta[rows] - pred) / d_std
    std = s_std * np.asarray(std_n, np.float64) / d_std
    return resid, std, (pred - np.asarray(base.norm.delta_mean, np.float64)) / d_std


def _differential_causes(eps: Episodes, ref_eps: Episodes, fit_eps, held_eps,
                         base: FittedModels, base_spec: ModelSpec, ckpt: str | None, seed: int,
                         heldout_frac: float, split_seed: int, lags: int, alpha: float,
                         min_score: float, progress: bool, log) -> dict:
    """The cause tests of the target against a reference dataset (see ``diagnose``)."""
    pooled, in_target = pool_episodes(eps, ref_eps)
    ref_fit, ref_held = split_episodes(ref_eps, heldout_frac, split_seed, min_length=2)
    fit_ep = np.r_[fit_eps, ref_fit + eps.n_episodes]
    held_ep = np.r_[held_eps, ref_held + eps.n_episodes]
    fit_rows, held_rows = pooled.rows(fit_ep), pooled.rows(held_ep)
    log(f"[diagnose] reference: {ref_eps.n} transitions, {ref_eps.n_episodes} episodes; the "
        f"causes are tested on what the data shows beyond it")
    if ckpt is not None:
        resid, std, pred_mean = _checkpoint_residuals(ckpt, base, pooled, held_rows)
    else:
        model = fit_models(pooled, fit_ep, base_spec, (seed,), progress=progress)
        mean, std_all = predict(model, pooled, held_rows)
        resid = normalized_delta(model, pooled, held_rows) - mean[0]
        std, pred_mean = std_all[0], mean[0]
    return diagnose_causes(pooled, held_rows, resid, std, fit_rows, pred_mean=pred_mean,
                           lags=lags, seed=split_seed, alpha=alpha, min_score=min_score,
                           in_target=in_target[held_rows])


def _gaussian_nll(resid: np.ndarray, std: np.ndarray) -> float:
    """Mean per-row Gaussian NLL (summed over dims) of residuals [n, o] under stds [n, o]."""
    z = resid / std
    return float((0.5 * z ** 2 + np.log(std) + 0.5 * np.log(2 * np.pi)).sum(-1).mean())


ADVERSARIAL_SHARE = 0.2  # adversarial updates per likelihood update for rl2s / gail retrains


def _method_spec(spec: ModelSpec, ckpt: str | None) -> tuple[ModelSpec, str]:
    """How the models fitted here are trained, in words: maximum likelihood through
    ``train_step`` (method "bc", one member per seed). The saved simulator's own method
    (adversarial, or CVaR over policies) is what the printed ``rl2s train`` command reruns
    with the extension; diagnosis compares model inputs, on the same footing."""
    words = "maximum likelihood through train_step (method bc, one member per seed)"
    if ckpt is not None:
        cfg = TrainConfig.from_saved(load_meta(ckpt)["config"])
        words += f"; the checkpoint's method, {cfg.method}, is what `rl2s train` reruns"
    return spec, words


def _value_setup(ds: Dataset, zoo: str | None, horizon: int | None, gamma: float | None):
    """Policies, task functions and true values for the value views, or (None, reason)."""
    task_name = ds.meta.get("task")
    if not task_name:
        return None, "the data names no registered task (no reward_fn / done_fn)"
    if not ds.has_values:
        return None, "the data holds no true policy values"

    if task_name not in TASKS:
        return None, f"task {task_name!r} is not registered"
    try:
        policies = policies_for(ds, zoo)
    except (ValueError, OSError) as e:
        return None, f"the policies are not available ({e})"
    task = TASKS[task_name]
    horizon = int(horizon or ds.meta.get("episode_length") or task.episode_length)
    gamma = float(gamma or ds.meta.get("gamma") or 0.999)
    truth = true_values(ds, horizon, gamma, strict=False)
    return {"policies": policies, "task": task, "horizon": horizon, "gamma": gamma,
            "true": truth}, None


def _values(fm: FittedModels, setup: dict, starts: np.ndarray, n_episodes: int, seed: int
            ) -> np.ndarray:
    """Simulated discounted values [S, P] of every policy in every seed's model."""

    return np.stack([rollout_values(fm, s, setup["policies"], starts, task=setup["task"],
                                    horizon=setup["horizon"], n_episodes=n_episodes,
                                    gamma=setup["gamma"], key=jax.random.PRNGKey(seed + s))
                     for s in range(fm.n_seeds)])


def _measure(fm: FittedModels, eps: Episodes, held_rows, held_eps, k_max: int,
             values: np.ndarray | None, truth: np.ndarray | None) -> dict:
    """Per-seed held-out metrics of one fitted model family. -> name -> [S] (kstep [S, k])."""
    m = heldout_metrics(fm, eps, held_rows)
    out = {"heldout_nll": np.asarray(m["nll"]), "heldout_mse": np.asarray(m["mse"])}
    ks = kstep_errors(fm, eps, held_eps, k_max=k_max)
    out["kstep_rmse"] = ks
    out[f"kstep_rmse@{k_max}"] = ks[:, -1]
    if values is not None:

        ok = np.isfinite(truth)
        vd = np.abs(values[:, ok] - truth[ok])
        out["avd"], out["mvd"] = vd.mean(1), vd.max(1)
        if ok.sum() >= 2:
            out["kendall_tau"] = np.array([kendall_tau(truth[ok], v[ok]) for v in values])
    return out


def _summarise(per_seed: dict) -> dict:
    out = {}
    for k, v in per_seed.items():
        v = np.asarray(v, np.float64)
        if v.ndim == 1:
            out[k] = float(v.mean())
            out[f"{k}_std"] = float(v.std(ddof=1)) if v.size > 1 else 0.0
            out[f"{k}_per_seed"] = v.tolist()
        else:
            out[k] = v.mean(0).tolist()
    return out


def _difference(before: dict, after: dict) -> dict:
    """after - before per metric, paired by seed: mean, std over seeds, per seed."""
    out = {}
    for k, b in before.items():
        b, a = np.asarray(b, np.float64), np.asarray(after[k], np.float64)
        if b.ndim != 1:
            continue
        d = a - b
        out[k] = {"mean": float(d.mean()), "std": float(d.std(ddof=1)) if d.size > 1 else 0.0,
                  "per_seed": d.tolist()}
    return out


def diagnose(ds: Dataset, out_dir: str | None = None, *, ckpt: str | None = None,
             seeds: Sequence[int] = (0, 1, 2), heldout_frac: float = 0.3, split_seed: int = 0,
             lags: int = 5, k_max: int = 20, base_spec: ModelSpec | None = None,
             zoo: str | None = None, value_episodes: int = 8, value_horizon: int | None = None,
             alpha: float = 0.01, min_score: float = 0.02, plots: bool = True,
             reference: Dataset | None = None, progress: bool = False,
             log: Callable[[str], None] = print) -> dict:
    """Diagnose a simulator of ``ds``: the one saved at ``ckpt``, or a base model fitted here.

    Fits the base model (``base_spec``, default ``ModelSpec()``) on the fit episodes for every
    seed, shows its held-out errors, tests the causes, fits the extension the causes call for
    with the same seeds, and measures before vs after. Writes report.json, report.md and PNGs
    to ``out_dir`` when given. -> the report dict (docs/DIAGNOSIS.md).

    ``reference``: a dataset of the same system without the effects sought (for example a
    clean recording). The causes are then tested differentially: only what the target's
    residuals show beyond the reference's counts (``causes.diagnose_causes(in_target=...)``).
    The residuals of both come from the saved simulator, or else from one base model fitted
    on the fit episodes of both (seed ``seeds[0]``); the extension is still fitted, and its
    gain measured, on ``ds`` alone.
    """
    seeds = tuple(int(s) for s in seeds)
    if not seeds:
        raise ValueError("seeds: expected at least one seed")
    if not isinstance(k_max, int) or k_max < 1:
        raise ValueError(f"k_max: expected an int >= 1, got {k_max!r}")
    if not isinstance(lags, int) or lags < 1:
        raise ValueError(f"lags: expected an int >= 1, got {lags!r}")
    base_spec = (base_spec or ModelSpec()).validate()
    if ckpt is not None and not os.path.isdir(ckpt):
        raise ValueError(f"ckpt: expected a checkpoint directory, got {ckpt!r}")
    base_spec, trained_by = _method_spec(base_spec, ckpt)
    t_start, timings = time.perf_counter(), {}

    def phase(name, t0):
        timings[name] = round(time.perf_counter() - t0, 2)
        log(f"[diagnose] {name}: {timings[name]:.1f}s")

    eps = from_dataset(ds)
    ref_eps = None
    if reference is not None:
        if not isinstance(reference, Dataset):
            raise ValueError(f"reference: expected a Dataset, got {type(reference).__name__}")
        ref_eps = from_dataset(reference, position_dims=eps.position_dims)
        pool_episodes(eps, ref_eps)  # checks the sizes before any work
    # One-row episodes (a recording cut right after a reset) cannot give a per-episode
    # context from their other half, and the extension may add one: both sides leave them out.
    fit_eps, held_eps = split_episodes(eps, heldout_frac, split_seed, min_length=2)
    fit_rows, held_rows = eps.rows(fit_eps), eps.rows(held_eps)
    one_row = int((eps.length < 2).sum())
    if one_row:
        log(f"[diagnose] {one_row} one-row episode(s) left out of fit and held-out sets")
    log(f"[diagnose] {eps.n} transitions, {eps.n_episodes} episodes, {eps.n_policies} "
        f"policies; fit on {len(fit_eps)} episodes, hold out {len(held_eps)}; seeds {seeds}")
    setup, no_values = _value_setup(ds, zoo, value_horizon, None)
    if no_values:
        log(f"[diagnose] value views skipped: {no_values}")
    starts = eps.obs[eps.start[held_eps]] if setup else None

    t0 = time.perf_counter()
    base = fit_models(eps, fit_eps, base_spec, seeds, progress=progress)
    phase("fit base", t0)
    t0 = time.perf_counter()
    if ckpt is not None:
        resid, std, pred_mean = _checkpoint_residuals(ckpt, base, eps, held_rows)
        source = f"checkpoint {ckpt}"
    else:
        mean, std_all = predict(base, eps, held_rows)
        resid = normalized_delta(base, eps, held_rows) - mean[0]
        std, pred_mean = std_all[0], mean[0]
        source = f"base model fitted here (seed {seeds[0]})"
    base_values = _values(base, setup, starts, value_episodes, 100) if setup else None
    truth = setup["true"] if setup else None
    before = _measure(base, eps, held_rows, held_eps, k_max, base_values, truth)
    phase("base residuals and metrics", t0)


    t0 = time.perf_counter()
    vd = None
    if setup:
        vd = {"policy": list(ds.meta.get("policy_names") or range(ds.n_policies)),
              "true": np.nan_to_num(truth).tolist(), "sim": base_values[0].tolist()}
    gaps = error_breakdown(eps, held_rows, resid, std, kstep=before["kstep_rmse"], vd=vd)
    phase("error breakdown", t0)
    t0 = time.perf_counter()
    if ref_eps is None:
        causes = diagnose_causes(eps, held_rows, resid, std, fit_rows, pred_mean=pred_mean,
                                 lags=lags, seed=split_seed, alpha=alpha, min_score=min_score)
    else:
        causes = _differential_causes(eps, ref_eps, fit_eps, held_eps, base, base_spec, ckpt,
                                      seeds[0], heldout_frac, split_seed, lags, alpha,
                                      min_score, progress, log)
    phase("cause tests", t0)
    top = causes["top_cause"]
    log(f"[diagnose] top cause: {top} (confidence {causes['confidence']:.2f})")
    spec, changes = extension_for(causes, base_spec)
    report = {
        "data": {"transitions": eps.n, "episodes": eps.n_episodes, "policies": eps.n_policies,
                 "obs_size": eps.obs_size, "action_size": eps.action_size,
                 "task": ds.meta.get("task"), "fit_episodes": int(len(fit_eps)),
                 "heldout_episodes": int(len(held_eps)), "one_row_episodes_left_out": one_row},
        "residuals_from": source,
        "reference": None if ref_eps is None else {
            "transitions": ref_eps.n, "episodes": ref_eps.n_episodes,
            "policies": ref_eps.n_policies, "task": reference.meta.get("task")},
        "value_views": "on" if setup else f"skipped: {no_values}",
        "gaps": gaps, "causes": causes["causes"], "top_cause": top,
        "confidence": causes["confidence"], "cause_settings": causes["settings"],
        "extension": {"base": base_spec.describe(), "extended": spec.describe(),
                      "changes": changes},
    }
    gain = {"seeds": list(seeds), "before": _summarise(before), "k_max": k_max}
    if ckpt is not None:  # the saved simulator itself, on the same held-out rows
        gain["saved"] = {"heldout_nll": float(_gaussian_nll(resid, std)),
                         "heldout_mse": float((resid ** 2).mean())}
    report["extension"]["trained_by"] = trained_by
    saved = None if ckpt is None else TrainConfig.from_saved(load_meta(ckpt)["config"])
    proposal = report["extension"]
    proposal["train_set"], proposal["not_trainable"], proposal["already_in_simulator"] = (
        train_set(changes, saved))
    proposal["method"] = "rl2s" if saved is None else saved.method
    if spec != base_spec:
        t0 = time.perf_counter()
        ext = fit_models(eps, fit_eps, spec, seeds, progress=progress)
        ext_values = _values(ext, setup, starts, value_episodes, 100) if setup else None
        after = _measure(ext, eps, held_rows, held_eps, k_max, ext_values, truth)
        phase("fit and measure the extension", t0)
        gain["after"] = _summarise(after)
        gain["difference"] = _difference(before, after)
        if "saved" in gain:
            gain["saved"]["extended_minus_saved"] = {
                k: {"mean": float(np.mean(after[k] - gain["saved"][k])),
                    "per_seed": (np.asarray(after[k]) - gain["saved"][k]).tolist()}
                for k in ("heldout_nll", "heldout_mse")}
    else:
        gain["after"] = None
        gain["difference"] = None
    report["gain"] = gain
    report["verdict"] = verdict(report)
    report["timings"] = timings
    report["seconds"] = round(time.perf_counter() - t_start, 1)
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
        figs = plot_gaps(out_dir, gaps) if plots else []
        if plots:
            figs += plot_gain(out_dir, gain)
        report["plots"] = [os.path.basename(f) for f in figs]
        write_json(os.path.join(out_dir, "report.json"), jsonable(report))
        write_text(os.path.join(out_dir, "report.md"),
                   report_markdown(report, gaps_markdown(gaps, figs)))
        log(f"[diagnose] wrote {out_dir}/report.json, report.md and {len(figs)} plots "
            f"({report['seconds']:.0f}s in all)")
    return report


_CAUSE_WORDS = {
    "actuation_delay": "an actuation delay", "unobserved_state": "an unobserved state",
    "hidden_episode_parameter": "a hidden parameter that changes from episode to episode",
    "time_drift": "a drift of the dynamics", "stochastic_noise": "state-dependent noise",
    "coverage_gap": "a coverage gap (too little data where the error is)",
}
_EXTENSION_WORDS = {
    "action_history": "past actions", "obs_history": "past observations",
    "context_dim": "a per-episode context", "noise": "a state-dependent noise head",
    "time_inputs": "time inputs", "policy_cvar_eps": "CVaR weighting of the worst policies",
}


def _cause_details(c: dict) -> str:
    d = c["details"]
    name = c["name"]
    if name == "actuation_delay":
        return f"lag {d['lag']} steps on actuator(s) {d['actuators']}"
    if name == "unobserved_state":
        return f"past observations at lags {d['lags']} explain dims {d['dims']}"
    if name == "time_drift":
        return f"over the {d['over'].replace('_', ' ')}, in dims {d['dims']}"
    if name == "stochastic_noise":
        return f"in dims {d['dims']}"
    if name == "coverage_gap":
        return f"worst policies {d['worst_policies']}"
    return f"in dims {d.get('dims', [])}"


def verdict(report: dict) -> dict:
    """The two sentences at the top of report.md: what is wrong and why; what the extension
    gained and whether to trust the extended simulator. -> {"wrong", "gain", "trust"}; trust
    is "extended" (the extension lowered held-out NLL on every seed without raising MSE by
    more than 10% or, where values exist, AVD), "base" (nothing to extend) or "neither"
    (the extension did not help cleanly: each failing check is named)."""
    top = report["top_cause"]
    ref = " beyond what the reference data shows" if report.get("reference") else ""
    worst = report["gaps"].get("by_dim") or []
    worst = max(worst, key=lambda d: d["share"] or 0) if worst else None
    where = (f"; the largest share of its one-step error ({worst['share']:.0%}) is in "
             f"{worst['name']}") if worst and worst["share"] is not None else ""
    if top == "none":
        wrong = (f"No cause explains the simulator's held-out errors{ref} (every test below "
                 f"{report['cause_settings']['min_score']} nats per transition or not "
                 f"significant){where}.")
        return {"wrong": wrong, "gain": "Nothing was extended, so the base simulator stands "
                "as it is.", "trust": "base"}
    c = next(c for c in report["causes"] if c["name"] == top)
    wrong = (f"The simulator misses {_CAUSE_WORDS[top]}{ref} ({_cause_details(c)}; it saves "
             f"{c['score']:.3g} nats per held-out transition, p = {c['p_value']:.1g}, "
             f"confidence {report['confidence']:.2f}){where}.")
    changes = report["extension"]["changes"]
    g = report["gain"]
    if not changes or not g.get("after"):
        return {"wrong": wrong, "gain": "The base model already has the extension this cause "
                "calls for, so nothing was retrained: a larger model or more data is the next "
                "step, and the base simulator should be trusted only where its errors are "
                "small.", "trust": "base"}
    added = ", ".join(sorted({_EXTENSION_WORDS.get(k, k) for ch in changes for k in ch["change"]}))
    d, b, a = g["difference"], g["before"], g["after"]
    nll_seeds = sum(x < 0 for x in d["heldout_nll"]["per_seed"])
    n = len(d["heldout_nll"]["per_seed"])
    parts = [f"held-out NLL {b['heldout_nll']:.3g} -> {a['heldout_nll']:.3g} (lower on "
             f"{nll_seeds} of {n} seeds)",
             f"MSE {b['heldout_mse']:.3g} -> {a['heldout_mse']:.3g}"]
    problems = []
    if nll_seeds < n:
        problems.append(f"NLL rose on {n - nll_seeds} seed(s)")
    if a["heldout_mse"] > 1.1 * b["heldout_mse"]:
        problems.append(f"MSE rose {a['heldout_mse'] / b['heldout_mse']:.2g}x (the likelihood "
                        "gained by widening the noise, not by a better mean)")
    if "avd" in b:
        parts.append(f"AVD {b['avd']:.3g} -> {a['avd']:.3g}")
        if a["avd"] > b["avd"]:
            problems.append("AVD rose")
    if "saved" in g:
        parts.append(f"against the saved simulator's own held-out NLL "
                     f"{g['saved']['heldout_nll']:.3g} and MSE {g['saved']['heldout_mse']:.3g}")
    by = report["extension"].get("trained_by", "maximum likelihood")
    gain = f"Adding {added}, trained by {by}, gave {', '.join(parts)}"
    if problems:
        return {"wrong": wrong, "gain": gain + f"; do not trust the extended simulator yet: "
                f"{'; '.join(problems)}.", "trust": "neither"}
    return {"wrong": wrong, "gain": gain + "; the extended simulator can be trusted where the "
            "base one was, and more.", "trust": "extended"}


def plot_gain(out_dir: str, gain: dict) -> list[str]:
    """Before vs after: held-out NLL / MSE / value error bars with seed spread, and the k-step
    error curves. -> [path] (nothing without an extension)."""
    if not gain.get("after"):
        return []
    # Imported here to keep start-up fast: matplotlib loads in about a second, and only
    # the plots need it.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b, a = gain["before"], gain["after"]
    keys = [k for k in ("heldout_nll", "heldout_mse", f"kstep_rmse@{gain['k_max']}", "avd",
                        "mvd") if k in b]
    fig, axes = plt.subplots(1, len(keys) + 1, figsize=(3.2 * (len(keys) + 1), 3.2))
    for ax, k in zip(axes[:-1], keys, strict=True):
        ax.bar([0, 1], [b[k], a[k]], yerr=[b[f"{k}_std"], a[f"{k}_std"]], capsize=4,
               color=["#999999", "#1f77b4"])
        ax.set_xticks([0, 1], ["base", "extended"])
        ax.set_title(k.replace("_", " "))
    ks = np.arange(1, len(b["kstep_rmse"]) + 1)
    axes[-1].plot(ks, b["kstep_rmse"], "o-", color="#999999", label="base")
    axes[-1].plot(ks, a["kstep_rmse"], "o-", color="#1f77b4", label="extended")
    axes[-1].set_xlabel("steps ahead k")
    axes[-1].set_ylabel("open-loop RMSE (obs stds)")
    axes[-1].legend()
    fig.suptitle(f"held-out gain of the extension (mean ± std over {len(gain['seeds'])} seeds)")
    fig.tight_layout()
    path = os.path.join(out_dir, "gain.png")
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return [path]


def report_markdown(report: dict, gaps_md: str) -> str:
    """The human-readable report."""
    lines = ["# Simulator diagnosis", ""]
    v = report.get("verdict")
    if v:
        lines += [f"**{v['wrong']}** {v['gain']}", ""]
    d = report["data"]
    lines += [f"Data: {d['transitions']} transitions, {d['episodes']} episodes, "
              f"{d['policies']} policies (task: {d['task']}). Residuals from the "
              f"{report['residuals_from']}, on {d['heldout_episodes']} held-out episodes. "
              f"Value views: {report['value_views']}.", ""]
    r = report.get("reference")
    if r:
        lines += [f"Differential: tested against a reference of {r['transitions']} transitions "
                  f"({r['episodes']} episodes); scores are the data's gain minus the "
                  "reference's, p-values a rank-sum test over episodes.", ""]
    lines += [f"## Cause: **{report['top_cause']}** (confidence {report['confidence']:.2f})", "",
              "| cause | score (nats/transition) | p-value | significant | details |",
              "|---|---|---|---|---|"]
    for c in report["causes"]:
        det = {k: v for k, v in c["details"].items()
               if k in ("lag", "actuators", "dims", "over", "lags", "worst_policies")}
        lines.append(f"| {c['name']} | {c['score']:.4f} | {c['p_value']:.2g} | "
                     f"{'yes' if c['significant'] else 'no'} | {det} |")
    lines += ["", "Score: held-out Gaussian NLL the cause's feature saves once every other "
              "feature is accounted for; p: signed-rank sign-flip test over episodes "
              "(docs/DIAGNOSIS.md).", ""]
    ext = report["extension"]
    lines += ["## Extension", ""]
    if ext["changes"]:
        lines += [f"- {c['cause']}: {c['change']}" for c in ext["changes"]]
        lines += ["", f"Extended model: {', '.join(ext['extended']['extensions'])}.", ""]
        if ext.get("train_set"):
            lines += ["To train it as the simulator: `rl2s train ... "
                      + " ".join(f"--set '{i}'" for i in ext["train_set"]) + "` "
                      "(`extension.train_set` in report.json).", ""]
        if ext.get("already_in_simulator"):
            lines += ["Already in the simulator `rl2s train` builds: "
                      + ", ".join(f"`{i}`" for i in ext["already_in_simulator"]) + ".", ""]
        lines += [f"Not built by `rl2s train` yet: {n['change']} ({n['why']})."
                  for n in ext.get("not_trainable", [])]
        if ext.get("not_trainable"):
            lines.append("")
    elif report["top_cause"] == "none":
        lines += ["None: no cause is significant, the base model is adequate.", ""]
    else:
        lines += [f"None: the base model already has the extension that "
                  f"{report['top_cause']} calls for ({', '.join(ext['base']['extensions'])}); "
                  "what remains is what it fails to learn from it (a larger model or more "
                  "data, not another input).", ""]
    g = report["gain"]
    lines += ["## Gain (held-out, mean ± std over seeds " + ", ".join(map(str, g["seeds"]))
              + ")", ""]
    keys = [k for k in ("heldout_nll", "heldout_mse", f"kstep_rmse@{g['k_max']}", "avd", "mvd",
                        "kendall_tau") if k in g["before"]]
    if g["after"]:
        lines += ["| metric | base | extended | difference |", "|---|---|---|---|"]
        for k in keys:
            b, a, df = g["before"], g["after"], g["difference"][k]
            lines.append(f"| {k} | {b[k]:.4g} ± {b[k + '_std']:.2g} | {a[k]:.4g} ± "
                         f"{a[k + '_std']:.2g} | {df['mean']:+.4g} ± {df['std']:.2g} |")
        if "gain.png" in report.get("plots", []):
            lines += ["", "![gain](gain.png)"]
    else:
        lines += ["| metric | base |", "|---|---|"]
        lines += [f"| {k} | {g['before'][k]:.4g} ± {g['before'][k + '_std']:.2g} |"
                  for k in keys]
    lines += ["", "## Where the model is wrong", "", gaps_md, ""]
    lines += [f"Took {report['seconds']:.0f}s: " + ", ".join(f"{k} {v:.0f}s" for k, v in
                                                          report["timings"].items()) + "."]
    return "\n".join(lines) + "\n"


def run_diagnose(spec: DiagnoseSpec) -> int:
    """`rl2s diagnose`'s body: ``diagnose`` the data (and ``spec.ckpt``'s simulator), print
    the top causes, the extension's gain and the `rl2s train` command that builds it; with
    ``spec.physics``, the MuJoCo model's diagnosis (app/physics_diagnosis.py) instead."""
    if spec.physics:
        from rl2s_jax.app.physics_diagnosis import physics_command  # local: MuJoCo only when asked

        return physics_command(spec)
    if spec.ckpt is not None and not os.path.isdir(spec.ckpt):
        raise ValueError(f"ckpt: expected a checkpoint directory, got {spec.ckpt!r}")
    if spec.reference is not None and not os.path.isfile(spec.reference):
        raise ValueError(f"reference: expected a Dataset file (.npz), got {spec.reference!r}")
    ds = load_dataset(spec.data)
    reference = None
    if spec.reference is not None:
        reference = load_dataset(spec.reference)
        for name in ("obs_size", "action_size"):
            if reference.meta.get(name) != ds.meta.get(name):
                raise ValueError(f"reference: its {name} {reference.meta.get(name)} differs "
                                 f"from the data's {ds.meta.get(name)}")
    model = ModelSpec()
    if spec.model_steps is not None:
        model = dataclasses.replace(model, steps=spec.model_steps)
    report = diagnose(ds, spec.out, ckpt=spec.ckpt, seeds=tuple(range(spec.seeds)),
                      reference=reference, heldout_frac=spec.heldout, split_seed=spec.seed,
                      lags=spec.lags, k_max=spec.k_max, base_spec=model.validate(),
                      zoo=spec.zoo, value_episodes=spec.value_episodes, alpha=spec.alpha,
                      progress=not spec.quiet)
    g = report["gain"]
    print(f"\ntop cause: {report['top_cause']} (confidence {report['confidence']:.2f})")
    for c in report["causes"][:4]:
        print(f"  {c['name']:<26} score {c['score']:8.4f}  p {c['p_value']:.2g}")
    if g["after"]:
        for k in ("heldout_nll", "heldout_mse", f"kstep_rmse@{g['k_max']}"):
            d = g["difference"][k]
            print(f"  {k:<16} {g['before'][k]:9.4f} -> {g['after'][k]:9.4f}  "
                  f"({d['mean']:+.4f} +- {d['std']:.4f} over {len(g['seeds'])} seeds)")
    steps = (load_meta(spec.ckpt)["step"] if spec.ckpt is not None else None) or None
    command = train_command(report, spec.data, os.path.join(spec.out, "extended"),
                            **({"steps": int(steps)} if steps else {}))
    if command:
        print(f"build the extended simulator (extension.train_set in report.json):\n  {command}")
    for n in report["extension"].get("not_trainable", []):
        print(f"  not built by rl2s train yet: {n['change']} ({n['why']})")
    print(f"-> {spec.out}/report.md, report.json")
    return 0
