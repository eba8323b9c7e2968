"""Resumable, time-limited training of one zoo learner (SAC or PPO) over vmapped seeds.

Training runs as jitted *snapshot intervals*: ``iterations_per_snapshot`` iterations of every
seed (one compiled program, seeds vmapped), after which each seed's policy is kept as a
snapshot with its training return and env steps. Python only moves between intervals: the
progress bar, the NaN check, checkpoints and the time limit.

A run lives in a work directory (one per learner)::

    WORK/<learner>/ckpt/<n>/{state,snapshots,meta}   orbax; n = snapshot intervals done

``state`` is the whole vmapped training state (replay buffer, env states, optimisers, keys),
``snapshots`` the policies so far, ``meta`` (JSON) the config, the training log and the leaf
specs, so a checkpoint describes itself. A run restarted with the same settings continues from
the latest checkpoint and ends with bit-identical snapshots (same device and software); a
larger ``env_steps`` extends a finished run. ``--time-limit`` stops after a checkpoint.

A run can also start from an imported export (``zoo_store``): a full one continues exactly;
a light one (no replay buffer / env states: a SAC buffer of 10^6 rows does not fit) starts
fresh envs and re-fills the buffer with ``warmup_steps`` steps of the current policies, so the
continued run is valid but not bit-identical (expect a short dip while the buffer is small).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from rl2s_jax.policy.policy import Params
from rl2s_jax.policy.ppo import PPOConfig, make_ppo
from rl2s_jax.policy.sac import SACConfig, make_sac
from rl2s_jax.zoo.store import (
    FORMAT,
    ZooCheckpointer,
    check_spec,
    flatten,
    strong,
    tree_spec,
    unflatten,
)

LEARNERS = ("sac", "ppo")


@dataclasses.dataclass(frozen=True)
class LearnerPlan:
    """How one learner grows a zoo: its config, env steps per seed and snapshots per seed
    (taken evenly along training, plus the initial random policy)."""

    config: SACConfig | PPOConfig
    env_steps: int
    snapshots: int = 40


class Learner(NamedTuple):
    """One seed's learner as pure functions (vmapped over seeds by ``train_learner``).

    transient: top-level state fields a light export leaves out (rebuilt by ``refill``);
    log_keys: metrics averaged over each interval into the training log.
    """

    name: str
    config: Any
    steps_per_iteration: int
    init: Callable[[jax.Array], Any]
    train: Callable[[Any, int], tuple[Any, dict]]
    policy: Callable[[Any], Params]
    refill: Callable[[Any], Any]
    transient: tuple[str, ...]
    log_keys: tuple[str, ...]


def make_learner(name: str, env, config: SACConfig | PPOConfig) -> Learner:
    """The learner ``name`` ('sac' | 'ppo') for an unwrapped brax env."""
    if name == "sac":
        if not isinstance(config, SACConfig):
            raise ValueError(f"config: expected a SACConfig for sac, got {type(config).__name__}")
        sac = make_sac(env, config)
        return Learner("sac", config, config.n_envs, lambda k: sac.init(k), sac.train,
                       lambda s: s.actor, sac.refill,
                       ("buffer", "env_state", "t", "episode_return"),
                       ("q_loss", "actor_loss", "alpha", "entropy", "q_mean"))
    if name == "ppo":
        if not isinstance(config, PPOConfig):
            raise ValueError(f"config: expected a PPOConfig for ppo, got {type(config).__name__}")
        ppo = make_ppo(env, config)
        return Learner("ppo", config, config.env_steps_per_iteration, ppo.init, ppo.train,
                       ppo.policy, ppo.refill, ("env_state", "episode_return"),
                       ("pg_loss", "v_loss", "entropy", "approx_kl"))
    raise ValueError(f"algo: expected one of {', '.join(LEARNERS)}, got {name!r}")


@dataclasses.dataclass
class LearnerRun:
    """The outcome of ``train_learner``. snapshots: {'params': [S, n + 1, ...] policies,
    'training_return' / 'reward_per_step': [S, n + 1], 'env_steps': [n + 1]} (index 0: the
    initial policy); meta: config, log rows, timings; complete: the env-step budget is done;
    intervals: snapshot intervals trained in this call."""

    name: str
    snapshots: dict
    meta: dict
    complete: bool
    intervals: int = 0


def _run_config(task: str, learner: Learner, seeds: int, seed: int) -> dict:
    return json.loads(json.dumps({"task": task, "learner": learner.name, "seeds": seeds,
                                  "seed": seed, "config": dataclasses.asdict(learner.config)}))


def _config_diff(saved: dict, now: dict) -> dict:
    flat = lambda d: {**{k: v for k, v in d.items() if k != "config"},
                      **{f"{k}": v for k, v in d["config"].items()}}
    a, b = flat(saved), flat(now)
    return {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


def _interval_fn(learner: Learner, ips: int):
    """jit(vmap over seeds) of: ips iterations -> (state, policy, interval summary)."""
    def one(state):
        state, m = learner.train(state, ips)
        ep = m["episodes"].sum()
        summary = {k: jnp.mean(m[k]) for k in learner.log_keys}
        summary["training_return"] = jnp.where(
            ep > 0, m["return_sum"].sum() / jnp.maximum(ep, 1), jnp.nan)
        summary["episodes"] = ep
        summary["reward_per_step"] = jnp.mean(m["reward_mean"])
        return strong(state), learner.policy(state), summary

    return jax.jit(jax.vmap(one))


def _finite(tree) -> bool:
    return all(bool(np.all(np.isfinite(x))) for x in jax.tree_util.tree_leaves(tree)
               if np.issubdtype(np.asarray(x).dtype, np.floating))


@dataclasses.dataclass
class _Progress:
    """A run between intervals: the device state and, per snapshot so far, the policies
    [S, ...], training returns and rewards per step [S] (host), plus the log rows."""

    state: Any
    params: list
    returns: list
    rewards: list
    log_rows: list
    ips: int
    train_s: float

    @property
    def done(self) -> int:
        return len(self.params) - 1

    def snapshots(self, interval_steps: int) -> dict:
        return {"params": jax.tree_util.tree_map(lambda *xs: np.stack(xs, 1), *self.params),
                "training_return": np.stack(self.returns, 1).astype(np.float32),
                "reward_per_step": np.stack(self.rewards, 1).astype(np.float32),
                "env_steps": np.arange(len(self.params), dtype=np.int64) * interval_steps}

    def meta(self, learner: Learner, run_cfg: dict, env_steps: int) -> dict:
        return {"format": FORMAT, "run": run_cfg, "iterations_per_snapshot": self.ips,
                "steps_per_iteration": learner.steps_per_iteration,
                "snapshots_done": self.done, "env_steps_target": env_steps,
                "train_seconds": round(self.train_s, 2), "log": self.log_rows,
                "transient": list(learner.transient)}

    def save(self, ckpt: ZooCheckpointer, learner: Learner, run_cfg: dict,
             env_steps: int) -> None:
        snaps = self.snapshots(1)
        del snaps["env_steps"]
        meta = self.meta(learner, run_cfg, env_steps)
        meta.update(state_spec=tree_spec(self.state), snapshot_spec=tree_spec(snaps))
        ckpt.save(self.done, flatten(self.state), flatten(snaps), meta)


def _fresh(learner: Learner, keys, env_steps: int, snapshots: int) -> _Progress:
    t0 = time.time()

    def init(keys):
        state = jax.vmap(learner.init)(keys)
        return strong(state), jax.vmap(learner.policy)(state)

    state, first = jax.jit(init)(keys)
    first = jax.device_get(first)
    nan = np.full(keys.shape[0], np.nan, np.float32)
    ips = max(1, round(env_steps / snapshots / learner.steps_per_iteration))
    return _Progress(state, [first], [nan], [nan], [], ips, time.time() - t0)


def _resume(learner: Learner, source: dict, where: str, keys, run_cfg: dict,
            log) -> _Progress:
    """The progress saved in ``source`` (a checkpoint or an imported run), checked against
    this learner's settings; a light import gets fresh envs and a re-filled buffer."""
    meta = source["meta"]
    if meta.get("format") != FORMAT:
        raise ValueError(f"work: format {meta.get('format')!r} in {where}, expected {FORMAT}")
    diff = _config_diff(meta["run"], run_cfg)
    if diff:
        raise ValueError(f"config: the run in {where} was started with other settings (saved "
                         f"vs now: {diff}); use another --work directory or the same settings")
    v_init = jax.vmap(learner.init)
    state_shape = jax.eval_shape(v_init, keys)
    check_spec(meta["state_spec"], tree_spec(state_shape), "state", where)
    if meta.get("export_exact", True):
        state = unflatten(state_shape, source["state"], "state")
    else:  # light export: fresh transient fields, then refilled with the current policies
        fresh = flatten(jax.jit(v_init)(keys))
        state = unflatten(state_shape, {k: source["state"].get(k, v) for k, v in fresh.items()},
                          "state")
        state = jax.jit(jax.vmap(learner.refill))(state)
        log(f"[zoo] {learner.name}: imported without replay buffers/env states; re-filled them "
            "with the current policies (the continued run is not bit-identical)")
    n1, seeds = meta["snapshots_done"] + 1, keys.shape[0]
    policy_shape = jax.eval_shape(jax.vmap(learner.policy), state_shape)
    template = {"params": jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct((seeds, n1) + x.shape[1:], x.dtype), policy_shape)}
    for k in ("training_return", "reward_per_step"):
        template[k] = jax.ShapeDtypeStruct((seeds, n1), np.float32)
    snaps = unflatten(template, source["snapshots"], "snapshots")
    ips = int(meta["iterations_per_snapshot"])
    log(f"[zoo] {learner.name}: resumed from {where} at {n1 - 1} snapshot intervals "
        f"({(n1 - 1) * ips * learner.steps_per_iteration:,} env steps per seed)")
    return _Progress(
        strong(jax.device_put(state)),
        [jax.tree_util.tree_map(lambda x, i=i: x[:, i], snaps["params"]) for i in range(n1)],
        [snaps["training_return"][:, i] for i in range(n1)],
        [snaps["reward_per_step"][:, i] for i in range(n1)],
        list(meta["log"]), ips, float(meta["train_seconds"]))


