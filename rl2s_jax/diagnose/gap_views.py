"""What `rl2s diagnose` shows of an error breakdown (``gaps.error_breakdown``): its figure and
its markdown section."""

from __future__ import annotations

import os

import numpy as np

from rl2s_jax._files import save_figure
from rl2s_jax.diagnose.gaps import _MAX_BARS, _MAX_HEAT_VARS, KSTEP_UNITS, RESID_UNITS, _num, _pct


def plot_gaps(out_dir: str, breakdown: dict, *, prefix: str = "gaps") -> list[str]:
    """Draw a breakdown into out_dir. -> paths of the PNGs written.

    ``{prefix}_one_step.png``: where the one-step error lies, 2x2 panels: by obs dim (bars:
    rmse, markers: mean z^2 against the z^2 = 1 calibration line), by policy, by step within
    the episode, and the region heat-map (variables x quantile bins, coloured by rmse / overall
    rmse). ``{prefix}_rollout.png``: what it costs over a rollout: k-step error growth (mean
    with a +-1 std band over seeds) and true vs simulated values per policy (y = x line);
    written only when kstep or vd is present. Panels whose data is absent are left out.
    """
    # Imported here to keep start-up fast: matplotlib loads in about a second, and only
    # the plots need it.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    os.makedirs(out_dir, exist_ok=True)
    files = []
    ov = breakdown.get("overall") or {}
    rmse_all = ov.get("rmse")

    panels = []
    if breakdown.get("by_dim"):
        panels.append("dim")
    if breakdown.get("by_policy"):
        panels.append("policy")
    if (breakdown.get("by_step") or {}).get("bins"):
        panels.append("step")
    if (breakdown.get("by_region") or {}).get("variables"):
        panels.append("region")

    if panels:
        regions = breakdown["by_region"]["variables"] if "region" in panels else []
        heat_vars = regions
        if len(regions) > _MAX_HEAT_VARS:
            peak = [max((r for r in v["ratio"] if r is not None), default=0) for v in regions]
            keep = sorted(np.argsort(peak)[::-1][:_MAX_HEAT_VARS])
            heat_vars = [regions[i] for i in keep]
        height = 8.0 + max(0, len(heat_vars) - 14) * 0.18
        ncols = 2 if len(panels) > 1 else 1
        nrows = (len(panels) + 1) // 2
        fig, axes = plt.subplots(nrows, ncols, figsize=(6.5 * ncols, height * nrows / 2),
                                 squeeze=False)
        axes = axes.ravel()
        for ax in axes[len(panels):]:
            ax.axis("off")
        for ax, what in zip(axes, panels, strict=False):
            if what == "dim":
                _panel_dim(ax, breakdown["by_dim"], rmse_all, ov.get("mean_z2"))
            elif what == "policy":
                _panel_policy(ax, breakdown["by_policy"], rmse_all)
            elif what == "step":
                _panel_step(ax, breakdown["by_step"], rmse_all)
            else:
                _panel_region(fig, ax, heat_vars, len(regions), TwoSlopeNorm)
        title = "Held-out one-step error"
        if rmse_all is not None:
            title += (f": rmse {_num(rmse_all)} {RESID_UNITS}, mean z² "
                      f"{_num(ov.get('mean_z2'))}, {ov.get('n_rows')} rows")
        fig.suptitle(title, fontsize=11)
        fig.tight_layout()
        path = os.path.join(out_dir, f"{prefix}_one_step.png")
        save_figure(fig, path, dpi=110)
        plt.close(fig)
        files.append(path)

    ks, vd = breakdown.get("kstep"), breakdown.get("vd")
    rp = [w for w, d in (("kstep", ks), ("vd", vd)) if d]
    if rp:
        fig, axes = plt.subplots(1, len(rp), figsize=(5.5 * len(rp), 4.2), squeeze=False)
        for ax, what in zip(axes[0], rp, strict=True):
            if what == "kstep":
                _panel_kstep(ax, ks)
            else:
                _panel_values(ax, vd)
        fig.tight_layout()
        path = os.path.join(out_dir, f"{prefix}_rollout.png")
        save_figure(fig, path, dpi=110)
        plt.close(fig)
        files.append(path)
    return files


