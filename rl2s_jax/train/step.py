"""Learning the simulator: RL2S, GAIL, BC and RL2S-BC behind one pure ``train_step``.

``train_step(state, data) -> (state, metrics)`` is a pure function of a ``TrainState`` pytree
(the generator ensemble, optimiser states, simulated envs and their buffer, the CVaR selection,
per-policy VD, the members' held-out scores, step counter, key) and the device-resident
``TrainData``. The config is a static field of the state, so ``jax.jit(train_step)``,
``lax.scan`` over it and ``jax.vmap`` over states built with different seeds or eps (``eps``
is a state leaf) all work as is.

The generator is an ensemble of E members of the dynamics-model family
(``rl2s_jax.model.dynamics``),
trained as one vmapped program; each member draws its own batches.

One step of an MLE method (bc, rl2s-bc), and of the pre-training phase of an adversarial one
(its first ``pretrain_steps`` steps, on every policy):
  1. ``updates_per_step`` likelihood updates of every member on rows of the selected policies;
  2. every member's NLL on the held-out episodes (whole episodes of every training policy that
     training never sees): early stopping (a member that has not gained ``min_delta`` for
     ``patience`` steps goes back to its best weights and stops) and the elites (the
     ``n_elites`` lowest).
One step of the adversarial phase (rl2s, gail), the official code's "train call" (the first one
starts from the pre-trained members: their best weights, fresh Adam moments):
  1. the simulated envs advance ``sim_steps`` steps: each runs a selected training policy inside
     p_phi from a real state of that policy (reset when the episode ends as the config's
     ``termination`` says, or after ``sim_horizon`` steps); their (s, a) go into a ring buffer;
  2. ``updates_per_step`` times: ``disc_updates`` Wasserstein critic updates (real (s, a, s') of
     the selected policies vs (s, a) from the buffer with s' from p_phi), then one update of
     every member maximising D on real and simulated (s, a), reparameterised through D (the
     first ``disc_warmup_steps`` steps train the critic only);
  3. the members' held-out NLL and the elites, as above (no early stopping).
Both then advance the value measurement (below). Rollouts step with a random elite per sample
(``member_mode``). With ``ema_decay``, ``simulator(state)`` (evaluation, checkpoints) is an
exponential moving average of the members' weights; the CVaR value measurement keeps using the
trained weights, so the average changes what is evaluated, never how training runs.

CVaR on the device: the value of every training policy in p_phi (``vd_episodes`` episodes of
``vd_horizon`` steps) is measured as a rollout spread over ``vd_every`` calls (ceil(H / K)
steps each), so each step costs the same, also under vmap, where a ``lax.cond`` every K steps
would run both branches. When it completes, VD = |V_true - V_sim| is stored and the worst
max(2, ceil(eps P)) policies become the selection until the next completion. ``init`` measures
the first selection with a full rollout. eps = 1 selects everyone (GAIL, BC).

The phase of an adversarial method with pre-training is chosen per step on the device
(``lax.cond``), or statically with ``train_step(state, data, phase="pretrain" | "main")``:
callers that know the step on the host (``fit``, experiments/paper.py) pass it, so a vmapped
program runs only the phase's branch.
"""
from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.generator import init_discriminator
from rl2s_jax.model.history import History, member_step_dist, push_history, take_history
from rl2s_jax.model.simulator import (
    Simulator,
    ValueRollout,
    advance_values,
    end_key,
    ends_episode,
    simulated_values,
    start_values,
    value_difference,
)
from rl2s_jax.policy.policy import Params, index_params, sample_action
from rl2s_jax.train import losses
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.cvar import n_worst, select_worst
from rl2s_jax.train.data import (
    TrainData,
    _real_batch_history,
    _real_windows_history,
    _sample_rows,
)
from rl2s_jax.train.learned import fit_learned
from rl2s_jax.train.losses import multistep_error

__all__ = ["TrainState", "init", "member_mle_updates", "simulator",
           "track_best", "train_step", "train_steps"]
ADVERSARIAL_METRICS = ("gen_loss", "disc_loss", "d_real", "d_fake", "sim_reset_rate")


@struct.dataclass
class SimEnvs:
    """E simulated envs: obs [E, o], policy [E] int32, t [E] int32 steps since reset; hist
    [E, ...] their past (None without history inputs)."""

    obs: jax.Array
    policy: jax.Array
    t: jax.Array
    hist: History | None = None


