"""Which physical quantities explain the physics model's error, and their values (MJX gradients).

Residuals are one-step: ``(step(theta, obs, a_delayed) - next_obs) / scale`` per obs dim, with
``scale`` the dim's standard deviation of ``next_obs - obs`` in the data. The data's episodes
are split in two halves (``fit`` and ``test``, alternately within each policy), each
subsampled to ``FitConfig.rows`` transitions (padded to that fixed size, so one compiled
step and one compiled Jacobian serve every dataset of a model).

Selection, forward stepwise (:func:`identify`). At the current fit:

1. screen every candidate: a continuous one by the linearised drop of the fit half's sum of
   squares were it added (its Jacobian column made orthogonal to the chosen ones'); an action
   delay (per actuator, 1..``max_delay`` steps) by the exact drop with the actions shifted;
   a contact margin also by the exact drop at each of ``MARGIN_TRIALS`` above its value (a
   larger margin switches on contacts the model has none of: its column is zero there);
   changes of structure, with the C backend, by their exact drop too: another integrator,
   and each group of like geoms (``mjx_model.collision_groups``: same type and size) with
   its contacts switched on or off (which parts of the robot touch the floor), alone and as
   a swap of a colliding group for a non-colliding one on the same bodies;
2. refine the best (Levenberg-Marquardt on the chosen set plus it, ``jax.jacfwd`` Jacobians;
   a margin from its best trial value);
3. keep it only if it is significant on the *test* half: the per-episode mean squared error
   drops, in a one-sided paired t-test over test episodes (episodes, not transitions, are
   the independent units: one episode's residuals are correlated in time), at level
   ``alpha``, and by at least ``min_gain`` of the current test error. Otherwise stop.

Intervals: a linearised bootstrap over fit episodes at the optimum (resample episodes, one
Gauss-Newton step from the optimum with their rows), percentile ``[2.5, 97.5]``, mapped to the
value scale; episode resampling keeps the time correlation that a Wald interval
``sigma^2 (J^T J)^-1`` (also computed, ``wald``) ignores. A delay's interval is its value.

Backends (``FitConfig.backend``): "mujoco" (default) steps C MuJoCo in float64 with
forward-difference Jacobians (:func:`c_backend`); "mjx" steps MJX with ``jax.jacfwd``
(:func:`compiled`), whose batched Jacobian compiled in 92 s once on the 2-core CPU and then
stalled in later runs (docs/DIAGNOSIS.md, "Physics"). :func:`fit_sysid` fits chosen
quantities with ``mujoco.sysid.optimize`` on the same residuals, for timing side by side.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np
from scipy import stats

from rl2s_jax.physics.mjx_model import (
    PhysicsModel,
    actuator_names,
    apply_to_mj,
    collision_groups,
    delayed_actions,
    integrator_name,
    integrator_value,
    set_integrator,
    switch_collisions,
)

__all__ = ["FitConfig", "identify", "fit_sysid", "compiled", "c_backend", "split_rows", "Rows",
           "format_value", "format_quantity"]


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """rows: transitions per half (fixed: one compile); max_params: most quantities named;
    lm_iterations: refinement steps per candidate; alpha, min_gain: the significance rule
    (module docstring); max_delay: action delays screened, in control steps; bootstrap:
    resamples for the intervals; seed: the split and subsample; integrators: the integrators
    screened in place of the model's, and collisions: whether each group of like geoms
    (``mjx_model.collision_groups``) is screened with its contacts switched (discrete
    candidates, C MuJoCo backend only)."""

    rows: int = 256  # a multiple of JAC_ROWS
    max_params: int = 5  # a change of parts needs two: capsules colliding, spheres not
    lm_iterations: int = 4
    alpha: float = 0.01
    min_gain: float = 0.1
    max_delay: int = 3
    bootstrap: int = 200
    seed: int = 0
    backend: str = "mujoco"
    integrators: tuple[str, ...] = ("Euler", "RK4", "implicitfast")
    collisions: bool = True


@dataclasses.dataclass(frozen=True)
class Rows:
    """One half's transitions, padded to ``FitConfig.rows``: obs [R, O], actions [R, A] per
    delay vector via ``actions(delays)``, next_obs [R, O], episode [R] (-1 = padding)."""

    obs: np.ndarray
    next_obs: np.ndarray
    episode: np.ndarray
    index: np.ndarray  # row in the dataset, for the delayed actions
    action_all: np.ndarray
    episode_all: np.ndarray
    t_all: np.ndarray

    def actions(self, delays) -> np.ndarray:
        return delayed_actions(self.action_all, self.episode_all, self.t_all, delays)[self.index]

    @property
    def weight(self) -> np.ndarray:
        return (self.episode >= 0).astype(np.float32)


_COMPILED: dict[int, tuple] = {}
# The Jacobian runs on chunks of this many rows: on the 2-core CPU a [64]-row Jacobian compiled
# in ~90 s while a [256]-row one had not finished after 7 minutes.
JAC_ROWS = 64


def c_backend(pm: PhysicsModel, fd_step: float = 1e-5, integrator: str | None = None,
              collisions: dict | None = None):
    """(pred, pred_jac) as :func:`compiled`'s, in C MuJoCo (float64): each row stepped from its
    measured state, the Jacobian by forward differences over theta (no compilation);
    ``integrator`` in place of the model's, geoms' contacts switched by ``collisions``."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    mj = switch_collisions(pm.mj, pm.xml_path, collisions)
    if integrator is not None:
        set_integrator(mj, integrator)
    data = mujoco.MjData(mj)
    nominal = {n: np.array(getattr(pm.mj, n)) for n in
               ("body_mass", "body_inertia", "dof_damping", "dof_armature", "geom_friction",
                "actuator_gear", "geom_margin")}

    def set_theta(theta):
        for n, v in nominal.items():
            getattr(mj, n)[:] = v
        apply_to_mj(mj, pm.candidates, theta)

    def pred(theta, obs, action):
        set_theta(theta)
        bias = np.zeros(pm.obs_size)
        for c, th in zip(pm.candidates, np.asarray(theta, np.float64), strict=True):
            if c.name == "obs_bias":
                bias[c.index] = th
        out = np.empty(obs.shape, np.float64)
        for i in range(len(obs)):
            mujoco.mj_resetData(mj, data)
            q, v = pm.obs_to_state_np(np.asarray(obs[i], np.float64) - bias)
            data.qpos[:], data.qvel[:], data.ctrl[:] = q, v, action[i]
            mujoco.mj_step(mj, data, nstep=pm.n_frames)
            out[i] = pm.state_to_obs_np(data.qpos, data.qvel) + bias
        return out

    def pred_jac(theta, obs, action):
        theta = np.asarray(theta, np.float64)
        base = pred(theta, obs, action)
        jac = np.empty(base.shape + (len(theta),))
        for k in range(len(theta)):
            t = theta.copy()
            t[k] += fd_step
            jac[..., k] = (pred(t, obs, action) - base) / fd_step
        return base, jac

    return pred, pred_jac


