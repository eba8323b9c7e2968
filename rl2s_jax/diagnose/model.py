"""Fitting the dynamics-model family (``rl2s_jax.model.dynamics``) for diagnosis: the base model and
its extensions, S seeds as one vmapped program (an ensemble of S members).

A model is a member of the family that training uses: p(delta_n | inputs) = N(mean,
diag(std^2)) over the normalised state change delta_n = (s' - s - delta_mean) / delta_std, fit
by maximum likelihood (Adam on the Gaussian NLL). ``ModelSpec.dynamics`` is its
``DynamicsSpec``. The base model sees the normalised s (position dims zeroed) and a, and has
one learned log-std per dim (``noise="global"``); ``log_std_bounds`` and ``weight_decay`` are
the family's options. Each other ``ModelSpec`` field switches on one extension:

- ``action_history`` / ``obs_history``: the k previous actions / observations of the episode
  (normalised; zero, with a validity mask, before the episode start);
- ``noise="state"``: a state-dependent log-std head (the generator's bounded log-std);
- ``time_inputs``: the episode's place in the recording order and the step's place in the
  episode (``Episodes.order``, ``Episodes.step_frac``);
- ``context_dim``: a per-episode latent c: an encoder embeds (s, a, delta) rows of the same
  episode and mean-pools them. The rows always come from the *other half* of the target row's
  episode (``episodes.half_split``), in training and at evaluation, so the model never sees the
  transition it predicts. New rollouts draw c from a Gaussian fitted to the fit episodes'
  contexts;
- ``policy_cvar_eps``: every ``cvar_every`` updates each policy's NLL is measured on a fixed
  subsample of its rows, and half of each batch comes from the worst ``train.n_worst(eps, P)``
  policies (``train.select_worst``), the other half uniformly.

S seeds train as one vmapped program; the update loop is a ``lax.scan`` run in chunks (so a
progress bar can move between them). With a context, a batch is groups of CONTEXT_GROUP rows
of one episode half sharing one context draw (each row still uniform over the fit rows), so
the encoder runs on few rows per update. Compilation dominates small fits on the CPU, so each
training block draws its randomness as one array of uniforms and initial weights come from
NumPy. Everything at the boundary is NumPy. Shapes: S seeds, n rows, o = obs size,
a = action size, C = context_dim, P policies.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from tqdm.auto import tqdm

from rl2s_jax.data.episodes import Episodes, half_split
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.dynamics import NOISE_KINDS, TIME_INPUTS, DynamicsSpec, Normalizer
from rl2s_jax.model.generator import spectral_normalize
from rl2s_jax.policy.policy import init_mlp, num_policies, sample_action
from rl2s_jax.train.cvar import n_worst, select_worst

__all__ = ["NOISE_KINDS", "TIME_INPUTS", "FittedModels", "ModelDiverged", "ModelSpec",
           "delta_scale", "fit_models", "heldout_metrics", "history", "kstep_errors",
           "normalized_delta", "predict", "rollout_values"]
OBS_CLIP = 10.0      # rollout states are kept within +-OBS_CLIP data stds of the obs mean
PROBE_ROWS = 128     # rows per policy for the CVaR policy NLL
CONTEXT_GROUP = 8    # batch rows that share one context draw (one half of one episode)
PREDICT_CHUNK = 16384


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Which model to fit (hashable: it is a static argument of the compiled programs).

    action_history / obs_history: number of past actions / observations fed as inputs.
    context_dim: size of the per-episode latent context (0: off); context_rows: M, the rows
    of the other half pooled into it; context_hidden: the encoder's hidden sizes.
    noise: "global" (one learned log-std per dim) or "state" (a log-std head of the inputs).
    nll_beta: the beta-NLL exponent of the training loss (0: plain NLL; 1: each dim's NLL
    weighted by stop_gradient(std^2), so the mean learns as under squared error and a
    state-dependent std cannot buy likelihood by giving up on the mean in noisy regions).
    time_inputs: subset of ("order", "step"). policy_cvar_eps: None, or the CVaR fraction of
    policies whose rows fill half of each batch, re-chosen every cvar_every updates.
    hidden, steps, batch_size, lr: the generator MLP and its Adam training (lr decays to lr/10
    along a cosine). log_std_bounds ("fixed" | "learned", with log_std_bound_weight) and
    weight_decay (L2 on the weight matrices): as the family's (``TrainConfig.gen_*``).
    adversarial_steps: generator updates of the adversarial phase (0: maximum likelihood
    only), run after the ``steps`` likelihood updates as RL2S / GAIL run after their
    pre-training (see ``fit_models``); disc_updates critic updates per generator update,
    adv_lr / disc_lr their Adam rates, adv_nll_weight the likelihood anchor on the real batch
    (``TrainConfig.adv_nll_weight``), disc_hidden the critic's hidden sizes.
    """

    action_history: int = 0
    obs_history: int = 0
    context_dim: int = 0
    noise: str = "global"
    nll_beta: float = 0.0
    time_inputs: tuple[str, ...] = ()
    policy_cvar_eps: float | None = None
    hidden: tuple[int, ...] = (128, 128)
    steps: int = 5000
    batch_size: int = 256
    lr: float = 3e-3
    context_rows: int = 16
    context_hidden: tuple[int, ...] = (64, 64)
    cvar_every: int = 100
    log_std_bounds: str = "fixed"
    log_std_bound_weight: float = 0.01
    weight_decay: float = 0.0
    adversarial_steps: int = 0
    disc_updates: int = 2
    adv_lr: float = 1e-4
    disc_lr: float = 1e-4
    adv_nll_weight: float = 10.0
    disc_hidden: tuple[int, ...] = (128, 128)

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

        for name in ("steps", "batch_size", "context_rows", "cvar_every", "disc_updates"):
            v = getattr(self, name)
            if not is_int(v) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        if not is_int(self.adversarial_steps) or self.adversarial_steps < 0:
            raise ValueError(f"adversarial_steps: expected an int >= 0, got "
                             f"{self.adversarial_steps!r}")
        if not (len(self.disc_hidden) and all(is_int(h) and h >= 1 for h in self.disc_hidden)):
            raise ValueError(f"disc_hidden: expected a non-empty tuple of ints >= 1, got "
                             f"{self.disc_hidden!r}")
        for name in ("adv_lr", "disc_lr"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite float, got {v!r}")
        e = self.policy_cvar_eps
        if e is not None and not (isinstance(e, int | float) and not isinstance(e, bool)
                                  and 0.0 < e <= 1.0):
            raise ValueError(f"policy_cvar_eps: expected None or a float in (0, 1], got {e!r}")
        self.dynamics.validate()
        if not (isinstance(self.lr, int | float) and math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr: expected a positive finite float, got {self.lr!r}")
        b = self.nll_beta
        if not (isinstance(b, int | float) and not isinstance(b, bool) and 0.0 <= b <= 1.0):
            raise ValueError(f"nll_beta: expected a float in [0, 1], got {b!r}")
        for name in ("weight_decay", "log_std_bound_weight", "adv_nll_weight"):
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
        if self.policy_cvar_eps is not None:
            out.append(f"policy_cvar_eps={self.policy_cvar_eps}")
        return tuple(out) or ("base",)

    def describe(self) -> dict:
        """JSON-able summary: every field and the list of extensions."""
        d = {k: (list(v) if isinstance(v, tuple) else v)
             for k, v in dataclasses.asdict(self).items()}
        d["extensions"] = list(self.extensions)
        return d


class ModelDiverged(FloatingPointError):
    """Training hit a NaN/Inf loss. ``last_good_params``: every seed's parameters at the end of
    the last chunk whose losses were all finite."""

    def __init__(self, seed: int, step: int, spec: ModelSpec, last_good_params):
        super().__init__(f"fit_models: the loss of seed {seed} turned NaN/Inf by update {step} "
                         f"({', '.join(spec.extensions)}); lower lr (now {spec.lr}) or check "
                         f"the data for extreme values")
        self.seed, self.step, self.last_good_params = seed, step, last_good_params


@struct.dataclass
class FittedModels:
    """S models of one spec fitted to the same rows with different seeds.

    params: family members stacked over seeds [S, ...] ({"layers", "log_std" [S, o] when noise
    is global, "enc" when context_dim > 0, "max_log_std" / "min_log_std" when the bounds are
    learned}); norm: the Normalizer of the fit rows;
    ctx_mean [S, C] / ctx_cov [S, C, C]: Gaussian of the fit episodes' contexts, one per half
    of each episode (C = 0: empty);
    train_loss [S]: mean batch NLL over the last cvar_every updates; loss_history [S, B]: the
    same per block of cvar_every updates; policy_nll [S, P]: each policy's NLL on its probe
    rows at the last CVaR refresh (NaN without policy_cvar_eps; -inf for policies with no fit
    rows); fit_episodes [E1].
    """

    params: Any
    norm: Normalizer
    ctx_mean: jax.Array
    ctx_cov: jax.Array
    train_loss: np.ndarray
    loss_history: np.ndarray
    policy_nll: np.ndarray
    fit_episodes: np.ndarray
    spec: ModelSpec = struct.field(pytree_node=False)
    position_dims: tuple[int, ...] = struct.field(pytree_node=False, default=())
    seeds: tuple[int, ...] = struct.field(pytree_node=False, default=(0,))
    obs_size: int = struct.field(pytree_node=False, default=0)
    action_size: int = struct.field(pytree_node=False, default=0)

    @property
    def n_seeds(self) -> int:
        return len(self.seeds)


# ------------------------------------------------------------------ inputs (host side)


def history(eps: Episodes, x: np.ndarray, k: int, rows: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """The k previous values of a per-row array x [N, ...] for the given rows only.

    -> (past [n, k, ...], valid [n, k] bool); past[:, j] is x at step t - 1 - j of the row's
    episode, zero where that is before the episode start. Same as ``eps.past(x, k)[rows]``
    without building the [N, k, ...] array.
    """
    rows = np.asarray(rows, np.int64)
    lags = np.arange(1, k + 1)
    valid = eps.t[rows][:, None] >= lags
    src = np.where(valid, rows[:, None] - lags, rows[:, None])
    past = x[src]
    mask = valid.reshape(valid.shape + (1,) * (x.ndim - 1))
    return np.where(mask, past, 0).astype(x.dtype), valid


def _gather_rows(eps: Episodes, spec: ModelSpec, rows: np.ndarray) -> dict[str, np.ndarray]:
    """Raw (unnormalised) model inputs of the rows, float32 (see ``_inputs``)."""
    f32 = np.float32
    past_a, valid_a = history(eps, eps.action, spec.action_history, rows)
    past_o, valid_o = history(eps, eps.obs, spec.obs_history, rows)
    times = {"order": eps.order, "step": eps.step_frac}
    t = [times[name][rows] for name in spec.time_inputs]
    return dict(obs=eps.obs[rows].astype(f32), action=eps.action[rows].astype(f32),
                past_act=past_a.astype(f32), past_act_valid=valid_a,
                past_obs=past_o.astype(f32), past_obs_valid=valid_o,
                times=(np.stack(t, -1) if t else np.zeros((len(rows), 0))).astype(f32))


def _context_pairs(eps: Episodes, rows: np.ndarray, other: bool = True
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (episode, other half) whose rows give each row its context (other=False: the
    row's own half).

    -> (lo [U], count [U]: first row and size of each distinct half; inverse [n]: which of
    the U each row uses).
    """
    half = half_split(eps)[rows]
    uniq, inverse = np.unique(2 * eps.episode[rows] + (1 - half if other else half),
                              return_inverse=True)
    e, h = uniq // 2, uniq % 2
    mid = eps.length[e] // 2
    lo = eps.start[e] + np.where(h == 1, mid, 0)
    count = np.where(h == 1, eps.length[e] - mid, mid)
    return lo, count, inverse.reshape(-1)


def _spread(lo: np.ndarray, count: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to m rows spread evenly over each range [lo, lo + count) (all of it when count <= m).
    -> (idx [U, m], mask [U, m])."""
    j = np.arange(m)
    c = count[:, None]
    off = np.where(c <= m, j, np.floor((j + 0.5) * c / m).astype(np.int64))
    mask = j < np.minimum(c, m)
    return lo[:, None] + np.where(mask, off, 0), mask


def _check_context_episodes(eps: Episodes, episodes: np.ndarray, what: str) -> None:
    short = episodes[eps.length[episodes] < 2]
    if short.size:
        raise ValueError(f"{what}: context_dim > 0 needs episodes of at least 2 steps (one for "
                         f"each half), but {short.size} have 1, e.g. episode {int(short[0])}; "
                         "leave them out")


# ---------------------------------------------------------------- networks (device)
# The family's functions (rl2s_jax.model.dynamics), under the names this module has always used.

_obs_inputs = dyn.obs_inputs
_other_inputs = dyn.other_inputs
_encoder_inputs = dyn.encoder_inputs
_pool = dyn.pool_context
_nll = dyn.gaussian_nll


def _inputs(norm: Normalizer, spec: ModelSpec, r: dict) -> jax.Array:
    """The generator inputs (without the context) of raw rows r (``_gather_rows``)."""
    del spec  # the rows carry the history and time arrays the spec asked for
    return dyn.model_inputs(norm, r)


@functools.partial(jax.jit, static_argnames="spec")
def _prepare_rows(norm: Normalizer, spec: ModelSpec, raw: dict, next_obs):
    """Training arrays of raw rows: (inputs x [n, d], normalised delta y [n, o], encoder
    inputs [n, 2o + a], or [n, 0] without a context)."""
    y = norm.norm_delta(raw["obs"], next_obs)
    enc = (_encoder_inputs(norm, raw["obs"], raw["action"], next_obs) if spec.context_dim
           else jnp.zeros((y.shape[0], 0)))
    return _inputs(norm, spec, raw), y, enc


def _input_size(spec: ModelSpec, o: int, a: int) -> int:
    return spec.dynamics.input_size(o, a)


def _dist(params, spec: ModelSpec, x, ctx=None):
    """Gaussian over the normalised delta. x [..., d], ctx [..., C] -> (mean, log_std) [..., o]."""
    return dyn.member_dist(params, x, ctx if spec.context_dim else None)


def _init_params(seed: int, spec: ModelSpec, o: int, a: int) -> dict:
    """One seed's parameters (NumPy)."""
    return dyn.init_member_numpy(seed, spec.dynamics, o, a)


# ------------------------------------------------------------------------ training


@struct.dataclass
class _TrainData:
    """Device-resident fit rows (n of them, in dataset order).

    x [n, d]: generator inputs without the context; y [n, o]: normalised delta; enc [n, 2o+a]:
    encoder inputs; own_lo / own_count and ctx_lo / ctx_count [n]: each row's own and other
    half of its episode (indices into these rows); by_policy [n]: rows sorted by policy,
    pol_start / pol_count [P] into it; probe [P, m] / probe_mask [P, m]: each policy's fixed
    rows for its CVaR NLL.
    """

    x: jax.Array
    y: jax.Array
    enc: jax.Array
    own_lo: jax.Array
    own_count: jax.Array
    ctx_lo: jax.Array
    ctx_count: jax.Array
    by_policy: jax.Array
    pol_start: jax.Array
    pol_count: jax.Array
    probe: jax.Array
    probe_mask: jax.Array


@struct.dataclass
class _TrainState:
    """One seed's training state: params, Adam state, key, CVaR selection [P] and NLL [P]."""

    params: Any
    opt_state: Any
    key: jax.Array
    selected: jax.Array
    policy_nll: jax.Array


def _optimizer(spec: ModelSpec) -> optax.GradientTransformation:
    schedule = optax.cosine_decay_schedule(spec.lr, spec.steps, alpha=0.1)
    decay = ([optax.add_decayed_weights(spec.weight_decay, mask=dyn.weight_mask)]
             if spec.weight_decay else [])
    return optax.chain(*decay, optax.clip_by_global_norm(10.0), optax.adam(schedule))


def _draw(u, lo, count):
    """Indices drawn uniformly (with replacement) from each range [lo, lo + count), from
    uniforms u [G, m] in [0, 1): lo, count [G] -> [G, m]."""
    off = jnp.minimum(jnp.floor(u * count[:, None]).astype(jnp.int32), count[:, None] - 1)
    return lo[:, None] + off


def _rows_dist(params, spec: ModelSpec, data: _TrainData, rows, u_ctx):
    """The model's (mean, log_std) [G, R, o] for rows [G, R] of the fit data, each group of R
    rows sharing one context drawn (by uniforms u_ctx [G, M]) from the other half of its
    first row's episode; all R must lie in one half."""
    ctx = None
    if spec.context_dim:
        idx = _draw(u_ctx, data.ctx_lo[rows[:, 0]], data.ctx_count[rows[:, 0]])
        ctx = jnp.broadcast_to(_pool(params, data.enc[idx])[:, None],
                               rows.shape + (spec.context_dim,))
    return _dist(params, spec, data.x[rows], ctx)


def _rows_nll(params, spec: ModelSpec, data: _TrainData, rows, u_ctx):
    """NLL [G, R] of rows [G, R] of the fit data (contexts as ``_rows_dist``)."""
    mean, log_std = _rows_dist(params, spec, data, rows, u_ctx)
    return _nll(mean, log_std, data.y[rows])


def _rows_loss(params, spec: ModelSpec, data: _TrainData, rows, u_ctx):
    """The training loss [G, R] of rows [G, R]: their NLL, each dim's weighted by
    stop_gradient(std^(2 nll_beta)) (beta-NLL, Seitzer et al. 2022)."""
    if not spec.nll_beta:
        return _rows_nll(params, spec, data, rows, u_ctx)
    mean, log_std = _rows_dist(params, spec, data, rows, u_ctx)
    return dyn.beta_nll(mean, log_std, data.y[rows], spec.nll_beta)


def _step_layout(spec: ModelSpec) -> tuple[int, int, dict[str, tuple[int, ...]]]:
    """(groups G, rows per group R, name -> shape of the uniforms one update draws)."""
    group = CONTEXT_GROUP if spec.context_dim else 1
    g = max(1, spec.batch_size // group)
    n_sel = g // 2 if spec.policy_cvar_eps is not None else 0
    return g, group, {"anchor": (g,), "policy": (n_sel,), "policy_row": (n_sel,),
                      "group": (g, group if group > 1 else 0),
                      "ctx": (g, spec.context_rows if spec.context_dim else 0)}


def _split_uniforms(u, layout: dict[str, tuple[int, ...]]) -> dict[str, jax.Array]:
    """Cut a flat array of uniforms [..., total] into named pieces of the given shapes."""
    out, i = {}, 0
    for name, shape in layout.items():
        size = math.prod(shape)
        out[name] = u[..., i:i + size].reshape(u.shape[:-1] + shape)
        i += size
    return out


def _batch_rows(u: dict[str, jax.Array], spec: ModelSpec, data: _TrainData, selected):
    """Batch row indices [G, R] (their mean NLL is the loss) from uniforms u (_step_layout).

    Each row is uniform over the fit rows (or, for the first half of the groups under CVaR,
    over the rows of a selected policy: a policy uniformly, then one of its rows). With a
    context, G = batch_size / CONTEXT_GROUP groups share one context each: a row drawn as
    above and CONTEXT_GROUP rows drawn uniformly from its half of its episode (each still
    uniform over the fit rows), which makes the encoder's cost per row small.
    """
    n = data.y.shape[0]
    anchors = jnp.minimum(jnp.floor(u["anchor"] * n).astype(jnp.int32), n - 1)
    n_sel = u["policy"].shape[0]
    if n_sel:
        ok = selected & (data.pol_count > 0)
        first = jnp.argsort(~ok, stable=True)           # the selected policies first
        k = jnp.floor(u["policy"] * ok.sum()).astype(jnp.int32)
        pol = first[jnp.minimum(k, ok.sum() - 1)]
        off = _draw(u["policy_row"][:, None], data.pol_start[pol], data.pol_count[pol])[:, 0]
        anchors = anchors.at[:n_sel].set(data.by_policy[off])
    if u["group"].shape[1] == 0:
        return anchors[:, None]
    return _draw(u["group"], data.own_lo[anchors], data.own_count[anchors])


def _refresh(state: _TrainState, spec: ModelSpec, data: _TrainData, n_present: int, u_ctx
             ) -> _TrainState:
    """Measure every policy's NLL on its probe rows [P, m] (contexts from u_ctx [P m, M]) and
    select the worst."""
    p, m = data.probe.shape
    nll = _rows_nll(state.params, spec, data, data.probe.reshape(-1, 1), u_ctx).reshape(p, m)
    w = data.probe_mask.astype(jnp.float32)
    pol_nll = jnp.where(data.pol_count > 0, (nll * w).sum(1) / jnp.maximum(w.sum(1), 1.0),
                        -jnp.inf)
    selected = select_worst(pol_nll, n_worst(spec.policy_cvar_eps, n_present))
    return state.replace(selected=selected, policy_nll=pol_nll)


def _train_blocks(states: _TrainState, data: _TrainData, *, spec: ModelSpec, n_blocks: int,
                  block_len: int, n_present: int) -> tuple[_TrainState, jax.Array]:
    """n_blocks blocks of block_len updates for every seed (states stacked [S, ...]); a CVaR
    refresh opens each block. -> (states, mean loss per block [S, n_blocks]).

    Each block draws all its randomness as one array of uniforms: every separate PRNG call
    in the program cost about a second of compilation on the CPU.
    """
    tx = _optimizer(spec)
    _, _, layout = _step_layout(spec)
    per_step = sum(math.prod(s) for s in layout.values())
    cvar = spec.policy_cvar_eps is not None
    m_ctx = spec.context_rows if spec.context_dim else 0
    n_refresh = data.probe.size * m_ctx if cvar else 0

    def update(state: _TrainState, u):
        u = _split_uniforms(u, layout)
        rows = _batch_rows(u, spec, data, state.selected)
        def loss_fn(p):
            loss = _rows_loss(p, spec, data, rows, u["ctx"]).mean()
            if spec.log_std_bounds == "learned":
                loss = loss + spec.log_std_bound_weight * dyn.bound_penalty(p)
            return loss

        loss, grads = jax.value_and_grad(loss_fn)(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return state.replace(params=params, opt_state=opt_state), loss

    def block(state: _TrainState, _):
        key, k_u = jax.random.split(state.key)
        u = jax.random.uniform(k_u, (n_refresh + block_len * per_step,))
        state = state.replace(key=key)
        if cvar:
            state = _refresh(state, spec, data, n_present,
                             u[:n_refresh].reshape(data.probe.size, m_ctx))
        state, losses = jax.lax.scan(update, state, u[n_refresh:].reshape(block_len, per_step))
        return state, losses.mean()

    def one_seed(state):
        return jax.lax.scan(block, state, None, length=n_blocks)

    return jax.vmap(one_seed)(states)


_train_blocks_jit = jax.jit(_train_blocks,
                            static_argnames=("spec", "n_blocks", "block_len", "n_present"))


# ------------------------------------------------------------ adversarial phase


def _critic(disc: dict, x, y, update_us: bool = False):
    """Conditional Wasserstein critic D(inputs, normalised delta): x [..., d], y [..., o] ->
    ([...], new power-iteration vectors). Every layer spectrally normalised (as
    ``models.discriminator``); it sees the model's inputs, histories and times included."""
    h = jnp.concatenate([x, y], -1)
    new_us = []
    for i, (layer, u) in enumerate(zip(disc["layers"], disc["us"], strict=True)):
        w, u = spectral_normalize(layer["w"], u, update_us)
        new_us.append(u)
        h = h @ w + layer["b"]
        if i < len(disc["layers"]) - 1:
            h = jax.nn.relu(h)
    return h[..., 0], new_us


def _init_critic(key, spec: ModelSpec, d: int, o: int) -> dict:
    k_w, k_u = jax.random.split(key)
    layers = init_mlp(k_w, [d + o, *spec.disc_hidden, 1])
    us = [u / jnp.linalg.norm(u) for u in
          (jax.random.normal(k, (layer["w"].shape[1],))
           for k, layer in zip(jax.random.split(k_u, len(layers)), layers, strict=True))]
    return {"layers": layers, "us": us}


@struct.dataclass
class _AdvState:
    """One seed's adversarial state: the generator (params, Adam), the critic (layers and
    power-iteration vectors, Adam), key, CVaR selection [P] and NLL [P]."""

    params: Any
    opt_state: Any
    disc: Any
    disc_opt: Any
    key: jax.Array
    selected: jax.Array
    policy_nll: jax.Array


def _adversarial_blocks(states: _AdvState, data: _TrainData, *, spec: ModelSpec,
                        n_blocks: int, block_len: int, n_present: int
                        ) -> tuple[_AdvState, jax.Array]:
    """The adversarial phase (WGAIL with a likelihood anchor, as ``train.py``'s adversarial
    step but one-step: fake transitions are the model's samples at real fit rows, histories
    and contexts included): per update, ``disc_updates`` critic updates on real rows vs the
    model's samples at other rows, then one generator update minimising -E[D] of its
    reparameterised samples plus adv_nll_weight x the real batch's NLL. Under CVaR the real
    and fake rows come from the policies ``_refresh`` selects (half of each batch, as the
    likelihood fit). States stacked over seeds. -> (states, mean generator loss per block
    [S, n_blocks])."""
    gen_tx = optax.chain(optax.clip_by_global_norm(10.0), optax.adam(spec.adv_lr))
    disc_tx = optax.adam(spec.disc_lr)
    _, _, layout = _step_layout(spec)
    per_batch = sum(math.prod(s) for s in layout.values())
    cvar = spec.policy_cvar_eps is not None
    m_ctx = spec.context_rows if spec.context_dim else 0
    n_refresh = data.probe.size * m_ctx if cvar else 0
    n_batches = 2 * spec.disc_updates + 2  # real and fake per critic update, then the gen's

    def fake(params, rows, u_ctx, key):
        mean, log_std = _rows_dist(params, spec, data, rows, u_ctx)
        return data.x[rows], mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)

    def update(state: _AdvState, inputs):
        u, key = inputs
        u = u.reshape(n_batches, per_batch)
        batches = [_split_uniforms(u[i], layout) for i in range(n_batches)]
        keys = jax.random.split(key, spec.disc_updates + 1)
        disc, disc_opt = state.disc, state.disc_opt
        for j in range(spec.disc_updates):
            real_u, fake_u = batches[2 * j], batches[2 * j + 1]
            r_rows = _batch_rows(real_u, spec, data, state.selected)
            f_x, f_y = fake(state.params, _batch_rows(fake_u, spec, data, state.selected),
                            fake_u["ctx"], keys[j])
            f_y = jax.lax.stop_gradient(f_y)

            def critic_loss(layers, r_rows=r_rows, f_x=f_x, f_y=f_y, us=disc["us"]):
                d = {"layers": layers, "us": us}
                d_real, new_us = _critic(d, data.x[r_rows], data.y[r_rows], update_us=True)
                d_fake, _ = _critic({"layers": layers, "us": new_us}, f_x, f_y)
                return d_fake.mean() - d_real.mean(), new_us

            (_, new_us), grads = jax.value_and_grad(critic_loss, has_aux=True)(disc["layers"])
            upd, disc_opt = disc_tx.update(grads, disc_opt, disc["layers"])
            disc = {"layers": optax.apply_updates(disc["layers"], upd), "us": new_us}
        real_u, fake_u = batches[-2], batches[-1]
        r_rows = _batch_rows(real_u, spec, data, state.selected)
        f_rows = _batch_rows(fake_u, spec, data, state.selected)

        def gen_loss(p):
            f_x, f_y = fake(p, f_rows, fake_u["ctx"], keys[-1])
            loss = -_critic(disc, f_x, f_y)[0].mean()
            if spec.adv_nll_weight:
                loss = loss + spec.adv_nll_weight * _rows_nll(p, spec, data, r_rows,
                                                              real_u["ctx"]).mean()
            if spec.log_std_bounds == "learned":
                loss = loss + spec.log_std_bound_weight * dyn.bound_penalty(p)
            return loss

        loss, grads = jax.value_and_grad(gen_loss)(state.params)
        upd, opt_state = gen_tx.update(grads, state.opt_state, state.params)
        return state.replace(params=optax.apply_updates(state.params, upd), opt_state=opt_state,
                             disc=disc, disc_opt=disc_opt), loss

    def block(state: _AdvState, _):
        key, k_u, k_n = jax.random.split(state.key, 3)
        u = jax.random.uniform(k_u, (n_refresh + block_len * n_batches * per_batch,))
        state = state.replace(key=key)
        if cvar:
            state = _refresh(state, spec, data, n_present,
                             u[:n_refresh].reshape(data.probe.size, m_ctx))
        u = u[n_refresh:].reshape(block_len, n_batches * per_batch)
        state, losses = jax.lax.scan(update, state, (u, jax.random.split(k_n, block_len)))
        return state, losses.mean()

    return jax.vmap(lambda st: jax.lax.scan(block, st, None, length=n_blocks))(states)


_adversarial_blocks_jit = jax.jit(_adversarial_blocks,
                                  static_argnames=("spec", "n_blocks", "block_len",
                                                   "n_present"))


@functools.partial(jax.jit, static_argnames=("spec", "d", "o"))
def _init_adv_states(states: _TrainState, *, spec: ModelSpec, d: int, o: int) -> _AdvState:
    """Adversarial states from the likelihood fit's final states (fresh Adam moments for the
    generator, as ``train._start_adversarial``)."""
    gen_tx = optax.chain(optax.clip_by_global_norm(10.0), optax.adam(spec.adv_lr))
    disc_tx = optax.adam(spec.disc_lr)

    def one(st: _TrainState):
        key, k_disc = jax.random.split(st.key)
        disc = _init_critic(k_disc, spec, d, o)
        return _AdvState(params=st.params, opt_state=gen_tx.init(st.params), disc=disc,
                         disc_opt=disc_tx.init(disc["layers"]), key=key,
                         selected=st.selected, policy_nll=st.policy_nll)

    return jax.vmap(one)(states)


@functools.partial(jax.jit, static_argnames=("spec", "n_policies"))
def _init_states(params, keys, *, spec: ModelSpec, n_policies: int) -> _TrainState:
    """Training states stacked over seeds from params [S, ...] and keys [S, 2]."""
    tx = _optimizer(spec)

    def init(params, key):
        return _TrainState(params=params, opt_state=tx.init(params), key=key,
                           selected=jnp.ones((n_policies,), bool),
                           policy_nll=jnp.full((n_policies,), jnp.nan, jnp.float32))

    return jax.vmap(init)(params, keys)


def _chunk_plan(steps: int, block_len: int, progress: bool) -> list[tuple[int, int]]:
    """[(n_blocks, block_len), ...] covering ``steps`` updates with few distinct shapes (each
    is a compilation): equal chunks of whole blocks (about 10 when showing progress), then a
    short block for the remainder."""
    full, rest = divmod(steps, block_len)
    plan = []
    if full:
        per = full
        if progress:
            target = max(1, full // 10)
            per = max(d for d in range(1, target + 1) if full % d == 0)
        plan += [(per, block_len)] * (full // per)
    if rest:
        plan.append((1, rest))
    return plan


def _as_rows(x, n: int, what: str) -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim != 1 or arr.size == 0 or not (np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{what}: expected a non-empty 1-d int array, got "
                         f"{arr.dtype} shape {arr.shape}")
    if arr.min() < 0 or arr.max() >= n:
        raise ValueError(f"{what}: expected indices in [0, {n}), got range "
                         f"[{arr.min()}, {arr.max()}]")
    return arr.astype(np.int64)


def _policy_table(policy: np.ndarray, n_policies: int, seed: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows grouped by policy (by_policy, pol_start, pol_count) and each policy's fixed probe
    rows [P, PROBE_ROWS] with mask (all its rows when it has fewer)."""
    by_policy = np.argsort(policy, kind="stable")
    count = np.bincount(policy, minlength=n_policies)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    rng = np.random.default_rng(seed)
    probe = np.zeros((n_policies, PROBE_ROWS), np.int64)
    mask = np.zeros((n_policies, PROBE_ROWS), bool)
    for p in np.flatnonzero(count):
        own = by_policy[start[p]:start[p] + count[p]]
        pick = own if own.size <= PROBE_ROWS else rng.choice(own, PROBE_ROWS, replace=False)
        probe[p, :pick.size] = pick
        mask[p, :pick.size] = True
    return by_policy, start, count, probe, mask


def fit_models(eps: Episodes, fit_episodes: np.ndarray, spec: ModelSpec,
               seeds: Sequence[int] = (0,), *, progress: bool = False) -> FittedModels:
    """Fit one model of ``spec`` per seed to the rows of ``fit_episodes`` [E1], by MLE.

    All seeds train as one vmapped program; their batches, inits and context draws differ.
    """
    spec.validate()
    fit_episodes = np.unique(_as_rows(fit_episodes, eps.n_episodes, "fit_episodes"))
    seeds = tuple(int(s) for s in seeds)
    if not seeds:
        raise ValueError("seeds: expected at least one seed, got none")
    if spec.context_dim:
        _check_context_episodes(eps, fit_episodes, "fit_episodes")
    rows = eps.rows(fit_episodes)
    o, a = eps.obs_size, eps.action_size
    norm = Normalizer.from_data(eps.obs[rows], eps.action[rows], eps.next_obs[rows],
                                ignore_dims=eps.position_dims)

    x, y, enc = _prepare_rows(norm, spec, _gather_rows(eps, spec, rows),
                              eps.next_obs[rows].astype(np.float32))
    halves = {}
    if spec.context_dim:
        pos = np.full(eps.n, -1, np.int64)  # global row -> index among the fit rows
        pos[rows] = np.arange(rows.size)
        for name, other in (("own", False), ("ctx", True)):
            lo, count, inverse = _context_pairs(eps, rows, other=other)
            halves[name + "_lo"], halves[name + "_count"] = pos[lo][inverse], count[inverse]
    else:
        halves = {k: np.zeros(rows.size, np.int64)
                  for k in ("own_lo", "own_count", "ctx_lo", "ctx_count")}
    policy = eps.policy[rows]
    by_policy, pol_start, pol_count, probe, probe_mask = _policy_table(policy, eps.n_policies,
                                                                       seeds[0])
    i32 = jnp.int32
    data = _TrainData(x=x, y=y, enc=enc, **{k: jnp.asarray(v, i32) for k, v in halves.items()},
                      by_policy=jnp.asarray(by_policy, i32),
                      pol_start=jnp.asarray(pol_start, i32), pol_count=jnp.asarray(pol_count, i32),
                      probe=jnp.asarray(probe, i32), probe_mask=jnp.asarray(probe_mask))

    params = jax.tree_util.tree_map(lambda *x: np.stack(x),
                                    *[_init_params(s, spec, o, a) for s in seeds])
    keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for s in seeds])
    states = _init_states(params, keys, spec=spec, n_policies=eps.n_policies)
    n_present = int((pol_count > 0).sum())
    block_len = min(spec.cvar_every, spec.steps)
    plan = _chunk_plan(spec.steps, block_len, progress)
    bar = None
    if progress:
        bar = tqdm(total=spec.steps + spec.adversarial_steps, unit="step", dynamic_ncols=True,
                   desc="fit " + ",".join(spec.extensions))
    losses, done = [], 0
    try:
        for n_blocks, length in plan:
            last_good = states
            states, block_loss = _train_blocks_jit(states, data, spec=spec, n_blocks=n_blocks,
                                                   block_len=length, n_present=n_present)
            block_loss = np.asarray(block_loss)
            if not np.isfinite(block_loss).all():
                seed_i, block = (int(x[0]) for x in np.nonzero(~np.isfinite(block_loss)))
                raise ModelDiverged(seeds[seed_i], done + (block + 1) * length, spec,
                                    last_good.params)
            done += n_blocks * length
            losses.append(block_loss)
            if bar is not None:
                bar.update(n_blocks * length)
                bar.set_postfix(nll=f"{float(losses[-1][:, -1].mean()):.3f}", refresh=False)
        if spec.adversarial_steps:
            states = _fit_adversarial(states, data, spec, n_present, seeds, bar)
    finally:
        if bar is not None:
            bar.close()
    loss_history = np.concatenate(losses, 1)
    fm = FittedModels(params=states.params, norm=norm,
                      ctx_mean=jnp.zeros((len(seeds), spec.context_dim)),
                      ctx_cov=jnp.zeros((len(seeds), spec.context_dim, spec.context_dim)),
                      train_loss=loss_history[:, -1], loss_history=loss_history,
                      policy_nll=np.asarray(states.policy_nll), fit_episodes=fit_episodes,
                      spec=spec, position_dims=tuple(eps.position_dims), seeds=seeds,
                      obs_size=o, action_size=a)
    if spec.context_dim:
        ctx = _episode_contexts(fm, eps, fit_episodes)  # [S, 2 E1, C]
        mean = ctx.mean(1)
        dev = ctx - mean[:, None]
        cov = np.einsum("sni,snj->sij", dev, dev) / max(ctx.shape[1] - 1, 1)
        fm = fm.replace(ctx_mean=jnp.asarray(mean, jnp.float32),
                        ctx_cov=jnp.asarray(cov, jnp.float32))
    return fm


def _fit_adversarial(states: _TrainState, data: _TrainData, spec: ModelSpec, n_present: int,
                     seeds: tuple[int, ...], bar) -> _TrainState:
    """Run the adversarial phase on the likelihood fit's states; -> the states with the
    adversarially trained params (ModelDiverged names the seed and update on a NaN)."""
    adv = _init_adv_states(states, spec=spec, d=int(data.x.shape[1]), o=int(data.y.shape[1]))
    block_len = min(spec.cvar_every, spec.adversarial_steps)
    done = spec.steps
    for n_blocks, length in _chunk_plan(spec.adversarial_steps, block_len, bar is not None):
        last_good = adv
        adv, block_loss = _adversarial_blocks_jit(adv, data, spec=spec, n_blocks=n_blocks,
                                                  block_len=length, n_present=n_present)
        block_loss = np.asarray(block_loss)
        if not np.isfinite(block_loss).all():
            seed_i, block = (int(x[0]) for x in np.nonzero(~np.isfinite(block_loss)))
            raise ModelDiverged(seeds[seed_i], done + (block + 1) * length, spec,
                                last_good.params)
        done += n_blocks * length
        if bar is not None:
            bar.update(n_blocks * length)
            bar.set_postfix(adv_loss=f"{float(block_loss[:, -1].mean()):.3f}", refresh=False)
    return states.replace(params=adv.params, selected=adv.selected, policy_nll=adv.policy_nll)


# ---------------------------------------------------------------------- evaluation


def _check_eps(fm: FittedModels, eps: Episodes) -> None:
    if (eps.obs_size, eps.action_size) != (fm.obs_size, fm.action_size):
        raise ValueError(f"eps: expected obs/action sizes ({fm.obs_size}, {fm.action_size}) "
                         f"of the fitted models, got ({eps.obs_size}, {eps.action_size})")


@jax.jit
def _pair_contexts(params, norm: Normalizer, obs, action, next_obs, mask):
    """Contexts [S, U, C] of U row sets (obs [U, M, o], ..., mask [U, M]) for every seed."""
    enc = _encoder_inputs(norm, obs, action, next_obs)
    return jax.vmap(lambda p: _pool(p, enc, mask))(params)


def _contexts(fm: FittedModels, eps: Episodes, lo: np.ndarray, count: np.ndarray) -> jax.Array:
    """Contexts [S, U, C] of the row ranges [lo, lo + count) (up to M rows of each, spread)."""
    idx, mask = _spread(lo, count, fm.spec.context_rows)
    f32 = np.float32
    return _pair_contexts(fm.params, fm.norm, eps.obs[idx].astype(f32),
                          eps.action[idx].astype(f32), eps.next_obs[idx].astype(f32), mask)


def _episode_contexts(fm: FittedModels, eps: Episodes, episodes: np.ndarray) -> np.ndarray:
    """Contexts [S, 2 E, C] of both halves of each episode."""
    mid = eps.length[episodes] // 2
    lo = np.concatenate([eps.start[episodes], eps.start[episodes] + mid])
    count = np.concatenate([mid, eps.length[episodes] - mid])
    return np.asarray(_contexts(fm, eps, lo, count))


def _row_contexts(fm: FittedModels, eps: Episodes, rows: np.ndarray) -> jax.Array:
    """Each row's context from its episode's other half: [S, n, C] ([S, n, 0] when off)."""
    if not fm.spec.context_dim:
        return jnp.zeros((fm.n_seeds, rows.size, 0), jnp.float32)
    _check_context_episodes(eps, np.unique(eps.episode[rows]), "rows")
    lo, count, inverse = _context_pairs(eps, rows)
    return _contexts(fm, eps, lo, count)[:, inverse]


@functools.partial(jax.jit, static_argnames="spec")
def _predict_jit(params, norm: Normalizer, spec: ModelSpec, raw: dict, ctx):
    x = _inputs(norm, spec, raw)
    mean, log_std = jax.vmap(lambda p, c: _dist(p, spec, x, c))(params, ctx)
    return mean, jnp.exp(log_std)


def _pad(n: int) -> int:
    """Padded chunk length: the next power of two (at least 256), at most PREDICT_CHUNK, so
    few distinct shapes are compiled."""
    return min(PREDICT_CHUNK, max(256, 1 << (n - 1).bit_length()))


def predict(fm: FittedModels, eps: Episodes, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predictive Gaussian of the normalised delta of the given rows of eps, with their true
    histories, times and episode context (other half). -> (mean [S, n, o], std [S, n, o])."""
    _check_eps(fm, eps)
    rows = _as_rows(rows, eps.n, "rows")
    ctx_all = _row_contexts(fm, eps, rows)
    chunk = _pad(rows.size)
    means, stds = [], []
    for lo in range(0, rows.size, chunk):
        r = rows[lo:lo + chunk]
        k = r.size
        r = np.concatenate([r, np.full(chunk - k, r[0])])
        ctx = ctx_all[:, lo:lo + k]
        ctx = jnp.concatenate([ctx, jnp.zeros((ctx.shape[0], chunk - k, ctx.shape[2]))], 1)
        mean, std = _predict_jit(fm.params, fm.norm, fm.spec,
                                 _gather_rows(eps, fm.spec, r), ctx)
        means.append(np.asarray(mean)[:, :k])
        stds.append(np.asarray(std)[:, :k])
    return np.concatenate(means, 1), np.concatenate(stds, 1)


def delta_scale(fm: FittedModels) -> np.ndarray:
    """[o] the delta std that normalises the model's targets."""
    return np.asarray(fm.norm.delta_std, np.float64)


def normalized_delta(fm: FittedModels, eps: Episodes, rows: np.ndarray) -> np.ndarray:
    """The model's target for the rows: (delta - delta_mean) / delta_std. -> [n, o]"""
    rows = _as_rows(rows, eps.n, "rows")
    mean = np.asarray(fm.norm.delta_mean, np.float64)
    return (eps.delta[rows] - mean) / delta_scale(fm)


def heldout_metrics(fm: FittedModels, eps: Episodes, rows: np.ndarray) -> dict[str, np.ndarray]:
    """{"nll": [S] mean per-row Gaussian NLL of the normalised delta (summed over dims),
    "mse": [S] mean squared error of the mean (normalised units, mean over dims)}."""
    mean, std = predict(fm, eps, rows)
    y = normalized_delta(fm, eps, rows)[None]
    z = (y - mean) / std
    nll = (0.5 * z**2 + np.log(std) + 0.5 * np.log(2 * np.pi)).sum(-1).mean(-1)
    return {"nll": nll, "mse": ((y - mean) ** 2).mean((-1, -2))}


@functools.partial(jax.jit, static_argnames="spec")
def _kstep_jit(params, norm: Normalizer, spec: ModelSpec, obs0, past_obs, past_valid, other_raw,
               ctx, target, weight):
    """Open-loop mean rollouts from obs0 [n, o] for k_max steps, summed squared errors.

    past_obs [n, K, o] / past_valid [n, K]: the real history before the start; other_raw: the
    per-step inputs that do not depend on the rollout (action [n, k, a], past_act, its mask,
    times); ctx [S, n, k, C]; target [n, k, o] real next states; weight [n] (0 for padding).
    -> [S, k] sum over starts of the mean-over-dims squared error in normalised obs units.
    """
    other = _other_inputs(norm, other_raw["action"], other_raw["past_act"],
                          other_raw["past_act_valid"], other_raw["times"])   # [n, k, d]
    lo = norm.obs_mean - OBS_CLIP * norm.obs_std
    hi = norm.obs_mean + OBS_CLIP * norm.obs_std

    def one_seed(p, c):
        def step(carry, j):
            obs, past, valid = carry
            x = jnp.concatenate([_obs_inputs(norm, obs, past, valid), other[:, j]], -1)
            mean, _ = _dist(p, spec, x, c[:, j])
            nxt = jnp.clip(norm.next_from_delta(obs, mean), lo, hi)
            err = (((nxt - target[:, j]) / norm.obs_std) ** 2).mean(-1)
            return (nxt, _shift(past, obs), _shift_valid(valid)), (err * weight).sum()

        _, sse = jax.lax.scan(step, (obs0, past_obs, past_valid), jnp.arange(target.shape[1]))
        return sse

    return jax.vmap(one_seed)(params, ctx)


def kstep_errors(fm: FittedModels, eps: Episodes, episodes: np.ndarray, k_max: int = 20,
                 n_starts: int | None = None, seed: int = 0) -> np.ndarray:
    """RMSE [S, k_max] of open-loop rollouts of the model mean, k = 1..k_max steps ahead.

    Starts are real states of ``episodes`` with at least k_max steps left (n_starts of them
    drawn at random, or all); each rollout is driven by the logged actions. The obs history
    is real before the start and the rollout's own after; past actions, times and each step's
    context (its row's other half) are the real ones. Error: (predicted - real next state) /
    obs_std, mean over dims and starts, square-rooted.
    """
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
            rng = np.random.default_rng(seed)
            starts = np.sort(rng.choice(starts, n_starts, replace=False))
    spec = fm.spec
    chunk = max(1, _pad(starts.size * k_max) // k_max)
    sse = np.zeros((fm.n_seeds, k_max))
    for lo in range(0, starts.size, chunk):
        s = starts[lo:lo + chunk]
        k = s.size
        s = np.concatenate([s, np.full(chunk - k, s[0])])
        steps = s[:, None] + np.arange(k_max)                    # [chunk, k_max] rows
        flat = steps.reshape(-1)
        raw = _gather_rows(eps, dataclasses.replace(spec, obs_history=0), flat)
        other = {key: raw[key].reshape(chunk, k_max, *raw[key].shape[1:])
                 for key in ("action", "past_act", "past_act_valid", "times")}
        past, valid = history(eps, eps.obs, spec.obs_history, s)
        ctx = _row_contexts(fm, eps, flat)
        ctx = ctx.reshape(ctx.shape[0], chunk, k_max, ctx.shape[-1])
        target = eps.next_obs[steps].astype(np.float32)
        weight = (np.arange(chunk) < k).astype(np.float32)
        sse += np.asarray(_kstep_jit(fm.params, fm.norm, spec,
                                     eps.obs[s].astype(np.float32), past.astype(np.float32),
                                     valid, other, ctx, target, weight))
    return np.sqrt(sse / starts.size)


# ------------------------------------------------------------------------ rollouts


@struct.dataclass
class _Rollout:
    """P x n simulated episodes: obs [P, n, o], past_obs [P, n, K_o, o] / valid, past_act
    [P, n, K_a, a] / valid, alive [P, n], ret [P, n], t []."""

    obs: jax.Array
    past_obs: jax.Array
    past_obs_valid: jax.Array
    past_act: jax.Array
    past_act_valid: jax.Array
    alive: jax.Array
    ret: jax.Array
    t: jax.Array


def _shift(past, new):
    """Push new [..., x] onto the front of past [..., K, x], dropping the oldest (K = 0:
    nothing to keep)."""
    if past.shape[-2] == 0:
        return past
    return jnp.concatenate([new[..., None, :].astype(past.dtype), past[..., :-1, :]], -2)


def _shift_valid(valid):
    """The validity mask [..., K] after a _shift: the newest entry is always valid."""
    return _shift(valid[..., None], jnp.ones(valid.shape[:-1] + (1,), bool))[..., 0]


def _rollout_values(params, norm: Normalizer, spec: ModelSpec, ctx_mean, ctx_sqrt, policies,
                    start_obs, key, gamma, *, reward_fn: Callable, done_fn: Callable,
                    horizon: int, n_episodes: int):
    n_pol = num_policies(policies)
    o, a = start_obs.shape[1], norm.act_mean.shape[0]
    k_start, k_ctx, k_pol, k_dyn = jax.random.split(key, 4)
    shape = (n_pol, n_episodes)
    obs0 = start_obs[jax.random.randint(k_start, shape, 0, start_obs.shape[0])]
    c = ctx_mean + jax.random.normal(k_ctx, shape + (spec.context_dim,)) @ ctx_sqrt.T
    ko, ka = spec.obs_history, spec.action_history
    roll = _Rollout(obs=obs0, past_obs=jnp.zeros(shape + (ko, o)),
                    past_obs_valid=jnp.zeros(shape + (ko,), bool),
                    past_act=jnp.zeros(shape + (ka, a)),
                    past_act_valid=jnp.zeros(shape + (ka,), bool),
                    alive=jnp.ones(shape, bool), ret=jnp.zeros(shape),
                    t=jnp.zeros((), jnp.int32))
    lo = norm.obs_mean - OBS_CLIP * norm.obs_std
    hi = norm.obs_mean + OBS_CLIP * norm.obs_std
    act = jax.vmap(sample_action)  # over policies; each call batches its n episodes

    def step(roll: _Rollout, keys):
        k_act, k_noise = keys
        action, _, _ = act(policies, roll.obs, k_act)
        tf = roll.t.astype(jnp.float32)
        times = {"order": jnp.ones(shape), "step": jnp.broadcast_to(tf / horizon, shape)}
        t_in = jnp.stack([times[name] for name in spec.time_inputs], -1) \
            if spec.time_inputs else jnp.zeros(shape + (0,))
        x = jnp.concatenate([
            _obs_inputs(norm, roll.obs, roll.past_obs, roll.past_obs_valid),
            _other_inputs(norm, action, roll.past_act, roll.past_act_valid, t_in)], -1)
        mean, log_std = _dist(params, spec, x, c)
        delta_n = mean + jnp.exp(log_std) * jax.random.normal(k_noise, mean.shape)
        next_obs = jnp.clip(norm.next_from_delta(roll.obs, delta_n), lo, hi)
        live = roll.alive
        reward = reward_fn(roll.obs, action, next_obs)
        done = done_fn(next_obs) > 0.5
        ret = roll.ret + jnp.where(live, jnp.asarray(gamma, jnp.float32) ** tf * reward, 0.0)
        return _Rollout(
            obs=next_obs, past_obs=_shift(roll.past_obs, roll.obs),
            past_obs_valid=_shift_valid(roll.past_obs_valid),
            past_act=_shift(roll.past_act, action),
            past_act_valid=_shift_valid(roll.past_act_valid),
            alive=live & ~done, ret=ret, t=roll.t + 1), None

    keys = (jax.random.split(k_pol, (horizon, n_pol)), jax.random.split(k_dyn, horizon))
    roll, _ = jax.lax.scan(step, roll, keys)
    return roll.ret.mean(1)


_rollout_values_jit = jax.jit(_rollout_values, static_argnames=(
    "spec", "reward_fn", "done_fn", "horizon", "n_episodes"))


def rollout_values(fm: FittedModels, seed_index: int, policies, start_obs: np.ndarray, *,
                   reward_fn: Callable, done_fn: Callable, horizon: int, n_episodes: int,
                   gamma: float, key: jax.Array) -> np.ndarray:
    """Mean discounted return [P] of each policy (stacked params, ``rl2s_jax.policy.policy``) over
    n_episodes episodes of at most ``horizon`` steps simulated in model ``seed_index``.

    Episodes start from rows of start_obs [N0, o] drawn at random and end when done_fn(s')
    fires; next states are sampled (mean + std * noise, kept within +-10 data stds); the
    context is drawn per episode from the fitted Gaussian; time inputs are order = 1 ("now")
    and step = t / horizon.
    """
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
    params = jax.tree_util.tree_map(lambda x: x[seed_index], fm.params)
    c = fm.spec.context_dim
    w, v = np.linalg.eigh(np.asarray(fm.ctx_cov[seed_index], np.float64).reshape(c, c))
    root = v * np.sqrt(np.maximum(w, 0.0))  # a square root of the covariance, also if singular
    values = _rollout_values_jit(params, fm.norm, fm.spec, fm.ctx_mean[seed_index],
                                 jnp.asarray(root, jnp.float32), policies,
                                 jnp.asarray(start_obs, jnp.float32), key, gamma,
                                 reward_fn=reward_fn, done_fn=done_fn, horizon=int(horizon),
                                 n_episodes=int(n_episodes))
    return np.asarray(values)
