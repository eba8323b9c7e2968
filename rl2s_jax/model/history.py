"""The past that a simulator with history inputs steps on, carried through rollouts.

A member of the dynamics family (``rl2s_jax.model.dynamics``) may see, beside (s, a), the k
previous actions and observations of its episode (each with a validity flag, 0 before the
episode start) and time inputs (``time_inputs``, a subset of ``dynamics.TIME_INPUTS``, fed
in the order named): "step", the step's place in the episode, t / episode_length clipped to
[0, 1];
"order", the episode's place in the recording order (0 the first episode, 1 the last;
``Episodes.order``). ``History`` is that past for a batch of episodes; a rollout starts it
empty (``empty_history``), pushes every step (``push_history``) and empties it where an
episode restarts (``reset_history``). The training rows get theirs from the logged episode
(``rl2s_jax.train.data``), so what training sees and what a rollout feeds are the same
inputs. A Markov member has no History (None), and its inputs are ``markov_inputs``.

A simulated episode runs as the system is at the end of the recording: its order is 1.0 from
the start (``empty_history``) and after every restart (``reset_history``), the newest
dynamics, which is what a user of a drifting system wants to simulate. Training rows and
held-out rows carry their logged episode's order (``dataset_episode_order``).

Newest first: ``past_act[..., 0, :]`` is the action of the previous step.
Shapes: Ko = obs_history, Ka = action_history, o = obs size, a = action size.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rl2s_jax.model.dynamics import (
    Normalizer,
    encoder_inputs,
    markov_inputs,
    member_dist,
    model_inputs,
    pool_context,
)

ROLLOUT_ORDER = 1.0  # a simulated episode's place in the recording order: the newest dynamics


@struct.dataclass
class History:
    """past_obs [..., Ko, o], past_obs_valid [..., Ko] bool, past_act [..., Ka, a],
    past_act_valid [..., Ka] bool, t [...] int32 steps since the episode began; order [...]
    float32, the episode's place in the recording order in [0, 1] (None unless "order" is
    among the time inputs; 1.0 in rollouts); the static ``time_inputs`` and
    ``episode_length`` say how t and order are fed. A past of length 0 is None (a checkpoint
    cannot hold zero-size arrays)."""

    past_obs: jax.Array | None
    past_obs_valid: jax.Array | None
    past_act: jax.Array | None
    past_act_valid: jax.Array | None
    t: jax.Array
    order: jax.Array | None = None
    time_inputs: tuple[str, ...] = struct.field(pytree_node=False, default=())
    episode_length: int = struct.field(pytree_node=False, default=1000)

    @property
    def times(self) -> jax.Array:
        """The time inputs [..., T] in [0, 1], in the order of ``time_inputs``: "step" is
        clip(t / episode_length, 0, 1), "order" the episode's place in the recording."""
        if not self.time_inputs:
            return jnp.zeros(self.t.shape + (0,), jnp.float32)
        if "order" in self.time_inputs and self.order is None:
            raise ValueError("order: the time inputs include 'order' (the episode's place in "
                             "the recording order) but this History has none; build it with "
                             "empty_history (rollouts: 1.0) or logged_history (logged rows)")
        step = jnp.clip(self.t.astype(jnp.float32) / self.episode_length, 0.0, 1.0)
        value = lambda name: step if name == "step" else self.order.astype(jnp.float32)
        return jnp.stack([value(name) for name in self.time_inputs], -1)


def empty_history(batch_shape: tuple[int, ...], obs_size: int, action_size: int, *,
                  obs_history: int, action_history: int, time_inputs: tuple[str, ...] = (),
                  episode_length: int = 1000) -> History:
    """The history of episodes that start now: nothing valid, t = 0, order 1.0 (the end of
    the recording) when "order" is among the time inputs."""
    b = tuple(batch_shape)
    past = lambda k, d: (None, None) if k == 0 else (jnp.zeros(b + (k, d), jnp.float32),
                                                     jnp.zeros(b + (k,), bool))
    past_obs, obs_valid = past(obs_history, obs_size)
    past_act, act_valid = past(action_history, action_size)
    order = jnp.full(b, ROLLOUT_ORDER, jnp.float32) if "order" in time_inputs else None
    return History(past_obs=past_obs, past_obs_valid=obs_valid, past_act=past_act,
                   past_act_valid=act_valid, t=jnp.zeros(b, jnp.int32), order=order,
                   time_inputs=tuple(time_inputs), episode_length=int(episode_length))


