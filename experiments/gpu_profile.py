"""Where a task's GPU-seconds go (issue 63 item 1; docs/BENCHMARKS.md, "Where one task's
GPU-seconds go"): `paper.py` runs of `device.sh streams`, one per GPU, joined with nvidia-smi's
utilization samples of their GPUs.

    python experiments/gpu_profile.py STREAMS_DIR [--json OUT.json] [--idle-min 6]

STREAMS_DIR holds
- progress.log: device.sh streams' lines "[s<i>] <k> start HH:MM:SS GPU <n>: paper <task> ..."
  and "[s<i>] <k> rc <rc> end HH:MM:SS" (each stream pinned to one GPU with `@n`);
- <stream>_<k>_paper_<task>.log: each run's log (`device.sh paper`'s paper_<task>.log);
- gpu_util.csv: `nvidia-smi --query-gpu=timestamp,index,utilization.gpu,memory.used
  --format=csv,noheader -l 2`, sampled during the runs.

paper.py's clock starts after Python's start and imports; its last line gives the clock's
total, so the clock's zero is put at the stream's end minus that total (the interpreter's exit,
about a second, lands before it; the first sample with GPU memory in use is printed beside it as
a check). Each "[paper] NAME: X s (elapsed Y s)" line is the window [Y - X, Y] on that clock
(Y is rounded to the second); the adversarial and likelihood phases are cut into their logged
parts (init, each chunk of training steps, each test evaluation, the rest), the data phase
into its "data_<part>" timings where the run logged them (setup, each program's compile and
run, the rows on the host, the split and save, the rest), the trust phase into its timings
(calibration policies' real values, each family's interval programs, the rest). What lies
before the first phase (Python, imports, JAX's backend), between phases and after the last is
a row of its own, so a task's rows add up to its stream's wall time.

A sample's utilization.gpu (the share of nvidia-smi's sample period in which any kernel ran)
holds from the midpoint with the sample before to the midpoint with the one after; busy
GPU-seconds are its integral over a window (time outside the samples counts as idle). Busy
says a kernel was running, not how much of the GPU it used. Idle spans: runs of samples at 0%
at least --idle-min seconds long, with the rows they fall in (compilation and host work sit
there). The summary adds one GPU's protocol: the tasks one after another without the oracle
and trust phases (the issue's `--no-oracle` protocol), its busy GPU-seconds against 600 s.
"""
from __future__ import annotations

import argparse
import ast
import datetime as dt
import os
import re
import sys

import numpy as np

from rl2s_jax._files import write_json

START = re.compile(r"^\[(s\d+)\] (\d+) start (\d\d:\d\d:\d\d)(?: GPU (\d+))?: (\S+) ?(\S*)(.*)$")
END = re.compile(r"^\[(s\d+)\] (\d+) rc (-?\d+) end (\d\d:\d\d:\d\d)$")
PHASE = re.compile(r"^\[paper\] (\w+): ([\d.]+)s \(elapsed (\d+)s\)$")
FAMILY = re.compile(r"^\[paper\] (\w+): \d+ lanes over .*; init ([\d.]+)s")
CHUNK = re.compile(r"^\[paper\] (\w+) step (\d+): (\d+) steps of (.+) in ([\d.]+)s; "
                   r"test evaluation ([\d.]+)s$")
TOTAL = re.compile(r"^\[paper\] \w+: .* in all; timings (\{.*\})$")
HARDWARE = re.compile(r"^\[paper\] task \w+ on (.+?) \((\w+), jax ([\w.]+)\)")
STAMP = "%Y/%m/%d %H:%M:%S.%f"
NOT_PROTOCOL = ("oracle", "trust")  # paper.py phases the protocol leaves out
# paper.py's timings "data_<part>" (paper.protocol.load_or_collect) -> the part's label; no
# ':' in them (the summary groups parts by the label up to one)
DATA_PARTS = {"data_load": "load (the reused .npz files)", "data_setup": "setup (zoo, env)",
              "data_rollout_compile": "transitions compile (trace, lower, XLA or cache)",
              "data_rollout_run": "transitions run (chunks, each copied to the host)",
              "data_rollout_host": "transitions into rows (host)",
              "data_values_compile": "true values compile (trace, lower, XLA or cache)",
              "data_values_run": "true values run",
              "data_split_save": "split and save (compressed .npz files)"}