def compiled(pm: PhysicsModel):
    """(pred, pred_and_jac) for ``pm``, compiled once per model:
    pred(theta [K], obs [R, O], action [R, A]) -> [R, O];
    pred_and_jac(...) -> ([R, O], d pred / d theta [R, O, K])."""
    if id(pm) not in _COMPILED:
        pred = jax.jit(jax.vmap(pm.step, in_axes=(None, 0, 0)))
        jac = jax.jit(jax.vmap(jax.jacfwd(pm.step), in_axes=(None, 0, 0)))

        def pred_jac(theta, obs, action):  # the Jacobian in chunks of JAC_ROWS rows
            js = [jac(theta, obs[s: s + JAC_ROWS], action[s: s + JAC_ROWS])
                  for s in range(0, len(obs), JAC_ROWS)]
            return pred(theta, obs, action), np.concatenate([np.asarray(j) for j in js])

        _COMPILED[id(pm)] = (pm, pred, pred_jac)
    return _COMPILED[id(pm)][1:]


def split_rows(ds, rows: int, seed: int) -> tuple[Rows, Rows]:
    """The fit and test halves of a Dataset (module docstring)."""
    rng = np.random.default_rng(seed)
    episodes = np.unique(ds.episode_id)
    pol = np.array([ds.policy_id[np.argmax(ds.episode_id == e)] for e in episodes])
    test_eps = np.concatenate([episodes[pol == p][1::2] for p in np.unique(pol)])
    if len(test_eps) < 3:  # few episodes per policy (e.g. one each): every second overall
        test_eps = episodes[np.lexsort((episodes, pol))][1::2]
    if len(test_eps) < 3 or len(episodes) - len(test_eps) < 1:
        raise ValueError(f"data: expected at least 6 episodes (every second one is tested "
                         f"on), got {len(episodes)}")
    is_test = np.isin(ds.episode_id, test_eps)
    halves = []
    for mask in (~is_test, is_test):
        idx = np.flatnonzero(mask)
        idx = np.sort(rng.choice(idx, rows, replace=False)) if len(idx) > rows else idx
        pad = rows - len(idx)
        episode = np.concatenate([ds.episode_id[idx], -np.ones(pad, int)])
        idx = np.concatenate([idx, np.full(pad, idx[0])])
        halves.append(Rows(np.asarray(ds.obs[idx]), np.asarray(ds.next_obs[idx]), episode, idx,
                           np.asarray(ds.action), np.asarray(ds.episode_id),
                           np.asarray(ds.t)))
    return halves[0], halves[1]


