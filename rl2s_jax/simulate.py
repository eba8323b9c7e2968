"""Roll policies inside a simulator and measure their values.

A simulator here is any ``dynamics(obs [..., o], action [..., a], key) -> next_obs [..., o]``
(the learned generator, or a task's true dynamics in tests); rewards and terminations come from
the task's ``reward_fn(obs, action, next_obs)`` and ``done_fn(next_obs)``.

Value rollouts run P policies x n episodes as one batch. They can be advanced piecewise
(``advance_values`` a few steps at a time), which is how ``train_step`` spreads one value
measurement over K calls instead of spiking every K-th call.
"""
from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rl2s_jax.models import Normalizer, generator_log_prob, generator_mean, generator_sample
from rl2s_jax.policies import Params, sample_action

Dynamics = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


@struct.dataclass
class Simulator:
    """A learned simulator p_phi: generator params, its normaliser, the task it models.

    ``dynamics`` is the ``Dynamics`` function the rollouts here take; ``task`` names the
    registered task whose reward_fn / done_fn apply (None for data without a task).
    """

    gen: Params
    norm: Normalizer
    task: str | None = struct.field(pytree_node=False, default=None)
    obs_clip: float = struct.field(pytree_node=False, default=10.0)
    noise_scale: float = struct.field(pytree_node=False, default=1.0)

    def sample(self, obs: jax.Array, action: jax.Array, key: jax.Array) -> jax.Array:
        """s' ~ p_phi(.|s, a) with the std times noise_scale, clipped to +-obs_clip data stds.
        [..., o], [..., a] -> [..., o]"""
        return generator_sample(self.gen, self.norm, obs, action, key, self.obs_clip,
                                self.noise_scale)

    def mean(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        """The mean next state. -> [..., o]"""
        return generator_mean(self.gen, self.norm, obs, action)

    def log_prob(self, obs: jax.Array, action: jax.Array, next_obs: jax.Array) -> jax.Array:
        """log density of the normalised delta. -> [...]"""
        return generator_log_prob(self.gen, self.norm, obs, action, next_obs)

    def dynamics(self, obs: jax.Array, action: jax.Array, key: jax.Array) -> jax.Array:
        return self.sample(obs, action, key)


@struct.dataclass
class ValueRollout:
    """P x n simulated episodes in progress.

    obs [P, n, o]; alive [P, n] (not yet terminated); ret [P, n] discounted return so far;
    length [P, n] steps survived; t [] steps taken.
    """

    obs: jax.Array
    alive: jax.Array
    ret: jax.Array
    length: jax.Array
    t: jax.Array


def start_pool(ds) -> jax.Array:
    """Real episode start states of a Dataset [S, o] (its rows with t == 0)."""
    pool = np.asarray(ds.obs)[np.asarray(ds.t) == 0]
    if pool.shape[0] == 0:
        raise ValueError("t: expected some episode start rows (t == 0) for the start states")
    return jnp.asarray(pool, jnp.float32)


def start_values(start_pool: jax.Array, n_policies: int, n_episodes: int, key: jax.Array
                 ) -> ValueRollout:
    """Fresh episodes from start states drawn (with replacement) from start_pool [S, o]."""
    idx = jax.random.randint(key, (n_policies, n_episodes), 0, start_pool.shape[0])
    shape = (n_policies, n_episodes)
    return ValueRollout(obs=start_pool[idx], alive=jnp.ones(shape, bool),
                        ret=jnp.zeros(shape, jnp.float32), length=jnp.zeros(shape, jnp.int32),
                        t=jnp.zeros((), jnp.int32))


def advance_values(roll: ValueRollout, policy_params: Params, dynamics: Dynamics,
                   reward_fn: Callable, done_fn: Callable, key: jax.Array, *, n_steps: int,
                   horizon: int, gamma: float | jax.Array) -> ValueRollout:
    """Run ``n_steps`` more steps (steps past ``horizon`` change nothing).

    policy_params: stacked [P, ...]; each policy acts stochastically in its own episodes.
    """
    n_pol = roll.obs.shape[0]
    act = jax.vmap(sample_action)  # over policies; each call batches its n episodes

    def step(roll: ValueRollout, key):
        k_act, k_dyn = jax.random.split(key)
        action, _, _ = act(policy_params, roll.obs, jax.random.split(k_act, n_pol))
        next_obs = dynamics(roll.obs, action, k_dyn)
        live = roll.alive & (roll.t < horizon)
        reward = reward_fn(roll.obs, action, next_obs)
        done = done_fn(next_obs) > 0.5
        discount = jnp.asarray(gamma, jnp.float32) ** roll.t.astype(jnp.float32)
        return ValueRollout(
            obs=jnp.where(live[..., None], next_obs, roll.obs),
            alive=roll.alive & ~(live & done),
            ret=roll.ret + jnp.where(live, discount * reward, 0.0),
            length=roll.length + live.astype(jnp.int32),
            t=jnp.minimum(roll.t + 1, horizon)), None

    roll, _ = jax.lax.scan(step, roll, jax.random.split(key, n_steps))
    return roll


def simulated_returns(policy_params: Params, dynamics: Dynamics, reward_fn: Callable,
                      done_fn: Callable, start_pool: jax.Array, key: jax.Array, *,
                      n_episodes: int, horizon: int, gamma: float
                      ) -> tuple[jax.Array, jax.Array]:
    """Each simulated episode's discounted return and length: n_episodes episodes of at most
    ``horizon`` steps per policy. -> (returns [P, n], lengths [P, n] int32)."""
    k_start, k_run = jax.random.split(key)
    n_pol = jax.tree_util.tree_leaves(policy_params)[0].shape[0]
    roll = start_values(start_pool, n_pol, n_episodes, k_start)
    roll = advance_values(roll, policy_params, dynamics, reward_fn, done_fn, k_run,
                          n_steps=horizon, horizon=horizon, gamma=gamma)
    return roll.ret, roll.length


def simulated_values(policy_params: Params, dynamics: Dynamics, reward_fn: Callable,
                     done_fn: Callable, start_pool: jax.Array, key: jax.Array, *,
                     n_episodes: int, horizon: int, gamma: float) -> tuple[jax.Array, jax.Array]:
    """Discounted value of each policy in ``dynamics``: mean over n_episodes episodes of at
    most ``horizon`` steps (``simulated_returns`` averaged).
    -> (values [P], mean episode lengths [P])."""
    ret, length = simulated_returns(policy_params, dynamics, reward_fn, done_fn, start_pool,
                                    key, n_episodes=n_episodes, horizon=horizon, gamma=gamma)
    return ret.mean(1), length.mean(1).astype(jnp.float32)


def value_difference(sim_values: jax.Array, true_values: jax.Array) -> jax.Array:
    """VD(pi) = |V(p*, pi) - V(p_phi, pi)|, elementwise [P]."""
    return jnp.abs(true_values - sim_values)


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
