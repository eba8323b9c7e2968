"""Issue 39's summary of fine-tuning inside the learned simulators: per method, over the
seeds of ``experiments/paper.py`` runs with improvement (e.g. ``--first-seed K --seeds 1``; a
method may lack seeds), beside the task's real-env control (docs/results/<task>.json).

    python experiments/improvement_summary.py --task hopper --runs A.json B.json C.json
        [--control docs/results/hopper.json] [--out docs/results/improvement_in_sim]
        [--bootstrap 2000]

Per method: ``median_gain`` (``improve.finetune.median_gain``: median real gain I = (C1 -
C0) / |C0| of the test policies below the zoo's top quartile, averaged over the seeds, C0
paired with C1), raw (all deployed) and through the protocol's guard (a kept start gains 0),
per seed, and through a perfect guard (``median_gain_perfect_guard``: each policy deployed
exactly where it gains in reality, the most any guard could keep of the raw gain); MPI / API
raw and guarded (means over seeds), deployed count, ``budget_env_steps``, commands.
``paired``: RL2S's raw (and guarded) gain minus GAIL's and BC's (``stats.paired_gain_difference``:
per (seed, policy below the top quartile) and per seed). ``bars`` (--control): ``issue_bars``.
``guard_rules``: what other rules would have deployed, from the members' predicted gains:
"every member predicts a gain" and, on the lanes that recorded them, the "training-error range
floor" (``paper.improvement_phases.lane_error_range``) and the "discordant-pair floor"
(``paper.improvement_phases.pair_floor_verdict``), beside the protocol's guard (``lanes``: how many
(method, seed) lanes). They read the test policies' real gains: they explain the guard, they
must not choose it. ``controls``: the same median gain for the runs' own controls (``paper.py
--improve-oracle-seeds``: the oracle's physics; ``--control``: the real env with the runs'
SAC). ``on_control_policies`` (with ``--control``): each method's median gain on the policies
the task's control fine-tuned. Writes OUT/<task>.json (the runs, trimmed, and the summary),
OUT/<task>.png (each (seed, policy)'s real gain per method, deployments marked, the control's
median), a table. The control's median gain is recomputed on today's zoo (a grown zoo moves
its top quartile; ``median_gain_recorded``: its file's). Validation runs (``paper.py
--policy-split validation``) take no --control: their own controls compare.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from rl2s_jax._files import save_figure, write_json
from rl2s_jax.improve.finetune import median_gain
from rl2s_jax.paper.improvement_phases import pair_floor_verdict
from rl2s_jax.paper.tables import PAPER
from rl2s_jax.stats import paired_gain_difference
from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids

KEEP = ("task", "command", "hardware", "jax_version", "sizes", "seed_ids", "test_policy_names",
        "zoo_sha256", "sac_config", "improve_variant", "timings", "improvement",
        "oracle_improvement", "control", "train_true_value", "policy_split", "guard_rescored")
LANE_KEEP, PAIR_MARGIN = ("family", "sim_value", "train_sim_value"), 0.02  # the recipe's
MIN_SEEDS, CONTROL_BAR = 3, 0.30  # issue 39's bars: 3 seeds; the control's median gain


def zoo_ids(run: dict, ids: list[int]) -> list[int]:
    """The zoo ids of test policies ``ids`` of a paper.py result (from its
    ``test_policy_names``, "<task>-<zoo id>")."""
    names = run["test_policy_names"]
    return names_to_zoo_ids([names[i] for i in ids])


def lane_rows(run: dict, zoo_returns: np.ndarray) -> list[dict]:
    """One row per (method, seed) lane of a paper.py result with improvement: the start
    returns of its policies in the zoo, C0 (paired) and C1, the guard's verdicts and the
    members' predicted gains [M, P]."""
    rows = []
    for lane, e in run["improvement"].items():
        zid = zoo_ids(run, e["policy_ids"])
        pair = None  # the discordant-pair floor's verdict, where the range floor was recorded
        if "guard_floor_range" in e and lane in run.get("lanes", {}):
            pair = pair_floor_verdict(run, lane, e["guard_member_gain"], PAIR_MARGIN,
                                      e["policy_ids"], e.get("guard_member_start"))
        rows.append({"method": e["method"], "seed": e["seed"], "zoo_ids": zid,
                     "start": zoo_returns[zid],
                     "c0": np.asarray(e["c0_paired"], float),
                     "c1": np.asarray(e["c1"], float),
                     "accepted": np.asarray(e["guard_accepted"], bool),
                     "member_gain": (np.asarray(e["guard_member_gain"], float)
                                     if "guard_member_gain" in e else None),
                     "accepted_range": (np.asarray(e["guard_accepted_range"], bool)
                                        if "guard_accepted_range" in e else None),
                     "accepted_pair": pair})
    return rows


