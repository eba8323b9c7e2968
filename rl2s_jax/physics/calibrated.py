"""The calibrated physics as a simulator (issue 62, item 3): policies' values in a physics model
with identified quantities ``theta`` [K] and per-actuator action ``delays`` [A].

Two equivalent paths:

- JAX (:func:`physics_dynamics`, :func:`physics_values`): ``dynamics(obs, action, key, hist)
  -> next_obs`` through ``PhysicsModel.step`` (MJX), rolled by the project's own
  ``model.simulator.simulated_returns``. Delays are carried in the rollout's ``History``
  (``action_history = max(delays)``): actuator ``j`` gets the action ``delays[j]`` steps back
  in the episode, 0 before its start (as the C-MuJoCo collector plants it).
- C MuJoCo (:func:`c_values`), for CPU measurements (an MJX step compiles in 10-15 s on a
  2-core CPU and runs slowly): the C model with ``theta`` applied (:func:`calibrated_mj`),
  stepped in float64 with the rollout's exact key stream (start states, policy draws) and the
  task's reward_fn / done_fn, so on a short horizon its values equal the JAX path's up to
  float32 round-off. With a planted C model (``measured.plant``) it gives the true values.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.model.history import empty_history
from rl2s_jax.model.simulator import simulated_returns, start_values
from rl2s_jax.physics.mjx_model import PhysicsModel, apply_to_mj
from rl2s_jax.policy.policy import sample_action

__all__ = ["physics_dynamics", "physics_values", "calibrated_mj", "obs_bias_of", "c_values"]


def _theta_delays(pm: PhysicsModel, theta, delays) -> tuple[np.ndarray, np.ndarray]:
    theta = np.zeros(len(pm.candidates)) if theta is None else np.asarray(theta, np.float64)
    delays = np.zeros(pm.action_size, int) if delays is None else np.asarray(delays)
    if theta.shape != (len(pm.candidates),):
        raise ValueError(f"theta: expected shape ({len(pm.candidates)},) (one value per "
                         f"candidate quantity), got {theta.shape}")
    if (delays.shape != (pm.action_size,) or (delays < 0).any()
            or not np.all(delays == np.round(delays))):
        raise ValueError(f"delays: expected {pm.action_size} non-negative ints, got {delays}")
    return theta, delays.astype(int)


def physics_dynamics(pm: PhysicsModel, theta=None, delays=None
                     ) -> tuple[Callable, Callable | None]:
    """The physics at ``theta`` [K] (None: nominal) with ``delays`` [A] as the rollouts'
    ``Dynamics`` -> (dynamics, new_history): ``dynamics(obs [..., O], action [..., A], key)``
    when no delay (new_history None), else ``dynamics(obs, action, key, hist)`` with
    ``new_history(batch_shape)`` giving the episodes' empty past of actions."""
    theta, delays = _theta_delays(pm, theta, delays)
    th = jnp.asarray(theta, jnp.float32)
    flat = jax.vmap(lambda o, a: pm.step(th, o, a))

    def physics(obs, action):
        lead = obs.shape[:-1]
        out = flat(obs.reshape(-1, obs.shape[-1]), action.reshape(-1, action.shape[-1]))
        return out.reshape(lead + (obs.shape[-1],))

    depth = int(delays.max())
    if depth == 0:
        return (lambda obs, action, key: physics(obs, action)), None
    d = jnp.asarray(delays)

    def dynamics(obs, action, key, hist):
        # past_act[..., i, :] is the action i + 1 steps back; column j takes delays[j] back
        past = jnp.where(hist.past_act_valid[..., None], hist.past_act, 0.0)
        stacked = jnp.concatenate([action[..., None, :], past], -2)  # [..., depth + 1, A]
        late = jnp.take_along_axis(stacked, jnp.broadcast_to(d, action.shape)[..., None, :],
                                   -2)[..., 0, :]
        return physics(obs, late)

    def new_history(batch_shape):
        return empty_history(tuple(batch_shape), pm.obs_size, pm.action_size, obs_history=0,
                             action_history=depth)

    return dynamics, new_history


def physics_values(pm: PhysicsModel, theta, delays, policy_params, task, start_pool,
                   key: jax.Array, *, n_episodes: int, horizon: int, gamma: float,
                   policy_fn: Callable | None = None) -> tuple[jax.Array, jax.Array]:
    """Each policy's discounted value in the physics at (theta, delays) under ``task``'s
    reward_fn / done_fn, by ``simulated_returns`` (its start draws, policy draws, ending
    rule). policy_params [P, ...]; start_pool [S, O]. -> (values [P], mean lengths [P])."""
    dynamics, new_history = physics_dynamics(pm, theta, delays)
    ret, length = simulated_returns(policy_params, dynamics, task.reward_fn, task.done_fn,
                                    jnp.asarray(start_pool, jnp.float32), key,
                                    n_episodes=n_episodes, horizon=horizon, gamma=gamma,
                                    new_history=new_history, policy_fn=policy_fn)
    return ret.mean(1), length.mean(1).astype(jnp.float32)


