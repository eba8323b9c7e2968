"""The dynamics-model family that training (``train.py``) and diagnosis (``diagnose/model.py``)
both use: an ensemble of Gaussian models of the normalised state change.

A member is p(delta_n | x) = N(mean, diag(std^2)) over delta_n = (s' - s - delta_mean) /
delta_std, an MLP of the inputs x. ``DynamicsSpec`` says which member:

- inputs: the normalised s (position dims zeroed) and a; optionally the k previous actions /
  observations of the episode with their validity masks (``action_history``,
  ``obs_history``), the episode's place in the recording order and the step's place in the
  episode (``time_inputs``), and a per-episode latent ``context_dim`` that an encoder
  mean-pools from (s, a, delta) rows of the same episode (``enc``);
- noise: ``"state"`` (a log-std head of the inputs) or ``"global"`` (one learned log-std per
  dim);
- matmul dtype: ``"float32"`` or ``"bfloat16"`` (the hidden layers' matmuls take bf16 inputs
  and weights and accumulate in float32, forward and backward: ``matmul``; parameters and
  every output stay float32);
- log-std bounds: ``"fixed"`` (softly within [LOG_STD_MIN, LOG_STD_MAX]) or ``"learned"`` (per
  dim, as PETS / mbrl-lib: parameters ``max_log_std`` / ``min_log_std`` initialised at those
  constants; the loss adds ``weight * (sum max - sum min)`` to keep them tight).

Parameters of one member are a dict: ``layers`` (the MLP), and ``log_std`` / ``max_log_std``,
``min_log_std`` / ``enc`` / the markers ``silu`` and ``bf16`` where the spec asks for them;
the apply functions read the kind of noise, bounds, activation and matmul dtype from which
keys are present. An ensemble stacks E members on a leading axis
(``init_ensemble``); ``map_members`` applies a one-member function to every member (vmap; for
E = 1 the member itself, so a one-member ensemble computes exactly what a single model does).

Ensemble use: members are ranked by held-out NLL (``rank_members``: rank 0 the lowest); the
``n_elites`` best are the elites. Rollouts draw a next state (``ensemble_moments``,
``ensemble_sample``) from a random elite per sample (``"random"``), from the elites' average
(``"mean"``) or from the best member (``"fixed"``). ``disagreement`` measures how much the
elites' means differ (normalised delta units). Everything is a pure function of pytrees.
Shapes: E members, o = obs size, a = action size, C = context_dim.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rl2s_jax.policy.policy import init_mlp

LOG_STD_MIN = -5.0  # std >= 0.7% of the data's delta std: sharper made BC collapse on Hopper
LOG_STD_MAX = 1.0
NOISE_KINDS = ("state", "global")
BOUND_KINDS = ("fixed", "learned")
ACTIVATIONS = ("relu", "silu")
TIME_INPUTS = ("order", "step")
MEMBER_MODES = ("random", "mean", "fixed")
UNCERTAINTY_KINDS = ("std", "max_pairwise")
MATMUL_DTYPES = ("float32", "bfloat16")


@struct.dataclass
class Normalizer:
    """Per-dimension mean/std of obs [o], action [a] and delta = next_obs - obs [o], and
    obs_input_mask [o]: 1 for the obs dims the networks see, 0 for those left out (absolute
    positions, which the dynamics do not depend on)."""

    obs_mean: jax.Array
    obs_std: jax.Array
    act_mean: jax.Array
    act_std: jax.Array
    delta_mean: jax.Array
    delta_std: jax.Array
    obs_input_mask: jax.Array | None = None  # None: every dim

    @classmethod
    def from_data(cls, obs, action, next_obs, min_std: float = 1e-6,
                  ignore_dims: tuple[int, ...] = ()) -> Normalizer:
        """Statistics of transitions obs [N, o], action [N, a], next_obs [N, o] (NumPy, float64);
        ``ignore_dims``: obs dims to leave out of the networks' inputs."""
        obs, action, next_obs = (np.asarray(x, np.float64) for x in (obs, action, next_obs))
        delta = next_obs - obs

        def stats(x):
            return (jnp.asarray(x.mean(0), jnp.float32),
                    jnp.asarray(np.maximum(x.std(0), min_std), jnp.float32))

        (om, os_), (am, as_), (dm, ds) = stats(obs), stats(action), stats(delta)
        mask = np.ones(obs.shape[1], np.float32)
        for d in ignore_dims:
            if not 0 <= d < obs.shape[1]:
                raise ValueError(f"ignore_dims: expected obs dims in [0, {obs.shape[1]}), got {d}")
            mask[d] = 0.0
        return cls(om, os_, am, as_, dm, ds, jnp.asarray(mask))

    def norm_obs(self, obs):
        return (obs - self.obs_mean) / self.obs_std

    def input_obs(self, obs):
        """The normalised obs as the networks see it (left-out dims zeroed)."""
        x = self.norm_obs(obs)
        return x if self.obs_input_mask is None else x * self.obs_input_mask

    def norm_act(self, action):
        return (action - self.act_mean) / self.act_std

    def norm_delta(self, obs, next_obs):
        return (next_obs - obs - self.delta_mean) / self.delta_std

    def next_from_delta(self, obs, delta_n):
        return obs + self.delta_mean + self.delta_std * delta_n

    def clip_obs(self, obs, obs_clip: float | None):
        """obs kept within +-obs_clip data stds of the obs mean (None: unchanged)."""
        if obs_clip is None:
            return obs
        return jnp.clip(obs, self.obs_mean - obs_clip * self.obs_std,
                        self.obs_mean + obs_clip * self.obs_std)


