"""The pipeline's report: report.json, report.md, PNG plots and a one-screen terminal table."""
from __future__ import annotations

import os

import jax
import jaxlib
import numpy as np

from rl2s_jax._files import read_jsonl, save_figure, write_json, write_text
from rl2s_jax.app.value_intervals import NO_INTERVAL

TABLE_KEYS = ("avd", "mvd", "kendall_tau", "spearman", "ndcg@1", "ndcg@3", "ndcg@5", "ndcg@10",
              "regret@1", "mpi", "api")

# (name, /proc/cpuinfo flag), widest first: XLA's CPU code, so MJX's rounding, follows them
_ISA = (("AVX512", "avx512f"), ("AVX2", "avx2"), ("AVX", "avx"), ("SSE4_2", "sse4_2"))


def cpu_from_cpuinfo(text: str) -> dict:
    """The first processor's model name and widest x86 vector instruction set in a
    /proc/cpuinfo text. -> {"cpu": str | None, "cpu_isa": str | None}"""
    model, flags = None, set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model is None:
            model = value.strip()
        elif key == "flags" and not flags:
            flags = set(value.split())
    isa = next((name for name, flag in _ISA if flag in flags), None)
    return {"cpu": model, "cpu_isa": isa}


def machine_info() -> dict:
    """Where a result was measured: JAX's backend and device kind, the CPU's model and widest
    instruction set (CPU results move with it: docs/RESULTS.md, "`make hopper` on the CPU"),
    and the jax / jaxlib versions."""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = cpu_from_cpuinfo(f.read())
    except OSError:
        cpu = {"cpu": None, "cpu_isa": None}
    return {"backend": jax.default_backend(), "device": jax.devices()[0].device_kind, **cpu,
            "jax": jax.__version__, "jaxlib": jaxlib.__version__}


def load_curve(path: str) -> list[dict]:
    """Rows of a run's eval.jsonl (test-policy metrics over training), or [] if absent."""
    if not os.path.exists(path):
        return []
    return read_jsonl(path)


def table(methods: dict[str, dict], keys=TABLE_KEYS) -> str:
    """Fixed-width table: one row per method, one column per metric."""
    head = f"{'method':<9}" + "".join(f"{k:>12}" for k in keys)
    rows = [head]
    for name, m in methods.items():
        rows.append(f"{name:<9}" + "".join(
            f"{m[k]:>12.3f}" if isinstance(m.get(k), (int, float)) else f"{'-':>12}"
            for k in keys))
    return "\n".join(rows)


