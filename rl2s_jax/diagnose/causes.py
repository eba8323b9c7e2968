"""Name the cause of a simulator's held-out errors.

Every cause is a *feature* that would explain the residuals if the cause were real: past
actions for an actuation delay, past observations for an unobserved state, an estimate from the
same episode's other half for a hidden per-episode parameter, the recording order and the step
index for drift; and, for the residuals' *size* rather than their mean, functions of (s, a) for
state-dependent noise and the data's local density for a coverage gap.

Each test is a cross-fitted ridge regression (folds of whole episodes) scored in one currency:
the held-out Gaussian NLL the feature saves, in nats per transition (summed over state dims).
A cause's score is its *unique* gain: the NLL of the model with every feature minus the
NLL with every feature but its own, so that causes that look alike (a delay also makes past
observations informative; drift also makes episodes differ) are told apart by which feature
still explains the residuals once the others are accounted for. Significance is a sign-flip
randomisation test over episodes of the per-episode gains (one-sided, normal approximation to
its null); how sure the winner is comes from resampling episodes.

All NumPy; see docs/DIAGNOSIS.md for the method and its limits.
"""
from __future__ import annotations

import numpy as np

from rl2s_jax.data.episodes import Episodes, half_split
from rl2s_jax.diagnose.crossfit import (
    _random_features,
    crossfit_ridge,
    episode_folds,
    episode_sums,
    gaussian_nll,
    knn_distance,
    variance_from_log,
)
from rl2s_jax.stats import rank_sum_p, sign_flip_p

MEAN_CAUSES = {  # cause -> the feature block that would explain the residuals' mean
    "actuation_delay": "past_actions",
    "unobserved_state": "past_obs",
    "hidden_episode_parameter": "episode",
    "time_drift": "time",
}
VARIANCE_CAUSES = {  # cause -> the feature block that would explain the residuals' size
    "stochastic_noise": "magnitude",
    "coverage_gap": "density",
}
CAUSES = (*MEAN_CAUSES, *VARIANCE_CAUSES)


def rivals(top: str) -> tuple[str, ...]:
    """The causes that may outrank or join ``top``. Mechanisms before symptoms: the variance
    causes are tested on what the linear mean model leaves, and a mean cause it captures only
    in part leaves errors whose size also looks "explained" (larger where the state is
    unusual, larger in the target overall). So under a mean cause only the mean causes
    compete (ranking, confidence) and join its extension; under a variance cause, all do."""
    return tuple(MEAN_CAUSES) if top in MEAN_CAUSES else CAUSES


# ----------------------------------------------------------------------------- features


def _input_dims(eps: Episodes) -> list[int]:
    """The obs dims the tests see: all but the absolute positions."""
    return [d for d in range(eps.obs_size) if d not in eps.position_dims]


def _inputs(eps: Episodes) -> tuple[np.ndarray, np.ndarray]:
    """Standardised observation (position dims left out) [N, o'] and action [N, a] of every
    row."""
    obs = eps.obs[:, _input_dims(eps)]
    return ((obs - obs.mean(0)) / (obs.std(0) + 1e-8),
            (eps.action - eps.action.mean(0)) / (eps.action.std(0) + 1e-8))


def episode_estimate(eps: Episodes, rows: np.ndarray, target: np.ndarray, x: np.ndarray,
                     ridge: float = 5.0) -> np.ndarray:
    """Per-episode ridge fit of target [n, o] on x [n, f] (plus intercept), estimated on one
    half of each episode and applied to the other half. -> prediction [n, o].

    rows must be whole episodes in dataset order. A hidden per-episode parameter makes this
    predictive; a row's own residual never enters its prediction.
    """
    x1 = np.concatenate([np.ones((x.shape[0], 1)), x], 1)
    group = 2 * eps.episode[rows] + half_split(eps)[rows]
    if np.any(np.diff(group) < 0):
        raise ValueError("rows: expected whole episodes in dataset order")
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    gids = group[starts]
    xtx = np.add.reduceat(x1[:, :, None] * x1[:, None, :], starts, axis=0)
    xty = np.add.reduceat(x1[:, :, None] * target[:, None, :], starts, axis=0)
    index = {g: i for i, g in enumerate(gids)}
    other = np.array([index.get(g ^ 1, -1) for g in gids])
    f = x1.shape[1]
    eye = ridge * np.eye(f)
    w = np.zeros((len(gids), f, target.shape[1]))
    has = other >= 0
    w[has] = np.linalg.solve(xtx[other[has]] + eye, xty[other[has]])
    row_group = np.repeat(np.arange(len(gids)), np.diff(np.append(starts, len(rows))))
    pred = np.einsum("nf,nfo->no", x1, w[row_group])
    bound = 3.0 * target.std(0)  # a half with saturated actions can extrapolate wildly
    return np.clip(pred, -bound, bound)