def plot(rows: list[dict], summary: dict, task: str, path: str) -> None:
    """Per method the real gain I of every (seed, policy) fine-tuned in its simulators (x: the
    policy's start return in the zoo; filled: deployed by the guard), on a symlog axis, with
    the control's median gain of the policies below the top quartile as a line."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(summary["methods"])
    fig, axes = plt.subplots(1, len(methods), figsize=(3.2 * len(methods), 3.2), sharey=True,
                             squeeze=False)
    ctl = (summary.get("control") or {}).get("median_gain")
    for ax, m in zip(axes[0], methods, strict=True):
        for r in (r for r in rows if r["method"] == m):
            gain = (r["c1"] - r["c0"]) / np.abs(r["c0"])
            ax.scatter(r["start"][~r["accepted"]], gain[~r["accepted"]], s=14,
                       facecolors="none", edgecolors="tab:blue")
            ax.scatter(r["start"][r["accepted"]], gain[r["accepted"]], s=18, c="tab:green")
        ax.axhline(0, color="0.6", lw=0.8)
        if ctl is not None:
            ax.axhline(ctl, color="tab:red", ls="--", lw=1, label=f"control median {ctl:+.2f}")
            ax.legend(fontsize=7, loc="upper right")
        s = summary["methods"][m]
        ax.set_title(f"{m}: median {s['median_gain_raw']:+.2f} raw, {s['deployed']} deployed",
                     fontsize=8)
        ax.set_yscale("symlog", linthresh=0.1), ax.set_xlabel("start return (zoo)", fontsize=8)
    axes[0][0].set_ylabel("real gain I (open: kept by the guard)", fontsize=8)
    fig.suptitle(f"{task}: fine-tuning inside the learned simulators", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def control_rows(runs: list[dict]) -> dict[str, list[tuple[list[int], list, list]]]:
    """The runs' own controls' (zoo ids, C0, C1) per seed: {"oracle_sim", "real_env"}."""
    rows = {"oracle_sim": [], "real_env": []}
    for run in runs:
        if "oracle_improvement" in run:
            oi = run["oracle_improvement"]
            rows["oracle_sim"] += [(zoo_ids(run, oi["policy_ids"]), p["c0_paired"], p["c1"])
                                   for p in oi["per_seed"]]
        if "control" in run:
            c = run["control"]
            rows["real_env"] += [(zoo_ids(run, c["policy_ids"]), a, b)
                                 for a, b in zip(c["c0"], c["c1"], strict=True)]
    return rows


def run_controls(runs: list[dict], zoo_returns: np.ndarray) -> dict:
    """The runs' own controls as {"oracle_sim" / "real_env": {"median_gain", "seeds",
    "median_gain_per_seed"}} (``median_gain`` of their C0 / C1 over all their seeds)."""
    out = {}
    for name, got in control_rows(runs).items():
        if not got:
            continue
        if len({tuple(z) for z, _, _ in got}) != 1:
            raise SystemExit(f"runs: the {name} controls fine-tuned different policies")
        start = zoo_returns[got[0][0]]
        c0, c1 = np.asarray([a for _, a, _ in got]), np.asarray([b for _, _, b in got])
        per_seed = [median_gain(a, b, start, zoo_returns)["median_gain"]
                    for a, b in zip(c0, c1, strict=True)]
        out[name] = {"median_gain": median_gain(c0, c1, start, zoo_returns)["median_gain"],
                     "seeds": len(got), "median_gain_per_seed": per_seed}
    return out


def on_control_policies(rows: list[dict], runs: list[dict], control: dict,
                        zoo_returns: np.ndarray) -> dict:
    """Every method's raw median gain and the runs' own controls' on the policies the task's
    control fine-tuned (``control["zoo_ids"]``), so that the gap to the control is read on the
    same policies: {"zoo_ids", "n_below", "control", <method>, "oracle_sim", "real_env"}."""
    keep = list(control["zoo_ids"])
    pick = lambda zid, x: np.asarray(x, np.float64)[[list(zid).index(i) for i in keep]]
    covers = lambda zid: set(keep) <= set(zid)
    out = {"zoo_ids": keep, "control": control.get("median_gain")}
    for m in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == m]
        if all(covers(r["zoo_ids"]) for r in mine):
            got = median_gain([pick(r["zoo_ids"], r["c0"]) for r in mine],
                              [pick(r["zoo_ids"], r["c1"]) for r in mine],
                              zoo_returns[keep], zoo_returns)
            out[m], out["n_below"] = got["median_gain"], got["n_below"]
    for name, got in control_rows(runs).items():
        if got and all(covers(z) for z, _, _ in got):
            out[name] = median_gain([pick(z, a) for z, a, _ in got],
                                    [pick(z, b) for z, _, b in got],
                                    zoo_returns[keep], zoo_returns)["median_gain"]
    return out


def summarise(rows: list[dict], zoo_returns: np.ndarray, n_boot: int) -> dict:
    """Per method: raw and guarded median gain (per seed and over seeds), MPI / API, deployed;
    the paired RL2S differences; the guard rules' counts. rows: ``lane_rows`` of every run."""
    out, gains, gains_g = {}, {}, {}
    for m in dict.fromkeys(r["method"] for r in rows):
        mine = sorted((r for r in rows if r["method"] == m), key=lambda r: r["seed"])
        c0 = np.stack([r["c0"] for r in mine])
        c1 = np.stack([r["c1"] for r in mine])
        dep = np.stack([np.where(r["accepted"], r["c1"], r["c0"]) for r in mine])
        start = mine[0]["start"]
        raw, guarded, perfect = (median_gain(c0, c, start, zoo_returns)
                                 for c in (c1, dep, np.maximum(c0, c1)))
        per_seed = [median_gain(a, b, start, zoo_returns)["median_gain"]
                    for a, b in zip(c0, c1, strict=True)]
        per_seed_g = [median_gain(a, b, start, zoo_returns)["median_gain"]
                      for a, b in zip(c0, dep, strict=True)]
        i_raw, i_dep = (c1 - c0) / np.abs(c0), (dep - c0) / np.abs(c0)
        below = np.asarray(raw["below"])
        seeds = [r["seed"] for r in mine]  # {seed: [policies below the top quartile]}
        gains[m] = dict(zip(seeds, i_raw[:, below], strict=True))
        gains_g[m] = dict(zip(seeds, i_dep[:, below], strict=True))
        out[m] = {"seeds": seeds, "policies": len(start), "n_below": raw["n_below"],
                  "median_gain_raw": raw["median_gain"], "median_gain_raw_per_seed": per_seed,
                  "median_gain": guarded["median_gain"], "median_gain_per_seed": per_seed_g,
                  "median_gain_perfect_guard": perfect["median_gain"],
                  "mpi_raw": float(i_raw.min(1).mean()), "api_raw": float(i_raw.mean(1).mean()),
                  "worst_raw": float(i_raw.min()),
                  "mpi": float(i_dep.min(1).mean()), "api": float(i_dep.mean(1).mean()),
                  "worst_deployed": float(i_dep.min()),
                  "deployed": int(sum(r["accepted"].sum() for r in mine)),
                  "lanes_x_policies": int(sum(len(r["accepted"]) for r in mine))}
    paired = {f"rl2s-{o}{sfx}": p for o in ("gail", "bc")  # over the seeds both ran
              for sfx, g in (("", gains), (" guarded", gains_g))
              if (p := paired_gain_difference(g.get("rl2s", {}), g.get(o, {}), n_boot))}
    rules = {}
    for m in out:
        mine = [r for r in rows if r["method"] == m and r["member_gain"] is not None]
        if not mine:
            continue
        real = np.concatenate([(r["c1"] - r["c0"]) / np.abs(r["c0"]) for r in mine])
        every = np.concatenate([(r["member_gain"] > 0).all(axis=0) for r in mine])
        prot = np.concatenate([r["accepted"] for r in mine])
        sels = [("protocol guard (training-MVD floor)", prot, len(mine)),
                ("every member predicts a gain", every, len(mine))]
        has = np.concatenate([np.full(len(r["accepted"]), r["accepted_range"] is not None)
                              for r in mine])
        for name, key in (("training-error range floor", "accepted_range"),
                          ("discordant-pair floor", "accepted_pair")):
            on = [r[key] is not None for r in mine]  # on the lanes that recorded it
            if any(on):
                sels.append((name, np.concatenate([
                    r[key] if r[key] is not None else np.zeros(len(r["accepted"]), bool)
                    for r in mine]), sum(on)))
        if has.any() and not has.all():  # the protocol guard on the range floor's lanes
            sels.append(("protocol guard on the range floor's lanes", prot & has,
                         sum(r["accepted_range"] is not None for r in mine)))
        rules[m] = {name: {"deployed": int(sel.sum()), "lanes": lanes,
                           "real_gain_median": (float(np.median(real[sel])) if sel.any()
                                                else None),
                           "real_gain_min": float(real[sel].min()) if sel.any() else None,
                           "worse_than_start": int((real[sel] < 0).sum())}
                    for name, sel, lanes in sels}
    return {"methods": out, "paired": paired, "guard_rules": rules}


