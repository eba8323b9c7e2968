"""RL2S's eps curve (issue 41, item 2: does a smaller eps lower the worst test-policy error?)
from the rows of docs/results/<task>_worst_case.json (experiments/worst_case_runs.py).

    python experiments/eps_curve.py [--tasks hopper walker2d halfcheetah ant]
        [--results docs/results] [--json docs/results/eps_curve.json]
        [--png docs/results/eps_curve.png] [--variant KEY=VALUE,...]

The curve's points: the rl2s rows grouped by eps, and the gail rows as the eps = 1 point (GAIL
is the eps = 1 lane of the same adversarial program; an rl2s point at eps 1 stays a separate
point). Other methods and the rows of other configurations are not on the curve: by default
the bars' (a null ``variant``), with --variant the rows of that worst_case_runs.py variant
(e.g. ``adv_nll_on=selected``, the anchor of the first eps lanes). Per point: n runs (a
rerun of a data seed and seed, worst_case_runs.py's ``rerun`` > 0, counts as a run of its own),
data seeds, median / max MVD over runs; mean MVD, mean Kendall tau and their 95% bootstrap
intervals (2000 replicates, numpy rng seed 0) over seeds, a (data seed, seed)'s reruns averaged
first (they share data and seed). ``paired_vs_0.25``: per other point, its MVD and tau minus
the eps 0.25 rl2s point's, paired within one run (data_seed, seed, rerun), averaged over a
seed's reruns: mean and 95% bootstrap interval over seeds, n pairs and n seeds (a negative MVD
difference: lower worst-case error than eps 0.25). ``rerun_noise``: per point with reruns, how
far a rerun's MVD lies from its first run's (the yardstick of run-to-run noise).
A missing task file is skipped; bad input stops with the file and field before anything is
written.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np

from rl2s_jax._files import save_figure, write_json
from rl2s_jax.stats import bootstrap_ci, mean_per_unit

TASKS = ("hopper", "walker2d", "halfcheetah", "ant")
DEFAULT_EPS, N_BOOT, GAIL = 0.25, 2000, "GAIL (eps 1)"
FIELDS = {"data_seed": int, "seed": int, "method": str, "eps": (int, float, type(None)),
          "mvd": (int, float, type(None)), "tau": (int, float, type(None))}


def _num(x) -> bool:
    return x is not None and math.isfinite(x)


def check_rows(doc, task: str, variant: str | None = None) -> list[dict]:
    """The curve's rows (rl2s, gail of ``variant``) of a worst_case file. ValueError naming
    the field."""
    if not isinstance(doc, dict) or not isinstance(doc.get("runs"), list):
        raise ValueError("no field 'runs' (a list of rows)")
    if doc.get("task", task) != task:
        raise ValueError(f"field 'task' is {doc['task']!r}, not {task!r}")
    rows, seen = [], set()
    for i, r in enumerate(doc["runs"]):
        if not isinstance(r, dict):
            raise ValueError(f"runs[{i}] is not an object")
        for k, typ in FIELDS.items():
            if k not in r:
                raise ValueError(f"runs[{i}] has no field {k!r}")
            if not isinstance(r[k], typ) or isinstance(r[k], bool):
                raise ValueError(f"runs[{i}] field {k!r}: bad value {r[k]!r}")
        rerun = r.get("rerun", 0)
        if not isinstance(rerun, int) or isinstance(rerun, bool) or rerun < 0:
            raise ValueError(f"runs[{i}] field 'rerun': bad value {rerun!r} (expected an int "
                             f">= 0)")
        if r["method"] == "rl2s" and r["eps"] is None:
            raise ValueError(f"runs[{i}] field 'eps': null for an rl2s row")
        if r["method"] == "gail" and r["eps"] not in (None, 1, 1.0):
            raise ValueError(f"runs[{i}] field 'eps': {r['eps']} for a gail row (expected 1)")
        if r["method"] not in ("rl2s", "gail") or r.get("variant") != variant:
            continue  # other methods, and other configurations (worst_case_runs.py's variant)
        key = (r["method"], r["eps"], r["data_seed"], r["seed"], rerun)
        if key in seen:
            raise ValueError(f"runs[{i}]: duplicate run (method, eps, data_seed, seed, rerun) "
                             f"{key}")
        seen.add(key)
        rows.append(r)
    return rows


def _ci(x: np.ndarray) -> list[float] | None:
    """95% bootstrap interval of the mean of x (N_BOOT replicates, rng seed 0)."""
    return bootstrap_ci(x, n_boot=N_BOOT, seed=0)


def _mean(x: np.ndarray) -> float | None:
    return float(x.mean()) if len(x) else None


def _by_seed(values: list[tuple[dict, float]]) -> np.ndarray:
    """[(row, value)] -> one value per (data_seed, seed): the mean over its reruns."""
    return mean_per_unit(((r["data_seed"], r["seed"]), v) for r, v in values)[0]


def curve(rows: list[dict]) -> list[dict]:
    """The points, sorted by eps (at equal eps rl2s before GAIL), each with its runs."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        gail = r["method"] == "gail"
        groups.setdefault((1.0 if gail else float(r["eps"]), gail), []).append(r)
    points = []
    for (eps, gail), runs in sorted(groups.items()):
        mvd = np.array([r["mvd"] for r in runs if _num(r["mvd"])], np.float64)
        mvd_u, tau_u = (_by_seed([(r, r[k]) for r in runs if _num(r[k])]) for k in ("mvd", "tau"))
        points.append({
            "label": GAIL if gail else f"rl2s eps {eps:g}", "method": "gail" if gail else "rl2s",
            "eps": eps, "n": len(runs), "n_seeds": len(mvd_u),
            "n_missing_mvd": len(runs) - len(mvd),
            "data_seeds": sorted({r["data_seed"] for r in runs}),
            "mean_mvd": _mean(mvd_u), "median_mvd": float(np.median(mvd)) if len(mvd) else None,
            "max_mvd": float(mvd.max()) if len(mvd) else None, "mean_tau": _mean(tau_u),
            "ci95_mean_mvd": _ci(mvd_u), "ci95_mean_tau": _ci(tau_u),
            "runs": [{"data_seed": r["data_seed"], "seed": r["seed"], "rerun": r.get("rerun", 0),
                      "mvd": r["mvd"], "tau": r["tau"]} for r in runs]})
    return points


