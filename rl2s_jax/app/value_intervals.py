"""`rl2s evaluate --level`: every evaluated policy's value interval (evaluate/trust.py) for one
or several checkpoints of a task, calibrated on policies whose truth is known (by default the
checkpoint's own training data; ``--calibration DATA`` adds or replaces held-out sets such as
``calibration_data``'s perturbed policies), never on the evaluated ones."""

from __future__ import annotations

import os

import jax
import numpy as np

from rl2s_jax.data.collect import collect
from rl2s_jax.data.dataset import load_dataset, save_dataset
from rl2s_jax.data.values import true_values
from rl2s_jax.envs.tasks import get_task
from rl2s_jax.evaluate import trust as tr
from rl2s_jax.model.simulator import start_pool
from rl2s_jax.physics.hybrid import load_hybrid
from rl2s_jax.policy.policy import index_params, save_policies
from rl2s_jax.zoo.zoo import load_zoo, policies_for

# Why a simulated value a command prints has no interval (issue 64: every command that prints
# a simulated value prints its interval or says why not; docs/EVALUATION.md, "Which printed
# values carry an interval").
NO_INTERVAL = {
    "sim_return": "simulated return: SAC's own return while fine-tuning inside the simulator "
                  "(the exploring actor over its training episodes), a training curve rather "
                  "than an estimate of a policy's value, so no interval",
    "floor_guard": "predicted gain: the elite members' gains that the guard compares with its "
                   "margin carry no interval, which needs fine-tuned policies with known real "
                   "gains to calibrate on (`rl2s improve --guard interval --guard-calibration "
                   "FILE`)",
    "training_policies": "sim value: of the training policies, whose data the simulator "
                         "learned from, beside their true values: the error is measured, not "
                         "predicted, so no interval (other policies' intervals: `rl2s "
                         "evaluate --ckpt`)",
    "oracle": "the oracle runs the real dynamics: its values are Monte-Carlo estimates of the "
              "truth, not a simulator's predictions (their episode noise: --bootstrap)",
    "level_0": "--level 0 turned them off",
}


def _calibration_paths(metas: list[dict], calibration: list[str] | None) -> tuple[list, set]:
    """(the calibration data files, the real paths of the checkpoints' training data)."""
    train = {os.path.realpath(p) for m in metas
             if (p := (m.get("data") or {}).get("path"))}
    if calibration:
        for p in calibration:
            if not os.path.isfile(p):
                raise FileNotFoundError(f"calibration: no such file {p}")
        return list(calibration), train
    return sorted(p for p in train if os.path.isfile(p)), train


