"""`make paper`'s scheduler (run by experiments/paper_all.sh): experiments/paper.py's units of
work over the GPUs of one host, one process per GPU at a time, and the wall time of each.

    python3 experiments/paper_schedule.py --out OUT --data-dir DIR --gpus N --py "PY"
        --tasks "hopper walker2d halfcheetah ant" [-- paper.py args]

With two GPUs or more a unit is one (task, family) pair (``paper.py --families F``, out dir
OUT/units/<task>_<family>/, log OUT/paper_<task>_<family>.log). The units wait in one queue,
costliest first (COST: one H100's measured seconds), and a GPU that comes free takes the first
unit that is ready. A task's data is collected once: its first unit in the queue (the
adversarial one) collects it into --data-dir, with the oracle and ``--control`` if asked; its
other units run with ``--no-oracle`` and without ``--control`` and are ready only once that
unit has printed ``[paper] data: `` (or has ended, when it failed before that: then the next
one collects, with the oracle and ``--control``). As soon as all of a task's units have
ended, and they all succeeded, the task is merged into OUT/<task>.json by
experiments/merge_results.py (log OUT/merge_<task>.log; in a thread, beside the units still
running), the collecting unit's file first so its oracle row is kept.

``--units task`` (or PAPER_UNITS=task) makes a whole task the unit on any number of GPUs,
costliest first: both families in one paper.py, so that the likelihood family's BC lanes
continue from the adversarial family's pre-training (docs/SCALING.md). ``--units family``
forces the pairs. The default, ``auto``, takes whole tasks when there are at least as many
GPUs as tasks but fewer than twice as many (one task per GPU: 584 s against 622 s for the
pairs on 4x H200, docs/BENCHMARKS.md), and the pairs otherwise (with fewer GPUs than tasks,
or with enough GPUs for every family to have its own).

With one GPU or none, a unit is a whole task (both families in one paper.py, OUT/<task>.json,
log OUT/paper_<task>.log, also shown here; splitting would only add a process start and the
data's reload per task): on one GPU two at a time by default (``--per-gpu`` below), without
a GPU one after another. With one GPU, CUDA_VISIBLE_DEVICES=0. GPU k is
the k-th of an inherited CUDA_VISIBLE_DEVICES where one is set (a run pinned to GPUs 1 and 2
schedules over those), else GPU k of the machine.

``--per-gpu K`` (or PAPER_PER_GPU=K): K processes share each GPU at once, each with 1/K of
the memory fraction, costliest first: a task's idle phases (data collection, compilation,
37% of the protocol's GPU time: docs/BENCHMARKS.md, "Where one task's GPU-seconds go") run
beside another's training. The default, ``auto``, is 2 on one GPU with two tasks or more, else
1. Measured on one H200 (docs/BENCHMARKS.md, "Two processes on one GPU"): Hopper and
HalfCheetah two at once 865 s against 1,103 s one after another, every result the same bit for
bit (each process runs the same programs as alone); experiments/share_model.py, which
predicted 845 s, models the four tasks at 1,749 s against 2,300.

At the end: every unit's task, family, GPU, start and wall seconds (and when its data phase
ended, seconds after its start), the merges, each GPU's busy seconds and the total, printed
and written to OUT/schedule.json. A failed unit does not stop the others; the script
then exits 1 naming each failed unit and its log. Standard library only (``python3``).
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import shlex
import subprocess
import sys
import threading
import time

FAMILIES = ("adversarial", "mle")
DATA_LINE = "[paper] data: "
# Seconds of one task's family on one H100 at the gpu profile (3 seeds, no improvement): the
# per_task "seconds" of docs/results/scaling.json (c08578d); adversarial includes the data
# collection, mle reused it. Only their order matters here (longest first).
COST = {"hopper": {"adversarial": 467, "mle": 200},
        "walker2d": {"adversarial": 487, "mle": 197},
        "halfcheetah": {"adversarial": 490, "mle": 197},
        "ant": {"adversarial": 498, "mle": 219}}
DEFAULT_COST = {"adversarial": 480, "mle": 200}


def split_families(args: list[str]) -> tuple[list[str], list[str]]:
    """paper.py args -> (the families of their --families, default both, in FAMILIES' order;
    the args without it)."""
    rest, text, i = [], ",".join(FAMILIES), 0
    while i < len(args):
        if args[i] == "--families" and i + 1 < len(args):
            text, i = args[i + 1], i + 2
        elif args[i].startswith("--families="):
            text, i = args[i].split("=", 1)[1], i + 1
        else:
            rest.append(args[i])
            i += 1
    names = {x.strip() for x in text.split(",") if x.strip()}
    if not names or names - set(FAMILIES):
        raise SystemExit(f"families: expected a comma list of {', '.join(FAMILIES)}, got "
                         f"{text!r}")
    return [f for f in FAMILIES if f in names], rest


def per_gpu_count(value: str, n_gpus: int, n_tasks: int) -> int:
    """``--per-gpu``'s value -> processes per GPU: a whole number >= 1 as given; "auto": 2 on
    one GPU with two tasks or more (measured: the same results, 0.78x the time), else 1."""
    if str(value) == "auto":
        return 2 if n_gpus == 1 and n_tasks > 1 else 1
    try:
        k = int(value)
    except ValueError:
        k = 0
    if k < 1:
        raise SystemExit(f"per-gpu: expected auto or a whole number >= 1, got {value!r}")
    return k


def plan(tasks: list[str], n_gpus: int, args: list[str], out: str,
         units: str = "auto", per_gpu: int = 1) -> list[dict]:
    """The units in queue order, each {task, family (None: every family), args, out, log,
    collects}; ``collects``: the task's first unit, which collects its data. ``units``
    "family": (task, family) pairs when there are two GPUs or more; "task": a whole task per
    unit whatever the GPUs (its families in one process, so that the likelihood family's BC
    lanes can continue from the adversarial pre-training: docs/SCALING.md); "auto": "task"
    when len(tasks) <= n_gpus < 2 len(tasks), else "family". ``per_gpu``: processes per GPU
    at once (whole tasks run costliest first wherever more than one runs at a time)."""
    if units not in ("auto", "family", "task"):
        raise SystemExit(f"units: expected auto, family or task, got {units!r}")
    if units == "auto":
        units = "task" if len(tasks) <= n_gpus < 2 * len(tasks) else "family"
    if n_gpus <= 1 or units == "task":
        if n_gpus * per_gpu > 1:  # the costliest tasks first
            tasks = sorted(tasks, key=lambda t: -sum(COST.get(t, DEFAULT_COST).values()))
        return [{"task": t, "family": None, "args": list(args), "out": out, "collects": True,
                 "log": os.path.join(out, f"paper_{t}.log")} for t in tasks]
    families, rest = split_families(args)
    pairs = sorted(((t, f) for t in tasks for f in families),
                   key=lambda p: -COST.get(p[0], DEFAULT_COST)[p[1]])
    units, seen = [], set()
    for t, f in pairs:
        first = t not in seen
        seen.add(t)
        extra = rest if first else [a for a in rest if a != "--control"] + ["--no-oracle"]
        units.append({"task": t, "family": f, "collects": first,
                      "args": [*extra, "--families", f],
                      # the args if it must collect after all (the collecting unit failed
                      # before its data): the oracle and control go with the data
                      "collect_args": [*rest, "--families", f],
                      "out": os.path.join(out, "units", f"{t}_{f}"),
                      "log": os.path.join(out, f"paper_{t}_{f}.log")})
    return units


def name(unit: dict) -> str:
    return f"{unit['task']}/{unit['family'] or 'all families'}"


def _pump(unit: dict, proc, tee: bool, events: queue.Queue) -> None:
    """Copy the unit's output to its log (and here when ``tee``) line by line, report its data
    line and its end."""
    with open(unit["log"], "w") as log:
        for raw in proc.stdout:
            line = raw.decode(errors="replace")
            log.write(line)
            log.flush()
            if tee:
                sys.stdout.write(line)
                sys.stdout.flush()
            if line.startswith(DATA_LINE):
                events.put(("data", unit, None))
    events.put(("end", unit, proc.wait()))


def visible_gpus(n: int) -> list[str]:
    """The device ids of the n GPUs the units run on: the first n of an inherited
    CUDA_VISIBLE_DEVICES, else 0..n-1. SystemExit when it lists fewer than n."""
    inherited = [g.strip() for g in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")
                 if g.strip()]
    if not inherited:
        return [str(g) for g in range(n)]
    if len(inherited) < n:
        raise SystemExit(f"gpus: {n} GPUs to schedule over, but CUDA_VISIBLE_DEVICES lists "
                         f"{len(inherited)} ({','.join(inherited)})")
    return inherited[:n]


def run_units(units: list[dict], slots: list, py: list[str], data_dir: str, t0: float,
              on_task_end=None) -> None:
    """Run ``units`` over ``slots`` (GPU indices, a GPU listed K times runs K processes at once,
    each with 1/K of the memory fraction (XLA_PYTHON_CLIENT_MEM_FRACTION, default 0.9);
    [None]: no GPU), one process per slot; each
    unit gets gpu, start_s, data_s, wall_s and rc. ``on_task_end(task)``: called once all of a
    task's units have ended (e.g. to merge it while the other tasks run)."""
    events: queue.Queue = queue.Queue()
    pending, free, data_done, running = list(units), sorted(slots), set(), 0  # [None] or ints
    share = max([slots.count(g) for g in slots if g is not None] or [1])
    mem = float(os.environ.get("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.9"))
    visible = visible_gpus(len(set(slots) - {None}))
    tee = len(slots) == 1
    while pending or running:
        while free:
            unit = next((u for u in pending if u["collects"] or u["task"] in data_done), None)
            if unit is None:
                break
            pending.remove(unit)
            gpu = unit["gpu"] = free.pop(0)
            env = {**os.environ, "PYTHONUNBUFFERED": "1"}
            if gpu is not None:
                env["CUDA_VISIBLE_DEVICES"] = visible[gpu]
                if share > 1:  # each process preallocates its share of the GPU's memory
                    env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{mem / share:.3f}"
            cmd = [*py, "experiments/paper.py", "--task", unit["task"], "--out", unit["out"],
                   "--data-dir", data_dir, *unit["args"]]
            os.makedirs(unit["out"], exist_ok=True)
            unit["start_s"] = round(time.monotonic() - t0, 1)
            print(f"[paper_all] {name(unit)} on GPU {visible[gpu] if gpu is not None else '-'} at "
                  f"{unit['start_s']:.0f}s: {shlex.join(cmd)}", flush=True)
            try:
                proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE,
                                        stderr=subprocess.STDOUT)
            except OSError as err:
                with open(unit["log"], "w") as f:
                    f.write(f"{cmd[0]}: {err}\n")
                events.put(("end", unit, 127))
            else:
                threading.Thread(target=_pump, args=(unit, proc, tee, events),
                                 daemon=True).start()
            running += 1
        kind, unit, rc = events.get()
        if kind == "data":
            unit.setdefault("data_s", round(time.monotonic() - t0 - unit["start_s"], 1))
            data_done.add(unit["task"])
            continue
        unit["wall_s"] = round(time.monotonic() - t0 - unit["start_s"], 1)
        unit["rc"] = rc
        if rc != 0 and unit["collects"] and "data_s" not in unit:
            heir = next((u for u in pending if u["task"] == unit["task"]), None)
            if heir is not None:  # it collects now, with the oracle and the control
                heir.update(collects=True, args=heir.get("collect_args", heir["args"]))
        data_done.add(unit["task"])  # ended: nobody waits for its data now
        free = sorted(free + [unit["gpu"]])
        running -= 1
        print(f"[paper_all] {name(unit)} ended with {rc} after {unit['wall_s']:.0f}s",
              flush=True)
        if on_task_end and all("rc" in u for u in units if u["task"] == unit["task"]):
            on_task_end(unit["task"])


