"""The protocol's fork and join (issue 40, item 3; ``paper.protocol.train_family``): the
adversarial family's lanes of a seed are identical through pre-training, so its first
method's lanes (the trunk) pre-train for all and the others fork off them (``Trunk``); the
likelihood family's BC lanes take the same pre-training steps, so they join from the trunk
(``Join``, ``join_trunk``) when ``join_refusal`` finds nothing that would make their own run
differ. ``train_chunk`` trains the lanes with a pending fork or join."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from rl2s_jax.sharding import replicate, shard_lanes
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.cvar import n_worst, select_worst
from rl2s_jax.train.lanes import fork_lanes, train_lanes
from rl2s_jax.train.step import TrainState


def take_lanes(tree, idx):
    """The lanes ``idx`` [K] of a pytree with a leading lane axis -> [K, ...] leaves."""
    idx = jnp.asarray(idx)
    return jax.tree_util.tree_map(lambda x: x[idx], tree)


def _on_one_device(tree):
    """``tree`` on this process's first device (lanes from meshes of different sizes meet
    there before ``shard_lanes`` spreads them again; one device: where they are)."""
    return jax.device_put(tree, jax.local_devices()[0])


class Trunk:
    """A family's lanes while its first method's lanes (the trunk, one per seed) pre-train for
    all of them (issue 40, item 3): ``train.lanes.fork_lanes`` forks the others off at the end
    of pre-training, or when training ends before it. ``record`` (train_family's
    ``share["trunk"]``): the trunk's evaluation points up to the fork and its pre-trained
    fields at step ``at``, for the likelihood family's BC lanes (``Join``)."""

    def __init__(self, starts, n_trunk: int, n_lanes: int, at: int, record: dict | None):
        self.starts = starts                              # every lane's fresh init [L]
        self.of = [i % n_trunk for i in range(n_lanes)]   # lane -> its trunk lane
        self.now = list(range(n_trunk))                   # the lanes that train now
        self.at, self.record = at, record

    def expand(self, rows: list) -> list:
        return [rows[j] for j in self.of]

    def rows(self, step, evals, values, returns, lengths, selects, m, n_sel):
        """The trunk's evaluation at ``step`` as every lane's (a lane is its seed's trunk
        lane until the fork; its selected count its own eps's, ``n_sel``)."""
        m = {k: np.asarray(v) for k, v in m.items()}
        if self.record is not None:
            self.record["points"][step] = dict(
                evals=list(evals), values=list(values), returns=list(returns),
                lengths=list(lengths), selects=list(selects),
                m={k: m[k] for k in ("avd_train", "mvd_train", "finite")})
        out = [self.expand(list(x)) for x in (evals, values, returns, lengths, selects)]
        m = {k: v[self.of] for k, v in m.items()}
        m["n_selected"] = np.asarray(n_sel)
        return (*out, m)

    def grow(self, trunk, m, mesh):
        """The fork of ``trunk`` (its states at the end of pre-training, or of training
        before it; ``m``: its metrics since the last evaluation, None for none)."""
        if self.record is not None and int(trunk.step[0]) == self.at:
            self.record["fields"] = _on_one_device({name: getattr(trunk, name)
                                                    for name in JOINED})
            self.record["finite_before"] = (np.ones(len(self.now), bool) if m is None
                                            else np.asarray(m["finite"]))
        return jax.block_until_ready(fork_lanes(shard_lanes(take_lanes(trunk, self.of), mesh),
                                                self.starts))

    def finite_before(self, m):
        return np.asarray(m["finite"])[self.of]


# What a BC lane takes from the adversarial trunk lane of its seed when it joins the likelihood
# family at the end of pre-training (``join_trunk``): everything pre-training writes, which the
# BC lane's own likelihood steps from the same key write bitwise alike (tests/test_fork.py).
JOINED = ("step", "key", "gen", "gen_opt", "best_gen", "ema_gen", "heldout_nll", "rank",
          "best_nll", "since_best", "stopped", "vd", "sim_value", "sim_length", "vd_roll")


def join_trunk(trunk: dict, start: TrainState) -> TrainState:
    """A BC lane continued from an adversarial trunk lane's pre-training (issue 40, item 3):
    ``start`` (the BC lane's fresh ``init``: step 0, its config and eps) with the trunk's
    ``JOINED`` fields (``trunk``: {name: leaf}); the rest (eps, normaliser, learned
    termination and reward heads, config) is start's, and ``selected`` is the worst
    n_worst(start's eps, P) of the trunk's VD, as the lane's own run holds it (every VD
    measurement recomputes it). With the same key and a config equal but for the method, the
    result is the state BC's own first ``step`` steps reach. Pure and jittable."""
    state = start.replace(**{name: trunk[name] for name in JOINED})
    if start.config.vd.every:
        state = state.replace(selected=select_worst(state.vd,
                                                    n_worst(start.eps, state.vd.shape[0])))
    return state


_join_lanes = jax.jit(jax.vmap(join_trunk))