@struct.dataclass
class TrainState:
    step: jax.Array               # [] int32 train_steps taken
    key: jax.Array
    eps: jax.Array                # [] float32 CVaR fraction (vmappable)
    norm: Normalizer
    gen: Params                   # the members, stacked [E, ...] (dynamics.init_ensemble)
    gen_opt: Any                  # their optimiser states, stacked [E, ...]
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
    heldout_nll: jax.Array        # [E] members' held-out NLL (a stopped member: its best)
    rank: jax.Array               # [E] int32 members by heldout_nll (0 = lowest)
    best_nll: jax.Array           # [E] lowest held-out NLL of the MLE steps (inf: none yet)
    since_best: jax.Array         # [E] int32 MLE steps since best_nll last fell
    stopped: jax.Array            # [E] bool: early-stopped (frozen at its best weights)
    best_gen: Params | None       # [E, ...] weights at best_nll (None: early stopping off)
    ema_gen: Params | None        # [E, ...] moving average of gen (None: ema_decay = 0)
    hazard: Params | None         # learned termination classifier (None: termination "rule")
    config: TrainConfig = struct.field(pytree_node=False)
    buffer_hist: History | None = None  # [B, ...] the buffered states' past (history inputs)
    reward: Params | None = None  # learned reward head (None: the task's reward_fn)


# ------------------------------------------------------------------ models and optimisers


def _sampler(gen, state: TrainState, noise_scale: float) -> Simulator:
    """The members as rollouts use them (no gradient into the generator)."""
    cfg = state.config
    return Simulator(gen=jax.lax.stop_gradient(gen), norm=state.norm, rank=state.rank,
                     hazard=state.hazard, reward=state.reward,
                     **cfg.simulator_settings(noise_scale))


def _clip_adam(cfg: TrainConfig, adam: optax.GradientTransformation) -> list:
    """[elementwise clip, adam], or both as one over a flat vector of the parameters
    (``optax.flatten``) where ``cfg.flat_optimizer``."""
    if cfg.flat_optimizer:
        return [optax.flatten(optax.chain(optax.clip(cfg.grad_clip), adam))]
    return [optax.clip(cfg.grad_clip), adam]


def _gen_tx(cfg: TrainConfig, lr: float) -> optax.GradientTransformation:
    """One member's optimiser: L2 on its weight matrices (gen_weight_decay), elementwise clip,
    Adam. Both phases share its state layout. (The decay's mask needs the parameters' tree:
    it stays outside the flat part.)"""
    decay = ([optax.add_decayed_weights(cfg.gen_weight_decay, mask=dyn.weight_mask)]
             if cfg.gen_weight_decay else [])
    return optax.chain(*decay, *_clip_adam(cfg, optax.adam(lr)))


def _disc_tx(cfg: TrainConfig) -> optax.GradientTransformation:
    adv = cfg.adversarial
    return optax.chain(*_clip_adam(cfg, optax.adam(adv.disc_lr, b1=adv.disc_beta1)))


def _tree_where(cond, new, old):
    """Per-row choice: cond [E] (or [], or [E] envs) selects new over old leaf by leaf."""
    def pick(n, o):
        c = jnp.reshape(cond, jnp.shape(cond) + (1,) * (jnp.ndim(n) - jnp.ndim(cond)))
        return jnp.where(c, n, o)
    return jax.tree_util.tree_map(pick, new, old)


def _heldout_nll(gen, norm: Normalizer, data: TrainData) -> jax.Array:
    """Every member's mean NLL [E] on the held-out rows (NaN without any)."""
    if data.n_heldout == 0:
        return jnp.full((dyn.n_members(gen),), jnp.nan, jnp.float32)
    y = norm.norm_delta(data.val_obs, data.val_next_obs)
    return dyn.map_members(lambda p: jnp.mean(dyn.gaussian_nll(*member_step_dist(
        p, norm, data.val_obs, data.val_action, data.val_hist), y)), gen)


# ------------------------------------------------------------------ init