def build_features(eps: Episodes, rows: np.ndarray, resid: np.ndarray, fit_rows: np.ndarray, *,
                   pred_mean: np.ndarray | None = None, lags: int = 5, n_random: int = 128,
                   seed: int = 0, max_ref: int = 5000) -> dict[str, np.ndarray]:
    """The feature blocks of the held-out rows, each [n, f].

    current: (s, a), random Fourier features of them and the model's predicted mean
    pred_mean [n, o] when given (always in every model: a model that shrinks its predictions
    towards the mean leaves residuals proportional to the true change, which the previous
    step's change, s_t - s_{t-1}, would otherwise "explain" as an unobserved state);
    past_actions / past_obs: a_{t-1..t-lags} / s_{t-1..t-lags} and their validity;
    episode: the other-half per-episode estimate of the residual (see episode_estimate);
    time: recording order and step fraction, alone and times (s, a);
    magnitude: |a|, a^2, |s|, s^2 (for the residuals' size); density: log distance to the
    nearest fit rows in (s, a), and the row's policy's log share of the fit data.
    """
    s_all, a_all = _inputs(eps)
    s, a = s_all[rows], a_all[rows]
    sa = np.concatenate([s, a], 1)
    current = np.concatenate([sa, _random_features(sa, n_random, seed)]
                             + ([] if pred_mean is None else [pred_mean]), 1)
    pa, va = eps.past(a_all, lags)
    po, _ = eps.past(s_all, lags)
    past_actions = np.concatenate([pa[rows].reshape(len(rows), -1), va[rows]], 1)
    past_obs = np.concatenate([po[rows].reshape(len(rows), -1), va[rows]], 1)
    episode = episode_estimate(eps, rows, resid, a)
    order = eps.order[rows, None] - 0.5
    step = eps.step_frac[rows, None] - 0.5
    time = np.concatenate([order, order * sa, step, step * sa], 1)
    magnitude = np.concatenate([np.abs(a), a ** 2, np.abs(s), s ** 2], 1)
    rng = np.random.default_rng(seed)
    ref_rows = fit_rows if len(fit_rows) <= max_ref else rng.choice(fit_rows, max_ref, False)
    dist = knn_distance(sa, np.concatenate([s_all[ref_rows], a_all[ref_rows]], 1))
    share = np.bincount(eps.policy[fit_rows], minlength=eps.n_policies) / len(fit_rows)
    density = np.stack([np.log(dist + 1e-6), np.log(share[eps.policy[rows]] + 1e-6)], 1)
    return {"current": current, "past_actions": past_actions, "past_obs": past_obs,
            "episode": episode, "time": time, "magnitude": magnitude, "density": density}


# ----------------------------------------------------------------------- cross-fitting


# ------------------------------------------------------------------------ significance


# ----------------------------------------------------------------------------- causes


def _cols(blocks: dict[str, np.ndarray], names) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    x = np.concatenate([blocks[n] for n in names], 1)
    index, start = {}, 0
    for n in names:
        index[n] = np.arange(start, start + blocks[n].shape[1])
        start += blocks[n].shape[1]
    return x, index


def _gain(nll_without: np.ndarray, nll_with: np.ndarray, episode: np.ndarray) -> dict:
    """Gain of a feature: per-row NLL saved (summed over dims), its mean, its per-episode sums
    and its sign-flip p-value."""
    row = (nll_without - nll_with).sum(1)
    per_ep = episode_sums(row, episode)
    return {"score": float(row.mean()), "p_value": sign_flip_p(per_ep), "per_episode": per_ep,
            "per_dim": (nll_without - nll_with).mean(0)}


