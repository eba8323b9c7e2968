"""Learning the simulator: RL2S, GAIL, BC and RL2S-BC behind one pure ``train_step``.

``train_step(state, data) -> (state, metrics)`` is a pure function of a ``TrainState`` pytree
(parameters, optimiser states, simulated envs and their buffer, the CVaR selection, per-policy
VD, step counter, key) and the device-resident ``TrainData``. The config is a static field of
the state, so ``jax.jit(train_step)``, ``lax.scan`` over it and ``jax.vmap`` over states built
with different seeds or eps (``eps`` is a state leaf) all work as is.

One step of an adversarial method (rl2s, gail):
  1. the simulated envs advance ``sim_steps`` steps: each runs a selected training policy inside
     p_phi from a real state of that policy (reset when done_fn fires or after ``sim_horizon``
     steps); their (s, a) go into a ring buffer;
  2. ``updates_per_step`` times: ``disc_updates`` Wasserstein critic updates (real (s, a, s') of
     the selected policies vs (s, a) from the buffer with s' from p_phi), then one generator
     update maximising D on real and simulated (s, a), reparameterised through D;
  3. the value measurement advances (see below).
An MLE method (bc, rl2s-bc) replaces 1-2 by ``updates_per_step`` likelihood steps on the
selected policies' data.

CVaR on the device: the value of every training policy in p_phi (``vd_episodes`` episodes of
``vd_horizon`` steps) is measured as a rollout spread over ``vd_every`` calls (ceil(H / K)
steps each), so each step costs the same, also under vmap, where a ``lax.cond`` every K steps
would run both branches. When it completes, VD = |V_true - V_sim| is stored and the worst
max(2, ceil(eps P)) policies become the selection until the next completion. ``init`` measures
the first selection with a full rollout. eps = 1 selects everyone (GAIL, BC).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from rl2s_jax import losses
from rl2s_jax.models import Normalizer, generator_sample, init_discriminator, init_generator
from rl2s_jax.policies import Params, index_params, num_policies, sample_action
from rl2s_jax.simulate import (
    Simulator,
    ValueRollout,
    advance_values,
    data_values,
    simulated_values,
    start_pool,
    start_values,
    value_difference,
)
from rl2s_jax.tasks import TASKS, get_task

METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
DEFAULT_EPS = {"rl2s": 0.25, "gail": 1.0, "bc": 1.0, "rl2s-bc": 0.25}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static settings of a training run (hashable: it is part of the jit cache key).

    Defaults are the official RL2S code's (exp_specs/l2s_hopper.yaml); ``small()`` is a
    CPU-sized variant. ``eps=None`` takes the method's default (0.25 for rl2s and rl2s-bc,
    1 for gail and bc); it is only the initial value of the vmappable ``TrainState.eps``.
    """

    task: str = "hopper"
    method: str = "rl2s"
    eps: float | None = None
    gen_hidden: tuple[int, ...] = (512, 512, 512, 512)
    disc_hidden: tuple[int, ...] = (512, 512, 512, 512)
    batch_size: int = 256
    updates_per_step: int = 50     # generator updates per train_step (a "train call")
    disc_updates: int = 5          # critic updates before each generator update
    gen_lr: float = 1e-4
    disc_lr: float = 1e-4
    disc_beta1: float = 0.5
    bc_lr: float = 1e-4             # 1e-3 and 3e-4 collapsed BC on Hopper (docs/BENCHMARKS.md)
    grad_clip: float = 0.5         # elementwise gradient clip, as the official code
    sim_envs: int = 32             # simulated envs stepping in p_phi (adversarial methods)
    sim_steps: int = 16            # their steps per train_step
    sim_horizon: int = 50          # a simulated env restarts from a real state after this
    buffer_size: int = 8192        # ring buffer of simulated (s, a)
    vd_every: int = 20             # K: calls per VD measurement / CVaR refresh
    vd_episodes: int = 8           # simulated episodes per training policy per measurement
    vd_horizon: int = 1000         # steps per simulated episode (the task's episode length)
    gamma: float = 0.999
    obs_clip: float = 10.0         # simulated states kept within +-obs_clip data stds
    sim_noise: float = 1.0         # std scale of p_phi in simulated rollouts (0: its mean)
    input_ignore_dims: tuple[int, ...] | None = None  # obs dims the networks do not see;
    # None: the task's position_dims (absolute x, y), () for none

    @property
    def adversarial(self) -> bool:
        return self.method in ("rl2s", "gail")

    @property
    def ignore_dims(self) -> tuple[int, ...]:
        if self.input_ignore_dims is not None:
            return tuple(self.input_ignore_dims)
        return get_task(self.task).position_dims if self.task in TASKS else ()

    @property
    def initial_eps(self) -> float:
        return DEFAULT_EPS[self.method] if self.eps is None else float(self.eps)

    @classmethod
    def small(cls, **overrides) -> TrainConfig:
        """A CPU-sized config: 2x64 networks, short value rollouts, few updates per step."""
        base = dict(gen_hidden=(64, 64), disc_hidden=(64, 64), batch_size=64,
                    updates_per_step=5, disc_updates=2, sim_envs=16, sim_steps=4,
                    buffer_size=1024, vd_every=5, vd_episodes=4, vd_horizon=100,
                    gen_lr=1e-3, disc_lr=1e-3, bc_lr=1e-3)
        base.update(overrides)
        return cls(**base)

    def validate(self) -> TrainConfig:
        """Raise ValueError naming the first bad field; returns self."""
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0.0 < self.initial_eps <= 1.0:
            raise ValueError(f"eps: expected a float in (0, 1], got {self.eps!r}")
        for name in ("batch_size", "updates_per_step", "disc_updates", "sim_envs", "sim_steps",
                     "sim_horizon", "buffer_size", "vd_episodes", "vd_horizon"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        if not isinstance(self.vd_every, int) or self.vd_every < 0:
            raise ValueError(f"vd_every: expected an int >= 0 (0 = no VD), got {self.vd_every!r}")
        if self.vd_every == 0 and self.initial_eps < 1.0:
            raise ValueError(f"vd_every: 0 turns off VD, which method {self.method!r} with eps "
                             f"{self.initial_eps} needs to choose its worst policies")
        for name in ("gen_hidden", "disc_hidden"):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and v and all(isinstance(h, int) and h > 0 for h in v)):
                raise ValueError(f"{name}: expected a non-empty tuple of positive ints, got {v!r}")
        for name in ("gen_lr", "disc_lr", "bc_lr", "grad_clip", "obs_clip"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite float, got {v!r}")
        if not (isinstance(self.sim_noise, (int, float)) and math.isfinite(self.sim_noise)
                and self.sim_noise >= 0):
            raise ValueError(f"sim_noise: expected a finite float >= 0, got {self.sim_noise!r}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma: expected a float in (0, 1], got {self.gamma!r}")
        if self.adversarial and self.buffer_size < self.batch_size:
            raise ValueError(f"buffer_size: expected >= batch_size ({self.batch_size}), "
                             f"got {self.buffer_size}")
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"config: unknown field(s) {unknown}")
        d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**d)