def init(key: jax.Array, config: TrainConfig, data: TrainData,
         eps: float | jax.Array | None = None) -> TrainState:
    """A fresh TrainState; measures every training policy's VD once for the first selection.

    Pure and jittable (``config`` static): vmap it over keys (and eps) for seeds / sweeps.
    """
    cfg = config.validate()
    norm = data.norm
    P = data.n_policies
    E = cfg.ensemble_size
    obs_size, act_size = data.obs.shape[1], data.action.shape[1]
    # keys folded from the key apart from the split: other draws stay as they were
    hazard, reward = fit_learned(key, cfg, data, norm)
    k_gen, k_disc, k_sim, k_buf, k_vd, k_roll, key = jax.random.split(key, 7)
    gen = dyn.init_ensemble(k_gen, cfg.dynamics, obs_size, act_size, E)
    heldout = _heldout_nll(gen, norm, data)
    rank = dyn.rank_members(heldout)
    eps = jnp.asarray(cfg.initial_eps if eps is None else eps, jnp.float32)
    everyone = jnp.ones((P,), bool)
    nan = jnp.full((P,), jnp.nan, jnp.float32)
    vd, sim_value, sim_length, vd_roll = nan, nan, nan, None
    selected = everyone
    state = TrainState(
        step=jnp.zeros((), jnp.int32), key=key, eps=eps, norm=norm, gen=gen,
        gen_opt=dyn.map_members(_gen_tx(cfg, cfg.bc_lr).init, gen), disc=None, disc_us=None,
        disc_opt=None, sim=None, buffer_obs=None, buffer_act=None, buffer_pos=None, vd=vd,
        sim_value=sim_value, sim_length=sim_length, selected=selected, vd_roll=vd_roll,
        heldout_nll=heldout, rank=rank, best_nll=jnp.full((E,), jnp.inf, jnp.float32),
        since_best=jnp.zeros((E,), jnp.int32), stopped=jnp.zeros((E,), bool),
        best_gen=gen if cfg.early_stopping else None,
        ema_gen=gen if cfg.ema_decay else None, hazard=hazard, reward=reward, config=cfg)
    if cfg.vd.every:
        sim = _sampler(gen, state, cfg.sim_noise)
        task = sim.task_fns()
        done_fn, hazard_fn = sim.terminations(task.done_fn)
        sim_value, sim_length = simulated_values(
            data.policies, sim.dynamics, task.reward_fn, done_fn, data.start_pool, k_vd,
            n_episodes=cfg.vd.episodes, horizon=cfg.vd.horizon, gamma=cfg.gamma,
            hazard_fn=hazard_fn, new_history=sim.new_history)
        vd = value_difference(sim_value, data.true_value)
        selected = select_worst(vd, n_worst(eps, P))
        vd_roll = start_values(data.start_pool, P, cfg.vd.episodes, k_roll, sim.new_history)
    state = state.replace(vd=vd, sim_value=sim_value, sim_length=sim_length, selected=selected,
                          vd_roll=vd_roll)
    if cfg.is_adversarial:
        disc, disc_us = init_discriminator(k_disc, obs_size, act_size, cfg.adversarial.disc_hidden)
        sampler = _sampler(gen, state, cfg.sim_noise)
        sim = _reset_sim(SimEnvs(obs=jnp.zeros((cfg.adversarial.sim_envs, obs_size)),
                                 policy=jnp.zeros((cfg.adversarial.sim_envs,), jnp.int32),
                                 t=jnp.zeros((cfg.adversarial.sim_envs,), jnp.int32),
                                 hist=sampler.new_history((cfg.adversarial.sim_envs,))),
                         jnp.ones((cfg.adversarial.sim_envs,), bool), data, selected, k_sim)
        # The buffer starts with real (s, a) of the selected policies; simulated ones replace
        # them within buffer_size / (sim_envs * sim_steps) steps.
        rows, _ = _sample_rows(k_buf, data, selected, cfg.adversarial.buffer_size)
        state = state.replace(disc=disc, disc_us=disc_us, disc_opt=_disc_tx(cfg).init(disc),
                              sim=sim, buffer_obs=data.obs[rows], buffer_act=data.action[rows],
                              buffer_pos=jnp.zeros((), jnp.int32),
                              buffer_hist=data.row_history(rows))
    return state


# ------------------------------------------------------------------ likelihood steps


