"""The paper's tables from experiments/paper.py results, written into a marked block of a
markdown file (replaced on every run, appended when absent).

    python experiments/paper_tables.py [--results docs/results] [--out docs/RESULTS.md]

Reads RESULTS/<task>.json for the tasks hopper, walker2d, halfcheetah, ant (those present) and
writes: Table 1 (Kendall tau and nDCG@1/3/5/10 per task and method), Table 2 (MPI / API), an
AVD / MVD table, each cell "mean ± std (n seeds)" beside the paper's published number, and the
quality bars per task (met / MISSED). Needs no JAX.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

TASKS = ("hopper", "walker2d", "halfcheetah", "ant")
METHODS = ("rl2s", "gail", "bc", "rl2s-bc")
BEGIN, END = "<!-- paper-tables:begin -->", "<!-- paper-tables:end -->"

# The paper's published numbers: PAPER[metric][method][task] -> number, or a string for a
# bound. Only numbers we could source are here; the tables print "n/a" for everything else.
# The paper's text was not reachable while this was written (searched: web pages, docs, the
# official code apexrl/RL2S, whose README gives commands but no results). The values below are
# as quoted in this project's issue, NOT checked against the paper; they carry the mark "†".
PAPER = {
    "kendall_tau": {"rl2s": {"hopper": 0.35, "walker2d": 0.23, "halfcheetah": 0.87,
                             "ant": 0.80}},
    "mpi": {"rl2s": {"ant": "< 0"}},
}
PAPER_MARK = "†"
PAPER_NOTE = (f"{PAPER_MARK} as quoted in the project's issue (RL2S Kendall tau per task; Ant's "
              "MPI negative), not checked against the paper, whose tables could not be "
              "reached from here; n/a: no published number found. The paper's zoos, data "
              "sizes and training budgets differ from ours, so its numbers are a reference, "
              "not a like-for-like comparison.")

TABLE1 = ("kendall_tau", "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10")
TABLE2 = ("mpi", "api")
TABLE3 = ("avd", "mvd")
NAMES = {"kendall_tau": "Kendall tau", "ndcg@1": "nDCG@1", "ndcg@3": "nDCG@3",
         "ndcg@5": "nDCG@5", "ndcg@10": "nDCG@10", "mpi": "MPI", "api": "API", "avd": "AVD",
         "mvd": "MVD"}
DIGITS = {"avd": 1, "mvd": 1}

BARS = (
    ("tau", "Kendall tau >= 0.8"),
    ("ndcg1", "nDCG@1 >= 0.95"),
    ("mvd", "RL2S MVD < GAIL's and BC's"),
    ("mpi", "RL2S MPI > 0"),
    ("control", "real-env control MPI > 0"),
)


def load_results(directory: str) -> dict[str, dict]:
    """{task: result} for the tasks whose RESULTS/<task>.json exists."""
    out = {}
    for task in TASKS:
        path = os.path.join(directory, f"{task}.json")
        if os.path.exists(path):
            with open(path) as f:
                out[task] = json.load(f)
    return out


def stats(result: dict, method: str, metric: str) -> tuple[float | None, float | None, int]:
    """(mean, sample std or None, n) over seeds: from per_seed when present, else from
    methods / std / n (n defaulting to seeds)."""
    per = (result.get("per_seed") or {}).get(method, {}).get(metric)
    if per is not None:
        vals = [float(v) for v in per if v is not None and math.isfinite(float(v))]
        if not vals:
            return None, None, 0
        mean = sum(vals) / len(vals)
        std = (math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1))
               if len(vals) > 1 else None)
        return mean, std, len(vals)
    mean = (result.get("methods") or {}).get(method, {}).get(metric)
    if mean is None:
        return None, None, 0
    std = (result.get("std") or {}).get(method, {}).get(metric)
    n = (result.get("n") or {}).get(method, {}).get(metric, result.get("seeds", 1))
    return float(mean), None if std is None else float(std), int(n)


def fmt_cell(mean, std, n, digits: int = 3) -> str:
    if mean is None:
        return "n/a"
    seeds = f"({n} seed{'s' if n != 1 else ''})"
    if std is None:
        return f"{mean:.{digits}f} {seeds}"
    return f"{mean:.{digits}f} ± {std:.{digits}f} {seeds}"


def paper_cell(metric: str, method: str, task: str) -> str:
    v = PAPER.get(metric, {}).get(method, {}).get(task)
    if v is None:
        return "n/a"
    return f"{v}{PAPER_MARK}" if isinstance(v, str) else f"{v:.2f}{PAPER_MARK}"


def metric_table(results: dict, metrics) -> list[str]:
    head = "| task | method | " + " | ".join(f"{NAMES[m]} | paper" for m in metrics) + " |"
    rule = "|---|---|" + "---:|---:|" * len(metrics)
    rows = [head, rule]
    for task in TASKS:
        if task not in results:
            continue
        for method in METHODS:
            cells = []
            for m in metrics:
                cells.append(fmt_cell(*stats(results[task], method, m), DIGITS.get(m, 3)))
                cells.append(paper_cell(m, method, task))
            rows.append(f"| {task} | {method} | " + " | ".join(cells) + " |")
    return rows


def bars(result: dict) -> dict[str, tuple[bool | None, str]]:
    """Each quality bar on the seed means: key -> (met or None if unknown, the numbers)."""
    mean = lambda method, metric: stats(result, method, metric)[0]
    out = {}
    tau = mean("rl2s", "kendall_tau")
    out["tau"] = (None if tau is None else tau >= 0.8, "n/a" if tau is None else f"{tau:.3f}")
    nd = mean("rl2s", "ndcg@1")
    out["ndcg1"] = (None if nd is None else nd >= 0.95, "n/a" if nd is None else f"{nd:.3f}")
    mv = {m: mean(m, "mvd") for m in ("rl2s", "gail", "bc")}
    if None in mv.values():
        out["mvd"] = (None, "n/a")
    else:
        out["mvd"] = (mv["rl2s"] < mv["gail"] and mv["rl2s"] < mv["bc"],
                      f"{mv['rl2s']:.1f} vs {mv['gail']:.1f}, {mv['bc']:.1f}")
    mpi = mean("rl2s", "mpi")
    out["mpi"] = (None if mpi is None else mpi > 0, "n/a" if mpi is None else f"{mpi:.3f}")
    c = (result.get("control") or {}).get("mpi")
    out["control"] = (None if c is None else c > 0, "n/a" if c is None else f"{c:.3f}")
    return out


def control_rows(results: dict) -> list[str]:
    """Table 2's real-env control: the same SAC fine-tuning in the real env (its ceiling)."""
    rows = []
    for task in TASKS:
        c = (results.get(task) or {}).get("control")
        if not c:
            continue
        n = c.get("seeds", 1)
        cells = [fmt_cell(c.get("mpi"), c.get("mpi_std"), n), "n/a",
                 fmt_cell(c.get("api"), c.get("api_std"), n), "n/a"]
        rows.append(f"| {task} | control (real env) | " + " | ".join(cells) + " |")
    return rows