def markdown_table(methods: dict[str, dict], keys=TABLE_KEYS) -> str:
    lines = ["| method | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for name, m in methods.items():
        cells = [f"{m[k]:.3f}" if isinstance(m.get(k), (int, float)) else "-" for k in keys]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def fine_tuning_text(imp: dict) -> list[str]:
    """How an improvement entry's policies were fine-tuned (SAC iterations and the simulated
    env of its ``recipe``), as [a sentence]; [] where the entry predates ``iterations``."""
    if "iterations" not in imp:
        return []
    env = imp.get("recipe") or {}
    branch, penalty = env.get("branch_length"), env.get("uncertainty_penalty") or 0.0
    return ["", f"Fine-tuned by SAC for {imp['iterations']} iterations per policy in "
            + (f"{branch}-step branches from the data's states" if branch
               else "whole episodes from the data's start states")
            + (f", reward minus {penalty:g} x the ensemble's disagreement" if penalty else "")
            + "."]


def improvement_text(evals: dict[str, dict]) -> str:
    """Per method and test policy of the improvement (``evals[m]["improvement"]``, the
    pipeline's ``improve_in_simulators``): deployed or kept, the simulator's predicted gain
    (the smallest over the elite members; the guard's criterion) and the real gain (paired C1
    vs C0); why the predicted gains have no interval. Markdown; "" without improvement."""
    lines = []
    for method, r in evals.items():
        imp = r.get("improvement")
        if imp is None:
            continue
        names = [str(n) for n in r["policy_names"]]
        g, floor = imp.get("guard_margin"), imp.get("guard_floor")
        k = imp.get("guard_floor_scale", 1.0)
        lines += ["", f"Improvement in {method}'s simulator ("
                  + (f"guard margin {g}" if g is not None else "no guard")
                  + (f", floor {floor:.3g}: every member's gain must exceed "
                     + ("" if k == 1 else f"{k:g} x ") + "the simulator's "
                     "MVD on the training policies" if floor else "")
                  + f"): {sum(imp['deployed'])} of {len(imp['I'])} deployed, MPI "
                  f"{imp['mpi']:.3f}, API {imp['api']:.3f}", *fine_tuning_text(imp), "",
                  "| policy | deployed | predicted gain (every member at least) | real C0 | "
                  "real C1 | real gain |", "|---|---|---:|---:|---:|---:|"]
        for j, name in enumerate(names):
            p = imp["predicted_gain"][j]
            lines.append(f"| {name} | {'deployed' if imp['deployed'][j] else 'kept (start)'} | "
                         + ("n/a" if p is None else f"{p:+.3f}") + f" | {imp['c0'][j]:.1f} | "
                         f"{imp['c1'][j]:.1f} | {imp['I'][j]:+.3f} |")
    if any((r.get("improvement") or {}).get("guard_margin") is not None for r in evals.values()):
        lines += ["", f"Why no interval: {NO_INTERVAL['floor_guard']}."]
    return "\n".join(lines)


def plot_all(out: str, evals: dict[str, dict], curves: dict[str, list[dict]]) -> list[str]:
    """Write the PNG plots into ``out``; returns their file names."""
    # Imported here to keep start-up fast: matplotlib loads in about a second, and only
    # the plots need it.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    if any(curves.values()):
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
        for name, rows in curves.items():
            if rows:
                steps = [r["step"] for r in rows]
                axes[0].plot(steps, [r["avd"] for r in rows], marker=".", label=name)
                axes[1].plot(steps, [r["mvd"] for r in rows], marker=".", label=name)
        for ax, what in zip(axes, ("AVD", "MVD"), strict=True):
            ax.set_xlabel("train_step")
            ax.set_ylabel(f"{what} on test policies")
            ax.grid(alpha=0.3)
        axes[0].legend()
        fig.tight_layout()
        save_figure(fig, os.path.join(out, "vd_curves.png"), dpi=110)
        plt.close(fig)
        files.append("vd_curves.png")

    if evals:
        first = next(iter(evals.values()))
        order = np.argsort(first["true_value"])
        names = [str(first["policy_names"][i]) for i in order]
        fig, ax = plt.subplots(figsize=(max(6, 0.22 * len(names) + 2), 3.6))
        width = 0.8 / len(evals)
        for j, (name, r) in enumerate(evals.items()):
            ax.bar(np.arange(len(names)) + j * width, np.asarray(r["vd"])[order], width,
                   label=name)
        ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=90, fontsize=6)
        ax.set_ylabel("VD (test policies, by true value)")
        ax.legend()
        fig.tight_layout()
        save_figure(fig, os.path.join(out, "vd_per_policy.png"), dpi=110)
        plt.close(fig)
        files.append("vd_per_policy.png")

        fig, axes = plt.subplots(1, len(evals), figsize=(3.2 * len(evals), 3.2), squeeze=False)
        for ax, (name, r) in zip(axes[0], evals.items(), strict=True):
            plot_true_vs_sim(ax, name, r)
        axes[0][0].set_ylabel("simulated value")
        fig.tight_layout()
        save_figure(fig, os.path.join(out, "true_vs_sim.png"), dpi=110)
        plt.close(fig)
        files.append("true_vs_sim.png")

        imps = {name: r["improvement"] for name, r in evals.items() if "improvement" in r}
        if imps:
            files.append(plot_improvement(out, imps, names, order))
    return files


def value_interval_bars(r: dict) -> tuple | None:
    """(lower, upper, trusted) [P] of an evaluation's value intervals (its "trust" block's
    policies, in its policy order; an unbounded end NaN), or None where it has none (skipped,
    or a report from before intervals)."""
    pols = (r.get("trust") or {}).get("policies")
    if not pols or len(pols) != len(r["sim_value"]):
        return None
    lo, hi = (np.array([np.nan if p["interval"][i] is None else p["interval"][i]
                        for p in pols], np.float64) for i in (0, 1))
    return lo, hi, np.array([bool(p["trusted"]) for p in pols])


def plot_true_vs_sim(ax, name: str, r: dict) -> None:
    """One method's simulated against true values on ``ax``: the diagonal, each policy's value
    interval as a vertical bar where the evaluation has them, untrusted policies in red
    (unbounded intervals drawn to the axes' edge), the coverage in the title."""
    t, s = np.asarray(r["true_value"]), np.asarray(r["sim_value"])
    lo, hi = min(t.min(), s.min()), max(t.max(), s.max())
    ax.plot([lo, hi], [lo, hi], color="grey", lw=0.8)
    title = f"{name}: tau {r['metrics'].get('kendall_tau', float('nan')):.2f}"
    bars = value_interval_bars(r)
    if bars is None:
        ax.scatter(t, s, s=10)
    else:
        ilo, ihi, trusted = bars
        pad = 0.1 * (hi - lo or 1.0)
        ilo = np.where(np.isfinite(ilo), ilo, lo - pad)  # unbounded: to the edge
        ihi = np.where(np.isfinite(ihi), ihi, hi + pad)
        for ok, colour, label in ((True, "C0", "trusted"), (False, "C3", "untrusted")):
            m = trusted == ok
            if m.any():
                ax.errorbar(t[m], s[m], yerr=[s[m] - ilo[m], ihi[m] - s[m]], fmt="o", ms=3,
                            lw=0.8, color=colour, label=label)
        ax.set_ylim(lo - pad, hi + pad)
        ax.legend(fontsize=6, loc="upper left")
        cov = (r.get("trust") or {}).get("coverage")
        if cov is not None:
            title += f", {r['trust']['level']:.0%} intervals cover {cov:.0%}"
    ax.set_title(title, fontsize=8)
    ax.set_xlabel("true value")


