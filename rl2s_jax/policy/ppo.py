"""PPO in pure JAX, used to grow the policy zoo (brax's trainers do not run on JAX >= 0.11).

``make_ppo(env, cfg)`` returns ``PPO(init, train, policy, refill)`` for one seed (purejaxrl
style: everything is a pure function of a ``PPOState`` pytree):

* ``init(key) -> PPOState``: fresh actor, critic, optimiser, normaliser and ``num_envs`` envs.
* ``train(state, n_iterations) -> (state, metrics)``: ``n_iterations`` (static) PPO iterations
  as one ``lax.scan``; each rolls ``unroll_length`` steps of the envs and updates
  ``update_epochs`` x ``num_minibatches`` times. metrics: dict of [n_iterations] arrays.
* ``policy(state) -> Params``: the standalone policy (policies.py layout), normaliser frozen in.
* ``refill(state) -> state``: fresh env states (after restoring a state saved without them).

``train_snapshots(ppo, key, n, k)``: the policies every k iterations (a small zoo, in tests).

``jax.vmap`` over ``init``'s keys and ``train``'s states trains several seeds as one program;
``rl2s_jax.zoo.learners`` runs it in jitted chunks with snapshots and checkpoints.

Losses follow brax's PPO: clipped surrogate on normalised advantages, GAE that neither
bootstraps across terminations nor accumulates across time-limit truncations, reward scaling,
an entropy bonus, and a running observation normaliser shared by actor and critic
(``ignore_obs_dims``, e.g. absolute positions, are masked out of it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.envs import training as brax_training
from brax.envs.base import Env

from rl2s_jax.policy.policy import (
    Params,
    RunningNorm,
    gaussian_log_prob,
    init_mlp,
    init_policy,
    mlp,
    normalize_obs,
    policy_dist,
)


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters (per seed). Env steps per iteration = num_envs * unroll_length.

    ignore_obs_dims: observation dims the actor and critic do not see (their normaliser maps
    them to ~0: ``policies.IGNORED_OBS_STD``); the zoo sets the task's absolute positions.
    """

    num_envs: int = 2048
    unroll_length: int = 10
    num_minibatches: int = 16
    update_epochs: int = 4
    gamma: float = 0.97
    gae_lambda: float = 0.95
    clip_eps: float = 0.3
    entropy_cost: float = 1e-2
    value_cost: float = 0.5
    learning_rate: float = 3e-4
    max_grad_norm: float = 1.0
    reward_scaling: float = 1.0
    episode_length: int = 1000
    hidden: tuple[int, ...] = (64, 64)
    value_hidden: tuple[int, ...] = (256, 256)
    ignore_obs_dims: tuple[int, ...] = ()

    @property
    def env_steps_per_iteration(self) -> int:
        return self.num_envs * self.unroll_length

    def validate(self) -> None:
        for name in ("num_envs", "unroll_length", "update_epochs", "num_minibatches",
                     "episode_length"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        batch = self.num_envs * self.unroll_length
        if batch % self.num_minibatches:
            raise ValueError(f"num_minibatches: must divide num_envs * unroll_length = {batch}, "
                             f"got {self.num_minibatches}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma: expected in [0, 1], got {self.gamma}")
        if self.learning_rate <= 0:
            raise ValueError(f"learning_rate: expected > 0, got {self.learning_rate}")


class PPOState(NamedTuple):
    params: dict          # {"policy": policy layers, "value": value layers}
    opt_state: Any
    norm: RunningNorm
    env_state: Any        # brax State of the wrapped, batched env
    episode_return: jax.Array  # [num_envs] running return of the current episodes
    key: jax.Array


class Transition(NamedTuple):
    obs: jax.Array
    raw_action: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    termination: jax.Array
    truncation: jax.Array


def _policy(params: dict, norm: RunningNorm, ignore_dims=()) -> Params:
    """The standalone policy pytree (policies.py layout) with the normaliser frozen in."""
    mean, std = norm.stats(ignore_dims)
    return {"obs_mean": mean, "obs_std": std, "layers": params["policy"]}


def value_fn(value_layers, pol: Params, obs: jax.Array) -> jax.Array:
    """The critic on the observation normalised as the policy ``pol`` normalises it."""
    return mlp(value_layers, normalize_obs(pol, obs))[..., 0]


def compute_gae(reward, value, next_value, termination, truncation, gamma, lam):
    """GAE over time-major arrays [T, N]; truncated steps neither count nor accumulate."""
    not_trunc = 1.0 - truncation
    delta = (reward + gamma * (1.0 - termination) * next_value - value) * not_trunc

    def back(acc, x):
        d, term, nt = x
        acc = d + gamma * lam * (1.0 - term) * nt * acc
        return acc, acc

    _, adv = jax.lax.scan(back, jnp.zeros_like(value[0]), (delta, termination, not_trunc),
                          reverse=True)
    return adv, adv + value


def ppo_loss(params, pol: Params, batch, cfg: PPOConfig):
    """Clipped PPO loss on one minibatch -> (loss, metrics). pol: the acting policy (its
    normaliser is the one actor and critic see)."""
    obs, raw, old_logp, adv, target = batch
    loc, scale = policy_dist({**pol, "layers": params["policy"]}, obs)
    # The tanh Jacobian depends only on the raw action, so it cancels in the ratio.
    logp = gaussian_log_prob(loc, scale, raw)
    ratio = jnp.exp(logp - old_logp)
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = -jnp.mean(jnp.minimum(ratio * adv,
                                    jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps) * adv))
    v_loss = 0.5 * jnp.mean((target - value_fn(params["value"], pol, obs)) ** 2)
    entropy = jnp.mean(jnp.sum(jnp.log(scale) + 0.5 * jnp.log(2 * jnp.pi * jnp.e), -1))
    loss = pg_loss + cfg.value_cost * v_loss - cfg.entropy_cost * entropy
    return loss, {"pg_loss": pg_loss, "v_loss": v_loss, "entropy": entropy,
                  "approx_kl": jnp.mean(old_logp - logp)}


