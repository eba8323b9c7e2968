"""Where the time of the physics diagnosis goes, and its two Jacobian backends side by side
(issue 62, items 2 and 7): record C-MuJoCo Hopper transitions from the shipped zoo's training
policies with one planted change, run ``rl2s diagnose --physics`` on them (its default backend,
C MuJoCo with finite differences), then the same identification with the MJX backend
(``jax.jacfwd`` through ``mjx.step``) twice (cold: with its compilation; warm), and, where
``mujoco.sysid`` is installed, ``fit_sysid`` on the quantity found.

    python experiments/physics_timing.py --out DIR [--transitions 50000]
        [--plant body_mass:torso:1.3] [--rows 256] [--backends mujoco mjx] [--no-sysid]

Writes DIR/timing.json (seconds per stage, what each backend named with its value and
interval, the device, the command).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax

from rl2s_jax._files import write_text
from rl2s_jax.app.physics_diagnosis import PhysicsSpec, diagnose_physics
from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.physics.identify import FitConfig, fit_sysid, identify
from rl2s_jax.physics.measured import Planted, collect_measured
from rl2s_jax.physics.mjx_model import physics_model
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo


def planted(text: str) -> Planted:
    """NAME:ELEMENT:VALUE -> Planted (e.g. body_mass:torso:1.3)."""
    try:
        name, element, value = text.split(":")
        value = int(value) if name == "action_delay" else float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"plant: expected NAME:ELEMENT:VALUE, got {text!r}") from None
    return Planted(name, element, value)


def _named(found: dict) -> dict | None:
    top = found["top_cause"]
    return None if top is None else {k: top[k] for k in ("name", "element", "value",
                                                          "interval")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--transitions", type=int, default=50_000)
    ap.add_argument("--plant", type=planted, default=planted("body_mass:torso:1.3"))
    ap.add_argument("--rows", type=int, default=256)
    ap.add_argument("--backends", nargs="+", default=["mujoco", "mjx"],
                    choices=["mujoco", "mjx"])
    ap.add_argument("--no-sysid", action="store_true")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    out = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
           "plant": dataclasses.asdict(args.plant), "rows": args.rows,
           "command": "python experiments/physics_timing.py " + " ".join(argv or sys.argv[1:])}

    pm = physics_model("hopper")
    zoo = load_zoo("hopper")
    ids = zoo.split_ids("train")
    t0 = time.perf_counter()
    ds = collect_measured(pm, index_params(zoo.params, ids),
                          transitions_per_policy=-(-args.transitions // len(ids)),
                          episode_length=1000, seed=0, changes=[args.plant],
                          policy_names=zoo.policy_names(ids),
                          source={"zoo": "hopper", "split": "train", "zoo_ids": ids})
    out["collect_s"] = round(time.perf_counter() - t0, 1)
    out["transitions"] = ds.n_transitions
    data = os.path.join(args.out, "data.npz")
    save_dataset(data, ds)
    print(f"[physics-timing] {ds.n_transitions} transitions ({out['collect_s']} s)", flush=True)

    t0 = time.perf_counter()
    report = diagnose_physics(PhysicsSpec(data=data, out=os.path.join(args.out, "report"),
                                          fit=FitConfig(rows=args.rows), quiet=True))
    out["diagnose_physics_s"] = round(time.perf_counter() - t0, 1)
    out["diagnose_physics_named"] = report["physics"]["top_cause"]
    print(f"[physics-timing] diagnose --physics: {out['diagnose_physics_s']} s, "
          f"{out['diagnose_physics_named']}", flush=True)

    chosen = None
    for backend in args.backends:
        for run in ("cold", "warm"):
            t0 = time.perf_counter()
            found = identify(pm, ds, FitConfig(rows=args.rows, backend=backend))
            seconds = round(time.perf_counter() - t0, 1)
            out[f"identify_{backend}_{run}_s"] = seconds
            out[f"identify_{backend}_named"] = _named(found)
            print(f"[physics-timing] identify {backend} {run}: {seconds} s, {_named(found)}",
                  flush=True)
            if found["top_cause"] is not None and chosen is None:
                chosen = [(p["name"], p["element"]) for p in found["parameters"]
                          if p.get("significant") and p["name"] != "action_delay"]
    if chosen and not args.no_sysid:
        try:
            fit = fit_sysid(pm, ds, chosen, cfg=FitConfig(rows=args.rows))
            out["sysid"] = {"chosen": chosen, "values": fit["values"],
                            "seconds": round(fit["seconds"], 2)}
        except (ImportError, AttributeError) as err:  # mujoco[sysid] not installed
            out["sysid"] = f"not run: {err}"
        print(f"[physics-timing] sysid: {out['sysid']}", flush=True)
    write_text(os.path.join(args.out, "timing.json"), json.dumps(out, indent=1, default=str))
    print(json.dumps(out, indent=1, default=str), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