def _test_causes(eps: Episodes, rows: np.ndarray, resid: np.ndarray, std: np.ndarray,
                 fit_rows: np.ndarray, *, pred_mean, lags: int, n_folds: int, seed: int,
                 resolution: float, side: np.ndarray | None = None) -> dict:
    """Every cause's unique gain on these rows. -> {"results": cause -> gain (``_gain`` plus
    "marginal"), "nll" / "vnll": model -> per-row NLL [n, o] of the mean / variance models,
    "u2" [n, o], "episode" [n], "rows", "resid", "blocks"}.

    side [n] (0/1, differential mode): which dataset each row comes from; every mean and
    variance model then carries a per-side intercept, so that a side's overall offset or
    error scale is never credited to a cause."""
    episode = eps.episode[rows]
    folds = episode_folds(eps, rows, n_folds, seed)
    blocks = build_features(eps, rows, resid, fit_rows, pred_mean=pred_mean, lags=lags,
                            seed=seed)
    if side is not None:
        blocks["side"] = np.asarray(side, np.float64)[:, None]
    mean_names = ["current", *MEAN_CAUSES.values()]
    x, idx = _cols(blocks, mean_names)
    everything = np.concatenate([idx[n] for n in mean_names])
    models = {"full": everything, "current": idx["current"]}
    for block in MEAN_CAUSES.values():
        models[f"-{block}"] = np.setdiff1d(everything, idx[block])
        models[f"+{block}"] = np.concatenate([idx["current"], idx[block]])
    n_a, n_s = eps.action_size, len(_input_dims(eps))
    pa = idx["past_actions"]
    for j in range(lags):  # drop one lag of actions / observations, then one actuator
        models[f"-a_lag{j + 1}"] = np.setdiff1d(everything, pa[j * n_a:(j + 1) * n_a])
        models[f"-s_lag{j + 1}"] = np.setdiff1d(
            everything, idx["past_obs"][j * n_s:(j + 1) * n_s])
    for i in range(n_a):
        models[f"-actuator{i}"] = np.setdiff1d(everything, pa[np.arange(lags) * n_a + i])
    split = 1 + n_s + n_a  # the time block: order and order * (s, a) first, then step
    models["-time-episode"] = np.setdiff1d(everything, np.r_[idx["time"], idx["episode"]])
    # Drift's sub-blocks, measured as drift itself is (without the per-episode block, which
    # otherwise absorbs a change over the recording order and leaves only "step" to credit).
    models["-order-episode"] = np.setdiff1d(everything,
                                            np.r_[idx["time"][:split], idx["episode"]])
    models["-step-episode"] = np.setdiff1d(everything,
                                           np.r_[idx["time"][split:], idx["episode"]])
    if side is not None:
        x = np.concatenate([x, blocks["side"]], 1)
        models = {m: np.append(cols, x.shape[1] - 1) for m, cols in models.items()}
    fits = crossfit_ridge(x, resid, folds, models)
    floor = resolution ** 2
    # Each model's error variance per dim is that of its own held-out errors, so a model that
    # overfits its folds pays for it.
    nll = {m: gaussian_nll(resid - pred, np.maximum(((resid - pred) ** 2).mean(0), floor))
           for m, pred in fits.items()}

    results = _mean_results(nll, episode)

    # The residuals' size, after the full mean model, in units of the model's own std.
    err = resid - fits["full"]
    u2 = (err / std) ** 2
    xv, vidx = _cols(blocks, ["magnitude", "density"])
    vmodels = {"none": np.array([], int), "full": np.arange(xv.shape[1]),
               "-magnitude": vidx["density"], "-density": vidx["magnitude"],
               "+magnitude": vidx["magnitude"], "+density": vidx["density"]}
    if side is not None:
        # What is new in the target's error size: a side intercept and side x magnitude (its
        # noise, overall or signal-dependent) and side x density (its sparse regions) on top
        # of the structure both sides share.
        sv = blocks["side"]
        on = sv[:, 0] > 0  # density centred on the target, so the side's overall error
        dens = blocks["density"] - blocks["density"][on].mean(0)  # scale stays with noise
        xv = np.concatenate([xv, sv, sv * blocks["magnitude"], sv * dens], 1)
        shared = np.arange(vidx["density"][-1] + 1)
        noise_new = np.arange(shared.size, shared.size + 1 + blocks["magnitude"].shape[1])
        gap_new = np.arange(noise_new[-1] + 1, xv.shape[1])
        vmodels = {"none": shared, "full": np.arange(xv.shape[1]),
                   "-magnitude": np.r_[shared, gap_new], "-density": np.r_[shared, noise_new],
                   "+magnitude": np.r_[shared, noise_new], "+density": np.r_[shared, gap_new]}
    # Log-variance regression (robust to the heavy tails of squared errors); each model's
    # predicted variance is rescaled per dim so that it is unbiased for u^2 on average.
    log_u2 = np.log(u2 + 1e-3 * u2.mean(0) + 1e-30)
    vfits = crossfit_ridge(xv, log_u2, folds, vmodels)
    vnll = {m: gaussian_nll(err, np.maximum(std ** 2 * variance_from_log(pred, log_u2, u2),
                                            floor))
            for m, pred in vfits.items()}
    for cause, block in VARIANCE_CAUSES.items():
        g = _gain(vnll[f"-{block}"], vnll["full"], episode)
        g["marginal"] = _gain(vnll["none"], vnll[f"+{block}"], episode)["score"]
        results[cause] = g
    return {"results": results, "nll": nll, "vnll": vnll, "u2": u2, "episode": episode,
            "rows": rows, "resid": resid, "blocks": blocks}


