"""Processes sharing one GPU (issue 63): does a second process on the same GPU add throughput
or only split it, with and without NVIDIA's Multi-Process Service (MPS)? `device.sh share`
runs the cases side by side in one call and prints the summary.

Each process compiles the protocol's adversarial family step (``--lanes`` runs vmapped as one
program, as the protocol's RL2S and GAIL lanes over its seeds; ``--policies`` training
policies; the profile's sizes, pre-training off as in bench_train.py), writes
BARRIER/ready_<id>, waits until ``--n`` processes are ready, then calls ``--steps``
train_steps back to back for ``--seconds`` and writes one JSON line: the mean ms of one step
of the whole program (all lanes) over the timed calls.

    python experiments/gpu_share.py --barrier DIR --n 2 --id 0 [--lanes 6] [--policies 17]
        [--steps 10] [--seconds 30] [--profile auto|cpu|gpu] --json DIR/pair_0.json
    python experiments/gpu_share.py --summary DIR    the ratios of DIR's <case>_<id>.json

The summary's ``throughput`` of a case is the steps all its processes finish per second over
what one process alone finishes (2.0: a second process on the GPU costs the first nothing;
1.0: the GPU is only split).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import time

CASES = ("alone", "pair", "mps_alone", "mps_pair")


def wait_barrier(directory: str, n: int, me: int, timeout_s: float = 900.0) -> None:
    """Mark process ``me`` ready in ``directory`` and wait until ``n`` processes are."""
    os.makedirs(directory, exist_ok=True)
    open(os.path.join(directory, f"ready_{me}"), "w").close()
    t0 = time.monotonic()
    while len(glob.glob(os.path.join(directory, "ready_*"))) < n:
        if time.monotonic() - t0 > timeout_s:
            raise SystemExit(f"barrier: {n} processes expected in {directory}, "
                             f"{len(glob.glob(os.path.join(directory, 'ready_*')))} came")
        time.sleep(0.05)


def summarize(directory: str) -> dict:
    """{case: {processes, step_ms (mean over processes), throughput vs "alone"}} from the
    ``<case>_<id>.json`` files of ``directory``; a case without files is left out."""
    by_case: dict[str, list[float]] = {}
    for path in sorted(glob.glob(os.path.join(directory, "*.json"))):
        m = re.fullmatch(r"(" + "|".join(CASES) + r")_(\d+)\.json", os.path.basename(path))
        if m:
            by_case.setdefault(m.group(1), []).append(json.load(open(path))["step_ms"])
    if "alone" not in by_case:
        raise SystemExit(f"summary: expected {directory}/alone_0.json (one process alone, the "
                         f"reference), found {sorted(by_case) or 'no case'}")
    ref = by_case["alone"][0]
    return {case: {"processes": len(ms), "step_ms": sum(ms) / len(ms),
                   "throughput": sum(ref / x for x in ms)}
            for case in CASES if case in by_case for ms in [by_case[case]]}


def measure(args: argparse.Namespace) -> dict:
    """Compile the family step, meet the others at the barrier, time it (see the module
    docstring)."""
    import jax
    from bench_train import fake_data

    from rl2s_jax.train.config import TrainConfig
    from rl2s_jax.train.step import init, train_steps

    profile = args.profile if args.profile != "auto" else (
        "gpu" if jax.default_backend() == "gpu" else "cpu")
    base = TrainConfig() if profile == "gpu" else TrainConfig.small()
    cfg = base.override({"task": "hopper", "method": "rl2s", "adversarial.pretrain_steps": 0,
                         "adversarial.disc_warmup_steps": 0}).validate()
    data = fake_data(args.policies)
    keys = jax.random.split(jax.random.PRNGKey(args.id), args.lanes)
    state = jax.jit(jax.vmap(lambda k: init(k, cfg, data)))(keys)
    run = jax.jit(jax.vmap(lambda s: train_steps(s, data, args.steps)[0]))
    t0 = time.perf_counter()
    state = jax.block_until_ready(run(state))
    compile_s = time.perf_counter() - t0
    wait_barrier(args.barrier, args.n, args.id)
    calls, t0 = 0, time.perf_counter()
    while calls == 0 or time.perf_counter() - t0 < args.seconds:
        state = jax.block_until_ready(run(state))
        calls += 1
    wall = time.perf_counter() - t0
    return {"id": args.id, "n": args.n, "lanes": args.lanes, "policies": args.policies,
            "profile": profile, "device": jax.devices()[0].device_kind,
            "jax": jax.__version__, "mps": bool(os.environ.get("CUDA_MPS_PIPE_DIRECTORY")),
            "calls": calls, "timed_s": wall, "step_ms": 1e3 * wall / (calls * args.steps),
            "compile_s": compile_s}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--summary", metavar="DIR", help="print the ratios of DIR's case files")
    ap.add_argument("--barrier", help="the folder where the processes meet")
    ap.add_argument("--n", type=int, default=1, help="processes that meet at the barrier")
    ap.add_argument("--id", type=int, default=0)
    ap.add_argument("--lanes", type=int, default=6)
    ap.add_argument("--policies", type=int, default=17)
    ap.add_argument("--steps", type=int, default=10, help="train_steps per timed call")
    ap.add_argument("--seconds", type=float, default=30.0, help="timed calls for this long")
    ap.add_argument("--profile", choices=("auto", "cpu", "gpu"), default="auto")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    if args.summary:
        table = summarize(args.summary)
        for case, row in table.items():
            print(f"{case:>10}: {row['processes']} process(es), {row['step_ms']:8.2f} ms per "
                  f"step, throughput {row['throughput']:.2f}x one process alone")
        from rl2s_jax._files import write_json
        write_json(os.path.join(args.summary, "share_summary.json"), table)
        return 0
    for field in ("n", "lanes", "policies", "steps"):
        if getattr(args, field) < 1:
            ap.error(f"--{field}: expected a whole number >= 1, got {getattr(args, field)}")
    if not args.barrier or not 0 <= args.id < args.n:
        ap.error(f"--barrier DIR and 0 <= --id < --n expected, got {args.barrier!r}, id "
                 f"{args.id}, n {args.n}")
    row = measure(args)
    print(json.dumps(row), flush=True)
    if args.json:
        from rl2s_jax._files import write_json
        write_json(args.json, row, indent=None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
