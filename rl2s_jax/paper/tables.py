"""The row builders of experiments/paper_tables.py: the paper's published numbers and, from
experiments/paper.py's result JSON (one dict per task), the markdown rows of each table of the
generated block of docs/RESULTS.md. Pure Python; uses no JAX itself.
"""
from __future__ import annotations

import json
import math
import os
import statistics

from rl2s_jax.stats import paired_seed_difference

TASKS = ("hopper", "walker2d", "halfcheetah", "ant")
METHODS = ("rl2s", "gail", "bc", "rl2s-bc")

# The paper's published numbers (../shared/PAPER.md, copied from its Tables 1 and 2): ranking
# on its test set of 20 policies, improvement on its 8 (Ant 14). PAPER[metric][method][task].
_T1 = {  # task: (tau, nDCG@1, @3, @5, @10) for RL2S, GAIL, RL2S-BC, BC
    "hopper": (
        (0.3474, 0.9464, 0.8326, 0.6843, 0.7326),
        (-0.1895, 0.0177, 0.2448, 0.3971, 0.5111),
        (-0.2842, 0.0177, 0.1507, 0.231, 0.3515),
        (-0.0632, 0.5868, 0.3816, 0.4501, 0.513),
    ),
    "walker2d": (
        (0.2316, 0.7954, 0.9069, 0.8988, 0.8859),
        (-0.0737, 0.6591, 0.7311, 0.7474, 0.7622),
        (-0.5474, 0.6184, 0.5614, 0.5971, 0.703),
        (0.0632, 0.6672, 0.5497, 0.6357, 0.7348),
    ),
    "halfcheetah": (
        (0.8737, 1.0, 0.9691, 0.9922, 0.9944),
        (0.8211, 0.9878, 0.9385, 0.9667, 0.9882),
        (0.4947, 0.6191, 0.7839, 0.8013, 0.869),
        (0.6, 0.9878, 0.9652, 0.943, 0.919),
    ),
    "ant": (
        (0.8, 1.0, 1.0, 0.9872, 0.9943),
        (0.6211, 0.8601, 0.9186, 0.9609, 0.9358),
        (0.2632, 0.665, 0.6888, 0.6988, 0.8093),
        (0.4105, 1.0, 0.9106, 0.9587, 0.9174),
    ),
}
_T2 = {  # task: (MPI, API) for RL2S, GAIL, RL2S-BC, BC
    "hopper": ((0.0293, 2.9400), (0.0039, 0.9758), (0.0124, 0.9587), (0.0090, 0.9235)),
    "walker2d": ((0.0067, 0.2306), (0.0065, 0.1458), (0.0032, 0.2178), (-0.0045, 0.1915)),
    "halfcheetah": ((0.0143, 0.0717), (0.0058, 0.0529), (0.0129, 0.0598), (0.0099, 0.0630)),
    "ant": ((-0.021, 0.0379), (-0.027, 0.0325), (-0.0232, 0.0295), (-0.0352, 0.0308)),
}
_PAPER_METHODS = ("rl2s", "gail", "rl2s-bc", "bc")
PAPER: dict[str, dict[str, dict[str, float]]] = {}
for _table, _metrics in ((_T1, ("kendall_tau", "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10")),
                         (_T2, ("mpi", "api"))):
    for _task, _rows in _table.items():
        for _method, _row in zip(_PAPER_METHODS, _rows, strict=True):
            for _metric, _v in zip(_metrics, _row, strict=True):
                PAPER.setdefault(_metric, {}).setdefault(_method, {})[_task] = _v
PAPER_NOTE = ("paper: the RL2S paper's Tables 1 and 2 (../shared/PAPER.md; its ranking test set "
              "has 20 policies, its AVD/MVD appear only as curves: n/a). Its zoos, data sizes "
              "and training budgets differ from ours, so its numbers are a reference, not a "
              "like-for-like comparison. oracle: the real dynamics through the same evaluation "
              "path (the ceiling of any simulator of this observation under this protocol). "
              "[lo, hi]: 95% bootstrap interval over evaluation episodes (mean over seeds of "
              "the per-seed ends).")