# ------------------------------------------------------------------------- the spec


def _is_int(v) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


@dataclasses.dataclass(frozen=True)
class DynamicsSpec:
    """One member of the family (hashable: a static argument of compiled programs).

    hidden: the MLP's hidden sizes; noise: "state" | "global"; log_std_bounds: "fixed" |
    "learned"; activation: of the hidden layers, "relu" | "silu" (x sigmoid(x), PETS' and
    MBPO's "swish"; a SiLU member carries a marker ``params["silu"]``, a scalar 0 that no
    computation reads, so no update moves it, and its parameters alone say how to apply it;
    an empty array would not, since orbax refuses to save one); action_history /
    obs_history: past actions / observations fed as inputs; time_inputs: subset of ("order",
    "step"); context_dim: per-episode latent (0: off) from an encoder with hidden sizes
    context_hidden.
    """

    hidden: tuple[int, ...] = (512, 512, 512, 512)
    noise: str = "state"
    log_std_bounds: str = "fixed"
    activation: str = "relu"
    action_history: int = 0
    obs_history: int = 0
    time_inputs: tuple[str, ...] = ()
    context_dim: int = 0
    context_hidden: tuple[int, ...] = (64, 64)
    matmul_dtype: str = "float32"

    def validate(self, names: dict[str, str] | None = None) -> DynamicsSpec:
        """Raise ValueError naming the first bad field (``names`` maps a field to the name the
        caller's config gives it); returns self."""
        name = (names or {}).get
        for f in ("action_history", "obs_history", "context_dim"):
            v = getattr(self, f)
            if not _is_int(v) or v < 0:
                raise ValueError(f"{name(f, f)}: expected an int >= 0, got {v!r}")
        for f, kinds in (("noise", NOISE_KINDS), ("log_std_bounds", BOUND_KINDS),
                         ("activation", ACTIVATIONS), ("matmul_dtype", MATMUL_DTYPES)):
            if getattr(self, f) not in kinds:
                raise ValueError(f"{name(f, f)}: expected one of "
                                 f"{', '.join(map(repr, kinds))}, got {getattr(self, f)!r}")
        t = self.time_inputs
        if (not isinstance(t, tuple) or any(x not in TIME_INPUTS for x in t)
                or len(set(t)) != len(t)):
            raise ValueError(f"{name('time_inputs', 'time_inputs')}: expected a tuple of "
                             f"distinct names from {TIME_INPUTS}, got {t!r}")
        for f in ("hidden", "context_hidden"):
            v = getattr(self, f)
            if not (isinstance(v, tuple) and v and all(_is_int(h) and h > 0 for h in v)):
                raise ValueError(f"{name(f, f)}: expected a non-empty tuple of positive ints, "
                                 f"got {v!r}")
        return self

    @property
    def markov(self) -> bool:
        """True when the inputs are the current (s, a) only (a ``Simulator`` can step it)."""
        return not (self.action_history or self.obs_history or self.time_inputs
                    or self.context_dim)

    def input_size(self, o: int, a: int) -> int:
        return (o + self.obs_history * (o + 1) + a + self.action_history * (a + 1)
                + len(self.time_inputs) + self.context_dim)

    def output_size(self, o: int) -> int:
        return 2 * o if self.noise == "state" else o


