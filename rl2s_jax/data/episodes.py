"""Transitions as episodes: the flat, NumPy view of a Dataset that diagnosis works on.

Every diagnosis step needs the same few things a Dataset only implies: a dense episode index,
each row's past actions and observations within its episode, the episode's place in the
recording order, and a split of whole episodes into fit and held-out sets. They are built once
here, in NumPy (N up to millions; all O(N k)).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from rl2s_jax.data.dataset import Dataset
from rl2s_jax.envs.tasks import TASKS


@dataclasses.dataclass(frozen=True)
class Episodes:
    """Rows in dataset order (an episode's rows contiguous and time-ordered).

    Shapes: N rows, E episodes, o = obs size, a = action size.
      obs, next_obs [N, o] float64; action [N, a] float64;
      policy [N] int (policy_id); episode [N] int, dense in [0, E) in order of appearance;
      t [N] int, step within the episode; order [N] float in [0, 1], the episode's rank in
      recording order (episode index / (E - 1)); step_frac [N] float, t / episode_length (or
      t / max t + 1 when the data has no time limit);
      start [E] int, first row of each episode; length [E] int; episode_policy [E] int.
    """

    obs: np.ndarray
    action: np.ndarray
    next_obs: np.ndarray
    policy: np.ndarray
    episode: np.ndarray
    t: np.ndarray
    order: np.ndarray
    step_frac: np.ndarray
    start: np.ndarray
    length: np.ndarray
    episode_policy: np.ndarray
    n_policies: int
    position_dims: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return self.obs.shape[0]

    @property
    def n_episodes(self) -> int:
        return self.start.shape[0]

    @property
    def obs_size(self) -> int:
        return self.obs.shape[1]

    @property
    def action_size(self) -> int:
        return self.action.shape[1]

    @property
    def delta(self) -> np.ndarray:
        """next_obs - obs [N, o]."""
        return self.next_obs - self.obs

    def past(self, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The k previous rows of a per-row array x [N, ...] within each row's episode.

        Returns (past [N, k, ...], valid [N, k] bool): past[:, j] is x at step t - 1 - j, zero
        where t - 1 - j < 0 (before the episode started; valid False there).
        """
        n = x.shape[0]
        past = np.zeros((n, k) + x.shape[1:], x.dtype)
        valid = np.zeros((n, k), bool)
        for j in range(k):
            lag = j + 1
            ok = self.t >= lag
            rows = np.flatnonzero(ok)
            past[rows, j] = x[rows - lag]
            valid[:, j] = ok
        return past, valid

    def past_actions(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(a_{t-1..t-k} [N, k, a], valid [N, k])."""
        return self.past(self.action, k)

    def past_obs(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(s_{t-1..t-k} [N, k, o], valid [N, k])."""
        return self.past(self.obs, k)

    def rows(self, episodes: np.ndarray) -> np.ndarray:
        """Row indices [n] of the given episodes (ascending)."""
        mask = np.zeros(self.n_episodes, bool)
        mask[np.asarray(episodes, int)] = True
        return np.flatnonzero(mask[self.episode])


def from_dataset(ds: Dataset, position_dims: tuple[int, ...] | None = None) -> Episodes:
    """Build the episode view of a (validated) Dataset.

    position_dims: obs dims that hold absolute positions the dynamics do not depend on (left
    out of model inputs); None takes them from the registered task, if any.
    """
    ep_id = np.asarray(ds.episode_id)
    n = ep_id.shape[0]
    starts = np.ones(n, bool)
    starts[1:] = ep_id[1:] != ep_id[:-1]
    start = np.flatnonzero(starts)
    episode = np.cumsum(starts) - 1
    length = np.diff(np.append(start, n))
    n_ep = start.shape[0]
    t = np.asarray(ds.t).astype(np.int64)
    horizon = ds.meta.get("episode_length") or int(t.max()) + 1
    if position_dims is None:
        position_dims = ()
        task = ds.meta.get("task")
        if task:
            if task in TASKS:
                position_dims = TASKS[task].position_dims
    policy = np.asarray(ds.policy_id).astype(np.int64)
    return Episodes(
        obs=np.asarray(ds.obs, np.float64),
        action=np.asarray(ds.action, np.float64),
        next_obs=np.asarray(ds.next_obs, np.float64),
        policy=policy,
        episode=episode,
        t=t,
        order=(episode / max(n_ep - 1, 1)).astype(np.float64),
        step_frac=t / float(horizon),
        start=start,
        length=length,
        episode_policy=policy[start],
        n_policies=int(ds.n_policies),
        position_dims=tuple(int(d) for d in position_dims),
    )


def split_episodes(eps: Episodes, heldout_frac: float = 0.3, seed: int = 0,
                   min_length: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Split whole episodes into fit and held-out sets, per policy (every policy with at least
    2 episodes keeps at least one on each side). Episodes shorter than ``min_length`` rows go
    to neither side. -> (fit_episodes [E1], heldout_episodes [E2]), sorted episode indices."""
    if not 0.0 < heldout_frac < 1.0:
        raise ValueError(f"heldout_frac: expected a fraction in (0, 1), got {heldout_frac}")
    rng = np.random.default_rng(seed)
    fit, held = [], []
    long_enough = eps.length >= min_length
    for p in np.unique(eps.episode_policy):
        ids = rng.permutation(np.flatnonzero((eps.episode_policy == p) & long_enough))
        if ids.size < 2:
            fit.extend(ids)
            continue
        k = int(np.clip(round(heldout_frac * ids.size), 1, ids.size - 1))
        held.extend(ids[:k])
        fit.extend(ids[k:])
    if not held:
        raise ValueError("split_episodes: no policy has 2 or more episodes; cannot hold any out")
    return np.sort(np.asarray(fit, int)), np.sort(np.asarray(held, int))


def half_split(eps: Episodes) -> np.ndarray:
    """[N] int in {0, 1}: which half of its episode a row lies in (first half 0, second 1).
    Used to estimate a per-episode quantity from one half and test it on the other."""
    mid = eps.length[eps.episode] // 2
    return (eps.t >= mid).astype(np.int64)


def pool_episodes(target: Episodes, reference: Episodes) -> tuple[Episodes, np.ndarray]:
    """One episode view of a target and a reference dataset of the same system, for the
    differential diagnosis: the target's rows first, then the reference's, with the
    reference's episodes and policies renumbered after the target's (a policy of both counts
    as two). Each dataset keeps its own recording order and step fractions.

    -> (pooled Episodes, in_target [N_target + N_reference] bool)."""
    for name, a, b in (("obs size", target.obs_size, reference.obs_size),
                       ("action size", target.action_size, reference.action_size)):
        if a != b:
            raise ValueError(f"reference: its {name} {b} differs from the data's {a}; the "
                             "reference must come from the same system with the same "
                             "observation")
    cat = lambda f: np.concatenate([getattr(target, f), getattr(reference, f)])
    pooled = Episodes(
        obs=cat("obs"), action=cat("action"), next_obs=cat("next_obs"),
        policy=np.concatenate([target.policy, reference.policy + target.n_policies]),
        episode=np.concatenate([target.episode, reference.episode + target.n_episodes]),
        t=cat("t"), order=cat("order"), step_frac=cat("step_frac"),
        start=np.concatenate([target.start, reference.start + target.n]),
        length=cat("length"),
        episode_policy=np.concatenate([target.episode_policy,
                                       reference.episode_policy + target.n_policies]),
        n_policies=target.n_policies + reference.n_policies,
        position_dims=target.position_dims)
    in_target = np.r_[np.ones(target.n, bool), np.zeros(reference.n, bool)]
    return pooled, in_target
