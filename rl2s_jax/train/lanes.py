"""Lanes: several training runs (seeds, robust eps, data sets) as one vmapped program.

Every lane is a ``TrainState`` stacked on a leading axis; one jitted ``vmap(train_steps)``
advances all of them. ``rl2s diagnose`` (its base and extended fits over seeds), the paper
protocol and the ablations use these; ``train.loop.fit`` is the single-lane host loop. The
lanes' evaluation is ``evaluate.lane_scores``; ``select_point`` chooses a lane's evaluation point
without the test policies, from the training policies' held-out episodes
(``heldout_start_pool``). ``fork`` / ``fork_lanes`` continue one pre-trained lane as several
adversarial lanes (issue 40: RL2S and GAIL of a seed pre-train once)."""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.model.simulator import start_pool
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.cvar import n_worst, select_worst
from rl2s_jax.train.data import TrainData, heldout_mask
from rl2s_jax.train.loop import WORST_VD_JUMP
from rl2s_jax.train.step import TrainState, init, train_steps


@partial(jax.jit, static_argnums=1)
def _init_lanes(keys, cfg: TrainConfig, data: TrainData, eps):
    if eps is None:
        return jax.vmap(lambda k: init(k, cfg, data))(keys)
    return jax.vmap(lambda k, e: init(k, cfg, data, eps=e))(keys, eps)


def init_lanes(keys: jax.Array, cfg: TrainConfig, data: TrainData,
               eps: jax.Array | None = None) -> TrainState:
    """keys [L, 2] (one PRNG key per lane), eps [L] or None (the method's default) ->
    TrainState with a leading lane axis of size L. Compiled once per (cfg, shapes)."""
    return _init_lanes(keys, cfg, data, None if eps is None else jnp.asarray(eps, jnp.float32))


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
        k = min(n - done, cfg.adversarial.pretrain_steps - step) if ph == "pretrain" else n - done
        if (k, ph) not in compiled:
            compiled[k, ph] = jax.jit(jax.vmap(partial(_lane_chunk, n=k, phase=ph),
                                               in_axes=(0, None)))
        states, mk = compiled[k, ph](states, data)
        m = mk if m is None else {**mk, "finite": jnp.logical_and(m["finite"], mk["finite"])}
        done += k
    return states, m


# What init draws for the adversarial phase alone, which pre-training never reads or writes.
FORK_REDRAWN = ("eps", "disc", "disc_us", "disc_opt", "sim", "buffer_obs", "buffer_act",
                "buffer_hist", "buffer_pos")


def fork(trunk: TrainState, start: TrainState) -> TrainState:
    """The lane ``start`` continued from ``trunk``'s pre-training (issue 40, item 3).

    An adversarial method's pre-training (its first ``pretrain_steps`` steps) is likelihood
    steps on every training policy and the value measurement; neither reads eps, the CVaR
    selection, the critic, the simulated envs or their buffer. So a lane of another eps (GAIL
    beside RL2S) need not pre-train again: ``trunk`` is a lane pre-trained for at most
    ``pretrain_steps`` steps, ``start`` the fresh ``init`` (step 0, the same static config) of
    the lane to continue. The result:

    - shared with ``trunk`` (what pre-training computed): ``step``, ``key`` (the rest of the
      run draws from the trunk's key stream), the normaliser, the members (``gen``,
      ``gen_opt``, ``best_gen``, ``ema_gen``), their held-out scores and early-stopping
      bookkeeping (``heldout_nll``, ``rank``, ``best_nll``, ``since_best``, ``stopped``), the
      value measurement (``vd``, ``sim_value``, ``sim_length``, ``vd_roll``) and the learned
      termination and reward heads (``hazard``, ``reward``);
    - taken from ``start`` (``FORK_REDRAWN``: drawn by ``init`` with start's key, untouched
      by pre-training): ``eps``, the critic (``disc``, ``disc_us``, ``disc_opt``), the
      simulated envs (``sim``) and the buffer (``buffer_obs``, ``buffer_act``,
      ``buffer_hist``, ``buffer_pos``);
    - recomputed: ``selected``, the worst n_worst(start's eps, P) of the trunk's last
      measured VD (everyone without a value measurement), which is what the lane's own run
      would hold, since every measurement recomputes the selection from the stored VD.

    With ``start = init(k, cfg, data, eps)`` and ``trunk`` pre-trained from ``init(k, cfg,
    data, eps')``, the fork is leaf for leaf the state that ``init(k, cfg, data, eps)``
    pre-trained for the trunk's steps would be (tests/test_fork.py checks it bit for bit); the
    paper protocol gives every method of a seed the key PRNGKey(seed), so its forked lanes are
    its separate lanes. With another key for ``start``, the critic, envs and buffer are fresh
    draws and the adversarial phase still draws from the trunk's key. Pure and jittable; the
    caller checks the steps (``fork_lanes`` does)."""
    if trunk.config != start.config:
        raise ValueError("fork: the trunk and the start have different configs")
    if not start.config.pretrains:
        raise ValueError("fork: needs an adversarial method with pretrain_steps > 0 (the "
                         "state the lanes share)")
    cfg = start.config
    state = trunk.replace(**{name: getattr(start, name) for name in FORK_REDRAWN})
    if cfg.vd.every:
        state = state.replace(selected=select_worst(trunk.vd,
                                                    n_worst(start.eps, trunk.vd.shape[0])))
    return state