def train_learner(learner: Learner, *, task: str, seeds: int, seed: int, env_steps: int,
                  snapshots: int, work_dir: str, deadline: float | None = None,
                  imported: dict | None = None, checkpoint_every_s: float = 120.0,
                  min_intervals: int = 1, progress: bool = True, log=print) -> LearnerRun:
    """Train ``seeds`` seeds of ``learner`` to ``env_steps`` env steps each, resuming from the
    latest checkpoint under ``work_dir`` (or, if there is none, from ``imported``: one run of
    ``read_export``). Snapshots every ``env_steps / snapshots`` env steps (rounded to whole
    iterations, fixed when the run starts). Checkpoints every ``checkpoint_every_s`` seconds
    and at the end; once the next interval would end past ``deadline`` (``time.time()``
    seconds) it stops after a checkpoint, but not before ``min_intervals`` intervals ran.
    Raises FloatingPointError (the last good state checkpointed) on a non-finite loss/policy.
    """
    if seeds < 1 or env_steps < 1 or snapshots < 1:
        raise ValueError(f"seeds, env_steps, snapshots: expected >= 1, got {seeds}, "
                         f"{env_steps}, {snapshots}")
    run_cfg = _run_config(task, learner, seeds, seed)
    key = jax.random.fold_in(jax.random.PRNGKey(seed), LEARNERS.index(learner.name))
    keys = jax.random.split(key, seeds)
    ckpt = ZooCheckpointer(os.path.join(work_dir, learner.name, "ckpt"))
    try:
        if ckpt.latest() is not None:
            run = _resume(learner, ckpt.restore(), ckpt.directory, keys, run_cfg, log)
        elif imported is not None:
            run = _resume(learner, imported, "the imported file", keys, run_cfg, log)
            run.save(ckpt, learner, run_cfg, env_steps)
        else:
            run = _fresh(learner, keys, env_steps, snapshots)
        interval_steps = run.ips * learner.steps_per_iteration
        target = math.ceil(env_steps / interval_steps)
        if run.done >= target:
            log(f"[zoo] {learner.name}: {run.done} snapshot intervals done (budget "
                f"{env_steps:,} env steps per seed)")
            return LearnerRun(learner.name, run.snapshots(interval_steps),
                              run.meta(learner, run_cfg, env_steps), True)
        log(f"[zoo] {task} {learner.name} x {seeds} seeds: {target * interval_steps:,} env "
            f"steps each, a snapshot every {interval_steps:,} ({run.ips} iterations of "
            f"{learner.steps_per_iteration:,})")
        ran = _loop(learner, run, target, interval_steps, ckpt, run_cfg, env_steps, deadline,
                    checkpoint_every_s, min_intervals, progress,
                    f"{task} {learner.name} x{seeds}")
        stopped = run.done < target
        if stopped:
            log(f"[zoo] {learner.name}: time limit; stopped after {run.done}/{target} snapshot "
                f"intervals ({run.done * interval_steps:,} env steps per seed), checkpoint in "
                f"{ckpt.directory}; run the same command to continue")
        else:
            log(f"[zoo] {learner.name}: trained {target * interval_steps:,} env steps per seed "
                f"in {run.train_s:.0f}s of training time (all calls); last training returns per"
                f" seed {np.round(run.returns[-1], 1).tolist()}")
        return LearnerRun(learner.name, run.snapshots(interval_steps),
                          run.meta(learner, run_cfg, env_steps), not stopped, ran)
    finally:
        ckpt.close()


