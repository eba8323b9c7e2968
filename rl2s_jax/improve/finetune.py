"""Policy improvement inside a learned simulator (the paper's downstream test).

Each policy is fine-tuned with SAC (``rl2s_jax.policy.sac``) inside the simulator, its actor
initialised from the policy (obs normaliser included), all P policies as one vmapped program.
Its real return before (C0) and after (C1) then gives the improvement

    I = (C1 - C0) / |C0|,   MPI = min_p I,   API = mean_p I.

The paper writes I = (C1 - C0) / C0; for the positive returns of its MuJoCo tasks that is the
same number. We divide by |C0| so that I > 0 always means the policy got better: with a
negative C0, (C1 - C0) / C0 would be negative for an improvement. Either way I is undefined for
C0 = 0 (refused) and large when |C0| is small, so compare I over tasks with clearly non-zero
returns.

The deployment guard (``member_values``, ``deployment_guard``, ``guarded``) keeps a fine-tuned
policy only where the simulator itself predicts a gain: every elite member, alone, must value
the fine-tuned policy above the start by more than ``margin * |start value|`` over the same
simulated episodes (common start states and keys). Elsewhere the start policy is kept, so its
improvement is exactly 0. Only the simulator is used for the decision, never the real system.
``select_by_members`` applies the same rule to the actor's snapshots along fine-tuning
(early stopping by the simulator) and deploys the snapshot whose smallest predicted gain over
the members is largest.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env
from tqdm.auto import tqdm

from rl2s_jax.data.collect import measure_values
from rl2s_jax.envs.tasks import Task, get_task
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model.simulator import Simulator, simulator_returns
from rl2s_jax.policy.policy import Params, num_policies
from rl2s_jax.policy.sac import SACConfig, episode_returns, make_sac
from rl2s_jax.stats import paired_gain


def improve_policies(sim: Env | Simulator | Callable, task: Task | str | None,
                     start_pool, policies: Params, key: jax.Array, sac_cfg: SACConfig, *,
                     n_iterations: int, deterministic: bool = False,
                     chunk_iterations: int | None = None, env_options: dict | None = None,
                     progress: bool = False, snapshots: bool = False) -> tuple[Params, dict]:
    """Fine-tune each of the stacked ``policies`` [P, ...] with SAC inside the simulator.

    sim: a ``SimulatorEnv`` (or any unwrapped brax Env, e.g. the real ``task.make_env()``;
      then task and start_pool are unused), or a ``Simulator`` / ``dynamics(obs, action,
      key)`` from which a ``SimulatorEnv`` is built with ``task``, ``start_pool`` [S, o],
      ``deterministic`` and ``env_options`` (SimulatorEnv keywords: rollout_length,
      uncertainty_fn, uncertainty_penalty, uncertainty_threshold, halt_penalty).
    n_iterations: SAC iterations per policy (each: ``sac_cfg.n_envs`` env steps and
      ``sac_cfg.updates_per_step`` updates), run as jitted chunks of ``chunk_iterations``
      (default: all at once); ``progress``: a progress bar over the chunks.

    Returns (improved policies [P, ...] in the same layout, metrics: dict of [P, n_iterations]
    arrays from ``sac.train``). ``snapshots=True``: the first item is instead the actor at the
    start and after every chunk, [C + 1, P, ...] (index 0: the start policies, index C: the
    final ones), the candidates of ``select_by_validation``.
    """
    if n_iterations < 1:
        raise ValueError(f"n_iterations: expected >= 1, got {n_iterations}")
    chunk = int(chunk_iterations or n_iterations)
    if chunk < 1:
        raise ValueError(f"chunk_iterations: expected >= 1, got {chunk_iterations}")
    if isinstance(sim, Env):
        env = sim
    else:
        env = SimulatorEnv(sim, start_pool, task, deterministic=deterministic,
                           **(env_options or {}))
    sac = make_sac(env, sac_cfg)
    n_pol = num_policies(policies)
    states = jax.jit(jax.vmap(sac.init))(jax.random.split(key, n_pol), policies)
    compiled, metrics, done = {}, [], 0
    kept = [states.actor] if snapshots else None
    bar = None
    if progress:
        bar = tqdm(total=n_iterations, unit="it", desc=f"SAC x {n_pol} policies",
                   dynamic_ncols=True)
    try:
        while done < n_iterations:
            n = min(chunk, n_iterations - done)
            if n not in compiled:
                compiled[n] = jax.jit(jax.vmap(lambda s, n=n: sac.train(s, n)))
            states, m = compiled[n](states)
            metrics.append(m)
            if kept is not None:
                kept.append(states.actor)
            done += n
            if bar is not None:
                ret = np.asarray(episode_returns(m))
                ret = ret[np.isfinite(ret)]
                bar.update(n)
                bar.set_postfix(sim_return=f"{ret.mean():.3g}" if ret.size else "n/a",
                                refresh=False)
    finally:
        if bar is not None:
            bar.close()
    metrics = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=1), *metrics)
    if kept is not None:
        return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *kept), metrics
    return states.actor, metrics


def choose_candidates(returns, z: float = 2.0) -> np.ndarray:
    """The rule of ``select_by_validation`` on measured returns.

    returns: [K + 1, P, E] episode returns of K + 1 candidates of each of P policies
    (candidate 0: the start policy), episode e of every candidate of policy p from the same
    start state and noise draws. Candidate k > 0 is eligible when its mean paired gain over the
    start exceeds ``z`` standard errors of the paired differences (and is > 0); the eligible
    candidate with the highest mean return wins, else the start (0). -> [P] int indices.
    """
    r = np.asarray(returns, np.float64)
    if r.ndim != 3 or r.shape[0] < 2 or r.shape[2] < 2:
        raise ValueError(f"returns: expected [K + 1 >= 2, P, E >= 2], got {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("returns: expected finite episode returns")
    if not (np.isfinite(z) and z >= 0):
        raise ValueError(f"z: expected a finite float >= 0, got {z!r}")
    mean, se = paired_gain(r)
    eligible = (mean > z * se) & (mean > 0)
    score = np.where(eligible, r[1:].mean(-1), -np.inf)
    best = score.argmax(0)
    return np.where(eligible.any(0), best + 1, 0).astype(np.int32)


def _candidate_shape(candidates: Params) -> tuple[int, int]:
    """(K + 1, P) of candidates [K + 1, P, ...]; refused unless every leaf has that lead."""
    leaves = jax.tree_util.tree_leaves(candidates)
    K1 = int(leaves[0].shape[0])
    if (K1 < 2 or any(x.ndim < 2 or x.shape[:2] != leaves[0].shape[:2] for x in leaves)):
        raise ValueError(f"candidates: expected leaves [K + 1 >= 2, P, ...] with one leading "
                         f"[K + 1, P], got {sorted({x.shape[:2] for x in leaves})}")
    return K1, int(leaves[0].shape[1])


def _pick_candidates(candidates: Params, index) -> Params:
    """Policy p's candidate index[p] from candidates [K + 1, P, ...] -> [P, ...]."""
    index = jnp.asarray(index)
    return jax.tree_util.tree_map(lambda x: x[index, jnp.arange(index.shape[0])], candidates)