# ------------------------------------------------------------------------ parameters


def init_member(key: jax.Array, spec: DynamicsSpec, obs_size: int, action_size: int) -> dict:
    """One member's parameters (JAX PRNG). Without a context the MLP takes ``key`` itself, so
    the default spec's layers are ``init_mlp(key, [o + a, *hidden, 2 o], 0.01)``."""
    o, a = obs_size, action_size
    k_layers, k_enc = jax.random.split(key) if spec.context_dim else (key, None)
    params = {"layers": init_mlp(k_layers, [spec.input_size(o, a), *spec.hidden,
                                            spec.output_size(o)], last_scale=0.01)}
    _add_extras(params, spec, o)
    if spec.context_dim:
        params["enc"] = init_mlp(k_enc, [2 * o + a, *spec.context_hidden, spec.context_dim])
    return params


def _mlp_numpy(rng: np.random.Generator, sizes: Sequence[int], last_scale: float = 1.0
               ) -> list[dict]:
    """Layers as ``policies.init_mlp`` makes them (LeCun-normal weights, zero biases, last
    layer scaled), drawn by NumPy."""
    layers = [{"w": (rng.standard_normal((a, b)) / math.sqrt(a)).astype(np.float32),
               "b": np.zeros((b,), np.float32)} for a, b in zip(sizes[:-1], sizes[1:], strict=True)]
    layers[-1]["w"] = layers[-1]["w"] * np.float32(last_scale)
    return layers


def init_member_numpy(seed: int, spec: DynamicsSpec, obs_size: int, action_size: int) -> dict:
    """One member's parameters drawn by NumPy from ``seed`` (diagnosis: compiling JAX's PRNG
    for every spec cost seconds per fit on the CPU)."""
    o, a = obs_size, action_size
    rng = np.random.default_rng([seed, 0x5EED])
    params = {"layers": _mlp_numpy(rng, [spec.input_size(o, a), *spec.hidden,
                                         spec.output_size(o)], 0.01)}
    _add_extras(params, spec, o, np)
    if spec.context_dim:
        params["enc"] = _mlp_numpy(rng, [2 * o + a, *spec.context_hidden, spec.context_dim])
    return params


def _add_extras(params: dict, spec: DynamicsSpec, o: int, xp=jnp) -> None:
    if spec.activation == "silu":
        params["silu"] = xp.zeros((), xp.float32)
    if spec.matmul_dtype == "bfloat16":
        params["bf16"] = xp.zeros((), xp.float32)
    if spec.noise == "global":
        params["log_std"] = xp.zeros((o,), xp.float32)
    if spec.log_std_bounds == "learned":
        params["max_log_std"] = xp.full((o,), LOG_STD_MAX, xp.float32)
        params["min_log_std"] = xp.full((o,), LOG_STD_MIN, xp.float32)


def init_ensemble(key: jax.Array, spec: DynamicsSpec, obs_size: int, action_size: int,
                  n_members: int) -> dict:
    """E members stacked on a leading axis; member i from ``split(key, E)[i]`` (E = 1: from
    ``key``, as a single model)."""
    if n_members == 1:
        return jax.tree_util.tree_map(lambda x: x[None],
                                      init_member(key, spec, obs_size, action_size))
    return jax.vmap(lambda k: init_member(k, spec, obs_size, action_size))(
        jax.random.split(key, n_members))


def member_keys(key: jax.Array, n_members: int) -> jax.Array:
    """Per-member keys [E, 2] (E = 1: ``key`` itself, as a single model uses it)."""
    return key[None] if n_members == 1 else jax.random.split(key, n_members)


def n_members(params) -> int:
    return int(jax.tree_util.tree_leaves(params)[0].shape[0])


def map_members(fn: Callable, params, *per_member):
    """fn(member params, *member slices of ``per_member``) for every member, stacked [E, ...].

    vmap over the leading axis; for E = 1 the member itself (exactly a single model's
    computation)."""
    if n_members(params) == 1:
        first = lambda t: jax.tree_util.tree_map(lambda x: x[0], t)
        out = fn(first(params), *(first(t) for t in per_member))
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], out)
    return jax.vmap(fn)(params, *per_member)


def weight_mask(params):
    """True for the MLP weight matrices (what weight decay shrinks), False elsewhere."""
    def is_weight(path, _):
        keys = [getattr(p, "key", None) for p in path]
        return keys[-1] == "w" and keys[0] in ("layers", "enc")
    return jax.tree_util.tree_map_with_path(is_weight, params)


