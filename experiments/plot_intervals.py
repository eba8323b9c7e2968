"""Issue 64's value intervals as a picture: per task, one lane's simulated against true values of
the test policies, each policy's conformal interval as a vertical bar, untrusted ones in red
(``app.report.plot_true_vs_sim``, the pipeline report's panel), from paper.py results.

    python experiments/plot_intervals.py \
        docs/results/data_seeds/{hopper,walker2d,halfcheetah,ant}_data23.json \
        --method rl2s --seed 0 --out docs/results/value_intervals_data23.png

One panel per result file, in the order given. ValueError (before drawing) when a file is not
a paper.py result with lane trust entries, or lacks the lane ``<method>/<seed>``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from rl2s_jax._files import save_figure  # noqa: E402
from rl2s_jax.app.report import plot_true_vs_sim  # noqa: E402


def lane_panel(result: dict, method: str, seed: int, path: str = "result") -> dict:
    """The evaluation dict ``plot_true_vs_sim`` draws from lane ``<method>/<seed>`` of a
    paper.py result: true and simulated values [P], the lane's tau, its "trust" entry as the
    "trust" block (policies with interval and trusted flag, level, coverage)."""
    lane = f"{method}/{seed}"
    for key in ("task", "true_value", "lanes", "test_policy_names"):
        if key not in result:
            raise ValueError(f"{path}: {key}: missing (expected a paper.py result)")
    entry = result["lanes"].get(lane)
    if entry is None:
        raise ValueError(f"{path}: lanes: no lane {lane!r} (has {sorted(result['lanes'])})")
    t = entry.get("trust") or {}
    if "interval" not in t:
        raise ValueError(f"{path}: lanes[{lane!r}].trust: no intervals "
                         f"({t.get('skipped', 'the run has no trust phase')})")
    names = result["test_policy_names"]
    pols = [{"name": n, "interval": iv, "trusted": ok}
            for n, iv, ok in zip(names, t["interval"], t["trusted"], strict=True)]
    per_seed = (result.get("per_seed") or {}).get(method, {}).get("kendall_tau")
    seeds = result.get("seed_ids") or list(range(len(per_seed or [])))
    tau = per_seed[seeds.index(seed)] if per_seed and seed in seeds else float("nan")
    return {"true_value": result["true_value"], "sim_value": t["sim_value"],
            "metrics": {"kendall_tau": tau},
            "trust": {"policies": pols, "level": t["level"], "coverage": t.get("coverage")}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", help="paper.py <task>.json files (one panel each)")
    ap.add_argument("--method", default="rl2s")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True, help="the PNG to write")
    args = ap.parse_args(argv)
    panels = []
    for path in args.results:
        with open(path) as f:
            result = json.load(f)
        panels.append((f"{result.get('task', '?')} {args.method}/{args.seed}",
                       lane_panel(result, args.method, args.seed, path)))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(3.4 * len(panels), 3.4), squeeze=False)
    for ax, (name, r) in zip(axes[0], panels, strict=True):
        plot_true_vs_sim(ax, name, r)
    axes[0][0].set_ylabel("simulated value")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    save_figure(fig, args.out, dpi=110)
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