TABLE1 = ("kendall_tau", "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10")
TABLE2 = ("mpi", "api", "mpi_paired", "api_paired")
TABLE3 = ("avd", "mvd")
NAMES = {"kendall_tau": "Kendall tau", "ndcg@1": "nDCG@1", "ndcg@3": "nDCG@3",
         "ndcg@5": "nDCG@5", "ndcg@10": "nDCG@10", "mpi": "MPI", "api": "API", "avd": "AVD",
         "mpi_paired": "MPI paired", "api_paired": "API paired",
         "mvd": "MVD"}
DIGITS = {"avd": 1, "mvd": 1}

BARS = (
    ("tau", "Kendall tau >= 0.8"),
    ("ndcg1", "nDCG@1 >= 0.95"),
    ("mvd", "RL2S MVD < GAIL's and BC's"),
    ("mpi", "RL2S MPI > 0"),
    ("control", "real-env control MPI > 0"),
    ("oracle", "oracle tau / nDCG@1 (the ceiling)"),
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


def fmt_cell(mean, std, n, digits: int = 3, interval: dict | None = None) -> str:
    if mean is None:
        return "n/a"
    seeds = f"({n} seed{'s' if n != 1 else ''})"
    text = (f"{mean:.{digits}f} {seeds}" if std is None
            else f"{mean:.{digits}f} ± {std:.{digits}f} {seeds}")
    if interval:
        text += f" [{interval['lo']:.{digits}f}, {interval['hi']:.{digits}f}]"
    return text


def interval_of(result: dict, method: str, metric: str) -> dict | None:
    return ((result.get("intervals") or {}).get(method) or {}).get(metric)


def paper_cell(metric: str, method: str, task: str) -> str:
    v = PAPER.get(metric, {}).get(method, {}).get(task)
    return "n/a" if v is None else f"{v:.4f}"


def metric_table(results: dict, metrics, with_oracle: bool = True) -> list[str]:
    head = "| task | method | " + " | ".join(f"{NAMES[m]} | paper" for m in metrics) + " |"
    rule = "|---|---|" + "---:|---:|" * len(metrics)
    rows = [head, rule]
    for task in TASKS:
        if task not in results:
            continue
        r = results[task]
        rows_for = METHODS + (("oracle",) if with_oracle and "oracle" in (
            r.get("per_seed") or {}) else ())
        for method in rows_for:
            cells = []
            for m in metrics:
                cells.append(fmt_cell(*stats(r, method, m), DIGITS.get(m, 3),
                                      interval_of(r, method, m)))
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
    # MPI > 0 as printed: a kept policy gains exactly 0, and float residue (+6e-7) is no gain
    mpi = mean("rl2s", "mpi")
    out["mpi"] = (None if mpi is None else round(mpi, 3) > 0,
                  "n/a" if mpi is None else f"{mpi:.3f}")
    c = (result.get("control") or {}).get("mpi")
    out["control"] = (None if c is None else round(c, 3) > 0, "n/a" if c is None else f"{c:.3f}")
    ot, on = mean("oracle", "kendall_tau"), mean("oracle", "ndcg@1")
    nc = (result.get("noise_ceiling") or {}).get("kendall_tau")
    noise = "" if nc is None else f"; noise alone allows tau {nc['mean']:.2f}"
    out["oracle"] = (None if ot is None else (ot >= 0.8 and on >= 0.95),
                     "n/a" if ot is None else f"{ot:.3f} / {on:.3f}{noise}")
    return out


def paired_mvd(result: dict, other: str) -> tuple[float, float, float, int, int] | None:
    """RL2S's MVD minus ``other``'s, seed by seed (the lanes of one seed share the key and the
    data): ``stats.paired_seed_difference``'s (mean, lo, hi, seeds where RL2S is lower, seeds)
    with a 95% t-interval over the seeds; None without two seeds that both methods ran."""
    per = result.get("per_seed") or {}
    a, b = (per.get(m, {}).get("mvd") or [] for m in ("rl2s", other))
    return paired_seed_difference(a, b)


def paired_mvd_rows(results: dict) -> list[str]:
    """The MVD bar per task as paired differences over seeds (RL2S - GAIL, RL2S - BC)."""
    rows = ["| task | RL2S - GAIL | RL2S - BC |", "|---|---|---|"]
    for task in TASKS:
        if task not in results:
            continue
        cells = []
        for other in ("gail", "bc"):
            p = paired_mvd(results[task], other)
            cells.append("n/a" if p is None else f"{p[0]:+.1f} [{p[1]:+.1f}, {p[2]:+.1f}], "
                                                 f"lower on {p[3]} of {p[4]} seeds")
        rows.append(f"| {task} | " + " | ".join(cells) + " |")
    return rows


def control_rows(results: dict) -> list[str]:
    """Table 2's real-env control: the same SAC fine-tuning in the real env (its ceiling)."""
    rows = []
    for task in TASKS:
        c = (results.get(task) or {}).get("control")
        if not c:
            continue
        n = c.get("seeds", 1)
        mpi = fmt_cell(c.get("mpi"), c.get("mpi_std"), n)
        api = fmt_cell(c.get("api"), c.get("api_std"), n)
        # the control measures C0 and C1 itself; paired since measure_improvement pairs them
        paired = (mpi, api) if c.get("paired") else ("n/a", "n/a")
        cells = [mpi, "n/a", api, "n/a", paired[0], "n/a", paired[1], "n/a"]
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


def improvement_lanes(results: dict):
    """(task, variant, method, [lane]) for every method's fine-tuning lanes, per simulated-env
    variant (``ablation.<variant>.lanes``, else ``improvement`` under its variant name)."""
    for task in TASKS:
        r = results.get(task) or {}
        by_variant = {v: e.get("lanes") for v, e in (r.get("ablation") or {}).items()
                      if e.get("lanes")}
        if not by_variant and r.get("improvement"):
            by_variant = {r.get("improve_variant", "full"): r["improvement"]}
        for variant, lanes in by_variant.items():
            for method in METHODS:
                mine = [ln for ln in lanes.values() if ln.get("method") == method]
                if mine:
                    yield task, variant, method, mine


def policy_rows(results: dict) -> list[str]:
    """Per task, simulated-env variant and method, the fine-tuned test policies pooled over
    the improvement seeds (``ablation.<variant>.lanes``, else ``improvement``): how many, the
    share whose real return rose (I > 0), the median I, and the API without the policy of the
    smallest |C0| (one policy near C0 = 0 can carry API alone), mean over seeds; where the
    deployment guard ran, how many fine-tuned policies it deployed."""
    rows = []
    for task, variant, method, mine in improvement_lanes(results):
        pooled, trimmed, deployed, offered = [], [], 0, 0
        for ln in mine:
            gains, c0 = ln.get("I") or [], ln.get("c0") or []
            pairs = [(i, c) for i, c in zip(gains, c0, strict=True)
                     if i is not None and math.isfinite(i)]
            if not pairs:
                continue
            pooled += [i for i, _ in pairs]
            smallest = min(range(len(pairs)), key=lambda k: abs(pairs[k][1]))
            rest = [i for k, (i, _) in enumerate(pairs) if k != smallest]
            if rest:
                trimmed.append(sum(rest) / len(rest))
            if ln.get("guard_accepted") is not None:
                deployed += sum(bool(a) for a in ln["guard_accepted"])
                offered += len(ln["guard_accepted"])
        if not pooled:
            continue
        n, median = len(pooled), statistics.median(pooled)
        share = sum(i > 0 for i in pooled) / n
        api_trim = "n/a" if not trimmed else f"{sum(trimmed) / len(trimmed):.3f}"
        guard = f"{deployed} of {offered}" if offered else "n/a"
        rows.append(f"| {task} | {variant} | {method} | {n} ({len(mine)} seeds) | "
                    f"{share:.2f} | {median:+.3f} | {api_trim} | {guard} |")
    if rows:
        rows = ["| task | variant | method | policies | share improved | median I | API "
                "without the smallest abs(C0) | deployed by the guard |",
                "|---|---|---|---:|---:|---:|---:|---:|", *rows]
    return rows


def guard_rows(results: dict, snapshots_only: bool = False) -> list[str]:
    """Per task, simulated-env variant and method, the deployment guard's effect (means over
    the improvement seeds of each lane's min / mean of I): every fine-tuned policy deployed
    ("final"), the guard on the final actor (``mpi_deployed``), and, where paper.py ran with
    --guard-snapshots, the guard over the snapshots (``mpi_snapshot``; "paired": the same
    choice measured against C0 re-measured on C1's episodes, ``I_snapshot_paired``) and how
    many fine-tuned policies each guard deployed. No rows for runs without a guard (with
    ``snapshots_only``, without the snapshot guard: the other columns are in the variant
    table's full / full+guard rows)."""
    rows = []
    mean = lambda xs: sum(xs) / len(xs)
    cell = lambda x: "n/a" if x is None else f"{x:.3f}"
    for task, variant, method, lanes in improvement_lanes(results):
        mine = [ln for ln in lanes if ln.get("guard_accepted") is not None]
        if not mine:
            continue

        def avg(key, mine=mine):
            vals = [ln.get(key) for ln in mine]
            return None if None in vals else mean(vals)

        snap = all(ln.get("guard_snapshot") is not None for ln in mine)
        if snapshots_only and not snap:
            continue
        paired = [ln.get("I_snapshot_paired") for ln in mine]
        paired_ok = snap and all(p for p in paired)
        n_final = sum(sum(bool(a) for a in ln["guard_accepted"]) for ln in mine)
        n_snap = (sum(sum(int(k) > 0 for k in ln["guard_snapshot"]) for ln in mine)
                  if snap else None)
        offered = sum(len(ln["guard_accepted"]) for ln in mine)
        cells = [avg("mpi"), avg("api"), avg("mpi_deployed"), avg("api_deployed"),
                 avg("mpi_snapshot") if snap else None,
                 avg("api_snapshot") if snap else None,
                 mean([min(p) for p in paired]) if paired_ok else None,
                 mean([mean(p) for p in paired]) if paired_ok else None]
        deployed = f"{n_final}" + ("" if n_snap is None else f" / {n_snap}")
        rows.append(f"| {task} | {variant} | {method} | {len(mine)} | "
                    + " | ".join(cell(c) for c in cells)
                    + f" | {deployed} of {offered} |")
    if rows:
        rows = ["| task | variant | method | seeds | MPI, all deployed | API | MPI, guard "
                "(final actor) | API | MPI, guard over snapshots | API | MPI, snapshots "
                "paired | API, paired | deployed: final / snapshots |",
                "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|", *rows]
    return rows


def selected_rows(results: dict) -> list[str]:
    """The test metrics at the evaluation point chosen on the TRAINING policies' held-out
    episodes (paper.py's ``selected``: per method, per-seed lists and the chosen steps); no
    rows for results without it."""
    cols = ("kendall_tau", "ndcg@1", "avd", "mvd")
    rows = []
    for task in TASKS:
        sel = (results.get(task) or {}).get("selected") or {}
        for method in METHODS:
            if method not in sel:
                continue
            cells = [fmt_cell(*stats({"per_seed": sel}, method, m), DIGITS.get(m, 3))
                     for m in cols]
            steps = ", ".join(str(s) for s in sel[method].get("step", []))
            rows.append(f"| {task} | {method} | " + " | ".join(cells) + f" | {steps} |")
    if not rows:
        return []
    head = ("| task | method | " + " | ".join(NAMES.get(m, m) for m in cols)
            + " | chosen steps (per seed) |")
    return [head, "|---|---|" + "---:|" * len(cols) + "---|", *rows]


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


def interval_guard_rows(results: dict, tasks) -> list[str]:
    """Issue 64 item 3: per task with a "guard" reading (``merge_results.py --guard-reading``)
    and per guard, each method's guarded median gain of the policies below the zoo's top
    quartile, the deployed count, the deployed real losses and MPI, beside the real-env
    control's median gain; none recorded: []."""
    rows = []
    methods = ("rl2s", "gail", "bc")
    for task in tasks:
        g = (results.get(task) or {}).get("guard") or {}
        if not {"floor", "interval"} <= set(g):
            continue
        ctl = next((b.get("control_median_gain") for b in g["floor"].values()), None)
        for kind in ("floor", "interval"):
            cells = []
            for m in methods:
                b = g[kind].get(m)
                cells.append("n/a" if b is None else
                             f"{b['median_gain']:+.2f} ({b['deployed']} of "
                             f"{b['lanes_x_policies']}, {b['deployed_losses']} lost, MPI "
                             f"{b['mpi']:.3f})")
            src = os.path.basename(os.path.dirname(g["runs"][0])) if g.get("runs") else "?"
            rows.append(f"| {task} | {src} | {'n/a' if ctl is None else f'{ctl:+.2f}'} | "
                        f"{kind} | " + " | ".join(cells) + " |")
    if rows:
        rows = ["| task | improvement runs | control | guard | RL2S: median gain (deployed, "
                "lost, MPI) | GAIL | BC |", "|---|---|---:|---|---|---|---|", *rows]
    return rows

