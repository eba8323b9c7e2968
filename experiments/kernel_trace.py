"""Where a train_step's device time goes, kernel by kernel (issue 63: the launch-bound chain).

Traces ``--steps`` train_steps of one config with jax.profiler and reads the trace back with
jax.profiler.ProfileData (no TensorBoard needed): every kernel the device ran (on a GPU the
CUPTI events of its stream lines; on the CPU XLA's thunks), their count per step and per
update (a critic or a generator update; a likelihood update), the device's busy fraction of
the traced window, the gaps between one kernel's end and the next one's start, and the
heaviest kernels by summed time. So it says whether a chain of small updates waits on the
kernels themselves (busy near 100%, each kernel short but many) or on their launches (idle
gaps between them).

    python experiments/kernel_trace.py [--official-sizes] [--method rl2s|bc] [--vmap N]
        [--set KEY=VALUE ...] [--steps 3] --out DIR
    python experiments/kernel_trace.py --plot TITLE=DIR/kernel_trace.json ... --out FIG.png

DIR gets ``trace/`` (the raw ``*.xplane.pb``, to read again with ``--read DIR``) and
``kernel_trace.json``. The data are bench_train.py's random rows of Hopper's shapes.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import numpy as np  # noqa: E402
from bench_train import bench_config, step_program  # noqa: E402

from rl2s_jax._files import save_figure, write_json  # noqa: E402
from rl2s_jax.train.config import TrainConfig  # noqa: E402

# host thunks that hold other thunks (their time is their children's) or mark an end
CONTAINERS = ("end:", "while", "conditional", "call")
GEMM_MARKS = ("gemm", "xmma", "cutlass", "cublas", "sm90_", "sm80_", "dot", "matmul")


def kind_of(name: str) -> str:
    """'gemm', 'memcpy' or 'other' (fusions, reductions, copies) from a kernel's name."""
    low = name.lower()
    if "memcpy" in low or "memset" in low:
        return "memcpy"
    return "gemm" if any(m in low for m in GEMM_MARKS) else "other"


def device_events(profile) -> tuple[list[tuple[str, int, int]], str]:
    """Kernels of a jax.profiler.ProfileData as [(name, start_ns, duration_ns)] sorted by
    start, and where they came from: the GPU planes' stream lines (every line where no line
    is named 'Stream ...'), else the host's XLA thunks (events with an ``hlo_op`` stat, but
    not loops and calls, whose children are the thunks)."""
    gpu = [p for p in profile.planes if p.name.startswith("/device:GPU")]
    events = []
    if gpu:
        for plane in gpu:
            lines = [ln for ln in plane.lines if ln.name.startswith("Stream")] or list(plane.lines)
            events += [(e.name, int(e.start_ns), int(e.duration_ns))
                       for ln in lines for e in ln.events]
        source = "gpu streams"
    else:
        for plane in profile.planes:
            for ln in plane.lines:
                for e in ln.events:
                    if (not e.name.startswith(CONTAINERS)
                            and any(k == "hlo_op" for k, _ in e.stats)):
                        events.append((e.name, int(e.start_ns), int(e.duration_ns)))
        source = "host XLA thunks"
    return sorted(events, key=lambda e: e[1]), source


