"""A learned termination hazard h(s, a) = P(the episode terminates at the next step | s, a).

Why: a learned simulator's states rarely cross a task's termination boundary the way real ones
do. On Ant the weak policies' real episodes end when the torso jumps above z = 1 (259 of 355
logged terminations) or drops below 0.2; the dynamics model's mean under-predicts the jump, so
simulated weak ants never end their episodes and are overvalued 2-3x (RESULTS@bf0c7b2: "Many
episodes on Ant and Hopper"). A classifier of the logged ``done`` flags on (s, a) gives each
simulated step a calibrated chance to end, learned from where real episodes ended, instead of
asking the model's predicted state to cross the exact boundary.

The classifier is a ReLU MLP of the normalised (s, a) (the dynamics model's inputs,
``dynamics.markov_inputs``) to one logit, trained by Adam on the binary cross-entropy of
uniformly drawn rows (uniform rows keep the probability calibrated; terminations are rare).
Rollouts (``simulate.advance_values``) end an episode when a uniform draw falls below h
(``termination="hazard"``), or when that or the task's rule fires (``"both"``); ``"rule"`` is the
task's ``done_fn`` alone on the state the rollout goes on from.

``"predictive"`` needs no classifier: the rule also fires when it holds for one draw from the
model's own one-step predictive distribution (noise scale 1), while the rollout goes on from
the state it would anyway (with ``sim_noise`` 0, the mean). A mean rollout then keeps the
chance of ending that the model's one-step uncertainty gives, without the drift that sampling
every step adds up to (sampled rollouts ended strong Ants far too early: RESULTS).
A window K > 1 smooths the target: the classifier learns q(s, a) = P(the episode ends within
the next K steps), and a step ends with h = 1 - (1 - q)^(1/K), the constant per-step hazard
that gives q over K steps (``window_labels``, ``hazard_prob``). Summed over real rows h still
counts the terminations where q is small, while a model whose states only come near the
states before an end (not onto the boundary itself) still gets a chance of ending.
Shapes: N rows, o = obs size, a = action size.
"""
from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import optax

from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.policy.policy import init_mlp

TERMINATIONS = ("rule", "hazard", "both", "predictive")
LEARNED = ("hazard", "both")  # the terminations that need a fitted classifier
HAZARD_LR = 1e-3
HAZARD_BATCH = 1024


def init_hazard(key: jax.Array, obs_size: int, action_size: int,
                hidden: Sequence[int]) -> dict:
    """{"layers": MLP [o + a, *hidden, 1]}, its last layer small (logit ~ 0 at the start)."""
    return {"layers": init_mlp(key, [obs_size + action_size, *hidden, 1], last_scale=0.01)}


def hazard_logit(params: dict, norm: Normalizer, obs: jax.Array, action: jax.Array
                 ) -> jax.Array:
    """The termination logit at (s, a). obs [..., o], action [..., a] -> [...]"""
    return dyn.relu_mlp(params["layers"], dyn.markov_inputs(norm, obs, action))[..., 0]


def hazard_prob(params: dict, norm: Normalizer, obs: jax.Array, action: jax.Array,
                window: int = 1) -> jax.Array:
    """The per-step hazard h(s, a) in [0, 1]: the classifier's probability for window 1, else
    1 - (1 - q)^(1/window) of its q = P(end within window steps). [..., o], [..., a] -> [...]"""
    logit = hazard_logit(params, norm, obs, action)
    if window == 1:
        return jax.nn.sigmoid(logit)
    return -jnp.expm1(jax.nn.log_sigmoid(-logit) / window)


def window_labels(done: jax.Array, steps_left: jax.Array, window: int) -> jax.Array:
    """[N] float32: 1 where the row's episode ends by termination within ``window`` steps
    (this row included). done [N]: 1 on terminal rows; steps_left [N]: rows of the same episode
    that follow (``train.episode_steps_left``). Window 1 gives ``done`` itself."""
    if window == 1:
        return done.astype(jnp.float32)
    last = jnp.arange(done.shape[0]) + steps_left
    return ((steps_left < window) & (done[last] > 0.5)).astype(jnp.float32)


def bce(logit: jax.Array, done: jax.Array) -> jax.Array:
    """Mean binary cross-entropy of logits [N] against 0/1 labels [N] (stable form). -> []"""
    done = done.astype(jnp.float32)
    return jnp.mean(jnp.maximum(logit, 0.0) - logit * done + jnp.log1p(jnp.exp(-jnp.abs(logit))))


def fit_hazard(key: jax.Array, params: dict, norm: Normalizer, obs: jax.Array,
               action: jax.Array, done: jax.Array, *, steps: int,
               batch_size: int = HAZARD_BATCH, lr: float = HAZARD_LR
               ) -> tuple[dict, jax.Array]:
    """``steps`` Adam updates of the classifier on batches of rows drawn uniformly from obs
    [N, o], action [N, a], done [N] (1: the row's next state is terminal). Pure; one
    ``lax.scan``. -> (params, batch loss per step [steps])"""
    tx = optax.adam(lr)
    n = obs.shape[0]

    def loss_fn(p, rows):
        return bce(hazard_logit(p, norm, obs[rows], action[rows]), done[rows])

    def update(carry, k):
        p, opt = carry
        rows = jax.random.randint(k, (batch_size,), 0, n)
        loss, grads = jax.value_and_grad(loss_fn)(p, rows)
        upd, opt = tx.update(grads, opt, p)
        return (optax.apply_updates(p, upd), opt), loss

    (params, _), losses = jax.lax.scan(update, (params, tx.init(params)),
                                       jax.random.split(key, steps))
    return params, losses
