"""Writes the generated part of docs/RESULTS.md: the paper's protocol tables from paper.py results.

    python experiments/paper_tables.py                  # rewrite docs/RESULTS.md's block
    python experiments/paper_tables.py --check          # exit 1 if that block is stale
    python experiments/paper_tables.py --results DIR --out FILE   # e.g. make paper's tables.md
    python experiments/paper_tables.py --guard DIR [DIR ...]      # the guard's table, printed

Design: docs/RESULTS.md holds two kinds of text. Everything between the markers BEGIN and END
below is generated here from RESULTS/<task>.json (the tasks hopper, walker2d, halfcheetah, ant
that are present) and replaced on every run; everything outside the markers is hand-written
(method, caveats, the results that are not the paper's protocol) and kept byte for byte. A file
without the markers gets the block appended (a new file: just the block). A hand edit inside the
markers is therefore lost on the next run, and ``--check`` (tests/test_paper.py runs it) fails
when the block differs from what the JSON gives: RESULTS.md regenerates identically from
docs/results/*.json. Paths print relative to the repository, so the block does not depend on
the working directory; the defaults are the repository's docs/results and docs/RESULTS.md.

The block: per task the command and hardware of the protocol run, of its oracle row and of its
real-env control row; Table 1 (Kendall tau and nDCG@1/3/5/10 per task and method, plus the
oracle), Table 2 (MPI / API, plus the real-env control; MPI / API per variant when a task ran
several --improve-variants), the fine-tuned policies, an AVD / MVD table (each cell "mean ± std
(n seeds) [95% interval]" beside the paper's published number, ../shared/PAPER.md Tables 1-2),
the model selection on the training policies, and the quality bars per task (met / MISSED) with
the MVD bar as paired differences over seeds. The row builders are in
rl2s_jax/paper/tables.py. Run logs (experiments/gpu_runs, experiments/cpu_runs, docs/logs)
are not tracked: a path into them is printed with "in git history at bf0c7b2". Runs no JAX
program (importing the package loads JAX, nothing more).

A second block, between PHYSICS_BEGIN and PHYSICS_END, is issue 62's "Physics diagnosis"
section, from physics_gain.json, physics_unseen.json and gymnasium_v5.json
(``paper.physics_tables``); written and checked alike wherever the results folder holds one of
them (``with_physics``).
"""
from __future__ import annotations

import argparse
import os
import sys

from rl2s_jax.paper.data_seeds import data_seed_rows, trust_rows
from rl2s_jax.paper.physics_tables import PHYSICS_BEGIN, PHYSICS_END, physics_block
from rl2s_jax.paper.tables import (
    PAPER_NOTE,
    TABLE1,
    TABLE2,
    TABLE3,
    TASKS,
    ablation_rows,
    bar_table,
    control_rows,
    guard_rows,
    interval_guard_rows,
    load_results,
    metric_table,
    paired_mvd_rows,
    policy_rows,
    selected_rows,
)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
BEGIN, END = "<!-- paper-tables:begin -->", "<!-- paper-tables:end -->"
RESULTS, OUT = os.path.join(ROOT, "docs", "results"), os.path.join(ROOT, "docs", "RESULTS.md")
HISTORY = "bf0c7b2"  # the last commit that tracked the run logs below
UNTRACKED = ("experiments/gpu_runs/", "experiments/cpu_runs/", "docs/logs/")


def shown(path: str) -> str:
    """``path`` as the block prints it: relative to the repository when inside it."""
    rel = os.path.relpath(os.path.abspath(path), ROOT)
    return path.rstrip("/") if rel.startswith("..") else rel.replace(os.sep, "/")


def in_history(text: str) -> str:
    """A note for a command or path that names an untracked run directory."""
    return (f" (its output: in git history at {HISTORY})"
            if any(u in str(text) for u in UNTRACKED) else "")


