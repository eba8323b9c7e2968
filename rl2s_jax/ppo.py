"""PPO in pure JAX, used to grow the policy zoo (brax's trainers do not run on JAX >= 0.11).

The whole training run is one jit-compiled function of a PRNG key (purejaxrl style), so
``jax.vmap(train)(keys)`` trains several seeds as one program. Training is an outer
``lax.scan`` over snapshots and an inner one over PPO iterations; every snapshot emits the
policy parameters (with the current observation statistics frozen in), which is how the zoo
samples policies of every quality along training.

Losses follow brax's PPO: clipped surrogate on normalised advantages, GAE that neither
bootstraps across terminations nor accumulates across time-limit truncations, reward scaling,
an entropy bonus, and a running observation normaliser shared by actor and critic.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.envs import training as brax_training
from brax.envs.base import Env

from rl2s_jax.policies import Params, gaussian_log_prob, init_mlp, init_policy, mlp, policy_dist


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters. Env steps per iteration = num_envs * unroll_length (per seed)."""

    num_envs: int = 2048
    unroll_length: int = 10
    num_minibatches: int = 16
    update_epochs: int = 4
    iterations_per_snapshot: int = 40
    n_snapshots: int = 14
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

    @property
    def env_steps_per_iteration(self) -> int:
        return self.num_envs * self.unroll_length

    @property
    def total_env_steps(self) -> int:
        return self.env_steps_per_iteration * self.iterations_per_snapshot * self.n_snapshots

    def validate(self) -> None:
        batch = self.num_envs * self.unroll_length
        if batch % self.num_minibatches:
            raise ValueError(f"num_minibatches: must divide num_envs * unroll_length = {batch}, "
                             f"got {self.num_minibatches}")
        for name in ("num_envs", "unroll_length", "update_epochs", "iterations_per_snapshot",
                     "n_snapshots", "episode_length"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")


class RunningNorm(NamedTuple):
    """Running observation mean and variance (parallel-algorithm update)."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @staticmethod
    def create(size: int) -> RunningNorm:
        return RunningNorm(jnp.zeros(size), jnp.ones(size), jnp.array(1e-4))

    def update(self, x: jax.Array) -> RunningNorm:
        x = x.reshape(-1, x.shape[-1])
        b_mean, b_var, b_n = x.mean(0), x.var(0), x.shape[0]
        delta, total = b_mean - self.mean, self.count + b_n
        mean = self.mean + delta * b_n / total
        m2 = self.var * self.count + b_var * b_n + delta**2 * self.count * b_n / total
        return RunningNorm(mean, m2 / total, total)

    def std(self) -> jax.Array:
        return jnp.sqrt(self.var + 1e-6)


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


def policy_params(state_params: dict, norm: RunningNorm) -> Params:
    """The standalone policy pytree (policies.py layout) with the normaliser frozen in."""
    return {"obs_mean": norm.mean.astype(jnp.float32), "obs_std": norm.std().astype(jnp.float32),
            "layers": state_params["policy"]}


def value_fn(value_layers, norm: RunningNorm, obs: jax.Array) -> jax.Array:
    x = jnp.clip((obs - norm.mean) / norm.std(), -10.0, 10.0)
    return mlp(value_layers, x)[..., 0]


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


def ppo_loss(params, norm, batch, cfg: PPOConfig):
    """Clipped PPO loss on one minibatch -> (loss, metrics)."""
    obs, raw, old_logp, adv, target = batch
    pol = {"obs_mean": norm.mean, "obs_std": norm.std(), "layers": params["policy"]}
    loc, scale = policy_dist(pol, obs)
    # The tanh Jacobian depends only on the raw action, so it cancels in the ratio.
    logp = gaussian_log_prob(loc, scale, raw)
    ratio = jnp.exp(logp - old_logp)
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = -jnp.mean(jnp.minimum(ratio * adv,
                                    jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps) * adv))
    v_loss = 0.5 * jnp.mean((target - value_fn(params["value"], norm, obs)) ** 2)
    entropy = jnp.mean(jnp.sum(jnp.log(scale) + 0.5 * jnp.log(2 * jnp.pi * jnp.e), -1))
    loss = pg_loss + cfg.value_cost * v_loss - cfg.entropy_cost * entropy
    return loss, {"pg_loss": pg_loss, "v_loss": v_loss, "entropy": entropy,
                  "approx_kl": jnp.mean(old_logp - logp)}


def make_train(env: Env, cfg: PPOConfig):
    """Returns ``train(key) -> (final PPOState, snapshots)``.

    snapshots: {"params": policy params stacked [n_snapshots + 1, ...] (index 0 = the initial
    random policy), "episode_return": [n_snapshots + 1] mean return of the training episodes
    finished since the previous snapshot (NaN when none finished), "env_steps": [...]}.
    """
    cfg.validate()
    wenv = brax_training.wrap(env, episode_length=cfg.episode_length)
    obs_size, act_size = env.observation_size, env.action_size
    tx = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                     optax.adam(cfg.learning_rate))
    n, T = cfg.num_envs, cfg.unroll_length
    mb_size = n * T // cfg.num_minibatches

    def rollout_step(carry, _):
        params, norm, env_state, ep_ret, key = carry
        key, k = jax.random.split(key)
        pol = {"obs_mean": norm.mean, "obs_std": norm.std(), "layers": params["policy"]}
        loc, scale = policy_dist(pol, env_state.obs)
        raw = loc + scale * jax.random.normal(k, loc.shape)
        logp = gaussian_log_prob(loc, scale, raw)
        nxt = wenv.step(env_state, jnp.tanh(raw))
        trunc = nxt.info["truncation"]
        ep_ret = ep_ret + nxt.reward
        finished = nxt.done
        stats = (jnp.sum(ep_ret * finished), jnp.sum(finished))
        ep_ret = ep_ret * (1.0 - finished)
        tr = Transition(env_state.obs, raw, logp, nxt.reward * cfg.reward_scaling,
                        nxt.done * (1.0 - trunc), trunc)
        return (params, norm, nxt, ep_ret, key), (tr, stats)

    def iteration(state: PPOState, _):
        (_, _, env_state, ep_ret, key), (traj, stats) = jax.lax.scan(
            rollout_step, (state.params, state.norm, state.env_state, state.episode_return,
                           state.key), None, length=T)
        norm = state.norm.update(traj.obs)
        values = value_fn(state.params["value"], norm, traj.obs)
        last_value = value_fn(state.params["value"], norm, env_state.obs)
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
                grads, metrics = jax.grad(ppo_loss, has_aux=True)(params, norm, mb, cfg)
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), metrics

            (params, opt_state), metrics = jax.lax.scan(minibatch, (params, opt_state), mbs)
            return (params, opt_state, key), metrics

        (params, opt_state, key), metrics = jax.lax.scan(
            epoch, (state.params, state.opt_state, key), None, length=cfg.update_epochs)
        new_state = PPOState(params, opt_state, norm, env_state, ep_ret, key)
        metrics = jax.tree_util.tree_map(jnp.mean, metrics)
        metrics["return_sum"], metrics["episodes"] = jnp.sum(stats[0]), jnp.sum(stats[1])
        return new_state, metrics

    def snapshot(state: PPOState, _):
        state, m = jax.lax.scan(iteration, state, None, length=cfg.iterations_per_snapshot)
        ep = m["episodes"].sum()
        ret = jnp.where(ep > 0, m["return_sum"].sum() / jnp.maximum(ep, 1), jnp.nan)
        summary = {k: v[-1] for k, v in m.items() if k not in ("return_sum", "episodes")}
        return state, (policy_params(state.params, state.norm), ret, summary)

    def train(key):
        k_pol, k_val, k_env, key = jax.random.split(key, 4)
        pol = init_policy(k_pol, obs_size, act_size, cfg.hidden)
        val = init_mlp(k_val, [obs_size, *cfg.value_hidden, 1])
        params = {"policy": pol["layers"], "value": val}
        norm = RunningNorm.create(obs_size)
        env_state = wenv.reset(jax.random.split(k_env, n))
        state = PPOState(params, tx.init(params), norm, env_state, jnp.zeros(n), key)
        initial = policy_params(params, norm)
        state, (snaps, rets, summaries) = jax.lax.scan(snapshot, state, None,
                                                       length=cfg.n_snapshots)
        snaps = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), initial, snaps)
        steps = jnp.arange(cfg.n_snapshots + 1) * cfg.iterations_per_snapshot \
            * cfg.env_steps_per_iteration
        return state, {"params": snaps, "episode_return": jnp.concatenate(
            [jnp.full((1,), jnp.nan), rets]), "env_steps": steps, "losses": summaries}

    return train
