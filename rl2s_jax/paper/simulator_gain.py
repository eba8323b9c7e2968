"""The gain table of issue 62 item 4 (experiments/physics_gain.py): physics models and learned
simulators scored alike on planted C-MuJoCo data, with t intervals over collection seeds.

Every simulator gets the same held-out rows and open-loop windows
(``physics.residuals.prediction_errors``) and the same start states and policy draws for the
values (one key; ``simulated_returns``' key stream, which ``calibrated.c_values`` follows). A
learned simulator's step there is its mean next state (``Simulator.mean``: the elites'
average), fed the logged actions (and the episode's logged past actions where it reads them:
a hybrid, an extended simulator); its values are sampled rollouts (``simulator_returns``).
"""

from __future__ import annotations

import os

import jax
import numpy as np

from rl2s_jax.evaluate.metrics import kendall_tau, value_differences
from rl2s_jax.model.history import logged_history
from rl2s_jax.model.simulator import Simulator, simulator_returns
from rl2s_jax.physics.residuals import prediction_errors
from rl2s_jax.stats import t_interval

__all__ = ["METRICS", "value_scores", "learned_scores", "train_learned", "seed_summary",
           "gain_rows"]

METRICS = ("one_step", "kstep", "avd", "mvd", "tau")
LABELS = {"one_step": "one-step RMSE", "kstep": "k-step RMSE", "avd": "AVD", "mvd": "MVD",
          "tau": "Kendall tau"}


def value_scores(true, sim) -> dict:
    """AVD, MVD and Kendall tau of simulated values [P] against true ones [P]."""
    vd = value_differences(true, sim)
    return {"avd": vd["avd"], "mvd": vd["mvd"], "tau": kendall_tau(true, sim)}


def learned_scores(sim: Simulator, held, task, policy_params, pool, key, true, *, k: int,
                   seed: int, n_episodes: int, horizon: int, gamma: float) -> dict:
    """A learned simulator's row: one-step / k-step error on the held-out Dataset ``held`` and
    value scores of ``policy_params`` [P, ...] against ``true`` [P] (module docstring)."""
    err = prediction_errors(_mean_step(sim, held), held, k=k, seed=seed, with_rows=True)
    ret, _ = simulator_returns(sim, task, policy_params, pool, key, n_episodes=n_episodes,
                               horizon=horizon, gamma=gamma)
    return {"one_step": err["one_step"], "kstep": err["kstep"][-1],
            **value_scores(true, np.asarray(ret.mean(1)))}


def _mean_step(sim: Simulator, held):
    """``step(obs [N, O], action [N, A], rows [N]) -> sim.mean`` [N, O]: a simulator with
    past-action or time inputs sees the held-out episode's logged past at ``rows``, as it
    would have seen its own actions in a rollout (a hybrid's delayed physics reads them)."""
    mean = jax.jit(sim.mean)
    if sim.obs_history:
        raise ValueError(f"sim: obs_history {sim.obs_history}: an open-loop window would need "
                         f"the model's own past observations, not the logged ones; expected "
                         f"obs_history 0")

    def step(obs, action, rows):
        hist = None if sim.markov else logged_history(
            held, rows, obs_history=0, action_history=sim.action_history,
            time_inputs=sim.time_inputs, episode_length=sim.episode_length)
        return mean(np.asarray(obs, np.float32), np.asarray(action, np.float32), hist)
    return step


def train_learned(train_path: str, method: str, out: str, *, steps: int, profile: str,
                  seed: int, gamma: float, horizon: int, log=print) -> Simulator:
    """``method`` ("bc", "rl2s") trained by ``app.training.run_training`` on the Dataset file
    (its meta names the zoo), its VD measured at this ``gamma`` and ``horizon``, the
    evaluation's -> the trained Simulator (checkpoint under ``out``)."""
    # Imported here: app.training pulls in the whole training stack, which the table's
    # helpers (and their tests) do not need.
    from rl2s_jax.app.specs import TrainSpec
    from rl2s_jax.app.training import run_training
    from rl2s_jax.train.checkpoint import load_simulator

    run_training(TrainSpec(data=train_path, steps=steps, out=out, method=method, profile=profile,
                           seed=seed, quiet=True,
                           set={"gamma": float(gamma), "vd.horizon": int(horizon)}), log=log)
    return load_simulator(os.path.join(out, "checkpoints"))


def seed_summary(runs: list[dict], sims: list[str]) -> dict:
    """Per simulator and metric over the seeds' runs ([{sim: {metric: x}}]; a run without a
    simulator is skipped for it): {sim: {metric: {"mean", "lo", "hi" (95% t interval; None
    with one seed), "n", "per_seed"}}}."""
    out = {}
    for sim in sims:
        have = [r[sim] for r in runs if r.get(sim) is not None]
        if not have:
            continue
        out[sim] = {}
        for m in METRICS:
            x = [float(r[m]) for r in have]
            ci = t_interval(x)
            out[sim][m] = {"mean": float(np.mean(x)), "lo": None if ci is None else ci[1],
                           "hi": None if ci is None else ci[2], "n": len(x), "per_seed": x}
    return out


def _cell(s: dict) -> str:
    if s["lo"] is None:
        return f"{s['mean']:.3g}"
    return f"{s['mean']:.3g} [{s['lo']:.3g}, {s['hi']:.3g}]"


def gain_rows(summary: dict) -> list[str]:
    """Markdown table of ``{case: seed_summary(...)}``: per case and simulator, each metric's
    mean over seeds with its 95% t interval."""
    lines = ["| case | simulator | seeds | " + " | ".join(LABELS[m] for m in METRICS) + " |",
             "|---|---|---|" + "---|" * len(METRICS)]
    for case, sims in summary.items():
        for sim, scores in sims.items():
            n = scores[METRICS[0]]["n"]
            lines.append(f"| {case} | {sim} | {n} | "
                         + " | ".join(_cell(scores[m]) for m in METRICS) + " |")
    return lines
