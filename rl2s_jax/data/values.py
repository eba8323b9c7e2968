"""True values of the logged policies: measured, or the discounted return of logged episodes."""

from __future__ import annotations

import numpy as np


def _measured_values_apply(ds, horizon: int, gamma: float) -> bool:
    """Whether the Dataset's measured values are the true values for this horizon and gamma:
    it has them, the horizon covers whole episodes and gamma matches."""
    meta = ds.meta
    full = meta.get("episode_length") is not None and horizon >= meta["episode_length"]
    return bool(ds.has_values and full and abs(float(meta.get("gamma") or 0) - gamma) < 1e-9)


def truth_used(ds, horizon: int, gamma: float, truth: str = "auto") -> str:
    """Which true value ``true_values`` gives for ``truth`` ("auto": measured where they
    apply, else logged; "measured": refused where they do not apply; "logged"): "measured"
    (the data's fresh-episode values) or "logged" (the logged episodes' discounted return)."""
    if truth not in ("auto", "measured", "logged"):
        raise ValueError(f"truth: expected auto, measured or logged, got {truth!r}")
    if truth == "logged":
        return "logged"
    if _measured_values_apply(ds, horizon, gamma):
        return "measured"
    if truth == "measured":
        raise ValueError(
            f"truth: 'measured' values are of whole episodes ({ds.meta.get('episode_length')} "
            f"steps) at gamma {ds.meta.get('gamma')} and need the data's value episodes "
            f"(has_values {ds.has_values}); this is horizon {horizon}, gamma {gamma}: use "
            f"--truth logged or auto, or a horizon of the whole episode")
    return "logged"


def true_values_se(ds, horizon: int, gamma: float, truth: str = "auto") -> np.ndarray | None:
    """Standard errors [P] of ``true_values`` where the data measured them, else None."""
    if truth_used(ds, horizon, gamma, truth) == "measured":
        return np.asarray(ds.value_discounted_se, np.float64)
    return None


def true_values(ds, horizon: int, gamma: float, strict: bool = True,
                truth: str = "auto") -> np.ndarray:
    """True discounted value [P] of each policy of ``ds`` over ``horizon`` steps.

    The Dataset's measured ``value_discounted`` when the horizon covers the whole episode and
    gamma matches; otherwise the logged episodes' discounted return over the first ``horizon``
    steps (``data_values``); ``truth`` picks one (``truth_used``). ``strict``: a policy
    without a usable episode is an error (else NaN).
    """
    if truth_used(ds, horizon, gamma, truth) == "measured":
        return np.asarray(ds.value_discounted, np.float32)
    ended = np.asarray(ds.done) | np.asarray(ds.truncated)
    values, _ = data_values(np.asarray(ds.reward), ended, np.asarray(ds.policy_id),
                            np.asarray(ds.episode_id), np.asarray(ds.t), ds.n_policies,
                            horizon=horizon, gamma=gamma)
    if strict and np.isnan(values).any():
        bad = int(np.flatnonzero(np.isnan(values))[0])
        raise ValueError(
            f"vd_horizon: policy {bad} has no logged episode that starts at t = 0 and is "
            f"seen for {horizon} steps (or to its end), so its true value over that horizon "
            f"is unknown; lower vd_horizon or collect whole episodes")
    return values.astype(np.float32)


def data_values(reward: np.ndarray, ended: np.ndarray, policy_id: np.ndarray,
                episode_id: np.ndarray, t: np.ndarray, n_policies: int, *, horizon: int,
                gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """True discounted value of each policy over the first ``horizon`` steps, from logged
    episodes that start at t = 0 and are seen until they end or reach ``horizon`` steps.

    Arrays [N]: a Dataset's reward, ``done | truncated``, policy_id, episode_id, t.
    -> (values [P], number of usable episodes [P]); a policy without one gets NaN.
    """
    reward = np.asarray(reward, np.float64)
    sums = np.zeros(n_policies)
    counts = np.zeros(n_policies, np.int64)
    bounds = np.flatnonzero(np.diff(episode_id) != 0) + 1
    for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(episode_id)], strict=True):
        if t[lo] != 0:
            continue
        n = min(hi - lo, horizon)
        if n < horizon and not ended[lo + n - 1]:
            continue  # cut off by the end of collection before the horizon: value unknown
        p = int(policy_id[lo])
        sums[p] += np.sum(reward[lo:lo + n] * gamma ** np.arange(n))
        counts[p] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan), counts
