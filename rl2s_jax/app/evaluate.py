"""`rl2s evaluate`: a checkpoint (or the oracle) scored on a Dataset file.

A checkpoint is evaluated by default with the settings training evaluated it with (its
config's vd_horizon and vd_episodes, ``checkpoint_settings``), so the two agree; the report
names the settings used and where each came from."""

from __future__ import annotations

import jax

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.envs.tasks import TASKS
from rl2s_jax.evaluate.simulator import evaluate_oracle, evaluate_simulator, one_step_errors
from rl2s_jax.train.checkpoint import load_checkpoint
from rl2s_jax.zoo.zoo import policies_for

DEFAULT_EPISODES = 16  # simulated episodes per policy where nothing else sets them


def _check_settings(n_episodes, horizon) -> None:
    for name, v in (("episodes", n_episodes), ("horizon", horizon)):
        if v is not None and (not isinstance(v, int) or v < 1):
            raise ValueError(f"{name}: expected an int >= 1 (or None: the default), got {v!r}")


def checkpoint_settings(config: dict, ds, n_episodes: int | None = None,
                        horizon: int | None = None) -> dict:
    """The horizon and episodes to evaluate a checkpoint with, and where each comes from.

    By default the ones the checkpoint was evaluated with during training: its config's
    ``vd_horizon`` (at most the data's episode_length: the real episodes end there) and
    ``vd_episodes``; given values win. -> {"horizon", "horizon_source", "n_episodes",
    "episodes_source"}."""
    _check_settings(n_episodes, horizon)
    out = {"horizon": horizon, "horizon_source": "--horizon",
           "n_episodes": n_episodes, "episodes_source": "--episodes"}
    if horizon is None:
        vd, ep = config.get("vd_horizon"), ds.meta.get("episode_length")
        if vd is None:
            out.update(horizon=int(ep or 1000), horizon_source="the data's episode_length")
        elif ep is not None and int(vd) > int(ep):
            out.update(horizon=int(ep), horizon_source=f"the data's episode_length; the "
                       f"checkpoint's vd_horizon {vd} is longer")
        else:
            out.update(horizon=int(vd), horizon_source="the checkpoint's vd_horizon")
    if n_episodes is None:
        vd = config.get("vd_episodes")
        out.update(n_episodes=int(vd or DEFAULT_EPISODES),
                   episodes_source=("the checkpoint's vd_episodes" if vd
                                    else f"the default {DEFAULT_EPISODES}"))
    return out


def evaluate_checkpoint(ckpt: str, data_path: str, *, zoo: str | None = None,
                        policy_file: str | None = None, seed: int = 0,
                        n_episodes: int | None = None, horizon: int | None = None,
                        step: int | None = None, n_boot: int = 0) -> dict:
    """Load a checkpoint's simulator and a Dataset (policies from ``zoo``, ``policy_file`` or
    the data's meta.source: ``zoo.policies_for``) and evaluate; no training data needed.
    Episodes and horizon default to the checkpoint's (``checkpoint_settings``); the report
    says which were used and where they came from (``horizon_source``, ``episodes_source``)."""

    _check_settings(n_episodes, horizon)
    ds = load_dataset(data_path)
    sim, meta = load_checkpoint(ckpt, step)  # the newest intact step unless step is given
    if ds.meta.get("task") != sim.task:
        raise ValueError(f"data: {data_path} is task {ds.meta.get('task')!r} but the "
                         f"checkpoint models {sim.task!r}")
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    settings = checkpoint_settings(meta.get("config") or {}, ds, n_episodes, horizon)
    report = evaluate_simulator(sim, ds, policies, key=jax.random.PRNGKey(seed),
                                n_episodes=settings["n_episodes"], horizon=settings["horizon"],
                                n_boot=n_boot)
    report.update(one_step_errors(sim, ds))
    report.update(checkpoint=ckpt, step=meta["step"], method=meta["config"]["method"],
                  data=data_path, seed=seed, backend=jax.default_backend(),
                  horizon_source=settings["horizon_source"],
                  episodes_source=settings["episodes_source"])
    return report


def evaluate_oracle_data(data_path: str, *, zoo: str | None = None,
                         policy_file: str | None = None, seed: int = 0,
                         n_episodes: int | None = None, horizon: int | None = None,
                         n_boot: int = 0) -> dict:
    """``evaluate_checkpoint`` with the task's real dynamics (``evaluate_oracle``): the control.
    Defaults: the data's episode_length and ``DEFAULT_EPISODES`` episodes."""
    _check_settings(n_episodes, horizon)
    ds = load_dataset(data_path)
    if ds.meta.get("task") not in TASKS:
        raise ValueError(f"oracle: {data_path} is data of no registered task (meta.task "
                         f"{ds.meta.get('task')!r}), so there are no real dynamics to run; "
                         f"its true values are in the data (rl2s evaluate --ckpt scores a "
                         f"simulator against them)")
    policies = policies_for(ds, zoo, policy_file=policy_file, data_path=data_path)
    report = evaluate_oracle(ds.meta.get("task"), ds, policies, key=jax.random.PRNGKey(seed),
                             n_episodes=n_episodes or DEFAULT_EPISODES, horizon=horizon,
                             n_boot=n_boot)
    report.update(method="oracle", data=data_path, seed=seed,
                  horizon_source=("--horizon" if horizon else "the data's episode_length"
                                  if ds.meta.get("episode_length") else "the default 1000"),
                  episodes_source=("--episodes" if n_episodes
                                   else f"the default {DEFAULT_EPISODES}"))
    return report


def format_report(r: dict) -> str:
    """A one-screen table of an evaluate report."""
    m = r["metrics"]
    what = ("the real dynamics (oracle)" if r.get("method") == "oracle"
            else f"{r.get('method', '?')} checkpoint step {r.get('step', '?')}")

    def source(key):
        return f" ({r[key]})" if key in r else ""
    head = [f"{what} on {r.get('data', '')}: {len(r['vd'])} policies, horizon {r['horizon']}"
            f"{source('horizon_source')}, {r['n_episodes']} episodes"
            f"{source('episodes_source')}, gamma {r['gamma']:g}",
            "  ".join(f"{k} {v:.3f}" for k, v in m.items())]
    if "heldout_nll" in r:
        head.append(f"one-step error on these {r['one_step_rows']} transitions: heldout_nll "
                    f"{r['heldout_nll']:.3f} nats (s' - s, data units), heldout_mse "
                    f"{r['heldout_mse']:.4f} (per dim, in this data's std of s' - s)")
    if "intervals" in r:
        iv = r["intervals"]
        head.append(f"{iv['level']:.0%} bootstrap intervals over {iv['n_episodes']} episodes: "
                    + "  ".join(f"{k} [{iv['metrics'][k]['lo']:.3f}, "
                                f"{iv['metrics'][k]['hi']:.3f}]"
                                for k in ("kendall_tau", "ndcg@1", "avd", "mvd")
                                if k in iv["metrics"])
                    + f"; evaluation noise alone moves tau by "
                      f"{iv['sim_only']['kendall_tau']['std']:.3f} (std)")
    rows = [f"{'policy':<14}{'true value':>12}{'sim value':>12}{'VD':>10}{'sim len':>9}"]
    for name, t, s, v, n in zip(r["policy_names"], r["true_value"], r["sim_value"], r["vd"],
                                r["sim_length"], strict=True):
        rows.append(f"{str(name):<14}{t:>12.2f}{s:>12.2f}{v:>10.2f}{n:>9.1f}")
    return "\n".join(head + rows)