def read_progress(path: str) -> list[dict]:
    """progress.log -> [{stream, job, gpu, task, args, start, end (HH:MM:SS), rc}] of the
    paper runs that ended."""
    runs, ends = {}, {}
    with open(path) as f:
        for line in f:
            if m := START.match(line.strip()):
                s, k, t, gpu, cmd, task, rest = m.groups()
                if cmd != "paper":
                    continue
                if gpu is None:
                    raise SystemExit(f"{path}: stream {s} has no GPU pin ('GPU <n>' after its "
                                     "start time; device.sh streams '@n ...'): its GPU's "
                                     "samples cannot be told from the others'")
                runs[(s, k)] = {"stream": s, "job": int(k), "gpu": int(gpu), "task": task,
                                "args": rest.strip(), "start": t}
            elif m := END.match(line.strip()):
                ends[m.group(1, 2)] = (int(m.group(3)), m.group(4))
    if not runs:
        raise SystemExit(f"{path}: expected '[s<i>] <k> start HH:MM:SS GPU <n>: paper <task> "
                         "...' lines, found none")
    out = []
    for key, run in runs.items():
        if key not in ends:
            raise SystemExit(f"{path}: stream {key[0]} run {key[1]} has a start but no end line")
        run["rc"], run["end"] = ends[key]
        out.append(run)
    return out


def read_util(path: str) -> dict:
    """gpu_util.csv -> {"t0": datetime of the first sample, gpu: (t [N] s after t0,
    utilization [N] as a fraction, memory [N] MiB)}."""
    rows = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            if not line.strip():
                continue
            parts = [p.strip() for p in line.split(",")]
            if len(parts) != 4 or not parts[2].endswith("%") or not parts[3].endswith("MiB"):
                raise SystemExit(f"{path}:{i}: expected 'timestamp, index, N %, M MiB' "
                                 f"(nvidia-smi --format=csv,noheader), got {line.strip()!r}")
            rows.append((dt.datetime.strptime(parts[0], STAMP), int(parts[1]),
                         float(parts[2][:-1]) / 100, float(parts[3][:-3])))
    if not rows:
        raise SystemExit(f"{path}: no samples")
    t0 = min(r[0] for r in rows)
    out = {"t0": t0}
    for gpu in sorted({r[1] for r in rows}):
        mine = sorted((r for r in rows if r[1] == gpu), key=lambda r: r[0])
        out[gpu] = tuple(np.array(c, np.float64) for c in zip(
            *[((r[0] - t0).total_seconds(), r[2], r[3]) for r in mine], strict=True))
    return out


def clock_seconds(hms: str, t0: dt.datetime) -> float:
    """HH:MM:SS (progress.log) -> seconds after t0, the samples' first timestamp (a time more
    than 12 h before t0 is the next day's)."""
    t = dt.datetime.combine(t0.date(), dt.time.fromisoformat(hms))
    seconds = (t - t0).total_seconds()
    return seconds + 86400 if seconds < -43200 else seconds


def parse_log(path: str) -> dict:
    """A paper.py log -> {"phases": [(name, seconds, elapsed)], "families": {family:
    {"init": s, "chunks": [(first step, last step, what, train s, eval s)]}},
    "timings": paper.py's final timings, "hardware": str}."""
    phases, families, timings, hardware = [], {}, None, ""
    with open(path) as f:
        for line in f:
            line = line.rstrip()
            if m := PHASE.match(line):
                if not m.group(1).startswith("data_"):  # data_<part>: the data phase's parts
                    phases.append((m.group(1), float(m.group(2)), float(m.group(3))))
            elif m := FAMILY.match(line):
                families[m.group(1)] = {"init": float(m.group(2)), "chunks": []}
            elif m := CHUNK.match(line):
                step, n = int(m.group(2)), int(m.group(3))
                families[m.group(1)]["chunks"].append(
                    (step - n + 1, step, m.group(4), float(m.group(5)), float(m.group(6))))
            elif m := TOTAL.match(line):
                timings = ast.literal_eval(m.group(1))
            elif m := HARDWARE.match(line):
                hardware = f"{m.group(1)} ({m.group(2)}, jax {m.group(3)})"
    if not phases or timings is None or "total" not in timings:
        raise SystemExit(f"{path}: expected paper.py's '[paper] NAME: Xs (elapsed Ys)' lines "
                         "and its last line's timings with 'total' (a run that ended); "
                         f"found {len(phases)} phase lines, timings {timings}")
    return {"phases": phases, "families": families, "timings": timings, "hardware": hardware}