def obs_scale(ds) -> np.ndarray:
    """Per-dim std of next_obs - obs [O], floored at 1e-3 of its mean."""
    s = np.std(np.asarray(ds.next_obs, np.float64) - np.asarray(ds.obs, np.float64), axis=0)
    return np.maximum(s, 1e-3 * s.mean() + 1e-12)


class _Fit:
    """Residuals of one dataset half under a model, theta and delays."""

    def __init__(self, pm, rows: Rows, scale, backend: str = "mujoco",
                 integrator: str | None = None, collisions: dict | None = None):
        self.pred, self.pred_jac = (compiled(pm) if backend == "mjx" else
                                    c_backend(pm, integrator=integrator, collisions=collisions))
        self.rows, self.scale = rows, scale
        self.w = rows.weight[:, None]

    def residual(self, theta, delays) -> np.ndarray:
        """Weighted normalised residuals [R, O] (0 on padding)."""
        p = np.asarray(self.pred(np.asarray(theta, np.float64), self.rows.obs,
                                 self.rows.actions(delays)))
        return (p - self.rows.next_obs) / self.scale * self.w

    def residual_jac(self, theta, delays) -> tuple[np.ndarray, np.ndarray]:
        """([R * O] residuals, [R * O, K] their Jacobian), float64."""
        p, j = self.pred_jac(np.asarray(theta, np.float64), self.rows.obs,
                             self.rows.actions(delays))
        r = (np.asarray(p, np.float64) - self.rows.next_obs) / self.scale * self.w
        jac = np.asarray(j, np.float64) / self.scale[None, :, None] * self.w[:, :, None]
        return r.reshape(-1), jac.reshape(-1, jac.shape[-1])

    def episode_errors(self, theta, delays) -> dict[int, float]:
        """Mean squared normalised residual per episode of the half."""
        se = np.sum(self.residual(theta, delays) ** 2, axis=1)
        return {int(e): float(se[self.rows.episode == e].mean())
                for e in np.unique(self.rows.episode) if e >= 0}


def _refine(fit: _Fit, theta, active, delays, iterations) -> np.ndarray:
    """Levenberg-Marquardt over theta[active] on the fit half."""
    theta = np.array(theta, np.float64)
    if not active:
        return theta
    lam = 1e-3
    for _ in range(iterations):
        r, jac = fit.residual_jac(theta, delays)
        ja = jac[:, active]
        jtj, g = ja.T @ ja, ja.T @ r
        cost = r @ r
        for _ in range(6):
            step = -np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-9), g)
            trial = theta.copy()
            trial[active] += np.clip(step, -1.0, 1.0)
            if np.sum(fit.residual(trial, delays) ** 2) < cost:
                theta, lam = trial, lam / 10
                break
            lam *= 10
        else:
            break
    return theta


