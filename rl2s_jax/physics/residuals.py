"""What a physics model gets wrong on measured data: one-step and open-loop k-step errors.

Errors are root mean squares of the residual ``predicted - measured``, both raw (the obs
dim's units) and normalised by the dim's std of ``next_obs - obs`` (``identify.obs_scale``):
by observation dim, by joint (its qpos and qvel dims) and the body it moves, in and out of
contact (any contact with penetration in the measured state, from C MuJoCo), and by policy.
The k-step error rolls the model open loop from an episode's measured state under the logged
(delayed) actions, over windows of ``k`` steps.
"""

from __future__ import annotations

import numpy as np

from rl2s_jax.physics.identify import c_backend, compiled, obs_scale
from rl2s_jax.physics.mjx_model import PhysicsModel, delayed_actions

__all__ = ["physics_errors", "prediction_errors", "predict", "in_contact"]


def predict(pm: PhysicsModel, theta, obs: np.ndarray, action: np.ndarray,
            rows: int = 256, backend: str = "mujoco") -> np.ndarray:
    """The model's next obs [N, O] for obs [N, O], action [N, A]: C MuJoCo (``backend``
    "mujoco") or MJX ("mjx", in padded chunks of ``rows``: one compiled program for any N)."""
    pred, _ = compiled(pm) if backend == "mjx" else c_backend(pm)
    out = []
    for s in range(0, len(obs), rows):
        o, a = obs[s: s + rows], action[s: s + rows]
        pad = rows - len(o)
        o = np.concatenate([o, np.repeat(o[:1], pad, 0)])
        a = np.concatenate([a, np.repeat(a[:1], pad, 0)])
        out.append(np.asarray(pred(np.asarray(theta, np.float64), o, a))[: rows - pad])
    return np.concatenate(out) if out else np.zeros_like(obs)


def in_contact(pm: PhysicsModel, obs: np.ndarray) -> np.ndarray:
    """Whether each measured state [N, O] has a penetrating contact (C MuJoCo) -> bool [N]."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    data = mujoco.MjData(pm.mj)
    out = np.zeros(len(obs), bool)
    for i, o in enumerate(obs):
        q, v = pm.obs_to_state_np(np.asarray(o, np.float64))
        data.qpos[:], data.qvel[:] = np.asarray(q), np.asarray(v)
        mujoco.mj_forward(pm.mj, data)
        out[i] = any(data.contact[c].dist < 0 for c in range(data.ncon))
    return out


def _rmse(x: np.ndarray, axis=0):
    return np.sqrt(np.mean(np.square(x), axis=axis)) if len(x) else np.full(x.shape[1:], np.nan)


def _joint_dims(pm: PhysicsModel) -> list[dict]:
    """Each joint with its obs dims and body: [{"joint", "body", "dims"}]."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    mj, out = pm.mj, []
    widths = {0: (7, 6), 1: (4, 3), 2: (1, 1), 3: (1, 1)}  # free, ball, slide, hinge
    for j in range(mj.njnt):
        nq, nv = widths[int(mj.jnt_type[j])]
        qa, va = int(mj.jnt_qposadr[j]), int(mj.jnt_dofadr[j])
        out.append({"joint": mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}",
                    "body": mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_BODY,
                                              int(mj.jnt_bodyid[j])) or "",
                    "dims": list(range(qa, qa + nq)) + [mj.nq + d for d in range(va, va + nv)]})
    return out


def _kstep(step, ds, action, k: int, max_windows: int, scale, with_rows: bool = False
           ) -> list[float]:
    """Normalised RMSE after 1..k open-loop steps of ``step(obs [N, O], action [N, A]) ->
    next_obs [N, O]`` (``with_rows``: ``step(obs, action, rows)``, rows [N] the dataset rows
    whose logged actions are fed), over up to max_windows windows (the same for any ``step``)."""
    starts = [i for i in range(len(ds.obs) - k)
              if ds.episode_id[i] == ds.episode_id[i + k - 1] and ds.t[i] % k == 0]
    if not starts:
        return []
    starts = np.array(starts)[np.linspace(0, len(starts) - 1, min(max_windows, len(starts)))
                              .astype(int)]
    obs = np.asarray(ds.obs[starts])
    out = []
    for j in range(k):
        rows = (starts + j,) if with_rows else ()
        obs = np.asarray(step(obs, action[starts + j], *rows))
        out.append(float(_rmse((obs - ds.next_obs[starts + j]) / scale, axis=None)))
    return out


