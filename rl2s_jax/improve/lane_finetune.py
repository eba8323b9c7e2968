"""Policy improvement in lanes: the same policies fine-tuned with SAC inside many simulators
(seeds, methods) at once, one program vmapped over simulators and policies, and the
simulator-side deployment guard of each lane.

A lane's simulator is a ``Simulator`` whose array leaves carry a leading lane axis L
(``train.simulator`` of vmapped training states). The variants of the simulated env
(``parse_variants``): ``full`` whole episodes from the data's start states, ``branched`` (MBPO)
short rollouts from every real state, ``penalty`` (MOPO) r - lambda * u, ``stop`` (MOReL) an
episode ended when u passes a threshold; u is the ensemble's disagreement
(``sim_env.scaled_env_options``). The paper protocol (``rl2s_jax.paper.improvement_phases``) uses
these."""
from __future__ import annotations

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.improve.finetune import deployment_guard, member_values, select_by_members
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model.simulator import Simulator
from rl2s_jax.policy.sac import SACConfig, episode_returns, make_sac

VARIANT_PARTS = ("full", "branched", "penalty", "stop")


def finite_mean(x) -> str:
    """The mean of the finite entries of x, formatted for a log line ("n/a ..." when none)."""
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return f"{x.mean():.1f}" if x.size else "n/a (no episode ended)"


def sac_for(sim: Simulator, pool, task, cfg: SACConfig, env_options=None):
    """SAC in ``sim``'s SimulatorEnv started from ``pool`` [S, o]; env_options(sim) ->
    SimulatorEnv keywords (None: the plain env)."""
    opts = env_options(sim) if env_options is not None else {}
    return make_sac(SimulatorEnv(sim, pool, task, **opts), cfg)


def parse_variants(text: str) -> list[str]:
    """A comma list of '+'-joined parts of VARIANT_PARTS, each with exactly one of full /
    branched (e.g. 'full,branched+penalty') -> the variants, in order. ValueError (starting
    "improve-variants:") on an unknown part, a variant without or with both of full /
    branched, or a repeated variant."""
    out = []
    for v in (x.strip() for x in text.split(",") if x.strip()):
        parts = v.split("+")
        bad = [p for p in parts if p not in VARIANT_PARTS]
        if bad or len(set(parts)) != len(parts) or sum(p in ("full", "branched")
                                                       for p in parts) != 1:
            raise ValueError(f"improve-variants: {v!r} must join with '+' one of full / "
                             f"branched and optionally penalty, stop (known parts: "
                             f"{', '.join(VARIANT_PARTS)})")
        out.append(v)
    if not out or len(set(out)) != len(out):
        raise ValueError(f"improve-variants: expected distinct variants, got {text!r}")
    return out


def variant_settings(variant: str, *, branch_length: int, uncertainty_penalty: float,
                     uncertainty_threshold: float, halt_penalty: float) -> dict:
    """The ``scaled_env_options`` settings of one variant (JSON-able): rollout_length
    (branched), uncertainty_penalty (penalty), uncertainty_threshold and halt_penalty (stop);
    the parts a variant lacks get their neutral values."""
    parts = variant.split("+")
    return {"rollout_length": branch_length if "branched" in parts else None,
            "uncertainty_penalty": uncertainty_penalty if "penalty" in parts else 0.0,
            "uncertainty_threshold": uncertainty_threshold if "stop" in parts else None,
            "halt_penalty": halt_penalty if "stop" in parts else 0.0}


def uses_uncertainty(variant: str) -> bool:
    """Whether the variant reads u (penalty or stop: needs >= 2 elites)."""
    return bool({"penalty", "stop"} & set(variant.split("+")))


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def improve_in_lanes(sims: Simulator, task, pool, policies, keys, cfg: SACConfig, *,
                     n_iterations: int, chunk: int, log: Callable[[str], None] | None = None,
                     env_options=None, snapshots: bool = False):
    """SAC fine-tuning of the stacked ``policies`` [P] inside each of the stacked simulators
    ``sims`` [L] (``finetune.improve_policies`` for every simulator at once: one program,
    vmapped over simulators and policies), ``chunk`` iterations per compiled call. keys
    [L, P, 2]; pool [S, o]. ``env_options(sim)``: SimulatorEnv keywords for one (traced)
    simulator. ``log``: one line per chunk. -> (actors [L, P, ...], simulated training
    return [L, P] of the episodes that ended in the last chunk (NaN if none));
    ``snapshots``: the actors after every chunk instead, [C, L, P, ...] (the last is the
    final one)."""
    pool = jnp.asarray(pool)

    def init_one(sim, ks, pols):
        return jax.vmap(sac_for(sim, pool, task, cfg, env_options).init)(ks, pols)

    states = jax.jit(jax.vmap(init_one, in_axes=(0, 0, None)))(sims, keys, policies)
    compiled, done, sim_return, kept = {}, 0, None, []
    while done < n_iterations:
        n = min(chunk, n_iterations - done)
        if n not in compiled:
            def train_one(sim, st, n=n):
                sac = sac_for(sim, pool, task, cfg, env_options)
                return jax.vmap(lambda s: sac.train(s, n))(st)
            compiled[n] = jax.jit(jax.vmap(train_one))
        t0 = time.perf_counter()
        states, metrics = compiled[n](sims, states)
        if snapshots:
            kept.append(states.actor)
        sim_return = np.asarray(episode_returns(metrics))
        done += n
        if log is not None:
            log(f"SAC {done}/{n_iterations} iterations ({time.perf_counter() - t0:.1f}s); "
                f"mean simulated training return {finite_mean(sim_return)}")
    if snapshots:
        return _stack(kept), sim_return
    return states.actor, sim_return


