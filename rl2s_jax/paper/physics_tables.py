"""The "Physics diagnosis (issue 62)" block of docs/RESULTS.md, from docs/results/
physics_gain.json (experiments/physics_gain.py), physics_unseen.json (physics_unseen.py) and
gymnasium_v5.json (gymnasium_v5.py's rows: ``v5_row``, merged by ``merge_v5_row``). Pure
Python; uses no JAX. Each table with the command and machine it came from.
"""

from __future__ import annotations

import json
import os

from rl2s_jax._files import write_json
from rl2s_jax.paper.simulator_gain import gain_rows
from rl2s_jax.physics.identify import format_quantity, format_value

__all__ = ["PHYSICS_BEGIN", "PHYSICS_END", "physics_block", "v5_row", "merge_v5_row"]

PHYSICS_BEGIN, PHYSICS_END = "<!-- physics-tables:begin -->", "<!-- physics-tables:end -->"


def _load(results: str, name: str) -> dict | None:
    path = os.path.join(results, name)
    if not os.path.exists(path):
        return None
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def _machine(m: dict | str | None) -> str:
    """A result's machine in words: a string as it is; machine_info's dict (plus cpu_count,
    mujoco where the script added them) as "NVIDIA H200 ..." or "CPU AMD EPYC (AVX512), 2
    cores", with its versions."""
    if isinstance(m, str) or m is None:
        return m or "?"
    cores = f", {m['cpu_count']} cores" if m.get("cpu_count") else ""
    where = (f"CPU {m.get('cpu', '?')} ({m.get('cpu_isa', '?')}){cores}"
             if m.get("backend") == "cpu" else f"{m.get('device', '?')}, host CPU "
             f"{m.get('cpu', '?')}{cores}")
    versions = f"jax {m.get('jax', '?')}" + (f", mujoco {m['mujoco']}" if m.get("mujoco") else "")
    return f"{where}; {versions}"


def _num(x, fmt: str = ".3g") -> str:
    return "n/a" if x is None else f"{x:{fmt}}"


def _gain_lines(doc: dict | None, source: str) -> list[str]:
    if doc is None:
        return [f"Not measured yet (`{source}/physics_gain.json`, from "
                "`experiments/physics_gain.py --out`)."]
    args = doc.get("args", {})
    cut = ("" if doc.get("complete", True) else
           f"INCOMPLETE run ({doc.get('units_done', '?')} case-seed units done). ")
    if args.get("profile") == "cpu":
        cut += ("A check of the code at CPU sizes, not the table (the `gpu` profile makes it: "
                "experiments/physics_gain.py's docstring). ")
    note = f". {doc['note'].rstrip('.')}" if doc.get("note") else ""
    return [f"{cut}`{doc['command']}` on {_machine(doc.get('machine'))}, "
            f"{doc.get('seconds', 0):.0f} s{note}"
            f"; profile {args.get('profile', '?')}: "
            f"{args.get('transitions', '?')} transitions per training policy, "
            f"{args.get('steps', '?')} training steps ({args.get('train_profile', '?')} "
            f"training profile), {args.get('episodes', '?')} value episodes of "
            f"{args.get('horizon', '?')} steps, gamma {args.get('gamma', '?')}, k "
            f"{args.get('k', '?')}. Cells: mean over collection seeds [95% t interval] "
            "(one seed: the mean alone). Learned simulators: their mean next state fed the "
            "logged actions (one- and k-step), sampled rollouts (values).", "",
            *gain_rows(doc["summary"])]


def _unseen_lines(doc: dict | None, source: str) -> list[str]:
    if doc is None:
        return [f"Not measured yet (`{source}/physics_unseen.json`)."]
    s = doc.get("sizes", {})
    lines = [f"`{doc['command']}` on {_machine(doc.get('machine'))}; "
             f"{s.get('policies', '?')} training policies x {s.get('transitions_per_policy')}"
             f" transitions, {s.get('episode_length')}-step episodes, collection seed "
             f"{s.get('seed')}. Each case: `rl2s diagnose --data D.npz --physics` as a user "
             "runs it; passed = the planted quantity and element named, value within 10% (a "
             "delay exactly), nothing named on clean data.", "",
             "| case | planted | found | value (truth) | interval | passed | seconds |",
             "|---|---|---|---|---|---|---|"]
    for c in doc["cases"]:
        t, f = (c["truth"] or [None])[0], c["found"]
        planted = "nothing" if t is None else f"{t['name']}[{t['element']}]"
        got = "nothing" if f is None else f"{f['name']}[{f['element']}]"
        value = ("-" if f is None else format_value(f["value"])
                 + ("" if t is None else f" ({format_value(t['value'])})"))
        ival = "-" if not (f and f.get("interval")) else (
            f"[{format_value(f['interval'][0])}, {format_value(f['interval'][1])}]")
        lines.append(f"| {c['case']} | {planted} | {got} | {value} | {ival} | "
                     f"{'yes' if c['passed'] else 'NO'} | {c['command_seconds']:.1f} |")
    return lines