def busy_seconds(t: np.ndarray, util: np.ndarray, a: float, b: float) -> float:
    """Integral of the utilization over [a, b] s: sample i [N] holds from the midpoint with
    sample i-1 to the midpoint with i+1; the first and last half the median spacing out."""
    if b <= a or len(t) == 0:
        return 0.0
    half = float(np.median(np.diff(t))) / 2 if len(t) > 1 else 1.0
    mid = (t[1:] + t[:-1]) / 2
    lo = np.concatenate([[t[0] - half], mid])
    hi = np.concatenate([mid, [t[-1] + half]])
    return float(np.clip(np.minimum(hi, b) - np.maximum(lo, a), 0, None) @ util)


def idle_spans(t: np.ndarray, util: np.ndarray, rows: list[dict], wall: float,
               min_s: float) -> list[dict]:
    """Runs of samples [N] at 0% (each sample's span as in busy_seconds) within [0, wall], at
    least min_s long, each with the innermost rows it overlaps by 1 s or more: {a, b,
    seconds, where}."""
    if len(t) < 2:
        return []
    half = float(np.median(np.diff(t))) / 2
    edges = np.concatenate([[t[0] - half], (t[1:] + t[:-1]) / 2, [t[-1] + half]])
    idle = np.concatenate([[0], (util == 0).astype(int), [0]])
    parents = {r["phase"] for r in rows if "part" in r}
    leaves = [(f"{r['phase']} / {r['part']}" if "part" in r else r["phase"], a, b)
              for r in rows if "part" in r or r["phase"] not in parents
              for a, b in (r.get("spans") or [(r["a"], r["b"])])]
    out = []
    for i, j in zip(np.flatnonzero(np.diff(idle) == 1), np.flatnonzero(np.diff(idle) == -1),
                    strict=True):
        a, b = max(float(edges[i]), 0.0), min(float(edges[j]), wall)
        if b - a >= min_s:
            where = [name for name, la, lb in leaves if min(b, lb) - max(a, la) >= 1.0]
            out.append({"a": round(a, 1), "b": round(b, 1), "seconds": round(b - a, 1),
                        "where": " + ".join(dict.fromkeys(where))})
    return out


def _parts(name: str, log: dict, a: float, b: float) -> list[tuple[str, float, float]]:
    """The logged parts of phase ``name`` laid end to end from a, the rest up to b."""
    parts, t = [], a
    family = name.removeprefix("train_")
    if name.startswith("train_") and family in log["families"]:
        fam = log["families"][family]
        parts.append(("init (data to the device, lanes)", fam["init"]))
        for first, last, what, train_s, eval_s in fam["chunks"]:
            parts += [(f"steps {first}-{last}: {what}", train_s),
                      (f"test evaluation at step {last}", eval_s)]
        rest = "the rest (final rows, bootstrap intervals)"
    elif name == "data" and any(k.startswith("data_") for k in log["timings"]):
        parts += [(DATA_PARTS.get(k, k.removeprefix("data_")), v)
                  for k, v in log["timings"].items() if k.startswith("data_")]
        rest = "the rest (logs, between parts)"
    elif name == "trust":
        timings = log["timings"]
        real = {"trust_calibration": "calibration policies' real values",
                "trust_evaluated": "evaluated (perturbed test) policies' real values"}
        parts += [(real.get(k, f"{k.removeprefix('trust_')} family's interval programs"), v)
                  for k, v in timings.items() if k.startswith("trust_")]
        rest = "the rest (interval blocks per method)"
    else:
        return []
    out = []
    for label, seconds in parts:
        out.append((label, t, min(t + seconds, b)))
        t = min(t + seconds, b)
    return out + [(rest, t, b)]


def windows(run: dict, log: dict, wall: float) -> list[dict]:
    """The run's rows {phase, part (None: the phase itself), a, b} (seconds after the stream's
    start), end to end from 0 to wall."""
    zero = wall - log["timings"]["total"]
    rows, t, gaps = [], 0.0, []
    for i, (name, seconds, elapsed) in enumerate(log["phases"]):
        b = min(zero + elapsed, wall)
        a = min(max(b - seconds, t), b)
        if i == 0:
            rows.append({"phase": "start: Python, imports, JAX's backend", "a": 0.0, "b": a})
        elif a > t:
            gaps.append((t, a))
        rows.append({"phase": name, "a": a, "b": b})
        rows += [{"phase": name, "part": p, "a": pa, "b": pb}
                 for p, pa, pb in _parts(name, log, a, b)]
        t = b
    rows.append({"phase": "end: results written, exit", "a": t, "b": wall})
    rows.insert(-1, {"phase": "between phases (saves, host work)", "a": None, "b": None,
                     "spans": gaps})
    return rows


