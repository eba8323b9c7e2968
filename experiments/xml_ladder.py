"""What each difference between two MJCF models explains of a dataset's one-step error: the
task's MJX XML with Gymnasium v5's differences put in one at a time (RESULTS rows 9 and 10:
v5's Ant and Walker2d against MJX's XMLs; these were scratch checks before).

    python experiments/xml_ladder.py --data DIR/ant/v5.npz --task ant [--json out.json]

Each rung applies one more edit of the XML text to the task's XML (mjx_model.task_xml) and
measures that model's errors on the data with ``residuals.physics_errors`` (C MuJoCo; the
rows, windows and normalisation of `rl2s diagnose --physics`'s report): the one-step RMSE over
all dims, in and out of contact, and the 10-step open-loop RMSE. Every rung is the task's
physics model (its frame count and observation convention) with the edited XML's compiled
model in place of the task's. After the last rung, v5's compiled model is compared with it
(gymnasium_v5.model_differences): what is left should be no physics (float64 against MJX's
float32, and Walker2d's rootz reference, a coordinate convention). The data come from
``experiments/gymnasium_v5.py --diagnose DIR`` (DIR/<task>/v5.npz).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
import xml.etree.ElementTree as ET

from rl2s_jax._files import write_json
from rl2s_jax.data.dataset import load_dataset
from rl2s_jax.physics.mjx_model import physics_model, task_xml
from rl2s_jax.physics.residuals import physics_errors


def _option(**attrs):
    def edit(root):
        option = root.find("option")
        if option is None:
            option = ET.SubElement(root, "option")
        option.attrib.update(attrs)
    return edit


def _every_geom(**attrs):
    def edit(root):
        for g in root.iter("geom"):
            g.attrib.update(attrs)
    return edit


def _delete(*names):
    def edit(root):
        for parent in list(root.iter()):
            for child in list(parent):
                if child.tag == "geom" and child.get("name") in names:
                    parent.remove(child)
    return edit


def _friction(name, value):
    def edit(root):
        g = next(g for g in root.iter("geom") if g.get("name") == name)
        rest = (g.get("friction") or "1 0.005 0.0001").split()[1:]
        g.set("friction", " ".join([str(value), *rest]))
    return edit


def _joint_range(value, *names):
    def edit(root):
        for j in root.iter("joint"):
            if j.get("name") in names:
                j.set("range", value)
    return edit


# (label, edit of the XML tree) applied one after another: Gymnasium v5's differences from
# MJX's XML, each read off the two files (and gymnasium_v5.py's table of the compiled models'
# differences). v5: RK4, the default solver's 100 iterations; Ant: margin 0.01 on every geom,
# every geom colliding (contype 1 against the floor's conaffinity 1), no foot spheres;
# Walker2d: the right foot's friction 1.9, every geom colliding, the knee and hip ranges of
# -150 degrees (brax's file writes -2.61799 rad). Not a rung: Walker2d's rootz reference
# (v5 qpos0 1.25, MJX 0), a coordinate convention the observation map takes care of.
LADDERS = {
    "ant": [("RK4", _option(integrator="RK4")),
            ("margin 0.01 on every geom", _every_geom(margin="0.01")),
            ("every geom colliding", _every_geom(contype="1")),
            ("no foot spheres", _delete("left_foot_geom", "right_foot_geom", "third_foot_geom",
                                        "fourth_foot_geom")),
            ("100 solver iterations", _option(iterations="100"))],
    "walker2d": [("RK4", _option(integrator="RK4")),
                 ("foot_geom friction 1.9", _friction("foot_geom", 1.9)),
                 ("every geom colliding", _every_geom(contype="1")),
                 ("100 solver iterations", _option(iterations="100")),
                 ("hip and knee ranges, full digits",
                  _joint_range(f"{-150 * math.pi / 180!r} 0", "thigh_joint", "leg_joint",
                               "thigh_left_joint", "leg_left_joint"))],
}


def rung_model(task_model, xml: str):
    """The task's PhysicsModel ``task_model`` with the compiled ``xml`` (an edit of its XML)
    in its place (its frame count and observation convention kept)."""
    import dataclasses

    import mujoco
    from mujoco import mjx

    from rl2s_jax.physics.mjx_model import candidates_of

    mj = mujoco.MjModel.from_xml_string(xml)
    return dataclasses.replace(task_model, mj=mj, mjx_model=mjx.put_model(mj),
                               candidates=candidates_of(mj))


def errors_of(pm, ds, k: int) -> dict:
    """A model's errors on the data: {"one_step", "in_contact", "out_of_contact",
    "kstep_last"} (normalised RMSEs)."""
    e = physics_errors(pm, ds, k=k)
    return {"one_step": e["one_step"]["rmse"], "in_contact": e["one_step"]["contact"]["in"],
            "out_of_contact": e["one_step"]["contact"]["out"], "kstep_last": e["kstep"][-1]}


def rung_xmls(task: str) -> list[tuple[str, str]]:
    """The ladder's MJCF texts: [(label, xml)], the task's XML first, then each edit of
    LADDERS[task] added to the ones before it. The file is edited as XML text, so every
    number not edited stays as written (MjSpec.to_xml would round them to 6 digits)."""
    tree = ET.parse(task_xml(task))
    out = [("the task's MJX XML", ET.tostring(tree.getroot(), encoding="unicode"))]
    for label, edit in LADDERS[task]:
        edit(tree.getroot())
        out.append(("+ " + label, ET.tostring(tree.getroot(), encoding="unicode")))
    return out


def ladder(task: str, ds, k: int = 10, log=print) -> tuple[list[dict], list[dict]]:
    """The ladder (module docstring) -> ([{"rung", **errors_of}], v5's differences from the
    last rung)."""
    from rl2s_jax.physics.gymnasium_v5 import model_differences

    rows, nominal = [], physics_model(task)
    for i, (label, xml) in enumerate(rung_xmls(task)):
        pm = nominal if i == 0 else rung_model(nominal, xml)
        rows.append({"rung": label, **errors_of(pm, ds, k)})
        log(f"  {label:<40} one-step {rows[-1]['one_step']:.3g}", flush=True)
    return rows, model_differences(task, model=pm.mj)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="a Dataset .npz of the task (v5.npz)")
    ap.add_argument("--task", required=True, choices=sorted(LADDERS))
    ap.add_argument("--k", type=int, default=10, help="open-loop window (steps)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    if not os.path.isfile(args.data):
        raise SystemExit(f"xml_ladder.py: --data: expected a Dataset .npz, got {args.data!r}")
    ds = load_dataset(args.data)
    if ds.meta.get("task") not in (None, args.task):
        raise SystemExit(f"xml_ladder.py: --data: its task is {ds.meta.get('task')!r}, "
                         f"expected {args.task!r}")
    start = time.perf_counter()
    print(f"{args.task}: {ds.n_transitions} transitions; one-step error (normalised RMSE, "
          f"C MuJoCo) of each XML:", flush=True)
    rows, left = ladder(args.task, ds, args.k)
    print("left between v5's compiled model and the last rung: " + "; ".join(
        f"{d['quantity']} {d['element']} {d['mjx']} / {d['v5']}".replace("  ", " ")
        for d in left), flush=True)
    if args.json:
        write_json(args.json, {"task": args.task, "data": args.data, "k": args.k,
                               "rows": rows, "left_differences": left,
                               "seconds": time.perf_counter() - start})
    return 0


if __name__ == "__main__":
    sys.exit(main())