# Contact margins tried by their exact drop (m): a margin above the nominal one switches on
# contacts that the nominal model has none of, where its Jacobian column is zero
MARGIN_TRIALS = (0.002, 0.005, 0.01, 0.02, 0.05)


def _screen(fit: _Fit, theta, active, delays, max_delay, others: dict | None = None,
            candidates=()):
    """The best next candidate: ("param", k, gain, start), ("delay", (actuator, d), gain,
    None) or a structural one (kind, what, gain, None); ``others``: {(kind, what): the fit
    half under that change of structure} (``_Structures.trials``), tried by their exact drop;
    ``candidates`` (the model's): each geom_margin also at MARGIN_TRIALS, by its exact drop,
    ``start`` then the theta its refinement starts from (else None)."""
    r, jac = fit.residual_jac(theta, delays)
    ja = jac[:, active]
    if active:
        jac = jac - ja @ np.linalg.lstsq(ja, jac, rcond=None)[0]
    norm = np.sum(jac**2, axis=0)
    usable = norm > 1e-12 * max(norm.max(), 1e-30)
    gain = np.where(usable, (r @ jac) ** 2 / np.where(usable, norm, 1.0), 0.0)
    gain[active] = 0.0
    best = ("param", int(np.argmax(gain)), float(gain.max()), None)
    cost = r @ r
    for k, c in enumerate(candidates):
        if c.name != "geom_margin" or k in active:
            continue
        for value in MARGIN_TRIALS:
            if value <= c.value(theta[k]):
                continue
            trial = np.array(theta, np.float64)
            trial[k] = c.to_theta(value)
            drop = cost - np.sum(fit.residual(trial, delays) ** 2)
            if drop > best[2]:
                best = ("param", k, float(drop), trial)
    for a in np.flatnonzero(np.asarray(delays) == 0):
        for d in range(1, max_delay + 1):
            trial = np.array(delays)
            trial[a] = d
            drop = cost - np.sum(fit.residual(theta, trial) ** 2)
            if drop > best[2]:
                best = ("delay", (int(a), d), float(drop), None)
    for (kind, what), other in (others or {}).items():  # the exact drop, as a delay's
        drop = cost - np.sum(other.residual(theta, delays) ** 2)
        if drop > best[2]:
            best = (kind, what, float(drop), None)
    return best


def _paired_test(before: dict, after: dict) -> tuple[float, float, float]:
    """(p-value of a one-sided paired t-test that after < before, mean drop, mean before)."""
    eps = sorted(before)
    drop = np.array([before[e] - after[e] for e in eps])
    base = float(np.mean([before[e] for e in eps]))
    if np.all(drop == drop[0]):
        return (0.0 if drop[0] > 0 else 1.0), float(drop.mean()), base
    return float(stats.ttest_1samp(drop, 0.0, alternative="greater").pvalue), \
        float(drop.mean()), base


def _drop_episodes(before: dict, after: dict) -> list[int]:
    """[the fewest test episodes that hold 90% of the error's drop, test episodes]: a change
    that only a rare contact shows drops the error in few, and the paired t-test over
    episodes cannot then pass however large the drop (one episode of n gives t near 1)."""
    drops = np.sort([before[e] - after[e] for e in before])[::-1]
    gain = drops[drops > 0]
    if gain.sum() <= 0:
        return [0, len(drops)]
    return [int(np.searchsorted(np.cumsum(gain), 0.9 * gain.sum()) + 1), len(drops)]