class PPO(NamedTuple):
    init: Callable[[jax.Array], PPOState]
    train: Callable[[PPOState, int], tuple[PPOState, dict]]
    policy: Callable[[PPOState], Params]
    refill: Callable[[PPOState], PPOState]


def make_ppo(env: Env, cfg: PPOConfig) -> PPO:
    """PPO for an unwrapped brax ``env`` (module docstring)."""
    cfg.validate()
    wenv = brax_training.wrap(env, episode_length=cfg.episode_length)
    obs_size, act_size = env.observation_size, env.action_size
    bad = [d for d in cfg.ignore_obs_dims if not 0 <= d < obs_size]
    if bad:
        raise ValueError(f"ignore_obs_dims: expected dims in [0, {obs_size}), got {bad}")
    tx = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                     optax.adam(cfg.learning_rate))
    n, T = cfg.num_envs, cfg.unroll_length
    mb_size = n * T // cfg.num_minibatches

    def rollout_step(carry, _):
        pol, env_state, ep_ret, key = carry
        key, k = jax.random.split(key)
        loc, scale = policy_dist(pol, env_state.obs)
        raw = loc + scale * jax.random.normal(k, loc.shape)
        logp = gaussian_log_prob(loc, scale, raw)
        nxt = wenv.step(env_state, jnp.tanh(raw))
        trunc = nxt.info["truncation"]
        ep_ret = ep_ret + nxt.reward
        finished = nxt.done
        stats = (jnp.sum(ep_ret * finished), jnp.sum(finished), jnp.mean(nxt.reward))
        ep_ret = ep_ret * (1.0 - finished)
        tr = Transition(env_state.obs, raw, logp, nxt.reward * cfg.reward_scaling,
                        nxt.done * (1.0 - trunc), trunc)
        return (pol, nxt, ep_ret, key), (tr, stats)

    def iteration(state: PPOState, _):
        pol = _policy(state.params, state.norm, cfg.ignore_obs_dims)
        (_, env_state, ep_ret, key), (traj, stats) = jax.lax.scan(
            rollout_step, (pol, state.env_state, state.episode_return, state.key), None,
            length=T)
        norm = state.norm.update(traj.obs)
        pol = _policy(state.params, norm, cfg.ignore_obs_dims)
        values = value_fn(state.params["value"], pol, traj.obs)
        last_value = value_fn(state.params["value"], pol, env_state.obs)
        next_values = jnp.concatenate([values[1:], last_value[None]], 0)
        adv, target = compute_gae(traj.reward, values, next_values, traj.termination,
                                  traj.truncation, cfg.gamma, cfg.gae_lambda)
        data = (traj.obs, traj.raw_action, traj.log_prob, adv, target)
        data = jax.tree_util.tree_map(lambda x: x.reshape((n * T,) + x.shape[2:]), data)

        def epoch(carry, _):
            params, opt_state, key = carry
            key, k = jax.random.split(key)
            perm = jax.random.permutation(k, n * T)
            mbs = jax.tree_util.tree_map(
                lambda x: x[perm].reshape((cfg.num_minibatches, mb_size) + x.shape[1:]), data)

            def minibatch(carry, mb):
                params, opt_state = carry
                grads, metrics = jax.grad(ppo_loss, has_aux=True)(params, pol, mb, cfg)
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), metrics

            (params, opt_state), metrics = jax.lax.scan(minibatch, (params, opt_state), mbs)
            return (params, opt_state, key), metrics

        (params, opt_state, key), metrics = jax.lax.scan(
            epoch, (state.params, state.opt_state, key), None, length=cfg.update_epochs)
        new_state = PPOState(params, opt_state, norm, env_state, ep_ret, key)
        metrics = jax.tree_util.tree_map(jnp.mean, metrics)
        metrics["return_sum"], metrics["episodes"] = jnp.sum(stats[0]), jnp.sum(stats[1])
        metrics["reward_mean"] = jnp.mean(stats[2])
        return new_state, metrics

    def init(key: jax.Array) -> PPOState:
        k_pol, k_val, k_env, key = jax.random.split(key, 4)
        pol = init_policy(k_pol, obs_size, act_size, cfg.hidden)
        val = init_mlp(k_val, [obs_size, *cfg.value_hidden, 1])
        params = {"policy": pol["layers"], "value": val}
        env_state = wenv.reset(jax.random.split(k_env, n))
        return PPOState(params, tx.init(params), RunningNorm.create(obs_size), env_state,
                        jnp.zeros(n), key)

    def train(state: PPOState, n_iterations: int) -> tuple[PPOState, dict]:
        """n_iterations (static) iterations -> (state, metrics: dict of [n_iterations]
        arrays: mean losses, return_sum / episodes of the episodes that ended, reward_mean)."""
        return jax.lax.scan(iteration, state, None, length=int(n_iterations))

    def policy(state: PPOState) -> Params:
        return _policy(state.params, state.norm, cfg.ignore_obs_dims)

    def refill(state: PPOState) -> PPOState:
        key, k_env = jax.random.split(state.key)
        return state._replace(env_state=wenv.reset(jax.random.split(k_env, n)),
                              episode_return=jnp.zeros(n), key=key)

    return PPO(init, train, policy, refill)


def train_snapshots(ppo: PPO, key: jax.Array, n_snapshots: int,
                    iterations_per_snapshot: int) -> Params:
    """One seed's policy after every ``iterations_per_snapshot`` iterations, ``n_snapshots``
    times, as one ``lax.scan`` (a small zoo without ``zoo_train``'s checkpoints). -> policies
    stacked [n_snapshots + 1, ...], index 0 the initial random policy. Jit it with the counts
    static."""
    state = ppo.init(key)

    def chunk(st, _):
        st, _ = ppo.train(st, iterations_per_snapshot)
        return st, ppo.policy(st)

    _, snaps = jax.lax.scan(chunk, state, None, length=int(n_snapshots))
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]),
                                  ppo.policy(state), snaps)