def _shift(past, valid, new):
    """past [..., K, d], valid [..., K] with ``new`` [..., d] put first; None stays None."""
    if past is None:
        return past, valid
    past = jnp.concatenate([new[..., None, :].astype(past.dtype), past[..., :-1, :]], -2)
    valid = jnp.concatenate([jnp.ones(valid.shape[:-1] + (1,), bool), valid[..., :-1]], -1)
    return past, valid


def push_history(hist: History, obs: jax.Array, action: jax.Array) -> History:
    """The history after a step from ``obs`` [..., o] with ``action`` [..., a]."""
    past_obs, obs_valid = _shift(hist.past_obs, hist.past_obs_valid, obs)
    past_act, act_valid = _shift(hist.past_act, hist.past_act_valid, action)
    return hist.replace(past_obs=past_obs, past_obs_valid=obs_valid, past_act=past_act,
                        past_act_valid=act_valid, t=hist.t + 1)


def reset_history(hist: History, reset: jax.Array) -> History:
    """Empty where ``reset`` [...] (bool) holds (nothing valid, t = 0, order 1.0: a
    restarted simulated episode runs at the end of the recording), unchanged elsewhere."""
    def pick(x, fill=0):
        r = jnp.reshape(reset, reset.shape + (1,) * (x.ndim - reset.ndim))
        return jnp.where(r, jnp.full_like(x, fill), x)
    out = jax.tree_util.tree_map(pick, hist.replace(order=None))
    return out.replace(order=None if hist.order is None else pick(hist.order, ROLLOUT_ORDER))


def step_inputs(norm: Normalizer, obs: jax.Array, action: jax.Array,
                hist: History | None) -> jax.Array:
    """A member's inputs at (obs [..., o], action [..., a]) with this past (None: Markov)."""
    if hist is None:
        return markov_inputs(norm, obs, action)

    def past(x, valid, ref):
        if x is None:
            return (jnp.zeros(ref.shape[:-1] + (0, ref.shape[-1]), ref.dtype),
                    jnp.zeros(ref.shape[:-1] + (0,), bool))
        return x, valid
    past_obs, obs_valid = past(hist.past_obs, hist.past_obs_valid, obs)
    past_act, act_valid = past(hist.past_act, hist.past_act_valid, action)
    return model_inputs(norm, {"obs": obs, "past_obs": past_obs, "past_obs_valid": obs_valid,
                               "action": action, "past_act": past_act,
                               "past_act_valid": act_valid, "times": hist.times})


def history_context(params: dict, norm: Normalizer, obs: jax.Array,
                    hist: History | None) -> jax.Array | None:
    """A member's per-episode context inferred from the episode's recent transitions (None
    for a member without a context encoder, ``params["enc"]``).

    The K = min(obs_history, action_history) newest transitions (s_{t-1-k}, a_{t-1-k},
    s_{t-k}), k < K, the newest ending at ``obs`` [..., o], are embedded by the encoder and
    mean-pooled over the valid ones (zeros before any). A hidden parameter that is fixed for
    an episode (a mass, a friction) shows in how its past states answered its past actions,
    so the context identifies it online, in training rows and rollouts alike. -> [..., C]"""
    if "enc" not in params:
        return None
    k = min(hist.past_obs.shape[-2], hist.past_act.shape[-2])
    s, a = hist.past_obs[..., :k, :], hist.past_act[..., :k, :]
    nxt = jnp.concatenate([obs[..., None, :].astype(s.dtype), s[..., :k - 1, :]], -2)
    valid = hist.past_obs_valid[..., :k] & hist.past_act_valid[..., :k]
    return pool_context(params, encoder_inputs(norm, s, a, nxt), valid)


def member_step_dist(params: dict, norm: Normalizer, obs: jax.Array, action: jax.Array,
                     hist: History | None) -> tuple[jax.Array, jax.Array]:
    """One member's Gaussian over the normalised delta at (obs [..., o], action [..., a])
    with this past, its context included. -> (mean, log_std), each [..., o]."""
    ctx = None if hist is None else history_context(params, norm, obs, hist)
    return member_dist(params, step_inputs(norm, obs, action, hist), ctx)


