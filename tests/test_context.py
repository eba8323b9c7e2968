"""The per-episode context of the simulator users train (TrainConfig.dynamics.context_dim;
rl2s_jax.model.history.history_context): inferred online from the episode's recent
transitions, in training rows and in rollouts alike."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs import base as brax_base
from test_train import BIASES, GAMMA
from test_train import _policies as _pm_policies

from rl2s_jax.data.collect import collect
from rl2s_jax.envs.tasks import POINTMASS_DT, PointMass, get_task
from rl2s_jax.evaluate.scores import one_step_errors
from rl2s_jax.improve.sim_env import SimulatorEnv
from rl2s_jax.model import history as H
from rl2s_jax.model.dynamics import DynamicsSpec, Normalizer, init_member
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.train.checkpoint import Checkpointer, load_simulator
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import make_train_data
from rl2s_jax.train.step import init, simulator, train_steps

TASK = get_task("pointmass")
HISTORY = TrainConfig.small().override({
    "task": "pointmass", "method": "bc", "vd.horizon": 50, "vd.every": 5,
    "dynamics.obs_history": 2, "dynamics.action_history": 2})
CONTEXT = HISTORY.override({"dynamics.context_dim": 2})


class EpisodeGain(PointMass):
    """Pointmass whose actuator gain is drawn once per episode (log-uniform in [1/4, 4]) and
    never observed: a hidden per-episode parameter with a known effect."""

    def reset(self, rng: jax.Array) -> brax_base.State:
        r_env, r_gain = jax.random.split(rng)
        state = super().reset(r_env)
        gain = jnp.exp(jax.random.uniform(r_gain, (), minval=np.log(0.25), maxval=np.log(4.0)))
        return state.replace(info={"gain": gain})

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        nxt = super().step(state, action)
        dv = (state.info["gain"] - 1.0) * POINTMASS_DT * 2.0 * jnp.clip(action[0], -1, 1)
        x = nxt.obs + jnp.stack([POINTMASS_DT * dv, dv])
        return nxt.replace(pipeline_state=x, obs=x)


@pytest.fixture(scope="module")
def gains():
    policies = _pm_policies(BIASES)
    kw = dict(transitions_per_policy=600, envs_per_policy=4,
              episode_length=TASK.episode_length, task="pointmass", gamma=GAMMA,
              progress=False)
    train = collect(EpisodeGain(), policies, key=jax.random.PRNGKey(0), value_episodes=4, **kw)
    held = collect(EpisodeGain(), policies, key=jax.random.PRNGKey(1), value_episodes=0, **kw)
    out = {}
    for name, cfg in (("history", HISTORY), ("context", CONTEXT)):
        data = make_train_data(train, policies, cfg)
        state, _ = jax.jit(train_steps, static_argnums=2)(
            jax.jit(init, static_argnums=1)(jax.random.PRNGKey(0), cfg, data), data, 40)
        out[name] = state
    return out, train, held, policies


def test_context_matches_a_numpy_reference():
    """Encoder over the K = min(Ko, Ka) newest transitions (s_{t-1-k}, a_{t-1-k}, s_{t-k}),
    the newest ending at the current obs, mean-pooled over the valid ones."""
    o, a, k_obs, k_act, C = 3, 2, 3, 2, 4
    spec = DynamicsSpec(hidden=(8,), action_history=k_act, obs_history=k_obs, context_dim=C,
                        context_hidden=(5,))
    params = init_member(jax.random.PRNGKey(0), spec, o, a)
    rng = np.random.default_rng(0)
    norm = Normalizer(obs_mean=jnp.asarray(rng.normal(size=o), jnp.float32),
                      obs_std=jnp.asarray(rng.uniform(0.5, 2, o), jnp.float32),
                      act_mean=jnp.zeros(a), act_std=jnp.ones(a),
                      delta_mean=jnp.asarray(rng.normal(size=o), jnp.float32),
                      delta_std=jnp.asarray(rng.uniform(0.5, 2, o), jnp.float32))
    B = 3
    obs = rng.normal(size=(B, o)).astype(np.float32)
    past_obs = rng.normal(size=(B, k_obs, o)).astype(np.float32)
    past_act = rng.normal(size=(B, k_act, a)).astype(np.float32)
    n_valid = np.array([0, 1, 3])  # steps since the start: none, one, more than the window
    hist = H.History(past_obs=jnp.asarray(past_obs),
                     past_obs_valid=jnp.asarray(np.arange(k_obs)[None] < n_valid[:, None]),
                     past_act=jnp.asarray(past_act),
                     past_act_valid=jnp.asarray(np.arange(k_act)[None] < n_valid[:, None]),
                     t=jnp.asarray(n_valid, jnp.int32))
    got = np.asarray(H.history_context(params, norm, jnp.asarray(obs), hist))

    def mlp(layers, x):
        for layer in layers[:-1]:
            x = np.maximum(x @ np.asarray(layer["w"]) + np.asarray(layer["b"]), 0)
        return x @ np.asarray(layers[-1]["w"]) + np.asarray(layers[-1]["b"])
    m = {k: np.asarray(getattr(norm, k)) for k in ("obs_mean", "obs_std", "delta_mean",
                                                   "delta_std")}
    for b in range(B):
        embs = []
        for k in range(min(k_obs, k_act, n_valid[b])):
            s, act = past_obs[b, k], past_act[b, k]
            nxt = obs[b] if k == 0 else past_obs[b, k - 1]
            x = np.r_[(s - m["obs_mean"]) / m["obs_std"], act,
                      (nxt - s - m["delta_mean"]) / m["delta_std"]]
            embs.append(mlp(params["enc"], x))
        want = np.mean(embs, 0) if embs else np.zeros(C)
        np.testing.assert_allclose(got[b], want, rtol=1e-4, atol=1e-5)


def test_context_learns_a_hidden_per_episode_gain(gains):
    """With the actuator gain hidden per episode, members with a context fit held-out
    episodes far better than members with the same past as plain inputs (40 BC steps each,
    same seed): held-out NLL of ``rl2s evaluate``'s score lower by over 0.5 nats, MSE
    halved (measured -6.1 vs -5.1 nats, 0.054 vs 0.20)."""
    states, _, held, _ = gains
    err = {k: one_step_errors(simulator(s), held) for k, s in states.items()}
    assert err["context"]["heldout_nll"] < err["history"]["heldout_nll"] - 0.5, err
    assert err["context"]["heldout_mse"] < 0.5 * err["history"]["heldout_mse"], err


def test_context_simulator_rolls_out_and_loads_from_a_checkpoint(gains, tmp_path):
    states, train, held, _ = gains
    state = states["context"]
    sim = simulator(state)
    assert "enc" in sim.gen
    env = SimulatorEnv(sim, start_pool(train))
    s = env.reset(jax.random.PRNGKey(3))
    for a in (0.7, -0.4, 0.2):
        s = env.step(s, jnp.asarray([a]))
    assert bool(jnp.isfinite(s.obs).all()) and int(s.pipeline_state[1].t) == 3
    # the step's prediction depends on the context: a blind encoder changes it
    blind = sim.replace(gen={**sim.gen, "enc": jax.tree_util.tree_map(jnp.zeros_like,
                                                                      sim.gen["enc"])})
    hist = s.pipeline_state[1]
    act = jnp.asarray([0.5])
    assert float(jnp.abs(sim.mean(s.obs, act, hist) - blind.mean(s.obs, act, hist)).max()) > 1e-4
    ck = Checkpointer(tmp_path / "ck")
    ck.save(state, {"data": {"obs_size": 2, "action_size": 1}})
    ck.close()
    loaded = load_simulator(tmp_path / "ck")
    assert one_step_errors(loaded, held) == one_step_errors(sim, held)


def test_context_without_a_past_is_refused_by_name():
    with pytest.raises(ValueError, match="context_dim.*obs_history and action_history"):
        TrainConfig.small(context_dim=2, obs_history=2).validate()
    with pytest.raises(ValueError, match="context_dim"):
        TrainConfig.small(context_dim=-1).validate()
    with pytest.raises(ValueError, match="context_hidden"):
        TrainConfig.small(context_dim=2, obs_history=1, action_history=1,
                          context_hidden=()).validate()
