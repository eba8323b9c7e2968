"""Issue 39's guard, calibrated on held-out training policies: the deployment guard with its
floor scaled, floor = k x the lane's training MVD, read offline on the elite members' recorded
predictions, with k chosen on runs of ``paper.py --policy-split validation`` (the simulators
learned from the "fit" policies, the "validation" policies fine-tuned) and then read on the
test policies' runs.

    python experiments/guard_calibration.py --task walker2d --validation V1.json [V2.json ...]
        --test T1.json [T2.json ...] [--scales 0,0.25,0.5,0.75,1] [--margin 0.02]
        [--out docs/results/guard_calibration] [--rescore DIR]

A lane's verdict at scale k is ``finetune.deployment_guard`` on its members' start values
(``guard_member_start``) and their predicted gains (``guard_member_gain``), both [M, P], with
margin ``--margin`` (the recipe's, ``improve.recipes``) and floor k x the lane's training MVD
(``guard_training_mvd``; before it was recorded, ``guard_floor``, at scale 1); the real gain of
a policy is I = (C1 - C0) / |C0| with C0 paired. The rule, set before any validation run: **k
is the smallest scale of the grid whose deployments on the validation runs (every method's
lanes pooled: the floor is the guard's, not a method's) include no real loss (I < 0); none
such: 1, the protocol's guard.** Amended at stop 59, before any validation run (the original
picks 0 when nothing deploys at any scale, and a scale that deploys nothing more than a larger
one on validation has no evidence for it): **of the scales that deploy as many on validation as
that smallest one, the largest** (no deployment at all: 1). On the test runs each scale reports
per method its deployed count, losses and guarded median gain (``finetune.median_gain``: kept
policies gain 0); the chosen scale's are the result. Writes OUT/<task>.json, OUT/<task>.png
(per split and method, deployed and lost policies against k, the chosen k marked) and prints a
table. ``--rescore DIR``: each test run again as DIR/<its name> (DIR/<i>_<its name>, i its
place in --test, where two share a name), its lanes' guard verdicts at the chosen k
(``guard_accepted``, ``guard_floor``, ``guard_floor_scale``; the verdicts it had dropped), for
``improvement_summary.py --record`` once a recipe takes k.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from rl2s_jax._files import save_figure, write_json
from rl2s_jax.improve.finetune import deployment_guard, median_gain
from rl2s_jax.improve.recipes import IMPROVE_RECIPES
from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids

SCALES = (0.0, 0.25, 0.5, 0.75, 1.0)
RULE = ("the smallest scale whose validation deployments (all methods pooled) include no real "
        "loss, then the largest scale deploying as many; no deployment or none such: 1")


def lanes_of(run: dict, path: str) -> list[dict]:
    """The guarded lanes of one paper.py result: per lane its method, seed, zoo ids, C0
    (paired), C1, members' start values and predicted gains [M, P] and training-MVD floor.
    SystemExit naming the file where a lane lacks what the guard read."""
    names = run["test_policy_names"]
    out = []
    for lane, e in run["improvement"].items():
        missing = [k for k in ("guard_member_gain", "guard_member_start", "guard_floor")
                   if k not in e]
        if missing:
            raise SystemExit(f"runs: {path} lane {lane} has no {', '.join(missing)} (a run "
                             "with --guard-margin, since the guard kept its members' starts)")
        out.append({"method": e["method"], "seed": e["seed"],
                    "zoo_ids": names_to_zoo_ids([names[i] for i in e["policy_ids"]]),
                    "c0": np.asarray(e["c0_paired"], np.float64),
                    "c1": np.asarray(e["c1"], np.float64),
                    "start": np.asarray(e["guard_member_start"], np.float64),
                    "gain": np.asarray(e["guard_member_gain"], np.float64),
                    "floor": float(e.get("guard_training_mvd", e["guard_floor"]))})
    return out


def load_runs(paths: list[str], task: str, split: str) -> tuple[list[dict], list[dict]]:
    """Every lane of the runs, each run checked to be ``task``'s on ``split``
    ("validation" or "zoo": paper.py --policy-split), and per run where it came from (its
    path, the command that made it and its device)."""
    lanes, sources = [], []
    for path in paths:
        with open(path) as f:
            run = json.load(f)
        if run.get("task") != task or run.get("policy_split", "zoo") != split:
            raise SystemExit(f"runs: {path} is task {run.get('task')!r} on the "
                             f"{run.get('policy_split', 'zoo')!r} split; expected {task!r} on "
                             f"{split!r}")
        if not run.get("improvement"):
            raise SystemExit(f"runs: {path} has no improvement (--improve-iterations 0?)")
        lanes += lanes_of(run, path)
        sources.append({"path": path, "command": run.get("command"),
                        "device": (run.get("machine") or {}).get("device")})
    keys = [(r["method"], r["seed"]) for r in lanes]
    if len(keys) != len(set(keys)):
        raise SystemExit(f"runs: a (method, seed) lane appears twice among {split} runs")
    return lanes, sources


def verdicts(lanes: list[dict], scale: float, margin: float) -> list[np.ndarray]:
    """Per lane [P] bool: the guard with floor ``scale`` x its training MVD."""
    return [deployment_guard(r["start"], r["start"] + r["gain"], margin, scale * r["floor"])
            for r in lanes]


def read_scale(lanes: list[dict], scale: float, margin: float, zoo_returns) -> dict:
    """Per method at one scale: deployed, real losses among them, lanes x policies, and (with
    ``zoo_returns``) the guarded median gain over the seeds."""
    out = {}
    for m in dict.fromkeys(r["method"] for r in lanes):
        mine = sorted((r for r in lanes if r["method"] == m), key=lambda r: r["seed"])
        acc = verdicts(mine, scale, margin)
        gain = [(r["c1"] - r["c0"]) / np.abs(r["c0"]) for r in mine]
        row = {"deployed": int(sum(a.sum() for a in acc)),
               "losses": int(sum((a & (g < 0)).sum() for a, g in zip(acc, gain, strict=True))),
               "lanes_x_policies": int(sum(a.size for a in acc)), "seeds": len(mine)}
        if zoo_returns is not None:
            dep = np.stack([np.where(a, r["c1"], r["c0"]) for a, r in zip(acc, mine,
                                                                           strict=True)])
            row["median_gain"] = median_gain(np.stack([r["c0"] for r in mine]), dep,
                                             zoo_returns[mine[0]["zoo_ids"]],
                                             zoo_returns)["median_gain"]
        out[m] = row
    return out


def rescore(path: str, scale: float, margin: float, dest: str) -> str:
    """Test run ``path`` with its lanes' guard at floor ``scale`` x the training MVD (what
    ``improvement_summary`` reads), written to dest; its deployed-only figures, read at the
    run's own floor, are dropped. -> dest."""
    with open(path) as f:
        run = json.load(f)
    rows = lanes_of(run, path)  # in run["improvement"]'s order
    for e, r, acc in zip(run["improvement"].values(), rows, verdicts(rows, scale, margin),
                         strict=True):
        e.update(guard_accepted=acc.tolist(), guard_training_mvd=r["floor"],
                 guard_floor=scale * r["floor"], guard_floor_scale=scale)
        for k in ("I_deployed", "mpi_deployed", "api_deployed"):
            e.pop(k, None)
    run["guard_rescored"] = {"scale": scale, "margin": margin, "from": path,
                             "by": "experiments/guard_calibration.py"}
    run["command"] = run.get("command", "?") + (
        f"; guard verdicts rescored at floor {scale:g} x the training MVD, margin {margin:g} "
        "(experiments/guard_calibration.py --rescore)")
    write_json(dest, run)
    return dest