# ------------------------------------------------------------------------------ inputs


def markov_inputs(norm: Normalizer, obs, action):
    """obs [..., o], action [..., a] -> [..., o + a]: the inputs of a Markov member."""
    return jnp.concatenate([norm.input_obs(obs), norm.norm_act(action)], -1)


def obs_inputs(norm: Normalizer, obs, past_obs, past_obs_valid):
    """obs [..., o], past_obs [..., K, o], valid [..., K] -> [..., o + K o + K]."""
    v = past_obs_valid.astype(jnp.float32)
    past = norm.input_obs(past_obs) * v[..., None]
    return jnp.concatenate([norm.input_obs(obs), past.reshape(*past.shape[:-2], -1), v], -1)


def other_inputs(norm: Normalizer, action, past_act, past_act_valid, times):
    """action [..., a], past_act [..., K, a], valid [..., K], times [..., T] in [0, 1]
    -> [..., a + K a + K + T]."""
    v = past_act_valid.astype(jnp.float32)
    past = norm.norm_act(past_act) * v[..., None]
    return jnp.concatenate([norm.norm_act(action), past.reshape(*past.shape[:-2], -1), v,
                            2.0 * times - 1.0], -1)


def model_inputs(norm: Normalizer, raw: dict):
    """The inputs (without the context) of raw rows: obs, past_obs, past_obs_valid, action,
    past_act, past_act_valid, times (see ``obs_inputs`` / ``other_inputs``). With no history
    and no times this equals ``markov_inputs``."""
    return jnp.concatenate([
        obs_inputs(norm, raw["obs"], raw["past_obs"], raw["past_obs_valid"]),
        other_inputs(norm, raw["action"], raw["past_act"], raw["past_act_valid"],
                     raw["times"])], -1)


def encoder_inputs(norm: Normalizer, obs, action, next_obs):
    """[..., o], [..., a], [..., o] -> [..., 2 o + a]."""
    return jnp.concatenate([norm.input_obs(obs), norm.norm_act(action),
                            norm.norm_delta(obs, next_obs)], -1)


def pool_context(params: dict, enc_in, mask=None):
    """Context: mean of the encoder's embeddings. enc_in [..., M, 2o + a], mask [..., M]
    -> [..., C]."""
    emb = relu_mlp(params["enc"], enc_in)
    if mask is None:
        return emb.mean(-2)
    w = mask.astype(jnp.float32)[..., None]
    return (emb * w).sum(-2) / jnp.maximum(w.sum(-2), 1.0)


# ------------------------------------------------------------------------------ apply


@jax.custom_vjp
def _bf16_matmul(x: jax.Array, w: jax.Array) -> jax.Array:
    return _bf16_matmul_fwd(x, w)[0]


def _dot_f32(a: jax.Array, b: jax.Array, contract: tuple) -> jax.Array:
    """tensordot of bf16 operands, accumulated in float32. XLA's CPU runtime refuses some
    bf16 x bf16 -> f32 dots ("Unsupported element type for DotThunk"): there the operands go
    up to float32 first, which gives the same products (a bf16 product is exact in float32)
    and accumulation; elsewhere (the GPU) the dot takes bf16 operands."""
    if jax.default_backend() == "cpu":
        a, b = a.astype(jnp.float32), b.astype(jnp.float32)
    return jnp.tensordot(a, b, axes=contract, preferred_element_type=jnp.float32)


def _bf16_matmul_fwd(x, w):
    xb, wb = x.astype(jnp.bfloat16), w.astype(jnp.bfloat16)
    return _dot_f32(xb, wb, ((xb.ndim - 1,), (0,))), (xb, wb)


def _bf16_matmul_bwd(res, g):
    # the backward matmuls in bf16 as well (JAX's own transpose of a bf16 x bf16 -> f32 dot
    # multiplies the f32 cotangent by the upcast operand: float32 matmuls)
    xb, wb = res
    gb = g.astype(jnp.bfloat16)
    lead = tuple(range(xb.ndim - 1))
    dx = _dot_f32(gb, wb, ((gb.ndim - 1,), (1,)))
    dw = _dot_f32(xb, gb, (lead, lead))
    return dx, dw


_bf16_matmul.defvjp(_bf16_matmul_fwd, _bf16_matmul_bwd)