def member_mle_updates(gen, opt, key: jax.Array, data: TrainData, selected: jax.Array,
                       norm: Normalizer, config: TrainConfig):
    """``updates_per_step`` likelihood updates of ONE member (params and optimiser state
    without the member axis) on batches of the selected policies' rows drawn with ``key``.
    -> (params, optimiser state, mean batch loss). The ensemble step is this, vmapped over
    the members with their keys ``dynamics.member_keys``."""
    cfg = config
    tx = _gen_tx(cfg, cfg.bc_lr)
    learned = cfg.dynamics.log_std_bounds == "learned"

    k = cfg.multistep_steps

    def loss_fn(g, batch):
        if k > 1:
            obs, action, next_obs, valid, hist = batch
            loss = losses.generator_beta_nll_loss(g, norm, obs, action[:, 0], next_obs[:, 0],
                                                  cfg.nll_beta, hist)[0]
            loss = loss + cfg.multistep_weight * multistep_error(
                g, norm, obs, action, next_obs, valid, cfg.obs_clip, hist)
        else:
            obs, action, next_obs, hist = batch
            loss = losses.generator_beta_nll_loss(g, norm, obs, action, next_obs,
                                                  cfg.nll_beta, hist)[0]
        return loss + cfg.log_std_bound_weight * dyn.bound_penalty(g) if learned else loss

    def draw(key):
        return (_real_windows_history(key, data, selected, cfg.batch_size, k) if k > 1
                else _real_batch_history(key, data, selected, cfg.batch_size))

    def update(carry, x):  # x: the update's key, or its batch (batches_up_front)
        gen, opt = carry
        batch = x if cfg.batches_up_front else draw(x)
        loss, grads = jax.value_and_grad(loss_fn)(gen, batch)
        updates, opt = tx.update(grads, opt, gen)
        return (optax.apply_updates(gen, updates), opt), loss

    keys = jax.random.split(key, cfg.updates_per_step)
    (gen, opt), batch_loss = jax.lax.scan(
        update, (gen, opt), jax.vmap(draw)(keys) if cfg.batches_up_front else keys,
        unroll=cfg.scan_unroll)
    return gen, opt, batch_loss.mean()


def track_best(nll: jax.Array, best: jax.Array, since: jax.Array, stopped: jax.Array, *,
               min_delta: float, patience: int):
    """One MLE step of the early-stopping bookkeeping, per member [E].

    improved = not stopped and nll < best - min_delta (NaN never improves); best and since
    (steps without improvement) follow; stop_now = not stopped and since >= patience (never
    for patience 0). -> (improved, best, since, stop_now)."""
    active = ~stopped
    improved = active & (nll < best - min_delta)
    best = jnp.where(improved, nll, best)
    since = jnp.where(improved, 0, since + active.astype(jnp.int32))
    stop_now = active & (since >= patience) if patience else jnp.zeros_like(stopped)
    return improved, best, since, stop_now


def _score_members(state: TrainState, data: TrainData, mle: bool) -> TrainState:
    """The members' held-out NLL and ranks; in an MLE step also the early-stopping bookkeeping
    (best NLL and weights, steps since; a stopping member gets its best weights back and
    stays frozen)."""
    if data.n_heldout == 0:
        return state
    cfg = state.config
    nll = _heldout_nll(state.gen, state.norm, data)
    gen, best_gen, stopped = state.gen, state.best_gen, state.stopped
    best, since = state.best_nll, state.since_best
    if mle:
        improved, best, since, stop_now = track_best(
            nll, best, since, stopped, min_delta=cfg.early_stop_min_delta,
            patience=cfg.early_stop_patience)
        if cfg.early_stopping:
            best_gen = _tree_where(improved, gen, best_gen)
            gen = _tree_where(stop_now, best_gen, gen)
            stopped = stopped | stop_now
            nll = jnp.where(stopped, best, nll)
    return state.replace(gen=gen, best_gen=best_gen, stopped=stopped, best_nll=best,
                         since_best=since, heldout_nll=nll, rank=dyn.rank_members(nll))


def _update_ema(state: TrainState) -> TrainState:
    d = state.config.ema_decay
    if not d:
        return state
    return state.replace(ema_gen=jax.tree_util.tree_map(lambda e, g: d * e + (1.0 - d) * g,
                                                        state.ema_gen, state.gen))