def _run(r: dict) -> tuple:
    """The run a row is a lane of: (data_seed, seed, rerun) (worst_case_runs.pair_key)."""
    return (r["data_seed"], r["seed"], r.get("rerun", 0))


def paired(point: dict, base: dict) -> dict:
    """point minus base over the runs they share, (data_seed, seed, rerun), for MVD and tau,
    averaged over a seed's reruns (_by_seed): the mean and interval are over seeds."""
    out = {}
    for k in ("mvd", "tau"):
        b = {_run(r): r[k] for r in base["runs"] if _num(r[k])}
        pairs = [(r, r[k] - b[_run(r)]) for r in point["runs"] if _num(r[k]) and _run(r) in b]
        d = _by_seed(pairs)
        out[k] = {"n_pairs": len(pairs), "n_seeds": len(d), "mean_diff": _mean(d), "ci95": _ci(d)}
    return out


def rerun_noise(point: dict) -> dict | None:
    """A point's run-to-run noise: the MVD of each rerun (``rerun`` k > 0) minus its first run's
    (same data seed and seed): n pairs, mean and max |difference|, and the mean |difference|
    over the first runs' mean MVD. None without reruns."""
    first = {(r["data_seed"], r["seed"]): r["mvd"] for r in point["runs"]
             if r["rerun"] == 0 and _num(r["mvd"])}
    pairs = [(first[(r["data_seed"], r["seed"])], r["mvd"]) for r in point["runs"]
             if r["rerun"] > 0 and _num(r["mvd"]) and (r["data_seed"], r["seed"]) in first]
    if not pairs:
        return None
    a, b = np.array(pairs, np.float64).T
    d = np.abs(b - a)
    return {"n_pairs": len(d), "mean_abs_diff": float(d.mean()), "max_abs_diff": float(d.max()),
            "relative": float(d.mean() / a.mean())}


def _f(x, fmt=".1f") -> str:
    return "n/a" if x is None else format(x, fmt)


def _ci_s(ci, fmt=".1f") -> str:
    return "n/a" if ci is None else f"[{_f(ci[0], fmt)}, {_f(ci[1], fmt)}]"


def report(task: str, res: dict) -> str:
    pts, pair = res["points"], res[f"paired_vs_{DEFAULT_EPS}"]
    lines = [f"{task}: {sum(p['n'] for p in pts)} runs on the curve",
             f"{'point':<14} {'n':>3} {'data':<6} {'mean MVD':>9} {'95% CI':>18} {'median':>8} "
             f"{'max':>8} {'tau':>6} {'95% CI':>16}  vs 0.25: dMVD [95%]; dtau [95%] "
             "(pairs / seeds)"]
    for p in pts:
        d = pair.get(p["label"])
        if p["method"] == "rl2s" and p["eps"] == DEFAULT_EPS:
            vs = "base"
        elif d is None:
            vs = "no base"
        else:
            vs = (f"{_f(d['mvd']['mean_diff'], '+.1f')} {_ci_s(d['mvd']['ci95'])}; "
                  f"{_f(d['tau']['mean_diff'], '+.3f')} {_ci_s(d['tau']['ci95'], '.3f')} "
                  f"({d['mvd']['n_pairs']} / {d['mvd']['n_seeds']})")
        lines.append(f"{p['label']:<14} {p['n']:>3} {','.join(map(str, p['data_seeds'])):<6} "
                     f"{_f(p['mean_mvd']):>9} {_ci_s(p['ci95_mean_mvd']):>18} "
                     f"{_f(p['median_mvd']):>8} {_f(p['max_mvd']):>8} "
                     f"{_f(p['mean_tau'], '.3f'):>6} {_ci_s(p['ci95_mean_tau'], '.3f'):>16}  {vs}")
    for label, n in res.get("rerun_noise", {}).items():
        lines.append(f"rerun noise {label}: mean |MVD rerun - first run| {n['mean_abs_diff']:.1f} "
                     f"({100 * n['relative']:.0f}% of the first runs' mean), max "
                     f"{n['max_abs_diff']:.1f}, {n['n_pairs']} pairs")
    return "\n".join(lines)


