"""How far this CPU's MJX physics moves `make hopper`'s true values (RESULTS, "`make hopper` on
the CPU"): collects the CPU profile's Hopper test data (seed 0) and prints the largest
|difference| of its true values (100 steps, gamma 0.999, as the report's) from each committed
report's.

    python experiments/cpu_values.py [--report docs/results/hopper_cpu_profile.json ...]
    XLA_FLAGS=--xla_cpu_max_isa=AVX2 python experiments/cpu_values.py   # XLA's ISA capped
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from rl2s_jax.app.pipeline import PROFILES, collect_dataset
from rl2s_jax.app.report import machine_info
from rl2s_jax.data.values import true_values

REPORTS = ("docs/results/hopper_cpu_profile.json", "docs/results/hopper_cpu_profile_avx512.json")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--report", action="append", help="a make hopper report.json (default: "
                    "the two committed ones)")
    args = ap.parse_args(argv)
    reports = args.report or list(REPORTS)
    refs = {}
    for path in reports:
        with open(path) as f:
            rep = json.load(f)
        first = next(iter(rep["evaluations"].values()))
        refs[path] = (np.asarray(first["true_value"], np.float64), first["horizon"],
                      first["gamma"])
    sizes = PROFILES["cpu"]
    ds = collect_dataset("hopper", "test", sizes["transitions_per_policy"], seed=0,
                         value_episodes=sizes["value_episodes"], progress=False)
    print(f"machine {machine_info()}, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    for path, (ref, horizon, gamma) in refs.items():
        mine = true_values(ds, horizon, gamma)
        print(f"true values ({len(mine)} test policies, {horizon} steps, gamma {gamma}): "
              f"max |this machine - {path}| = {np.abs(mine - ref).max():.4g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
