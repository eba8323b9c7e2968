"""The one policy architecture of the project, and the policy zoo.

A policy is a tanh-squashed Gaussian MLP with a frozen observation normaliser. Its parameters
are a plain pytree (dict of arrays), so a zoo of P policies is the same pytree with a leading
axis [P, ...] and anything written for one policy runs over a zoo with ``jax.vmap``.

Params layout (one policy)::

    {"obs_mean": [obs], "obs_std": [obs],
     "layers": [{"w": [in, out], "b": [out]}, ...]}   # last layer out = 2 * action_size

The last layer's output is split into the pre-tanh mean ``loc`` and a raw scale; the scale is
``softplus(raw) + MIN_SCALE`` (as brax's NormalTanhDistribution), so the policy is state
dependent, differentiable, and fine to fine-tune with SAC.

A policy file (``save_policies`` / ``load_policies``, docs/DATA.md "Policy file") holds P such
policies, stacked, with P unique names, in one ``.npz``.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax._files import atomic_open

Params = dict[str, Any]
MIN_SCALE = 1e-3
DEFAULT_HIDDEN = (64, 64)


def init_mlp(key: jax.Array, sizes: Sequence[int], last_scale: float = 1.0) -> list[dict]:
    """MLP layers for ``mlp``: lecun-normal weights (last layer scaled), zero biases."""
    keys = jax.random.split(key, len(sizes) - 1)
    init = jax.nn.initializers.lecun_normal()
    layers = [{"w": init(k, (a, b), jnp.float32), "b": jnp.zeros((b,), jnp.float32)}
              for k, a, b in zip(keys, sizes[:-1], sizes[1:], strict=True)]
    layers[-1]["w"] = layers[-1]["w"] * last_scale
    return layers


def init_policy(key: jax.Array, obs_size: int, action_size: int,
                hidden: Sequence[int] = DEFAULT_HIDDEN) -> Params:
    """Fresh policy parameters with an identity normaliser.

    A small last layer keeps the initial policy near zero mean with a moderate spread.
    """
    return {"obs_mean": jnp.zeros((obs_size,), jnp.float32),
            "obs_std": jnp.ones((obs_size,), jnp.float32),
            "layers": init_mlp(key, [obs_size, *hidden, 2 * action_size], last_scale=0.01)}


def mlp(layers: list[dict[str, jax.Array]], x: jax.Array) -> jax.Array:
    """A swish MLP; no activation after the last layer. x: [..., in] -> [..., out]."""
    for layer in layers[:-1]:
        x = jax.nn.swish(x @ layer["w"] + layer["b"])
    return x @ layers[-1]["w"] + layers[-1]["b"]


def normalize_obs(params: Params, obs: jax.Array) -> jax.Array:
    """Observation normalised by the policy's frozen statistics, clipped to [-10, 10]."""
    return jnp.clip((obs - params["obs_mean"]) / params["obs_std"], -10.0, 10.0)


def policy_dist(params: Params, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Pre-tanh Gaussian of one policy. obs: [..., obs] -> (loc, scale), each [..., act]."""
    out = mlp(params["layers"], normalize_obs(params, obs))
    loc, raw_scale = jnp.split(out, 2, axis=-1)
    return loc, jax.nn.softplus(raw_scale) + MIN_SCALE


def gaussian_log_prob(loc: jax.Array, scale: jax.Array, raw: jax.Array) -> jax.Array:
    """log N(raw; loc, scale) summed over the last axis. -> [...]"""
    z = (raw - loc) / scale
    return jnp.sum(-0.5 * z**2 - jnp.log(scale) - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def tanh_log_det(raw: jax.Array) -> jax.Array:
    """log |d tanh(raw) / d raw| summed over the last axis (numerically stable form)."""
    return jnp.sum(2.0 * (jnp.log(2.0) - raw - jax.nn.softplus(-2.0 * raw)), axis=-1)


def sample_action(params: Params, obs: jax.Array, key: jax.Array
                  ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Stochastic action of one policy.

    obs: [..., obs] -> (action [..., act] in (-1, 1), raw pre-tanh action [..., act],
    log-prob of the squashed action [...]).
    """
    loc, scale = policy_dist(params, obs)
    raw = loc + scale * jax.random.normal(key, loc.shape, loc.dtype)
    logp = gaussian_log_prob(loc, scale, raw) - tanh_log_det(raw)
    return jnp.tanh(raw), raw, logp


def mode_action(params: Params, obs: jax.Array) -> jax.Array:
    """Deterministic action tanh(loc). obs: [..., obs] -> [..., act]."""
    return jnp.tanh(policy_dist(params, obs)[0])


# Observation dims a policy should not see (absolute positions) get this std and mean 0, so
# their normalised value is ~0 for any reachable position: the policy ignores them.
IGNORED_OBS_STD = 1e6


def mask_obs_stats(mean: jax.Array, std: jax.Array, ignore_dims: Sequence[int] = ()
                   ) -> tuple[jax.Array, jax.Array]:
    """(mean, std) [obs] with the ``ignore_dims`` set to (0, IGNORED_OBS_STD)."""
    if len(ignore_dims):
        idx = jnp.asarray(tuple(ignore_dims), jnp.int32)
        mean, std = mean.at[idx].set(0.0), std.at[idx].set(IGNORED_OBS_STD)
    return mean, std


class RunningNorm(NamedTuple):
    """Running observation mean and variance (parallel-algorithm update), the source of a
    trained policy's ``obs_mean`` / ``obs_std``."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @staticmethod
    def create(size: int) -> RunningNorm:
        return RunningNorm(jnp.zeros(size), jnp.ones(size), jnp.array(1e-4))

    def update(self, x: jax.Array) -> RunningNorm:
        """Fold in a batch x [..., obs]."""
        x = x.reshape(-1, x.shape[-1])
        b_mean, b_var, b_n = x.mean(0), x.var(0), x.shape[0]
        delta, total = b_mean - self.mean, self.count + b_n
        mean = self.mean + delta * b_n / total
        m2 = self.var * self.count + b_var * b_n + delta**2 * self.count * b_n / total
        return RunningNorm(mean, m2 / total, total)

    def std(self) -> jax.Array:
        return jnp.sqrt(self.var + 1e-6)

    def stats(self, ignore_dims: Sequence[int] = ()) -> tuple[jax.Array, jax.Array]:
        """(obs_mean, obs_std) [obs] float32 for a policy, ``ignore_dims`` masked out."""
        return mask_obs_stats(self.mean.astype(jnp.float32), self.std().astype(jnp.float32),
                              ignore_dims)


def stack_params(params_list: Sequence[Params]) -> Params:
    """[policy_0, policy_1, ...] -> one pytree with a leading policy axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *params_list)


