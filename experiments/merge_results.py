"""Assemble docs/results/<task>.json from the GPU runs of one zoo: the protocol
(experiments/paper.py), the oracle control (experiments/oracle_check.py) and the improvement
control (experiments/improve_control.py), each optional.

    python experiments/merge_results.py --task hopper [--paper P.json [--paper Q.json]]
        [--oracle O.json | --oracle-paper R.json] [--control C.json] [--out docs/results]

Several --paper files are runs of one protocol split over calls or GPUs on the same data:
other families (paper.py --families adversarial / mle) or other seeds (--first-seed K, e.g.
seeds 3-4 beside a run of seeds 0-2). paper.merge_runs joins them (a method's seeds in seed
order) and refuses runs of different sizes, zoo, data or training settings, a method's seed
in two runs, and methods left with different seeds.

The oracle's row with the most episodes at the longest horizon becomes the "oracle" method
(per_seed lists of one value, its bootstrap intervals) unless the paper run has its own; the
control's MPI/API and their 95% intervals become "control". --oracle-paper takes the oracle
row (per seed, intervals, noise ceiling) from another paper.py run that measured it with the
same test policies and episode counts (its own data collection: the ceiling of the protocol's
sizes, not of this run's draw), so a protocol split over calls need not measure it again.
zoo_sha256 is the shipped zoo's, checked against the paper run's when both exist.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def zoo_sha256(task: str) -> str:
    with open(os.path.join(ROOT, "rl2s_jax", "zoo", "shipped", task, "zoo.npz"), "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


ORACLE_SIZES = ("test_policies", "eval_episodes", "value_episodes", "episode_length")


def attach_paper_oracle(result: dict, path: str, sha: str) -> None:
    """Copy the oracle row of the paper.py run at ``path`` into ``result`` (in place); exits
    naming the field where that run's protocol differs from ``result``'s."""
    with open(path) as f:
        orc = json.load(f)
    if "oracle" not in orc.get("per_seed", {}):
        raise SystemExit(f"oracle-paper: {path} has no oracle row (run without --no-oracle)")
    if orc.get("task") != result.get("task"):
        raise SystemExit(f"oracle-paper: task {orc.get('task')!r}, expected "
                         f"{result.get('task')!r}")
    if orc.get("zoo_sha256") not in (None, sha):
        raise SystemExit(f"oracle-paper: measured on zoo {orc['zoo_sha256']}, the shipped zoo "
                         f"is {sha}")
    if "sizes" in result:
        for k in ORACLE_SIZES:
            if orc["sizes"].get(k) != result["sizes"].get(k):
                raise SystemExit(f"oracle-paper: sizes.{k} differs ({orc['sizes'].get(k)!r} "
                                 f"vs {result['sizes'].get(k)!r})")
    result["per_seed"]["oracle"] = orc["per_seed"]["oracle"]
    for k in ("methods", "std", "n"):
        if "oracle" in orc.get(k, {}):
            result.setdefault(k, {})["oracle"] = orc[k]["oracle"]
    result.setdefault("intervals", {})["oracle"] = orc.get("intervals", {}).get("oracle", {})
    if "noise_ceiling" in orc:
        result["noise_ceiling"] = orc["noise_ceiling"]
    result["oracle"] = {"source": orc.get("command"), "hardware": orc.get("hardware"),
                        "n_episodes": orc["sizes"].get("eval_episodes"),
                        "seeds": len(orc["per_seed"]["oracle"].get("kendall_tau", [])),
                        "metrics": orc["methods"].get("oracle"),
                        "data": "its own collection (another run)"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--paper", action="append", help="paper.py's <task>.json (repeat for "
                    "runs of other --families or --first-seed on the same data)")
    ap.add_argument("--oracle")
    ap.add_argument("--oracle-paper", help="paper.py's <task>.json of a run with the oracle, "
                    "same test policies and episode counts: its oracle row")
    ap.add_argument("--control")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "results"))
    args = ap.parse_args(argv)
    if args.oracle and args.oracle_paper:
        raise SystemExit("oracle, oracle-paper: expected at most one oracle source")
    sha = zoo_sha256(args.task)
    if args.paper:
        parts = []
        for p in args.paper:
            with open(p) as f:
                parts.append(json.load(f))
        if len(parts) == 1:
            result = parts[0]
        else:
            sys.path.insert(0, os.path.join(ROOT, "experiments"))
            from paper import merge_runs
            try:
                result = merge_runs(parts)
            except ValueError as err:
                raise SystemExit(f"paper: {err}") from None
        if result.get("zoo_sha256") not in (None, sha):
            raise SystemExit(f"paper: measured on zoo {result['zoo_sha256']}, the shipped zoo "
                             f"is {sha}")
    else:
        result = {"task": args.task, "methods": {}, "std": {}, "n": {}, "per_seed": {},
                  "note": "the protocol was not re-run on this zoo"}
    result["zoo_sha256"] = sha
    if args.oracle and "oracle" not in result.get("per_seed", {}):
        with open(args.oracle) as f:
            orc = json.load(f)
        row = max(orc["rows"], key=lambda r: (r["horizon"], r["n_episodes"]))
        result["per_seed"]["oracle"] = {k: [v] for k, v in row["metrics"].items()}
        result.setdefault("intervals", {})["oracle"] = (row.get("intervals") or {}).get(
            "metrics", {})
        if not args.paper:
            result.update(command=orc["command"], hardware=orc["hardware"], seeds=1,
                          jax_version=orc["jax_version"])
        result["oracle"] = {"source": orc["command"], "hardware": orc["hardware"],
                            "horizon": row["horizon"], "n_episodes": row["n_episodes"],
                            "policies": orc["policies"], "metrics": row["metrics"],
                            "eval_noise_tau_std": ((row.get("intervals") or {}).get(
                                "sim_only", {}).get("kendall_tau", {}).get("std"))}
    if args.oracle_paper and "oracle" not in result.get("per_seed", {}):
        attach_paper_oracle(result, args.oracle_paper, sha)
    if args.control:
        with open(args.control) as f:
            ctl = json.load(f)
        name, c = next(iter(ctl["configs"].items()))
        result["control"] = {"config": name, "seeds": ctl["seeds"],
                             "iterations": ctl["iterations"], "policies": len(ctl["zoo_ids"]),
                             "mpi": c["mpi"], "api": c["api"], "mpi_ci95": c["mpi_ci95"],
                             "api_ci95": c["api_ci95"], "c0": c["c0"], "c1": c["c1"],
                             "I": c["I"], "device": ctl["device"],
                             "paired": bool(c.get("paired"))}
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"{args.task}.json")
    with open(path, "w") as f:
        json.dump(result, f, indent=1)
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