@struct.dataclass
class TrainData:
    """The training data on the device, rows grouped by policy.

    obs [N, o], action [N, a], next_obs [N, o]; policy_start, policy_count [P] (policy p owns
    rows policy_start[p] : policy_start[p] + policy_count[p]); start_pool [S, o] real episode
    start states; true_value [P] discounted value over vd_horizon steps (NaN = unknown);
    policies: the P training policies, stacked; norm: the data's Normalizer.
    """

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    policy_start: jax.Array
    policy_count: jax.Array
    start_pool: jax.Array
    true_value: jax.Array
    policies: Params
    norm: Normalizer

    @property
    def n_policies(self) -> int:
        return int(self.policy_start.shape[0])


def _measured_values_apply(ds, horizon: int, gamma: float) -> bool:
    """Whether the Dataset's measured values are the true values for this horizon and gamma:
    it has them, the horizon covers whole episodes and gamma matches."""
    meta = ds.meta
    full = meta.get("episode_length") is not None and horizon >= meta["episode_length"]
    return bool(ds.has_values and full and abs(float(meta.get("gamma") or 0) - gamma) < 1e-9)


def true_values_se(ds, horizon: int, gamma: float) -> np.ndarray | None:
    """Standard errors [P] of ``true_values`` where the data measured them, else None."""
    if _measured_values_apply(ds, horizon, gamma):
        return np.asarray(ds.value_discounted_se, np.float64)
    return None