def _v5_lines(doc: dict | None, source: str) -> list[str]:
    if doc is None:
        return [f"Not measured yet (`{source}/gymnasium_v5.json`)."]
    lines = [doc.get("note", ""), "",
             "| task | run | one-step (in / out of contact) | k-step | tau v5 vs MJX (noise "
             "floor) | AVD | MVD | physics diagnosis |", "|---|---|---|---|---|---|---|---|"]
    runs = []
    for i, r in enumerate(doc["rows"], 1):
        contact = (f" ({_num(r.get('one_step_in'))} / {_num(r.get('one_step_out'))})"
                   if r.get("one_step_in") is not None else "")
        tau = "not measured" if r.get("tau") is None else (
            f"{r['tau']:.3f}" + ("" if r.get("tau_floor") is None
                                 else f" ({r['tau_floor']:.3f})"))
        lines.append(f"| {r['task']} | {i} | {_num(r.get('one_step'))}{contact} | "
                     f"{_num(r.get('kstep'))} | {tau} | {_num(r.get('avd'), '.1f')} | "
                     f"{_num(r.get('mvd'), '.1f')} | {r.get('diagnosis') or 'not run'} |")
        cmds = r["command"] if isinstance(r["command"], list) else [r["command"]]
        runs.append(f"{i}. on {_machine(r.get('hardware'))}: "
                    + "; ".join(f"`{c}`" for c in cmds)
                    + (f". {r['notes']}" if r.get("notes") else ""))
    return lines + ["", "Runs:", "", *runs]


def physics_block(results: str, source: str) -> str:
    """The markdown block, markers included, from the JSON files in ``results`` (it names
    ``source`` as their folder); a missing file gives a "not measured yet" line."""
    lines = [PHYSICS_BEGIN, "## Physics diagnosis (issue 62) (generated by "
             "`experiments/paper_tables.py`)", "",
             f"Generated from `{source}/physics_gain.json`, `physics_unseen.json` and "
             "`gymnasium_v5.json` (do not edit between the markers). Method and the earlier "
             "nominal-vs-calibrated table: docs/DIAGNOSIS.md, \"Physics\".", "",
             "### The gain: physics and learned simulators on planted C-MuJoCo Hopper", "",
             *_gain_lines(_load(results, "physics_gain.json"), source), "",
             "### Planted changes no test has seen", "",
             *_unseen_lines(_load(results, "physics_unseen.json"), source), "",
             "### Gymnasium v5 (C MuJoCo, float64) against the MJX tasks' physics", "",
             *_v5_lines(_load(results, "gymnasium_v5.json"), source), PHYSICS_END]
    return "\n".join(lines) + "\n"


def v5_row(rec: dict, command: str, hardware: str) -> dict:
    """One task's row of gymnasium_v5.json from experiments/gymnasium_v5.py's record of it."""
    v5, values = rec["v5"], rec["values"]
    diag = rec.get("physics_diagnosis")
    if diag is None:
        what = None
    elif diag["top_cause"] is None:
        what = f"nothing named (unexplained {diag['unexplained']:.3f})"
    else:  # every quantity the diagnosis kept, in its order; the top cause where none listed
        kept = [p for p in diag.get("parameters") or () if p.get("significant")]
        named = "; ".join(format_quantity(p, interval=False)
                          for p in kept or [diag["top_cause"]])
        what = f"{named} (unexplained {diag['unexplained']:.3f})"
    return {"task": rec["task"], "command": command, "hardware": hardware,
            "one_step": v5["one_step_mean"], "one_step_in": v5.get("one_step_in_contact"),
            "one_step_out": v5.get("one_step_no_contact"), "kstep": v5["k_step_mean"],
            "tau": values["kendall_tau"], "tau_floor": rec.get("mjx_remeasured_vs_zoo_tau"),
            "avd": values["avd"], "mvd": values["mvd"], "diagnosis": what,
            "source": "written by experiments/gymnasium_v5.py --results"}


def merge_v5_row(path: str, row: dict) -> None:
    """Add ``row`` to the gymnasium_v5.json at ``path`` (created when absent), replacing an
    earlier row of the same task, command and hardware; other rows are kept."""
    doc = {"note": "", "rows": []}
    if os.path.exists(path):
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    same = lambda r: all(r.get(k) == row[k] for k in ("task", "command", "hardware"))  # noqa: E731
    doc["rows"] = [r for r in doc["rows"] if not same(r)] + [row]
    write_json(path, doc)
