"""What processes sharing one GPU could gain, modelled from a measured profile (issue 63):
the protocol's tasks on one GPU one after another, two at once (``paper_schedule.py
--per-gpu 2``), and two at once staggered (a task starts only while no other is in its data
phase: the model found it slower, so the scheduler does not do it).

A model, not a measurement (its Hopper + HalfCheetah prediction, 845 s two at once, was
measured at 865 s: docs/BENCHMARKS.md, "Two processes on one GPU"). Each task is its profiled
segments in order (``gpu_profile.py``'s rows: a phase, or its logged parts where it has them;
the oracle and trust phases left out, as in the protocol the bar times), each with its wall
seconds w and busy GPU-seconds b. Alone a segment takes w and asks the GPU for b / w of its
time. Running together, segments whose asks sum to at most 1 all go at full speed (one computes
while the other waits on its host); above 1 each goes at ``efficiency`` / (the sum) of its
speed alone: time-sliced, the GPU's time split in proportion, less what switching costs (0.92:
two training processes measured by ``gpu_share.py``, BENCHMARKS "Two processes on one GPU").
The host's CPUs are taken to be enough for both (16 cores on a 1-GPU H200 machine; the
compilations may contend: unmodelled).

    python experiments/share_model.py docs/results/gpu_util_h200x4/profile.json
        [--tasks hopper,halfcheetah] [--efficiency 0.92] [--also 3,4] [--json OUT]

``--also 3,4``: rows for that many processes at once too (the same efficiency for any number
sharing, which only two have been measured at).
"""
from __future__ import annotations

import argparse
import json
import sys

COST_ORDER = ("ant", "halfcheetah", "walker2d", "hopper")  # paper_schedule's costliest first
SKIPPED = ("oracle", "trust")
DATA_PHASES = ("start", "data")  # the phases before paper.py's "[paper] data: " line


def task_segments(rows: list[dict]) -> list[dict]:
    """A run's profile rows -> its segments in order: {phase, wall_s, busy_gpu_s, data}
    (a phase's parts where it has them, the phase's own row where not; oracle and trust left
    out; ``data``: before the data line)."""
    with_parts = {r["phase"] for r in rows if r.get("part")}
    out = []
    for r in rows:
        phase = r["phase"].split(":")[0]
        if phase in SKIPPED or (r["phase"] in with_parts and not r.get("part")):
            continue
        out.append({"phase": r["phase"] + (f" / {r['part']}" if r.get("part") else ""),
                    "wall_s": float(r["wall_s"]), "busy_gpu_s": float(r["busy_gpu_s"] or 0.0),
                    "data": phase in DATA_PHASES})
    return [s for s in out if s["wall_s"] > 0]


def simulate(tasks: list[list[dict]], per_gpu: int, staggered: bool,
             efficiency: float = 0.92) -> dict:
    """The tasks (each a list of segments) on one GPU, ``per_gpu`` at a time, in the given
    order; ``staggered``: a task starts only while none running is in a data segment.
    -> {"total_s", "starts_s": [per task], "ends_s": [per task]}."""
    pending, running, t = list(range(len(tasks))), {}, 0.0  # running: task -> [seg, left]
    starts, ends = [None] * len(tasks), [None] * len(tasks)
    while pending or running:
        while pending and len(running) < per_gpu and not (staggered and any(
                tasks[k][s]["data"] for k, (s, _) in running.items())):
            k = pending.pop(0)
            running[k], starts[k] = [0, 1.0], t
        ask = {k: tasks[k][s]["busy_gpu_s"] / tasks[k][s]["wall_s"]
               for k, (s, _) in running.items()}
        total = sum(ask.values())
        rate = 1.0 if total <= 1.0 + 1e-12 else min(1.0, efficiency / total)
        # time until the first running segment ends (left: its fraction still to go)
        dt = min(left * tasks[k][s]["wall_s"] / rate for k, (s, left) in running.items())
        t += dt
        for k in list(running):
            s, left = running[k]
            left -= dt * rate / tasks[k][s]["wall_s"]
            if left <= 1e-9:
                s, left = s + 1, 1.0
            if s == len(tasks[k]):
                del running[k]
                ends[k] = t
            else:
                running[k] = [s, left]
    return {"total_s": t, "starts_s": starts, "ends_s": ends}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("profile", help="gpu_profile.py's --json output")
    ap.add_argument("--efficiency", type=float, default=0.92,
                    help="the GPU's share two time-sliced processes keep (measured 0.92)")
    ap.add_argument("--tasks", help="comma list: only these of the profile's tasks")
    ap.add_argument("--also", default="", help="comma list of more processes at once (3,4)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    if not 0.0 < args.efficiency <= 1.0:
        ap.error(f"--efficiency: expected a float in (0, 1], got {args.efficiency}")
    try:
        also = [int(x) for x in args.also.split(",") if x.strip()]
    except ValueError:
        also = [0]
    if any(k < 3 for k in also):
        ap.error(f"--also: expected a comma list of whole numbers >= 3, got {args.also!r}")
    runs = json.load(open(args.profile)).get("runs") or []
    by_task = {r["task"]: task_segments(r["rows"]) for r in runs if r.get("rows")}
    if not by_task:
        raise SystemExit(f"profile: expected 'runs' with 'rows' (gpu_profile.py --json) in "
                         f"{args.profile}, found none")
    if args.tasks:
        wanted = [t.strip() for t in args.tasks.split(",") if t.strip()]
        if not wanted or set(wanted) - set(by_task):
            raise SystemExit(f"tasks: expected a comma list of {', '.join(by_task)}, got "
                             f"{args.tasks!r}")
        by_task = {t: by_task[t] for t in wanted}
    names = [t for t in COST_ORDER if t in by_task] + [t for t in by_task if t not in COST_ORDER]
    tasks = [by_task[t] for t in names]
    out = {"tasks": names, "efficiency": args.efficiency,
           "alone_s": {t: sum(s["wall_s"] for s in by_task[t]) for t in names},
           "busy_gpu_s": {t: sum(s["busy_gpu_s"] for s in by_task[t]) for t in names}}
    for label, k, stag in (("one_after_another", 1, False), ("two_at_once", 2, False),
                           ("two_at_once_staggered", 2, True),
                           *((f"{k}_at_once", k, False) for k in also)):
        out[label] = simulate(tasks, k, stag, args.efficiency)
        print(f"{label:>22}: {out[label]['total_s']:7.1f} s", flush=True)
    print(f"{'busy GPU-s (the floor)':>22}: {sum(out['busy_gpu_s'].values()):7.1f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