def join_refusal(trunk: dict | None, cfg: TrainConfig, lanes, joining, eps, *, seeds,
                  sizes, inputs) -> str | None:
    """Why the BC lanes (``joining``) of this family cannot continue from the shared trunk
    record ``trunk`` (None: they can)."""
    if trunk is None:
        return ("no adversarial trunk shared in this process (the adversarial family did not "
                "run before it with the fork, or --families / --no-fork left it out)")
    if jax.process_count() != 1:
        return f"{jax.process_count()} processes (the join is within one)"
    if len(joining) == len(lanes):
        return "no other lanes to train until the join"
    if any(eps[i] != 1.0 for i in joining):
        return "a bc lane of eps < 1 trains on its worst policies, not on all as pre-training"
    if list(trunk["seeds"]) != list(seeds):
        return f"the trunk ran seeds {trunk['seeds']}, this family {list(seeds)}"
    other = trunk["config"]
    if dataclasses.replace(cfg, method=other.method) != other:
        mine, theirs = cfg.to_dotted(), other.to_dotted()
        diff = [k for k in mine if k != "method" and mine[k] != theirs[k]]
        return f"the trunk's config differs in {', '.join(diff)}"
    if trunk["at_step"] != cfg.adversarial.pretrain_steps:
        return (f"the trunk pre-trained {trunk['at_step']} steps, this config's "
                f"pretrain_steps is {cfg.adversarial.pretrain_steps}")
    if trunk["fields"] is None:
        return f"the trunk's training ended before step {trunk['at_step']}"
    if sizes["steps"] < trunk["at_step"]:
        return f"this family trains {sizes['steps']} steps, fewer than {trunk['at_step']}"
    theirs = trunk["sizes"]
    ours = {k: sizes[k] for k in theirs}
    if theirs != ours:
        return f"the trunk was evaluated with {theirs}, this family with {ours}"
    if any(a is not b for a, b in zip(trunk["inputs"], inputs, strict=True)):
        return "the trunk trained or was evaluated on other data or policies"
    return None


class Join:
    """A likelihood family's lanes while its BC lanes wait for the adversarial trunk's
    pre-training (issue 40, item 3; ``train_family``'s ``share``): the other lanes train alone
    until the trunk's step ``at``, the BC lanes' evaluations until then are the trunk lane's
    of their seed; at ``at`` each BC lane joins as its fresh init continued from its seed's
    trunk lane (``join_trunk``) and every lane trains on."""

    def __init__(self, trunk: dict, starts, lanes, joining: list):
        self.trunk, self.at = trunk, trunk["at_step"]
        self.now = [i for i in range(len(lanes)) if i not in joining]
        self.joining = joining
        self.of = np.asarray([trunk["seeds"].index(lanes[i][1]) for i in joining])
        self.starts = take_lanes(starts, joining)
        self.order = np.argsort(self.now + joining)  # [now..., joining...] -> lane order

    def _merge(self, now: list, theirs: list) -> list:
        both = [*now, *(theirs[j] for j in self.of)]
        return [both[k] for k in self.order]

    def rows(self, step, evals, values, returns, lengths, selects, m, n_sel):
        """The evaluation at ``step`` of the lanes training now, with the trunk's at that
        step for the BC lanes (their selected count their eps's, ``n_sel``)."""
        p = self.trunk["points"][step]
        out = [self._merge(list(x), p[k]) for x, k in (
            (evals, "evals"), (values, "values"), (returns, "returns"),
            (lengths, "lengths"), (selects, "selects"))]
        theirs = {k: np.asarray(v)[self.of] for k, v in p["m"].items()}
        theirs["n_selected"] = np.asarray(n_sel)[self.joining]
        m = {k: np.concatenate([np.asarray(m[k]), theirs[k]])[self.order] for k in theirs}
        return (*out, m)

    def grow(self, states, m, mesh):
        joined = _join_lanes(take_lanes(self.trunk["fields"], self.of), self.starts)
        both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]),
                                      _on_one_device(states), joined)
        return jax.block_until_ready(shard_lanes(take_lanes(both, self.order), mesh))

    def finite_before(self, m):
        return np.concatenate([np.asarray(m["finite"]),
                               self.trunk["finite_before"][self.of]])[self.order]


def train_chunk(states, data, n, cfg, compiled, pending: Trunk | Join | None, data_host,
                 mesh_all):
    """n steps of the lanes; with a pending fork or join, the steps of the lanes training now
    up to its step, then the fork / join and the rest.
    -> (states, metrics [lanes], data, pending: None once done)"""
    if pending is None:
        return (*train_lanes(states, data, n, cfg, compiled), data, None)
    k = min(n, pending.at - int(states.step[0]))
    m = None
    if k > 0:
        states, m = train_lanes(states, data, k, cfg, compiled)
    if k == n:
        return states, m, data, pending
    states = pending.grow(states, m, mesh_all)
    data = replicate(data_host, mesh_all)
    states, m2 = train_lanes(states, data, n - k, cfg, compiled)
    if m is not None:
        m2 = {**m2, "finite": jnp.logical_and(m2["finite"],
                                              jnp.asarray(pending.finite_before(m)))}
    return states, m2, data, None
