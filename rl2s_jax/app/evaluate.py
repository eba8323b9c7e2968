"""`rl2s evaluate`: a checkpoint (or the oracle) scored on a Dataset file."""

from __future__ import annotations

import jax

from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.evaluate.simulator import evaluate_simulator, one_step_errors
from rl2s_jax.train.checkpoint import load_checkpoint
from rl2s_jax.zoo.zoo import policies_for


def evaluate_checkpoint(ckpt: str, data_path: str, *, zoo: str | None = None, seed: int = 0,
                        n_episodes: int = 16, horizon: int | None = None, step: int | None = None,
                        n_boot: int = 0) -> dict:
    """Load a checkpoint's simulator and a Dataset (policies from ``zoo`` or the data's
    meta.source) and evaluate; no training data needed."""

    ds = load_dataset(data_path)
    sim, meta = load_checkpoint(ckpt, step)  # the newest intact step unless step is given
    if ds.meta.get("task") != sim.task:
        raise ValueError(f"data: {data_path} is task {ds.meta.get('task')!r} but the "
                         f"checkpoint models {sim.task!r}")
    report = evaluate_simulator(sim, ds, policies_for(ds, zoo), key=jax.random.PRNGKey(seed),
                                n_episodes=n_episodes, horizon=horizon, n_boot=n_boot)
    report.update(one_step_errors(sim, ds))
    report.update(checkpoint=ckpt, step=meta["step"], method=meta["config"]["method"],
                  data=data_path, seed=seed, backend=jax.default_backend())
    return report


def format_report(r: dict) -> str:
    """A one-screen table of an evaluate report."""
    m = r["metrics"]
    head = [f"{r.get('method', '?')} checkpoint step {r.get('step', '?')} on {r.get('data', '')}"
            f" ({len(r['vd'])} policies, {r['n_episodes']} episodes x {r['horizon']} steps)",
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