def true_values(ds, horizon: int, gamma: float, strict: bool = True) -> np.ndarray:
    """True discounted value [P] of each policy of ``ds`` over ``horizon`` steps.

    The Dataset's measured ``value_discounted`` when the horizon covers the whole episode and
    gamma matches; otherwise the logged episodes' discounted return over the first ``horizon``
    steps (``simulate.data_values``). ``strict``: a policy without a usable episode is an error
    (else NaN).
    """
    if _measured_values_apply(ds, horizon, gamma):
        return np.asarray(ds.value_discounted, np.float32)
    ended = np.asarray(ds.done) | np.asarray(ds.truncated)
    values, _ = data_values(np.asarray(ds.reward), ended, np.asarray(ds.policy_id),
                            np.asarray(ds.episode_id), np.asarray(ds.t), ds.n_policies,
                            horizon=horizon, gamma=gamma)
    if strict and np.isnan(values).any():
        bad = int(np.flatnonzero(np.isnan(values))[0])
        raise ValueError(
            f"vd_horizon: policy {bad} has no logged episode that starts at t = 0 and is "
            f"seen for {horizon} steps (or to its end), so its true value over that horizon "
            f"is unknown; lower vd_horizon or collect whole episodes")
    return values.astype(np.float32)


def make_train_data(ds, policies: Params, config: TrainConfig) -> TrainData:
    """TrainData from a Dataset and its P stacked policies (policy i of ``policies`` collected
    the rows with policy_id i).

    The true values: the Dataset's measured discounted values when vd_horizon covers the whole
    episode and gamma matches; otherwise the logged episodes' discounted return over the first
    vd_horizon steps.
    """
    P = ds.n_policies
    if num_policies(policies) != P:
        raise ValueError(f"policies: expected {P} stacked policies (the Dataset's n_policies), "
                         f"got {num_policies(policies)}")
    pid = np.asarray(ds.policy_id)
    counts = np.bincount(pid, minlength=P)
    if (counts == 0).any():
        raise ValueError(f"policy_id: expected rows for every policy, none for policy "
                         f"{int(np.flatnonzero(counts == 0)[0])}")
    order = np.argsort(pid, kind="stable")
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    true_value = true_values(ds, config.vd_horizon, config.gamma, strict=bool(config.vd_every))
    f32 = lambda x: jnp.asarray(np.asarray(x)[order], jnp.float32)
    return TrainData(obs=f32(ds.obs), action=f32(ds.action), next_obs=f32(ds.next_obs),
                     policy_start=jnp.asarray(starts, jnp.int32),
                     policy_count=jnp.asarray(counts, jnp.int32),
                     start_pool=start_pool(ds),
                     true_value=jnp.asarray(true_value, jnp.float32),
                     policies=jax.tree_util.tree_map(jnp.asarray, policies),
                     norm=Normalizer.from_data(ds.obs, ds.action, ds.next_obs,
                                               ignore_dims=config.ignore_dims))


@struct.dataclass
class SimEnvs:
    """E simulated envs: obs [E, o], policy [E] int32, t [E] int32 steps since reset."""

    obs: jax.Array
    policy: jax.Array
    t: jax.Array