def over_seeds_text(o: dict) -> str:
    """A paired entry's ``over_seeds`` as text: mean [t95] (per seed), or the one seed's."""
    per = " / ".join(f"{d:+.3f}" for d in o["per_seed"])
    return (f"{per} (one seed)" if o["mean"] is None else
            f"{o['mean']:+.3f} [{o['t95'][0]:+.3f}, {o['t95'][1]:+.3f}] ({per})")


def issue_bars(summary: dict, task: str) -> dict:
    """Issue 39's bars on this summary (with its ``control``): the control's median gain >=
    CONTROL_BAR; RL2S's guarded median gain >= half the control's, its guarded MPI >= 0 and API
    >= the paper's; RL2S's guarded median gain >= GAIL's and BC's, or the 95% interval of
    their paired guarded difference holds 0. Each {value, target, holds} (holds None: that
    method was not run); ``verdict`` "pass" / "fail", or why not yet (RL2S on fewer than
    MIN_SEEDS seeds, no control, a method not run)."""
    ctl, rl2s = (summary.get("control") or {}).get("median_gain"), summary["methods"].get("rl2s")
    if ctl is None or rl2s is None:
        return {"verdict": "no control or no rl2s lanes"}
    paper_api = PAPER["api"]["rl2s"].get(task)  # None: a task the paper has not (never holds)
    bars = {"control median gain": (ctl, CONTROL_BAR, ctl >= CONTROL_BAR),
            "rl2s median gain": (rl2s["median_gain"], ctl / 2, rl2s["median_gain"] >= ctl / 2),
            "rl2s mpi": (rl2s["mpi"], 0.0, rl2s["mpi"] >= 0),
            "rl2s api": (rl2s["api"], paper_api,
                         paper_api is not None and rl2s["api"] >= paper_api)}
    unrun = [m for m in ("gail", "bc") if m not in summary["methods"]]
    for other in ("gail", "bc"):
        if other in unrun:  # not run: the bar cannot be judged
            bars[f"rl2s >= {other}"] = (rl2s["median_gain"], None, None)
            continue
        theirs, pair = summary["methods"][other]["median_gain"], summary["paired"].get(
            f"rl2s-{other} guarded")
        tie = pair is not None and pair["ci95"][0] <= 0 <= pair["ci95"][1]
        bars[f"rl2s >= {other}"] = (rl2s["median_gain"], theirs,
                                    rl2s["median_gain"] >= theirs or tie)
    out = {k: {"value": v, "target": t, "holds": None if h is None else bool(h)}
           for k, (v, t, h) in bars.items()}
    n, held = len(rl2s["seeds"]), [b["holds"] for b in out.values()]
    out["verdict"] = (f"not enough seeds: {n} of {MIN_SEEDS}" if n < MIN_SEEDS else
                      "fail" if False in held else
                      f"incomplete: no {' or '.join(unrun)} lanes" if unrun else "pass")
    return out