def provenance(task: str, r: dict) -> list[str]:
    """The commands and hardware behind the task's rows: the protocol run, the oracle row
    (``oracle``: another run's, merged by merge_results.py) and the control row."""
    secs = (r.get("timings") or {}).get("total")
    extra = [f"{r.get('seeds', '?')} seeds", f"jax {r.get('jax_version', '?')}"]
    if secs is not None:
        extra.append(f"{secs:.0f} s")
    if not r.get("complete", True):
        extra.append("INCOMPLETE run")
    cmd = r.get("command", "?")
    lines = [f"- {task}: `{cmd}` on {r.get('hardware', '?')} ({', '.join(extra)})"
             f"{in_history(cmd)}"]
    o = r.get("oracle")
    if isinstance(o, dict) and o.get("source"):
        what = [f"{o['n_episodes']} episodes" if o.get("n_episodes") else None,
                f"{o['seeds']} seeds" if o.get("seeds") else None,
                f"data: {o['data']}" if o.get("data") else None]
        what = "; ".join(w for w in what if w)
        lines.append(f"  - oracle row: `{o['source']}` on {o.get('hardware', '?')}"
                     + (f" ({what})" if what else "") + in_history(o["source"]))
    c = r.get("control")
    if isinstance(c, dict) and c.get("command"):
        src, hw = c.get("source"), c.get("hardware") or f"device {c.get('device', '?')}"
        where = (f"; `{src}`, in git history at {HISTORY}" if in_history(src)
                 else f"; `{src}`" if src else "")
        n = c.get("seeds", "?")
        gain = ("" if c.get("median_gain") is None else "; median gain of the policies below "
                f"the zoo's top quartile {c['median_gain']:+.2f}")
        lines.append(f"  - control row: `{c['command']}` on {hw} ({n} seed{'' if n == 1 else 's'}"
                     f"{where}{gain})")
    return lines


def render(results: dict, source: str) -> str:
    """The markdown block, markers included (it names ``source``, not the file it goes to)."""
    lines = [BEGIN, "## The paper's protocol: four tasks (generated by "
             "`experiments/paper_tables.py`)", ""]
    if not results:
        lines += [f"No results in `{source}/` yet (`<task>.json` from `experiments/paper.py`).",
                  END]
        return "\n".join(lines) + "\n"
    lines += [f"Generated from `{source}/<task>.json` by `experiments/paper_tables.py` (do "
              "not edit between the markers; `--check` tells whether this block is current). "
              "Each cell: mean ± sample std over seeds (n seeds); MPI/API only for the seeds "
              "whose simulators were used for improvement. Commands and hardware:", ""]
    for task in TASKS:
        if task in results:
            lines += provenance(task, results[task])
    lines += ["", "### Table 1: ranking the test policies", ""]
    lines += metric_table(results, TABLE1)
    lines += data_seed_section(results)
    lines += trust_section(results)
    lines += guard_section(results)
    lines += ["", "### Table 2: policy improvement (SAC inside each simulator, real return)", ""]
    lines += metric_table(results, TABLE2, with_oracle=False) + control_rows(results)
    lines += ["", "MPI / API: C0 is the test data's true value, C1 measured apart. MPI / API "
              "paired: C0 re-measured with C1 from the same starts and noise draws "
              "(`--improve-episodes` each), so the min over policies (MPI) is not dragged "
              "down by measurement noise; n/a for runs made before the paired measurement."]
    ablation = ablation_rows(results)
    if ablation:
        lines += ["", "### Improvement by simulated-env variant (means over the improvement "
                  "seeds)", "", *ablation]
    per_policy = policy_rows(results)
    if per_policy:
        lines += ["", "### Improvement per fine-tuned policy (pooled over the improvement "
                  "seeds)", "", *per_policy]
    guarded = guard_rows(results, snapshots_only=True)
    if guarded:
        lines += ["", "### The deployment guard (means over the improvement seeds)", "",
                  *guarded]
    lines += ["", "### Value difference on the test policies", ""]
    lines += metric_table(results, TABLE3)
    chosen = selected_rows(results)
    if chosen:
        lines += ["", "### Model selection without the test policies", "",
                  "Each lane's evaluation point chosen by the highest Kendall tau of its "
                  "TRAINING policies, started from their held-out episodes' start states, "
                  "against their true values (ties: the lower training AVD); the test "
                  "policies' metrics there:", "", *chosen]
    lines += ["", PAPER_NOTE, "", "### Quality bars (RL2S, means over seeds)", ""]
    lines += bar_table(results)
    lines += ["", "### The MVD bar, paired by seed", "",
              "RL2S's MVD minus the other method's, seed by seed (the lanes of one seed share "
              "the key and the data; RL2S and GAIL also their pre-training): mean and 95% "
              "t-interval over the seeds. An interval that contains 0 means the seeds do not "
              "resolve the difference.", "", *paired_mvd_rows(results)]
    lines.append(END)
    return "\n".join(lines) + "\n"


