"""Lanes: several training runs (seeds, robust eps, data sets) as one vmapped program.

Every lane is a ``TrainState`` stacked on a leading axis; one jitted ``vmap(train_steps)``
advances all of them. ``rl2s diagnose`` (its base and extended fits over seeds), the paper
protocol and the ablations use these; ``train.loop.fit`` is the single-lane host loop."""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import TrainData
from rl2s_jax.train.step import TrainState, init, train_steps


def init_lanes(keys: jax.Array, cfg: TrainConfig, data: TrainData,
               eps: jax.Array | None = None) -> TrainState:
    """keys [L, 2] (one PRNG key per lane), eps [L] or None (the method's default) ->
    TrainState with a leading lane axis of size L."""
    if eps is None:
        return jax.jit(jax.vmap(lambda k, d: init(k, cfg, d), in_axes=(0, None)))(keys, data)
    return jax.jit(jax.vmap(lambda k, e, d: init(k, cfg, d, eps=e), in_axes=(0, 0, None)))(
        keys, jnp.asarray(eps, jnp.float32), data)


def _lane_chunk(st, d, n, phase):
    st, m = train_steps(st, d, n, phase)
    return st, {"finite": jnp.all(m["finite"]), "avd_train": m["avd_train"][-1],
                "mvd_train": m["mvd_train"][-1], "n_selected": m["n_selected"][-1]}


def train_lanes(states: TrainState, data: TrainData, n: int, cfg: TrainConfig,
                compiled: dict) -> tuple[TrainState, dict]:
    """n train_steps of every lane (states vmapped over lanes) -> (states, metrics of the last
    step [L]; "finite" over all n). Pieces end at the pre-training boundary, so each compiled
    program (cached in ``compiled`` by (steps, phase)) runs one phase: its static ``phase``."""
    done, m = 0, None
    while done < n:
        step = int(states.step[0])
        ph = cfg.phase(step)
        k = min(n - done, cfg.pretrain_steps - step) if ph == "pretrain" else n - done
        if (k, ph) not in compiled:
            compiled[k, ph] = jax.jit(jax.vmap(partial(_lane_chunk, n=k, phase=ph),
                                               in_axes=(0, None)))
        states, mk = compiled[k, ph](states, data)
        m = mk if m is None else {**mk, "finite": jnp.logical_and(m["finite"], mk["finite"])}
        done += k
    return states, m