def _mle_step(state: TrainState, data: TrainData, key, selected):
    cfg = state.config
    keys = dyn.member_keys(key, cfg.ensemble_size)
    gen, opt, nll = dyn.map_members(
        lambda g, o, k: member_mle_updates(g, o, k, data, selected, state.norm, cfg),
        state.gen, state.gen_opt, keys)
    if cfg.early_stopping:  # stopped members keep their (best) weights
        gen, opt = _tree_where(state.stopped, (state.gen, state.gen_opt), (gen, opt))
    state = _score_members(state.replace(gen=gen, gen_opt=opt), data, mle=True)
    return _update_ema(state), {"nll": jnp.mean(nll)}


# ------------------------------------------------------------------ adversarial steps


def _reset_sim(sim: SimEnvs, reset: jax.Array, data: TrainData, selected, key) -> SimEnvs:
    """Restart the envs where ``reset`` [E] from real states of the selected policies; with
    history inputs an env restarts with the logged past of its real state's row."""
    rows, pol = _sample_rows(key, data, selected, sim.obs.shape[0])
    hist = None if sim.hist is None else _tree_where(reset, data.row_history(rows), sim.hist)
    return SimEnvs(obs=jnp.where(reset[:, None], data.obs[rows], sim.obs),
                   policy=jnp.where(reset, pol.astype(jnp.int32), sim.policy),
                   t=jnp.where(reset, 0, sim.t), hist=hist)


def _advance_sim(state: TrainState, data: TrainData, key):
    """Step the simulated envs sim_steps times in p_phi; write their (s, a) to the buffer."""
    cfg = state.config
    sampler = _sampler(state.gen, state, cfg.sim_noise)
    sim_step = sampler.step
    # the simulated envs end as the value rollouts do (rule, learned hazard or both)
    done_fn, hazard_fn = sampler.terminations(sampler.task_fns().done_fn)
    E, B = cfg.adversarial.sim_envs, cfg.adversarial.buffer_size
    act = jax.vmap(sample_action)

    def step(carry, key):
        sim, buf_obs, buf_act, buf_hist, pos = carry
        k_act, k_dyn, k_reset = jax.random.split(key, 3)
        action, _, _ = act(index_params(data.policies, sim.policy), sim.obs,
                           jax.random.split(k_act, E))
        k_dyn, k_end = end_key(k_dyn, hazard_fn)
        next_obs, u = sim_step(sim.obs, action, k_dyn, sim.hist)
        hist = None if sim.hist is None else push_history(sim.hist, sim.obs, action)
        rows = (pos + jnp.arange(E)) % B
        buf_obs, buf_act = buf_obs.at[rows].set(sim.obs), buf_act.at[rows].set(action)
        if buf_hist is not None:
            buf_hist = jax.tree_util.tree_map(lambda b, x: b.at[rows].set(x), buf_hist,
                                              sim.hist)
        t = sim.t + 1
        ended = ends_episode(sim.obs, action, next_obs, k_end, done_fn, hazard_fn)
        reset = ended | (t >= cfg.adversarial.sim_horizon)
        sim = _reset_sim(SimEnvs(next_obs, sim.policy, t, hist), reset, data, state.selected,
                         k_reset)
        return (sim, buf_obs, buf_act, buf_hist, (pos + E) % B), (reset.mean(), u.mean())

    carry = (state.sim, state.buffer_obs, state.buffer_act, state.buffer_hist, state.buffer_pos)
    carry, (reset_rate, u) = jax.lax.scan(step, carry,
                                          jax.random.split(key, cfg.adversarial.sim_steps))
    sim, buf_obs, buf_act, buf_hist, pos = carry
    metrics = {"sim_reset_rate": reset_rate.mean()}
    if cfg.ensemble_size > 1:
        metrics["sim_disagreement"] = u.mean()
    return state.replace(sim=sim, buffer_obs=buf_obs, buffer_act=buf_act, buffer_hist=buf_hist,
                         buffer_pos=pos), metrics