def calibrated_mj(pm: PhysicsModel, theta):
    """A copy of ``pm``'s C model with ``theta`` [K] applied as ``PhysicsModel.apply`` does
    (observation bias excluded: see ``obs_bias_of``)."""
    theta, _ = _theta_delays(pm, theta, None)
    mj = copy.deepcopy(pm.mj)
    apply_to_mj(mj, pm.candidates, theta)
    return mj


def obs_bias_of(pm: PhysicsModel, theta) -> np.ndarray:
    """The observation bias [O] that ``theta`` [K] holds."""
    theta, _ = _theta_delays(pm, theta, None)
    bias = np.zeros(pm.obs_size)
    for c, th in zip(pm.candidates, theta, strict=True):
        if c.name == "obs_bias":
            bias[c.index] = th
    return bias


def c_values(pm: PhysicsModel, mj, delays, policy_params, task, start_pool, key: jax.Array,
             *, n_episodes: int, horizon: int, gamma: float, bias=None,
             policy_fn: Callable | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`physics_values` in C MuJoCo (float64) on the C model ``mj`` (``calibrated_mj``,
    ``measured.plant``'s, or ``pm.mj``) with ``delays`` [A] and observation ``bias`` [O]: the
    same start states and policy draws as ``simulated_returns`` with this key (module
    docstring). -> (values [P], mean lengths [P]) float64."""
    import mujoco  # local: keeps `import rl2s_jax.physics` free of MuJoCo

    _, delays = _theta_delays(pm, None, delays)
    bias = np.zeros(pm.obs_size) if bias is None else np.asarray(bias, np.float64)
    if bias.shape != (pm.obs_size,):
        raise ValueError(f"bias: expected shape ({pm.obs_size},), got {bias.shape}")
    n_pol = jax.tree_util.tree_leaves(policy_params)[0].shape[0]
    k_start, k_run = jax.random.split(key)
    pool = jnp.asarray(start_pool, jnp.float32)
    obs = np.asarray(start_values(pool, n_pol, n_episodes, k_start).obs, np.float64)
    one = policy_fn or (lambda p, o, k: sample_action(p, o, k)[0])
    act = jax.jit(jax.vmap(one))
    reward_fn, done_fn = jax.jit(task.reward_fn), jax.jit(task.done_fn)
    datas = [[mujoco.MjData(mj) for _ in range(n_episodes)] for _ in range(n_pol)]
    for p in range(n_pol):
        for e in range(n_episodes):
            q, v = pm.obs_to_state_np(obs[p, e] - bias)
            datas[p][e].qpos[:], datas[p][e].qvel[:] = q, v
    alive = np.ones((n_pol, n_episodes), bool)
    ret, length = np.zeros((n_pol, n_episodes)), np.zeros((n_pol, n_episodes))
    actions = []  # applied history for the delays, [t][P, n, A]
    for t, k_step in enumerate(jax.random.split(k_run, horizon)):
        k_act, _ = jax.random.split(k_step)  # advance_values' split: the same policy draws
        o32 = jnp.asarray(obs, jnp.float32)
        action = np.asarray(act(policy_params, o32, jax.random.split(k_act, n_pol)))
        actions.append(action)
        late = np.stack([actions[-1 - d][..., j] if t >= d else np.zeros(action.shape[:-1])
                         for j, d in enumerate(delays)], -1)
        nxt = obs.copy()
        for p, e in zip(*np.nonzero(alive), strict=True):
            data = datas[p][e]
            data.ctrl[:] = late[p, e]
            mujoco.mj_step(mj, data, nstep=pm.n_frames)
            nxt[p, e] = pm.state_to_obs_np(data.qpos.copy(), data.qvel.copy()) + bias
        n32 = jnp.asarray(nxt, jnp.float32)
        reward = np.asarray(reward_fn(o32, jnp.asarray(action), n32), np.float64)
        done = np.asarray(done_fn(n32)) > 0.5
        ret += np.where(alive, gamma ** t * reward, 0.0)
        length += alive
        alive &= ~done
        obs = nxt
    return ret.mean(1), length.mean(1)