def profile_run(run: dict, log: dict, util: dict, idle_min_s: float = 6.0) -> dict:
    """One run's rows with wall s, busy GPU-s, utilization %, idle s, its totals and its
    idle spans of at least idle_min_s."""
    t0 = util["t0"]
    start = clock_seconds(run["start"], t0)
    wall = clock_seconds(run["end"], t0) - start
    if run["gpu"] not in util:
        raise SystemExit(f"gpu_util.csv: no samples of GPU {run['gpu']} (stream "
                         f"{run['stream']}); it has GPUs {sorted(k for k in util if k != 't0')}")
    t, u, mem = util[run["gpu"]]
    t = t - start
    rows, spans_of_idle = [], idle_spans(t, u, windows(run, log, wall), wall, idle_min_s)
    for row in windows(run, log, wall):
        spans = row.pop("spans", None) or [(row["a"], row["b"])]
        wall_s = sum(b - a for a, b in spans if a is not None)
        busy = sum(busy_seconds(t, u, a, b) for a, b in spans if a is not None)
        rows.append({**row, "wall_s": round(wall_s, 2), "busy_gpu_s": round(busy, 2),
                     "util_pct": round(100 * busy / wall_s, 1) if wall_s > 0 else 0.0,
                     "idle_s": round(wall_s - busy, 2)})
    top = [r for r in rows if "part" not in r]
    left_out = [r for r in top if r["phase"] in NOT_PROTOCOL]
    used = np.flatnonzero(mem > 0)
    total = {k: round(sum(r[k] for r in top), 2) for k in ("wall_s", "busy_gpu_s", "idle_s")}
    return {"stream": run["stream"], "gpu": run["gpu"], "task": run["task"],
            "args": run["args"], "rc": run["rc"], "hardware": log["hardware"],
            "paper_clock_zero_s": round(wall - log["timings"]["total"], 2),
            "first_memory_sample_s": round(float(t[used[0]]), 2) if used.size else None,
            "rows": rows, "total": total, "idle_spans": spans_of_idle,
            "protocol": {k: round(total[k] - sum(r[k] for r in left_out), 2) for k in total},
            **{f"{name}_{k}": round(sum(r[k] for r in top if r["phase"] == name), 2)
               for name in NOT_PROTOCOL for k in ("wall_s", "busy_gpu_s")}}


def summarise(runs: list[dict], bar_s: float = 600.0) -> dict:
    """Sums over the runs, and one GPU's protocol (no oracle, no trust) if run one task after
    another: its wall time, its busy GPU-seconds (what sharing the GPU cannot go below), the
    bar."""
    def add(key, sub=None):
        return round(sum((r[key] if sub is None else r[key][sub]) for r in runs), 1)

    by_phase: dict[str, dict] = {}
    for r in runs:
        for row in r["rows"]:
            key = row["phase"] + (f" / {row['part'].split(':')[0]}" if "part" in row else "")
            acc = by_phase.setdefault(key, {"wall_s": 0.0, "busy_gpu_s": 0.0, "idle_s": 0.0})
            for k in acc:
                acc[k] = round(acc[k] + row[k], 2)
    return {"tasks": [r["task"] for r in runs], "by_phase": by_phase,
            "wall_s": add("total", "wall_s"), "busy_gpu_s": add("total", "busy_gpu_s"),
            "oracle_wall_s": add("oracle_wall_s"), "oracle_busy_gpu_s": add("oracle_busy_gpu_s"),
            "trust_wall_s": add("trust_wall_s"), "trust_busy_gpu_s": add("trust_busy_gpu_s"),
            "one_gpu": {"protocol_wall_s": add("protocol", "wall_s"),
                        "protocol_busy_gpu_s": add("protocol", "busy_gpu_s"),
                        "protocol_idle_s": add("protocol", "idle_s"),
                        "with_trust_wall_s": round(add("protocol", "wall_s")
                                                   + add("trust_wall_s"), 1),
                        "with_trust_busy_gpu_s": round(add("protocol", "busy_gpu_s")
                                                       + add("trust_busy_gpu_s"), 1),
                        "bar_s": bar_s}}