def guard_lanes(sims: Simulator, policies, actors, snaps, task, starts, *, margin: float,
                horizon: int, gamma: float, n_episodes: int = 16, floors=None):
    """The deployment guard of every lane, each judged by its own simulator (the elites
    differ per lane, so the lanes run one after another; keys PRNGKey(40 + lane)).
    sims [L]; policies [P] the start policies; actors [L, P, ...] the fine-tuned ones; snaps
    [C, L, P, ...] the actor after every chunk, or None; starts [S, o]; floors: L floats, each
    lane's floor in value units (``finetune.deployment_guard``), or None (0).
    -> (accepted: L bool arrays [P] (``finetune.deployment_guard`` of the final actors),
    chosen_index: L int arrays [P] (0: the start, c: snapshot c; None without snaps),
    chosen: L stacked policies [P], the snapshots ``select_by_members`` picks ([] without),
    gains: L arrays [M, P], each elite member's predicted gain of the final actor over the start
    in simulated value units: what the guard judged; starts: L arrays [M, P], each member's
    value of the start policy, which the margin scales).
    """
    n_lanes = jax.tree_util.tree_leaves(sims)[0].shape[0]
    n_pol = jax.tree_util.tree_leaves(policies)[0].shape[0]
    accepted, chosen, gains, starts_v = [], [], [], []
    chosen_index = [] if snaps is not None else None
    floors = [0.0] * n_lanes if floors is None else [float(f) for f in floors]
    if len(floors) != n_lanes:
        raise ValueError(f"floors: expected one per lane ({n_lanes}), got {len(floors)}")
    for i in range(n_lanes):
        sim, actor = jax.tree_util.tree_map(lambda x, i=i: x[i], (sims, actors))
        if snaps is None:
            both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), policies, actor)
            v = member_values(sim, task, both, starts, jax.random.PRNGKey(40 + i),
                              n_episodes=n_episodes, horizon=horizon, gamma=gamma)
            accepted.append(deployment_guard(v[:, :n_pol], v[:, n_pol:], margin, floors[i]))
            gains.append(np.asarray(v[:, n_pol:] - v[:, :n_pol]))
            starts_v.append(np.asarray(v[:, :n_pol]))
            continue
        # the start and every snapshot [C + 1, P, ...], valued once: the guard on the final
        # actors reads the first and last rows of the same values
        cands = jax.tree_util.tree_map(lambda p0, x, i=i: jnp.concatenate([p0[None], x[:, i]]),
                                       policies, snaps)
        pick, info = select_by_members(sim, task, cands, starts, jax.random.PRNGKey(40 + i),
                                       n_episodes=n_episodes, horizon=horizon, gamma=gamma,
                                       margin=margin, floor=floors[i])
        accepted.append(deployment_guard(info["values"][0], info["values"][-1], margin,
                                         floors[i]))
        gains.append(np.asarray(info["values"][-1] - info["values"][0]))
        starts_v.append(np.asarray(info["values"][0]))
        chosen_index.append(info["index"])
        chosen.append(pick)
    return accepted, chosen_index, chosen, gains, starts_v


def pick_policies(c0: np.ndarray, n: int | None) -> list[int]:
    """Indices of n policies spread evenly over their true returns c0 [P] (all when n is None
    or >= P), sorted."""
    order = np.argsort(c0, kind="stable")
    P = len(order)
    if n is None or n >= P:
        return sorted(order.tolist())
    pos = np.unique(np.round(np.linspace(0, P - 1, n)).astype(int))
    return sorted(order[pos].tolist())
