"""Time `rl2s diagnose` on a dataset of the issue's size bound: 50k transitions, 20 state
dims, 6 action dims (five two-mass systems side by side, one of them with an actuation delay,
actions truncated to the first 6).

    python experiments/diagnose_speed.py --out DIR      # writes DIR/speed.npz, runs the CLI
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from rl2s_jax.cli import main as rl2s
from rl2s_jax.data import Dataset, save_dataset
from rl2s_jax.diagnose.planted import make_planted


def speed_dataset(n_episodes: int = 834) -> Dataset:
    """[n_episodes * 60, 20] obs, 6 actions."""
    parts = [make_planted(e, n_episodes=n_episodes, seed=i)
             for i, e in enumerate(["delay", "clean", "clean", "clean", "clean"])]
    arrays = dict(parts[0].arrays())
    for k in ("obs", "next_obs", "action"):
        arrays[k] = np.concatenate([getattr(p, k) for p in parts], 1)
    arrays["action"] = arrays["action"][:, :6]
    meta = dict(parts[0].meta, obs_size=20, action_size=6)
    return Dataset.from_arrays(arrays, meta)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "speed.npz")
    ds = speed_dataset()
    save_dataset(path, ds)
    print(f"{ds.n_transitions} transitions, obs {ds.obs_size}, action {ds.action_size}")
    t0 = time.perf_counter()
    rc = rl2s(["diagnose", "--data", path, "--out", os.path.join(args.out, "diag"), "--quiet"])
    print(f"rl2s diagnose: {time.perf_counter() - t0:.1f}s (exit {rc})")
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
