"""Soft actor-critic in pure JAX, with the actor in our policy format (``policies.py``).

The actor is a tanh-Gaussian policy pytree ``{"obs_mean", "obs_std", "layers"}``: training
updates ``layers`` only, the observation normaliser stays frozen. So the actor can start from
a zoo policy (fine-tuning) and the result is a policy that ``collect`` / ``measure_values`` take
as it is. The twin critics are swish MLPs on (actor-normalised obs, action); their targets
follow by Polyak averaging; the temperature alpha is learned towards a target entropy.

Fine-tuning a given policy (``init(key, actor_params)``) needs other settings than training
from scratch, so that SAC improves a good policy instead of first destroying it.
``SACConfig.fine_tuning()`` gives them (the plain ``SACConfig()`` defaults are the
from-scratch ones and keep SAC as it was):

* the temperature starts small (``init_alpha``) and its target is the start policy's own
  entropy, measured on the warm-up states (``target_entropy="start"``), so the entropy bonus
  does not swamp the task's reward and drive a near-deterministic policy towards noise;
* the critics first learn the start policy's value while the actor waits
  (``critic_warmup_updates``; the env keeps stepping with the frozen start policy);
* the actor loss holds a KL(pi || pi_start) penalty to the frozen start policy
  (``kl_weight``, relative to the batch's mean |Q| as TD3+BC scales its BC term, so one
  value works across reward scales); the KL of two tanh-Gaussians is that of their
  pre-tanh Gaussians (tanh is a bijection), in closed form.

From scratch (``init(key)``) "start" means ``-action_size`` and the KL is never applied.

``make_sac(env, cfg)`` returns ``SAC(init, train)``:

* ``init(key, actor_params=None) -> SACState``: fresh critics, the given (or a fresh) actor,
  ``n_envs`` envs reset, and a replay buffer prefilled with ``warmup_steps`` vectorised env steps
  of the initial actor (no updates).
* ``train(state, n_iterations) -> (state, metrics)``: ``n_iterations`` times (``lax.scan``):
  one step of the ``n_envs`` envs with the current actor, then ``updates_per_step`` gradient
  updates. For the first ``critic_warmup_updates`` updates only the critics learn (so a
  fine-tuned actor is not pushed around by random critics). ``n_iterations`` is static.

From scratch (``init(key)`` with no actor), ``normalize_observations=True`` keeps a running
observation normaliser (``SACState.obs_norm``) updated with every env step's observations and
written into the actor's ``obs_mean`` / ``obs_std`` (``ignore_obs_dims`` masked out), so the
critics, which normalise with the actor's statistics, see the same input and the actor is a
zoo policy as it is. ``refill(state)`` gives fresh envs and an empty buffer re-filled with
``warmup_steps`` steps of the current actor (resuming from a state saved without its buffer).

Everything is one pure program of the state: ``jax.jit(train, static_argnums=1)``, and
``jax.vmap(init)(keys, stacked_policies)`` / ``jax.vmap(train, in_axes=(0, None))`` fine-tune
several policies as one batch. The env must be an unwrapped brax Env (no time limit, no
auto-reset): SAC resets ended episodes itself with a fresh ``env.reset`` (so a SimulatorEnv
draws a new start state per episode), and bootstraps through time-limit truncations: its own
``episode_length`` and an env's ``info["truncation"]`` (a SimulatorEnv's ``rollout_length``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.envs.base import Env

from rl2s_jax.envs.checks import check_env, tree_where
from rl2s_jax.policy.policy import (
    Params,
    RunningNorm,
    init_mlp,
    init_policy,
    mask_obs_stats,
    mlp,
    normalize_obs,
    policy_dist,
    sample_action,
)


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """SAC hyper-parameters (per seed / per fine-tuned policy).

    One iteration = one step of ``n_envs`` envs + ``updates_per_step`` gradient updates on
    batches of ``batch_size``. ``warmup_steps`` vectorised env steps fill the buffer in ``init``;
    ``buffer_size`` rows are kept (ring buffer). ``hidden``: critic hidden sizes;
    ``actor_hidden``: hidden sizes of a fresh actor (ignored when fine-tuning).

    Fine-tuning settings (module docstring; defaults keep plain SAC, ``fine_tuning()`` gives
    the tested ones): ``actor_learning_rate``, ``critic_learning_rate``,
    ``alpha_learning_rate``: None = ``learning_rate``; an alpha rate of 0 keeps alpha at
    ``init_alpha``. ``target_entropy``: None or "action_size" (-action_size, the SAC paper's
    rule), "start" (the start policy's measured entropy plus ``target_entropy_offset``;
    -action_size from scratch) or a number. ``kl_weight``: weight of KL(pi || pi_start) in the
    actor loss, times the batch's mean |Q| (0: off; never applied from scratch).
    ``max_grad_norm``: clip each network's gradient norm (None: no clipping).

    From-scratch options (defaults keep fine-tuning as it was): ``normalize_observations``:
    running observation normaliser written into a fresh actor's obs_mean/obs_std;
    ``ignore_obs_dims``: obs dims a fresh actor and the critics do not see (absolute positions);
    ``learn_alpha``: False keeps alpha at ``init_alpha``.
    """

    learning_rate: float = 3e-4
    batch_size: int = 256
    gamma: float = 0.99
    tau: float = 0.005
    n_envs: int = 16
    updates_per_step: int = 1
    warmup_steps: int = 64
    critic_warmup_updates: int = 0
    buffer_size: int = 100_000
    hidden: tuple[int, ...] = (256, 256)
    actor_hidden: tuple[int, ...] = (64, 64)
    episode_length: int = 1000
    init_alpha: float = 1.0
    reward_scaling: float = 1.0
    # fine-tuning (issue 11); the defaults keep plain SAC, see fine_tuning()
    actor_learning_rate: float | None = None
    critic_learning_rate: float | None = None
    alpha_learning_rate: float | None = None
    target_entropy: float | str | None = None
    target_entropy_offset: float = 0.0
    kl_weight: float = 0.0
    max_grad_norm: float | None = None
    # from-scratch training (issue 15)
    normalize_observations: bool = False
    ignore_obs_dims: tuple[int, ...] = ()
    learn_alpha: bool = True

    @classmethod
    def fine_tuning(cls, **overrides) -> SACConfig:
        """The tested settings for fine-tuning a given policy (module docstring): alpha from
        FINE_TUNING["init_alpha"], target = the start policy's entropy, a KL anchor to it;
        ``overrides`` replace any field (e.g. critic_warmup_updates, sizes)."""
        return cls(**{**FINE_TUNING, **overrides})

    def validate(self) -> None:
        for name in ("batch_size", "n_envs", "updates_per_step", "buffer_size",
                     "episode_length"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.critic_warmup_updates < 0:
            raise ValueError(f"critic_warmup_updates: expected >= 0, "
                             f"got {self.critic_warmup_updates}")
        if self.warmup_steps < 1:
            raise ValueError("warmup_steps: expected >= 1 (the buffer must hold data before "
                             f"the first update), got {self.warmup_steps}")
        if self.warmup_steps * self.n_envs > self.buffer_size:
            raise ValueError(f"buffer_size: must hold the warmup_steps * n_envs = "
                             f"{self.warmup_steps * self.n_envs} warmup rows, got "
                             f"{self.buffer_size}")
        if self.n_envs > self.buffer_size:
            raise ValueError(f"buffer_size: expected >= n_envs = {self.n_envs}, "
                             f"got {self.buffer_size}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau: expected in (0, 1], got {self.tau}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma: expected in [0, 1], got {self.gamma}")
        if self.learning_rate <= 0 or self.init_alpha <= 0:
            bad = "learning_rate" if self.learning_rate <= 0 else "init_alpha"
            raise ValueError(f"{bad}: expected > 0, got {getattr(self, bad)}")
        for name in ("actor_learning_rate", "critic_learning_rate"):
            v = getattr(self, name)
            if v is not None and v <= 0:
                raise ValueError(f"{name}: expected > 0 or None, got {v}")
        if self.alpha_learning_rate is not None and self.alpha_learning_rate < 0:
            raise ValueError(f"alpha_learning_rate: expected >= 0 or None, got "
                             f"{self.alpha_learning_rate}")
        te = self.target_entropy
        if isinstance(te, str) and te not in ("start", "action_size"):
            raise ValueError(f"target_entropy: expected None, 'start', 'action_size' or a "
                             f"number, got {te!r}")
        if self.kl_weight < 0:
            raise ValueError(f"kl_weight: expected >= 0, got {self.kl_weight}")
        if self.max_grad_norm is not None and self.max_grad_norm <= 0:
            raise ValueError(f"max_grad_norm: expected > 0 or None, got {self.max_grad_norm}")

    def optimizer(self, which: str) -> optax.GradientTransformation:
        """Adam for "actor", "critic" or "alpha" with its learning rate (and clipping)."""
        lr = getattr(self, f"{which}_learning_rate")
        lr = self.learning_rate if lr is None else lr
        adam = optax.adam(lr)
        if self.max_grad_norm is None or which == "alpha":
            return adam
        return optax.chain(optax.clip_by_global_norm(self.max_grad_norm), adam)


# SACConfig.fine_tuning()'s settings (measured on pointmass: tests/test_improve.py; the
# critic warm-up depends on the budget, `rl2s improve` uses a quarter of the updates).
FINE_TUNING = dict(init_alpha=0.01, target_entropy="start", kl_weight=0.01)


class Buffer(NamedTuple):
    """Ring buffer of transitions. obs/next_obs [N, o], action [N, a], reward, terminal [N];
    ptr: next row to write; size: rows filled (<= N)."""

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    terminal: jax.Array
    ptr: jax.Array
    size: jax.Array

    @staticmethod
    def create(capacity: int, obs_size: int, action_size: int) -> Buffer:
        z = lambda *s: jnp.zeros(s, jnp.float32)
        return Buffer(z(capacity, obs_size), z(capacity, action_size), z(capacity),
                      z(capacity, obs_size), z(capacity), jnp.zeros((), jnp.int32),
                      jnp.zeros((), jnp.int32))

    def add(self, obs, action, reward, next_obs, terminal) -> Buffer:
        """Append a batch of n rows (n <= capacity), overwriting the oldest."""
        cap, n = self.obs.shape[0], obs.shape[0]
        idx = (self.ptr + jnp.arange(n)) % cap
        put = lambda buf, x: buf.at[idx].set(x.astype(buf.dtype))
        return Buffer(put(self.obs, obs), put(self.action, action), put(self.reward, reward),
                      put(self.next_obs, next_obs), put(self.terminal, terminal),
                      (self.ptr + n) % cap, jnp.minimum(self.size + n, cap))

    def sample(self, key: jax.Array, batch_size: int) -> tuple[jax.Array, ...]:
        """batch_size rows drawn uniformly (with replacement) from the filled part."""
        idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(self.size, 1))
        return self.obs[idx], self.action[idx], self.reward[idx], self.next_obs[idx], \
            self.terminal[idx]


class SACState(NamedTuple):
    actor: Params          # policies.py layout; only "layers" is trained
    critic: Any            # twin Q layers, stacked [2, ...]
    target_critic: Any
    log_alpha: jax.Array   # []
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any
    buffer: Buffer
    env_state: Any         # brax State batched [n_envs]
    t: jax.Array           # [n_envs] steps into the current episodes
    episode_return: jax.Array  # [n_envs] undiscounted return of the current episodes
    updates: jax.Array     # [] gradient updates done
    key: jax.Array
    # fine-tuning only (None from scratch, so a from-scratch state is the zoo trainer's):
    anchor: Params = None  # the start actor (frozen; the KL penalty's reference)
    kl_coef: jax.Array = None  # [] kl_weight
    target_entropy: jax.Array = None  # [] alpha's target (from scratch: static_target)
    obs_norm: Any = None   # RunningNorm when cfg.normalize_observations, else None


class SAC(NamedTuple):
    init: Callable[..., SACState]
    train: Callable[[SACState, int], tuple[SACState, dict]]
    refill: Callable[[SACState], SACState] | None = None


def q_values(critic, actor: Params, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Both critics. obs [..., o], action [..., a] -> [2, ...]."""
    x = jnp.concatenate([normalize_obs(actor, obs), action], -1)
    return jax.vmap(lambda layers: mlp(layers, x)[..., 0])(critic)