class Merger:
    """merge_results.py for a task whose units all succeeded (collecting unit first), each in
    its own thread as soon as the task's units have ended, so that the merges overlap the
    units still running (``__call__``: run_units' on_task_end); ``wait`` -> the merges in
    task order."""

    def __init__(self, units: list[dict], tasks: list[str], py: list[str], out: str,
                 t0: float):
        self.units, self.tasks, self.py, self.out, self.t0 = units, tasks, py, out, t0
        self.threads, self.merges = [], {}

    def __call__(self, task: str) -> None:
        mine = [u for u in self.units if u["task"] == task]
        if not mine or any(u.get("rc") != 0 for u in mine):
            return
        th = threading.Thread(target=self._merge, args=(task, mine), daemon=True)
        th.start()
        self.threads.append(th)

    def _merge(self, task: str, mine: list[dict]) -> None:
        self.merges[task] = merge_task(task, mine, self.py, self.out, self.t0)

    def wait(self) -> list[dict]:
        for th in self.threads:
            th.join()
        return [self.merges[t] for t in self.tasks if t in self.merges]


def merge_task(t: str, mine: list[dict], py: list[str], out: str, t0: float) -> dict:
    """merge_results.py of task ``t`` from its units ``mine`` (the collecting one first)."""
    mine = sorted(mine, key=lambda u: not u["collects"])
    cmd = [*py, "experiments/merge_results.py", "--task", t,
           *[a for u in mine for a in ("--paper", os.path.join(u["out"], f"{t}.json"))],
           "--out", out]
    m = {"task": t, "log": os.path.join(out, f"merge_{t}.log"),
         "start_s": round(time.monotonic() - t0, 1)}
    with open(m["log"], "w") as log:
        try:
            m["rc"] = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
        except OSError as err:
            log.write(f"{cmd[0]}: {err}\n")
            m["rc"] = 127
    m["wall_s"] = round(time.monotonic() - t0 - m["start_s"], 1)
    return m