def _bootstrap(fit: _Fit, theta, active, delays, n, seed) -> np.ndarray:
    """Linearised episode bootstrap of theta[active] -> [n, len(active)]."""
    if not active or n < 1:
        return np.zeros((0, len(active)))
    r, jac = fit.residual_jac(theta, delays)
    width = fit.rows.obs.shape[1]
    eps = fit.rows.episode
    ids = np.unique(eps[eps >= 0])
    ja = jac[:, active].reshape(len(eps), width, len(active))
    rr = r.reshape(len(eps), width)
    jtj = {e: np.einsum("roa,rob->ab", ja[eps == e], ja[eps == e]) for e in ids}
    jtr = {e: np.einsum("roa,ro->a", ja[eps == e], rr[eps == e]) for e in ids}
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        pick = rng.choice(ids, len(ids))
        a = sum(jtj[e] for e in pick)
        b = sum(jtr[e] for e in pick)
        out.append(theta[active] - np.linalg.lstsq(a, b, rcond=None)[0])
    return np.array(out)


def _wald(fit: _Fit, theta, active, delays) -> np.ndarray:
    """Wald standard errors of theta[active] from sigma^2 (J^T J)^-1 (rows independent)."""
    r, jac = fit.residual_jac(theta, delays)
    ja = jac[:, active]
    n = int(fit.rows.weight.sum()) * fit.rows.obs.shape[1]
    sigma2 = r @ r / max(n - len(active), 1)
    return np.sqrt(np.diag(sigma2 * np.linalg.pinv(ja.T @ ja)))


class _Structures:
    """The fit and test halves under each structure of the model: its integrator (one of
    ``cfg.integrators`` in place of the model's) and the collision groups
    (``mjx_model.collision_groups``) whose contacts are switched. Changes of structure are
    screened with the C backend only (MJX's compiled step keeps the model's)."""

    def __init__(self, pm: PhysicsModel, fit_rows: Rows, test_rows: Rows, scale,
                 cfg: FitConfig):
        self.pm, self.rows, self.scale, self.cfg = pm, (fit_rows, test_rows), scale, cfg
        self.nominal = integrator_name(pm.mj)
        c_only = cfg.backend == "mujoco"
        self.integrators = [n for n in (cfg.integrators if c_only else ()) if n != self.nominal]
        for name in self.integrators:  # a bad name: its ValueError before any stepping
            integrator_value(name)
        self.groups = collision_groups(pm.mj) if c_only and cfg.collisions else []
        self._halves: dict[tuple, tuple[_Fit, _Fit]] = {}

    def collisions(self, switched) -> dict:
        """{geom name: collides} of the switched groups."""
        return {n: not self.groups[g]["collides"] for g in switched
                for n in self.groups[g]["names"]}

    def halves(self, integrator: str, switched: tuple = ()) -> tuple[_Fit, _Fit]:
        key = (integrator, tuple(sorted(switched)))
        if key not in self._halves:
            nominal = key == (self.nominal, ())
            kw = dict(backend=self.cfg.backend if nominal else "mujoco",
                      integrator=None if integrator == self.nominal else integrator,
                      collisions=self.collisions(switched))
            self._halves[key] = tuple(_Fit(self.pm, r, self.scale, **kw) for r in self.rows)
        return self._halves[key]

    def trials(self, integrator: str, switched: tuple) -> dict:
        """{(kind, what): fit half} of each change of structure from here: another
        integrator while the model's is kept; each collision group not yet switched, alone
        ((g,)) and, for a non-colliding group on the bodies of a colliding one, as the two
        swapped ((on, off): the bodies touch through other geoms, which one switch alone
        cannot show where the geoms overlap)."""
        out = {}
        if integrator == self.nominal:
            out.update({("integrator", n): self.halves(n, switched)[0]
                        for n in self.integrators})
        free = [g for g in range(len(self.groups)) if g not in switched]
        swaps = [(a, b) for a in free for b in free
                 if not self.groups[a]["collides"] and self.groups[b]["collides"]
                 and set(self.groups[b]["bodies"]) <= set(self.groups[a]["bodies"])]
        out.update({("collision", w): self.halves(integrator, switched + w)[0]
                    for w in [(g,) for g in free] + swaps})
        return out