def section(title: str, text: str, rows: list[str]) -> list[str]:
    """A generated subsection: its title, what it shows, its table; no rows: nothing."""
    return ["", f"### {title}", "", text, "", *rows] if rows else []


def data_seed_section(results: dict) -> list[str]:
    """The table "Ranking over data seeds" (issue 66) from the tasks' ``by_data_seed``
    (``rl2s_jax.paper.data_seeds``); no task has one: nothing."""
    return section(
        "Ranking over data seeds",
        "Kendall tau on the test policies per data collection (`--data-seed`; each cell "
        "the mean over that data seed's seeds), the mean over data seeds with its 95% "
        "t-interval (each data seed one draw of the whole protocol), the oracle and the "
        "noise ceiling (an exact simulator's expected tau) of the same data seed, and "
        "issue 66's bar. Recorded by `experiments/merge_results.py` (by_data_seed; the "
        "commands are in the task JSONs). \"not measured\": no run measured it.",
        data_seed_rows(results, TASKS))


def trust_section(results: dict) -> list[str]:
    """The table "Value intervals over data seeds" (issue 64) from the tasks' "trust"
    blocks (``data_seeds.trust_rows``); no task has one: nothing."""
    return section(
        "Value intervals over data seeds",
        "Each test policy's split-conformal interval for its true value at level 0.9 "
        "(`paper/trust_phase.py`: calibrated on 20 perturbed training policies measured in "
        "the real env, never on test policies), per method over every run (seed x data "
        "seed): coverage of the true values, mean width over the range of the true values, "
        "the plain seed-spread interval's width once scaled WITH the truth to the same "
        "coverage (✓: the conformal interval is narrower), the share of runs whose "
        "largest-error policy is flagged untrusted, and a data seed's 3 seeds as one "
        "estimate (`rl2s evaluate --ckpt A --ckpt B --ckpt C`; mean over the data seeds), "
        "and the same intervals on 20 perturbed / interpolated test policies per run "
        "(`paper.py --trust-evaluated 20`, a repeat of each data seed's run; coverage and "
        "width over their own range, and the median width over it: the mean can be one "
        "policy's, as HalfCheetah RL2S-BC's 2.132 is, one of the 20 with intervals 337,434 "
        "and 474,244 wide in two of its data-seed-7 lanes). Issue 64's bars beside each "
        "(✓ / ✗). "
        "Recorded by `experiments/merge_results.py --data-seed-run` and `--evaluated-run` "
        "(the commands are in the task JSONs, the evaluated runs' in their own JSONs, "
        "`docs/results/data_seeds/<task>_data<D>_evaluated.json`).", trust_rows(results, TASKS))


def guard_section(results: dict) -> list[str]:
    """The table "The interval guard against the floor guard" (issue 64 item 3) from the
    tasks' "guard" readings (``tables.interval_guard_rows``); none recorded: nothing."""
    return section(
        "The interval guard against the floor guard",
        "The recorded in-simulator fine-tuning runs (RESULTS' \"Policy improvement inside "
        "the simulators\", the task's recipe) read offline by `experiments/interval_guard.py"
        "` at level 0.9: the floor guard the runs used, and the interval guard (deploy where "
        "the lower end of the predicted gain's conformal interval is above 0), each half of "
        "the fine-tuned policies calibrated on the other half's real gains. Median gain of "
        "the policies below the zoo's top quartile, kept policies at 0; deployed of "
        "lanes x policies.", interval_guard_rows(results, TASKS))