def matmul(x: jax.Array, w: jax.Array, dtype: str = "float32") -> jax.Array:
    """x [..., i] @ w [i, j] -> [..., j] float32. dtype "bfloat16": x and w rounded to bf16,
    products accumulated in float32, and the gradient's two matmuls likewise (the cotangent
    rounded to bf16): mixed precision for the GPU's bf16 tensor cores. "float32": ``x @ w``."""
    if dtype == "float32":
        return x @ w
    if dtype != "bfloat16":
        raise ValueError(f"matmul_dtype: expected one of {MATMUL_DTYPES}, got {dtype!r}")
    return _bf16_matmul(x.astype(jnp.float32), w.astype(jnp.float32))


def relu_mlp(layers: list[dict], x: jax.Array, activation: Callable = jax.nn.relu,
             matmul_dtype: str = "float32") -> jax.Array:
    """The MLP; ``matmul_dtype`` applies to the hidden layers' matmuls (``matmul``), the
    output layer's stays float32."""
    for layer in layers[:-1]:
        x = activation(matmul(x, layer["w"], matmul_dtype) + layer["b"])
    return x @ layers[-1]["w"] + layers[-1]["b"]


def bounded_log_std(raw: jax.Array, params: dict | None = None) -> jax.Array:
    """Smoothly bound log-std to about [lo, hi]: the constants, or the member's learned
    ``min_log_std`` / ``max_log_std``. It can exceed hi by log(1 + e^(lo - hi)) (0.0025 for
    the constants); gradients never vanish outright."""
    if params is not None and "max_log_std" in params:
        lo, hi = params["min_log_std"], params["max_log_std"]
    else:
        lo, hi = LOG_STD_MIN, LOG_STD_MAX
    x = hi - jax.nn.softplus(hi - raw)
    return lo + jax.nn.softplus(x - lo)


def member_dist(params: dict, x: jax.Array, ctx: jax.Array | None = None
                ) -> tuple[jax.Array, jax.Array]:
    """One member's Gaussian over the normalised delta. x [..., d], ctx [..., C] or None
    -> (mean, log_std), each [..., o]."""
    if ctx is not None:
        x = jnp.concatenate([x, ctx], -1)
    out = relu_mlp(params["layers"], x, jax.nn.silu if "silu" in params else jax.nn.relu,
                   "bfloat16" if "bf16" in params else "float32")
    if "log_std" in params:
        return out, jnp.broadcast_to(bounded_log_std(params["log_std"], params), out.shape)
    mean, raw = jnp.split(out, 2, axis=-1)
    return mean, bounded_log_std(raw, params)


def gaussian_nll_per_dim(mean, log_std, y):
    """Gaussian NLL of y, per element. -> [..., o]"""
    z = (y - mean) * jnp.exp(-log_std)
    return 0.5 * z**2 + log_std + 0.5 * jnp.log(2 * jnp.pi)


def gaussian_nll(mean, log_std, y):
    """Gaussian NLL of y, summed over the last axis. -> [...]"""
    return jnp.sum(gaussian_nll_per_dim(mean, log_std, y), -1)


def beta_nll(mean, log_std, y, beta: float):
    """beta-NLL (Seitzer et al. 2022), summed over the last axis: each element's Gaussian
    NLL weighted by stop_gradient(std^(2 beta)). Its gradient in the mean is that of the
    NLL times std^(2 beta): at beta = 1, (mean - y), as under squared error. -> [...]"""
    weight = jax.lax.stop_gradient(jnp.exp(2.0 * beta * log_std))
    return jnp.sum(weight * gaussian_nll_per_dim(mean, log_std, y), -1)


def bound_penalty(params: dict) -> jax.Array:
    """sum(max_log_std) - sum(min_log_std) of a member with learned bounds (else 0): the
    PETS term that keeps the learned bounds tight. -> []"""
    if "max_log_std" not in params:
        return jnp.zeros(())
    return jnp.sum(params["max_log_std"]) - jnp.sum(params["min_log_std"])


def ensemble_dist(params, x: jax.Array, ctx: jax.Array | None = None
                  ) -> tuple[jax.Array, jax.Array]:
    """Every member's Gaussian. -> (mean, log_std), each [E, ..., o]."""
    return map_members(lambda p: member_dist(p, x, ctx), params)


# ---------------------------------------------------------------------------- ensembles


def rank_members(nll: jax.Array) -> jax.Array:
    """Rank [E] int32 of each member by held-out NLL [E]: 0 = lowest; ties to the lower
    index; NaN ranks last."""
    nll = jnp.where(jnp.isnan(nll), jnp.inf, nll)
    order = jnp.argsort(nll, stable=True)
    return jnp.zeros_like(order).at[order].set(jnp.arange(nll.shape[0], dtype=order.dtype)
                                               ).astype(jnp.int32)