def gaussian_kl(loc: jax.Array, scale: jax.Array, loc0: jax.Array, scale0: jax.Array
                ) -> jax.Array:
    """KL(N(loc, scale) || N(loc0, scale0)) of diagonal Gaussians, summed over the last axis.
    It is also the KL of their tanh-squashed distributions (tanh is a bijection). -> [...]"""
    return jnp.sum(jnp.log(scale0 / scale)
                   + (scale**2 + (loc - loc0) ** 2) / (2.0 * scale0**2) - 0.5, axis=-1)


def make_sac(env: Env, cfg: SACConfig) -> SAC:
    """SAC for an unwrapped brax ``env`` (module docstring)."""
    cfg.validate()
    check_env(env)
    obs_size, act_size = int(env.observation_size), int(env.action_size)
    actor_opt_, critic_opt_, alpha_opt_ = (cfg.optimizer(w) for w in ("actor", "critic",
                                                                       "alpha"))
    bad = [d for d in cfg.ignore_obs_dims if not 0 <= d < obs_size]
    if bad:
        raise ValueError(f"ignore_obs_dims: expected dims in [0, {obs_size}), got {bad}")
    # alpha's target from scratch (and for fine-tuning unless "start"): a number or -action_size
    te = cfg.target_entropy
    static_target = -float(act_size) if te is None or isinstance(te, str) else float(te)
    n = cfg.n_envs
    v_reset, v_step = jax.vmap(env.reset), jax.vmap(env.step)

    def env_step(actor, env_state, t, ep_ret, buffer, key):
        """One step of the n envs: store the transitions, reset the ended episodes."""
        k_act, k_reset = jax.random.split(key)
        obs = env_state.obs
        action, _, _ = sample_action(actor, obs, k_act)
        nxt = v_step(env_state, action)
        terminal = nxt.done > 0.5
        end = terminal | (t + 1 >= cfg.episode_length)
        if "truncation" in nxt.info:  # the env's own rollout limit (SimulatorEnv)
            end = end | (nxt.info["truncation"] > 0.5)
        buffer = buffer.add(obs, action, nxt.reward * cfg.reward_scaling, nxt.obs,
                            terminal.astype(jnp.float32))
        ep_ret = ep_ret + nxt.reward
        stats = (jnp.sum(jnp.where(end, ep_ret, 0.0)), jnp.sum(end), jnp.mean(nxt.reward))
        env_state = tree_where(end, v_reset(jax.random.split(k_reset, n)), nxt)
        t = jnp.where(end, 0, t + 1)
        ep_ret = jnp.where(end, 0.0, ep_ret)
        return env_state, t, ep_ret, buffer, stats

    def observe(actor, norm, obs):
        """Fold obs [n, o] into the running normaliser and write its statistics into the
        actor (no-op without normalize_observations)."""
        if norm is None:
            return actor, norm
        norm = norm.update(obs)
        mean, std = norm.stats(cfg.ignore_obs_dims)
        return {**actor, "obs_mean": mean, "obs_std": std}, norm

    def critic_loss(critic, actor, target_critic, alpha, batch, key):
        obs, action, reward, next_obs, terminal = batch
        next_action, _, next_logp = sample_action(actor, next_obs, key)
        q_next = jnp.min(q_values(target_critic, actor, next_obs, next_action), axis=0)
        target = reward + cfg.gamma * (1.0 - terminal) * (q_next - alpha * next_logp)
        q = q_values(critic, actor, obs, action)
        loss = 0.5 * jnp.mean(jnp.sum((q - jax.lax.stop_gradient(target)) ** 2, axis=0))
        return loss, jnp.mean(q)

    def actor_loss(layers, actor, critic, alpha, anchor, kl_coef, obs, key):
        pol = {**actor, "layers": layers}
        action, _, logp = sample_action(pol, obs, key)
        q = jnp.min(q_values(critic, actor, obs, action), axis=0)
        loss = jnp.mean(alpha * logp - q)
        if anchor is None or cfg.kl_weight == 0:  # static: from scratch or no anchor in the loss
            return loss, (logp, jnp.zeros((), jnp.float32))
        kl = jnp.mean(gaussian_kl(*policy_dist(pol, obs), *policy_dist(anchor, obs)))
        scale = jax.lax.stop_gradient(jnp.mean(jnp.abs(q)))
        return loss + kl_coef * scale * kl, (logp, kl)

    def update(state: SACState, key):
        k_batch, k_critic, k_actor = jax.random.split(key, 3)
        batch = state.buffer.sample(k_batch, cfg.batch_size)
        alpha = jnp.exp(state.log_alpha)

        (q_loss, q_mean), g = jax.value_and_grad(critic_loss, has_aux=True)(
            state.critic, state.actor, state.target_critic, alpha, batch, k_critic)
        upd, critic_opt = critic_opt_.update(g, state.critic_opt, state.critic)
        critic = optax.apply_updates(state.critic, upd)
        target = jax.tree_util.tree_map(lambda t, c: (1 - cfg.tau) * t + cfg.tau * c,
                                        state.target_critic, critic)

        (pi_loss, (logp, kl)), g = jax.value_and_grad(actor_loss, has_aux=True)(
            state.actor["layers"], state.actor, critic, alpha, state.anchor, state.kl_coef,
            batch[0], k_actor)
        upd, actor_opt = actor_opt_.update(g, state.actor_opt, state.actor["layers"])
        layers = optax.apply_updates(state.actor["layers"], upd)

        entropy = -jnp.mean(logp)
        target_entropy = (static_target if state.target_entropy is None
                          else state.target_entropy)
        a_loss, g = jax.value_and_grad(
            lambda la: -la * jax.lax.stop_gradient(target_entropy - entropy)
        )(state.log_alpha)
        upd, alpha_opt = alpha_opt_.update(g, state.alpha_opt, state.log_alpha)
        log_alpha = optax.apply_updates(state.log_alpha, upd)

        # Actor and alpha wait for the critics during critic_warmup_updates.
        live = state.updates >= cfg.critic_warmup_updates
        keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(live, a, b),
                                                       new, old)
        if not cfg.learn_alpha:
            log_alpha, alpha_opt = state.log_alpha, state.alpha_opt
        state = state._replace(
            actor={**state.actor, "layers": keep(layers, state.actor["layers"])},
            actor_opt=keep(actor_opt, state.actor_opt), critic=critic, target_critic=target,
            critic_opt=critic_opt, log_alpha=keep(log_alpha, state.log_alpha),
            alpha_opt=keep(alpha_opt, state.alpha_opt), updates=state.updates + 1)
        return state, {"q_loss": q_loss, "q_mean": q_mean, "actor_loss": pi_loss,
                       "alpha_loss": a_loss, "alpha": alpha, "entropy": entropy, "kl": kl}

    def iteration(state: SACState, _):
        key, k_env, k_upd = jax.random.split(state.key, 3)
        actor, obs_norm = observe(state.actor, state.obs_norm, state.env_state.obs)
        env_state, t, ep_ret, buffer, (ret_sum, n_ended, reward_mean) = env_step(
            actor, state.env_state, state.t, state.episode_return, state.buffer, k_env)
        state = state._replace(env_state=env_state, t=t, episode_return=ep_ret, buffer=buffer,
                               key=key, actor=actor, obs_norm=obs_norm)
        state, m = jax.lax.scan(update, state, jax.random.split(k_upd, cfg.updates_per_step))
        m = jax.tree_util.tree_map(lambda x: x[-1], m)
        if state.anchor is not None and cfg.kl_weight == 0:  # static
            # no anchor in the loss, but how far the actor moved is measured: once per
            # iteration on a replay batch, not in every update (only the last is reported)
            obs = state.buffer.sample(jax.random.fold_in(k_upd, 1), cfg.batch_size)[0]
            m["kl"] = jnp.mean(gaussian_kl(*policy_dist(state.actor, obs),
                                           *policy_dist(state.anchor, obs)))
        m["return_sum"], m["episodes"], m["reward_mean"] = ret_sum, n_ended, reward_mean
        return state, m

    def warmup(actor, obs_norm, k_env, k_warm):
        """Fresh envs and a buffer filled by warmup_steps steps of ``actor`` (no updates)."""
        buffer = Buffer.create(cfg.buffer_size, obs_size, act_size)
        env_state = v_reset(jax.random.split(k_env, n))
        t, ep_ret = jnp.zeros((n,), jnp.int32), jnp.zeros((n,), jnp.float32)

        def warm(carry, k):
            actor, obs_norm, *env = carry
            actor, obs_norm = observe(actor, obs_norm, env[0].obs)
            return (actor, obs_norm, *env_step(actor, *env, k)[:4]), None

        carry, _ = jax.lax.scan(warm, (actor, obs_norm, env_state, t, ep_ret, buffer),
                                jax.random.split(k_warm, cfg.warmup_steps))
        return carry

    def init(key: jax.Array, actor_params: Params | None = None) -> SACState:
        """Fresh critics and buffer; the actor is ``actor_params`` (one policy) or fresh."""
        k_actor, k_critic, k_env, k_warm, key = jax.random.split(key, 5)
        k_ent = jax.random.fold_in(k_warm, 1)
        obs_norm = None
        if actor_params is None:
            actor = init_policy(k_actor, obs_size, act_size, cfg.actor_hidden)
            mean, std = mask_obs_stats(actor["obs_mean"], actor["obs_std"], cfg.ignore_obs_dims)
            actor = {**actor, "obs_mean": mean, "obs_std": std}
            if cfg.normalize_observations:
                obs_norm = RunningNorm.create(obs_size)
        elif cfg.normalize_observations:
            raise ValueError("normalize_observations: only for a fresh actor (init without "
                             "actor_params); a given actor keeps its own frozen normaliser")
        else:
            actor = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), actor_params)
            mean = actor["obs_mean"]
            if mean.shape != (obs_size,):
                raise ValueError(f"actor_params: obs_mean of shape {mean.shape}, expected "
                                 f"({obs_size},) (one policy, not a stack)")
            out = actor["layers"][-1]["b"].shape
            if out != (2 * act_size,):
                raise ValueError(f"actor_params: last layer outputs {out}, expected "
                                 f"({2 * act_size},) for action_size {act_size}")
        sizes = [obs_size + act_size, *cfg.hidden, 1]
        critic = jax.vmap(lambda k: init_mlp(k, sizes))(jax.random.split(k_critic, 2))
        log_alpha = jnp.log(jnp.asarray(cfg.init_alpha, jnp.float32))
        actor, obs_norm, env_state, t, ep_ret, buffer = warmup(actor, obs_norm, k_env, k_warm)
        fine_tuning = actor_params is not None
        anchor = kl_coef = target = None
        if fine_tuning:
            anchor, kl_coef = actor, jnp.asarray(cfg.kl_weight, jnp.float32)
            if cfg.target_entropy == "start":
                # the start policy's entropy, estimated on the warm-up states
                _, _, logp = sample_action(actor, buffer.obs[:cfg.warmup_steps * n], k_ent)
                target = (-jnp.mean(logp) + cfg.target_entropy_offset).astype(jnp.float32)
            else:
                target = jnp.asarray(static_target, jnp.float32)
        return SACState(actor=actor, critic=critic, target_critic=critic, log_alpha=log_alpha,
                        actor_opt=actor_opt_.init(actor["layers"]),
                        critic_opt=critic_opt_.init(critic), alpha_opt=alpha_opt_.init(log_alpha),
                        buffer=buffer, env_state=env_state, t=t, episode_return=ep_ret,
                        updates=jnp.zeros((), jnp.int32), key=key, anchor=anchor,
                        kl_coef=kl_coef, target_entropy=target, obs_norm=obs_norm)

    def train(state: SACState, n_iterations: int) -> tuple[SACState, dict]:
        """n_iterations (static) iterations. metrics: dict of [n_iterations] arrays: losses,
        alpha, entropy of the last update; return_sum / episodes of the episodes that ended."""
        return jax.lax.scan(iteration, state, None, length=int(n_iterations))

    def refill(state: SACState) -> SACState:
        """Fresh envs, an empty buffer re-filled by warmup_steps steps of the current actor."""
        key, k_env, k_warm = jax.random.split(state.key, 3)
        actor, obs_norm, env_state, t, ep_ret, buffer = warmup(state.actor, state.obs_norm,
                                                               k_env, k_warm)
        return state._replace(actor=actor, obs_norm=obs_norm, env_state=env_state, t=t,
                              episode_return=ep_ret, buffer=buffer, key=key)

    return SAC(init, train, refill)


def episode_returns(metrics: dict) -> jax.Array:
    """Mean undiscounted return of the training episodes that ended during the iterations of
    ``train``'s metrics ([..., T] -> [...]; NaN where none ended)."""
    ep = metrics["episodes"].sum(-1)
    return jnp.where(ep > 0, metrics["return_sum"].sum(-1) / jnp.maximum(ep, 1), jnp.nan)