def plot(tasks: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullLocator

    fig, axes = plt.subplots(2, len(tasks), figsize=(3.6 * len(tasks) + 0.6, 6.2),
                             squeeze=False)
    for j, (task, res) in enumerate(tasks.items()):
        pts = res["points"]
        ticks = sorted({p["eps"] for p in pts})
        for i, (k, ci, name) in enumerate((("mvd", "ci95_mean_mvd", "test MVD"),
                                           ("tau", "ci95_mean_tau", "Kendall tau"))):
            ax = axes[i][j]
            rl = [p for p in pts if p["method"] == "rl2s"]
            for p in pts:   # GAIL beside an rl2s point at eps 1
                shift = 1.08 if p["method"] == "gail" and any(q["eps"] == 1.0 for q in rl) else 1
                x, m = p["eps"] * shift, p[f"mean_{k}"]
                ys = [r[k] for r in p["runs"] if _num(r[k])]
                xd = x * (1.07 if shift > 1 else 0.93)   # the runs beside the error bar
                ax.plot([xd] * len(ys), ys, ".", color="0.55", ms=3, zorder=1,
                        label="run" if p is pts[0] else None)
                if m is None:
                    continue
                err = None if p[ci] is None else [[m - p[ci][0]], [p[ci][1] - m]]
                gail = p["method"] == "gail"
                ax.errorbar([x], [m], yerr=err, fmt="s" if gail else "o", capsize=3, zorder=2,
                            color="tab:red" if gail else "tab:blue",
                            label=GAIL if gail else ("RL2S mean, 95% CI"
                                                     if p is (rl or [None])[0] else None))
            if rl:
                ax.plot([p["eps"] for p in rl], [p[f"mean_{k}"] for p in rl], "-",
                        color="tab:blue", lw=1, zorder=1)
            ax.set_xscale("log")
            ax.set_xticks(ticks)
            seeds = {p["eps"]: p["data_seeds"] for p in pts if p["method"] == "rl2s"}
            mixed = len({tuple(v) for v in seeds.values()}) > 1   # points on other data
            ax.set_xticklabels([f"{e:g}" + (f"\nds {','.join(map(str, seeds.get(e, [])))}"
                                            if mixed and e in seeds else "") for e in ticks])
            ax.xaxis.set_minor_locator(NullLocator())
            ax.set_xlim(min(ticks) / 1.6, max(ticks) * 1.6)
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(f"{task} ({sum(p['n'] for p in pts)} runs)")
            else:
                ax.set_xlabel("eps (initial CVaR fraction)")
            if j == 0:
                ax.set_ylabel(name)
                if i == 0:
                    ax.legend(fontsize=7)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", nargs="+", default=list(TASKS))
    ap.add_argument("--results", default=os.path.join("docs", "results"))
    ap.add_argument("--json", default=os.path.join("docs", "results", "eps_curve.json"))
    ap.add_argument("--png", default=os.path.join("docs", "results", "eps_curve.png"))
    ap.add_argument("--variant", help="the rows of this worst_case_runs.py variant (default: "
                    "the bars' configuration)")
    args = ap.parse_args(argv)
    tasks = {}
    for task in args.tasks:
        path = os.path.join(args.results, f"{task}_worst_case.json")
        if not os.path.exists(path):
            print(f"{task}: no {path}, skipped")
            continue
        try:
            with open(path) as f:
                rows = check_rows(json.load(f), task, args.variant)
        except (OSError, ValueError) as err:
            raise SystemExit(f"{path}: {err}") from None
        if not rows:
            print(f"{task}: no rl2s or gail rows of variant {args.variant} in {path}, skipped")
            continue
        points = curve(rows)
        base = next((p for p in points if p["method"] == "rl2s" and p["eps"] == DEFAULT_EPS),
                    None)
        if base is None:
            print(f"{task}: no rl2s rows at eps {DEFAULT_EPS}, no paired differences")
        tasks[task] = {"points": points, f"paired_vs_{DEFAULT_EPS}": {
            p["label"]: paired(p, base) for p in points if base is not None and p is not base},
            "rerun_noise": {p["label"]: n for p in points if (n := rerun_noise(p))}}
    if not tasks:
        raise SystemExit(f"no curve: no {{task}}_worst_case.json with rl2s or gail rows under "
                         f"{args.results} for tasks {args.tasks}")
    for task, res in tasks.items():
        print(report(task, res) + "\n")
    cmd = " ".join(["python", "experiments/eps_curve.py",
                    *(sys.argv[1:] if argv is None else argv)])
    os.makedirs(os.path.dirname(args.json) or ".", exist_ok=True)
    write_json(args.json, {"command": cmd, "variant": args.variant, "tasks": tasks})
    plot(tasks, args.png)
    print(f"-> {args.json}, {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
