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

``calibration_from_runs`` calibrates from such validation runs (``paper.py --guard-calibration``
and ``rl2s improve --guard interval --guard-calibration``); ``read_calibration`` reads either
those runs or a saved calibration (``calibrate_gains``' dict with its "task") for one task.
"""
from __future__ import annotations

import json
import math

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


def interval_guard(features: dict, cal: dict) -> tuple[np.ndarray, np.ndarray]:
    """The interval guard: deploy where the lower end of the predicted gain's interval is above
    zero. features: ``gain_features``' {"gain" [P], "member_sd" [P]} (a caller that reports
    them too computes them once). -> ([P] bool deploy, [P] lower ends)."""
    lower = gain_lower_bound(features["gain"], features["member_sd"], cal)
    return lower > 0, lower


def calibration_from_runs(runs: list[dict], task: str, level: float) -> dict:
    """The interval guard's calibration (``calibrate_gains``) from results of ``paper.py
    --policy-split validation --guard-margin M`` on ``task``: the fine-tuned validation
    policies of every lane pooled (simulators that learned from the "fit" policies only),
    their real gain I_paired. ValueError naming what a run lacks."""
    g, sd, real, sources = [], [], [], []
    for run in runs:
        if run.get("task") != task or run.get("policy_split") != "validation":
            raise ValueError(f"guard-calibration: expected a {task!r} run on the validation "
                             f"split, got {run.get('task')!r} on {run.get('policy_split')!r}")
        for lane, e in (run.get("improvement") or {}).items():
            if "guard_member_gain" not in e or "guard_member_start" not in e:
                raise ValueError(f"guard-calibration: lane {lane} has no guard_member_gain / "
                                 f"guard_member_start (a run with --guard-margin)")
            f = gain_features(e["guard_member_start"], e["guard_member_gain"])
            ok = np.asarray([x is not None for x in e["I_paired"]])
            g += f["gain"][ok].tolist()
            sd += f["member_sd"][ok].tolist()
            real += [x for x in e["I_paired"] if x is not None]
        sources.append(run.get("command"))
    if not g:
        raise ValueError("guard-calibration: the runs hold no fine-tuned policies")
    return {**calibrate_gains(g, sd, real, level), "sources": sources,
            "what": "fine-tuned validation policies (paper.py --policy-split validation), "
                    "all lanes pooled; real gain I_paired"}


CALIBRATION_KEYS = ("task", "level", "q", "floor", "n")


def _saved_calibration(d: dict, task: str, path: str) -> dict:
    """A saved calibration {"task", "level", "q", "floor", "n"} (q None or inf: too few
    calibration policies for the level), checked."""
    missing = [k for k in CALIBRATION_KEYS if k not in d]
    if missing:
        raise ValueError(f"guard-calibration: {path} lacks {missing}; expected a calibration "
                         f"{{{', '.join(CALIBRATION_KEYS)}}} or a paper.py validation-split "
                         f"result")
    if d["task"] != task:
        raise ValueError(f"guard-calibration: {path} calibrates task {d['task']!r}, the "
                         f"simulator models {task!r}")
    q = math.inf if d["q"] is None else d["q"]
    ok = (all(isinstance(d[k], int | float) and not isinstance(d[k], bool)
              for k in ("level", "floor", "n")) and isinstance(q, int | float)
          and not isinstance(q, bool) and 0 < d["level"] < 1 and d["n"] >= 1
          and math.isfinite(d["floor"]) and d["floor"] > 0 and q >= 0 and not math.isnan(q))
    if not ok:
        raise ValueError(f"guard-calibration: {path}: expected level in (0, 1), q >= 0 (None: "
                         f"infinite), floor > 0 finite, n >= 1, got "
                         f"{ {k: d[k] for k in CALIBRATION_KEYS[1:]} }")
    return {"level": float(d["level"]), "q": float(q), "floor": float(d["floor"]),
            "n": int(d["n"])}


def read_calibration(paths: list[str], task: str, level: float = tr.DEFAULT_LEVEL) -> dict:
    """The interval guard's calibration for ``task`` from ``paths``: one saved calibration
    (``_saved_calibration``), or paper.py validation-split results pooled at ``level``
    (``calibration_from_runs``). -> {"level", "q", "floor", "n", "source": the paths}.
    ValueError naming --guard-calibration for a missing, unreadable or other task's file."""
    docs = []
    for path in paths:
        try:
            with open(path) as f:
                docs.append(json.load(f))
        except FileNotFoundError:
            raise ValueError(f"guard-calibration: no such file {path}") from None
        except (OSError, ValueError) as err:  # UnicodeDecodeError and JSONDecodeError too
            raise ValueError(f"guard-calibration: {path} is not readable JSON ({err})") from None
        if not isinstance(docs[-1], dict):
            raise ValueError(f"guard-calibration: {path}: expected a JSON object")
    if any("improvement" not in d for d in docs):
        if len(docs) > 1:
            raise ValueError("guard-calibration: a saved calibration comes alone; expected one "
                             "file, or paper.py validation-split results")
        cal = _saved_calibration(docs[0], task, paths[0])
    else:
        cal = calibration_from_runs(docs, task, level)
    return {**{k: cal[k] for k in ("level", "q", "floor", "n")}, "source": list(paths)}