@struct.dataclass
class TrainState:
    step: jax.Array               # [] int32 train_steps taken
    key: jax.Array
    eps: jax.Array                # [] float32 CVaR fraction (vmappable)
    norm: Normalizer
    gen: Params
    gen_opt: Any
    disc: Params | None           # None for bc / rl2s-bc
    disc_us: Any
    disc_opt: Any
    sim: SimEnvs | None
    buffer_obs: jax.Array | None  # [B, o] simulated states
    buffer_act: jax.Array | None  # [B, a] the policies' actions in them
    buffer_pos: jax.Array | None  # [] int32 next ring-buffer row
    vd: jax.Array                 # [P] last measured VD (NaN before the first measurement)
    sim_value: jax.Array          # [P] last measured value in p_phi
    sim_length: jax.Array         # [P] mean simulated episode length of that measurement
    selected: jax.Array           # [P] bool: the policies the generator trains on
    vd_roll: ValueRollout | None  # the measurement in progress
    config: TrainConfig = struct.field(pytree_node=False)


# ------------------------------------------------------------------ CVaR selection


def n_worst(eps: jax.Array | float, n_policies: int) -> jax.Array:
    """max(2, ceil(eps * P)) capped at P. A slack of a few float32 ulps keeps rounding error
    from rounding up (0.15 * 20 is 3, not 4; 0.6 * 205 is 123). -> [] int32"""
    x = jnp.asarray(eps, jnp.float32) * n_policies
    k = jnp.ceil(x - 3e-7 * jnp.maximum(x, 1.0)).astype(jnp.int32)
    return jnp.minimum(jnp.maximum(k, 2), n_policies)


def select_worst(vd: jax.Array, n_select: jax.Array) -> jax.Array:
    """Mask [P] of the n_select largest VDs; ties go to the lower index; NaN counts as worst."""
    vd = jnp.where(jnp.isnan(vd), jnp.inf, vd)
    order = jnp.argsort(-vd, stable=True)
    rank = jnp.zeros_like(order).at[order].set(jnp.arange(vd.shape[0], dtype=order.dtype))
    return rank < n_select


# ------------------------------------------------------------------ sampling


def _sample_rows(key: jax.Array, data: TrainData, selected: jax.Array, n: int) -> jax.Array:
    """Row indices [n]: a policy uniformly among the selected, then one of its rows uniformly."""
    k_pol, k_row = jax.random.split(key)
    logits = jnp.where(selected, 0.0, -jnp.inf)
    pol = jax.random.categorical(k_pol, logits, shape=(n,))
    count = data.policy_count[pol]
    off = jnp.floor(jax.random.uniform(k_row, (n,)) * count).astype(jnp.int32)
    return data.policy_start[pol] + jnp.minimum(off, count - 1), pol


def _real_batch(key, data: TrainData, selected, n):
    rows, _ = _sample_rows(key, data, selected, n)
    return data.obs[rows], data.action[rows], data.next_obs[rows]


def _simulator(gen, norm: Normalizer, cfg: TrainConfig) -> Simulator:
    """p_phi as rollouts use it (no gradient into the generator)."""
    return Simulator(gen=jax.lax.stop_gradient(gen), norm=norm, task=cfg.task,
                     obs_clip=cfg.obs_clip, noise_scale=cfg.sim_noise)


# ------------------------------------------------------------------ init


def _optimizers(cfg: TrainConfig):
    gen = optax.chain(optax.clip(cfg.grad_clip),
                      optax.adam(cfg.gen_lr if cfg.adversarial else cfg.bc_lr))
    disc = optax.chain(optax.clip(cfg.grad_clip), optax.adam(cfg.disc_lr, b1=cfg.disc_beta1))
    return gen, disc