def summarise(events: list[tuple[str, int, int]], n_steps: int, updates_per_step: int,
              top: int = 12, timeline: int = 150) -> dict:
    """Counts, busy time and gaps of kernels [(name, start_ns, duration_ns)] sorted by start.

    busy: the union of the kernels' intervals; window: first start to last end; a gap is the
    idle time between the union's pieces (overlapping kernels make no gap). ``timeline``
    kernels from the middle of the window are kept as they ran (start and length in us)."""
    if not events:
        raise ValueError("kernel_trace: the trace holds no device events")
    starts = np.array([e[1] for e in events], np.int64)
    ends = starts + np.array([e[2] for e in events], np.int64)
    pieces, gaps = [], []
    lo, hi = starts[0], ends[0]
    for s, e in zip(starts[1:], ends[1:], strict=True):
        if s > hi:
            pieces.append(hi - lo)
            gaps.append(s - hi)
            lo, hi = s, e
        else:
            hi = max(hi, e)
    pieces.append(hi - lo)
    window = int(ends.max() - starts[0])
    busy = int(sum(pieces))
    by_name: dict[str, list[int]] = {}
    for name, _, dur in events:
        by_name.setdefault(name, []).append(dur)
    heaviest = sorted(by_name.items(), key=lambda kv: -sum(kv[1]))[:top]
    kinds: dict[str, dict] = {}
    for name, _, dur in events:
        k = kinds.setdefault(kind_of(name), {"count": 0, "total_ms": 0.0})
        k["count"] += 1
        k["total_ms"] += dur / 1e6
    gaps_us = np.array(gaps, np.float64) / 1e3
    n_updates = n_steps * updates_per_step
    mid = max(0, len(events) // 2 - timeline // 2)
    t0 = events[mid][1]
    return {
        "kernels": len(events), "kernels_per_step": len(events) / n_steps,
        "kernels_per_update": len(events) / n_updates if n_updates else None,
        "window_ms": window / 1e6, "busy_ms": busy / 1e6, "busy_fraction": busy / window,
        "mean_kernel_us": float(np.mean([e[2] for e in events]) / 1e3),
        "median_kernel_us": float(np.median([e[2] for e in events]) / 1e3),
        "gaps": len(gaps), "mean_gap_us": float(gaps_us.mean()) if len(gaps) else 0.0,
        "median_gap_us": float(np.median(gaps_us)) if len(gaps) else 0.0,
        "gap_ms_over_100us": float(gaps_us[gaps_us > 100].sum() / 1e3) if len(gaps) else 0.0,
        "per_update_us": {"busy": busy / 1e3 / n_updates, "window": window / 1e3 / n_updates}
        if n_updates else None,
        "kinds": kinds,
        "heaviest": [{"name": n[:120], "count": len(d), "total_ms": sum(d) / 1e6,
                      "mean_us": sum(d) / len(d) / 1e3} for n, d in heaviest],
        "timeline": [[n[:60], (s - t0) / 1e3, d / 1e3] for n, s, d in events[mid:mid + timeline]],
    }


def read_trace(directory: str, n_steps: int, updates_per_step: int) -> dict:
    """summarise() of the newest ``*.xplane.pb`` under ``directory``."""
    from jax.profiler import ProfileData
    paths = sorted(glob.glob(os.path.join(directory, "**", "*.xplane.pb"), recursive=True),
                   key=os.path.getmtime)
    if not paths:
        raise SystemExit(f"kernel_trace.py: no *.xplane.pb under {directory}")
    events, source = device_events(ProfileData.from_file(paths[-1]))
    return {"source": source, "xplane": os.path.relpath(paths[-1], directory),
            **summarise(events, n_steps, updates_per_step)}


def updates_per_step(cfg: TrainConfig) -> int:
    """Dependent updates in one train_step: each generator update with its critic updates
    (adversarial), or the likelihood updates."""
    per = 1 + cfg.adversarial.disc_updates if cfg.is_adversarial else 1
    return cfg.updates_per_step * per


def config(args: argparse.Namespace) -> TrainConfig:
    """bench_train.py's config for the device: paper sizes on a GPU, small elsewhere."""
    profile = "gpu" if jax.default_backend() == "gpu" else "cpu"
    return bench_config(args.method, profile, args.official_sizes, args.set, "kernel_trace.py")


def trace(cfg: TrainConfig, n_steps: int, runs: int, directory: str) -> dict:
    """Compile, time (best of 3) and trace one call of ``n_steps`` train_steps."""
    run, state = step_program(cfg, 17, n_steps, runs)
    t0 = time.perf_counter()
    jax.block_until_ready(run(state))
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(run(state))
        best = min(best, time.perf_counter() - t0)
    with jax.profiler.trace(directory):
        t0 = time.perf_counter()
        jax.block_until_ready(run(state))
        traced = time.perf_counter() - t0
    return {"compile_s": compile_s, "step_ms": 1e3 * best / n_steps,
            "traced_step_ms": 1e3 * traced / n_steps}


def plot_timelines(results: list[tuple[str, dict]], path: str) -> str:
    """One row per (title, kernel_trace.json content): its kept timeline as bars on a shared
    microsecond axis, GEMMs dark, other kernels light, idle white."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"gemm": "#1f4e79", "other": "#9ecae1", "memcpy": "#fdae6b"}
    fig, axes = plt.subplots(len(results), 1, figsize=(11, 1.3 + 1.1 * len(results)),
                             squeeze=False)
    for ax, (title, res) in zip(axes[:, 0], results, strict=True):
        for name, start, dur in res["timeline"]:
            ax.barh(0, dur, left=start, height=0.8, color=colors[kind_of(name)], lw=0)
        ax.set(yticks=[], title=f"{title}: {res['kernels_per_update']:.0f} kernels per update, "
               f"GPU busy {res['busy_fraction']:.0%}", xlim=(0, None))
        ax.title.set_fontsize(9)
    axes[-1, 0].set_xlabel("microseconds (150 consecutive kernels from mid-step; dark: GEMMs, "
                           "light: other fusions)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--method", choices=("rl2s", "bc"), default="rl2s")
    ap.add_argument("--official-sizes", action="store_true",
                    help="the race's equal-work sizes (bench_train.OFFICIAL_SIZES)")
    ap.add_argument("--vmap", type=int, default=1, help="runs vmapped as one program")
    ap.add_argument("--steps", type=int, default=3, help="train_steps in the traced call")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE")
    ap.add_argument("--out", required=True, help="directory for trace/ and kernel_trace.json")
    ap.add_argument("--read", action="store_true", help="only read OUT's trace again")
    ap.add_argument("--plot", nargs="+", metavar="TITLE=JSON", help="only draw the timelines "
                    "of these kernel_trace.json files into OUT (a PNG path)")
    args = ap.parse_args(argv)
    if args.plot:
        pairs = [p.split("=", 1) for p in args.plot]
        if any(len(p) != 2 or not os.path.isfile(p[1]) for p in pairs):
            raise SystemExit("kernel_trace.py: --plot: expected TITLE=JSON with an existing "
                             f"kernel_trace.json each, got {args.plot}")
        results = []
        for title, path in pairs:
            with open(path) as f:
                results.append((title, json.load(f)))
        print(plot_timelines(results, args.out))
        return 0
    if args.steps < 1 or args.vmap < 1:
        raise SystemExit("kernel_trace.py: --steps and --vmap must be at least 1")
    cfg = config(args)
    per = updates_per_step(cfg)
    tdir = os.path.join(args.out, "trace")
    timing = {} if args.read else trace(cfg, args.steps, args.vmap, tdir)
    result = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
              "xla_flags": os.environ.get("XLA_FLAGS", ""), "method": cfg.method,
              "official_sizes": args.official_sizes, "vmapped_runs": args.vmap,
              "steps": args.steps, "updates_per_step": per, **timing,
              **read_trace(tdir, args.steps, per)}
    write_json(os.path.join(args.out, "kernel_trace.json"), result)
    pu = result["per_update_us"]
    print(f"{result['device']}: {result['kernels_per_update']:.1f} kernels per update, "
          f"busy {result['busy_fraction']:.1%} of the traced window; per update "
          f"{pu['window']:.1f} us ({pu['busy']:.1f} busy); mean kernel "
          f"{result['mean_kernel_us']:.2f} us, mean gap {result['mean_gap_us']:.2f} us; "
          f"step {timing.get('step_ms', float('nan')):.2f} ms untraced", flush=True)
    for h in result["heaviest"]:
        print(f"  {h['total_ms']:9.3f} ms {h['count']:7d} x {h['mean_us']:8.2f} us  {h['name']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