def _adversarial_draws(state: TrainState, data: TrainData):
    """The adversarial updates' draws, which no update changes, as functions of their keys:
    ``critic(key)`` -> one critic update's (real (obs, action, next_obs), fake (obs, action,
    hist) from the buffer, the members' noise key); ``update(key)`` -> one adversarial
    update's {"disc": its critic updates' keys, or their draws where batches_up_front,
    "real", "fake", "keys" (the members'), "anchors" (the likelihood anchor's batches)}."""
    cfg, adv = state.config, state.config.adversarial
    n = cfg.batch_size

    def fake_sa(key):
        rows = jax.random.randint(key, (n,), 0, adv.buffer_size)
        return (state.buffer_obs[rows], state.buffer_act[rows],
                take_history(state.buffer_hist, rows))

    def critic(key):
        k_real, k_fake, k_gen = jax.random.split(key, 3)
        return _real_batch_history(k_real, data, state.selected, n)[:3], fake_sa(k_fake), k_gen

    def update(key):
        k_disc, k_real, k_fake, k_gen = jax.random.split(key, 4)
        disc = jax.random.split(k_disc, adv.disc_updates)
        real = _real_batch_history(k_real, data, state.selected, n)
        anchors = [real]
        if adv.nll_weight and adv.nll_on != "selected":  # fold_in: "selected" keeps
            every = _real_batch_history(jax.random.fold_in(k_real, 1), data,  # its keys
                                        jnp.ones_like(state.selected), n)
            anchors = [every] if adv.nll_on == "all" else anchors + [every]
        return {"disc": jax.vmap(critic)(disc) if cfg.batches_up_front else disc,
                "real": real, "fake": fake_sa(k_fake),
                "keys": dyn.member_keys(k_gen, cfg.ensemble_size), "anchors": anchors}

    return critic, update


def _adversarial_updates(state: TrainState, data: TrainData, key):
    cfg, adv = state.config, state.config.adversarial
    gen_tx, disc_tx = _gen_tx(cfg, cfg.gen_lr), _disc_tx(cfg)
    scan = partial(jax.lax.scan, unroll=cfg.scan_unroll)
    train_gen = (state.step >= adv.pretrain_steps + adv.disc_warmup_steps
                 if adv.disc_warmup_steps else None)
    critic, draw = _adversarial_draws(state, data)
    up_front = cfg.batches_up_front  # each x below: its key, or its draws drawn before

    def disc_update(carry, x):
        gen, disc, us, opt = carry
        real, (f_obs, f_act, f_hist), k_gen = x if up_front else critic(x)
        f_next = _sampler(gen, state, 1.0).sample(f_obs, f_act, k_gen, f_hist)
        (loss, (us, aux)), grads = jax.value_and_grad(losses.discriminator_loss, has_aux=True)(
            disc, us, state.norm, real, (f_obs, f_act, f_next), cfg.dynamics.matmul_dtype)
        updates, opt = disc_tx.update(grads, opt, disc)
        return (gen, optax.apply_updates(disc, updates), us, opt), {"disc_loss": loss, **aux}

    def loop(carry, x):
        gen, gen_opt, disc, us, disc_opt = carry
        d = x if up_front else draw(x)
        (_, disc, us, disc_opt), d_metrics = scan(disc_update, (gen, disc, us, disc_opt),
                                                  d["disc"])
        (r_obs, r_act, _, r_hist), (f_obs, f_act, f_hist) = d["real"], d["fake"]
        obs, act = jnp.concatenate([r_obs, f_obs]), jnp.concatenate([r_act, f_act])
        hist = (None if r_hist is None else
                jax.tree_util.tree_map(lambda r, f: jnp.concatenate([r, f]), r_hist, f_hist))

        def member_loss(g, k):
            loss = losses.generator_adversarial_loss(g, disc, us, state.norm, obs, act, k,
                                                     hist, cfg.dynamics.matmul_dtype)[0]
            if adv.nll_weight:  # the likelihood anchor (static: off costs nothing)
                nll = sum(losses.generator_nll_loss(g, state.norm, *a)[0]
                          for a in d["anchors"])
                loss = loss + adv.nll_weight * nll / len(d["anchors"])
            return loss

        def total(g_all):  # each member's loss on the same (s, a), its own noise: sum
            per = dyn.map_members(member_loss, g_all, d["keys"])
            return per.sum(), per

        (_, per), grads = jax.value_and_grad(total, has_aux=True)(gen)
        updates, new_opt = dyn.map_members(lambda g, gr, o: gen_tx.update(gr, o, g),
                                           gen, grads, gen_opt)
        new_gen = optax.apply_updates(gen, updates)
        if train_gen is not None:  # critic warm-up: the members wait
            new_gen, new_opt = _tree_where(train_gen, (new_gen, new_opt), (gen, gen_opt))
        metrics = jax.tree_util.tree_map(lambda x: x[-1], d_metrics)
        return (new_gen, new_opt, disc, us, disc_opt), {"gen_loss": per.mean(), **metrics}

    keys = jax.random.split(key, cfg.updates_per_step)
    carry = (state.gen, state.gen_opt, state.disc, state.disc_us, state.disc_opt)
    carry, metrics = scan(loop, carry, jax.vmap(draw)(keys) if up_front else keys)
    gen, gen_opt, disc, us, disc_opt = carry
    state = state.replace(gen=gen, gen_opt=gen_opt, disc=disc, disc_us=us, disc_opt=disc_opt)
    return state, jax.tree_util.tree_map(jnp.mean, metrics)