def _mean_results(nll: dict, episode: np.ndarray) -> dict:
    """Each mean cause's unique gain (``_gain`` plus "marginal") from the per-row NLLs of the
    mean models. Drift is the structured case of a per-episode difference (one that the
    recording order predicts), so it is credited first: its gain is measured without the
    per-episode block, and the per-episode block keeps only what the time inputs cannot
    explain."""
    results = {}
    for cause, block in MEAN_CAUSES.items():
        without, with_ = ("-time-episode", "-episode") if block == "time" else (f"-{block}",
                                                                                 "full")
        results[cause] = _gain(nll[without], nll[with_], episode)
        results[cause]["marginal"] = _gain(nll["current"], nll[f"+{block}"], episode)["score"]
    return results


def _side_view(tested: dict, mask: np.ndarray) -> dict:
    """The rows ``mask`` [n] of a pooled ``_test_causes`` result, with each cause's gains
    recomputed on them alone (the fitted models stay the pooled ones)."""
    episode = tested["episode"][mask]
    nll = {m: v[mask] for m, v in tested["nll"].items()}
    vnll = {m: v[mask] for m, v in tested["vnll"].items()}
    results = _mean_results(nll, episode)
    for cause, block in VARIANCE_CAUSES.items():
        results[cause] = _gain(vnll[f"-{block}"], vnll["full"], episode)
        results[cause]["marginal"] = _gain(vnll["none"], vnll[f"+{block}"], episode)["score"]
    return {"results": results, "nll": nll, "vnll": vnll, "u2": tested["u2"][mask],
            "episode": episode, "rows": tested["rows"][mask], "resid": tested["resid"][mask],
            "blocks": {b: v[mask] for b, v in tested["blocks"].items()}}


def _difference(tested: dict, ref: dict, pooled: dict) -> dict:
    """Differential gains. Mean causes: target minus reference score, per dim and marginal,
    the p-value from the rank-sum test of per-episode mean gains (target > reference).
    Variance causes: the pooled gain of the target-only terms (side x magnitude / density),
    which only the target's own error size can earn, with the sign-flip p over all
    episodes."""
    out = {}
    for c, g in tested["results"].items():
        if c in VARIANCE_CAUSES:
            out[c] = dict(pooled["results"][c])
            continue
        r = ref["results"][c]
        out[c] = {"score": g["score"] - r["score"], "per_dim": g["per_dim"] - r["per_dim"],
                  "marginal": g["marginal"] - r["marginal"],
                  "per_episode": g["per_episode"],
                  "p_value": rank_sum_p(_per_row(g["per_episode"], tested["episode"]),
                                        _per_row(r["per_episode"], ref["episode"]))}
    return out


