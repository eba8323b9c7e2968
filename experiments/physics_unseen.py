"""Planted C-MuJoCo Hopper changes that no test and no physics_gain.py CASES entry uses, each
diagnosed through the command line as a user would run it (issue 62, "done when").

The cases and their amounts were fixed here before any of them was run (2026-11-28): elements
and amounts that tests/test_physics.py, tests/test_physics_simulator.py and physics_gain.py's
CASES (torso mass x1.3, foot_geom friction x0.6, leg_joint gear x0.7, foot_joint damping x3,
thigh_joint delay 2) do not plant:

    thigh_mass      body_mass[thigh]        x0.75 (lighter)
    leg_damping     dof_damping[leg_joint]  x2.5
    foot_friction   geom_friction[foot_geom] x1.5 (higher: the CASES entry is lower)
    thigh_gear      actuator_gear[thigh_joint] x1.2 (stronger: the CASES entry is weaker)
    foot_armature   dof_armature[foot_joint] x2 (no test plants armature)
    foot_delay      action_delay[foot_joint] 1 step
    clean           nothing planted (another collection seed than the tests')

Per case: ``collect_measured`` records the shipped zoo's training policies in the planted C
model (``--transitions`` per policy, ``--episode-length``-step episodes, collection seed
``--seed``), saved as D.npz; then ``rl2s diagnose --data D.npz --physics --out DIR --quiet``
runs in its own process. The check: the top cause names the planted quantity and element,
its value within 10% of the truth (a delay exactly); the clean case names nothing. Writes
``--out`` (JSON: per case the truth, what was found, the check, the diagnosis' own seconds
and the command's wall seconds) with the command and the machine.

    PYTHONPATH=. python experiments/physics_unseen.py --work /tmp/unseen \
        --out docs/results/physics_unseen.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import mujoco

from rl2s_jax._files import write_json
from rl2s_jax.app.report import machine_info
from rl2s_jax.data.dataset import save_dataset
from rl2s_jax.physics.measured import Planted, collect_measured
from rl2s_jax.physics.mjx_model import physics_model
from rl2s_jax.policy.policy import index_params
from rl2s_jax.zoo.zoo import load_zoo

UNSEEN = {
    "thigh_mass": [("body_mass", "thigh", 0.75)],
    "leg_damping": [("dof_damping", "leg_joint", 2.5)],
    "foot_friction": [("geom_friction", "foot_geom", 1.5)],
    "thigh_gear": [("actuator_gear", "thigh_joint", 1.2)],
    "foot_armature": [("dof_armature", "foot_joint", 2.0)],
    "foot_delay": [("action_delay", "foot_joint", 1)],
    "clean": [],
}


def check(truth: list[dict], top: dict | None) -> dict:
    """Whether the top cause is the planted change: {"named", "value_ok", "passed"} (clean:
    passed when nothing is named; value within 10%, a delay exactly)."""
    if not truth:
        return {"named": top is None, "value_ok": None, "passed": top is None}
    want = truth[0]
    named = top is not None and (top["name"], top["element"]) == (want["name"], want["element"])
    if not named:
        return {"named": False, "value_ok": False, "passed": False}
    if want["name"] == "action_delay":
        ok = int(round(top["value"])) == int(want["value"])
    else:
        ok = abs(top["value"] - want["value"]) <= 0.1 * abs(want["value"])
    return {"named": True, "value_ok": bool(ok), "passed": bool(ok)}


def run_case(case: str, pm, zoo, args) -> dict:
    """Collect, save and diagnose one case through the CLI -> its row of the JSON."""
    folder = os.path.join(args.work, case)
    os.makedirs(folder, exist_ok=True)
    ids = list(zoo.train_ids)
    ds = collect_measured(pm, index_params(zoo.params, ids), seed=args.seed,
                          transitions_per_policy=args.transitions,
                          episode_length=args.episode_length,
                          changes=[Planted(*c) for c in UNSEEN[case]],
                          policy_names=zoo.policy_names(ids),
                          source={"zoo": "hopper", "zoo_ids": ids})
    data = os.path.join(folder, "D.npz")
    save_dataset(data, ds)
    cli = ["diagnose", "--data", data, "--physics", "--out", os.path.join(folder, "diag"),
           "--quiet", "--force"]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "rl2s_jax.cli", *cli], check=True)
    wall = time.perf_counter() - t0
    with open(os.path.join(folder, "diag", "report.json")) as f:
        physics = json.load(f)["physics"]
    top = physics["top_cause"]
    truth = ds.meta["source"]["planted"]
    found = None if top is None else {k: top[k] for k in ("name", "element", "nominal",
                                                          "value", "interval")}
    return {"case": case, "truth": truth, "found": found, **check(truth, top),
            "significant": [f"{p['name']}[{p['element']}]" for p in physics["parameters"]
                            if p.get("significant")],
            "unexplained": physics["unexplained"], "diagnose_seconds": physics["seconds"],
            "command_seconds": wall, "command": "rl2s " + " ".join(cli),
            "transitions": ds.n_transitions}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=list(UNSEEN), choices=list(UNSEEN))
    ap.add_argument("--transitions", type=int, default=300, help="per training policy")
    ap.add_argument("--episode-length", type=int, default=100)
    ap.add_argument("--seed", type=int, default=7, help="collection seed")
    ap.add_argument("--work", required=True, help="folder for the data and the reports")
    ap.add_argument("--out", required=True, help="the JSON written")
    args = ap.parse_args(argv)
    pm, zoo = physics_model("hopper"), load_zoo("hopper")
    rows = []
    for case in args.cases:
        row = run_case(case, pm, zoo, args)
        rows.append(row)
        print(f"{case}: truth {row['truth']}; found {row['found']}; passed {row['passed']} "
              f"({row['command_seconds']:.1f} s)", flush=True)
        machine = {**machine_info(), "cpu_count": os.cpu_count(), "mujoco": mujoco.__version__}
        sizes = {"transitions_per_policy": args.transitions, "episode_length": args.episode_length,
                 "policies": len(zoo.train_ids), "seed": args.seed}
        doc = {"command": "PYTHONPATH=. python experiments/physics_unseen.py " + " ".join(argv),
               "machine": machine, "sizes": sizes, "cases": rows}
        write_json(args.out, doc)
    failed = [r["case"] for r in rows if not r["passed"]]
    print(f"{len(rows) - len(failed)} of {len(rows)} passed; failed: {failed or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
