"""Diagnosis's models: the base model and its extensions, fitted by maximum likelihood through
the same ``train_step`` that builds the simulator users train (method "bc"), S seeds as
vmapped lanes (``rl2s_jax.train.lanes``). Diagnosis has no trainer of its own.

A model is a member of the dynamics family (``rl2s_jax.model.dynamics``): p(delta_n | inputs)
= N(mean, diag(std^2)) over the normalised state change. ``ModelSpec`` says which one and
``ModelSpec.train_config`` is the ``TrainConfig`` it is fitted with: one member per lane,
every fit row drawn uniformly, no held-out rows inside the fit (diagnosis holds out whole
episodes itself). The base model sees the normalised s (position dims zeroed) and a, with one
learned log-std per dim (``noise="global"``); each other field switches on one extension, as
``rl2s train --set`` does for the simulator users train:

- ``action_history`` / ``obs_history``: the k previous actions / observations of the episode;
- ``noise="state"``: a state-dependent log-std head; ``nll_beta``: the beta-NLL exponent;
- ``time_inputs``: the step's place in the episode ("step") and the episode's place in the
  recording ("order"; simulated episodes run at the end of the recording);
- ``context_dim``: a per-episode context inferred from the episode's recent transitions
  (``model.history.history_context``; needs both pasts).

Everything at the boundary is NumPy. Shapes: S seeds, n rows, o = obs size, a = action size.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm.auto import tqdm

from rl2s_jax.data.episodes import Episodes
from rl2s_jax.model.dynamics import NOISE_KINDS, TIME_INPUTS, DynamicsSpec, Normalizer
from rl2s_jax.model.history import History, episode_steps_back, past_rows, push_history
from rl2s_jax.model.simulator import Simulator, simulator_returns
from rl2s_jax.train.config import TrainConfig, VDConfig
from rl2s_jax.train.data import TrainData, episode_steps_left
from rl2s_jax.train.lanes import init_lanes, train_lanes
from rl2s_jax.train.step import TrainState, simulator

PROBE_ROWS = 4096    # fit rows whose NLL is the training loss reported after every chunk
PREDICT_CHUNK = 16384
CHUNKS = 10          # progress-bar updates (and NaN checks) per fit


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Which model to fit (hashable).

    action_history / obs_history: past actions / observations fed as inputs; context_dim:
    size of the per-episode context (0: off; needs both pasts), context_hidden its encoder's
    hidden sizes; noise: "global" (one learned log-std per dim) or "state" (a log-std head);
    nll_beta: the beta-NLL exponent (0: plain NLL); time_inputs: subset of ("order", "step").
    hidden, steps (gradient updates), batch_size, lr, updates_per_step (updates per
    ``train_step``): the member and its Adam training. log_std_bounds ("fixed" | "learned",
    with log_std_bound_weight) and weight_decay: as ``TrainConfig.gen_*``.
    """

    action_history: int = 0
    obs_history: int = 0
    context_dim: int = 0
    noise: str = "global"
    nll_beta: float = 0.0
    time_inputs: tuple[str, ...] = ()
    hidden: tuple[int, ...] = (128, 128)
    steps: int = 5000
    batch_size: int = 256
    lr: float = 3e-3
    updates_per_step: int = 50
    context_hidden: tuple[int, ...] = (64, 64)
    log_std_bounds: str = "fixed"
    log_std_bound_weight: float = 0.01
    weight_decay: float = 0.0

    @property
    def dynamics(self) -> DynamicsSpec:
        """The model as a member of the dynamics-model family."""
        return DynamicsSpec(hidden=self.hidden, noise=self.noise,
                            log_std_bounds=self.log_std_bounds,
                            action_history=self.action_history, obs_history=self.obs_history,
                            time_inputs=self.time_inputs, context_dim=self.context_dim,
                            context_hidden=self.context_hidden)

    def validate(self) -> ModelSpec:
        """Raise ValueError naming the first bad field; returns self."""
        def is_int(v):
            return isinstance(v, int | np.integer) and not isinstance(v, bool)

        for name in ("steps", "batch_size", "updates_per_step"):
            v = getattr(self, name)
            if not is_int(v) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        if self.noise not in NOISE_KINDS:
            raise ValueError(f"noise: expected one of {NOISE_KINDS}, got {self.noise!r}")
        bad_time = [t for t in self.time_inputs if t not in TIME_INPUTS]
        if bad_time:
            raise ValueError(f"time_inputs: expected names from {TIME_INPUTS}, got "
                             f"{self.time_inputs!r}")
        self.dynamics.validate()
        if self.context_dim and not (self.obs_history and self.action_history):
            raise ValueError("context_dim: the context is inferred from the episode's recent "
                             "transitions; set obs_history and action_history >= 1")
        if not (isinstance(self.lr, int | float) and math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr: expected a positive finite float, got {self.lr!r}")
        b = self.nll_beta
        if not (isinstance(b, int | float) and not isinstance(b, bool) and 0.0 <= b <= 1.0):
            raise ValueError(f"nll_beta: expected a float in [0, 1], got {b!r}")
        for name in ("weight_decay", "log_std_bound_weight"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite float >= 0, got {v!r}")
        return self

    @property
    def extensions(self) -> tuple[str, ...]:
        """Names of the extensions switched on ("base" alone for none)."""
        out = []
        if self.action_history:
            out.append(f"action_history={self.action_history}")
        if self.obs_history:
            out.append(f"obs_history={self.obs_history}")
        if self.context_dim:
            out.append(f"context_dim={self.context_dim}")
        if self.noise != "global":
            out.append(f"noise={self.noise}")
        if self.nll_beta:
            out.append(f"nll_beta={self.nll_beta:g}")
        if self.time_inputs:
            out.append("time_inputs=" + "+".join(self.time_inputs))
        return tuple(out) or ("base",)

    def describe(self) -> dict:
        """JSON-able summary: every field and the list of extensions."""
        d = {k: (list(v) if isinstance(v, tuple) else v)
             for k, v in dataclasses.asdict(self).items()}
        d["extensions"] = list(self.extensions)
        return d

    def train_config(self, episode_length: int, position_dims: Sequence[int] = ()
                     ) -> TrainConfig:
        """The ``TrainConfig`` this model is fitted with: maximum likelihood ("bc") of one
        member per lane, no value measurement, no held-out rows inside the fit; mean-free
        rollouts sample the member (``sim_noise`` 1). ``episode_length`` scales the "step"
        time input (as the data's ``Episodes.step_frac``)."""
        dynamics = DynamicsSpec(
            hidden=self.hidden, noise=self.noise, activation="relu",
            log_std_bounds=self.log_std_bounds, action_history=self.action_history,
            obs_history=self.obs_history, time_inputs=tuple(self.time_inputs),
            context_dim=self.context_dim, context_hidden=tuple(self.context_hidden))
        return TrainConfig(
            task=None, method="bc", dynamics=dynamics,
            log_std_bound_weight=self.log_std_bound_weight, gen_weight_decay=self.weight_decay,
            nll_beta=float(self.nll_beta), batch_size=self.batch_size, bc_lr=float(self.lr),
            updates_per_step=self.updates_per_step, ensemble_size=1, n_elites=1,
            holdout_frac=0.0, early_stop_patience=0,
            vd=VDConfig(every=0, horizon=int(episode_length)), sim_noise=1.0,
            input_ignore_dims=tuple(int(d) for d in position_dims)).validate()


class ModelDiverged(FloatingPointError):
    """Training hit a NaN/Inf loss. ``last_good``: every seed's state at the end of the last
    chunk whose losses were all finite."""

    def __init__(self, seed: int, step: int, spec: ModelSpec, last_good):
        super().__init__(f"fit_models: the loss of seed {seed} turned NaN/Inf by update {step} "
                         f"({', '.join(spec.extensions)}); lower lr (now {spec.lr}) or check "
                         f"the data for extreme values")
        self.seed, self.step, self.last_good = seed, step, last_good


@struct.dataclass
class FittedModels:
    """S models of one spec fitted to the same rows with different seeds.

    states: the seeds' ``TrainState`` stacked [S, ...] (lanes); norm: the fit rows'
    Normalizer; train_loss [S]: NLL on a probe of the fit rows at the end; loss_history
    [S, B]: the same after each of B chunks; fit_episodes [E1]."""

    states: TrainState
    norm: Normalizer
    train_loss: np.ndarray
    loss_history: np.ndarray
    fit_episodes: np.ndarray
    spec: ModelSpec = struct.field(pytree_node=False)
    episode_length: int = struct.field(pytree_node=False, default=1000)
    seeds: tuple[int, ...] = struct.field(pytree_node=False, default=(0,))
    obs_size: int = struct.field(pytree_node=False, default=0)
    action_size: int = struct.field(pytree_node=False, default=0)

    @property
    def n_seeds(self) -> int:
        return len(self.seeds)

    @property
    def simulators(self) -> Simulator:
        """Every seed's model as a ``Simulator``, stacked [S, ...]."""
        return jax.vmap(simulator)(self.states)

    def simulator(self, seed_index: int) -> Simulator:
        """Seed ``seed_index``'s model as a ``Simulator``."""
        return simulator(jax.tree_util.tree_map(lambda x: x[seed_index], self.states))


# ------------------------------------------------------------------ the episodes' past (host)


def _as_rows(x, n: int, what: str) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 1 or (x.size and (not np.issubdtype(x.dtype, np.integer) or x.min() < 0
                                   or x.max() >= n)):
        raise ValueError(f"{what}: expected a 1-D array of ints in [0, {n}), got "
                         f"{x.dtype} array of shape {x.shape}")
    return x.astype(np.int64)


def episode_history(eps: Episodes, rows, *, obs_history: int, action_history: int,
                    time_inputs: tuple[str, ...] = (), episode_length: int = 1000
                    ) -> History | None:
    """The logged past of Episodes rows [n] as a simulator with those inputs sees it (None
    when it has none): the same gather as training's (``model.history.past_rows``)."""
    if not (obs_history or action_history or time_inputs):
        return None
    rows = np.asarray(rows, np.int64)
    back = episode_steps_back(eps.policy, eps.episode, eps.t)

    def past(x, k):
        p, v = past_rows(np.asarray(x, np.float32), back, rows, k, xp=np)
        return (None, None) if k == 0 else (jnp.asarray(p), jnp.asarray(v))
    past_obs, obs_valid = past(eps.obs, obs_history)
    past_act, act_valid = past(eps.action, action_history)
    extra = {}
    if "order" in time_inputs:
        extra["order"] = jnp.asarray(eps.order[rows], jnp.float32)
    return History(past_obs=past_obs, past_obs_valid=obs_valid, past_act=past_act,
                   past_act_valid=act_valid, t=jnp.asarray(eps.t[rows], jnp.int32),
                   time_inputs=tuple(time_inputs), episode_length=int(episode_length), **extra)


def _spec_history(fm: FittedModels, eps: Episodes, rows) -> History | None:
    s = fm.spec
    return episode_history(eps, rows, obs_history=s.obs_history,
                           action_history=s.action_history, time_inputs=tuple(s.time_inputs),
                           episode_length=fm.episode_length)


def _episode_length(eps: Episodes) -> int:
    """What scales the data's ``step_frac`` (its time limit, or the longest episode)."""
    ok = eps.t > 0
    if not ok.any():
        return int(eps.t.max()) + 1
    return int(round(float(np.median(eps.t[ok] / eps.step_frac[ok]))))


def _train_data(eps: Episodes, rows: np.ndarray, cfg: TrainConfig) -> TrainData:
    """The fit rows [n] as one group of rows drawn uniformly (no policies, no values)."""
    f32 = lambda x: jnp.asarray(np.asarray(x)[rows], jnp.float32)
    obs, action, next_obs = (np.asarray(x)[rows] for x in (eps.obs, eps.action, eps.next_obs))
    pid, epi, t = eps.policy[rows], eps.episode[rows], eps.t[rows]
    o, a = eps.obs_size, eps.action_size
    extra = {}
    if not cfg.markov:
        extra = dict(steps_back=jnp.asarray(episode_steps_back(pid, epi, t), jnp.int32),
                     t=jnp.asarray(t, jnp.int32),
                     val_hist=episode_history(eps, rows[:0], obs_history=cfg.dynamics.obs_history,
                                              action_history=cfg.dynamics.action_history,
                                              time_inputs=tuple(cfg.dynamics.time_inputs),
                                              episode_length=cfg.episode_length))
        if "order" in cfg.dynamics.time_inputs:
            extra["order"] = f32(eps.order)
    starts = rows[eps.t[rows] == 0] if (eps.t[rows] == 0).any() else rows[:1]
    return TrainData(
        obs_history=cfg.dynamics.obs_history, action_history=cfg.dynamics.action_history,
        time_inputs=tuple(cfg.dynamics.time_inputs), episode_length=cfg.episode_length, **extra,
        obs=f32(eps.obs), action=f32(eps.action), next_obs=f32(eps.next_obs),
        policy_start=jnp.zeros((1,), jnp.int32),
        policy_count=jnp.asarray([rows.size], jnp.int32),
        start_pool=jnp.asarray(eps.obs[starts], jnp.float32),
        true_value=jnp.full((1,), jnp.nan, jnp.float32), policies={},
        norm=Normalizer.from_data(obs, action, next_obs, ignore_dims=cfg.ignore_dims),
        val_obs=jnp.zeros((0, o), jnp.float32), val_action=jnp.zeros((0, a), jnp.float32),
        val_next_obs=jnp.zeros((0, o), jnp.float32),
        steps_left=jnp.asarray(episode_steps_left(pid, epi, t), jnp.int32),
        done=jnp.zeros((rows.size,), jnp.float32))


# ------------------------------------------------------------------------ fitting


def fit_models(eps: Episodes, fit_episodes: np.ndarray, spec: ModelSpec,
               seeds: Sequence[int] = (0,), *, progress: bool = False) -> FittedModels:
    """Fit one model of ``spec`` per seed to the rows of ``fit_episodes`` [E1] through
    ``train_step`` (``spec.train_config``); the seeds are lanes of one vmapped program."""
    spec.validate()
    fit_episodes = np.unique(_as_rows(fit_episodes, eps.n_episodes, "fit_episodes"))
    seeds = tuple(int(s) for s in seeds)
    if not seeds:
        raise ValueError("seeds: expected at least one seed, got none")
    rows = eps.rows(fit_episodes)
    length = _episode_length(eps)
    cfg = spec.train_config(length, eps.position_dims)
    data = _train_data(eps, rows, cfg)
    states = init_lanes(jnp.stack([jax.random.PRNGKey(s) for s in seeds]), cfg, data)
    probe = rows[np.linspace(0, rows.size - 1, min(PROBE_ROWS, rows.size)).astype(np.int64)]
    n_steps = max(1, math.ceil(spec.steps / spec.updates_per_step))
    per_chunk = max(1, math.ceil(n_steps / CHUNKS))
    fm = FittedModels(states=states, norm=data.norm, train_loss=np.zeros(len(seeds)),
                      loss_history=np.zeros((len(seeds), 0)), fit_episodes=fit_episodes,
                      spec=spec, episode_length=length, seeds=seeds, obs_size=eps.obs_size,
                      action_size=eps.action_size)
    bar = (tqdm(total=n_steps * spec.updates_per_step, unit="update", dynamic_ncols=True,
                desc="fit " + ",".join(spec.extensions)) if progress else None)
    losses, done, compiled = [], 0, {}
    try:
        while done < n_steps:
            k = min(per_chunk, n_steps - done)
            last_good = fm.states
            states, m = train_lanes(fm.states, data, k, cfg, compiled)
            fm = fm.replace(states=states)
            loss = heldout_metrics(fm, eps, probe)["nll"]
            bad = ~(np.asarray(m["finite"], bool) & np.isfinite(loss))
            if bad.any():
                raise ModelDiverged(seeds[int(np.flatnonzero(bad)[0])],
                                    (done + k) * spec.updates_per_step, spec, last_good)
            done += k
            losses.append(loss)
            if bar is not None:
                bar.update(k * spec.updates_per_step)
                bar.set_postfix(nll=f"{float(loss.mean()):.3f}", refresh=False)
    finally:
        if bar is not None:
            bar.close()
    history = np.stack(losses, 1)
    return fm.replace(train_loss=history[:, -1], loss_history=history)


# ---------------------------------------------------------------------- evaluation


def _check_eps(fm: FittedModels, eps: Episodes) -> None:
    if (eps.obs_size, eps.action_size) != (fm.obs_size, fm.action_size):
        raise ValueError(f"eps: expected obs/action sizes ({fm.obs_size}, {fm.action_size}) "
                         f"of the fitted models, got ({eps.obs_size}, {eps.action_size})")


@jax.jit
def _predict_jit(sims: Simulator, norm: Normalizer, obs, action, hist):
    """Every seed's member Gaussian, in the fit's normalised delta units: (mean, std) [S, n, o]
    (the norm is the same in every lane)."""
    mean, log_std = jax.vmap(lambda s: s.member_dists(obs, action, hist))(sims)
    return mean[:, 0], jnp.exp(log_std[:, 0])


def _pad(n: int) -> int:
    """Padded chunk length (a power of two, 256 to PREDICT_CHUNK): few shapes compile."""
    return min(PREDICT_CHUNK, max(256, 1 << (max(n, 1) - 1).bit_length()))


def predict(fm: FittedModels, eps: Episodes, rows) -> tuple[np.ndarray, np.ndarray]:
    """Predictive Gaussian of the normalised delta of the given rows of eps, with their logged
    past, times and context. -> (mean [S, n, o], std [S, n, o])."""
    _check_eps(fm, eps)
    rows = _as_rows(rows, eps.n, "rows")
    sims = fm.simulators
    chunk = _pad(rows.size)
    means, stds = [], []
    for lo in range(0, rows.size, chunk):
        r = rows[lo:lo + chunk]
        k = r.size
        r = np.concatenate([r, np.full(chunk - k, r[0])])
        mean, std = _predict_jit(sims, fm.norm, jnp.asarray(eps.obs[r], jnp.float32),
                                 jnp.asarray(eps.action[r], jnp.float32),
                                 _spec_history(fm, eps, r))
        means.append(np.asarray(mean)[:, :k])
        stds.append(np.asarray(std)[:, :k])
    if not means:
        o = fm.obs_size
        return np.zeros((fm.n_seeds, 0, o)), np.zeros((fm.n_seeds, 0, o))
    return np.concatenate(means, 1), np.concatenate(stds, 1)


def delta_scale(fm: FittedModels) -> np.ndarray:
    """[o] the delta std that normalises the model's targets."""
    return np.asarray(fm.norm.delta_std, np.float64)


def normalized_delta(fm: FittedModels, eps: Episodes, rows) -> np.ndarray:
    """The model's target for the rows: (delta - delta_mean) / delta_std. -> [n, o]"""
    rows = _as_rows(rows, eps.n, "rows")
    mean = np.asarray(fm.norm.delta_mean, np.float64)
    return (eps.delta[rows] - mean) / delta_scale(fm)


def heldout_metrics(fm: FittedModels, eps: Episodes, rows) -> dict[str, np.ndarray]:
    """{"nll": [S] mean per-row Gaussian NLL of the normalised delta (summed over dims),
    "mse": [S] mean squared error of the mean (normalised units, mean over dims)}."""
    mean, std = predict(fm, eps, rows)
    y = normalized_delta(fm, eps, rows)[None]
    z = (y - mean) / std
    nll = (0.5 * z**2 + np.log(std) + 0.5 * np.log(2 * np.pi)).sum(-1).mean(-1)
    return {"nll": nll, "mse": ((y - mean) ** 2).mean((-1, -2))}


@jax.jit
def _kstep_jit(sims: Simulator, obs0, hist0, actions, target, weight):
    """Open-loop mean rollouts of every seed from obs0 [n, o] under the logged actions
    [n, k, a], the past pushed along (``hist0``: the starts' logged past) -> [S, k] sum over
    starts of the mean-over-dims squared error (in obs stds) against target [n, k, o]."""
    def one_seed(sim: Simulator):
        def step(carry, j):
            obs, hist = carry
            a = actions[:, j]
            nxt = sim.norm.clip_obs(sim.mean(obs, a, hist), sim.obs_clip)
            err = (((nxt - target[:, j]) / sim.norm.obs_std) ** 2).mean(-1)
            hist = None if hist is None else push_history(hist, obs, a)
            return (nxt, hist), (err * weight).sum()
        _, sse = jax.lax.scan(step, (obs0, hist0), jnp.arange(target.shape[1]))
        return sse
    return jax.vmap(one_seed)(sims)


def kstep_errors(fm: FittedModels, eps: Episodes, episodes, k_max: int = 20,
                 n_starts: int | None = None, seed: int = 0) -> np.ndarray:
    """RMSE [S, k_max] of open-loop rollouts of the model mean, k = 1..k_max steps ahead.

    Starts are real states of ``episodes`` with at least k_max steps left (n_starts of them
    drawn at random, or all); each rollout is driven by the logged actions, its past logged
    before the start and its own after (so is the context inferred from it). Error:
    (predicted - real next state) / obs_std, mean over dims and starts, square-rooted."""
    _check_eps(fm, eps)
    if not isinstance(k_max, int) or k_max < 1:
        raise ValueError(f"k_max: expected an int >= 1, got {k_max!r}")
    episodes = np.unique(_as_rows(episodes, eps.n_episodes, "episodes"))
    rows = eps.rows(episodes)
    starts = rows[eps.t[rows] <= eps.length[eps.episode[rows]] - k_max]
    if starts.size == 0:
        raise ValueError(f"k_max: no episode of those given has {k_max} steps (longest "
                         f"{int(eps.length[episodes].max())})")
    if n_starts is not None:
        if not isinstance(n_starts, int) or n_starts < 1:
            raise ValueError(f"n_starts: expected None or an int >= 1, got {n_starts!r}")
        if n_starts < starts.size:
            starts = np.sort(np.random.default_rng(seed).choice(starts, n_starts,
                                                                replace=False))
    sims = fm.simulators
    chunk = max(1, _pad(starts.size * k_max) // k_max)
    sse = np.zeros((fm.n_seeds, k_max))
    for lo in range(0, starts.size, chunk):
        s = starts[lo:lo + chunk]
        k = s.size
        s = np.concatenate([s, np.full(chunk - k, s[0])])
        steps = s[:, None] + np.arange(k_max)
        sse += np.asarray(_kstep_jit(
            sims, jnp.asarray(eps.obs[s], jnp.float32), _spec_history(fm, eps, s),
            jnp.asarray(eps.action[steps], jnp.float32),
            jnp.asarray(eps.next_obs[steps], jnp.float32),
            jnp.asarray(np.arange(chunk) < k, jnp.float32)))
    return np.sqrt(sse / starts.size)


# ------------------------------------------------------------------------ rollouts


def rollout_values(fm: FittedModels, seed_index: int, policies, start_obs: np.ndarray, *,
                   task, horizon: int, n_episodes: int, gamma: float, key: jax.Array
                   ) -> np.ndarray:
    """Mean discounted return [P] of each policy (stacked params) over n_episodes episodes of
    at most ``horizon`` steps simulated in model ``seed_index``, under ``task``'s reward_fn /
    done_fn (``model.simulator.simulator_returns``: next states sampled, kept within +-10
    data stds; history inputs carried; order 1, the end of the recording)."""
    if not isinstance(seed_index, int | np.integer) or not 0 <= seed_index < fm.n_seeds:
        raise ValueError(f"seed_index: expected an int in [0, {fm.n_seeds}), got {seed_index!r}")
    start_obs = np.asarray(start_obs)
    if start_obs.ndim != 2 or start_obs.shape[0] == 0 or start_obs.shape[1] != fm.obs_size:
        raise ValueError(f"start_obs: expected shape [N0 >= 1, {fm.obs_size}], got "
                         f"{start_obs.shape}")
    for name, v in (("horizon", horizon), ("n_episodes", n_episodes)):
        if not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma: expected a float in (0, 1], got {gamma!r}")
    ret, _ = _returns_jit(fm.simulator(int(seed_index)), task, policies,
                          jnp.asarray(start_obs, jnp.float32), key, n_episodes=int(n_episodes),
                          horizon=int(horizon), gamma=float(gamma))
    return np.asarray(ret).mean(1)


_returns_jit = jax.jit(simulator_returns,
                       static_argnames=("task", "n_episodes", "horizon", "gamma"))