_fork_lanes = jax.jit(jax.vmap(fork))


def fork_lanes(trunk: TrainState, starts: TrainState) -> TrainState:
    """``fork`` of every lane: trunk [L] pre-trained lanes (``paper.fork.take_lanes`` repeats a
    trunk lane for each lane forked from it), starts [L] their fresh ``init_lanes`` -> [L].
    ValueError when a start is not at step 0 or the trunk is past its pre-training."""
    cfg = starts.config
    steps = np.asarray(trunk.step)
    if np.any(np.asarray(starts.step) != 0):
        raise ValueError("fork_lanes: the starts must be fresh lanes (step 0)")
    if not cfg.pretrains or np.any(steps > cfg.adversarial.pretrain_steps):
        raise ValueError(f"fork_lanes: the trunk must be within its pre-training (steps <= "
                         f"adversarial.pretrain_steps {cfg.adversarial.pretrain_steps}), got "
                         f"steps {steps.tolist()}")
    return _fork_lanes(trunk, starts)


def heldout_start_pool(train_ds) -> jax.Array:
    """Start states [S, o] of the training policies' held-out episodes (the split
    ``make_train_data`` makes with the default holdout_frac, whatever the variant's), the
    whole data's start pool if none of them starts at t = 0."""
    held = heldout_mask(train_ds, TrainConfig().holdout_frac)
    starts = held & (np.asarray(train_ds.t) == 0)
    if not starts.any():
        return start_pool(train_ds)
    return jnp.asarray(np.asarray(train_ds.obs)[starts], jnp.float32)


def select_point(points: list[dict]) -> dict | None:
    """Model selection without the test policies: of a lane's evaluation points
    ({"step", "select": metrics of the TRAINING policies started from their held-out episodes,
    "test": the test metrics}), the one with the highest selection tau (ties: the lower
    selection AVD; non-finite last). A point whose selection MVD exploded (above
    WORST_VD_JUMP times the lane's lowest) is rejected, unless every point would be (issue
    41: a catastrophic RL2S seed ranked well while its worst training VD had blown up). None
    when no point has both."""
    ok = [p for p in points if p["select"] is not None and p["test"] is not None]
    if not ok:
        return None
    mvd = np.asarray([p["select"].get("mvd", np.nan) for p in ok], np.float64)
    tau = np.asarray([p["select"]["kendall_tau"] for p in ok], np.float64)
    healthy = np.isfinite(mvd) & np.isfinite(tau)  # a diverged point sets no bound
    if healthy.any():
        bound = WORST_VD_JUMP * mvd[healthy].min()
        ok = [p for p, m in zip(ok, mvd, strict=True) if np.isfinite(m) and m <= bound] or ok
    finite = lambda x: x if np.isfinite(x) else -np.inf
    return max(ok, key=lambda p: (finite(p["select"]["kendall_tau"]),
                                  finite(-p["select"]["avd"])))