def _per_row(per_episode: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """Per-episode sums [E'] divided by the episodes' row counts: mean gain per transition."""
    _, counts = np.unique(episode, return_counts=True)
    return per_episode / counts


def diagnose_causes(eps: Episodes, rows: np.ndarray, resid: np.ndarray, std: np.ndarray,
                fit_rows: np.ndarray, *, pred_mean: np.ndarray | None = None, lags: int = 5,
                n_folds: int = 5, seed: int = 0,
                alpha: float = 0.01, min_score: float = 0.02, resolution: float = 0.03,
                n_boot: int = 200, obs_names=None, action_names=None,
                in_target: np.ndarray | None = None) -> dict:
    """Test the held-out residuals against every cause.

    eps: the episodes; rows [n]: held-out rows (whole episodes, dataset order); resid [n, o]:
    normalised residuals (delta / delta_std minus the model's mean); std [n, o]: the model's
    std in the same units; fit_rows: the rows the model was fit on (for the density feature);
    pred_mean [n, o]: the model's predicted mean in the same units (recommended).

    resolution: errors below this fraction of the data's delta std count as exact (a variance
    floor in every NLL), so that round-off on a dim the model gets right is never "explained".
    A cause is *significant* when its p-value is below alpha / (number of causes) and its unique
    score is at least ``min_score`` nats per transition. Returns {"causes": [...] ranked (most
    significant first, then by score), "top_cause", "confidence", "scores": {...}}; each cause is
    {"name", "score", "p_value", "significant", "marginal_score", "details"}.

    Differential mode (``in_target`` [n] bool given): ``rows`` hold the held-out rows of a
    target dataset and of a reference dataset of the same system (``episodes.pool_episodes``),
    the residuals of both from the same model. The tests' regressions are fitted once, on
    both sides' rows (cross-fitted over the pooled episodes, with a per-side intercept); a
    cause's score is its mean gain on the target's rows minus that on the reference's, and its
    p-value is a one-sided rank-sum test that the target's per-episode gains exceed the
    reference's. Both sides share every fitted model, so the side labels are exchangeable when
    the datasets do not differ and the rank-sum test keeps its level (fitting each side on its
    own, as an earlier version did, made clean-vs-clean "significant" on large data). An
    effect that both datasets show scores about zero; what is new in the target stands out.
    The details (lag, actuators, dims) come from the same differences.
    """
    rows = np.asarray(rows)
    resid, std = np.asarray(resid, np.float64), np.asarray(std, np.float64)
    if resid.shape != (len(rows), eps.obs_size) or std.shape != resid.shape:
        raise ValueError(f"resid, std: expected shape [{len(rows)}, {eps.obs_size}], got "
                         f"{resid.shape} and {std.shape}")
    if not (np.isfinite(resid).all() and np.isfinite(std).all() and (std > 0).all()):
        raise ValueError("resid, std: expected finite residuals and positive stds")
    obs_names = obs_names or [f"obs{d}" for d in range(eps.obs_size)]
    action_names = action_names or [f"act{i}" for i in range(eps.action_size)]
    kw = dict(pred_mean=pred_mean, lags=lags, n_folds=n_folds, seed=seed, resolution=resolution)
    if in_target is None:
        tested = _test_causes(eps, rows, resid, std, fit_rows, **kw)
        ref = None
    else:
        sel = np.asarray(in_target, bool)
        if sel.shape != (len(rows),):
            raise ValueError(f"in_target: expected a bool mask of shape [{len(rows)}], got "
                             f"{sel.shape}")
        if sel.all() or not sel.any():
            raise ValueError("in_target: expected held-out rows of both the target and the "
                             "reference")
        pooled = _test_causes(eps, rows, resid, std, fit_rows, **kw, side=sel.astype(int))
        tested, ref = _side_view(pooled, sel), _side_view(pooled, ~sel)
    results = tested["results"] if ref is None else _difference(tested, ref, pooled)
    n_tests = len(CAUSES)
    for g in results.values():
        g["significant"] = bool(g["p_value"] < alpha / n_tests and g["score"] >= min_score)

    details = _details(results, tested, ref, None if ref is None else pooled, eps, lags=lags,
                       alpha=alpha,
                       obs_names=obs_names, action_names=action_names)
    # Significant mean causes first, then by score (mechanisms before symptoms: ``rivals``).
    ranked = sorted(results, key=lambda c: (not results[c]["significant"],
                                            c not in MEAN_CAUSES, -results[c]["score"]))
    top = ranked[0] if results[ranked[0]]["significant"] else "none"
    confidence = _confidence(results, top, tested, ref, min_score, n_boot, seed)
    causes = [{"name": c, "score": results[c]["score"], "p_value": results[c]["p_value"],
               "significant": results[c]["significant"],
               "marginal_score": results[c]["marginal"], "details": details[c]} for c in ranked]
    none_entry = {"name": "none", "score": 0.0,
                  "p_value": float(min(1.0, min(results[c]["p_value"] for c in results)
                                       * n_tests)),
                  "significant": top == "none", "marginal_score": 0.0,
                  "details": {"meaning": "no cause explains the held-out residuals beyond "
                                         f"{min_score} nats/transition at level {alpha}"}}
    causes.insert(0 if top == "none" else len(causes), none_entry)
    return {"causes": causes, "top_cause": top, "confidence": confidence,
            "settings": {"lags": lags, "folds": n_folds, "alpha": alpha,
                         "min_score": min_score, "n_boot": n_boot,
                         "rows": int(len(tested["episode"])),
                         "episodes": int(len(np.unique(tested["episode"]))),
                         "differential": ref is not None,
                         **({} if ref is None else {
                             "reference_rows": int(len(ref["episode"])),
                             "reference_episodes": int(len(np.unique(ref["episode"])))})}}


def _dims_of(per_dim: np.ndarray, frac: float = 0.1) -> list[int]:
    """Dims that carry at least ``frac`` of the largest per-dim gain (and a positive one)."""
    if per_dim.max() <= 0:
        return []
    return [int(d) for d in np.flatnonzero(per_dim >= frac * per_dim.max())]


def _details(results, tested, ref, pooled, eps, *, lags, alpha, obs_names, action_names
             ) -> dict:
    u2, episode = tested["u2"], tested["episode"]
    rows, resid, blocks = tested["rows"], tested["resid"], tested["blocks"]

    def side_gain(t, name, d=None, against="full"):
        """The gain of dropping model ``name`` (from model ``against``) on one side (summed
        dims), or of the noise terms on dim d."""
        if d is None:
            return _gain(t["nll"][name], t["nll"][against], t["episode"])
        return _gain(t["vnll"]["-magnitude"][:, d:d + 1], t["vnll"]["full"][:, d:d + 1],
                     t["episode"])

    def drop_gain(name, d=None, against="full"):
        """Its gain, the reference's subtracted in differential mode (a noise dim's: pooled,
        as the stochastic_noise score)."""
        if ref is not None and name is None:
            return side_gain(pooled, name, d)
        g = side_gain(tested, name, d, against)
        if ref is None:
            return g
        r = side_gain(ref, name, d, against)
        return {"score": g["score"] - r["score"],
                "p_value": rank_sum_p(_per_row(g["per_episode"], episode),
                                      _per_row(r["per_episode"], ref["episode"]))}

    n_a = eps.action_size
    lag_gain = [drop_gain(f"-a_lag{j + 1}")["score"] for j in range(lags)]
    act = [drop_gain(f"-actuator{i}") for i in range(n_a)]
    best_act = max(g["score"] for g in act)
    actuators = [i for i, g in enumerate(act)
                 if g["score"] >= 0.2 * best_act and g["score"] > 0 and g["p_value"] < alpha]
    obs_lag_gain = [drop_gain(f"-s_lag{j + 1}")["score"] for j in range(lags)]
    order_gain = drop_gain("-order-episode", against="-episode")["score"]
    step_gain = drop_gain("-step-episode", against="-episode")["score"]
    # Between-episode share of the residual variance, per dim (intra-class correlation).
    _, inv = np.unique(episode, return_inverse=True)
    counts = np.bincount(inv)
    ep_mean = np.stack([np.bincount(inv, weights=resid[:, d]) for d in range(resid.shape[1])],
                       1) / counts[:, None]
    between = (counts[:, None] * (ep_mean - resid.mean(0)) ** 2).sum(0)
    total = ((resid - resid.mean(0)) ** 2).sum(0) + 1e-12
    noise_dim = results["stochastic_noise"]["per_dim"]
    noise_p = [drop_gain(None, d)["p_value"] for d in range(u2.shape[1])]
    noise_dims = [d for d in range(u2.shape[1])
                  if noise_p[d] < alpha / u2.shape[1] and noise_dim[d] > 0.01]
    dens = blocks["density"][:, 0]
    sparse = dens >= np.quantile(dens, 0.8)
    err = u2.sum(1)
    per_policy = {int(p): float(err[eps.policy[rows] == p].mean())
                  for p in np.unique(eps.policy[rows])}
    worst_policies = sorted(per_policy, key=per_policy.get, reverse=True)[:3]

    def names(ids, table):
        return [table[i] for i in ids]

    delay_lag = int(np.argmax(lag_gain)) + 1
    return {
        "actuation_delay": {
            "lag": delay_lag, "actuators": actuators,
            "actuator_names": names(actuators, action_names),
            "gain_by_lag": lag_gain, "gain_by_actuator": [g["score"] for g in act],
            "dims": _dims_of(results["actuation_delay"]["per_dim"])},
        "unobserved_state": {
            "lags": [j + 1 for j, g in enumerate(obs_lag_gain)
                     if g >= 0.2 * max(max(obs_lag_gain), 1e-12) and g > 0],
            "gain_by_lag": obs_lag_gain,
            "dims": _dims_of(results["unobserved_state"]["per_dim"])},
        "hidden_episode_parameter": {
            "dims": _dims_of(results["hidden_episode_parameter"]["per_dim"]),
            "between_episode_share": (between / total).tolist()},
        "time_drift": {
            "over": "episode_order" if order_gain >= step_gain else "step",
            "gain_order": order_gain, "gain_step": step_gain,
            "dims": _dims_of(results["time_drift"]["per_dim"])},
        "stochastic_noise": {
            "dims": noise_dims, "dim_names": names(noise_dims, obs_names),
            "gain_by_dim": noise_dim.tolist(), "p_by_dim": noise_p,
            "calibration_z2": u2.mean(0).tolist()},
        "coverage_gap": {
            "error_ratio_sparse_vs_rest": float(err[sparse].mean() / max(err[~sparse].mean(),
                                                                          1e-12)),
            "worst_policies": worst_policies,
            "error_by_policy": per_policy},
    }


def _confidence(results: dict, top: str, tested: dict, ref: dict | None, min_score: float,
                n_boot: int, seed: int) -> float:
    """Share of episode resamples in which the reported cause still wins: the top cause has
    the highest score (among the mean causes when it is one; for "none": no cause reaches
    min_score). Each side's episodes are
    resampled on their own; in differential mode a mean cause's score is the target's minus
    the reference's, a variance cause's the gain over both sides' rows (``_difference``)."""
    names = list(results)
    variance = np.array([c in VARIANCE_CAUSES for c in names])
    rng = np.random.default_rng(seed + 1)
    sides = []
    for t in [tested] if ref is None else [tested, ref]:
        per_ep = np.stack([t["results"][c]["per_episode"] for c in names])  # [C, E]
        _, inv = np.unique(t["episode"], return_inverse=True)
        sides.append((per_ep, np.bincount(inv).astype(float)))
    wins = 0
    for _ in range(n_boot):
        sums, rows = [], []
        for per_ep, n_rows in sides:
            pick = rng.integers(0, per_ep.shape[1], per_ep.shape[1])
            sums.append(per_ep[:, pick].sum(1))
            rows.append(n_rows[pick].sum())
        if ref is None:
            scores = sums[0] / rows[0]
        else:
            scores = np.where(variance, (sums[0] + sums[1]) / (rows[0] + rows[1]),
                              sums[0] / rows[0] - sums[1] / rows[1])
        if top == "none":
            wins += bool(scores.max() < min_score)
        else:  # among the causes that may outrank it, as in the ranking
            pool = np.isin(names, rivals(top))
            best = np.flatnonzero(pool)[int(np.argmax(scores[pool]))]
            wins += bool(names[best] == top and scores[best] >= min_score)
    return wins / n_boot