def _loop(learner, run: _Progress, target, interval_steps, ckpt, run_cfg, env_steps,
          deadline, checkpoint_every_s, min_intervals, progress, desc) -> int:
    """Run snapshot intervals until ``target`` or the deadline (``train_learner``).
    -> the number of intervals run."""

    interval = _interval_fn(learner, run.ips)
    seeds = len(run.returns[0])
    last_save, saved, ran, est = time.time(), run.done, 0, 0.0
    past = lambda: deadline is not None and time.time() + est > deadline
    with tqdm(total=target * interval_steps, initial=run.done * interval_steps, unit="step",
              unit_scale=True, desc=desc, disable=not progress, dynamic_ncols=True) as bar:
        while run.done < target and not (ran >= min_intervals and past()):
            t0 = time.time()
            state, policy, summary = interval(run.state)
            policy, summary = jax.device_get((policy, summary))
            est = time.time() - t0
            losses = {k: summary[k] for k in learner.log_keys}
            if not (_finite(losses) and _finite(policy)):
                run.save(ckpt, learner, run_cfg, env_steps)
                bad = [k for k, v in {**losses, "policy": policy}.items() if not _finite(v)]
                raise FloatingPointError(
                    f"{learner.name} training diverged in snapshot interval {run.done + 1} "
                    f"(non-finite {', '.join(bad)}); the last good state is checkpointed in "
                    f"{ckpt.directory}")
            run.state, run.train_s, ran = state, run.train_s + est, ran + 1
            run.params.append(policy)
            run.returns.append(np.asarray(summary["training_return"], np.float32))
            run.rewards.append(np.asarray(summary["reward_per_step"], np.float32))
            for s in range(seeds):
                row = {"learner": learner.name, "seed": s, "snapshot": run.done,
                       "env_steps": run.done * interval_steps, "seconds": round(est, 3)}
                row.update({k: _num(v[s]) for k, v in summary.items()})
                run.log_rows.append(row)
            bar.update(interval_steps)
            bar.set_postfix(_postfix(run.returns, deadline), refresh=False)
            if run.done == target or past() or time.time() - last_save >= checkpoint_every_s:
                run.save(ckpt, learner, run_cfg, env_steps)
                last_save, saved = time.time(), run.done
    if saved != run.done:
        run.save(ckpt, learner, run_cfg, env_steps)
    return ran


def _postfix(returns: list[np.ndarray], deadline: float | None) -> dict:
    """Progress-bar fields: mean training return of the last interval over seeds, the best
    seed's return so far, seconds left before the time limit."""
    last = returns[-1][np.isfinite(returns[-1])]
    seen = np.concatenate(returns)
    seen = seen[np.isfinite(seen)]
    post = {"ret": f"{last.mean():.1f}" if last.size else "-",
            "best": f"{seen.max():.1f}" if seen.size else "-"}
    if deadline is not None:
        post["left"] = f"{max(0.0, deadline - time.time()):.0f}s"
    return post


def _num(x):
    x = float(x)
    return None if not math.isfinite(x) else x


__all__ = ["LEARNERS", "Learner", "LearnerPlan", "LearnerRun", "make_learner", "train_learner"]