def init(key: jax.Array, config: TrainConfig, data: TrainData,
         eps: float | jax.Array | None = None) -> TrainState:
    """A fresh TrainState; measures every training policy's VD once for the first selection.

    Pure and jittable (``config`` static): vmap it over keys (and eps) for seeds / sweeps.
    """
    cfg = config.validate()
    norm = data.norm
    P = data.n_policies
    obs_size, act_size = data.obs.shape[1], data.action.shape[1]
    k_gen, k_disc, k_sim, k_buf, k_vd, k_roll, key = jax.random.split(key, 7)
    gen = init_generator(k_gen, obs_size, act_size, cfg.gen_hidden)
    gen_tx, disc_tx = _optimizers(cfg)
    eps = jnp.asarray(cfg.initial_eps if eps is None else eps, jnp.float32)
    everyone = jnp.ones((P,), bool)
    nan = jnp.full((P,), jnp.nan, jnp.float32)
    vd, sim_value, sim_length, vd_roll = nan, nan, nan, None
    selected = everyone
    if cfg.vd_every:
        task = get_task(cfg.task)
        sim_value, sim_length = simulated_values(
            data.policies, _simulator(gen, norm, cfg).dynamics, task.reward_fn, task.done_fn,
            data.start_pool, k_vd, n_episodes=cfg.vd_episodes, horizon=cfg.vd_horizon,
            gamma=cfg.gamma)
        vd = value_difference(sim_value, data.true_value)
        selected = select_worst(vd, n_worst(eps, P))
        vd_roll = start_values(data.start_pool, P, cfg.vd_episodes, k_roll)
    disc = disc_us = disc_opt = sim = buf_obs = buf_act = buf_pos = None
    if cfg.adversarial:
        disc, disc_us = init_discriminator(k_disc, obs_size, act_size, cfg.disc_hidden)
        disc_opt = disc_tx.init(disc)
        sim = _reset_sim(SimEnvs(obs=jnp.zeros((cfg.sim_envs, obs_size)),
                                 policy=jnp.zeros((cfg.sim_envs,), jnp.int32),
                                 t=jnp.zeros((cfg.sim_envs,), jnp.int32)),
                         jnp.ones((cfg.sim_envs,), bool), data, selected, k_sim)
        # The buffer starts with real (s, a) of the selected policies; simulated ones replace
        # them within buffer_size / (sim_envs * sim_steps) steps.
        rows, _ = _sample_rows(k_buf, data, selected, cfg.buffer_size)
        buf_obs, buf_act = data.obs[rows], data.action[rows]
        buf_pos = jnp.zeros((), jnp.int32)
    return TrainState(step=jnp.zeros((), jnp.int32), key=key, eps=eps, norm=norm, gen=gen,
                      gen_opt=gen_tx.init(gen), disc=disc, disc_us=disc_us, disc_opt=disc_opt,
                      sim=sim, buffer_obs=buf_obs, buffer_act=buf_act, buffer_pos=buf_pos,
                      vd=vd, sim_value=sim_value, sim_length=sim_length, selected=selected,
                      vd_roll=vd_roll, config=cfg)


# ------------------------------------------------------------------ the step


def _reset_sim(sim: SimEnvs, reset: jax.Array, data: TrainData, selected, key) -> SimEnvs:
    rows, pol = _sample_rows(key, data, selected, sim.obs.shape[0])
    return SimEnvs(obs=jnp.where(reset[:, None], data.obs[rows], sim.obs),
                   policy=jnp.where(reset, pol.astype(jnp.int32), sim.policy),
                   t=jnp.where(reset, 0, sim.t))