def by_method(summary: dict, runs: list[dict], source: str) -> dict:
    """Issue 39's record for docs/results/<task>.json: for the control and each method its
    ``median_gain`` (guarded: deployed or kept), ``mpi``, ``api``, ``deployed`` and
    ``budget_env_steps``, with the commands of the runs that ran it, the bars' verdict and
    this summary's path."""
    keys = ("median_gain", "median_gain_raw", "median_gain_per_seed",
            "median_gain_perfect_guard", "mpi", "api", "deployed", "lanes_x_policies", "seeds")
    out = {"control": summary["control"]}
    out.update({m: {**{k: s[k] for k in keys}, "budget_env_steps": summary["budget_env_steps"],
                    "commands": [r["command"] for r in runs if any(
                        e["method"] == m for e in r["improvement"].values())]}
                for m, s in summary["methods"].items()})
    out["verdict"] = summary["bars"]["verdict"]
    out["source"] = source
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--runs", nargs="+", required=True, help="paper.py JSONs with improvement")
    ap.add_argument("--control", help="the task's docs/results JSON with 'control'")
    ap.add_argument("--out", default="docs/results/improvement_in_sim")
    ap.add_argument("--bootstrap", type=int, default=2000)
    ap.add_argument("--record", action="store_true",
                    help="also write improvement_by_method into the --control file")
    args = ap.parse_args(argv)
    if args.record and not args.control:
        ap.error("--record writes into the task's results JSON: give it as --control")
    runs = []
    for path in args.runs:
        with open(path) as f:
            run = json.load(f)
        if run.get("task") != args.task:
            raise SystemExit(f"runs: {path} is task {run.get('task')!r}, not {args.task!r}")
        if not run.get("improvement"):
            raise SystemExit(f"runs: {path} has no improvement (--improve-iterations 0?)")
        if run.get("policy_split", "zoo") != "zoo" and args.control:
            raise SystemExit(f"runs: {path} fine-tuned validation policies; the task's control "
                             "is the test policies' (their own: paper.py --control)")
        runs.append({k: run[k] for k in KEEP if k in run} | ({"lanes": {
            lane: {k: e[k] for k in LANE_KEEP if k in e}
            for lane, e in run["lanes"].items()}} if "lanes" in run else {}))
    lanes = [(e["method"], e["seed"]) for r in runs for e in r["improvement"].values()]
    if len(lanes) != len(set(lanes)) or len({r.get("policy_split") for r in runs}) > 1:
        raise SystemExit("runs: a (method, seed) lane appears twice, or --policy-split differs")
    zoo_returns = np.asarray(load_zoo(args.task).returns, np.float64)
    rows = [row for r in runs for row in lane_rows(r, zoo_returns)]
    summary = summarise(rows, zoo_returns, args.bootstrap)
    summary["controls"] = run_controls(runs, zoo_returns)
    sizes = runs[0]["sizes"]
    summary["budget_env_steps"] = sizes["improve_iterations"] * sizes["sac_envs"]
    summary["commands"] = [r["command"] for r in runs]
    summary["hardware"] = sorted({r.get("hardware", "") for r in runs})
    if args.control:
        with open(args.control) as f:
            doc = json.load(f)
        ctl, names = doc["control"], doc.get("test_policy_names")
        summary["control"] = {k: ctl.get(k) for k in ("median_gain", "mpi", "api", "deployed",
                                                      "seeds", "budget_env_steps", "command")}
        if ctl.get("zoo_ids") or names:  # older files: the first `policies` test names
            zid = summary["control"]["zoo_ids"] = ctl.get("zoo_ids") or zoo_ids(
                doc, range(ctl.get("policies", len(names))))
            if "c0" in ctl and "c1" in ctl:  # "below the top quartile" of today's zoo
                now = median_gain(ctl["c0"], ctl["c1"], zoo_returns[zid], zoo_returns)
                if not np.isclose(now["median_gain"], ctl.get("median_gain", np.nan)):
                    summary["control"]["median_gain_recorded"] = ctl.get("median_gain")
                summary["control"].update(median_gain=now["median_gain"],
                                          n_below=now["n_below"])
            summary["on_control_policies"] = on_control_policies(
                rows, runs, summary["control"], zoo_returns)
        summary["bars"] = issue_bars(summary, args.task)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"{args.task}.json")
    write_json(path, {"summary": summary, "runs": runs})
    plot(rows, summary, args.task, os.path.join(args.out, f"{args.task}.png"))
    if args.record:
        doc["improvement_by_method"] = by_method(summary, runs, path)
        write_json(args.control, doc)
    ctl = summary.get("control") or {}
    print(f"{args.task}: budget {summary['budget_env_steps']} simulated env steps per policy"
          + (f"; control median gain {ctl['median_gain']:+.3f}" if ctl.get("median_gain")
             is not None else ""))
    print(f"{'method':<8} {'raw median':>10} {'per seed':>22} {'guarded':>8} {'perfect':>8} "
          f"{'deployed':>9} {'MPI':>7} {'API':>7} {'worst raw':>9}")
    for m, s in summary["methods"].items():
        per = " / ".join(f"{g:+.2f}" for g in s["median_gain_raw_per_seed"])
        print(f"{m:<8} {s['median_gain_raw']:>+10.3f} {per:>22} {s['median_gain']:>+8.3f} "
              f"{s['median_gain_perfect_guard']:>+8.3f} {s['deployed']:>4}/"
              f"{s['lanes_x_policies']:<4} {s['mpi']:>+7.3f} {s['api']:>+7.3f} "
              f"{s['worst_raw']:>+9.3f}")
    for name, c in summary["controls"].items():
        print(f"{name:<8} {c['median_gain']:>+10.3f} (the runs' own control, {c['seeds']} seeds)")
    common = summary.get("on_control_policies")
    if common:
        print(f"on the control's {len(common['zoo_ids'])} policies ({common.get('n_below')} "
              "below the top quartile): " + ", ".join(
                  f"{k} {v:+.3f}" for k, v in common.items()
                  if k not in ("zoo_ids", "n_below") and v is not None))
    for k, v in summary["paired"].items():
        print(f"paired {k}: median {v['median']:+.3f} [{v['ci95'][0]:+.3f}, "
              f"{v['ci95'][1]:+.3f}]; RL2S higher in {v['rl2s_higher']} of {v['pairs']} "
              f"(seed, policy) pairs; over seeds " + over_seeds_text(v["over_seeds"]))
    for m, rules in summary["guard_rules"].items():
        print(f"guard rules {m}: " + "; ".join(f"{k} {r['deployed']} deployed, "
              f"{r['worse_than_start']} worse" for k, r in rules.items()))
    for k, b in summary.get("bars", {}).items():
        print(f"bar {k}: {b}" if k == "verdict" else
              f"bar {k}: {b['value']:+.3f} (target "
              f"{'n/a' if b['target'] is None else format(b['target'], '.3g')}) holds "
              f"{'n/a (not run)' if b['holds'] is None else b['holds']}")
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
