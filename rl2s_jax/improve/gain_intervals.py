"""The deployment guard as a value interval (issue 64 item 3): one notion of trust for values
and for gains. A fine-tuned policy is deployed when the lower end of its predicted GAIN's
split-conformal interval is above zero, instead of every member predicting a gain above a
floor scaled per task (``finetune.deployment_guard``, ``recipes``' floor scales).

The gain of policy p in a simulator, from what the guard already simulates
(``lane_finetune.guard_lanes``: each elite member alone, the start and the tuned policy from
common random numbers), relative to the start as the real gain I = (C1 - C0) / |C0| is:

    g_m = (V_m(tuned) - V_m(start)) / |mean_m V_m(start)|,  predicted gain G = mean_m g_m,
    sigma = std_m g_m x 1 + floor  (``trust.difficulty`` with only the member spread: the
    guard records no seed spread, Monte-Carlo error or support; floor: FLOOR_FRACTION x the
    calibration policies' range of G)

Calibration (``calibrate_gains``): fine-tuned policies whose real gain is known and whose
simulators never saw them, e.g. ``paper.py --policy-split validation``'s fine-tuned validation
policies; score |G - I| / sigma, q their conformal quantile at ``level``. Guard: deploy where
G - q sigma > 0. Relative gains put the simulated (discounted, at the guard's horizon) and
the real (undiscounted) gains on one scale; what is left of the difference is in the scores.
"""
from __future__ import annotations

import numpy as np

from rl2s_jax.evaluate import trust as tr


def gain_features(member_start, member_gain, scale=None) -> dict:
    """member_start, member_gain [M, P] (the guard's ``guard_member_start`` /
    ``guard_member_gain``: each elite's value of the start and its predicted gain, value
    units; member_start may be None where ``scale`` is given); scale [P]: what a gain is
    relative to (None: |mean_m member_start|) -> {"gain" [P] predicted relative gain G,
    "member_sd" [P] the elites' std of it (0 for one elite)}."""
    g = np.asarray(member_gain, np.float64)
    v0 = g if member_start is None else np.asarray(member_start, np.float64)
    if g.ndim != 2 or v0.shape != g.shape:
        raise ValueError(f"member_gain: expected the shape of member_start [M, P] {v0.shape}, "
                         f"got {g.shape}")
    if not (np.all(np.isfinite(v0)) and np.all(np.isfinite(g))):
        raise ValueError("member_start, member_gain: expected finite simulated values")
    if scale is None and member_start is None:
        raise ValueError("scale: expected [P] values where member_start is None")
    scale = np.maximum(np.abs(v0.mean(0) if scale is None else np.asarray(scale, np.float64)),
                       1e-9)
    rel = g / scale
    sd = rel.std(0, ddof=1) if rel.shape[0] > 1 else np.zeros(rel.shape[1])
    return {"gain": rel.mean(0), "member_sd": sd}


def _sigma(member_sd, floor: float) -> np.ndarray:
    z = np.zeros_like(np.asarray(member_sd, np.float64))
    return tr.difficulty(member_sd, z, z, np.ones_like(z), floor)


def calibrate_gains(gain, member_sd, real_gain, level: float = tr.DEFAULT_LEVEL) -> dict:
    """The interval guard's calibration from fine-tuned policies whose real relative gain
    ``real_gain`` [n] is known (never the policies it then guards): gain, member_sd [n] of
    ``gain_features``. -> {"level", "q" (inf below ``trust.min_calibration(level)``),
    "floor", "n"}."""
    level = tr.check_level(level)
    g, sd, real = (np.asarray(x, np.float64).ravel() for x in (gain, member_sd, real_gain))
    if not (g.shape == sd.shape == real.shape) or g.size == 0:
        raise ValueError(f"gain, member_sd, real_gain: expected three [n] arrays, n >= 1, got "
                         f"{g.shape}, {sd.shape}, {real.shape}")
    if not np.all(np.isfinite(real)):
        raise ValueError("real_gain: the calibration policies need finite real gains")
    floor = tr.sigma_floor(g)
    scores = np.abs(g - real) / _sigma(sd, floor)
    return {"level": level, "q": tr.conformal_quantile(scores, level), "floor": floor,
            "n": int(g.size)}


def gain_lower_bound(gain, member_sd, cal: dict) -> np.ndarray:
    """[P] the lower end G - q sigma of each predicted gain's interval (-inf for an infinite
    q)."""
    g = np.asarray(gain, np.float64)
    return g - cal["q"] * _sigma(member_sd, cal["floor"]) if np.isfinite(cal["q"]) else \
        np.full(g.shape, -np.inf)


def interval_guard(member_start, member_gain, cal: dict) -> tuple[np.ndarray, np.ndarray]:
    """The interval guard: deploy where the lower end of the predicted gain's interval is above
    zero. member_start, member_gain [M, P]. -> ([P] bool deploy, [P] lower ends)."""
    f = gain_features(member_start, member_gain)
    lower = gain_lower_bound(f["gain"], f["member_sd"], cal)
    return lower > 0, lower
