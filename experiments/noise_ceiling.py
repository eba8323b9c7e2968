"""How far evaluation noise alone keeps a task's ranking from tau 1 (issue 10, item 1).

Reads a paper.py result that ran the oracle over several seeds (``oracle_sim_value``: [S, P]
values of the real dynamics, each from ``eval_episodes`` simulated episodes, against
``true_value`` from ``value_episodes`` real ones) and prints:
- the oracle's tau against the truth per seed (as the protocol measures it);
- the oracle seeds' tau against each other: two exact simulators that differ only in their
  episodes, i.e. evaluation noise measured directly;
- the per-episode standard deviation of each policy's return, from the spread over seeds;
- ``evaluate.noise_ceiling``: the tau an exact simulator is expected to be measured at, for
  the run's episode counts and for larger ones, and the fewest episodes per side that bring
  the expected tau to --target.

    python experiments/noise_ceiling.py RESULT.json [--episodes 64,128,256,512,1024]
        [--pairs 16:32,...] [--target 0.9] [--n-rep 2000] [--json OUT.json]

(--pairs: other truth:simulator episode counts to evaluate, e.g. an earlier protocol's.)

Needs no GPU: the numbers come from the JSON.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from rl2s_jax._files import write_json  # noqa: E402
from rl2s_jax.evaluate.metrics import kendall_tau, noise_ceiling  # noqa: E402


def analyse(result: dict, episodes=(64, 128, 256, 512, 1024), target: float = 0.9,
            n_rep: int = 2000, pairs=()) -> dict:
    """The numbers this script prints, as a dict (see the module docstring)."""
    if "oracle_sim_value" not in result or "true_value" not in result:
        raise SystemExit("result: expected a paper.py JSON with the oracle row "
                         "('oracle_sim_value', 'true_value'); run paper.py without --no-oracle")
    sim = np.asarray(result["oracle_sim_value"], np.float64)
    truth = np.asarray(result["true_value"], np.float64)
    if sim.ndim != 2 or sim.shape[0] < 2 or sim.shape[1] != truth.size:
        raise SystemExit(f"oracle_sim_value: expected [S >= 2 seeds, P = {truth.size}], got "
                         f"{list(sim.shape)}; the spread over seeds needs two or more")
    sizes = result.get("sizes") or {}
    n_sim, n_truth = int(sizes["eval_episodes"]), int(sizes["value_episodes"])
    episode_sd = sim.std(0, ddof=1) * np.sqrt(n_sim)
    ceiling = lambda nt, ns: noise_ceiling(truth, episode_sd, n_truth=nt, n_sim=ns,
                                           n_rep=n_rep)
    run = ceiling(n_truth, n_sim)
    grid = {n: ceiling(n, n)["kendall_tau"] for n in episodes}
    enough = next((n for n in episodes if grid[n]["mean"] >= target), None)
    return {
        "task": result.get("task"), "source_command": result.get("command"),
        "n_truth_episodes": n_truth, "n_sim_episodes": n_sim, "seeds": sim.shape[0],
        "oracle_tau_per_seed": [kendall_tau(truth, s) for s in sim],
        "oracle_tau_seed_vs_seed": [kendall_tau(sim[i], sim[j])
                                    for i, j in itertools.combinations(range(len(sim)), 2)],
        "oracle_tau_pooled_seeds": kendall_tau(truth, sim.mean(0)),
        "episode_sd": episode_sd.tolist(),
        "ceiling_at_run": {k: run[k] for k in ("kendall_tau", "ndcg@1")},
        "ceiling_equal_episodes": {str(n): v for n, v in grid.items()},
        "ceiling_pairs": {f"{nt}:{ns}": ceiling(nt, ns)["kendall_tau"] for nt, ns in pairs},
        "target": target, "episodes_for_target": enough,
    }


def report(a: dict) -> str:
    f = lambda xs: ", ".join(f"{x:.3f}" for x in xs)
    c = a["ceiling_at_run"]["kendall_tau"]
    lines = [
        f"{a['task']}: truth from {a['n_truth_episodes']} episodes, oracle from "
        f"{a['n_sim_episodes']} per seed, {a['seeds']} seeds",
        f"  oracle tau vs truth per seed: {f(a['oracle_tau_per_seed'])}  (seeds pooled: "
        f"{a['oracle_tau_pooled_seeds']:.3f})",
        f"  oracle seed vs oracle seed:   {f(a['oracle_tau_seed_vs_seed'])}",
        f"  per-episode sd: median {np.median(a['episode_sd']):.0f}, "
        f"max {np.max(a['episode_sd']):.0f}",
        f"  expected tau of an exact simulator at these counts: {c['mean']:.3f} "
        f"[{c['lo']:.2f}, {c['hi']:.2f}]",
    ]
    for n, v in a["ceiling_equal_episodes"].items():
        lines.append(f"    {n:>5} episodes per side: {v['mean']:.3f} [{v['lo']:.2f}, "
                     f"{v['hi']:.2f}]")
    for pair, v in a.get("ceiling_pairs", {}).items():
        lines.append(f"    truth:simulator {pair} episodes: {v['mean']:.3f} [{v['lo']:.2f}, "
                     f"{v['hi']:.2f}]")
    e = a["episodes_for_target"]
    lines.append(f"  expected tau >= {a['target']}: "
                 + (f"{e} episodes per side" if e else "not within the counts tried"))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("result", help="a paper.py <task>.json with the oracle over >= 2 seeds")
    ap.add_argument("--episodes", default="64,128,256,512,1024",
                    help="comma list of episode counts per side to try")
    ap.add_argument("--pairs", default="", help="comma list of TRUTH:SIM episode counts")
    ap.add_argument("--target", type=float, default=0.9)
    ap.add_argument("--n-rep", type=int, default=2000)
    ap.add_argument("--json", help="also write the numbers here")
    args = ap.parse_args(argv)
    try:
        episodes = tuple(int(x) for x in args.episodes.split(",") if x.strip())
    except ValueError:
        raise SystemExit(f"episodes: expected a comma list of ints, got {args.episodes!r}"
                         ) from None
    if not episodes or min(episodes) < 1:
        raise SystemExit(f"episodes: expected counts >= 1, got {args.episodes!r}")
    try:
        pairs = tuple(tuple(int(n) for n in p.split(":")) for p in args.pairs.split(",")
                      if p.strip())
    except ValueError:
        raise SystemExit(f"pairs: expected TRUTH:SIM ints, got {args.pairs!r}") from None
    if any(len(p) != 2 or min(p) < 1 for p in pairs):
        raise SystemExit(f"pairs: expected TRUTH:SIM counts >= 1, got {args.pairs!r}")
    with open(args.result) as fh:
        a = analyse(json.load(fh), episodes, args.target, args.n_rep, pairs)
    print(report(a))
    if args.json:
        write_json(args.json, a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