def _error_rows(n: int, max_rows: int, seed: int) -> np.ndarray:
    """The rows [<= max_rows] the one-step error is measured on (the same for any model)."""
    rows = np.arange(n)
    if n > max_rows:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_rows, replace=False))
    return rows


def prediction_errors(step, ds, *, action=None, k: int = 10, max_rows: int = 2048,
                      max_windows: int = 64, seed: int = 0, with_rows: bool = False) -> dict:
    """Any one-step model's errors on a Dataset, on the rows and windows ``physics_errors``
    uses: ``step(obs [N, O], action [N, A]) -> next_obs [N, O]`` (a learned simulator's mean,
    a physics model) fed ``action`` [N, A] (default the logged actions); ``with_rows``:
    ``step(obs, action, rows)`` with rows [N] the dataset rows whose actions are fed (a model
    that reads the episode's logged past there, e.g. its past actions).
    -> {"one_step": normalised RMSE, "kstep": [k] normalised RMSEs}."""
    action = np.asarray(ds.action if action is None else action)
    if action.shape != np.shape(ds.action):
        raise ValueError(f"action: expected shape {np.shape(ds.action)} (one per row), got "
                         f"{action.shape}")
    rows = _error_rows(len(ds.obs), max_rows, seed)
    scale = obs_scale(ds)
    extra = (rows,) if with_rows else ()
    z = (np.asarray(step(np.asarray(ds.obs[rows]), action[rows], *extra))
         - ds.next_obs[rows]) / scale
    return {"one_step": float(_rmse(z, axis=None)),
            "kstep": _kstep(step, ds, action, k, max_windows, scale, with_rows)}


def physics_errors(pm: PhysicsModel, ds, theta=None, delays=None, *, k: int = 10,
                   max_rows: int = 2048, max_windows: int = 64, seed: int = 0) -> dict:
    """Errors of ``pm`` at ``theta`` [K] (default nominal) with per-actuator ``delays`` on a
    Dataset (module docstring): {"one_step": {"by_dim", "by_joint", "contact",
    "by_policy", "rmse"}, "kstep": [k]} (normalised RMSEs; by_dim also raw)."""
    theta = np.zeros(len(pm.candidates)) if theta is None else np.asarray(theta)
    delays = np.zeros(pm.action_size, int) if delays is None else np.asarray(delays)
    action = delayed_actions(np.asarray(ds.action), np.asarray(ds.episode_id),
                             np.asarray(ds.t), delays)
    rows = _error_rows(len(ds.obs), max_rows, seed)
    scale = obs_scale(ds)
    resid = predict(pm, theta, np.asarray(ds.obs[rows]), action[rows]) - ds.next_obs[rows]
    z = resid / scale
    touch = in_contact(pm, np.asarray(ds.obs[rows]))
    pol = np.asarray(ds.policy_id[rows])
    names = ds.meta.get("policy_names") or [str(p) for p in range(ds.n_policies)]
    return {
        "one_step": {
            "rmse": float(_rmse(z, axis=None)),
            "by_dim": [{"dim": d, "rmse": float(r), "rmse_normalised": float(n)}
                       for d, (r, n) in enumerate(zip(_rmse(resid), _rmse(z), strict=True))],
            "by_joint": [{"joint": j["joint"], "body": j["body"],
                          "rmse_normalised": float(_rmse(z[:, j["dims"]], axis=None))}
                         for j in _joint_dims(pm)],
            "contact": {"share": float(touch.mean()),
                        "in": float(_rmse(z[touch], axis=None)) if touch.any() else None,
                        "out": float(_rmse(z[~touch], axis=None)) if (~touch).any() else None},
            "by_policy": [{"policy": names[p], "rmse_normalised":
                           float(_rmse(z[pol == p], axis=None))} for p in np.unique(pol)],
        },
        "kstep": _kstep(lambda o, a: predict(pm, theta, o, a), ds, action, k, max_windows,
                        scale),
    }