def with_block(text: str, block: str, begin: str = BEGIN, end_mark: str = END) -> str:
    """``text`` with its block marked by ``begin`` / ``end_mark`` replaced by ``block``
    (appended when absent); the text outside the markers is kept as it is."""
    start, end = text.find(begin), text.find(end_mark)
    if start >= 0 and end > start:
        end += len(end_mark)
        if text[end:end + 1] == "\n":
            end += 1
        return text[:start] + block + text[end:]
    if text and not text.endswith("\n"):
        text += "\n"
    return text + ("\n" if text else "") + block


def read(path: str) -> str:
    if not os.path.exists(path):
        return ""
    with open(path, encoding="utf-8") as f:
        return f.read()


def write_block(path: str, block: str, results: str | None = None) -> None:
    """Replace the marked block of ``path`` (append it when absent; create the file), and the
    physics block where ``results`` holds its JSON (``with_physics``)."""
    text = with_block(read(path), block)
    if results is not None:
        text = with_physics(text, results)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)


def regen_command(results: str, out: str) -> str:
    """The command line that regenerates ``out`` from ``results`` (defaults left out)."""
    cmd = "python experiments/paper_tables.py"
    if os.path.abspath(results) != RESULTS:
        cmd += f" --results {shown(results)}"
    if os.path.abspath(out) != OUT:
        cmd += f" --out {shown(out)}"
    return cmd


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default=RESULTS, help="directory of <task>.json (default: "
                    "the repository's docs/results)")
    ap.add_argument("--out", default=OUT, help="markdown file whose marked block is (re)written "
                    "(default: the repository's docs/RESULTS.md)")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 when the "
                    "marked block of --out differs from what --results gives")
    ap.add_argument("--guard", nargs="+", metavar="DIR", help="only print the deployment "
                    "guard's table of the <task>.json in these directories (runs of single "
                    "tasks, e.g. paper.py --guard-snapshots); writes nothing")
    args = ap.parse_args(argv)
    if args.guard:
        found = {}
        for d in args.guard:
            for task, r in load_results(d).items():
                if task in found:
                    raise SystemExit(f"guard: {task}.json is in two of the directories "
                                     f"({args.guard}); give one run per task")
                found[task] = r
        rows = guard_rows(found)
        print("\n".join(rows) if rows else f"guard: no lanes with a guard in {args.guard}")
        return 0 if rows else 1
    results = load_results(args.results)
    block = render(results, shown(args.results))
    if args.check:
        text = read(args.out)
        if with_physics(with_block(text, block), args.results) != text:
            print(f"{shown(args.out)}: the generated block is not what {shown(args.results)}/"
                  f"<task>.json gives; run: {regen_command(args.results, args.out)}",
                  file=sys.stderr)
            return 1
        print(f"{shown(args.out)}: up to date ({len(text.splitlines())} lines)")
        return 0
    write_block(args.out, block, args.results)
    print(block)
    print(f"-> {args.out} ({len(results)} task(s): {', '.join(results) or 'none'})")
    return 0


# ------------------------------------------------------------------ issue 62's physics block
PHYSICS_FILES = ("physics_gain.json", "physics_unseen.json", "gymnasium_v5.json")


def with_physics(text: str, results: str) -> str:
    """``text`` with the "Physics diagnosis (issue 62)" block (``paper.physics_tables``)
    rewritten from ``results``; unchanged where ``results`` holds none of PHYSICS_FILES (a
    protocol-only results folder)."""
    if not any(os.path.exists(os.path.join(results, f)) for f in PHYSICS_FILES):
        return text
    return with_block(text, physics_block(results, shown(results)), PHYSICS_BEGIN, PHYSICS_END)


if __name__ == "__main__":
    sys.exit(main())