def select_by_validation(env: Env, candidates: Params, key: jax.Array, *, n_episodes: int,
                         episode_length: int, gamma: float = 0.999, z: float = 2.0
                         ) -> tuple[Params, dict]:
    """Per policy, the candidate with the best validated return in ``env``.

    candidates: [K + 1, P, ...] (``improve_policies(snapshots=True)``; index 0 the start
    policies). All (K + 1) x P run ``n_episodes`` episodes in ``env`` with common random
    numbers across the candidates of a policy; ``choose_candidates`` then keeps a fine-tuned
    snapshot only where its paired gain over the start is significant (``z`` standard errors),
    so a policy that fine-tuning did not clearly improve is deployed unchanged. Use episodes
    (a key) that the final measurement does not reuse. -> (chosen policies [P, ...],
    {"index": [P] chosen candidate, "validation_mean": [K + 1, P], "gain_se": [K, P]}).
    """
    K1, P = _candidate_shape(candidates)
    group = lambda k: jax.tree_util.tree_map(lambda x: x[k], candidates)  # noqa: E731
    r0, rest = paired_episode_returns(env, group(0), [group(k) for k in range(1, K1)], key,
                                      n_episodes=n_episodes, episode_length=episode_length,
                                      gamma=gamma)
    r = np.stack([r0, *rest]).astype(np.float64)
    index = choose_candidates(r, z)
    return (_pick_candidates(candidates, index),
            {"index": index, "validation_mean": r.mean(-1), "gain_se": paired_gain(r)[1]})


