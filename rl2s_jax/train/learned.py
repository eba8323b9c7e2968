"""The learned parts of a simulator beside its dynamics: the termination hazard
(``model.termination``) and the reward head (``model.reward``), both fitted once in ``init`` on
every training row; and what the simulator's reward and termination get wrong on the held-out
episodes (``heldout_errors``, in `rl2s train`'s summary)."""
from __future__ import annotations

import jax
import numpy as np

from rl2s_jax.model.dynamics import Normalizer
from rl2s_jax.model.reward import fit_reward, init_reward
from rl2s_jax.model.simulator import Simulator
from rl2s_jax.model.termination import LEARNED, fit_hazard, init_hazard, window_labels
from rl2s_jax.train.config import TrainConfig
from rl2s_jax.train.data import TrainData


def fit_learned(key: jax.Array, cfg: TrainConfig, data: TrainData, norm: Normalizer):
    """The hazard (termination "hazard" / "both") and the reward head (reward "learned") of a
    run, fitted on the training rows; None where the config uses neither. Pure and jittable.
    -> (hazard params | None, reward params | None)"""
    obs_size, act_size = data.obs.shape[1], data.action.shape[1]
    hazard = reward = None
    if cfg.outcome.termination in LEARNED:
        if data.done is None:
            raise ValueError(f"outcome.termination: {cfg.outcome.termination!r} learns from the "
                             f"data's done flags, and TrainData.done is None (make_train_data "
                             f"sets it)")
        k_init, k_fit = jax.random.split(jax.random.fold_in(key, 7))
        if cfg.outcome.hazard_window > 1 and data.steps_left is None:
            raise ValueError("hazard_window: a window > 1 needs TrainData.steps_left "
                             "(make_train_data sets it); set hazard_window=1")
        labels = (data.done if cfg.outcome.hazard_window == 1
                  else window_labels(data.done, data.steps_left, cfg.outcome.hazard_window))
        hazard, _ = fit_hazard(k_fit, init_hazard(k_init, obs_size, act_size,
                                                  cfg.outcome.hazard_hidden),
                               norm, data.obs, data.action, labels, steps=cfg.outcome.hazard_steps)
    if cfg.outcome.reward == "learned":
        if data.reward is None:
            raise ValueError("reward: 'learned' fits a head on the data's rewards, and "
                             "TrainData.reward is None (make_train_data sets it)")
        k_init, k_fit = jax.random.split(jax.random.fold_in(key, 8))
        reward, _ = fit_reward(k_fit, init_reward(k_init, obs_size, act_size,
                                                  cfg.outcome.reward_hidden),
                               norm, data.obs, data.action, data.next_obs, data.reward,
                               steps=cfg.outcome.reward_steps)
    return hazard, reward


def _logloss(p: np.ndarray, y: np.ndarray) -> float:
    p = np.clip(p, 1e-7, 1 - 1e-7)
    return float(-np.mean(y * np.log(p) + (1 - y) * np.log1p(-p)))


def heldout_errors(sim: Simulator, data: TrainData) -> dict:
    """How the simulator's reward and termination match the held-out episodes' logged ones,
    on their rows (``TrainData.val_*``), each step's own (s, a, s') given.

    -> {"reward": {"source": "learned" or "task <name>", "heldout_mse" (squared error in the
    data's reward units), "heldout_r2" (1 - mse / the rows' reward variance),
    "heldout_rows"}, "termination": {"source": "hazard" | "both" | "rule <task>",
    "heldout_ends" (logged terminations), "predicted_ends" (sum of the per-step hazard, or the
    rule's count), and for a hazard "heldout_logloss" with "constant_logloss" (a constant
    hazard at the training rows' rate, the baseline it should beat)}}. A part that cannot be
    scored (no held-out episodes, nothing gives a reward) has its numbers None and a "note"."""
    out = {}
    V = data.n_heldout
    try:
        task = sim.task_fns()
    except ValueError as err:
        task, why = None, str(err)
    reward = {"source": ("learned" if sim.reward is not None
                         else None if task is None else f"task {task.name}")}
    term = {"source": (sim.termination if sim.termination != "rule" or task is None
                       else f"rule {task.name}")}
    if V == 0 or data.val_reward is None or data.val_done is None:
        note = "no held-out episodes (holdout_frac 0)" if V == 0 else "no held-out labels"
        return {"reward": {**reward, "heldout_mse": None, "heldout_r2": None, "note": note},
                "termination": {**term, "heldout_ends": None, "note": note}}
    obs, act, nxt = data.val_obs, data.val_action, data.val_next_obs
    y = np.asarray(data.val_reward, np.float64)
    if task is None:
        reward.update(heldout_mse=None, heldout_r2=None, note=why)
    else:
        pred = np.asarray(jax.jit(task.reward_fn)(obs, act, nxt), np.float64)
        mse = float(np.mean((pred - y) ** 2))
        var = float(np.var(y))
        reward.update(heldout_mse=mse, heldout_r2=1.0 - mse / var if var > 0 else None)
    reward["heldout_rows"] = V
    out["reward"] = reward
    done = np.asarray(data.val_done, np.float64)
    term["heldout_ends"] = int(done.sum())
    if sim.hazard is not None and sim.termination != "rule":
        h = np.asarray(jax.jit(sim.hazard_prob)(obs, act), np.float64)
        rate = float(np.mean(np.asarray(data.done))) if data.done is not None else done.mean()
        term.update(predicted_ends=float(h.sum()), heldout_logloss=_logloss(h, done),
                    constant_logloss=_logloss(np.full_like(done, rate), done))
    elif task is not None and sim.termination == "rule":
        fired = np.asarray(jax.jit(task.done_fn)(nxt)) > 0.5
        term.update(predicted_ends=int(fired.sum()),
                    heldout_agreement=float(np.mean(fired == (done > 0.5))))
    term["heldout_rows"] = V
    out["termination"] = term
    return out


def learned_lines(errors: dict) -> list[str]:
    """Lines of `rl2s train`'s printed summary for ``heldout_errors``."""
    r, t = errors["reward"], errors["termination"]
    lines = []
    if r.get("heldout_mse") is not None:
        r2 = "" if r.get("heldout_r2") is None else f", R^2 {r['heldout_r2']:.3f}"
        lines.append(f"reward ({r['source']}) on {r['heldout_rows']} held-out rows: MSE "
                     f"{r['heldout_mse']:.4g}{r2}")
    elif r.get("note"):
        lines.append(f"reward ({r['source']}): not scored ({r['note']})")
    if t.get("heldout_logloss") is not None:
        lines.append(f"termination ({t['source']}) on {t['heldout_rows']} held-out rows: "
                     f"log-loss {t['heldout_logloss']:.4f} (constant rate "
                     f"{t['constant_logloss']:.4f}), predicted ends "
                     f"{t['predicted_ends']:.1f} vs {t['heldout_ends']} logged")
    elif t.get("predicted_ends") is not None:
        lines.append(f"termination ({t['source']}) on {t['heldout_rows']} held-out rows: "
                     f"{t['predicted_ends']} ends vs {t['heldout_ends']} logged, agreement "
                     f"{t['heldout_agreement']:.4f}")
    return lines

