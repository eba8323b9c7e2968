"""``TrainData``: a Dataset and its policies on the device, with held-out episodes for scoring."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rl2s_jax.data.episodes import from_dataset, split_episodes
from rl2s_jax.data.values import true_values
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.history import (
    History,
    dataset_episode_order,
    dataset_steps_back,
    logged_history,
    past_rows,
)
from rl2s_jax.model.simulator import (
    start_pool,
)
from rl2s_jax.policy.policy import Params, num_policies
from rl2s_jax.train.config import TrainConfig


@struct.dataclass
class TrainData:
    """The training data on the device, training rows grouped by policy.

    obs [N, o], action [N, a], next_obs [N, o]; policy_start, policy_count [P] (policy p owns
    rows policy_start[p] : policy_start[p] + policy_count[p]); start_pool [S, o] real episode
    start states; true_value [P] discounted value over vd_horizon steps (NaN = unknown);
    policies: the P training policies, stacked; norm: the training rows' Normalizer;
    val_obs, val_action, val_next_obs [V, ...]: rows of the held-out episodes the members are
    scored on (V = 0 without held-out episodes); those episodes are not among the N rows.
    steps_left [N] int32: how many rows of the same episode follow row i, in order (row i + j
    continues row i for j <= steps_left[i]); the multi-step loss needs it (None: unknown).
    done [N] float32: 1 where the row's next state is terminal (the learned termination hazard
    is fitted to it; None: unknown); reward [N] float32: the rows' logged rewards (the learned
    reward head is fitted to them; None: unknown); val_reward, val_done [V]: the held-out
    rows' (their held-out errors).
    History inputs (static ``obs_history``, ``action_history``, ``time_inputs``,
    ``episode_length``, as the config's): steps_back [N] int32, how many rows of the same
    episode precede row i, in order; t [N] int32, the row's step in its episode; order [N]
    float32, its episode's place in the recording order (``dataset_episode_order``; None
    unless "order" is among the time inputs); val_hist, the held-out rows' past
    (``row_history`` gives the training rows').
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
    val_obs: jax.Array
    val_action: jax.Array
    val_next_obs: jax.Array
    steps_left: jax.Array | None = None
    done: jax.Array | None = None
    reward: jax.Array | None = None
    val_reward: jax.Array | None = None
    val_done: jax.Array | None = None
    steps_back: jax.Array | None = None
    t: jax.Array | None = None
    order: jax.Array | None = None
    val_hist: History | None = None
    obs_history: int = struct.field(pytree_node=False, default=0)
    action_history: int = struct.field(pytree_node=False, default=0)
    time_inputs: tuple[str, ...] = struct.field(pytree_node=False, default=())
    episode_length: int = struct.field(pytree_node=False, default=1000)

    @property
    def markov(self) -> bool:
        return not (self.obs_history or self.action_history or self.time_inputs)

    def row_history(self, rows: jax.Array) -> History | None:
        """The logged past of training rows [n] (None without history inputs)."""
        if self.markov:
            return None
        if self.steps_back is None or self.t is None:
            raise ValueError("history inputs need TrainData.steps_back and t "
                             "(make_train_data sets them)")
        if "order" in self.time_inputs and self.order is None:
            raise ValueError("time_inputs: 'order' needs TrainData.order, each row's episode's "
                             "place in the recording (make_train_data sets it)")
        past_obs, obs_valid = past_rows(self.obs, self.steps_back, rows, self.obs_history)
        past_act, act_valid = past_rows(self.action, self.steps_back, rows,
                                       self.action_history)
        return History(past_obs=past_obs, past_obs_valid=obs_valid, past_act=past_act,
                       past_act_valid=act_valid, t=self.t[rows],
                       order=None if self.order is None else self.order[rows],
                       time_inputs=self.time_inputs, episode_length=self.episode_length)

    @property
    def n_policies(self) -> int:
        return int(self.policy_start.shape[0])

    @property
    def n_heldout(self) -> int:
        return int(self.val_obs.shape[0])


def heldout_mask(ds, holdout_frac: float, seed: int = 0) -> np.ndarray:
    """[N] bool: the rows of whole held-out episodes, ``holdout_frac`` of each policy's
    episodes (at least one of every policy with two or more; ``diagnose.episodes
    .split_episodes``). All False for holdout_frac = 0."""
    if not holdout_frac:
        return np.zeros(ds.n_transitions, bool)

    eps = from_dataset(ds, position_dims=())
    try:
        _, held = split_episodes(eps, holdout_frac, seed)
    except ValueError:
        raise ValueError("holdout_frac: no training policy has 2 or more episodes, so none can "
                         "be held out to score the members; collect longer or set "
                         "holdout_frac=0 (with n_elites = ensemble_size and "
                         "early_stop_patience = 0)") from None
    return np.isin(eps.episode, held)


def make_train_data(ds, policies: Params, config: TrainConfig) -> TrainData:
    """TrainData from a Dataset and its P stacked policies (policy i of ``policies`` collected
    the rows with policy_id i).

    ``holdout_frac`` of every policy's episodes are held out whole (``heldout_mask``); up to
    ``holdout_rows`` of their rows, evenly spread, score the members. The true values: the
    Dataset's measured discounted values when vd_horizon covers the whole episode and gamma
    matches; otherwise the logged episodes' discounted return over the first vd_horizon steps
    (all episodes, held-out ones included).
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
    held = heldout_mask(ds, config.holdout_frac)
    keep = np.flatnonzero(~held)
    counts = np.bincount(pid[keep], minlength=P)
    order = keep[np.argsort(pid[keep], kind="stable")]
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    val = np.flatnonzero(held)
    if val.size > config.holdout_rows:
        val = val[np.round(np.linspace(0, val.size - 1, config.holdout_rows)).astype(int)]
    true_value = true_values(ds, config.vd.horizon, config.gamma, strict=bool(config.vd.every))
    f32 = lambda x, rows: jnp.asarray(np.asarray(x)[rows], jnp.float32)
    obs, action, next_obs = (np.asarray(x)[keep] for x in (ds.obs, ds.action, ds.next_obs))
    steps_left = episode_steps_left(np.asarray(ds.policy_id)[order],
                                    np.asarray(ds.episode_id)[order], np.asarray(ds.t)[order])
    d = config.dynamics
    hist = dict(obs_history=d.obs_history, action_history=d.action_history,
                time_inputs=tuple(d.time_inputs), episode_length=config.episode_length)
    extra = {}
    if not config.markov:
        back_all = dataset_steps_back(ds)
        ep_order = dataset_episode_order(ds) if "order" in config.dynamics.time_inputs else None
        extra = dict(steps_back=jnp.asarray(back_all[order], jnp.int32),
                     t=jnp.asarray(np.asarray(ds.t)[order], jnp.int32),
                     order=None if ep_order is None else jnp.asarray(ep_order[order],
                                                                     jnp.float32),
                     val_hist=logged_history(ds, val, steps_back=back_all,
                                             episode_order=ep_order, **hist))
    return TrainData(**hist, **extra, obs=f32(ds.obs, order), action=f32(ds.action, order),
                     next_obs=f32(ds.next_obs, order),
                     policy_start=jnp.asarray(starts, jnp.int32),
                     policy_count=jnp.asarray(counts, jnp.int32),
                     start_pool=start_pool(ds),
                     true_value=jnp.asarray(true_value, jnp.float32),
                     policies=jax.tree_util.tree_map(jnp.asarray, policies),
                     norm=Normalizer.from_data(obs, action, next_obs,
                                               ignore_dims=config.ignore_dims),
                     val_obs=f32(ds.obs, val), val_action=f32(ds.action, val),
                     val_next_obs=f32(ds.next_obs, val),
                     steps_left=jnp.asarray(steps_left, jnp.int32),
                     done=f32(ds.done, order), reward=f32(ds.reward, order),
                     val_reward=f32(ds.reward, val), val_done=f32(ds.done, val))


def episode_steps_left(policy_id: np.ndarray, episode_id: np.ndarray, t: np.ndarray
                       ) -> np.ndarray:
    """[N] int: for each row, how many following rows continue its episode without a gap (same
    policy and episode, t one higher each row). Rows are in storage order."""
    n = len(t)
    cont = np.zeros(n, bool)  # cont[i]: row i + 1 continues row i
    if n > 1:
        cont[:-1] = ((policy_id[1:] == policy_id[:-1]) & (episode_id[1:] == episode_id[:-1])
                     & (t[1:] == t[:-1] + 1))
    run = np.cumsum(np.r_[0, ~cont[:-1]]) if n else np.zeros(0, int)  # run id of each row
    last = np.zeros(run.max() + 1 if n else 0, int)
    np.maximum.at(last, run, np.arange(n))
    return last[run] - np.arange(n)


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


def _real_batch_history(key, data: TrainData, selected, n):
    """``_real_batch`` and the rows' past (None without history inputs): the same draws.
    -> (obs, action, next_obs, hist)"""
    rows, _ = _sample_rows(key, data, selected, n)
    return data.obs[rows], data.action[rows], data.next_obs[rows], data.row_history(rows)


def _real_windows(key, data: TrainData, selected, n: int, k: int):
    """n windows of k consecutive rows of one episode, starting at rows drawn as _real_batch's.
    -> (obs [n, o] the first state, action [n, k, a], next_obs [n, k, o], valid [n, k]: step
    j exists (the episode goes on that long; invalid steps repeat the last valid row))."""
    rows, _ = _sample_rows(key, data, selected, n)
    return _windows_at(data, rows, k)


def _windows_at(data: TrainData, rows: jax.Array, k: int):
    """The windows of k rows that start at ``rows`` [n] (``_real_windows``)."""
    if data.steps_left is None:
        raise ValueError("multistep_steps: the multi-step loss needs TrainData.steps_left "
                         "(make_train_data sets it); set multistep_steps=1")
    j = jnp.arange(k)[None, :]
    left = data.steps_left[rows][:, None]
    idx = rows[:, None] + jnp.minimum(j, left)
    return data.obs[rows], data.action[idx], data.next_obs[idx], j <= left


def _real_windows_history(key, data: TrainData, selected, n: int, k: int):
    """``_real_windows`` and the start rows' past (None without history inputs): one draw."""
    rows, _ = _sample_rows(key, data, selected, n)
    return (*_windows_at(data, rows, k), data.row_history(rows))