@partial(jax.jit, static_argnames=("task", "n_episodes", "horizon", "gamma"))
def _member_returns(sim: Simulator, members, policies, pool, key, *, task: Task,
                    n_episodes: int, horizon: int, gamma: float) -> jax.Array:
    """[M, P] mean simulated return of each policy under each of ``members`` [M] alone
    (``sim`` in member_mode "fixed": the member ranked first is the one that steps). Every
    policy runs its episodes as if it were alone, with the same key: common start states and
    noise draws for every policy and member."""
    E = sim.n_members

    def one(m, policy):
        alone = sim.replace(rank=((jnp.arange(E) - m) % E).astype(jnp.int32))
        ret, _ = simulator_returns(alone, task, jax.tree_util.tree_map(lambda x: x[None], policy),
                                   pool, key, n_episodes=n_episodes, horizon=horizon,
                                   gamma=gamma)
        return ret[0].mean()
    return jax.vmap(lambda m: jax.vmap(lambda p: one(m, p))(policies))(members)


def member_values(sim: Simulator, task: Task | str | None, policies: Params, start_pool,
                  key: jax.Array, *, n_episodes: int, horizon: int, gamma: float
                  ) -> np.ndarray:
    """Each elite member's simulated discounted value of each policy, the member alone (its
    mean step when the simulator's noise_scale is 0): [M elites, P], best elite first. Every
    member and policy runs from the same start states with the same keys (each policy as if
    valued alone, so a value does not depend on the other policies valued with it), and
    differences between two policies are paired comparisons. ``task`` None: the simulator's
    own ``task_fns`` (a learned reward is then a traced argument, not a constant)."""
    task = get_task(task) if isinstance(task, str) else task
    E = sim.n_members
    rank = np.arange(E) if sim.rank is None else np.asarray(sim.rank)
    n_el = E if sim.n_elites is None else min(int(sim.n_elites), E)
    elites = jnp.asarray(np.argsort(rank, kind="stable")[:n_el], jnp.int32)
    values = _member_returns(sim.replace(member_mode="fixed"), elites, policies,
                             jnp.asarray(start_pool), key, task=task, n_episodes=n_episodes,
                             horizon=horizon, gamma=float(gamma))
    return np.asarray(values, np.float64)