def index_params(stacked: Params, ids) -> Params:
    """Policies ``ids`` (int or int array) of a stacked pytree."""
    ids = jnp.asarray(ids)
    return jax.tree_util.tree_map(lambda x: x[ids], stacked)


def num_policies(stacked: Params) -> int:
    return int(jax.tree_util.tree_leaves(stacked)[0].shape[0])


# ---------------------------------------------------------------------------- policy files

POLICY_FILE_FORMAT = 1


def flatten_params(params: Params) -> dict[str, np.ndarray]:
    """Stacked policy params -> host arrays under the keys ``obs_mean``, ``obs_std``,
    ``layers/<i>/w``, ``layers/<i>/b`` (the keys of policy files and zoo.npz). Anything but
    the policy pytree (module docstring) is refused, naming what differs."""
    if not isinstance(params, dict) or set(params) != {"obs_mean", "obs_std", "layers"}:
        got = sorted(params) if isinstance(params, dict) else type(params).__name__
        raise ValueError(f"params: expected a dict with keys ['layers', 'obs_mean', "
                         f"'obs_std'] (the tanh-Gaussian MLP policy), got {got}")
    layers = params["layers"]
    if (not isinstance(layers, list | tuple) or not layers
            or any(not isinstance(x, dict) or set(x) != {"w", "b"} for x in layers)):
        raise ValueError("params: expected 'layers' to be a non-empty list of {'w', 'b'} dicts")
    flat = {"obs_mean": params["obs_mean"], "obs_std": params["obs_std"]}
    for i, layer in enumerate(layers):
        flat[f"layers/{i}/w"], flat[f"layers/{i}/b"] = layer["w"], layer["b"]
    return {k: np.asarray(jax.device_get(v)) for k, v in flat.items()}


def unflatten_params(flat: dict[str, np.ndarray]) -> Params:
    """The inverse of ``flatten_params`` (device arrays)."""
    n_layers = 1 + max(int(k.split("/")[1]) for k in flat if k.startswith("layers/"))
    return {"obs_mean": jnp.asarray(flat["obs_mean"]), "obs_std": jnp.asarray(flat["obs_std"]),
            "layers": [{"w": jnp.asarray(flat[f"layers/{i}/w"]),
                        "b": jnp.asarray(flat[f"layers/{i}/b"])} for i in range(n_layers)]}