def _advance_sim(state: TrainState, data: TrainData, key):
    """Step the simulated envs sim_steps times in p_phi; write their (s, a) to the buffer."""
    cfg = state.config
    task = get_task(cfg.task)
    dynamics = _simulator(state.gen, state.norm, cfg).dynamics
    E, B = cfg.sim_envs, cfg.buffer_size
    act = jax.vmap(sample_action)

    def step(carry, key):
        sim, buf_obs, buf_act, pos = carry
        k_act, k_dyn, k_reset = jax.random.split(key, 3)
        action, _, _ = act(index_params(data.policies, sim.policy), sim.obs,
                           jax.random.split(k_act, E))
        next_obs = dynamics(sim.obs, action, k_dyn)
        rows = (pos + jnp.arange(E)) % B
        buf_obs, buf_act = buf_obs.at[rows].set(sim.obs), buf_act.at[rows].set(action)
        t = sim.t + 1
        reset = (task.done_fn(next_obs) > 0.5) | (t >= cfg.sim_horizon)
        sim = _reset_sim(SimEnvs(next_obs, sim.policy, t), reset, data, state.selected, k_reset)
        return (sim, buf_obs, buf_act, (pos + E) % B), reset.mean()

    carry = (state.sim, state.buffer_obs, state.buffer_act, state.buffer_pos)
    carry, reset_rate = jax.lax.scan(step, carry, jax.random.split(key, cfg.sim_steps))
    sim, buf_obs, buf_act, pos = carry
    return state.replace(sim=sim, buffer_obs=buf_obs, buffer_act=buf_act, buffer_pos=pos), {
        "sim_reset_rate": reset_rate.mean()}


def _adversarial_updates(state: TrainState, data: TrainData, key):
    cfg = state.config
    gen_tx, disc_tx = _optimizers(cfg)
    n = cfg.batch_size

    def fake_sa(key):
        rows = jax.random.randint(key, (n,), 0, cfg.buffer_size)
        return state.buffer_obs[rows], state.buffer_act[rows]

    def disc_update(carry, key):
        gen, disc, us, opt = carry
        k_real, k_fake, k_gen = jax.random.split(key, 3)
        real = _real_batch(k_real, data, state.selected, n)
        f_obs, f_act = fake_sa(k_fake)
        f_next = generator_sample(jax.lax.stop_gradient(gen), state.norm, f_obs, f_act, k_gen,
                                  cfg.obs_clip)
        (loss, (us, aux)), grads = jax.value_and_grad(losses.discriminator_loss, has_aux=True)(
            disc, us, state.norm, real, (f_obs, f_act, f_next))
        updates, opt = disc_tx.update(grads, opt, disc)
        return (gen, optax.apply_updates(disc, updates), us, opt), {"disc_loss": loss, **aux}

    def loop(carry, key):
        gen, gen_opt, disc, us, disc_opt = carry
        k_disc, k_real, k_fake, k_gen = jax.random.split(key, 4)
        (_, disc, us, disc_opt), d_metrics = jax.lax.scan(
            disc_update, (gen, disc, us, disc_opt), jax.random.split(k_disc, cfg.disc_updates))
        r_obs, r_act, _ = _real_batch(k_real, data, state.selected, n)
        f_obs, f_act = fake_sa(k_fake)
        obs, act = jnp.concatenate([r_obs, f_obs]), jnp.concatenate([r_act, f_act])
        loss, grads = jax.value_and_grad(
            lambda g: losses.generator_adversarial_loss(g, disc, us, state.norm, obs, act,
                                                        k_gen)[0])(gen)
        updates, gen_opt = gen_tx.update(grads, gen_opt, gen)
        gen = optax.apply_updates(gen, updates)
        metrics = jax.tree_util.tree_map(lambda x: x[-1], d_metrics)
        return (gen, gen_opt, disc, us, disc_opt), {"gen_loss": loss, **metrics}

    carry = (state.gen, state.gen_opt, state.disc, state.disc_us, state.disc_opt)
    carry, metrics = jax.lax.scan(loop, carry, jax.random.split(key, cfg.updates_per_step))
    gen, gen_opt, disc, us, disc_opt = carry
    state = state.replace(gen=gen, gen_opt=gen_opt, disc=disc, disc_us=us, disc_opt=disc_opt)
    return state, jax.tree_util.tree_map(jnp.mean, metrics)


