"""Data with planted effects: a tiny two-body system whose ground truth is known exactly.

"twomass": two damped point masses on a line, each driven by its own actuator and joined by a
weak spring. Observation (p1, v1, p2, v2), actions (a1, a2) in [-1, 1], dt = 0.05, with
semi-implicit Euler (:func:`twomass_dynamics`)::

    v_j' = decay v_j + dt (gain a_j - spring (p_j - p_other)) / mass_j
    p_j' = p_j + dt v_j'

Clean data is exactly this deterministic model (the state is rounded to float32 every step,
so ``twomass_dynamics(obs, action)`` reproduces ``next_obs`` bit for bit). Each effect of
:func:`make_planted` changes the true system in one way a diagnosis should find and name; the
truth goes to ``meta["source"]["planted"]``. Everything is NumPy, vectorised over episodes
(all episodes step together; Python loops over time steps only).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from rl2s_jax.data.dataset import Dataset

__all__ = ["EFFECTS", "TWOMASS", "make_planted", "twomass_dynamics"]

#: Constants of the clean system.
TWOMASS = {"dt": 0.05, "decay": 0.96, "gain": 3.0, "mass": (1.0, 1.0), "spring": 1.0}

#: Effect name -> its keyword arguments and their defaults.
EFFECTS: dict[str, dict[str, Any]] = {
    "clean": {},
    "delay": {"lag": 2, "actuators": (0,)},
    "episode_param": {"mass_range": (0.5, 2.0)},
    "noise": {"dims": (3,), "scale": 0.03, "base": 0.2},
    "unobserved": {"spring": 2.0, "mass": 0.5, "decay": 0.99},
    "drift": {"gain_start": 1.0, "gain_end": 0.6},
}

_VELOCITY_DIM_OF_BODY = (1, 3)  # obs dim of v_j for body j (0-based)
# Independent random streams, so that datasets of different effects with the same seed share
# policies, start states and exploration noise.
_RNG_POLICIES, _RNG_STARTS, _RNG_EXPLORE, _RNG_EFFECT = range(4)


def twomass_dynamics(obs: np.ndarray, action: np.ndarray, *, mass1: Any = None,
                     gain_scale: Any = 1.0, force1: Any = 0.0) -> np.ndarray:
    """The twomass step in float64. obs [..., 4], action [..., 2] -> next_obs [..., 4].

    The clean system with the defaults. mass1 (body 1's mass; default TWOMASS["mass"][0]),
    gain_scale (factor on both actuator gains) and force1 (an extra force on body 1)
    broadcast against obs[..., 0]. Actions are clipped to [-1, 1].
    """
    obs = np.asarray(obs, np.float64)
    a = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
    c = TWOMASS
    mass1 = c["mass"][0] if mass1 is None else np.asarray(mass1, np.float64)
    p1, v1, p2, v2 = (obs[..., i] for i in range(4))
    gain = c["gain"] * np.asarray(gain_scale, np.float64)
    f1 = gain * a[..., 0] - c["spring"] * (p1 - p2) + force1
    f2 = gain * a[..., 1] - c["spring"] * (p2 - p1)
    v1n = c["decay"] * v1 + c["dt"] * f1 / mass1
    v2n = c["decay"] * v2 + c["dt"] * f2 / c["mass"][1]
    return np.stack([p1 + c["dt"] * v1n, v1n, p2 + c["dt"] * v2n, v2n], axis=-1)


def make_planted(effect: str = "clean", *, n_episodes: int = 240, episode_length: int = 60,
                 n_policies: int = 6, seed: int = 0, **effect_kwargs) -> Dataset:
    """A twomass Dataset with one planted effect (see module docstring for the system).

    effect (defaults in :data:`EFFECTS`):
      "clean": nothing.
      "delay": actuators in ``actuators`` apply a_{t-lag} (zeros before the episode start).
      "episode_param": body 1's mass is drawn per episode, log-uniform in ``mass_range``.
      "noise": v_j' of each velocity obs dim in ``dims`` (1 -> body 1, 3 -> body 2) gets
        N(0, (scale (base + |a_j|))^2) added: motor noise, growing with the command. It is an
        impulse at the end of the step: positions move by it from the next step on.
      "unobserved": a hidden body 3 (p3, v3; mass ``mass``, velocity decay ``decay``) hangs
        on body 1 by a spring of stiffness ``spring``; p3 and v3 are not observed.
      "drift": both actuator gains fall linearly over the recording order, from
        ``gain_start`` x (first episode) to ``gain_end`` x (last).

    Episodes are of fixed length (truncated, never done), each from a fresh random start, in
    recording order (episode_id = time order); episode e runs policy e % n_policies. Policies
    are PD controllers towards per-policy targets with autocorrelated exploration noise and a
    slow sinusoid. Returns a validated Dataset without values (N = n_episodes *
    episode_length rows); ``meta["source"]["planted"]`` holds the ground truth (dims are
    0-based obs indices, actuators 0-based action indices):

      clean:         {"effect": "none"}
      delay:         {"effect": "actuation_delay", "lag": 2, "actuators": [0]}
      episode_param: {"effect": "hidden_episode_parameter", "parameter": "mass1",
                      "distribution": "log-uniform", "range": [0.5, 2.0],
                      "values": [mass1 of each episode, in episode_id order]}
      noise:         {"effect": "stochastic_noise", "dims": [3], "std": "...",
                      "scale": 0.03, "base": 0.2}
      unobserved:    {"effect": "unobserved_state", "hidden": ["p3", "v3"],
                      "coupled_to": "body1", "dims": [0, 1], "spring": 2.0, "mass": 0.5,
                      "decay": 0.99}
      drift:         {"effect": "time_drift", "over": "episode_order",
                      "parameter": "actuator_gain", "actuators": [0, 1], "start": 1.0,
                      "end": 0.6}

    Effects combine with "+" (for example "delay+noise": both at once, each with its
    defaults; ``effect_kwargs`` must then be empty). The truth of a combination is
    {"effect": "combined", "effects": [the truth of each part]}.

    Raises ValueError on a bad argument, before any work.
    """
    parts = tuple(str(effect).split("+")) if isinstance(effect, str) else (effect,)
    if len(parts) > 1:
        if effect_kwargs:
            raise ValueError(f"effect {effect!r}: a combination takes no effect arguments, "
                             f"got {', '.join(sorted(effect_kwargs))}")
        if len(set(parts)) != len(parts) or "clean" in parts:
            raise ValueError(f"effect: expected distinct effects other than 'clean' joined "
                             f"by '+', got {effect!r}")
        kws = {p: _check_args(p, {}, n_episodes, episode_length, n_policies) for p in parts}
    else:
        kws = {effect: _check_args(effect, effect_kwargs, n_episodes, episode_length,
                                   n_policies)}
    E, L, P = n_episodes, episode_length, n_policies
    rng = {k: np.random.default_rng([seed, k]) for k in
           (_RNG_POLICIES, _RNG_STARTS, _RNG_EXPLORE, _RNG_EFFECT)}
    policies = _make_policies(rng[_RNG_POLICIES], P)
    episode_policy = np.arange(E) % P
    pol = {k: v[episode_policy] for k, v in policies.items()}  # each [E, ...]
    order = np.arange(E) / max(E - 1, 1)

    state = _f32(np.concatenate([rng[_RNG_STARTS].uniform(-1.0, 1.0, (E, 1)),
                                 rng[_RNG_STARTS].uniform(-0.5, 0.5, (E, 1)),
                                 rng[_RNG_STARTS].uniform(-1.0, 1.0, (E, 1)),
                                 rng[_RNG_STARTS].uniform(-0.5, 0.5, (E, 1))], axis=1))
    phase = rng[_RNG_STARTS].uniform(0.0, 2 * np.pi, (E, 2))
    explore = np.zeros((E, 2))
    erng = rng[_RNG_EFFECT]

    mass1 = np.full(E, TWOMASS["mass"][0])
    gain_scale = np.ones(E)
    truths: list[dict[str, Any]] = []
    if "delay" in kws:
        kd = kws["delay"]
        queue = np.zeros((E, kd["lag"], 2))  # a_{t-lag} ... a_{t-1}
        delayed = np.isin(np.arange(2), kd["actuators"])
        truths.append({"effect": "actuation_delay", "lag": kd["lag"],
                       "actuators": sorted(kd["actuators"])})
    if "episode_param" in kws:
        lo, hi = kws["episode_param"]["mass_range"]
        mass1 = np.exp(erng.uniform(math.log(lo), math.log(hi), E))
        truths.append({"effect": "hidden_episode_parameter", "parameter": "mass1",
                       "distribution": "log-uniform", "range": [lo, hi],
                       "values": [round(float(m), 6) for m in mass1]})
    if "noise" in kws:
        kn = kws["noise"]
        noisy_bodies = [_VELOCITY_DIM_OF_BODY.index(d) for d in kn["dims"]]
        truths.append({"effect": "stochastic_noise", "dims": sorted(kn["dims"]),
                       "std": "scale * (base + |a_j|), a_j the actuator of the body",
                       "scale": kn["scale"], "base": kn["base"]})
    if "unobserved" in kws:
        ku = kws["unobserved"]
        hidden = np.concatenate([rng[_RNG_STARTS].uniform(-1.0, 1.0, (E, 1)),
                                 rng[_RNG_STARTS].uniform(-0.5, 0.5, (E, 1))], axis=1)
        truths.append({"effect": "unobserved_state", "hidden": ["p3", "v3"],
                       "coupled_to": "body1", "dims": [0, 1], "spring": ku["spring"],
                       "mass": ku["mass"], "decay": ku["decay"]})
    if "drift" in kws:
        kg = kws["drift"]
        gain_scale = kg["gain_start"] + (kg["gain_end"] - kg["gain_start"]) * order
        truths.append({"effect": "time_drift", "over": "episode_order",
                       "parameter": "actuator_gain", "actuators": [0, 1],
                       "start": kg["gain_start"], "end": kg["gain_end"]})
    truth = (truths[0] if len(truths) == 1 else {"effect": "none"} if not truths
             else {"effect": "combined", "effects": truths})

    obs = np.zeros((E, L, 4), np.float32)
    action = np.zeros((E, L, 2), np.float32)
    for t in range(L):
        a, explore = _policy_action(pol, state, t, phase, explore, rng[_RNG_EXPLORE])
        applied = a.astype(np.float64)
        force1 = 0.0
        if "delay" in kws:
            applied = np.where(delayed, queue[:, 0], applied)
            queue = np.concatenate([queue[:, 1:], a[:, None]], axis=1)
        if "unobserved" in kws:
            force1 = -ku["spring"] * (state[:, 0] - hidden[:, 0])
        nxt = twomass_dynamics(state, applied, mass1=mass1, gain_scale=gain_scale,
                               force1=force1)
        if "noise" in kws:
            for d, j in zip(kn["dims"], noisy_bodies, strict=True):
                std = kn["scale"] * (kn["base"] + np.abs(a[:, j]))
                nxt[:, d] += std * erng.standard_normal(E)
        if "unobserved" in kws:
            v3 = ku["decay"] * hidden[:, 1] + TWOMASS["dt"] * ku["spring"] * (
                state[:, 0] - hidden[:, 0]) / ku["mass"]
            hidden = np.stack([hidden[:, 0] + TWOMASS["dt"] * v3, v3], axis=1)
        obs[:, t], action[:, t] = state, a
        state = _f32(nxt)
    next_obs = np.concatenate([obs[:, 1:], state[:, None].astype(np.float32)], axis=1)

    n = E * L
    truncated = np.zeros((E, L), bool)
    truncated[:, -1] = True
    reward = (1.0 - 0.5 * (next_obs[..., 0] ** 2 + next_obs[..., 2] ** 2)
              - 0.05 * np.sum(action ** 2, axis=-1))
    arrays = {
        "obs": obs.reshape(n, 4), "action": action.reshape(n, 2),
        "next_obs": next_obs.reshape(n, 4), "reward": reward.reshape(n).astype(np.float32),
        "done": np.zeros(n, bool), "truncated": truncated.reshape(n),
        "policy_id": np.repeat(episode_policy, L).astype(np.int32),
        "episode_id": np.repeat(np.arange(E), L).astype(np.int32),
        "t": np.tile(np.arange(L), E).astype(np.int32),
    }
    meta = {"task": None, "obs_size": 4, "action_size": 2, "n_policies": P, "gamma": None,
            "episode_length": L, "policy_names": [f"twomass-pd-{i}" for i in range(P)],
            "source": {"generator": "planted.twomass", "planted": truth, "seed": seed,
                       "effect": effect,
                       "effect_kwargs": (_jsonable(kws[effect]) if effect in kws
                                         else {p: _jsonable(k) for p, k in kws.items()}),
                       "system": _jsonable(TWOMASS)}}
    return Dataset.from_arrays(arrays, meta)


# --------------------------------------------------------------------------- policies


def _make_policies(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    """P varied PD policies: each field [P, 2] (one entry per actuator) or [P, 1]."""
    return {
        "target": rng.uniform(-0.6, 0.6, (n, 2)),
        "kp": rng.uniform(0.5, 3.0, (n, 2)),
        "kd": rng.uniform(0.1, 1.5, (n, 2)),
        "cross": rng.uniform(-0.5, 0.5, (n, 2)),  # gain on the other body's position error
        "noise": rng.uniform(0.15, 0.6, (n, 2)),
        "rho": rng.uniform(0.0, 0.85, (n, 1)),  # AR(1) coefficient of the exploration noise
        "amp": rng.uniform(0.0, 0.5, (n, 2)),
        "period": rng.uniform(15.0, 60.0, (n, 2)),  # steps
    }


def _policy_action(pol: dict[str, np.ndarray], state: np.ndarray, t: int, phase: np.ndarray,
                   explore: np.ndarray, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Actions [E, 2] float32 in [-1, 1] of every episode's policy at step t, and the next
    exploration noise state [E, 2]."""
    p, v = state[:, 0::2].astype(np.float64), state[:, 1::2].astype(np.float64)
    err = pol["target"] - p
    rho = pol["rho"]
    explore = rho * explore + np.sqrt(1.0 - rho ** 2) * pol["noise"] * rng.standard_normal(
        explore.shape)
    a = (pol["kp"] * err - pol["kd"] * v + pol["cross"] * err[:, ::-1]
         + pol["amp"] * np.sin(2 * np.pi * t / pol["period"] + phase) + explore)
    return np.clip(a, -1.0, 1.0).astype(np.float32), explore


# --------------------------------------------------------------------------- arguments


def _check_args(effect: Any, kwargs: dict[str, Any], n_episodes: int, episode_length: int,
                n_policies: int) -> dict[str, Any]:
    """Validate every argument; returns the effect's kwargs with defaults filled in."""
    if effect not in EFFECTS:
        raise ValueError(f"effect: expected one of {', '.join(map(repr, EFFECTS))}, "
                         f"got {effect!r}")
    for name, value in (("n_episodes", n_episodes), ("episode_length", episode_length),
                        ("n_policies", n_policies)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name}: expected a positive int, got {value!r}")
    accepted = EFFECTS[effect]
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise ValueError(f"effect {effect!r}: unknown argument(s) {', '.join(unknown)}; "
                         f"accepted: {', '.join(accepted) or 'none'}")
    kw = {**accepted, **kwargs}

    def bad(name: str, expected: str):
        return ValueError(f"effect {effect!r}: {name}: expected {expected}, got {kw[name]!r}")

    def positive(name: str) -> float:
        try:
            value = float(kw[name])
        except (TypeError, ValueError):
            raise bad(name, "a positive number") from None
        if not value > 0 or not math.isfinite(value):
            raise bad(name, "a positive number")
        return value

    def index_set(name: str, allowed: tuple[int, ...]) -> tuple[int, ...]:
        try:
            values = tuple(int(i) for i in np.atleast_1d(kw[name]))
        except (TypeError, ValueError):
            raise bad(name, f"a non-empty set of distinct values in {allowed}") from None
        if not values or len(set(values)) != len(values) or not set(values) <= set(allowed):
            raise bad(name, f"a non-empty set of distinct values in {allowed}")
        return values

    if effect == "delay":
        lag = kw["lag"]
        if not isinstance(lag, (int, np.integer)) or isinstance(lag, bool) or lag < 1:
            raise bad("lag", "an int >= 1 (steps)")
        kw["lag"] = int(lag)
        kw["actuators"] = index_set("actuators", (0, 1))
    elif effect == "episode_param":
        try:
            lo, hi = (float(x) for x in kw["mass_range"])
        except (TypeError, ValueError):
            raise bad("mass_range", "(low, high) with 0 < low < high") from None
        if not 0 < lo < hi < math.inf:
            raise bad("mass_range", "(low, high) with 0 < low < high")
        kw["mass_range"] = (lo, hi)
    elif effect == "noise":
        kw["dims"] = index_set("dims", _VELOCITY_DIM_OF_BODY)
        kw["scale"] = positive("scale")
        base = kw["base"]
        if not isinstance(base, (int, float, np.floating)) or not 0 <= base < math.inf:
            raise bad("base", "a number >= 0")
        kw["base"] = float(base)
    elif effect == "unobserved":
        kw["spring"], kw["mass"] = positive("spring"), positive("mass")
        if not 0 < positive("decay") <= 1:
            raise bad("decay", "a number in (0, 1]")
        kw["decay"] = float(kw["decay"])
    elif effect == "drift":
        kw["gain_start"], kw["gain_end"] = positive("gain_start"), positive("gain_end")
    return kw


def _f32(x: np.ndarray) -> np.ndarray:
    """Round to float32 and back: the recorded state is what the system carries on from."""
    return np.asarray(x, np.float32).astype(np.float64)


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
