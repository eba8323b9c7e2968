"""Roll a whole policy zoo at once in MJX and record a Dataset, plus each policy's true value.

All P policies x E parallel envs step together as one flat batch of B = P * E envs. Every
episode starts from a *fresh* random initial state: brax's AutoResetWrapper reuses one cached
start state, so we keep our own pool instead. Each env holds one pending start state drawn
from ``env.reset``; when its episode ends it swaps that start in. Every ``refresh_every``
steps one batched reset replaces all used pending starts; if an env ends before its pending
start was replaced (two ends within one refresh period), that step refreshes at once
(the same ``lax.cond`` branch), so the guarantee holds whatever the episode lengths. On a GPU
a batched reset costs about the same whatever the number of envs it resets (its kernels are
latency-bound at these batch sizes), so resetting rarely, not resetting few, is what keeps
collection close to raw stepping speed (docs/BENCHMARKS.md).

With several local devices the policy axis is split over them (``shard=True``, the default):
the policies and their envs' states live on the device of their policy, the same program runs
on every device, and the data is the same as on one device (tests/test_sharding.py).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env
from tqdm.auto import tqdm

from rl2s_jax._timing import PartTimer, timed
from rl2s_jax.data.dataset import Dataset
from rl2s_jax.envs.checks import check_env, tree_where
from rl2s_jax.policy.policy import Params, num_policies, sample_action
from rl2s_jax.sharding import lane_mesh, replicate, shard_lanes


class RolloutCarry(NamedTuple):
    env_state: Any          # brax State, batched [B]
    pending: Any            # brax State, batched [B]: the next episode's start for each env
    fresh: jax.Array        # [B] bool: pending start not used yet
    t: jax.Array            # [B] int32: step within the current episode
    key: jax.Array
    n: jax.Array            # [] int32: rollout steps taken (sets the refresh schedule)


def make_rollout_step(env: Env, n_policies: int, envs_per_policy: int, episode_length: int,
                      refresh_every: int = 8):
    """Returns ``init(key) -> carry`` and ``step(params, carry) -> (carry, record)``.

    params: stacked policy params [P, ...]. record: dict of [B, ...] arrays for one step
    (obs, action, next_obs, reward, done, truncated, t), B = P * E, row b = p * E + e.
    ``refresh_every``: steps between the batched resets that replace used pending starts
    (1: every step).
    """
    if (not isinstance(refresh_every, (int, np.integer)) or isinstance(refresh_every, bool)
            or refresh_every < 1):
        raise ValueError(f"refresh_every: expected an int >= 1, got {refresh_every!r}")
    P, E, L = n_policies, envs_per_policy, episode_length
    B = P * E
    v_reset, v_step = jax.vmap(env.reset), jax.vmap(env.step)
    act = jax.vmap(sample_action)

    def init(key):
        k_start, k_pending, key = jax.random.split(key, 3)
        return RolloutCarry(env_state=v_reset(jax.random.split(k_start, B)),
                            pending=v_reset(jax.random.split(k_pending, B)),
                            fresh=jnp.ones((B,), bool), t=jnp.zeros((B,), jnp.int32), key=key,
                            n=jnp.zeros((), jnp.int32))

    def step(params, carry: RolloutCarry):
        key, k_act, k_reset = jax.random.split(carry.key, 3)
        obs = carry.env_state.obs
        action, _, _ = act(params, obs.reshape(P, E, -1), jax.random.split(k_act, P))
        action = action.reshape(B, -1)
        nxt = v_step(carry.env_state, action)
        done = nxt.done > 0.5
        truncated = (carry.t + 1 >= L) & ~done
        end = done | truncated

        # Refresh on schedule, or now if an env that ends has no fresh start waiting.
        refresh = (carry.n % refresh_every == 0) | jnp.any(end & ~carry.fresh)
        pending = jax.lax.cond(
            refresh, lambda p: tree_where(carry.fresh, p, v_reset(jax.random.split(k_reset, B))),
            lambda p: p, carry.pending)
        fresh = (carry.fresh | refresh) & ~end
        env_state = tree_where(end, pending, nxt)

        record = {"obs": obs, "action": action, "next_obs": nxt.obs,
                  "reward": nxt.reward.astype(jnp.float32), "done": done,
                  "truncated": truncated, "t": carry.t}
        t = jnp.where(end, 0, carry.t + 1).astype(jnp.int32)
        return RolloutCarry(env_state, pending, fresh, t, key, carry.n + 1), record

    return init, step


def _policy_mesh(n_policies: int, shard: bool):
    """The mesh collection splits the policy axis over: the most local devices that divide
    n_policies (one device when ``shard`` is False)."""
    return lane_mesh(n_policies, None if shard else jax.devices()[:1])


def _shard_batch(tree, mesh, batch: int):
    """Leaves whose leading axis is the env batch [B] split over ``mesh`` (B = P * E in policy
    order, so each device gets the envs of its own policies); the others (keys, scalars)
    replicated."""
    if mesh.size == 1:
        return tree
    is_batch = lambda x: np.ndim(x) > 0 and np.shape(x)[0] == batch
    return jax.tree_util.tree_map(
        lambda x: shard_lanes(x, mesh) if is_batch(x) else replicate(x, mesh), tree)


def run_chunked(step_fn, carry, total_steps: int, chunk_steps: int, desc: str,
                progress: bool, keep_outputs: bool = False):
    """Run ``carry, out = step_fn(carry)`` total_steps times as jitted scans of chunk_steps.

    Python only moves between chunks (progress bar, copying outputs to the host).
    Returns (carry, [host outputs of each chunk, each stacked [chunk, ...]]).
    """

    compiled, outputs, done = {}, [], 0
    with tqdm(total=total_steps, desc=desc, unit="step", leave=False,
              disable=not progress) as bar:
        while done < total_steps:
            n = min(chunk_steps, total_steps - done)
            if n not in compiled:
                compiled[n] = jax.jit(lambda c, n=n: jax.lax.scan(
                    lambda c, _: step_fn(c), c, None, length=n))
            carry, out = compiled[n](carry)
            if keep_outputs:
                outputs.append(jax.device_get(out))
            done += n
            bar.update(n)
    return carry, outputs


EPISODE_LENGTH = 1000  # collect's default episode length


def equal_chunks(total_steps: int, chunk_steps: int) -> tuple[int, int]:
    """(n, size): the fewest chunks of at most ``chunk_steps`` steps, all of one size, that
    cover ``total_steps`` (n * size - total_steps < n). One size means one compiled scan: a
    remainder chunk compiles the whole env step again (tens of seconds for MJX on a GPU)."""
    if not isinstance(chunk_steps, (int, np.integer)) or chunk_steps < 1:
        raise ValueError(f"chunk_steps: expected an int >= 1, got {chunk_steps!r}")
    if total_steps < 1:
        raise ValueError(f"total_steps: expected an int >= 1, got {total_steps!r}")
    n = math.ceil(total_steps / chunk_steps)
    return n, math.ceil(total_steps / n)


def default_envs_per_policy(transitions_per_policy: int,
                            episode_length: int = EPISODE_LENGTH) -> int:
    """As few envs per policy as let each run about one episode length (so the data covers
    whole episodes, not only their starts), at most 64."""
    return max(1, min(64, int(transitions_per_policy) // int(episode_length)))


# The parts ``collect(timer=...)`` times, in order: the transitions' programs (env resets and
# the rollout scan) compiled and run, with each chunk's copy to the host; the chunks' records
# rearranged into the Dataset's rows on the host; the true values' programs compiled and run.
COLLECT_PARTS = ("rollout_compile", "rollout_run", "rollout_host", "values_compile",
                 "values_run")


def _rows(records: list[dict], P: int, E: int, steps: int, N: int) -> dict[str, np.ndarray]:
    """The chunks' host records ({field: [chunk, B, ...]}, B = P * E) -> the Dataset's row
    fields [P * N, ...]: policy by policy, env slot by env slot, time-ordered within a slot,
    the first N of each policy; episode_id counts the episode starts (t == 0)."""
    def per_policy(name):  # [S, B, ...] -> [P * N, ...]
        x = np.concatenate([r[name] for r in records], axis=0)
        x = np.swapaxes(x, 0, 1).reshape((P, E * steps) + x.shape[2:])[:, :N]
        return x.reshape((P * N,) + x.shape[2:])

    fields = {k: per_policy(k) for k in records[0]}
    t = fields.pop("t").astype(np.int32)
    return {**{k: fields[k].astype(np.float32) for k in ("obs", "action", "next_obs", "reward")},
            "done": fields["done"], "truncated": fields["truncated"],
            "policy_id": np.repeat(np.arange(P, dtype=np.int32), N),
            "episode_id": (np.cumsum(t == 0) - 1).astype(np.int32), "t": t}


def collect(env: Env, params: Params, *, key: jax.Array, transitions_per_policy: int,
            envs_per_policy: int | None = None, episode_length: int = EPISODE_LENGTH,
            refresh_every: int = 8, chunk_steps: int = 100, task: str | None = None,
            policy_names: list[str] | None = None, gamma: float = 0.999,
            value_episodes: int = 16, source: dict | None = None, progress: bool = True,
            shard: bool = True, timer: PartTimer | None = None):
    """Collect ``transitions_per_policy`` transitions from each policy of a stacked zoo.

    env: any unwrapped brax Env (registered task or user env with changed dynamics).
    params: stacked policy params [P, ...]. Returns a ``Dataset`` whose rows are ordered policy
    by policy, env slot by env slot, time-ordered within a slot; per-policy true values come
    from ``measure_values`` (skipped when value_episodes == 0). ``shard``: split the policies
    over the local devices (module docstring). ``timer`` (``_timing.PartTimer``): times
    COLLECT_PARTS; the Dataset is the same with or without it.
    """

    check_env(env)
    P = num_policies(params)
    N = int(transitions_per_policy)
    if N <= 0:
        raise ValueError(f"transitions_per_policy: expected a positive integer, got {N}")
    if episode_length <= 0:
        raise ValueError(f"episode_length: expected a positive integer, got {episode_length}")
    E = int(envs_per_policy or default_envs_per_policy(N, episode_length))
    if not 0 < E <= N:
        raise ValueError(f"envs_per_policy: expected 1..{N}, got {E}")
    n_chunks, chunk_steps = equal_chunks(math.ceil(N / E), chunk_steps)
    steps = n_chunks * chunk_steps  # >= ceil(N / E); the extra steps are trimmed below
    policy_names = policy_names or [f"policy-{i:03d}" for i in range(P)]
    if len(policy_names) != P:
        raise ValueError(f"policy_names: expected {P} names, got {len(policy_names)}")

    key_collect, key_values = jax.random.split(key)
    init, step = make_rollout_step(env, P, E, episode_length, refresh_every)

    with timed(timer, "rollout", split_compile=True):  # ends with every chunk on the host
        mesh = _policy_mesh(P, shard)
        params = shard_lanes(params, mesh)
        carry = _shard_batch(jax.jit(init)(key_collect), mesh, P * E)
        carry, records = run_chunked(lambda c: step(params, c), carry, steps, chunk_steps,
                                     f"collect {task or 'env'} ({P} policies x {E} envs)",
                                     progress, keep_outputs=True)
    with timed(timer, "rollout_host"):
        rows = _rows(records, P, E, steps, N)
    values = {}
    if value_episodes > 0:
        with timed(timer, "values", split_compile=True):  # returns host arrays
            values = measure_values(env, params, key=key_values, n_episodes=value_episodes,
                                    episode_length=episode_length, gamma=gamma,
                                    progress=progress, shard=shard)
    meta = {"task": task, "obs_size": int(rows["obs"].shape[-1]),
            "action_size": int(rows["action"].shape[-1]), "n_policies": P,
            "gamma": float(gamma) if values else None, "episode_length": int(episode_length),
            "policy_names": list(policy_names),
            "source": {"collector": "rl2s_jax.data.collect", "envs_per_policy": E,
                       "steps_per_env": steps, "refresh_every": refresh_every,
                       "value_episodes": value_episodes, "env": type(env).__name__,
                       **(source or {})}}
    return Dataset(**rows, value=values.get("value"), value_se=values.get("value_se"),
                   value_discounted=values.get("value_discounted"),
                   value_discounted_se=values.get("value_discounted_se"), meta=meta)


def measure_values(env: Env, params: Params, *, key: jax.Array, n_episodes: int,
                   episode_length: int, gamma: float = 0.999, chunk_steps: int = 100,
                   progress: bool = False, shard: bool = True, common_groups: int = 1,
                   per_episode: bool = False) -> dict[str, np.ndarray]:
    """True value of each policy of a stacked zoo: n_episodes fresh episodes each.

    Returns {"value", "value_se", "value_discounted", "value_discounted_se"}, each [P]:
    mean (discounted) episode return over the episodes and its standard error;
    ``per_episode`` adds "returns" and "returns_discounted" [P, n_episodes].

    ``common_groups`` G > 1: the P policies are G groups of P / G (policy p in group
    p // (P / G)); the policies at one position of every group run with common random
    numbers: the same start states and the same action-noise draws, episode by episode. A
    difference between groups (for example a policy before and after fine-tuning) is then
    measured paired, with far less noise than two independent measurements.
    """
    check_env(env)
    P, E, L = num_policies(params), int(n_episodes), int(episode_length)
    if E < 1:
        raise ValueError(f"n_episodes: expected >= 1, got {E}")
    G = common_groups
    if (not isinstance(G, (int, np.integer)) or isinstance(G, bool) or G < 1 or P % G):
        raise ValueError(f"common_groups: expected an int >= 1 dividing the {P} policies, "
                         f"got {G!r}")
    G = int(G)
    B = P * E

    def common(k, n):  # n keys per group, the same in every group -> [G * n]
        keys = jax.random.split(k, n)
        return keys if G == 1 else jnp.concatenate([keys] * G)
    act = jax.vmap(sample_action)
    v_step = jax.vmap(env.step)

    def step(carry, _):
        state, alive, ret, dret, disc, key = carry
        key, k_act = jax.random.split(key)
        action, _, _ = act(params, state.obs.reshape(P, E, -1), common(k_act, P // G))
        nxt = v_step(state, action.reshape(B, -1))
        r = jnp.where(alive, nxt.reward, 0.0)
        alive_next = alive & (nxt.done < 0.5)
        return (nxt, alive_next, ret + r, dret + disc * r, disc * gamma, key), None

    mesh = _policy_mesh(P, shard)
    params = shard_lanes(params, mesh)
    k_reset, key = jax.random.split(key)
    carry = (jax.jit(jax.vmap(env.reset))(common(k_reset, B // G)),
             jnp.ones((B,), bool), jnp.zeros((B,)), jnp.zeros((B,)), jnp.ones(()), key)
    carry = _shard_batch(carry, mesh, B)
    carry, _ = run_chunked(lambda c: step(c, None), carry, L, chunk_steps, "measure values",
                           progress)
    ret = np.asarray(carry[2], np.float64).reshape(P, E)
    dret = np.asarray(carry[3], np.float64).reshape(P, E)
    se = lambda x: (x.std(axis=1, ddof=1) / np.sqrt(E)) if E > 1 else np.zeros(P)
    out = {"value": ret.mean(1).astype(np.float32), "value_se": se(ret).astype(np.float32),
           "value_discounted": dret.mean(1).astype(np.float32),
           "value_discounted_se": se(dret).astype(np.float32)}
    if per_episode:
        out.update(returns=ret, returns_discounted=dret)
    return out