def identify(pm: PhysicsModel, ds, cfg: FitConfig = FitConfig()) -> dict:
    """Forward stepwise identification (module docstring) -> the report's ``physics`` object
    minus ``command``: {"top_cause", "parameters", "unexplained", "error_nominal",
    "error_calibrated", "seconds", "delays", "theta", "integrator", "collisions", "scale"}
    (errors: mean squared normalised one-step residual over test episodes; "integrator": the
    model's, or the one chosen in its place; "collisions": {geom name: collides} of the
    switched geoms)."""
    if ds.obs_size != pm.obs_size or ds.action_size != pm.action_size:
        raise ValueError(f"data: expected obs_size {pm.obs_size} and action_size "
                         f"{pm.action_size} (the physics model's), got {ds.obs_size}, "
                         f"{ds.action_size}")
    if cfg.backend not in ("mujoco", "mjx"):
        raise ValueError(f"backend: expected 'mujoco' or 'mjx', got {cfg.backend!r}")
    start = time.perf_counter()
    scale = obs_scale(ds)
    structures = _Structures(pm, *split_rows(ds, cfg.rows, cfg.seed), scale, cfg)
    integrator, switched = structures.nominal, ()
    fit, test = structures.halves(integrator)
    theta, delays, active = np.zeros(len(pm.candidates)), np.zeros(pm.action_size, int), []
    screened = []
    nominal_test = current = test.episode_errors(theta, delays)
    for _ in range(cfg.max_params):
        kind, what, gain, from_theta = _screen(fit, theta, active, delays, cfg.max_delay,
                                               structures.trials(integrator, switched),
                                               pm.candidates)
        if gain <= 0:
            break
        t_delays, t_active, t_integrator, t_switched = delays.copy(), list(active), \
            integrator, switched
        if kind == "param":
            t_active.append(what)
        elif kind == "delay":
            t_delays[what[0]] = what[1]
        elif kind == "integrator":
            t_integrator = what
        else:
            t_switched = switched + what
        t_fit, t_test = structures.halves(t_integrator, t_switched)
        t_theta = _refine(t_fit, theta if from_theta is None else from_theta, t_active,
                          t_delays, cfg.lm_iterations)
        after = t_test.episode_errors(t_theta, t_delays)
        p, drop, base = _paired_test(current, after)
        significant = bool(p < cfg.alpha and drop >= cfg.min_gain * base)
        screened.append({"kind": kind, "what": what, "theta": t_theta, "p_value": p,
                         "gain": drop / max(base, 1e-30), "significant": significant,
                         "drop_episodes": _drop_episodes(current, after),
                         "groups": [structures.groups[g] for g in what]
                         if kind == "collision" else None})
        if not significant:
            break
        theta, delays, active, current = t_theta, t_delays, t_active, after
        fit, test, integrator, switched = t_fit, t_test, t_integrator, t_switched
    boot = _bootstrap(fit, theta, active, delays, cfg.bootstrap, cfg.seed)
    wald = _wald(fit, theta, active, delays) if active else np.zeros(0)
    params = [_describe(pm, e, active, theta, boot, wald) for e in screened]
    tot = lambda errs: float(np.mean(list(errs.values())))  # noqa: E731
    top = next((p for p in params if p["significant"]), None)
    return {"top_cause": None if top is None else {
                k: top[k] for k in ("name", "element", "nominal", "value", "interval")},
            "parameters": params, "unexplained": tot(current) / max(tot(nominal_test), 1e-30),
            "error_nominal": tot(nominal_test), "error_calibrated": tot(current),
            "seconds": time.perf_counter() - start, "delays": delays.tolist(),
            "theta": theta.tolist(), "integrator": integrator,
            "collisions": structures.collisions(switched), "scale": scale.tolist()}


def format_value(x) -> str:
    """A reported quantity's value as printed: a number to 4 significant digits, a name (an
    integrator's) as it is."""
    return x if isinstance(x, str) else f"{x:.4g}"