def trust_for(ckpts: list[str], data_path: str, report: dict, *, level: float,
              calibration: list[str] | None = None, zoo: str | None = None,
              policy_file: str | None = None, step: int | None = None) -> dict:
    """The intervals of the policies of ``data_path`` under the checkpoints ``ckpts`` (one, or
    several seeds of one task), in the evaluation setting of ``report`` (an
    ``evaluate_checkpoint`` report of the first: horizon, gamma, episodes, seed, truth).
    calibration: Dataset files of policies with known truth (default: the checkpoints'
    training data; a file that is the training data counts as "train", others "heldout").
    -> {"trust": ``trust_report`` (or {"skipped": why}), "interval": [[lo, hi]] per policy,
    "trusted": [bool]} (the last two absent when skipped)."""
    level = tr.check_level(level)
    loaded = [load_hybrid(c, step) for c in ckpts]
    sims, metas = [s for s, _ in loaded], [m for _, m in loaded]
    paths, train = _calibration_paths(metas, calibration)
    if not paths:
        return {"trust": {"skipped": "no calibration data: the checkpoint's training data is "
                          "not on this machine; pass --calibration DATA (policies with known "
                          "true values, not the evaluated ones)"}}
    if os.path.realpath(data_path) in {os.path.realpath(p) for p in paths}:
        if not calibration:  # the training policies evaluated: nothing else to calibrate on
            return {"trust": {"skipped": "the evaluated data is the checkpoint's training data "
                              "(calibration never uses the evaluated policies); pass "
                              "--calibration DATA"}}
        raise ValueError(f"calibration: {data_path} is the evaluated data itself; calibrate "
                         f"on other policies (training / validation / perturbed)")
    kw = dict(key=jax.random.PRNGKey(report["seed"]), n_episodes=report["n_episodes"],
              horizon=report["horizon"], gamma=report["gamma"])
    truth_kind = (report.get("setting") or {}).get("truth", "auto")
    unit_ds = load_dataset(next((p for p in paths if os.path.realpath(p) in train), paths[0]))
    units = [tr.data_disagreement(s, unit_ds) if tr.elites(s).size > 1 else None for s in sims]

    def features(ds, policies):
        pool = start_pool(ds)
        return tr.combine_features([tr.policy_features(s, pool, policies, u_unit=u, **kw)
                                    for s, u in zip(sims, units, strict=True)])

    cal_feats, cal_truth, kinds = [], [], []
    for p in paths:
        ds = load_dataset(p)
        try:
            policies = policies_for(ds, data_path=p)
        except (ValueError, FileNotFoundError) as err:
            if calibration:  # asked for: an error; the default training data: a note
                raise ValueError(f"calibration: {p}: {err}") from None
            return {"trust": {"skipped": f"the training data {p} does not name its policies "
                              f"({err}); pass --calibration DATA"}}
        cal_feats.append(features(ds, policies))
        cal_truth.append(true_values(ds, kw["horizon"], kw["gamma"], truth=truth_kind))
        kinds += ["train" if os.path.realpath(p) in train else "heldout"] * ds.n_policies
    cal = tr.calibrate({k: np.concatenate([f[k] for f in cal_feats]) for k in cal_feats[0]},
                       np.concatenate(cal_truth), kinds, level)
    cal["sources"] = paths
    ds = load_dataset(data_path)
    feats = features(ds, policies_for(ds, zoo, policy_file=policy_file, data_path=data_path))
    truth = np.asarray(report["true_value"], np.float64)
    t = tr.trust_report(feats, cal, report["policy_names"],
                        truth if np.all(np.isfinite(truth)) else None)
    return {"trust": t, "interval": [p["interval"] for p in t["policies"]],
            "trusted": [p["trusted"] for p in t["policies"]]}


def calibration_data(zoo_dir: str, out: str, *, n: int, seed: int = 0, noise: float = 0.1,
                     split: str = "train", transitions_per_policy: int = 200,
                     value_episodes: int = 16, episode_length: int | None = None,
                     gamma: float = 0.999) -> str:
    """A held-out calibration set: ``n`` ``perturbed_policies`` of the zoo's ``split``
    policies, measured in the real env (their true values and some transitions) and written
    as a Dataset ``out`` whose meta.source names their policy file (``out`` with
    ``.policies.npz``). The simulator never trained on these policies' data, but they sit near
    the training policies. -> out"""
    zoo = load_zoo(zoo_dir)
    ids = zoo.split_ids(split)
    task = get_task(zoo.task)
    params, origins = tr.perturbed_policies(index_params(zoo.params, np.asarray(ids)),
                                            jax.random.PRNGKey(seed), n, noise=noise)
    names = [f"{zoo.task}-{split}-perturbed-{i:03d}" for i in range(n)]
    pol_path = os.path.splitext(out)[0] + ".policies.npz"
    save_policies(pol_path, params, names)
    ds = collect(task.make_env(), params, key=jax.random.PRNGKey(seed + 1),
                 transitions_per_policy=transitions_per_policy,
                 episode_length=episode_length or task.episode_length, task=zoo.task,
                 value_episodes=value_episodes, progress=False, policy_names=names, gamma=gamma,
                 source={"policy_file": os.path.basename(pol_path), "perturbed_from": {
                     "zoo": zoo_dir, "split": split, "zoo_ids": ids, "origins": origins}})
    save_dataset(out, ds)
    return out