def deployment_guard(start_values, tuned_values, margin: float = 0.0,
                     floor: float = 0.0) -> np.ndarray:
    """[P] bool: deploy the fine-tuned policy p only if every member predicts a gain,
    tuned_values[m, p] - start_values[m, p] > max(margin * |start_values[m, p]|, floor) for
    all m. start_values, tuned_values: [M, P] (``member_values``). ``floor``: a gain in value
    units that a prediction must exceed, e.g. the simulator's worst value error on the
    training policies (their MVD), whose true values are known: a gain smaller than the
    error the simulator is known to make is not trusted."""
    v0, v1 = np.asarray(start_values, np.float64), np.asarray(tuned_values, np.float64)
    if v0.ndim != 2 or v0.shape != v1.shape:
        raise ValueError(f"tuned_values: expected the shape of start_values [M, P] "
                         f"{v0.shape}, got {v1.shape}")
    if not (np.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin: expected a finite float >= 0, got {margin!r}")
    if not (np.isfinite(floor) and floor >= 0):
        raise ValueError(f"floor: expected a finite float >= 0 (value units), got {floor!r}")
    if not (np.all(np.isfinite(v0)) and np.all(np.isfinite(v1))):
        raise ValueError("start_values, tuned_values: expected finite simulated values")
    return np.all(v1 - v0 > np.maximum(margin * np.abs(v0), floor), axis=0)


def choose_by_members(values, margin: float = 0.0, floor: float = 0.0) -> np.ndarray:
    """The deployment guard over several snapshots: early stopping by the simulator alone.

    values: [K + 1, M, P] each elite member's simulated value (``member_values``) of K + 1
    candidates of each of P policies (candidate 0: the start policy). Candidate k > 0 is
    eligible when every member predicts a gain over the start above ``margin`` x |start
    value| and ``floor`` (``deployment_guard``); the eligible candidate with the largest
    smallest gain over the members wins, else the start (0). With K = 1 this is
    ``deployment_guard``.
    -> [P] int indices.
    """
    v = np.asarray(values, np.float64)
    if v.ndim != 3 or v.shape[0] < 2:
        raise ValueError(f"values: expected [K + 1 >= 2, M, P], got {v.shape}")
    eligible = np.stack([deployment_guard(v[0], vk, margin, floor) for vk in v[1:]])  # [K, P]
    score = np.where(eligible, (v[1:] - v[:1]).min(axis=1), -np.inf)
    return np.where(eligible.any(0), score.argmax(0) + 1, 0).astype(np.int32)


def select_by_members(sim: Simulator, task: Task | str | None, candidates: Params,
                      start_pool, key: jax.Array, *, n_episodes: int, horizon: int,
                      gamma: float, margin: float = 0.0, floor: float = 0.0
                      ) -> tuple[Params, dict]:
    """Per policy, the snapshot the simulator's elite members all rank above the start.

    candidates: [K + 1, P, ...] (``improve_policies(snapshots=True)``; index 0 the start
    policies). Every candidate is valued by every elite member alone over the same simulated
    episodes (``member_values``); ``choose_by_members`` picks. Only the simulator decides.
    -> (chosen policies [P, ...], {"index": [P], "values": [K + 1, M, P]}).
    """
    K1, P = _candidate_shape(candidates)
    flat = jax.tree_util.tree_map(lambda x: x.reshape((K1 * P,) + x.shape[2:]), candidates)
    v = member_values(sim, task, flat, start_pool, key, n_episodes=n_episodes,
                      horizon=horizon, gamma=gamma)                # [M, (K + 1) * P]
    values = v.reshape(v.shape[0], K1, P).transpose(1, 0, 2)
    index = choose_by_members(values, margin, floor)
    return _pick_candidates(candidates, index), {"index": index, "values": values}


def guarded(start: Params, tuned: Params, accept) -> Params:
    """The deployed policies [P, ...]: ``tuned`` where ``accept`` [P], else ``start``."""
    accept = jnp.asarray(accept, bool)

    def pick(a, b):
        return jnp.where(accept.reshape(accept.shape + (1,) * (a.ndim - 1)), b, a)
    return jax.tree_util.tree_map(pick, start, tuned)


def improve_in_real_env(task: Task | str, policies: Params, key: jax.Array,
                        sac_cfg: SACConfig, *, n_iterations: int, n_episodes: int,
                        episode_length: int | None = None, gamma: float = 0.999,
                        chunk_iterations: int | None = None, env: Env | None = None,
                        progress: bool = False, select_episodes: int = 0,
                        select_z: float = 2.0) -> tuple[Params, dict, dict]:
    """The real-env control: the same SAC fine-tuning (same start policies, budget and
    settings) run in the real env instead of a learned simulator, then the real returns
    before and after (``measure_improvement``, ``n_episodes`` fresh episodes each).

    It is the ceiling of improvement for that budget: when it does not improve the policies,
    no simulator can be blamed. task: a Task or its name (``env`` defaults to
    ``task.make_env()``). -> (improved policies [P, ...], SAC metrics [P, n_iterations],
    {"c0", "c0_se", "c1", "c1_se", "I": [P], "mpi", "api"}).

    ``select_episodes`` > 0: early stopping on real validation returns. The actor is kept at
    the start and after every chunk of ``chunk_iterations``, and each policy deploys the
    snapshot that ``select_by_validation`` picks over ``select_episodes`` further real
    episodes (start states and noise draws apart from the final measurement's); the result
    then also holds "selected" (the chosen snapshot [P], 0 = the start) and "final" (the same
    measurement of the last snapshot, undeployed, for comparison).
    """
    task = get_task(task) if isinstance(task, str) else task
    env = task.make_env() if env is None else env
    if select_episodes < 0 or select_episodes == 1:
        raise ValueError(f"select_episodes: expected 0 (off) or >= 2, got {select_episodes}")
    k_sac, k_measure, k_select = jax.random.split(key, 3)
    length = episode_length or task.episode_length
    out, metrics = improve_policies(env, None, None, policies, k_sac, sac_cfg,
                                    n_iterations=n_iterations, chunk_iterations=chunk_iterations,
                                    progress=progress, snapshots=select_episodes > 0)
    if select_episodes == 0:
        res = measure_improvement(env, policies, out, k_measure, n_episodes=n_episodes,
                                  episode_length=length, gamma=gamma)
        return out, metrics, res
    after, info = select_by_validation(env, out, k_select, n_episodes=select_episodes,
                                       episode_length=length, gamma=gamma, z=select_z)
    final = jax.tree_util.tree_map(lambda x: x[-1], out)
    r0, (r_after, r_final) = paired_episode_returns(env, policies, [after, final], k_measure,
                                                    n_episodes=n_episodes,
                                                    episode_length=length, gamma=gamma)
    res, res_final = paired_returns(r0, r_after), paired_returns(r0, r_final)
    res["selected"] = info["index"]
    res["validation_mean"] = info["validation_mean"]
    res["validation_gain_se"] = info["gain_se"]
    res["final"] = res_final
    return after, metrics, res


def training_return_curve(metrics: dict, n_points: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """SAC's own (simulated) training return over the iterations, from ``train``'s metrics
    ([P, T] return_sum / episodes): the mean return of the episodes that ended in each of
    ``n_points`` equal windows. -> (iteration at each window's end [W], returns [P, W];
    NaN where no episode ended)."""
    ret, ep = np.asarray(metrics["return_sum"]), np.asarray(metrics["episodes"])
    T = ret.shape[-1]
    edges = np.unique(np.linspace(0, T, min(n_points, T) + 1).astype(int))
    r = np.add.reduceat(ret, edges[:-1], axis=-1)
    e = np.add.reduceat(ep, edges[:-1], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return edges[1:], np.where(e > 0, r / np.maximum(e, 1), np.nan)


def improvement_metrics(c0, c1) -> dict[str, np.ndarray | float]:
    """Improvement of each policy from real returns before (c0 [P]) and after (c1 [P]).

    -> {"I": (c1 - c0) / |c0| [P], "mpi": min I, "api": mean I} (see the module docstring for
    |c0| rather than c0).
    """
    c0 = np.asarray(c0, np.float64)
    c1 = np.asarray(c1, np.float64)
    for name, c in (("c0", c0), ("c1", c1)):
        if c.ndim != 1 or c.shape[0] < 1:
            raise ValueError(f"{name}: expected shape [P >= 1], got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError(f"{name}: expected finite returns, got {c}")
    if c0.shape != c1.shape:
        raise ValueError(f"c1: expected the shape of c0 {c0.shape}, got {c1.shape}")
    if np.any(c0 == 0):
        raise ValueError(f"c0: improvement is undefined for a zero return, got zeros at "
                         f"{np.flatnonzero(c0 == 0).tolist()}")
    imp = (c1 - c0) / np.abs(c0)
    return {"I": imp, "mpi": float(imp.min()), "api": float(imp.mean())}


def median_gain(c0, c1, start_returns, zoo_returns, quantile: float = 0.75) -> dict:
    """Issue 39's summary of fine-tuning: the median real gain of the policies that start
    below the zoo's top quartile.

    c0, c1: [R, P] real returns before / after over R seeds (or [P]); start_returns [P]: the
    zoo's measured return of each fine-tuned policy; zoo_returns [Z]: every zoo policy's. A
    policy counts when its start return is below the ``quantile`` of ``zoo_returns``; its gain
    is I = (C1 - C0) / |C0| averaged over the seeds. -> {"median_gain", "n_below", "below":
    [P] bool, "gain": [P] seed-mean I}."""
    c0 = np.atleast_2d(np.asarray(c0, np.float64))
    c1 = np.atleast_2d(np.asarray(c1, np.float64))
    start = np.asarray(start_returns, np.float64)
    if c0.shape != c1.shape or c0.shape[1] != start.shape[0]:
        raise ValueError(f"c0, c1, start_returns: expected [R, P], [R, P], [P], got {c0.shape}, "
                         f"{c1.shape}, {start.shape}")
    gain = np.mean([improvement_metrics(a, b)["I"] for a, b in zip(c0, c1, strict=True)], 0)
    below = start < np.quantile(np.asarray(zoo_returns, np.float64), quantile)
    med = float(np.median(gain[below])) if below.any() else float("nan")
    return {"median_gain": med, "n_below": int(below.sum()), "below": below.tolist(),
            "gain": gain.tolist()}


def measure_improvement(real_env: Env, before: Params, after: Params, key: jax.Array, *,
                        n_episodes: int, episode_length: int, gamma: float = 0.99,
                        discounted: bool = False) -> dict[str, np.ndarray | float]:
    """Real returns of the stacked policies before and after [P, ...] (``measure_values`` in
    ``real_env``, n_episodes each) and their improvement.

    The two are measured paired: policy p before and after fine-tuning run from the same
    start states with the same action-noise draws (``measure_values(common_groups=2)``), so
    C1 - C0 is measured with the per-episode differences' standard error ``diff_se``, far
    smaller than the two returns' own. A policy whose parameters did not change (a guard or
    the selection kept its start) gets C1 = C0 exactly. C is the mean undiscounted episode
    return (``discounted=True``: the discounted one).
    -> {"c0", "c0_se", "c1", "c1_se", "diff_se": [P], "I": [P], "mpi", "api"}.
    """
    r0, (r1,) = paired_episode_returns(real_env, before, [after], key, n_episodes=n_episodes,
                                       episode_length=episode_length, gamma=gamma,
                                       discounted=discounted)
    return paired_returns(r0, r1)


def paired_episode_returns(env: Env, before: Params, afters: Sequence[Params], key: jax.Array,
                           *, n_episodes: int, episode_length: int, gamma: float,
                           discounted: bool = False) -> tuple[np.ndarray, list[np.ndarray]]:
    """Episode returns of ``before`` [P, ...] and of each of ``afters`` (each [P, ...]) in
    ``env``, policy p of every group from the same start states with the same action-noise
    draws. -> (r0 [P, E], [r_k [P, E] per after]).

    Groups of one layout run as one batch (``measure_values(common_groups=1 + K)``), others in
    calls of their own with the same key (the same starts and draws). A policy whose parameters
    equal its ``before`` gets r0: it is the same random variable (two lanes of one batch can
    round differently, on the CPU and for Ant on the GPU, and a chaotic task turns that into a
    different episode).
    """
    P = num_policies(before)
    for k, a in enumerate(afters):
        if num_policies(a) != P:
            raise ValueError(f"after: expected {P} policies as before, got {num_policies(a)} "
                             f"(group {k})")
    kw = dict(n_episodes=n_episodes, episode_length=episode_length, gamma=gamma,
              per_episode=True)
    field = "returns_discounted" if discounted else "returns"
    same = [_same_layout(before, a) for a in afters]
    batched = [a for a, s in zip(afters, same, strict=True) if s]
    groups = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), before, *batched)
    r = np.asarray(measure_values(env, groups, key=key, common_groups=1 + len(batched),
                                  **kw)[field])
    r0, out, k = r[:P], [], 0
    for a, s in zip(afters, same, strict=True):
        if s:
            k += 1
            rk = r[k * P:(k + 1) * P]
            out.append(np.where(unchanged_policies(before, a)[:, None], r0, rk))
        else:
            out.append(np.asarray(measure_values(env, a, key=key, **kw)[field]))
    return r0, out


def _same_layout(a: Params, b: Params) -> bool:
    return (jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
            and all(x.shape == y.shape for x, y in zip(jax.tree_util.tree_leaves(a),
                                                       jax.tree_util.tree_leaves(b),
                                                       strict=True)))


def unchanged_policies(before: Params, after: Params) -> np.ndarray:
    """[P] bool: policy p's parameters are equal in ``before`` and ``after`` (same layout)."""
    eq = [np.asarray(a == b).reshape(a.shape[0], -1).all(1)
          for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after),
                          strict=True)]
    return np.logical_and.reduce(eq)


def paired_returns(r0: np.ndarray, r1: np.ndarray) -> dict[str, np.ndarray | float]:
    """Means, standard errors and improvement from paired episode returns r0, r1 [P, E]
    (episode e of policy p before and after shares its start and noise draws).
    -> {"c0", "c0_se", "c1", "c1_se", "diff_se": [P], "I": [P], "mpi", "api"}."""
    r0, r1 = np.asarray(r0, np.float64), np.asarray(r1, np.float64)
    if r0.ndim != 2 or r0.shape != r1.shape:
        raise ValueError(f"r0, r1: expected one shape [P, E], got {r0.shape} and {r1.shape}")
    E = r0.shape[1]
    se = (lambda x: x.std(axis=1, ddof=1) / np.sqrt(E)) if E > 1 else (
        lambda x: np.zeros(x.shape[0]))
    c0, c1 = r0.mean(1), r1.mean(1)
    return {"c0": c0, "c0_se": se(r0), "c1": c1, "c1_se": se(r1), "diff_se": se(r1 - r0),
            **improvement_metrics(c0, c1)}