def ablation_rows(results: dict) -> list[str]:
    """MPI / API per simulated-env variant (paper.py --improve-variants), when a task ran
    more than one."""
    rows = []
    for task in TASKS:
        ab = (results.get(task) or {}).get("ablation") or {}
        if len(ab) < 2:
            continue
        for variant, v in ab.items():
            for method in METHODS:
                m = (v.get("methods") or {}).get(method) or {}
                cell = lambda x: "n/a" if x is None else f"{x:.3f}"
                rows.append(f"| {task} | {variant} | {method} | {cell(m.get('mpi'))} | "
                            f"{cell(m.get('api'))} |")
    if rows:
        rows = ["| task | variant | method | MPI | API |", "|---|---|---|---:|---:|", *rows]
    return rows


def bar_table(results: dict) -> list[str]:
    rows = ["| task | " + " | ".join(name for _, name in BARS) + " |",
            "|---|" + "---|" * len(BARS)]
    for task in TASKS:
        if task not in results:
            continue
        b = bars(results[task])
        cells = []
        for key, _ in BARS:
            ok, numbers = b[key]
            word = "n/a" if ok is None else ("met" if ok else "MISSED")
            cells.append(f"{word} ({numbers})")
        rows.append(f"| {task} | " + " | ".join(cells) + " |")
    return rows


def render(results: dict, source: str) -> str:
    """The markdown block, markers included."""
    lines = [BEGIN, "## The paper's protocol: four tasks (generated by "
             "`experiments/paper_tables.py`)", ""]
    if not results:
        lines += [f"No results in `{source}/` yet (`<task>.json` from `experiments/paper.py`).",
                  END]
        return "\n".join(lines) + "\n"
    lines += [f"From `{source}/<task>.json`. Each cell: mean ± sample std over seeds (n "
              "seeds); MPI/API only for the seeds whose simulators were used for "
              "improvement. Commands and hardware:", ""]
    for task in TASKS:
        r = results.get(task)
        if r is None:
            continue
        secs = (r.get("timings") or {}).get("total")
        extra = [f"{r.get('seeds', '?')} seeds", f"jax {r.get('jax_version', '?')}"]
        if secs is not None:
            extra.append(f"{secs:.0f} s")
        if not r.get("complete", True):
            extra.append("INCOMPLETE run")
        lines.append(f"- {task}: `{r.get('command', '?')}` on {r.get('hardware', '?')} "
                     f"({', '.join(extra)})")
    lines += ["", "### Table 1: ranking the test policies", ""]
    lines += metric_table(results, TABLE1)
    lines += ["", "### Table 2: policy improvement (SAC inside each simulator, real return)", ""]
    lines += metric_table(results, TABLE2) + control_rows(results)
    ablation = ablation_rows(results)
    if ablation:
        lines += ["", "### Improvement by simulated-env variant (means over the improvement "
                  "seeds)", "", *ablation]
    lines += ["", "### Value difference on the test policies", ""]
    lines += metric_table(results, TABLE3)
    lines += ["", PAPER_NOTE, "", "### Quality bars (RL2S, means over seeds)", ""]
    lines += bar_table(results)
    lines.append(END)
    return "\n".join(lines) + "\n"


def write_block(path: str, block: str) -> None:
    """Replace the marked block of ``path`` (append it when absent; create the file)."""
    text = ""
    if os.path.exists(path):
        with open(path) as f:
            text = f.read()
    start, end = text.find(BEGIN), text.find(END)
    if start >= 0 and end > start:
        end += len(END)
        if text[end:end + 1] == "\n":
            end += 1
        text = text[:start] + block + text[end:]
    else:
        if text and not text.endswith("\n"):
            text += "\n"
        text += ("\n" if text else "") + block
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default="docs/results", help="directory of <task>.json")
    ap.add_argument("--out", default="docs/RESULTS.md", help="markdown file whose marked "
                    "block is (re)written")
    args = ap.parse_args(argv)
    results = load_results(args.results)
    block = render(results, args.results.rstrip("/"))
    write_block(args.out, block)
    print(block)
    print(f"-> {args.out} ({len(results)} task(s): {', '.join(results) or 'none'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