def elite_mask(rank: jax.Array | None, n_elites: int | None, n: int) -> jax.Array:
    """[E] bool: the n_elites best-ranked members (all when rank or n_elites is None)."""
    if rank is None or n_elites is None:
        return jnp.ones((n,), bool)
    return rank < n_elites


def ensemble_moments(means: jax.Array, log_stds: jax.Array, key: jax.Array | None, *,
                     rank: jax.Array | None = None, n_elites: int | None = None,
                     mode: str = "random") -> tuple[jax.Array, jax.Array, jax.Array | None]:
    """The Gaussian a rollout step samples from, out of the members' (means, log_stds)
    [E, ..., o]. -> (mean [..., o], log_std [..., o], the key left for the noise).

    "random": one elite per sample, drawn uniformly (uses a split of ``key``); "mean": the
    elites' average mean, with std = sqrt(mean of the elites' variances); "fixed": the
    best-ranked member. One member: that member, whatever the mode (``key`` untouched).
    """
    E = means.shape[0]
    if E == 1:
        return means[0], log_stds[0], key
    if mode == "fixed":
        best = jnp.argmin(jnp.arange(E) if rank is None else rank)
        return means[best], log_stds[best], key
    elite = elite_mask(rank, n_elites, E)
    if mode == "mean":
        w = (elite / elite.sum()).astype(means.dtype).reshape((E,) + (1,) * (means.ndim - 1))
        var = jnp.sum(w * jnp.exp(2.0 * log_stds), 0)
        return jnp.sum(w * means, 0), 0.5 * jnp.log(var), key
    if mode != "random":
        raise ValueError(f"member_mode: expected one of {MEMBER_MODES}, got {mode!r}")
    k_member, k_noise = jax.random.split(key)
    pick = jax.random.categorical(k_member, jnp.where(elite, 0.0, -jnp.inf),
                                  shape=means.shape[1:-1])
    take = lambda x: jnp.take_along_axis(x, pick[None, ..., None], 0)[0]
    return take(means), take(log_stds), k_noise


def mixture_log_prob(means, log_stds, y, *, rank=None, n_elites=None, mode="random"):
    """log density of y [..., o] (normalised delta) under what rollouts sample: the uniform
    mixture of the elites ("random"), or the one Gaussian of "mean" / "fixed". -> [...]"""
    E = means.shape[0]
    if E == 1 or mode != "random":
        mean, log_std, _ = ensemble_moments(means, log_stds, None, rank=rank,
                                            n_elites=n_elites, mode=mode)
        return -gaussian_nll(mean, log_std, y)
    elite = elite_mask(rank, n_elites, E).reshape((E,) + (1,) * (means.ndim - 2))
    lp = jnp.where(elite, -gaussian_nll(means, log_stds, y[None]), -jnp.inf)
    return jax.scipy.special.logsumexp(lp, 0) - jnp.log(elite.sum())


def disagreement(means: jax.Array, *, rank: jax.Array | None = None,
                 n_elites: int | None = None, kind: str = "std") -> jax.Array:
    """How much the elites' means [E, ..., o] (normalised delta units) differ. -> [...]

    "std": sqrt(mean over dims of the variance over elites); "max_pairwise": the largest
    root-mean-square (over dims) distance between two elites' means. 0 for one member."""
    E = means.shape[0]
    if E == 1:
        return jnp.zeros(means.shape[1:-1], means.dtype)
    elite = elite_mask(rank, n_elites, E)
    if kind == "std":
        w = (elite / elite.sum()).astype(means.dtype).reshape((E,) + (1,) * (means.ndim - 1))
        mu = jnp.sum(w * means, 0)
        return jnp.sqrt(jnp.mean(jnp.sum(w * (means - mu) ** 2, 0), -1))
    if kind != "max_pairwise":
        raise ValueError(f"uncertainty: expected one of {UNCERTAINTY_KINDS}, got {kind!r}")
    d = jnp.sqrt(jnp.mean((means[:, None] - means[None]) ** 2, -1))      # [E, E, ...]
    both = (elite[:, None] & elite[None]).reshape((E, E) + (1,) * (d.ndim - 2))
    return jnp.max(jnp.where(both, d, 0.0), (0, 1))