def _start_adversarial(state: TrainState) -> TrainState:
    """At the first adversarial step after pre-training: the members' best weights (early
    stopping), fresh optimiser moments (the likelihood ones do not fit the new loss), the
    moving average restarted there."""
    cfg = state.config
    first = state.step == cfg.adversarial.pretrain_steps
    gen = _tree_where(first, state.best_gen, state.gen) if cfg.early_stopping else state.gen
    fresh = dyn.map_members(_gen_tx(cfg, cfg.gen_lr).init, gen)
    state = state.replace(gen=gen, gen_opt=_tree_where(first, fresh, state.gen_opt))
    if cfg.ema_decay:
        state = state.replace(ema_gen=_tree_where(first, gen, state.ema_gen))
    return state


def _adversarial_step(state: TrainState, data: TrainData, k_sim, k_upd):
    if state.config.adversarial.pretrain_steps:
        state = _start_adversarial(state)
    state, metrics = _advance_sim(state, data, k_sim)
    state, m = _adversarial_updates(state, data, k_upd)
    metrics.update(m)
    state = _score_members(state, data, mle=False)
    return _update_ema(state), metrics


# ------------------------------------------------------------------ value measurement


def _advance_vd(state: TrainState, data: TrainData, key):
    """Advance the spread-out value measurement; on completion refresh VD and the selection."""
    cfg = state.config
    H, K = cfg.vd.horizon, cfg.vd.every
    k_run, k_restart = jax.random.split(key)
    sim = _sampler(state.gen, state, cfg.sim_noise)
    task = sim.task_fns()
    done_fn, hazard_fn = sim.terminations(task.done_fn)
    roll = advance_values(state.vd_roll, data.policies, sim.dynamics, task.reward_fn, done_fn,
                          k_run, n_steps=-(-H // K), horizon=H, gamma=cfg.gamma,
                          hazard_fn=hazard_fn)
    done = roll.t >= H
    sim_value = roll.ret.mean(1)
    vd = value_difference(sim_value, data.true_value)
    fresh = start_values(data.start_pool, data.n_policies, cfg.vd.episodes, k_restart,
                         sim.new_history)
    pick = lambda new, old: jnp.where(done, new, old)
    return state.replace(
        vd=pick(vd, state.vd), sim_value=pick(sim_value, state.sim_value),
        sim_length=pick(roll.length.mean(1).astype(jnp.float32), state.sim_length),
        selected=pick(select_worst(vd, n_worst(state.eps, data.n_policies)), state.selected),
        vd_roll=jax.tree_util.tree_map(pick, fresh, roll)), done


# ------------------------------------------------------------------ the step


def _phase_step(state: TrainState, data: TrainData, k_sim, k_upd, phase: str):
    """One phase's updates. -> (state, metrics, finite flags); an adversarial method with
    pre-training reports the metrics of both phases (NaN for the other one)."""
    cfg = state.config
    if phase == "pretrain":
        state, metrics = _mle_step(state, data, k_upd, jnp.ones_like(state.selected))
    elif cfg.is_adversarial:
        state, metrics = _adversarial_step(state, data, k_sim, k_upd)
    else:
        state, metrics = _mle_step(state, data, k_upd, state.selected)
    finite = {f"finite/{k}": jnp.isfinite(v) for k, v in metrics.items()}
    if cfg.pretrains:
        names = ("nll", *ADVERSARIAL_METRICS) + (("sim_disagreement",)
                                                 if cfg.ensemble_size > 1 else ())
        nan = jnp.full((), jnp.nan, jnp.float32)
        finite = {f"finite/{k}": finite.get(f"finite/{k}", jnp.bool_(True)) for k in names}
        metrics = {k: metrics.get(k, nan) for k in names}
        metrics["phase"] = jnp.int32(phase != "pretrain")
    return state, metrics, finite


def train_step(state: TrainState, data: TrainData, phase: str | None = None
               ) -> tuple[TrainState, dict]:
    """One training call. -> (new state, metrics: dict of scalars).

    ``phase`` (static): "pretrain" or "main" for an adversarial method with pre-training when
    the caller knows on which side of ``pretrain_steps`` the step lies (else chosen on the
    device); ignored otherwise. Metrics: the losses of the method (``nll`` in likelihood
    steps; ``gen_loss``, ``disc_loss``, ``d_real``, ``d_fake``, ``sim_reset_rate`` and, for
    E > 1, ``sim_disagreement`` in adversarial ones; ``phase`` 0 / 1 with pre-training),
    ``heldout_nll`` (mean over the elites; with held-out episodes), ``n_stopped`` (early
    stopping), ``avd_train`` / ``mvd_train`` (mean / max VD of the training policies at the
    last completed measurement), ``n_selected``, ``vd_refreshed`` and ``finite`` (every loss
    and parameter finite after this step).
    """
    cfg = state.config
    if phase not in (None, "pretrain", "main"):
        raise ValueError(f"phase: expected None, 'pretrain' or 'main', got {phase!r}")
    key, k_sim, k_upd, k_vd = jax.random.split(state.key, 4)
    if not cfg.pretrains:
        state, metrics, finite = _phase_step(state, data, k_sim, k_upd, "main")
    elif phase is not None:
        state, metrics, finite = _phase_step(state, data, k_sim, k_upd, phase)
    else:
        state, metrics, finite = jax.lax.cond(
            state.step < cfg.adversarial.pretrain_steps,
            lambda s: _phase_step(s, data, k_sim, k_upd, "pretrain"),
            lambda s: _phase_step(s, data, k_sim, k_upd, "main"), state)
    refreshed = jnp.bool_(False)
    if cfg.vd.every:
        state, refreshed = _advance_vd(state, data, k_vd)
    finite["finite/params"] = losses.tree_all_finite((state.gen, state.disc))
    if data.n_heldout:
        elite = state.rank < cfg.n_elites
        metrics["heldout_nll"] = jnp.sum(jnp.where(elite, state.heldout_nll, 0.0)) / cfg.n_elites
    if cfg.early_stopping:
        metrics["n_stopped"] = jnp.sum(state.stopped).astype(jnp.int32)
    metrics.update(
        avd_train=jnp.mean(state.vd), mvd_train=jnp.max(state.vd),
        n_selected=jnp.sum(state.selected).astype(jnp.int32), vd_refreshed=refreshed,
        finite=jnp.all(jnp.stack(list(finite.values()))), **finite)
    return state.replace(step=state.step + 1, key=key), metrics


def train_steps(state: TrainState, data: TrainData, n_steps: int, phase: str | None = None
                ) -> tuple[TrainState, dict]:
    """``n_steps`` train_steps as one lax.scan (``phase``: as train_step, for all of them).
    -> (state, metrics stacked [n_steps])."""
    return jax.lax.scan(lambda s, _: train_step(s, data, phase), state, None, length=n_steps)


def simulator(state: TrainState, average: bool | None = None) -> Simulator:
    """The learned simulator of a training state: the members, their ranks (by the trained
    weights' held-out NLL), the normaliser, the rollout settings. ``average``: the moving
    average of the members' weights (None: when ema_decay > 0; True needs ema_decay > 0) or
    the trained weights themselves (False)."""
    if average is None:
        average = bool(state.config.ema_decay)
    if average and not state.config.ema_decay:
        raise ValueError("average: the state keeps no moving average (ema_decay = 0)")
    return _sampler(state.ema_gen if average else state.gen, state, state.config.sim_noise)
