"""A learned reward head r(s, a, s'), for data of a system that no registered task describes.

Why: a learned simulator predicts next states only; the reward of a simulated step comes from
the task's ``reward_fn``. Data of a system nobody registered (``meta.task`` null: a Minari
import, a real robot's logs) still holds every transition's reward, so the reward can be
learned as the termination is (``termination.py``): a regression of the logged rewards on the
transition, fitted once in ``train.step.init``.

The head is a ReLU MLP of the normalised (s, a) (the dynamics model's inputs,
``dynamics.markov_inputs``: position dims left out) and the normalised change s' - s
(``Normalizer.norm_delta``: a forward-velocity reward needs the position's change), to the
standardised reward; the reward's mean and std over the training rows are parameters beside the
layers (``mean``, ``std``), so a checkpoint holds everything the prediction needs. Trained by
Adam on the squared error of uniformly drawn rows. Shapes: N rows, o = obs size, a = action
size.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import optax

from rl2s_jax.envs.tasks import TASKS, Task, get_task
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.termination import LEARNED
from rl2s_jax.policy.policy import init_mlp

REWARDS = ("task", "learned")  # where a simulated step's reward comes from
REWARD_LR = 1e-3
REWARD_BATCH = 1024


def init_reward(key: jax.Array, obs_size: int, action_size: int,
                hidden: Sequence[int]) -> dict:
    """{"layers": MLP [2 o + a, *hidden, 1], "mean": [], "std": []} (the reward's scale; 0, 1
    until ``fit_reward`` sets them)."""
    return {"layers": init_mlp(key, [2 * obs_size + action_size, *hidden, 1]),
            "mean": jnp.zeros((), jnp.float32), "std": jnp.ones((), jnp.float32)}


def reward_inputs(norm: Normalizer, obs: jax.Array, action: jax.Array, next_obs: jax.Array
                  ) -> jax.Array:
    """[..., o], [..., a], [..., o] -> [..., 2 o + a]: normalised (s, a) and s' - s."""
    return jnp.concatenate([dyn.markov_inputs(norm, obs, action),
                            norm.norm_delta(obs, next_obs)], -1)


def _standard(params: dict, norm: Normalizer, obs, action, next_obs) -> jax.Array:
    return dyn.relu_mlp(params["layers"], reward_inputs(norm, obs, action, next_obs))[..., 0]


def predict_reward(params: dict, norm: Normalizer, obs: jax.Array, action: jax.Array,
                   next_obs: jax.Array) -> jax.Array:
    """The learned r(s, a, s') in the data's units: a ``reward_fn``. -> [...]"""
    return params["mean"] + params["std"] * _standard(params, norm, obs, action, next_obs)


def never_done(next_obs: jax.Array) -> jax.Array:
    """A ``done_fn`` that never fires (no rule: episodes end by the learned hazard)."""
    return jnp.zeros(next_obs.shape[:-1], bool)


def fit_reward(key: jax.Array, params: dict, norm: Normalizer, obs: jax.Array,
               action: jax.Array, next_obs: jax.Array, reward: jax.Array, *, steps: int,
               batch_size: int = REWARD_BATCH, lr: float = REWARD_LR
               ) -> tuple[dict, jax.Array]:
    """The reward's mean and std over the rows, then ``steps`` Adam updates of the layers on
    batches drawn uniformly from obs [N, o], action [N, a], next_obs [N, o], reward [N] (mean
    squared error of the standardised reward). Pure; one ``lax.scan``.
    -> (params, batch loss per step [steps], in standardised units)"""
    tx = optax.adam(lr)
    n = obs.shape[0]
    mean, std = jnp.mean(reward), jnp.maximum(jnp.std(reward), 1e-6)
    target = (reward - mean) / std

    def loss_fn(layers, rows):
        p = {"layers": layers, "mean": mean, "std": std}
        pred = _standard(p, norm, obs[rows], action[rows], next_obs[rows])
        return jnp.mean((pred - target[rows]) ** 2)

    def update(carry, k):
        layers, opt = carry
        rows = jax.random.randint(k, (batch_size,), 0, n)
        loss, grads = jax.value_and_grad(loss_fn)(layers, rows)
        upd, opt = tx.update(grads, opt, layers)
        return (optax.apply_updates(layers, upd), opt), loss

    (layers, _), losses = jax.lax.scan(update, (params["layers"], tx.init(params["layers"])),
                                       jax.random.split(key, steps))
    return {"layers": layers, "mean": mean.astype(jnp.float32),
            "std": std.astype(jnp.float32)}, losses


def simulator_task(sim) -> Task:
    """The ``Task`` (reward_fn, done_fn, sizes) that a ``Simulator``'s rollouts step with
    (``Simulator.task_fns``): the registered task's, with the learned reward in place of its
    reward_fn where the simulator has one (``sim.reward``); for a task that is not registered
    (data of no task), the learned reward and a done_fn that never fires, its episodes ending
    by the learned hazard (``termination`` 'hazard' or 'both'). ValueError naming what is
    missing otherwise."""
    # a plain closure (hashable, unlike a bound method of the Simulator's arrays)
    learned = (None if sim.reward is None else
               lambda obs, action, next_obs: predict_reward(sim.reward, sim.norm, obs, action,
                                                            next_obs))
    if sim.task in TASKS:
        task = get_task(sim.task)
        return task if learned is None else dataclasses.replace(task, reward_fn=learned)
    name = "no task" if sim.task is None else f"task {sim.task!r} (not registered here)"
    if learned is None:
        raise ValueError(f"task: this simulator models {name} and has no learned reward, so "
                         f"nothing gives its rollouts a reward; register the task "
                         f"(rl2s_jax.envs.tasks.register) or train with reward='learned'")
    if sim.termination not in LEARNED:
        raise ValueError(f"termination: {sim.termination!r} ends episodes by the task's "
                         f"done_fn, and this simulator models {name}; register the task or "
                         f"train with termination='hazard'")
    return Task(name=sim.task or "unregistered", obs_size=int(sim.norm.obs_mean.shape[-1]),
                action_size=int(sim.norm.act_mean.shape[-1]),
                episode_length=int(sim.episode_length), make_env=_no_real_env,
                reward_fn=learned, done_fn=never_done, dt=1.0)


def _no_real_env(**_):
    raise NotImplementedError("this simulator models a system that no registered task "
                              "describes, so there is no real env to run: learn and evaluate "
                              "from its data")