def print_run(r: dict) -> None:
    tot = r["total"]
    print(f"\n{r['task']} ({r['stream']}, GPU {r['gpu']}, {r['hardware']}; {r['args']}): "
          f"{tot['wall_s']:.1f} s wall, {tot['busy_gpu_s']:.1f} busy GPU-s "
          f"({100 * tot['busy_gpu_s'] / tot['wall_s']:.0f}%); paper.py's clock starts at "
          f"+{r['paper_clock_zero_s']:.1f} s, first GPU memory in use at "
          f"+{r['first_memory_sample_s']} s")
    print(f"  {'phase':<62} {'wall s':>7} {'util %':>6} {'busy GPU-s':>10} {'idle s':>7}")
    for row in r["rows"]:
        name = f"  - {row['part']}" if "part" in row else row["phase"]
        print(f"  {name[:62]:<62} {row['wall_s']:7.1f} {row['util_pct']:6.1f} "
              f"{row['busy_gpu_s']:10.1f} {row['idle_s']:7.1f}")
    p = r["protocol"]
    print(f"  {'total':<62} {tot['wall_s']:7.1f} {'':6} {tot['busy_gpu_s']:10.1f} "
          f"{tot['idle_s']:7.1f}\n  {'without oracle and trust':<62} {p['wall_s']:7.1f} "
          f"{'':6} {p['busy_gpu_s']:10.1f} {p['idle_s']:7.1f}")
    in_spans = sum(s["seconds"] for s in r["idle_spans"])
    print(f"  idle spans (all samples at 0%; {in_spans:.0f} s of the {tot['idle_s']:.0f} s "
          "idle): " + "; ".join(
        f"{s['seconds']:.0f} s at +{s['a']:.0f} ({s['where']})" for s in r["idle_spans"]))


def print_summary(s: dict) -> None:
    one = s["one_gpu"]
    print(f"\nall tasks, by phase (parts: the logged parts' labels up to ':')\n"
          f"  {'phase':<62} {'wall s':>7} {'util %':>6} {'busy GPU-s':>10} {'idle s':>7}")
    for name, v in s["by_phase"].items():
        name = f"  - {name.split(' / ', 1)[1]}" if " / " in name else name
        util = 100 * v["busy_gpu_s"] / v["wall_s"] if v["wall_s"] > 0 else 0.0
        print(f"  {name[:62]:<62} {v['wall_s']:7.1f} {util:6.1f} {v['busy_gpu_s']:10.1f} "
              f"{v['idle_s']:7.1f}")
    print(f"\nall {len(s['tasks'])} tasks ({', '.join(s['tasks'])}): {s['wall_s']:.1f} s of "
          f"wall, {s['busy_gpu_s']:.1f} busy GPU-s; oracle {s['oracle_wall_s']:.1f} s "
          f"({s['oracle_busy_gpu_s']:.1f} busy), trust {s['trust_wall_s']:.1f} s "
          f"({s['trust_busy_gpu_s']:.1f} busy)")
    print(f"one GPU, the tasks one after another, without oracle and trust: "
          f"{one['protocol_wall_s']:.1f} s wall, {one['protocol_busy_gpu_s']:.1f} busy GPU-s, "
          f"{one['protocol_idle_s']:.1f} s idle (bar {one['bar_s']:.0f} s: busy alone is "
          f"{one['protocol_busy_gpu_s'] / one['bar_s']:.2f}x it); with trust "
          f"{one['with_trust_wall_s']:.1f} s wall, {one['with_trust_busy_gpu_s']:.1f} busy")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("streams_dir", help="progress.log, gpu_util.csv, <stream>_<k>_paper_*.log")
    ap.add_argument("--json", help="write the profile here")
    ap.add_argument("--idle-min", type=float, default=6.0,
                    help="list idle spans at least this many seconds long (default 6)")
    args = ap.parse_args(argv)
    if args.idle_min <= 0:
        raise SystemExit(f"idle-min: expected seconds > 0, got {args.idle_min}")
    d = args.streams_dir
    for name in ("progress.log", "gpu_util.csv"):
        if not os.path.isfile(os.path.join(d, name)):
            raise SystemExit(f"streams_dir: expected {name} in {d}")
    runs = read_progress(os.path.join(d, "progress.log"))
    logs = []
    for run in runs:
        path = os.path.join(d, f"{run['stream']}_{run['job']}_paper_{run['task']}.log")
        if not os.path.isfile(path):
            raise SystemExit(f"streams_dir: expected {os.path.basename(path)} (stream "
                             f"{run['stream']} run {run['job']}'s log) in {d}")
        logs.append(parse_log(path))
    util = read_util(os.path.join(d, "gpu_util.csv"))
    profiles = [profile_run(run, log, util, args.idle_min)
                for run, log in zip(runs, logs, strict=True)]
    profiles.sort(key=lambda r: r["gpu"])
    for r in profiles:
        print_run(r)
    summary = summarise(profiles)
    print_summary(summary)
    if args.json:
        write_json(args.json, {"streams_dir": d, "runs": profiles, "summary": summary})
        print(f"-> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