def take_history(hist: History | None, idx) -> History | None:
    """Rows ``idx`` of a batch of histories (None stays None)."""
    if hist is None:
        return None
    return jax.tree_util.tree_map(lambda x: x[idx], hist)


# ------------------------------------------------------------------ logged episodes (host)


def episode_steps_back(policy_id: np.ndarray, episode_id: np.ndarray, t: np.ndarray
                       ) -> np.ndarray:
    """[N] int: for each row, how many preceding rows its episode has without a gap (same
    policy and episode, t one lower each row). Rows are in storage order."""
    n = len(t)
    cont = np.zeros(n, bool)  # cont[i]: row i continues row i - 1
    if n > 1:
        cont[1:] = ((policy_id[1:] == policy_id[:-1]) & (episode_id[1:] == episode_id[:-1])
                    & (t[1:] == t[:-1] + 1))
    first = np.maximum.accumulate(np.where(cont, 0, np.arange(n))) if n else np.zeros(0, int)
    return np.arange(n) - first


def past_rows(x, steps_back, rows, k: int, xp=jnp):
    """The k previous values of x [N, d] for rows [n], newest first, zero before the episode
    start (``steps_back`` [N]: rows of the same episode before each row, in order); jnp or
    NumPy (``xp``). -> (past [n, k, d], valid [n, k] bool); (None, None) for k = 0."""
    if k == 0:
        return None, None
    lags = xp.arange(1, k + 1)
    valid = steps_back[rows][:, None] >= lags
    src = xp.where(valid, rows[:, None] - lags, rows[:, None])
    return xp.where(valid[..., None], x[src], 0.0).astype(x.dtype), valid


def dataset_steps_back(ds) -> np.ndarray:
    """``episode_steps_back`` of a Dataset's rows (storage order)."""
    return episode_steps_back(np.asarray(ds.policy_id), np.asarray(ds.episode_id),
                              np.asarray(ds.t))


def dataset_episode_order(ds) -> np.ndarray:
    """[N] float64: every Dataset row's episode's place in the recording order, exactly
    ``rl2s_jax.data.episodes.from_dataset(ds).order``: episodes numbered densely in order of
    appearance (a new one wherever episode_id changes from the row before), divided by
    (E - 1), so the first episode is 0 and the last 1 (0 for a Dataset of one episode)."""
    ep_id = np.asarray(ds.episode_id)
    starts = np.ones(ep_id.shape[0], bool)
    starts[1:] = ep_id[1:] != ep_id[:-1]
    episode = np.cumsum(starts) - 1
    return (episode / max(int(starts.sum()) - 1, 1)).astype(np.float64)


def logged_history(ds, rows, *, obs_history: int, action_history: int,
                   time_inputs: tuple[str, ...] = (), episode_length: int = 1000,
                   steps_back: np.ndarray | None = None,
                   episode_order: np.ndarray | None = None) -> History:
    """The logged past of Dataset rows [n] (storage order; ``steps_back``: the Dataset's
    ``dataset_steps_back``, ``episode_order``: its ``dataset_episode_order``, each computed
    when None and needed), built on the host: what a member with history inputs sees at those
    rows, their episodes' places in the recording order included."""
    rows = np.asarray(rows, np.int64)
    back = dataset_steps_back(ds) if steps_back is None else np.asarray(steps_back)
    order = None
    if "order" in time_inputs:
        order = dataset_episode_order(ds) if episode_order is None else episode_order
        order = jnp.asarray(np.asarray(order)[rows], jnp.float32)

    def past(x, k):
        out = past_rows(np.asarray(x, np.float32), back, rows, k, xp=np)
        return (None, None) if k == 0 else (jnp.asarray(out[0], jnp.float32),
                                            jnp.asarray(out[1]))

    past_obs, obs_valid = past(ds.obs, obs_history)
    past_act, act_valid = past(ds.action, action_history)
    return History(past_obs=past_obs, past_obs_valid=obs_valid, past_act=past_act,
                   past_act_valid=act_valid, t=jnp.asarray(np.asarray(ds.t)[rows], jnp.int32),
                   order=order, time_inputs=tuple(time_inputs),
                   episode_length=int(episode_length))
