"""Roll policies inside a simulator and measure their values.

A simulator here is any ``dynamics(obs [..., o], action [..., a], key) -> next_obs [..., o]``
(the learned generator, or a task's true dynamics in tests); rewards and terminations come from
the task's ``reward_fn(obs, action, next_obs)`` and ``done_fn(next_obs)``.

Value rollouts run P policies x n episodes as one batch. They can be advanced piecewise
(``advance_values`` a few steps at a time), which is how ``train_step`` spreads one value
measurement over K calls instead of spiking every K-th call.
"""
from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rl2s_jax.envs.tasks import Task
from rl2s_jax.model import dynamics as dyn
from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.generator import sample_next
from rl2s_jax.model.history import (
    History,
    empty_history,
    member_step_dist,
    push_history,
    step_inputs,
)
from rl2s_jax.model.reward import predict_reward, simulator_task
from rl2s_jax.model.termination import TERMINATIONS, hazard_prob
from rl2s_jax.policy.policy import Params, sample_action

Dynamics = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


@struct.dataclass
class Simulator:
    """A learned simulator p_phi: an ensemble of family members, its normaliser, the task it
    models (docs/SIMULATOR.md).

    gen: member parameters stacked [E, ...] (``dynamics.init_ensemble``); a bare list of MLP
      layers (one generator, ``models.init_generator``) is taken as E = 1.
    rank: [E] int32 members by held-out NLL (0 = best), or None (all equal, member 0 first);
      the ``n_elites`` best are the elites (None: every member).
    member_mode: how a step picks its Gaussian: "random" (an elite drawn per sample), "mean"
      (the elites' average), "fixed" (the best member). ``uncertainty``: the disagreement
      measure ("std" or "max_pairwise", ``dynamics.disagreement``).

    hazard: a learned termination classifier (``termination.init_hazard``) or None, of
    P(end within ``hazard_window`` steps);
    termination: what ends a simulated episode, "rule" (the task's done_fn on the simulated
    next state), "hazard" (a draw below h(s, a)), "both", or "predictive" (the rule, or the
    rule on one noise-scale-1 draw of the next state; ``terminations``).

    reward: a learned reward head r(s, a, s') (``reward.init_reward``) or None.
    ``dynamics`` is the ``Dynamics`` function the rollouts here take; ``task`` names the
    registered task whose reward_fn / done_fn apply (None for data without a task);
    ``task_fns()`` gives the reward_fn / done_fn every rollout steps with (the learned reward
    where there is one, the learned termination where no task is registered).
    ``uncertainty_fn(obs, action)`` and ``step(obs, action, key) -> (next_obs, u)`` give the
    ensemble's disagreement at every step (0 for one member).

    History inputs (``obs_history``, ``action_history``, ``time_inputs``, with t scaled by
    ``episode_length``): the members also see the episode's past, so every method here then
    takes ``hist`` (``rl2s_jax.model.history.History``; ``new_history`` at an episode start,
    ``push_history`` after each step) and ``dynamics`` is ``(obs, action, key, hist)``. The
    rollouts of this module carry it for any Simulator (``new_history=sim.new_history``).

    base: a deterministic dynamics ``base(obs [..., o], action [..., a], hist) -> [..., o]``
    that the members' delta is added to (``anchor``): s' = base(s, a) + delta. None (the
    default): the identity, s' = s + delta. A hybrid (``rl2s_jax.physics.hybrid``) sets it to
    the calibrated physics, its members having learned the physics' residual; it is not saved
    in a checkpoint (the checkpoint's meta says how to rebuild it).
    """

    gen: Params
    norm: Normalizer
    rank: jax.Array | None = None
    hazard: Params | None = None
    reward: Params | None = None
    task: str | None = struct.field(pytree_node=False, default=None)
    obs_clip: float = struct.field(pytree_node=False, default=10.0)
    noise_scale: float = struct.field(pytree_node=False, default=1.0)
    n_elites: int | None = struct.field(pytree_node=False, default=None)
    member_mode: str = struct.field(pytree_node=False, default="random")
    uncertainty: str = struct.field(pytree_node=False, default="std")
    termination: str = struct.field(pytree_node=False, default="rule")
    hazard_window: int = struct.field(pytree_node=False, default=1)
    obs_history: int = struct.field(pytree_node=False, default=0)
    action_history: int = struct.field(pytree_node=False, default=0)
    time_inputs: tuple[str, ...] = struct.field(pytree_node=False, default=())
    episode_length: int = struct.field(pytree_node=False, default=1000)
    base: Callable | None = struct.field(pytree_node=False, default=None)

    def __post_init__(self):
        if isinstance(self.gen, list | tuple):  # one generator: an ensemble of one
            layers = [{k: jnp.asarray(v)[None] for k, v in layer.items()} for layer in self.gen]
            object.__setattr__(self, "gen", {"layers": layers})

    @property
    def n_members(self) -> int:
        return dyn.n_members(self.gen)

    @property
    def markov(self) -> bool:
        """True when the members see the current (s, a) only (no ``hist`` needed)."""
        return not (self.obs_history or self.action_history or self.time_inputs)

    def new_history(self, batch_shape: tuple[int, ...]) -> History | None:
        """The history of episodes starting now, batch_shape of them (None when Markov)."""
        if self.markov:
            return None
        return empty_history(tuple(batch_shape), self.norm.obs_mean.shape[-1],
                             self.norm.act_mean.shape[-1], obs_history=self.obs_history,
                             action_history=self.action_history,
                             time_inputs=self.time_inputs, episode_length=self.episode_length)

    def inputs(self, obs: jax.Array, action: jax.Array, hist: History | None = None
               ) -> jax.Array:
        """The members' inputs at (obs [..., o], action [..., a]) with this past."""
        if hist is None and not self.markov:
            raise ValueError(
                f"hist: this simulator's members see the episode's past (obs_history "
                f"{self.obs_history}, action_history {self.action_history}, time_inputs "
                f"{self.time_inputs}); pass hist= (Simulator.new_history at the episode start, "
                f"history.push_history after each step)")
        return step_inputs(self.norm, obs, action, hist)

    def member_dists(self, obs: jax.Array, action: jax.Array, hist: History | None = None
                     ) -> tuple[jax.Array, jax.Array]:
        """Every member's Gaussian over the normalised delta: (mean, log_std) [E, ..., o]."""
        x = self.inputs(obs, action, hist)
        if "enc" not in self.gen:
            return dyn.ensemble_dist(self.gen, x)
        return dyn.map_members(lambda p: member_step_dist(p, self.norm, obs, action, hist),
                               self.gen)

    def anchor(self, obs: jax.Array, action: jax.Array, hist: History | None = None
               ) -> jax.Array:
        """What the members' delta is added to: ``obs`` itself, or ``base(obs, action, hist)``
        where the simulator has a base dynamics (a hybrid). [..., o], [..., a] -> [..., o]"""
        return obs if self.base is None else self.base(obs, action, hist)

    def _moments(self, means, log_stds, key):
        return dyn.ensemble_moments(means, log_stds, key, rank=self.rank,
                                    n_elites=self.n_elites, mode=self.member_mode)

    def sample(self, obs: jax.Array, action: jax.Array, key: jax.Array,
               hist: History | None = None) -> jax.Array:
        """s' ~ p_phi(.|s, a) (member by member_mode) with the std times noise_scale, clipped
        to +-obs_clip data stds. [..., o], [..., a] -> [..., o]"""
        return self.step(obs, action, key, hist)[0]

    def step(self, obs: jax.Array, action: jax.Array, key: jax.Array,
             hist: History | None = None) -> tuple[jax.Array, jax.Array]:
        """One simulated step and the ensemble's disagreement at (obs, action), from one pass
        over the members. -> (next_obs [..., o], u [...])"""
        means, log_stds = self.member_dists(obs, action, hist)
        mean, log_std, k_noise = self._moments(means, log_stds, key)
        nxt = sample_next(self.norm, self.anchor(obs, action, hist), mean, log_std, k_noise,
                          self.obs_clip, self.noise_scale)
        return nxt, self._disagreement(means)

    def transition(self, obs: jax.Array, action: jax.Array, key: jax.Array,
                   hist: History | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Everything a consumer of one step needs, from one pass over the members (e.g. an
        uncertainty-penalised reward r - lambda * u for policy improvement):
        -> (mean next state [..., o] as ``mean``, a sample [..., o] as ``sample`` with this
        key, the elites' disagreement u [...] as ``disagreement``; 0 for one member)."""
        means, log_stds = self.member_dists(obs, action, hist)
        mean, log_std, k_noise = self._moments(means, log_stds, key)
        start = self.anchor(obs, action, hist)
        nxt = sample_next(self.norm, start, mean, log_std, k_noise, self.obs_clip,
                          self.noise_scale)
        return self.mean_of(start, means, log_stds), nxt, self._disagreement(means)

    def mean(self, obs: jax.Array, action: jax.Array, hist: History | None = None
             ) -> jax.Array:
        """The mean next state: of the best member ("fixed") or the elites' average. -> [..., o]"""
        return self.mean_of(self.anchor(obs, action, hist),
                            *self.member_dists(obs, action, hist))

    def mean_of(self, start: jax.Array, means: jax.Array, log_stds: jax.Array) -> jax.Array:
        """``mean`` from the members' Gaussians [E, ..., o] already computed, added to
        ``start`` [..., o]: the step's ``anchor`` (obs itself unless there is a base)."""
        mode = "fixed" if self.member_mode == "fixed" else "mean"
        avg, _, _ = dyn.ensemble_moments(means, log_stds, None, rank=self.rank,
                                         n_elites=self.n_elites, mode=mode)
        return self.norm.next_from_delta(start, avg)

    def log_prob(self, obs: jax.Array, action: jax.Array, next_obs: jax.Array,
                 hist: History | None = None) -> jax.Array:
        """log density of the normalised delta (next_obs - ``anchor``) under what ``sample``
        draws from (for "random": the uniform mixture of the elites). -> [...]"""
        means, log_stds = self.member_dists(obs, action, hist)
        y = self.norm.norm_delta(self.anchor(obs, action, hist), next_obs)
        return dyn.mixture_log_prob(means, log_stds, y, rank=self.rank, n_elites=self.n_elites,
                                    mode=self.member_mode)

    def predictive(self, obs: jax.Array, action: jax.Array, hist: History | None = None
                   ) -> tuple[jax.Array, jax.Array]:
        """Mean and std [..., o] of the normalised delta that ``sample`` draws (noise_scale 1;
        added to ``anchor``):
        for "random", the elite mixture's (std includes the spread of the elites' means)."""
        means, log_stds = self.member_dists(obs, action, hist)
        mode = "mean" if self.member_mode == "random" else self.member_mode
        mean, log_std, _ = dyn.ensemble_moments(means, log_stds, None, rank=self.rank,
                                                n_elites=self.n_elites, mode=mode)
        var = jnp.exp(2.0 * log_std)
        if self.member_mode == "random" and means.shape[0] > 1:
            elite = dyn.elite_mask(self.rank, self.n_elites, means.shape[0])
            w = (elite / elite.sum()).reshape((-1,) + (1,) * (means.ndim - 1))
            var = var + jnp.sum(w * (means - mean) ** 2, 0)
        return mean, jnp.sqrt(var)

    def _disagreement(self, means):
        return dyn.disagreement(means, rank=self.rank, n_elites=self.n_elites,
                                kind=self.uncertainty)

    def disagreement(self, obs: jax.Array, action: jax.Array, hist: History | None = None
                     ) -> jax.Array:
        """The elites' disagreement at (obs, action) in normalised delta units (0 for one
        member). [..., o], [..., a] -> [...]"""
        return self._disagreement(self.member_dists(obs, action, hist)[0])

    def uncertainty_fn(self, obs: jax.Array, action: jax.Array, hist: History | None = None
                       ) -> jax.Array:
        """``uncertainty_fn(obs, action) -> [...]``: the disagreement, for a penalised reward
        r - lambda * u (policy improvement) or to flag untrusted regions (diagnosis)."""
        return self.disagreement(obs, action, hist)

    def dynamics(self, obs: jax.Array, action: jax.Array, key: jax.Array,
                 hist: History | None = None) -> jax.Array:
        return self.sample(obs, action, key, hist)

    def hazard_prob(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        """The learned chance that the step from (obs, action) ends the episode.
        [..., o], [..., a] -> [...]"""
        if self.hazard is None:
            raise ValueError("hazard: this simulator has no learned termination (train with "
                             "termination='hazard' or 'both')")
        return hazard_prob(self.hazard, self.norm, obs, action, self.hazard_window)

    def terminations(self, done_fn: Callable | None) -> tuple[Callable | None, Callable | None]:
        """(done_fn, hazard_fn) for ``advance_values`` under this simulator's ``termination``:
        the task's rule ``done_fn`` unless "hazard"; the learned h(s, a) for "hazard" and
        "both"; for "predictive", 1 where ``done_fn`` holds for a draw of the next state at
        noise scale 1 (a Bernoulli of the model's own P(end))."""
        if self.termination not in TERMINATIONS:
            raise ValueError(f"termination: expected one of {', '.join(TERMINATIONS)}, got "
                             f"{self.termination!r}")
        if self.termination == "rule":
            return done_fn, None
        if self.termination == "predictive":
            if not self.markov:
                raise ValueError("termination: 'predictive' draws a next state from (obs, "
                                 "action) alone; a simulator with history inputs uses 'rule', "
                                 "'hazard' or 'both'")
            if done_fn is None:
                raise ValueError("termination: 'predictive' applies the task's done_fn to a "
                                 "draw of the next state; got done_fn=None")
            noisy = self.replace(noise_scale=1.0)
            return done_fn, lambda obs, action, key: (
                done_fn(noisy.sample(obs, action, key)) > 0.5).astype(jnp.float32)
        if self.hazard is None:
            raise ValueError(f"termination: {self.termination!r} needs a learned hazard, and "
                             f"this simulator has none (hazard=None)")
        learned = lambda obs, action, key: self.hazard_prob(obs, action)
        return (None if self.termination == "hazard" else done_fn), learned

    def predict_reward(self, obs: jax.Array, action: jax.Array, next_obs: jax.Array
                       ) -> jax.Array:
        """The learned reward of the step (obs, action) -> next_obs. -> [...]"""
        if self.reward is None:
            raise ValueError("reward: this simulator has no learned reward (train with "
                             "reward='learned')")
        return predict_reward(self.reward, self.norm, obs, action, next_obs)

    def task_fns(self) -> Task:
        """The ``Task`` (reward_fn, done_fn, sizes) that this simulator's rollouts step with:
        the one place every rollout takes them from (``reward.simulator_task``)."""
        return simulator_task(self)


@struct.dataclass
class ValueRollout:
    """P x n simulated episodes in progress.

    obs [P, n, o]; alive [P, n] (not yet terminated); ret [P, n] discounted return so far;
    length [P, n] steps survived; t [] steps taken; hist: the episodes' past [P, n, ...] for a
    simulator with history inputs (None: Markov dynamics).
    """

    obs: jax.Array
    alive: jax.Array
    ret: jax.Array
    length: jax.Array
    t: jax.Array
    hist: History | None = None


def start_pool(ds) -> jax.Array:
    """Real episode start states of a Dataset [S, o] (its rows with t == 0)."""
    pool = np.asarray(ds.obs)[np.asarray(ds.t) == 0]
    if pool.shape[0] == 0:
        raise ValueError("t: expected some episode start rows (t == 0) for the start states")
    return jnp.asarray(pool, jnp.float32)


def start_values(start_pool: jax.Array, n_policies: int, n_episodes: int, key: jax.Array,
                 new_history: Callable | None = None) -> ValueRollout:
    """Fresh episodes from start states drawn (with replacement) from start_pool [S, o].
    ``new_history(batch_shape)``: their empty past (``Simulator.new_history``; None: none)."""
    idx = jax.random.randint(key, (n_policies, n_episodes), 0, start_pool.shape[0])
    shape = (n_policies, n_episodes)
    return ValueRollout(obs=start_pool[idx], alive=jnp.ones(shape, bool),
                        ret=jnp.zeros(shape, jnp.float32), length=jnp.zeros(shape, jnp.int32),
                        t=jnp.zeros((), jnp.int32),
                        hist=None if new_history is None else new_history(shape))


def step_dynamics(dynamics: Dynamics, obs, action, key, hist: History | None
                  ) -> tuple[jax.Array, History | None]:
    """One step of ``dynamics`` and the past after it: ``dynamics(obs, action, key)`` without a
    history, ``dynamics(obs, action, key, hist)`` (a Simulator's) with one."""
    if hist is None:
        return dynamics(obs, action, key), None
    return dynamics(obs, action, key, hist), push_history(hist, obs, action)


def end_key(key: jax.Array, hazard_fn: Callable | None) -> tuple[jax.Array, jax.Array | None]:
    """(key for the dynamics, key for ``ends_episode``'s hazard draw): split only where there
    is a hazard, so that without one the dynamics' draws stay those of the rule-only code."""
    if hazard_fn is None:
        return key, None
    k_dyn, k_end = jax.random.split(key)
    return k_dyn, k_end


def ends_episode(obs: jax.Array, action: jax.Array, next_obs: jax.Array, key: jax.Array,
                 done_fn: Callable | None, hazard_fn: Callable | None) -> jax.Array:
    """Whether a step ends its episode: the task's rule ``done_fn(next_obs)`` (None: never) or
    a draw below the hazard ``hazard_fn(obs, action, key) -> P(end) [...]`` (None: none).
    -> bool [...]"""
    done = (jnp.zeros(next_obs.shape[:-1], bool) if done_fn is None
            else done_fn(next_obs) > 0.5)
    if hazard_fn is not None:
        k_prob, k_draw = jax.random.split(key)
        done = done | (jax.random.uniform(k_draw, done.shape) < hazard_fn(obs, action, k_prob))
    return done


def _sampled_action(params: Params, obs: jax.Array, key: jax.Array) -> jax.Array:
    return sample_action(params, obs, key)[0]


def advance_values(roll: ValueRollout, policy_params: Params, dynamics: Dynamics,
                   reward_fn: Callable, done_fn: Callable | None, key: jax.Array, *,
                   n_steps: int, horizon: int, gamma: float | jax.Array,
                   hazard_fn: Callable | None = None,
                   policy_fn: Callable | None = None) -> ValueRollout:
    """Run ``n_steps`` more steps (steps past ``horizon`` change nothing).

    policy_params: stacked [P, ...]; each policy acts in its own episodes. policy_fn(params,
    obs [n, o], key) -> action [n, a] applies ONE policy's params (any JAX function; None:
    the project's tanh-Gaussian policy, sampled). An episode ends as ``ends_episode`` says
    (``Simulator.terminations`` gives a simulator's done_fn / hazard_fn).
    """
    n_pol = roll.obs.shape[0]
    act = jax.vmap(policy_fn or _sampled_action)  # over policies; each batches its n episodes

    def step(roll: ValueRollout, key):
        k_act, k_dyn = jax.random.split(key)
        action = act(policy_params, roll.obs, jax.random.split(k_act, n_pol))
        k_dyn, k_end = end_key(k_dyn, hazard_fn)
        next_obs, hist = step_dynamics(dynamics, roll.obs, action, k_dyn, roll.hist)
        live = roll.alive & (roll.t < horizon)
        reward = reward_fn(roll.obs, action, next_obs)
        done = ends_episode(roll.obs, action, next_obs, k_end, done_fn, hazard_fn)
        discount = jnp.asarray(gamma, jnp.float32) ** roll.t.astype(jnp.float32)
        return ValueRollout(
            obs=jnp.where(live[..., None], next_obs, roll.obs),
            alive=roll.alive & ~(live & done),
            ret=roll.ret + jnp.where(live, discount * reward, 0.0),
            length=roll.length + live.astype(jnp.int32),
            t=jnp.minimum(roll.t + 1, horizon), hist=hist), None

    roll, _ = jax.lax.scan(step, roll, jax.random.split(key, n_steps))
    return roll


def simulated_returns(policy_params: Params, dynamics: Dynamics, reward_fn: Callable,
                      done_fn: Callable | None, start_pool: jax.Array, key: jax.Array, *,
                      n_episodes: int, horizon: int, gamma: float,
                      hazard_fn: Callable | None = None, new_history: Callable | None = None,
                      policy_fn: Callable | None = None) -> tuple[jax.Array, jax.Array]:
    """Each simulated episode's discounted return and length: n_episodes episodes of at most
    ``horizon`` steps per policy, ended as ``ends_episode`` says (``new_history``: as
    ``start_values``; ``policy_fn``: as ``advance_values``).
    -> (returns [P, n], lengths [P, n] int32)."""
    k_start, k_run = jax.random.split(key)
    n_pol = jax.tree_util.tree_leaves(policy_params)[0].shape[0]
    roll = start_values(start_pool, n_pol, n_episodes, k_start, new_history)
    roll = advance_values(roll, policy_params, dynamics, reward_fn, done_fn, k_run,
                          n_steps=horizon, horizon=horizon, gamma=gamma, hazard_fn=hazard_fn,
                          policy_fn=policy_fn)
    return roll.ret, roll.length


def simulator_returns(sim: Simulator, task, policy_params: Params, start_pool: jax.Array,
                      key: jax.Array, *, n_episodes: int, horizon: int, gamma: float,
                      policy_fn: Callable | None = None) -> tuple[jax.Array, jax.Array]:
    """``simulated_returns`` of a Simulator under a task's ``reward_fn`` / ``done_fn`` (None:
    the simulator's own, ``Simulator.task_fns``), its episodes ended as the simulator's
    ``termination`` says (``Simulator.terminations``); ``policy_fn``: your own policies'
    function (``advance_values``). -> (returns [P, n], lengths [P, n])"""
    task = sim.task_fns() if task is None else task
    done_fn, hazard_fn = sim.terminations(task.done_fn)
    return simulated_returns(policy_params, sim.dynamics, task.reward_fn, done_fn, start_pool,
                             key, n_episodes=n_episodes, horizon=horizon, gamma=gamma,
                             hazard_fn=hazard_fn, new_history=sim.new_history,
                             policy_fn=policy_fn)


def simulated_values(policy_params: Params, dynamics: Dynamics, reward_fn: Callable,
                     done_fn: Callable | None, start_pool: jax.Array, key: jax.Array, *,
                     n_episodes: int, horizon: int, gamma: float,
                     hazard_fn: Callable | None = None, new_history: Callable | None = None
                     ) -> tuple[jax.Array, jax.Array]:
    """Discounted value of each policy in ``dynamics``: mean over n_episodes episodes of at
    most ``horizon`` steps (``simulated_returns`` averaged).
    -> (values [P], mean episode lengths [P])."""
    ret, length = simulated_returns(policy_params, dynamics, reward_fn, done_fn, start_pool,
                                    key, n_episodes=n_episodes, horizon=horizon, gamma=gamma,
                                    hazard_fn=hazard_fn, new_history=new_history)
    return ret.mean(1), length.mean(1).astype(jnp.float32)


def value_difference(sim_values: jax.Array, true_values: jax.Array) -> jax.Array:
    """VD(pi) = |V(p*, pi) - V(p_phi, pi)|, elementwise [P]."""
    return jnp.abs(true_values - sim_values)


# ------------------------------------------------------------------ open loop


def open_loop_windows(ds, k: int, n_windows: int, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Windows of at most ``k`` logged steps per policy of a Dataset, for ``open_loop_returns``.

    Start rows are drawn uniformly (with replacement, ``seed``) among a policy's rows whose
    episode either goes on for k more steps in the data or ends by termination before that; a
    window cut by the time limit or the end of collection has no known outcome and is never
    drawn. -> (rows [P, n_windows] int64 start rows, steps [P, n_windows] int64: the logged
    steps of each window, k unless the episode terminates first)."""
    if not (isinstance(k, int | np.integer) and k >= 1):
        raise ValueError(f"k: expected an int >= 1, got {k!r}")
    if not (isinstance(n_windows, int | np.integer) and n_windows >= 1):
        raise ValueError(f"n_windows: expected an int >= 1, got {n_windows!r}")
    pid, eid = np.asarray(ds.policy_id), np.asarray(ds.episode_id)
    done = np.asarray(ds.done, bool)
    n = pid.shape[0]
    new = np.r_[True, (np.diff(eid) != 0) | (np.diff(pid) != 0)]
    last = np.r_[np.flatnonzero(new)[1:] - 1, n - 1][np.cumsum(new) - 1]  # each row's episode end
    left = last - np.arange(n) + 1  # logged steps from this row to its episode's end
    ok = (left >= k) | done[last]
    rng = np.random.default_rng(seed)
    rows = np.empty((ds.n_policies, n_windows), np.int64)
    for p in range(ds.n_policies):
        mine = np.flatnonzero(ok & (pid == p))
        if mine.size == 0:
            raise ValueError(f"policy_id: policy {p} has no window of {k} logged steps that "
                             f"ends by the data's own termination or goes on k steps")
        rows[p] = rng.choice(mine, n_windows)
    return rows, np.minimum(left[rows], k)


def open_loop_returns(dynamics: Dynamics, reward_fn: Callable, done_fn: Callable | None,
                      obs: jax.Array, actions: jax.Array, steps: jax.Array, key: jax.Array, *,
                      hazard_fn: Callable | None = None
                      ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``dynamics`` rolled from real states under LOGGED actions (no policy in the loop): the
    model's error on a fixed action sequence, which a closed-loop episode mixes with the
    policy's reaction to it.

    obs [N, o] start states; actions [N, k, a] (entries past ``steps`` are never used);
    steps [N] logged steps of each window. The simulated episode ends as ``ends_episode``
    says. -> (reward [N, k]: each simulated step's reward, 0 once the simulated episode has
    ended or past ``steps``; live [N, k]: step j was taken; ended [N, k]: step j ended it)."""
    n_steps = actions.shape[1]

    def step(carry, xs):
        s, alive = carry
        a, j, k_step = xs
        k_dyn, k_end = jax.random.split(k_step)
        nxt = dynamics(s, a, k_dyn)
        live = alive & (j < steps)
        reward = jnp.where(live, reward_fn(s, a, nxt), 0.0)
        done = ends_episode(s, a, nxt, k_end, done_fn, hazard_fn)
        return (nxt, alive & ~(live & done)), (reward, live, live & done)

    alive0 = jnp.ones(obs.shape[:-1], bool)
    xs = (jnp.swapaxes(actions, 0, 1), jnp.arange(n_steps), jax.random.split(key, n_steps))
    _, out = jax.lax.scan(step, (obs, alive0), xs)
    return tuple(jnp.swapaxes(x, 0, 1) for x in out)


def logged_window_returns(ds, rows: np.ndarray, steps: np.ndarray, k: int,
                          reward_fn: Callable) -> tuple[np.ndarray, np.ndarray]:
    """What the real system did in the windows of ``open_loop_windows``: the per-step reward
    ``reward_fn`` gives the logged transitions (as the simulator's rewards are computed) and
    whether the window ends by termination. rows, steps [...] -> (reward [..., k] (0 past
    ``steps``), ended [...] bool)."""
    j = np.arange(k)
    idx = np.asarray(rows)[..., None] + np.minimum(j, np.asarray(steps)[..., None] - 1)
    valid = j < np.asarray(steps)[..., None]
    reward = np.asarray(reward_fn(jnp.asarray(np.asarray(ds.obs)[idx]),
                                  jnp.asarray(np.asarray(ds.action)[idx]),
                                  jnp.asarray(np.asarray(ds.next_obs)[idx])), np.float64)
    ended = np.asarray(ds.done, bool)[idx[..., -1]]
    return np.where(valid, reward, 0.0), ended


# ------------------------------------------------------------------ error on the visited states


def step_errors(model_next: jax.Array, reference_next: jax.Array, obs: jax.Array,
                action: jax.Array, reward_fn: Callable, scale: jax.Array
                ) -> tuple[jax.Array, jax.Array]:
    """One step's error of a simulator against a reference from the same (obs, action): the
    next states' difference per dim in units of ``scale`` [o] (0 where the scale is 0: the dim
    is left out), and the reward difference r(s, a, model) - r(s, a, reference).
    [..., o] -> (scaled error [..., o], reward difference [...]); ``mean_square`` of the first
    is the step's squared error over the dims used."""
    scale = jnp.asarray(scale, jnp.float32)
    used = scale > 0
    z = jnp.where(used, (model_next - reference_next) / jnp.where(used, scale, 1.0), 0.0)
    return z, reward_fn(obs, action, model_next) - reward_fn(obs, action, reference_next)


def mean_square(z: jax.Array, scale: jax.Array) -> jax.Array:
    """The mean of z ** 2 over the dims with ``scale`` > 0. [..., o] -> [...]"""
    return jnp.sum(z ** 2, -1) / jnp.maximum(jnp.sum(jnp.asarray(scale) > 0), 1)


def visited_step_errors(policy_params: Params, dynamics: Dynamics, reference: Dynamics,
                        reward_fn: Callable, done_fn: Callable | None, start_pool: jax.Array,
                        key: jax.Array, *, n_episodes: int, horizon: int, scale: jax.Array,
                        hazard_fn: Callable | None = None,
                        new_history: Callable | None = None) -> dict:
    """A simulator's one-step error on the states ITS OWN closed-loop episodes visit: the
    policies' episodes run in ``dynamics`` as ``simulated_returns`` runs them (start states,
    termination), and at every live step ``reference`` (the real dynamics, e.g.
    ``oracle.oracle_dynamics``) is stepped from the same state and action (``step_errors``).
    Beside the same error on logged states it shows whether the model errs more where it
    takes the policies than where the data is.

    policy_params [P, ...]; scale [o]. -> {"rmse", "reward_bias" (mean reward difference per
    step), "reward_abs" (its mean absolute value), "steps" (live steps)}: each [P]; and
    "rmse_per_dim" [P, o]."""
    n_pol = jax.tree_util.tree_leaves(policy_params)[0].shape[0]
    k_start, k_run = jax.random.split(key)
    roll = start_values(start_pool, n_pol, n_episodes, k_start, new_history)
    act = jax.vmap(sample_action)
    zeros = jnp.zeros(roll.alive.shape, jnp.float32)

    def step(carry, key):
        (obs, hist), alive, t, dim_sum, bias_sum, abs_sum, count = carry
        k_act, k_dyn = jax.random.split(key)  # advance_values' draws: the same episodes
        action, _, _ = act(policy_params, obs, jax.random.split(k_act, n_pol))
        k_ref = jax.random.fold_in(k_dyn, 1)
        k_dyn, k_end = end_key(k_dyn, hazard_fn)
        nxt, hist = step_dynamics(dynamics, obs, action, k_dyn, hist)
        ref = reference(obs, action, k_ref)
        z, dr = step_errors(nxt, ref, obs, action, reward_fn, scale)
        live = alive & (t < horizon)
        w = live.astype(jnp.float32)
        done = ends_episode(obs, action, nxt, k_end, done_fn, hazard_fn)
        return ((jnp.where(live[..., None], nxt, obs), hist), alive & ~(live & done), t + 1,
                dim_sum + w[..., None] * z ** 2, bias_sum + w * dr, abs_sum + w * jnp.abs(dr),
                count + w), None

    carry = ((roll.obs, roll.hist), roll.alive, jnp.zeros((), jnp.int32),
             jnp.zeros_like(roll.obs), zeros, zeros, zeros)
    carry, _ = jax.lax.scan(step, carry, jax.random.split(k_run, horizon))
    dim_sum = carry[3].sum(1)  # [P, o], over episodes
    bias_sum, abs_sum, count = (jnp.sum(x, -1) for x in carry[4:])
    n = jnp.maximum(count, 1.0)
    per_dim = jnp.sqrt(dim_sum / n[:, None])
    return {"rmse": jnp.sqrt(mean_square(per_dim, scale)), "reward_bias": bias_sum / n,
            "reward_abs": abs_sum / n, "steps": count, "rmse_per_dim": per_dim}
