"""A Dataset in numbers a person reads: per-episode returns, episode lengths and the `rl2s
inspect` summary."""

from __future__ import annotations

import json

import numpy as np

from rl2s_jax.data.dataset import Dataset, _episode_starts


def episode_returns(ds: Dataset, gamma: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-episode returns in row order, from the data (the ds must be valid).

    Returns ``(returns [E] float64, policy_of_episode [E] int32, complete [E] bool)``:
    the sum of ``reward`` (times ``gamma ** t`` if ``gamma`` is given) over each episode's
    rows, its policy, and whether its last row is done or truncated (otherwise the episode
    is open: collection stopped mid-episode and its return is partial).
    """
    reward = np.asarray(ds.reward, dtype=np.float64)
    if gamma is not None:
        reward = reward * float(gamma) ** np.asarray(ds.t, dtype=np.float64)
    starts = np.flatnonzero(_episode_starts(np.asarray(ds.episode_id)))
    last = np.append(starts[1:] - 1, reward.shape[0] - 1)
    returns = np.add.reduceat(reward, starts)
    complete = np.asarray(ds.done)[last] | np.asarray(ds.truncated)[last]
    return returns, np.asarray(ds.policy_id)[starts].astype(np.int32), complete


def episode_lengths(ds: Dataset) -> np.ndarray:
    """[P] mean length of each policy's logged episodes (a terminated or truncated one counts
    its steps; the last, cut-off episode of a policy is left out when others exist)."""
    pid, ep = np.asarray(ds.policy_id), np.asarray(ds.episode_id)
    ended = np.asarray(ds.done) | np.asarray(ds.truncated)
    out = np.zeros(ds.n_policies)
    for p in range(ds.n_policies):
        mine = pid == p
        ids, counts = np.unique(ep[mine], return_counts=True)
        whole = np.isin(ids, ep[mine & ended])
        out[p] = counts[whole].mean() if whole.any() else counts.mean()
    return out


def dataset_summary(ds: Dataset) -> str:
    """A multi-line human summary: sizes, episode counts and a per-policy table."""
    m, p, n = ds.meta, ds.n_policies, ds.n_transitions
    returns, pol, complete = episode_returns(ds)
    last = np.append(np.flatnonzero(_episode_starts(np.asarray(ds.episode_id)))[1:] - 1, n - 1)
    n_done = int(np.asarray(ds.done)[last].sum())
    n_trunc = int(np.asarray(ds.truncated)[last].sum())
    per_pol = np.bincount(np.asarray(ds.policy_id), minlength=p)
    eps = np.bincount(pol, minlength=p)
    comp = np.bincount(pol, weights=complete, minlength=p).astype(int)
    ret_sum = np.bincount(pol, weights=np.where(complete, returns, 0.0), minlength=p)
    lines = [
        f"task: {m.get('task')}",
        f"transitions (N): {n}",
        f"policies (P): {p}",
        f"obs_size: {ds.obs_size}, action_size: {ds.action_size}, "
        f"episode_length: {m.get('episode_length')}, gamma: {m.get('gamma')}",
        f"episodes: {len(returns)} ({int(complete.sum())} complete: {n_done} done, "
        f"{n_trunc} truncated; {int((~complete).sum())} open)",
        f"transitions per policy: min {int(per_pol.min())}, max {int(per_pol.max())}",
        f"true values: {'present' if ds.has_values else 'absent'}"
        + (f" (measured on {(m.get('source') or {}).get('value_episodes', '?')} real "
           f"episodes per policy: undiscounted return and discounted value at gamma "
           f"{m.get('gamma')})" if ds.has_values else ""),
        f"source: {json.dumps(m.get('source'))}",
        "",
    ]
    names = list(m.get("policy_names") or [str(i) for i in range(p)])
    w = max([len("policy")] + [len(s) for s in names])
    disc = ds.has_values and ds.value_discounted is not None
    head = (f"{'id':>4}  {'policy':<{w}}  {'transitions':>11}  {'episodes':>8}  {'complete':>8}"
            f"  {'logged return':>13}")
    if ds.has_values:
        head += f"  {'true return ± se':>22}"
    if disc:
        head += f"  {'true disc. value ± se':>22}"
    lines.append(head)
    for i in range(p):
        mean = f"{ret_sum[i] / comp[i]:13.3f}" if comp[i] else f"{'-':>13}"
        row = (f"{i:>4}  {names[i]:<{w}}  {per_pol[i]:>11}  {eps[i]:>8}  {comp[i]:>8}  {mean}")
        if ds.has_values:
            v, se = float(np.asarray(ds.value)[i]), float(np.asarray(ds.value_se)[i])
            row += f"  {f'{v:.3f} ± {se:.3f}':>22}"
        if disc:
            v, se = (float(np.asarray(x)[i]) for x in (ds.value_discounted,
                                                         ds.value_discounted_se))
            row += f"  {f'{v:.3f} ± {se:.3f}':>22}"
        lines.append(row)
    lines += ["", "logged return: undiscounted, mean over the data's complete episodes; "
              "true return / disc. value: of the real episodes measured for the values "
              "(undiscounted / discounted at gamma over the whole episode)"
              if ds.has_values else
              "logged return: undiscounted, mean over the data's complete episodes"]
    return "\n".join(lines)