def _panel_dim(ax, dims: list[dict], rmse_all, z2_all) -> None:
    title = "Error by state dim"
    if len(dims) > _MAX_BARS:
        keep = sorted(np.argsort([-(d["share"] or 0) for d in dims])[:_MAX_BARS])
        dims = [dims[i] for i in keep]
        title += f" (top {_MAX_BARS} by share)"
    x = np.arange(len(dims))
    rm = [d["rmse"] or 0 for d in dims]
    ax.bar(x, rm, color="tab:blue", alpha=0.8, label="rmse (left)")
    if rmse_all is not None:
        ax.axhline(rmse_all, color="tab:blue", ls=":", lw=1, label="overall rmse")
    ax.set_xticks(x, [d["name"] for d in dims], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(f"one-step RMSE ({RESID_UNITS})")
    ax.set_title(title, fontsize=10)
    z = np.array([d["mean_z2"] if d["mean_z2"] is not None else np.nan for d in dims])
    ax2 = ax.twinx()
    ax2.plot(x, z, "o", color="tab:red", ms=5, label="mean z² (right)")
    ax2.axhline(1.0, color="tab:red", ls="--", lw=1,
                label="z² = 1: predicted std matches the error")
    ax2.set_yscale("log")  # over- and under-confidence by the same factor look alike
    zf = z[np.isfinite(z) & (z > 0)]
    ax2.set_ylim(min(0.3, zf.min() / 1.5) if zf.size else 0.3,
                 max(3.0, zf.max() * 1.5) if zf.size else 3.0)
    ax2.set_ylabel("mean z² = (resid / std)² (log; 1 = calibrated)", color="tab:red")
    if len(dims) <= 16:
        for xi, zi in enumerate(z):
            if np.isfinite(zi):
                ax2.annotate(f"{zi:.2g}", (xi, zi), ha="left", va="bottom", fontsize=6,
                             color="tab:red", xytext=(3, 1), textcoords="offset points")
    ax.set_ylim(0, 1.45 * max(max(rm), rmse_all or 0, 1e-12))  # room for the legend
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper left")


def _panel_policy(ax, pols: list[dict], rmse_all) -> None:
    title = "Error by policy (worst first)"
    if len(pols) > _MAX_BARS:
        pols = pols[:_MAX_BARS]
        title += f", top {_MAX_BARS}"
    x = np.arange(len(pols))
    ax.bar(x, [p["rmse"] for p in pols], color="tab:purple", alpha=0.8)
    if rmse_all is not None:
        ax.axhline(rmse_all, color="grey", ls=":", lw=1, label="overall rmse")
        ax.legend(fontsize=7)
    if any("abs_vd" in p for p in pols) and len(pols) <= 15:
        for xi, p in enumerate(pols):
            if "abs_vd" in p:
                ax.annotate(f"|VD| {_num(p['abs_vd'])}", (xi, p["rmse"]), ha="center",
                            va="bottom", fontsize=6, xytext=(0, 2), textcoords="offset points")
    ax.set_xticks(x, [p["name"] for p in pols], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(f"one-step RMSE ({RESID_UNITS})")
    ax.set_title(title, fontsize=10)


def _panel_step(ax, step: dict, rmse_all) -> None:
    bins = step["bins"]
    x = np.arange(len(bins))
    ax.bar(x, [s["rmse"] for s in bins], color="tab:green", alpha=0.8)
    for xi, s in enumerate(bins):
        ax.annotate(f"n={s['n']}", (xi, s["rmse"]), ha="center", va="bottom", fontsize=6,
                    xytext=(0, 2), textcoords="offset points")
    if rmse_all is not None:
        ax.axhline(rmse_all, color="grey", ls=":", lw=1, label="overall rmse")
        ax.legend(fontsize=7)
    ax.set_xticks(x, [f"{s['t_lo']}-{s['t_hi']}" for s in bins], rotation=30, fontsize=7)
    ax.set_xlabel("step t within the episode (equal-count bins)")
    ax.set_ylabel(f"one-step RMSE ({RESID_UNITS})")
    ax.set_title("Error by step within episode", fontsize=10)


def _panel_region(fig, ax, variables: list[dict], n_total: int, norm_cls) -> None:
    m = max(len(v["ratio"]) for v in variables)
    grid = np.full((len(variables), m), np.nan)
    for i, v in enumerate(variables):
        grid[i, :len(v["ratio"])] = [r if r is not None else np.nan for r in v["ratio"]]
    finite = grid[np.isfinite(grid)]
    lo = min(0.5, float(finite.min())) if finite.size else 0.5
    hi = max(2.0, float(finite.max())) if finite.size else 2.0
    im = ax.imshow(np.ma.masked_invalid(grid), aspect="auto", cmap="RdBu_r",
                   norm=norm_cls(vmin=lo, vcenter=1.0, vmax=hi))
    if grid.size <= 240:
        for (i, j), val in np.ndenumerate(grid):
            if np.isfinite(val):
                ax.text(j, i, f"{val:.2g}", ha="center", va="center", fontsize=6,
                        color="white" if val > 0.6 * hi or val < 0.6 else "black")
    ax.set_yticks(np.arange(len(variables)), [v["name"] for v in variables], fontsize=7)
    labels = [f"q{j + 1}" for j in range(m)]
    if m > 1:
        labels[0] += "\nlowest"
        labels[-1] += "\nhighest"
    ax.set_xticks(np.arange(m), labels, fontsize=7)
    ax.set_xlabel("quantile bin of the variable (held-out rows)")
    title = "Where in state/action space: rmse / overall rmse"
    if n_total > len(variables):
        title += f"\n({len(variables)} of {n_total} variables with the highest peak)"
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, fraction=0.04, pad=0.02, label="rmse ratio (1 = average)")


def _panel_kstep(ax, ks: dict) -> None:
    k = np.array(ks["k"])
    rm = np.array(ks["rmse"], dtype=float)
    ax.plot(k, rm, marker="o", ms=3, color="tab:orange",
            label=f"mean over {ks['n_seeds']} seed(s)" if ks["n_seeds"] > 1 else "rmse")
    if ks.get("std") is not None:
        sd = np.array(ks["std"], dtype=float)
        ax.fill_between(k, rm - sd, rm + sd, color="tab:orange", alpha=0.25, label="±1 std")
    ax.set_xlabel("open-loop rollout length k (steps)")
    ax.set_ylabel(f"k-step RMSE ({KSTEP_UNITS})")
    g = ks.get("growth")
    ax.set_title(f"Error growth over a rollout: {g:.2g}x from k=1 to k={k[-1]}"
                 if g is not None else "Error growth over a rollout", fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def _panel_values(ax, vd: dict) -> None:
    t, s = np.array(vd["true"], dtype=float), np.array(vd["sim"], dtype=float)
    lo, hi = float(min(t.min(), s.min())), float(max(t.max(), s.max()))
    pad = 0.05 * (hi - lo or 1.0)
    ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="grey", lw=0.8,
            label="y = x (perfect simulator)")
    ax.scatter(t, s, s=14, color="tab:blue", zorder=3)
    absvd = np.array(vd["abs_vd"], dtype=float)
    for j in np.argsort(absvd)[::-1][:3]:
        ax.annotate(str(vd["policy"][j]), (t[j], s[j]), fontsize=7, xytext=(3, 3),
                    textcoords="offset points")
    ax.set_xlabel("true value (return on the real system)")
    ax.set_ylabel("simulated value (return in the learned simulator)")
    ax.set_title(f"True vs simulated value per policy: mean |VD| {_num(vd['mean_abs_vd'])}",
                 fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


# Why the by-policy table's simulated values have no interval (issue 64: every printed simulated
# value has its interval or says why not; app/value_intervals.py NO_INTERVAL for the others)
VALUES_NO_INTERVAL = ("Why no interval: sim is the diagnosed model's value of each of the data's "
                      "own policies, beside its true value: the error is measured, not "
                      "predicted (other policies' intervals: `rl2s evaluate --ckpt`).")


def gaps_markdown(breakdown: dict, plots: list[str], *, rel_to: str | None = None,
                  max_rows: int = 8) -> str:
    """A compact markdown section: findings, top rows of the by-dim and by-policy tables, the
    worst regions, and image links (relative to ``rel_to``, default: the file names, i.e. the
    markdown sits in the plots' out_dir)."""
    ov = breakdown["overall"]
    lines = ["## Where the simulator is wrong", "",
             f"Held-out one-step error over {ov['n_rows']} rows ({ov['n_episodes']} episodes); "
             f"residuals in {RESID_UNITS} (delta / delta std per dim); z = residual / predicted "
             "std (mean z² = 1: calibrated).", ""]
    lines += [f"- {s}" for s in breakdown.get("summary", [])] + [""]

    dims = sorted(breakdown["by_dim"], key=lambda d: -(d["share"] or 0))
    more = len(dims) - max_rows
    lines += [f"**By state dim** (largest share first{f'; {more} more' if more > 0 else ''})",
              "", "| dim | rmse | share | mean z² | bias |", "|---|---:|---:|---:|---:|"]
    for d in dims[:max_rows]:
        lines.append(f"| {d['name']} | {_num(d['rmse'])} | {_pct(d['share'] or 0)} | "
                     f"{_num(d['mean_z2'])} | {_num(d['bias'])} |")
    lines.append("")

    pols = breakdown["by_policy"]
    has_vd = any("abs_vd" in p for p in pols)
    more = len(pols) - max_rows
    lines += [f"**By policy** (largest rmse first{f'; {more} more' if more > 0 else ''})", "",
              "| policy | rows | rmse | nll | " + ("true | sim | \\|VD\\| |" if has_vd else ""),
              "|---|---:|---:|---:|" + ("---:|---:|---:|" if has_vd else "")]
    for p in pols[:max_rows]:
        row = f"| {p['name']} | {p['n']} | {_num(p['rmse'])} | {_num(p['nll'])} |"
        if has_vd:
            row += "".join(f" {_num(p.get(k))} |" for k in ("true", "sim", "abs_vd"))
        lines.append(row)
    if has_vd:
        lines += ["", VALUES_NO_INTERVAL]
    lines.append("")

    worst = breakdown["by_region"]["worst"]
    if worst:
        lines += ["**Worst regions** (rmse / overall rmse)", "",
                  "| variable | range | rows | ratio | mostly in |", "|---|---|---:|---:|---|"]
        for w in worst:
            lines.append(f"| {w['variable']} | [{_num(w['lo'])}, {_num(w['hi'])}] | "
                         f"{w['n_rows']} | {w['ratio']:.2f} | {w['top_dim']} |")
        lines.append("")
    hot = [w for w in breakdown["by_region"].get("worst_dim") or [] if w["ratio"] >= 1.5]
    if hot:
        lines += ["**Per-dim hot spots** (a dim's rmse in the bin / its own overall rmse)", "",
                  "| error in | where | range | rows | ratio |", "|---|---|---|---:|---:|"]
        for w in hot:
            lines.append(f"| {w['error_dim_name']} | {w['variable']} | [{_num(w['lo'])}, "
                         f"{_num(w['hi'])}] | {w['n_rows']} | {w['ratio']:.2f} |")
        lines.append("")

    for p in plots:
        name = os.path.relpath(p, rel_to) if rel_to else os.path.basename(p)
        lines.append(f"![{os.path.basename(p)}]({name})")
    return "\n".join(lines).rstrip() + "\n"