def report(units: list[dict], merges: list[dict], n_gpus: int, total: float, out: str,
           per_gpu: int = 1) -> str:
    """The wall time per part as text; OUT/schedule.json written (busy per GPU: its units'
    seconds summed, so more than the wall time where ``per_gpu`` processes shared it)."""
    ran = sorted(units, key=lambda u: (u.get("start_s", float("inf")), u["task"]))
    lines = [f"[paper_all] wall time per part, {n_gpus} GPU(s)"
             f"{f', {per_gpu} processes per GPU' if per_gpu > 1 else ''}:",
             f"  {'task':<12} {'family':<12} {'gpu':>3} {'start (s)':>9} {'wall (s)':>9}  "
             f"{'data (s)':>8}  status"]
    for u in ran:
        status = "ok" if u.get("rc") == 0 else f"FAILED ({u.get('rc')}): {u['log']}"
        lines.append(f"  {u['task']:<12} {u['family'] or 'all':<12} "
                     f"{'-' if u.get('gpu') is None else u['gpu']:>3} "
                     f"{u.get('start_s', 0):>9.1f} {u.get('wall_s', 0):>9.1f}  "
                     f"{'-' if u.get('data_s') is None else u['data_s']:>8}  {status}")
    for m in merges:
        status = "ok" if m["rc"] == 0 else f"FAILED ({m['rc']}): {m['log']}"
        lines.append(f"  {m['task']:<12} {'merge':<12} {'-':>3} {m['start_s']:>9.1f} "
                     f"{m['wall_s']:>9.1f}  {'':>8}  {status}")
    busy = {}
    for u in ran:
        g = "-" if u.get("gpu") is None else str(u["gpu"])
        busy[g] = round(busy.get(g, 0.0) + u.get("wall_s", 0.0), 1)
    lines.append(f"[paper_all] busy per GPU (s): "
                 f"{', '.join(f'{g}: {b:.1f}' for g, b in sorted(busy.items()))}; the units "
                 f"summed {sum(busy.values()):.1f}s")
    lines.append(f"[paper_all] in all: {total:.1f}s -> {os.path.join(out, 'schedule.json')}")
    keys = ("task", "family", "gpu", "start_s", "wall_s", "data_s", "rc", "collects", "log",
            "out")
    with open(os.path.join(out, "schedule.json"), "w") as f:
        json.dump({"gpus": n_gpus, "per_gpu": per_gpu, "total_s": round(total, 1),
                   "busy_s": busy,
                   "units": [{k: u.get(k) for k in keys} for u in ran], "merges": merges},
                  f, indent=1)
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--gpus", type=int, default=0, help="GPUs of this host (0: none)")
    ap.add_argument("--py", default="python3", help="the python command of paper.py and "
                    "merge_results.py (may carry a prefix, e.g. 'timeout 560 python3')")
    ap.add_argument("--tasks", default="hopper walker2d halfcheetah ant")
    ap.add_argument("--units", default=os.environ.get("PAPER_UNITS", "auto"),
                    help="auto (default): task when tasks <= GPUs < 2 x tasks, else family; "
                    "family: (task, family) units with two GPUs or more; task: one process "
                    "per task whatever the GPUs (env PAPER_UNITS)")
    ap.add_argument("--per-gpu", default=os.environ.get("PAPER_PER_GPU", "auto"),
                    help="paper.py processes per GPU at once (env PAPER_PER_GPU): a whole "
                    "number, or auto (default): 2 on one GPU with two tasks or more (one "
                    "task's data collection and compilation, the GPU idle, run beside "
                    "another's training), else 1")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    tasks, py, n = args.tasks.split(), shlex.split(args.py), max(0, args.gpus)
    args.per_gpu = per_gpu_count(args.per_gpu, n, len(tasks))
    visible_gpus(n)  # refused before any unit starts
    os.makedirs(args.out, exist_ok=True)
    units = plan(tasks, n, extra, args.out, args.units, args.per_gpu)
    merger = Merger(units, tasks, py, args.out, t0)
    split = any(u["family"] for u in units)
    slots = [g for g in range(n) for _ in range(args.per_gpu)] if n else [None]
    run_units(units, slots, py, args.data_dir, t0, merger if split else None)
    merges = merger.wait()
    print(report(units, merges, n, time.monotonic() - t0, args.out, args.per_gpu), flush=True)
    failed = [f"{name(u)} (exit {u.get('rc')}, log {u['log']})" for u in units
              if u.get("rc") != 0]
    failed += [f"merge of {m['task']} (exit {m['rc']}, log {m['log']})" for m in merges
               if m["rc"] != 0]
    for f in failed:
        print(f"paper_all: FAILED {f}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