def format_quantity(p: dict, interval: bool = True) -> str:
    """One reported quantity ({"name", "element", "nominal", "value", "interval"?}) as
    "name[element] nominal -> value [lo, hi]" (the interval left out where ``interval`` is
    false)."""
    ival = p.get("interval") if interval else None
    ival = f" [{format_value(ival[0])}, {format_value(ival[1])}]" if ival else ""
    return (f"{p['name']}[{p['element']}] {format_value(p['nominal'])} -> "
            f"{format_value(p['value'])}{ival}")


def _describe(pm, entry, active, theta, boot, wald) -> dict:
    """One screened quantity in the report's form."""
    base = {"p_value": entry["p_value"], "gain": entry["gain"],
            "significant": entry["significant"], "drop_episodes": entry["drop_episodes"]}
    if entry["kind"] == "delay":
        a, d = entry["what"]
        return {"name": "action_delay", "element": actuator_names(pm.mj)[a], "nominal": 0,
                "value": d, "interval": [d, d], **base}
    if entry["kind"] == "integrator":  # a choice among names: no interval
        return {"name": "integrator", "element": "opt", "nominal": integrator_name(pm.mj),
                "value": entry["what"], "interval": None, "wald": None, **base}
    if entry["kind"] == "collision":  # groups' contacts on or off: no interval
        groups = entry["groups"]
        yes_no = lambda on: "; ".join("yes" if g["collides"] == on else "no"  # noqa: E731
                                      for g in groups)
        return {"name": "geom_collides",
                "element": "; ".join(", ".join(g["names"]) for g in groups),
                "nominal": yes_no(True), "value": yes_no(False), "interval": None,
                "wald": None, **base}
    k = entry["what"]
    c = pm.candidates[k]
    th = theta[k] if entry["significant"] else entry["theta"][k]
    if entry["significant"] and k in active and len(boot):
        col = active.index(k)
        lo, hi = np.percentile(boot[:, col], [2.5, 97.5])
        ival = sorted([c.value(lo), c.value(hi)])
        wald_ival = sorted([c.value(th - 1.96 * wald[col]), c.value(th + 1.96 * wald[col])])
    else:
        ival, wald_ival = None, None
    return {"name": c.name, "element": c.element, "nominal": c.nominal, "value": c.value(th),
            "interval": ival, "wald": wald_ival, **base}


def fit_sysid(pm: PhysicsModel, ds, chosen: list[tuple[str, str]], delays=None,
              cfg: FitConfig = FitConfig()) -> dict:
    """The same quantities fitted with ``mujoco.sysid.optimize`` (scipy least squares,
    finite differences over the same C-MuJoCo one-step residuals of the same fit half), for
    timing against :func:`identify`. chosen: [(name, element)] -> {"values": {label: value},
    "theta" [K], "seconds"}."""
    from mujoco import sysid  # local: the optional mujoco[sysid] extra, only needed here

    if not hasattr(sysid, "optimize"):  # mujoco.sysid imports without its extra, empty
        raise ImportError("fit_sysid needs MuJoCo's system identification extra: "
                          "pip install 'mujoco[sysid]' (or this package's [sysid] extra)")

    fit_rows, _ = split_rows(ds, cfg.rows, cfg.seed)
    fit = _Fit(pm, fit_rows, obs_scale(ds), "mujoco")
    idx = [pm.index(n, e) for n, e in chosen]
    delays = np.zeros(pm.action_size, int) if delays is None else np.asarray(delays)
    params = sysid.ParameterDict()
    for k in idx:
        params.add(sysid.Parameter(pm.candidates[k].label, 0.0, -3.0, 3.0))

    def residual_fn(x, _params):
        theta = np.zeros(len(pm.candidates))
        theta[idx] = x
        return [fit.residual(theta, delays).reshape(-1)], None, None

    start = time.perf_counter()
    opt, _ = sysid.optimize(params, residual_fn, optimizer="scipy", verbose=False)
    theta = np.zeros(len(pm.candidates))
    theta[idx] = opt.as_vector()
    return {"values": {pm.candidates[k].label: pm.candidates[k].value(theta[k]) for k in idx},
            "theta": theta.tolist(), "seconds": time.perf_counter() - start}