def check_policy_arrays(flat: dict[str, np.ndarray], where: str) -> tuple[int, int, int]:
    """Validate flat stacked policy arrays (``flatten_params``'s keys): float32, one leading
    policy axis P >= 1, chained layer sizes, an even last layer (loc and scale), finite values,
    obs_std > 0. -> (P, obs_size, action_size); a ValueError names ``where`` and the key."""
    layer_ids = [int(m.group(1)) for k in flat if (m := re.fullmatch(r"layers/(\d+)/[wb]", k))]
    n_layers = 1 + max(layer_ids, default=0)
    expected = ["obs_mean", "obs_std"] + [f"layers/{i}/{x}" for i in range(n_layers)
                                           for x in "wb"]
    missing, unknown = sorted(set(expected) - set(flat)), sorted(set(flat) - set(expected))
    if missing or unknown:
        raise ValueError(f"{where}: expected arrays obs_mean, obs_std, layers/<i>/w, "
                         f"layers/<i>/b (i = 0, 1, ...), got "
                         + "; ".join(f"{what} {keys}" for what, keys in
                                     (("missing", missing), ("unknown", unknown)) if keys))
    for k in expected:
        a = flat[k]
        if a.dtype != np.float32:
            raise ValueError(f"{where}: {k}: expected float32, got {a.dtype}")
        if a.ndim != (3 if k.endswith("/w") else 2):
            raise ValueError(f"{where}: {k}: expected {3 if k.endswith('/w') else 2} dims "
                             f"[P, ...] (stacked on a leading policy axis), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{where}: {k}: expected finite values, got NaN or Inf")
    P, obs = flat["obs_mean"].shape
    size = obs
    for k in expected:
        a = flat[k]
        want = {"obs_mean": (P, obs), "obs_std": (P, obs)}.get(k)
        if k.endswith("/w"):
            want, size = (P, size, a.shape[2]), a.shape[2]
        elif k.endswith("/b"):
            want = (P, size)
        if a.shape != want:
            raise ValueError(f"{where}: {k}: expected shape {list(want)}, got {list(a.shape)}")
    if P < 1 or obs < 1 or size < 2 or size % 2:
        raise ValueError(f"{where}: expected P >= 1 policies, obs_size >= 1 and an even last "
                         f"layer (2 x action_size), got P {P}, obs_size {obs}, last layer "
                         f"{size}")
    if not np.all(flat["obs_std"] > 0):
        raise ValueError(f"{where}: obs_std: expected values > 0")
    return P, obs, size // 2


def _check_names(names, n_policies: int, where: str) -> list[str]:
    if isinstance(names, str) or not isinstance(names, Sequence | np.ndarray):
        raise ValueError(f"{where}: expected a list of {n_policies} strings, got "
                         f"{type(names).__name__}")
    names = list(names)
    bad = [n for n in names if not isinstance(n, str)]
    if bad:
        raise ValueError(f"{where}: expected strings, got {bad[0]!r}")
    if len(names) != n_policies:
        raise ValueError(f"{where}: expected {n_policies} names (one per policy), got "
                         f"{len(names)}")
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"{where}: expected unique names, got {dup!r} more than once")
    return names


def save_policies(path: str | os.PathLike, params: Params, names: Sequence[str]) -> None:
    """Write stacked policy params [P, ...] and P unique names to one ``.npz`` at exactly
    ``path`` (docs/DATA.md "Policy file"; written to a temporary name, then renamed). Params
    are checked first (float32 leaves, one leading P, chained layer sizes, finite)."""
    flat = flatten_params(params)
    n, _, _ = check_policy_arrays(flat, "params")
    names = _check_names(names, n, "names")
    meta = {"format_version": POLICY_FILE_FORMAT, "policy_names": names}
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with atomic_open(path, "wb") as f:  # a file object: savez adds no .npz suffix
        np.savez_compressed(f, meta=np.array(json.dumps(meta)), **flat)


def load_policies(path: str | os.PathLike) -> tuple[Params, list[str]]:
    """A policy file -> (stacked params [P, ...], P names). Refuses, naming the field, a file
    that is not one ``save_policies`` writes: no or bad ``meta``, another format_version,
    missing or unknown arrays, wrong dtypes or shapes, non-finite values, bad names."""
    path = os.fspath(path)
    where = f"policy file {path}"
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{where}: no such file")
    if not zipfile.is_zipfile(path):
        with open(path, "rb") as f:
            head = f.read(8)
        raise ValueError(f"{where}: expected an .npz archive written by save_policies, got a "
                         f"file that is not a zip archive (starts with {head!r})")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise ValueError(f"{where}: expected an .npz archive written by save_policies, got "
                         f"{type(err).__name__}: {err}") from None
    if "meta" not in arrays:
        raise ValueError(f"{where}: no 'meta' entry: expected a file written by save_policies "
                         f"(a zoo's zoo.npz is not one: pass the zoo's directory as --zoo)")
    try:
        meta = json.loads(str(arrays.pop("meta")[()]))
    except (ValueError, TypeError) as err:
        raise ValueError(f"{where}: meta: expected a JSON object, got {err}") from None
    if not isinstance(meta, dict) or meta.get("format_version") != POLICY_FILE_FORMAT:
        got = meta.get("format_version") if isinstance(meta, dict) else meta
        raise ValueError(f"{where}: meta.format_version: expected {POLICY_FILE_FORMAT}, got "
                         f"{got!r}")
    n, _, _ = check_policy_arrays(arrays, where)
    names = _check_names(meta.get("policy_names"), n, f"{where}: meta.policy_names")
    return unflatten_params(arrays), names
