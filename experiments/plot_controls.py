"""One figure of the step-error controls (RESULTS@bf0c7b2: "The control of the open loop"):
how an unbiased step error of sigma x the one-step change std moves the REAL dynamics' 50-step
open-loop return (``open_loop_control.py``) and their closed-loop ranking
(``closed_loop_control.py``), per task, beside the learned models' own numbers where they were
measured (an ablation JSON with ``open_loop`` / ``visited_error``).

    python experiments/plot_controls.py --runs experiments/cpu_runs/2026-11-25 \
        [--model ant=experiments/gpu_runs/2026-11-25i/ant_visited/ablation_ant_rl2s.json ...]
        (several --model of one task are merged: one run's open loop, another's visited error)
        [--out docs/results/step_error_controls.png]
"""
from __future__ import annotations

import argparse
import glob
import json
import os

import numpy as np

from rl2s_jax._files import save_figure


def load_controls(root: str) -> tuple[dict, dict]:
    """{task: open-loop control JSON}, {task: closed-loop control JSON} found below root."""
    read = lambda pattern: {json.load(open(p))["task"]: json.load(open(p))
                            for p in sorted(glob.glob(os.path.join(root, "**", pattern),
                                                      recursive=True))}
    return read("open_loop_control_*.json"), read("closed_loop_control_*.json")


def open_loop_curve(res: dict, k: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """(sigma [S], mean relative k-step error over the seeds [S]) of an open-loop control."""
    scales = sorted(res["scales"], key=float)
    return (np.asarray([float(s) for s in scales]),
            np.asarray([np.mean(res["scales"][s][str(k)]["relative_error"]) for s in scales]))


def closed_loop_curve(res: dict, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(sigma [S], ``what`` of each scale against the exact run [S]), sigma 0 first (1 for tau
    and spread, 0 for the value change)."""
    scales = sorted(res["scales"], key=float)
    exact = {"tau_vs_exact": 1.0, "spread_ratio": 1.0, "relative_change": 0.0}[what]
    return (np.asarray([0.0] + [float(s) for s in scales]),
            np.asarray([exact] + [res["scales"][s][what] for s in scales]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", required=True, help="folder holding the control JSONs")
    ap.add_argument("--model", action="append", default=[], metavar="TASK=ABLATION_JSON",
                    help="a learned model's ablation JSON to mark (open loop at k = 50 and "
                    "its one-step error on visited states)")
    ap.add_argument("--out", default="docs/results/step_error_controls.png")
    args = ap.parse_args(argv)
    open_runs, closed_runs = load_controls(args.runs)
    if not open_runs and not closed_runs:
        raise SystemExit(f"runs: no open_loop_control_*.json or closed_loop_control_*.json "
                         f"below {args.runs!r}")
    models = {}
    for item in args.model:
        task, _, path = item.partition("=")
        if not (task and path and os.path.exists(path)):
            raise SystemExit(f"model: expected TASK=PATH of an existing ablation JSON, got "
                             f"{item!r}")
        models[task] = {**models.get(task, {}), **json.load(open(path))}  # several: merged

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_open, ax_closed) = plt.subplots(1, 2, figsize=(11, 4.2))
    floor = 1e-3  # sigma 0 drawn at this position of the log axis
    colors = dict(zip(sorted(set(open_runs) | set(closed_runs)),
                      plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False))
    for task, res in open_runs.items():
        s, err = open_loop_curve(res)
        ax_open.plot(np.maximum(s, floor), 100 * err, "o-", color=colors[task],
                     label=f"{task}: real dynamics + step error")
        ol = (models.get(task) or {}).get("open_loop", {}).get("50")
        if ol:
            ax_open.axhline(100 * np.mean(ol["relative_error"]), ls="--", color=colors[task],
                            label=f"{task}: learned model")
    ax_open.set(xscale="log", xlabel="step error sigma (x one-step change std; 0 at left)",
                ylabel="50-step return error under replayed actions (%)",
                title="Open loop: logged actions replayed")
    ax_open.legend(fontsize=8)
    for task, res in closed_runs.items():
        s, tau = closed_loop_curve(res, "tau_vs_exact")
        _, spread = closed_loop_curve(res, "spread_ratio")
        ax_closed.plot(np.maximum(s, floor), spread, "o-", color=colors[task],
                       label=f"{task}: value spread vs exact")
        ax_closed.plot(np.maximum(s, floor), tau, "s:", color=colors[task],
                       label=f"{task}: tau vs exact")
        ax_closed.axhline(res["exact_other_keys"]["tau_vs_exact"], ls="--", lw=0.8,
                          color=colors[task], label=f"{task}: tau of other episodes (noise)")
        ve = (models.get(task) or {}).get("visited_error")
        if ve:
            lo, hi = np.percentile(np.asarray(ve["visited"]["rmse"], np.float64), [25, 75])
            ax_closed.axvspan(lo, hi, color=colors[task], alpha=0.15,
                              label=f"{task}: learned model's step error (IQR)")
    ax_closed.set(xscale="log", xlabel="step error sigma (x one-step change std; 0 at left)",
                  ylabel="against the exact dynamics, same keys",
                  title=f"Closed loop: policies in the loop, "
                        f"{next(iter(closed_runs.values()))['episodes'] if closed_runs else ''}"
                        " episodes")
    ax_closed.legend(fontsize=7)
    fig.tight_layout()
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    save_figure(fig, args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
