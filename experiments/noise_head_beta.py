"""The noise extension's training loss: held-out NLL and MSE of the base model and of the
state-dependent noise head trained with beta-NLL at several beta, on one saved recording.

    python experiments/diagnose_hopper.py --out DIR --reference --effects noise \
        --seeds 1 --value-episodes 0 --save-data
    python experiments/noise_head_beta.py DIR/noise/data.npz [--betas 0 0.5 1] [--seeds 2]

The fit / held-out split is diagnose's (30% of the episodes held out, split seed 0).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from rl2s_jax.data import load_dataset
from rl2s_jax.diagnose.episodes import from_dataset, split_episodes
from rl2s_jax.diagnose.model import ModelSpec, fit_models, heldout_metrics


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="a dataset file (save_dataset)")
    ap.add_argument("--betas", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args(argv)
    eps = from_dataset(load_dataset(args.data))
    fit_eps, held_eps = split_episodes(eps, 0.3, 0, min_length=2)
    held_rows = eps.rows(held_eps)
    specs = [("base (global std)", ModelSpec())] + [
        (f"noise=state, nll_beta={b:g}", ModelSpec(noise="state", nll_beta=b))
        for b in args.betas]
    print("| model | held-out NLL per seed | held-out MSE per seed | seconds |\n|---|---|---|---:|")
    for name, spec in specs:
        t0 = time.perf_counter()
        m = heldout_metrics(fit_models(eps, fit_eps, spec, seeds=tuple(range(args.seeds))),
                            eps, held_rows)
        print(f"| {name} | {np.round(np.asarray(m['nll']), 3).tolist()} | "
              f"{np.round(np.asarray(m['mse']), 4).tolist()} | "
              f"{time.perf_counter() - t0:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