def plot_improvement(out: str, imps: dict[str, dict], names: list[str], order) -> str:
    """improvement.png: each test policy's real improvement I per method, deployed policies
    as filled bars in the method's colour, policies the guard kept (I = 0 by definition) as a
    hollow marker on the zero line; the legend tells them apart. -> the file name."""
    # Imported here to keep start-up fast (matplotlib loads in about a second).
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig, ax = plt.subplots(figsize=(max(6, 0.22 * len(names) + 2), 3.8))
    width = 0.8 / len(imps)
    handles, any_kept = [], False
    for j, (name, imp) in enumerate(imps.items()):
        colour = f"C{j}"
        x = np.arange(len(names)) + j * width
        i_ = np.asarray(imp["I"], float)[order]
        dep = np.asarray(imp.get("deployed", [True] * len(imp["I"])), bool)[order]
        ax.bar(x[dep], i_[dep], width, color=colour)
        if (~dep).any():
            any_kept = True
            ax.scatter(x[~dep], np.zeros((~dep).sum()), marker="o", s=22,
                       facecolors="none", edgecolors=colour, zorder=3)
        handles.append(Patch(color=colour, label=f"{name}: {int(dep.sum())} deployed (MPI "
                             f"{imp['mpi']:.2f}, API {imp['api']:.2f})"))
    if any_kept:
        handles.append(Line2D([], [], ls="", marker="o", markerfacecolor="none",
                              markeredgecolor="black", label="kept by the guard (I = 0)"))
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=90, fontsize=6)
    ax.set_ylabel("real improvement I = (C1 - C0) / |C0|")
    margin = next(iter(imps.values())).get("guard_margin")
    ax.set_title("deployed (bars) and kept (hollow) policies, guard margin "
                 f"{margin}" if margin is not None else "no guard: every policy deployed",
                 fontsize=8)
    ax.legend(handles=handles, fontsize=7)
    fig.tight_layout()
    save_figure(fig, os.path.join(out, "improvement.png"), dpi=110)
    plt.close(fig)
    return "improvement.png"


def trust_lines(evals: dict[str, dict]) -> list[str]:
    """report.md's lines on each method's value intervals (evaluate/trust.py), or why it has
    none, if either."""
    lines = []
    for name, r in evals.items():
        t = r.get("trust") or {}
        if "skipped" in t:
            lines.append(f"- {name}: value intervals skipped: {t['skipped']}")
        if "coverage" in t:
            c, wor = t["calibration"], t["width_over_range"]
            lines.append(f"- {name}: {t['level']:.0%} value intervals cover "
                         f"{t['coverage']:.0%} of the test policies, width/range "
                         f"{'n/a' if wor is None else f'{wor:.3f}'}, "
                         f"{sum(not p['trusted'] for p in t['policies'])} untrusted; largest "
                         f"error {t['worst']['name']} "
                         f"{'flagged' if t['worst']['flagged'] else 'not flagged'} (calibrated "
                         f"on {c['n']} {'training (optimistic)' if c['optimistic'] else 'held-out'}"
                         f" policies)")
    return lines + [""] if lines else []


def write_report(out: str, summary: dict, evals: dict[str, dict],
                 curves: dict[str, list[dict]]) -> str:
    """report.json + report.md + plots in ``out``. -> the terminal table."""
    methods = {name: r["metrics"] for name, r in evals.items()}
    plots = plot_all(out, evals, curves)
    report = {**summary, "methods": methods, "curves": curves, "evaluations": evals,
              "plots": plots}
    write_json(os.path.join(out, "report.json"), report)
    first = next(iter(evals.values()), None)
    mach = summary.get("machine") or {}
    where = (f" ({mach.get('device')}, CPU {mach.get('cpu')} with {mach.get('cpu_isa')}, jax "
             f"{mach.get('jax')})" if mach else "")
    lines = [f"# {summary.get('task', '')} pipeline report", "",
             f"Profile `{summary.get('profile')}` on `{summary.get('backend')}`{where}; "
             f"command: `{summary.get('command', '')}`.", ""]
    if first is not None:
        st = first.get("setting") or {}
        lines += [f"Test policies: {len(first['vd'])}; each simulated for "
                  f"{first['n_episodes']} episodes of {first['horizon']} steps (gamma "
                  f"{first['gamma']}, evaluation seed {st.get('seed', '?')}); true values "
                  f"from the test data ({first.get('true_value_source', '?')}, --truth "
                  f"{st.get('truth', 'auto')}).", "",
                  markdown_table(methods), ""]
    lines += trust_lines(evals)
    imp = improvement_text(evals)
    if imp:
        lines += [imp.lstrip("\n"), ""]
    for k, v in summary.get("notes", {}).items():
        lines.append(f"- **{k}**: {v}")
    lines += [""] + [f"![{p}]({p})" for p in plots]
    write_text(os.path.join(out, "report.md"), "\n".join(lines) + "\n")
    return table(methods)