def _mle_updates(state: TrainState, data: TrainData, key):
    cfg = state.config
    gen_tx, _ = _optimizers(cfg)

    def update(carry, key):
        gen, opt = carry
        batch = _real_batch(key, data, state.selected, cfg.batch_size)
        loss, grads = jax.value_and_grad(
            lambda g: losses.generator_nll_loss(g, state.norm, *batch)[0])(gen)
        updates, opt = gen_tx.update(grads, opt, gen)
        return (optax.apply_updates(gen, updates), opt), {"nll": loss}

    (gen, opt), metrics = jax.lax.scan(update, (state.gen, state.gen_opt),
                                       jax.random.split(key, cfg.updates_per_step))
    return state.replace(gen=gen, gen_opt=opt), jax.tree_util.tree_map(jnp.mean, metrics)


def _advance_vd(state: TrainState, data: TrainData, key):
    """Advance the spread-out value measurement; on completion refresh VD and the selection."""
    cfg = state.config
    task = get_task(cfg.task)
    H, K = cfg.vd_horizon, cfg.vd_every
    k_run, k_restart = jax.random.split(key)
    roll = advance_values(state.vd_roll, data.policies,
                          _simulator(state.gen, state.norm, cfg).dynamics, task.reward_fn,
                          task.done_fn, k_run, n_steps=-(-H // K), horizon=H, gamma=cfg.gamma)
    done = roll.t >= H
    sim_value = roll.ret.mean(1)
    vd = value_difference(sim_value, data.true_value)
    fresh = start_values(data.start_pool, data.n_policies, cfg.vd_episodes, k_restart)
    pick = lambda new, old: jnp.where(done, new, old)
    return state.replace(
        vd=pick(vd, state.vd), sim_value=pick(sim_value, state.sim_value),
        sim_length=pick(roll.length.mean(1).astype(jnp.float32), state.sim_length),
        selected=pick(select_worst(vd, n_worst(state.eps, data.n_policies)), state.selected),
        vd_roll=jax.tree_util.tree_map(pick, fresh, roll)), done


def train_step(state: TrainState, data: TrainData) -> tuple[TrainState, dict]:
    """One training call. -> (new state, metrics: dict of scalars).

    Metrics: the losses of the method, ``avd_train`` / ``mvd_train`` (mean / max VD of the
    training policies at the last completed measurement), ``n_selected``, ``vd_refreshed``
    and ``finite`` (every loss and parameter finite after this step).
    """
    cfg = state.config
    key, k_sim, k_upd, k_vd = jax.random.split(state.key, 4)
    metrics = {}
    if cfg.adversarial:
        state, m = _advance_sim(state, data, k_sim)
        metrics.update(m)
        state, m = _adversarial_updates(state, data, k_upd)
    else:
        state, m = _mle_updates(state, data, k_upd)
    metrics.update(m)
    refreshed = jnp.bool_(False)
    if cfg.vd_every:
        state, refreshed = _advance_vd(state, data, k_vd)
    params = (state.gen, state.disc)
    finite = {f"finite/{k}": jnp.isfinite(v) for k, v in metrics.items()}
    finite["finite/params"] = losses.tree_all_finite(params)
    metrics.update(
        avd_train=jnp.mean(state.vd), mvd_train=jnp.max(state.vd),
        n_selected=jnp.sum(state.selected).astype(jnp.int32), vd_refreshed=refreshed,
        finite=jnp.all(jnp.stack(list(finite.values()))), **finite)
    return state.replace(step=state.step + 1, key=key), metrics


def train_steps(state: TrainState, data: TrainData, n_steps: int) -> tuple[TrainState, dict]:
    """``n_steps`` train_steps as one lax.scan. -> (state, metrics stacked [n_steps])."""
    return jax.lax.scan(lambda s, _: train_step(s, data), state, None, length=n_steps)


def simulator(state: TrainState) -> Simulator:
    """The learned simulator of a training state (generator + normaliser)."""
    return _simulator(state.gen, state.norm, state.config)