def choose_scale(by_scale: dict) -> float:
    """RULE: the smallest scale whose validation deployments (all methods) lose nothing, then
    the largest scale that deploys as many (a lower floor that deploys nothing more on
    validation has no evidence for it: with no deployments at all, 1); none: 1 (the
    protocol's guard). A larger floor deploys a subset, so the loss-free scales are the top
    of the grid."""
    total = {k: [sum(r[q] for r in by_scale[k]["validation"].values())
                 for q in ("deployed", "losses")] for k in by_scale}
    safe = [k for k in sorted(by_scale) if total[k][1] == 0]
    if not safe:
        return 1.0
    most = total[safe[0]][0]
    return 1.0 if most == 0 else max(k for k in safe if total[k][0] == most)


def plot(by_scale: dict, chosen: float, task: str, path: str) -> None:
    """Per split (validation, test) one panel: each method's deployed count against the floor
    scale k (solid) and its real losses among them (dashed, crosses), the chosen k marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scales = sorted(by_scale)
    splits = [s for s in ("validation", "test") if s in by_scale[scales[0]]]
    fig, axes = plt.subplots(1, len(splits), figsize=(4.2 * len(splits), 3.2), squeeze=False)
    for ax, split in zip(axes[0], splits, strict=True):
        for n, m in enumerate(by_scale[scales[0]][split]):
            color = f"C{n}"
            rows = [by_scale[k][split][m] for k in scales]
            ax.plot(scales, [r["deployed"] for r in rows], "o-", color=color, label=m)
            ax.plot(scales, [r["losses"] for r in rows], "x--", color=color)
        ax.axvline(chosen, color="0.5", lw=0.8, ls=":", label=f"chosen k {chosen:g}")
        ax.set_xlabel("floor scale k (x the lane's training MVD)", fontsize=8)
        ax.set_title(f"{split}: deployed (solid), real losses (dashed)", fontsize=8)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("(seed, policy) pairs", fontsize=8)
    fig.suptitle(f"{task}: the guard's floor, calibrated on held-out training policies",
                 fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--validation", nargs="+", required=True,
                    help="paper.py --policy-split validation JSONs (guarded, fine-tuned)")
    ap.add_argument("--test", nargs="*", default=[], help="paper.py JSONs of the test policies")
    ap.add_argument("--scales", default=",".join(f"{k:g}" for k in SCALES))
    ap.add_argument("--margin", type=float,
                    default=IMPROVE_RECIPES["control"]["guard_margin"])
    ap.add_argument("--out", default="docs/results/guard_calibration")
    ap.add_argument("--rescore", metavar="DIR", help="write the test runs at the chosen k")
    args = ap.parse_args(argv)
    try:
        scales = sorted({float(x) for x in args.scales.split(",") if x.strip()})
    except ValueError:
        scales = []
    if not scales or not all(np.isfinite(k) and k >= 0 for k in scales):
        raise SystemExit(f"scales: expected a comma list of floats >= 0, got {args.scales!r}")
    if not (np.isfinite(args.margin) and args.margin >= 0):
        raise SystemExit(f"margin: expected a finite float >= 0, got {args.margin}")
    val, val_sources = load_runs(args.validation, args.task, "validation")
    test, test_sources = load_runs(args.test, args.task, "zoo") if args.test else ([], [])
    zret = np.asarray(load_zoo(args.task).returns, np.float64)
    by_scale = {k: {"validation": read_scale(val, k, args.margin, zret),
                    **({"test": read_scale(test, k, args.margin, zret)} if test else {})}
                for k in scales}
    chosen = choose_scale(by_scale)
    doc = {"task": args.task, "margin": args.margin, "scales": scales, "chosen_scale": chosen,
           "rule": RULE,
           "by_scale": {f"{k:g}": v for k, v in by_scale.items()},
           "command": "python experiments/guard_calibration.py " + " ".join(
               sys.argv[1:] if argv is None else argv),
           "validation_runs": val_sources, "test_runs": test_sources}
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"{args.task}.json")
    write_json(path, doc)
    plot(by_scale, chosen, args.task, os.path.join(args.out, f"{args.task}.png"))
    for k, parts in by_scale.items():
        for split, rows in parts.items():
            print(f"k {k:<5g} {split:<10} " + "; ".join(
                f"{m} {r['deployed']}/{r['lanes_x_policies']} deployed, {r['losses']} lost, "
                f"median {r['median_gain']:+.3f}" for m, r in rows.items()))
    print(f"chosen scale {chosen:g} (the rule: {doc['rule']}) -> {path}")
    if args.rescore and args.test:
        names = [os.path.basename(p) for p in args.test]
        if len(set(names)) < len(names):  # paper.py names every run <task>.json
            names = [f"{i}_{n}" for i, n in enumerate(names)]
        os.makedirs(args.rescore, exist_ok=True)
        for p, name in zip(args.test, names, strict=True):
            dest = rescore(p, chosen, args.margin, os.path.join(args.rescore, name))
            print(f"rescored at k {chosen:g} -> {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
