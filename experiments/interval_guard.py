"""Issue 64 item 3 read offline: the interval guard (``improve.gain_intervals``: deploy where
the lower end of the predicted relative gain's conformal interval is above 0) beside the floor
guard the runs used, on paper.py results that recorded the members' predicted gains
(``--guard-margin``), with no validation runs: the fine-tuned policies are split in two by zoo
id and each half's verdicts are calibrated on the other half's real gains (all lanes pooled;
``paper.trust_phase.crossfit_interval_guard``). ``paper.py --guard-calibration`` is the
protocol's version, calibrated on fine-tuned validation policies.

    python experiments/interval_guard.py --task ant --runs R.json [R2.json ...]
        [--level 0.9] [--out OUT.json]

A file is a paper.py result or a bundle {"runs": [results], "summary": {"control": ...}}
(docs/results/improvement_*/<task>.json). Prints per guard and method the deployed count,
the real losses among them, the guarded median gain (``finetune.median_gain``, kept policies
at C0), MPI (kept at 0) and the real-env control's median gain where the bundle has it.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from rl2s_jax._files import write_json
from rl2s_jax.paper.trust_phase import crossfit_interval_guard, guard_block
from rl2s_jax.zoo.zoo import load_zoo, names_to_zoo_ids


def load_entries(paths: list[str], task: str) -> tuple[list[dict], list[str], dict | None]:
    """Every lane entry of the runs (with "zoo_ids"), the test policy names, the control."""
    entries, names, control = [], None, None
    for path in paths:
        with open(path) as f:
            data = json.load(f)
        runs = data["runs"] if "runs" in data else [data]
        control = control or (data.get("summary") or {}).get("control") or data.get("control")
        for run in runs:
            if run.get("task") != task or run.get("policy_split", "zoo") != "zoo":
                raise SystemExit(f"runs: {path} holds a {run.get('task')!r} run on the "
                                 f"{run.get('policy_split', 'zoo')!r} split; expected {task!r}")
            names = names or run["test_policy_names"]
            for lane, e in (run.get("improvement") or {}).items():
                if "guard_member_gain" not in e:
                    raise SystemExit(f"runs: {path} lane {lane} has no guard_member_gain")
                ids = names_to_zoo_ids([run["test_policy_names"][i] for i in e["policy_ids"]])
                entries.append({**e, "zoo_ids": ids})
    if not entries:
        raise SystemExit("runs: no fine-tuned lanes")
    return entries, names, control


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--level", type=float, default=0.9)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    entries, names, control = load_entries(args.runs, args.task)
    cross = crossfit_interval_guard(entries, args.level)
    zret = np.asarray(load_zoo(args.task).returns, np.float64)
    out = {"task": args.task, "level": args.level, "crossfit": cross, "runs": args.runs,
           "command": " ".join(["python", "experiments/interval_guard.py", *(argv or
                                                                             sys.argv[1:])])}
    print(f"{args.task}: interval guard at level {args.level}, q per fold "
          f"{[None if q is None else round(q, 3) for q in cross['q']]} from "
          f"{cross['n']} calibration points (scale: {cross['scale']})")
    for kind, key in (("floor", "guard_accepted"), ("interval", "guard_accepted_interval")):
        out[kind] = {}
        for m in dict.fromkeys(e["method"] for e in entries):
            es = [e for e in entries if e["method"] == m]
            b = guard_block(es, [e[key] for e in es], zret, names, None)
            if control and control.get("median_gain") is not None:
                b["control_median_gain"] = control["median_gain"]
            out[kind][m] = b
            print(f"  {kind:<8} {m:<8} deployed {b['deployed']:>3} of {b['lanes_x_policies']}"
                  f" ({b['deployed_losses']} lose)  median gain {b['median_gain']:+.3f}  MPI "
                  f"{b['mpi']:+.3f}  control median gain {b['control_median_gain']}")
    if args.out:
        write_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
