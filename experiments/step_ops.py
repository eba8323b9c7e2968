"""How many ops the compiled train_step runs per update: the top-level ops of each update loop's
body in XLA's optimised program (issue 63: the one-lane chain of small updates is
launch-bound on the GPU, where each top-level fusion, dot or custom call is a kernel launch).

    python experiments/step_ops.py [--method rl2s] [--official-sizes] [--set field=value ...]
        [--json OUT]

Compiles ``train_steps(state, data, 1)`` at the GPU profile's config (bench_train.py's, its
``fake_data`` with 17 policies) on this machine's backend and prints, for every loop of the
program that runs ``updates_per_step`` or ``disc_updates`` times, the count of its body's
top-level ops by kind (parameters, tuples, bitcasts and constants left out: no work), the
largest first. The CPU's random-bit generator runs its hash as a loop of 5 rounds too: those
loops (``RANDOM`` in their op_name) are left out. A count, not a time: the CPU's fusions differ
from the GPU's, so compare settings on one backend.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from collections import Counter

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bench_train as bt  # noqa: E402
import jax  # noqa: E402

from rl2s_jax.app.training import parse_overrides  # noqa: E402
from rl2s_jax.train.config import TrainConfig  # noqa: E402
from rl2s_jax.train.step import init, train_steps  # noqa: E402

# the CPU's random-bit generator hashes in a loop of 5 rounds: not an update loop
RANDOM = re.compile(r"_threefry|_uniform|_randint|_gumbel|_normal|random_bits")
NO_WORK = {"parameter", "tuple", "get-tuple-element", "bitcast", "constant", "after-all"}
_HEAD = re.compile(r"^(?:ENTRY )?%([\w.\-]+) \(")
_OP = re.compile(r"^\s+(?:ROOT )?%[\w.\-]+ = .*? ([a-z][\w\-]*)\(")


def computations(hlo: str) -> dict[str, list[str]]:
    """XLA's optimised HLO text -> {computation name: its instruction lines}."""
    out, cur = {}, None
    for line in hlo.splitlines():
        m = _HEAD.match(line)
        if m:
            cur = out[m.group(1)] = []
        elif cur is not None and line.startswith("  "):
            cur.append(line)
    return out


def top_ops(lines: list[str]) -> list[tuple[str, str]]:
    """(opcode, line) of the instructions that do work."""
    found = ((m.group(1), line) for line in lines if (m := _OP.match(line)))
    return [(op, line) for op, line in found if op not in NO_WORK]


def update_loops(hlo: str, trips: set[int]) -> list[dict]:
    """Every while loop whose known trip count is in ``trips`` (but the random-bit hash's):
    its trip count, op_name and its body's top-level ops by kind, the most ops first."""
    comps = computations(hlo)
    rows = []
    for lines in comps.values():
        for op, line in top_ops(lines):
            trip = re.search(r'"known_trip_count":\{"n":"(\d+)"\}', line)
            name = re.search(r'op_name="([^"]+)"', line)
            if (op != "while" or not trip or int(trip.group(1)) not in trips
                    or (name and RANDOM.search(name.group(1)))):
                continue
            body = re.search(r"body=%([\w.\-]+)", line).group(1)
            kinds = Counter(o for o, _ in top_ops(comps[body]))
            rows.append({"trip_count": int(trip.group(1)), "ops": sum(kinds.values()),
                         "kinds": dict(kinds.most_common()),
                         "op_name": name.group(1)[-90:] if name else ""})
    return sorted(rows, key=lambda r: -r["ops"])


def step_loops(cfg: TrainConfig, n_policies: int = 17) -> list[dict]:
    """``update_loops`` of ``train_steps(state, data, 1)`` compiled for ``cfg`` on bench_train's
    ``fake_data`` (Hopper's shapes) on this machine's backend."""
    data = bt.fake_data(n_policies)
    state = jax.jit(init, static_argnums=1)(jax.random.PRNGKey(0), cfg, data)
    hlo = jax.jit(lambda s: train_steps(s, data, 1)[0]).lower(state).compile().as_text()
    trips = {cfg.updates_per_step} | ({cfg.adversarial.disc_updates} if cfg.is_adversarial
                                      else set())
    return update_loops(hlo, trips)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="rl2s", choices=("rl2s", "gail", "bc", "rl2s-bc"))
    ap.add_argument("--official-sizes", action="store_true",
                    help="bench_train.py's OFFICIAL_SIZES (one 4x512 generator, batch 256)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    cfg = TrainConfig().override({"task": "hopper", "method": args.method,
                                  "adversarial.pretrain_steps": 0,
                                  "adversarial.disc_warmup_steps": 0})
    if args.official_sizes:
        cfg = cfg.override(bt.OFFICIAL_SIZES)
    try:
        cfg = cfg.override(parse_overrides(args.set), "--set").validate()
    except ValueError as err:
        raise SystemExit(f"step_ops.py: {err}") from None
    rows = step_loops(cfg)
    print(f"step_ops: {args.method}, {' '.join(args.set) or 'defaults'}"
          f"{', official sizes' if args.official_sizes else ''} on {jax.default_backend()}")
    for r in rows:
        print(f"  loop x{r['trip_count']}: {r['ops']} ops {r['kinds']}  [{r['op_name']}]")
    if args.json:
        from rl2s_jax._files import write_json
        write_json(args.json, {"method": args.method, "set": args.set,
                               "official_sizes": args.official_sizes,
                               "backend": jax.default_backend(),
                               "device": jax.devices()[0].device_kind, "loops": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
